//! The client's errors as Python exceptions, and the client's runtime.

use pyo3::exceptions::{PyException, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use tamrm_client::tonic::{Code, Status};
use tamrm_client::Error;

pyo3::create_exception!(
    _native,
    StatusError,
    PyException,
    "A failed call: args are (code: int, message: str), the gRPC status."
);

/// A gRPC status as the Python side turns it into a `tamrm.TamrmError`.
pub(crate) fn status_error(status: &Status) -> PyErr {
    StatusError::new_err((status.code() as i32, status.message().to_string()))
}

/// A status of our own making.
pub(crate) fn status(code: Code, message: impl Into<String>) -> PyErr {
    StatusError::new_err((code as i32, message.into()))
}

/// A client error as Python sees it: a bad argument is a `ValueError`, a status a
/// `StatusError`, an interrupt the exception the signal handler raised.
pub(crate) fn client_error(e: Error) -> PyErr {
    match e {
        Error::Invalid(m) => PyValueError::new_err(m),
        Error::Runtime(m) => PyRuntimeError::new_err(m),
        Error::Status(s) => status_error(&s),
        Error::Interrupted(e) => match e.downcast::<PyErr>() {
            Ok(err) => *err,
            Err(other) => PyRuntimeError::new_err(other.to_string()),
        },
    }
}

/// The client's tokio runtime (shared with the embedded engine).
pub(crate) fn runtime() -> PyResult<&'static tokio::runtime::Runtime> {
    tamrm_client::runtime()
        .map_err(|e| PyRuntimeError::new_err(format!("tamrm: cannot start the tokio runtime: {e}")))
}
