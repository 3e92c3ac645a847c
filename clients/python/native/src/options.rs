//! `tamrm._native.ChannelOptions`: the Python face of [`tamrm_client::ChannelOptions`]
//! (TLS, keepalive, metadata, resume), built by `tamrm.Client` and checked when made: a
//! malformed PEM or a non-positive interval is a `ValueError` then, not a failed
//! connection later.

use std::sync::Arc;
use std::time::Duration;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use tamrm_client::{BoxError, DEFAULT_RESUME_TIMEOUT, MAX_BUSY_POLL};

use crate::client_error;

/// Connection settings of a channel.
#[pyclass(frozen, module = "tamrm._native")]
#[derive(Clone, Debug, Default)]
pub struct ChannelOptions {
    pub(crate) inner: tamrm_client::ChannelOptions,
}

/// The longest `busy_poll_us` accepted: one second.
pub const MAX_BUSY_POLL_US: u64 = MAX_BUSY_POLL.as_micros() as u64;

fn seconds(name: &str, value: f64) -> PyResult<Duration> {
    if !(value.is_finite() && value > 0.0) {
        return Err(PyValueError::new_err(format!(
            "{name} must be a positive number of seconds, got {value}"
        )));
    }
    Duration::try_from_secs_f64(value)
        .map_err(|e| PyValueError::new_err(format!("{name} = {value}: {e}")))
}

/// The check a waiting step runs: a Ctrl-C raises in the signal handler, and the step
/// ends with that exception.
fn check_signals() -> Result<(), BoxError> {
    Python::attach(|py| py.check_signals()).map_err(|e| Box::new(e) as BoxError)
}

#[pymethods]
impl ChannelOptions {
    /// Connection settings; PEM arguments are the file contents (bytes). TLS is on when
    /// `tls` is true or any certificate is given; without `root_certificates` the
    /// system's CA store is trusted.
    #[new]
    #[pyo3(signature = (
        *,
        metadata = Vec::new(),
        tls = false,
        root_certificates = None,
        certificate_chain = None,
        private_key = None,
        server_name = None,
        keepalive_secs = Some(30.0),
        keepalive_timeout_secs = 20.0,
        resume_timeout_secs = Some(DEFAULT_RESUME_TIMEOUT.as_secs_f64()),
        busy_poll_us = 0,
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        metadata: Vec<(String, String)>,
        tls: bool,
        root_certificates: Option<Vec<u8>>,
        certificate_chain: Option<Vec<u8>>,
        private_key: Option<Vec<u8>>,
        server_name: Option<String>,
        keepalive_secs: Option<f64>,
        keepalive_timeout_secs: f64,
        resume_timeout_secs: Option<f64>,
        busy_poll_us: u64,
    ) -> PyResult<ChannelOptions> {
        if busy_poll_us > MAX_BUSY_POLL_US {
            return Err(PyValueError::new_err(format!(
                "busy_poll_us must be at most {MAX_BUSY_POLL_US} (one second), got {busy_poll_us}"
            )));
        }
        let mut o = tamrm_client::ChannelOptions::new()
            .tls(tls)
            .busy_poll(Duration::from_micros(busy_poll_us))
            .map_err(client_error)?
            .interrupt(Arc::new(check_signals));
        if let Some(pem) = root_certificates {
            o = o.root_certificates(pem).map_err(client_error)?;
        }
        o = match (certificate_chain, private_key) {
            (Some(chain), Some(key)) => o.identity(chain, key).map_err(client_error)?,
            (None, None) => o,
            _ => {
                return Err(PyValueError::new_err(
                    "certificate_chain and private_key go together (a client certificate for mutual TLS)",
                ))
            }
        };
        if let Some(name) = server_name {
            o = o.server_name(name);
        }
        o.check().map_err(client_error)?;
        let keepalive = keepalive_secs
            .map(|s| seconds("keepalive_secs", s))
            .transpose()?;
        let keepalive_timeout = seconds("keepalive_timeout_secs", keepalive_timeout_secs)?;
        let resume_timeout = resume_timeout_secs
            .map(|s| seconds("resume_timeout_secs", s))
            .transpose()?;
        for (k, v) in metadata {
            o = o.metadata(k, v);
        }
        let inner = o
            .keepalive(keepalive)
            .keepalive_timeout(keepalive_timeout)
            .resume_timeout(resume_timeout);
        inner.check().map_err(client_error)?;
        Ok(ChannelOptions { inner })
    }

    /// Whether the channel speaks TLS.
    #[getter]
    fn tls(&self) -> bool {
        self.inner.uses_tls()
    }
}
