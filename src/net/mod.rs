//! What the server, its settings and the clients share about the wire, below all of them:
//! the TLS files and their checks ([`tls`]), a `host:port` address ([`parse_addr`]), and the full text of a failed call
//! ([`status_chain`], [`chain`]). A leaf module: it uses nothing of the crate, so
//! `settings`, `server` and the Python extension (`clients/python/native`) use it without
//! using each other.

mod addr;
mod status;
pub mod tls;

pub use addr::parse_addr;
pub use status::{chain, status_chain};
