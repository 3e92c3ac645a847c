//! `tamrm._native`: the Rust half of tamrm's Python client, PyO3 glue over
//! [`tamrm_client`], the one gRPC client of the tree.
//!
//! One session ([`tamrm_client::Session`], wrapped by [`stream::NativeStream`]) over
//! two transports:
//! - the embedded [`engine::Engine`]: the server's own registry, stores and session layer
//!   in-process (no socket), for `tamrm.Engine`;
//! - a [`tamrm_client::Channel`] ([`channel::Channel`]) to one or several servers, for
//!   `tamrm.Client`, with its local sessions (SPEC §13).
//!
//! The Python package (`tamrm._session`, `tamrm._client`, `tamrm._engine`) checks argument
//! types and shapes and turns answers into its dataclasses; everything per entry (range and
//! finiteness checks, [`columns`]) is here, and the round trip runs in the client with the
//! GIL released. [`sb3`] is the Stable-Baselines3 fast path.

mod channel;
mod columns;
mod engine;
mod errors;
mod options;
mod sb3;
mod stream;

use pyo3::prelude::*;

pub(crate) use errors::{client_error, runtime, status, status_error, StatusError};

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("StatusError", m.py().get_type::<StatusError>())?;
    // The workspace's version, which maturin also gives the Python package.
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("MAX_BUSY_POLL_US", options::MAX_BUSY_POLL_US)?;
    m.add_class::<engine::Engine>()?;
    m.add_class::<channel::Channel>()?;
    m.add_class::<options::ChannelOptions>()?;
    m.add_class::<stream::NativeStream>()?;
    m.add_class::<sb3::mlp::Mlp>()?;
    m.add_class::<sb3::vecstep::VecStep>()?;
    m.add_function(wrap_pyfunction!(sb3::record_step, m)?)?;
    Ok(())
}
