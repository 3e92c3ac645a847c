//! `tamrm-client`: the Rust client of tamrm, the reward-shaping service.
//!
//! - [`Channel::connect`] makes a lazily connecting channel to one or several servers
//!   (`host:port` or `unix:PATH`; TLS, an API key, keepalive: [`ChannelOptions`]); calls
//!   and streams go to the first address and fail over to the next when it cannot be
//!   reached (SPEC §9, §10).
//! - Unary calls: typed ([`Channel::create_task`], [`Channel::get_task`], ...) or on
//!   serialized messages ([`Channel::call`], one table of RPCs: [`rpc`]).
//! - [`Channel::open`] opens a [`Session`] (a `Shape` stream): [`Session::step`] shapes one
//!   step of columns ([`Batch`]); a broken stream is resumed transparently (SPEC §9: the
//!   session re-opens with its episodes and re-sends the step), for up to
//!   [`ChannelOptions::resume_timeout`].
//! - [`Channel::follow`] opens a local session (SPEC §13): the steps are shaped in-process
//!   against a copy of the server's pool that a `Follow` stream keeps current.
//!
//! The API is blocking (it runs on the crate's own tokio runtime, [`runtime()`]): call it
//! from ordinary threads, not from inside an async task. The Python client's native
//! extension is built on this crate.

mod answer;
mod channel;
mod error;
pub mod local;
mod options;
pub mod remote;
pub mod rpc;
mod runtime;
mod session;
mod tracker;

pub use answer::Answer;
pub use channel::Channel;
pub use error::{BoxError, Error};
pub use local::EngineStream;
pub use options::{ChannelOptions, Interrupt, DEFAULT_RESUME_TIMEOUT, MAX_BUSY_POLL};
pub use runtime::runtime;
pub use session::{Session, Transport};
/// The generated protocol types (`tamrm.v1`), as the server crate generates them.
pub use tamrm::proto;
/// The columns of one step, borrowed (B = `rewards.len()`; SPEC §7).
pub use tamrm::session::Batch;
/// The gRPC library the client is built on (its `Status` and `Code` are the errors').
pub use tonic;
pub use tracker::Tracker;
