//! Sessions shaped in-process: the session layer of the server crate over a registry,
//! either the embedded engine's own ([`EngineStream::open`]) or, for a local session of
//! a [`crate::Channel`] (SPEC §13), one whose only task follows the server's through a
//! `Follow` stream ([`FollowStore`]).

mod connection;
mod driver;
mod engine;
mod follow;
mod plans;
mod shared;
mod wire;

pub(crate) use connection::Connection;
pub(crate) use engine::local_session;
pub use engine::EngineStream;
pub(crate) use follow::FollowStore;
