//! The transport to a server: the addresses of a channel and their connections
//! ([`targets`]), failure classification ([`failure`]), and the `Shape` stream of a
//! session ([`RemoteStream`]) on its own connection ([`driver`]).

mod driver;
pub(crate) mod failure;
mod stream;
pub(crate) mod targets;

pub use stream::{step_batch, RemoteStream};
pub(crate) use stream::{StreamConfig, FIRST_PAUSE, MAX_PAUSE};
