//! `tamrm._native`: the Rust half of tamrm's Python client.
//!
//! One session implementation ([`stream::NativeStream`]) over two transports:
//! - the embedded [`engine::Engine`]: the server's own registry, stores and session layer
//!   in-process (no socket), for `tamrm.Engine`;
//! - a tonic gRPC channel ([`remote::Channel`]), for `tamrm.Client`;
//! - local sessions of a `tamrm.Client` (SPEC §13): the embedded engine's session layer
//!   over a store that follows the server's pool ([`follow::FollowStore`]).
//!
//! The Python package (`tamrm._session`, `tamrm._client`, `tamrm._engine`) checks argument
//! types and shapes and turns answers into its dataclasses; everything per entry (range and
//! finiteness checks, the episode state a re-opened stream resumes, the round trip) is here,
//! with the GIL released while the step runs.

mod columns;
mod engine;
mod follow;
mod mlp;
mod options;
mod remote;
mod stream;
mod tracker;
mod vecstep;

use std::sync::Mutex;

use pyo3::exceptions::{PyException, PyRuntimeError};
use pyo3::prelude::*;

pyo3::create_exception!(
    _native,
    StatusError,
    PyException,
    "A failed call: args are (code: int, message: str), the gRPC status."
);

/// A gRPC status as the Python side turns it into a `tamrm.TamrmError`.
pub(crate) fn status_error(status: &tonic::Status) -> PyErr {
    StatusError::new_err((status.code() as i32, status.message().to_string()))
}

/// A status of our own making.
pub(crate) fn status(code: tonic::Code, message: impl Into<String>) -> PyErr {
    StatusError::new_err((code as i32, message.into()))
}

struct Runtime {
    pid: u32,
    rt: tokio::runtime::Runtime,
}

static RUNTIME: Mutex<Option<&'static Runtime>> = Mutex::new(None);

/// The module's tokio runtime (two worker threads: the transports' connections, the disk
/// store's blocking work). A forked child (a process-based vector env started by fork)
/// gets a runtime of its own: the parent's threads do not exist in it.
pub(crate) fn runtime() -> PyResult<&'static tokio::runtime::Runtime> {
    let mut slot = RUNTIME.lock().unwrap_or_else(|e| e.into_inner());
    let pid = std::process::id();
    if let Some(r) = *slot {
        if r.pid == pid {
            return Ok(&r.rt);
        }
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("tamrm-native")
        .enable_all()
        .build()
        .map_err(|e| {
            PyRuntimeError::new_err(format!("tamrm: cannot start the tokio runtime: {e}"))
        })?;
    // Leaked on purpose: it lives as long as the process (in a forked child the parent's
    // runtime is never dropped either: its threads are not there to stop).
    let r: &'static Runtime = Box::leak(Box::new(Runtime { pid, rt }));
    *slot = Some(r);
    Ok(&r.rt)
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("StatusError", m.py().get_type::<StatusError>())?;
    m.add("MAX_BUSY_POLL_US", options::MAX_BUSY_POLL_US)?;
    m.add_class::<engine::Engine>()?;
    m.add_class::<remote::Channel>()?;
    m.add_class::<options::ChannelOptions>()?;
    m.add_class::<stream::NativeStream>()?;
    m.add_class::<mlp::Mlp>()?;
    m.add_class::<vecstep::VecStep>()?;
    m.add_function(wrap_pyfunction!(vecstep::record_step, m)?)?;
    Ok(())
}
