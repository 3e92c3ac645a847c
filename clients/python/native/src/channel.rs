//! `tamrm._native.Channel`: `tamrm.Client`'s transport, a [`tamrm_client::Channel`]
//! whose calls run with the GIL released.

use std::time::Duration;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use tamrm_client::tonic::Code;

use crate::options::ChannelOptions;
use crate::stream::NativeStream;
use crate::{client_error, runtime, status, status_error};

/// A connection to one or several servers (`tamrm._native.Channel`).
#[pyclass(frozen, module = "tamrm._native")]
pub struct Channel {
    inner: tamrm_client::Channel,
}

#[pymethods]
impl Channel {
    /// A lazily connecting channel to `targets` (each `host:port` or `unix:PATH`; the
    /// first is used first) with `options` (TLS, keepalive, metadata sent on every call).
    #[new]
    #[pyo3(signature = (targets, options=None))]
    fn new(targets: Vec<String>, options: Option<ChannelOptions>) -> PyResult<Channel> {
        runtime()?;
        let options = options.unwrap_or_default().inner;
        let inner = tamrm_client::Channel::connect(&targets, options).map_err(client_error)?;
        Ok(Channel { inner })
    }

    /// Whether the channel speaks TLS.
    #[getter]
    fn tls(&self) -> bool {
        self.inner.tls()
    }

    /// One unary call on serialized messages; `timeout` in seconds (`None`: none).
    #[pyo3(signature = (method, request, timeout=None))]
    fn call<'py>(
        &self,
        py: Python<'py>,
        method: &str,
        request: &[u8],
        timeout: Option<f64>,
    ) -> PyResult<Bound<'py, PyBytes>> {
        let timeout = match timeout {
            None => None,
            Some(t) if t.is_nan() => {
                return Err(PyValueError::new_err(
                    "timeout must be a number of seconds, got nan",
                ))
            }
            // A deadline already past (or beyond any clock): fail now, as gRPC does.
            Some(t) => Some(Duration::try_from_secs_f64(t).map_err(|_| {
                status(
                    Code::DeadlineExceeded,
                    format!("deadline of {t}s exceeded before the call"),
                )
            })?),
        };
        let inner = &self.inner;
        let out = py
            .detach(|| inner.call(method, request, timeout))
            .map_err(|s| status_error(&s))?;
        Ok(PyBytes::new(py, &out))
    }

    /// Blocks until a connection to the server is established, up to `timeout` seconds.
    /// A failed TLS handshake ends the wait at once. With several addresses: until one
    /// of them connects, which becomes the current one.
    fn wait_ready(&self, py: Python<'_>, timeout: f64) -> PyResult<()> {
        let wait = Duration::try_from_secs_f64(timeout).unwrap_or(Duration::ZERO);
        let inner = &self.inner;
        py.detach(|| inner.wait_ready(wait))
            .map_err(|s| status_error(&s))
    }

    /// Whether `grpc.health.v1.Health/Check` answers SERVING for `service` within
    /// `timeout` seconds (retrying while the server cannot be reached yet).
    fn health(&self, py: Python<'_>, service: &str, timeout: f64) -> bool {
        let wait = Duration::try_from_secs_f64(timeout).unwrap_or(Duration::ZERO);
        let inner = &self.inner;
        py.detach(|| inner.health(service, wait))
    }

    /// Opens a local session (SPEC §13): a `Follow` stream on `task_id`, and the steps
    /// of `num_envs` environments shaped in-process against the followed pool.
    fn follow(
        &self,
        py: Python<'_>,
        task_id: &str,
        num_envs: u32,
        client_id: &str,
    ) -> PyResult<NativeStream> {
        let inner = &self.inner;
        NativeStream::open(
            py,
            || inner.follow(task_id, num_envs, client_id),
            client_error,
        )
    }

    /// Opens a `Shape` stream on `task_id` for `num_envs` environments.
    fn open(
        &self,
        py: Python<'_>,
        task_id: &str,
        num_envs: u32,
        client_id: &str,
    ) -> PyResult<NativeStream> {
        let inner = &self.inner;
        NativeStream::open(
            py,
            || inner.open(task_id, num_envs, client_id),
            client_error,
        )
    }
}
