//! How a [`crate::remote::Channel`] connects: TLS, HTTP/2 keepalive and the metadata sent
//! on every call, as one value built by `tamrm.Client` (`tamrm._native.ChannelOptions`).
//! A new connection setting (an API key, say) is a new field here, not a new argument
//! threaded through every constructor.

use std::time::Duration;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use rustls_pki_types::pem::PemObject;
use rustls_pki_types::{CertificateDer, PrivateKeyDer};
use tonic::metadata::{AsciiMetadataKey, AsciiMetadataValue, MetadataMap};
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity};

/// Connection settings of a channel. Checked when made: a malformed PEM or a
/// non-positive interval is a `ValueError` then, not a failed connection later.
#[pyclass(frozen, module = "tamrm._native")]
#[derive(Clone, Debug)]
pub struct ChannelOptions {
    metadata: Vec<(String, String)>,
    tls: bool,
    root_certificates: Option<Vec<u8>>,
    identity: Option<(Vec<u8>, Vec<u8>)>,
    server_name: Option<String>,
    keepalive: Option<Duration>,
    keepalive_timeout: Duration,
    /// How long a session step keeps trying to resume on a broken stream (SPEC §9);
    /// `None`: it fails at once.
    resume_timeout: Option<Duration>,
    /// How long a session step polls for its answer before it sleeps (zero: it sleeps
    /// at once).
    busy_poll: Duration,
}

impl Default for ChannelOptions {
    fn default() -> ChannelOptions {
        ChannelOptions {
            metadata: Vec::new(),
            tls: false,
            root_certificates: None,
            identity: None,
            server_name: None,
            keepalive: Some(Duration::from_secs(30)),
            keepalive_timeout: Duration::from_secs(20),
            resume_timeout: Some(DEFAULT_RESUME_TIMEOUT),
            busy_poll: Duration::ZERO,
        }
    }
}

/// The longest `busy_poll_us` accepted: one second.
pub const MAX_BUSY_POLL_US: u64 = 1_000_000;

/// How long a step resumes a broken session by default.
pub const DEFAULT_RESUME_TIMEOUT: Duration = Duration::from_secs(60);

fn seconds(name: &str, value: f64) -> PyResult<Duration> {
    if !(value.is_finite() && value > 0.0) {
        return Err(PyValueError::new_err(format!(
            "{name} must be a positive number of seconds, got {value}"
        )));
    }
    Duration::try_from_secs_f64(value)
        .map_err(|e| PyValueError::new_err(format!("{name} = {value}: {e}")))
}

fn check_certs(name: &str, pem: &[u8]) -> PyResult<()> {
    let certs = CertificateDer::pem_slice_iter(pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| PyValueError::new_err(format!("{name}: not valid PEM certificates ({e})")))?;
    if certs.is_empty() {
        return Err(PyValueError::new_err(format!(
            "{name}: no PEM certificate in it (expected -----BEGIN CERTIFICATE-----)"
        )));
    }
    Ok(())
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
        if let Some(pem) = &root_certificates {
            check_certs("root_certificates", pem)?;
        }
        let identity = match (certificate_chain, private_key) {
            (Some(chain), Some(key)) => {
                check_certs("certificate_chain", &chain)?;
                PrivateKeyDer::from_pem_slice(&key).map_err(|e| {
                    PyValueError::new_err(format!(
                        "private_key: no PEM private key (PKCS#8, PKCS#1 or SEC1) in it ({e})"
                    ))
                })?;
                Some((chain, key))
            }
            (None, None) => None,
            _ => {
                return Err(PyValueError::new_err(
                    "certificate_chain and private_key go together (a client certificate for mutual TLS)",
                ))
            }
        };
        let tls = tls || root_certificates.is_some() || identity.is_some();
        if server_name.is_some() && !tls {
            return Err(PyValueError::new_err("tls_server_name needs TLS"));
        }
        let options = ChannelOptions {
            metadata,
            tls,
            root_certificates,
            identity,
            server_name,
            keepalive: keepalive_secs
                .map(|s| seconds("keepalive_secs", s))
                .transpose()?,
            keepalive_timeout: seconds("keepalive_timeout_secs", keepalive_timeout_secs)?,
            resume_timeout: resume_timeout_secs
                .map(|s| seconds("resume_timeout_secs", s))
                .transpose()?,
            busy_poll: Duration::from_micros(busy_poll_us),
        };
        options.metadata_map()?;
        Ok(options)
    }

    /// Whether the channel speaks TLS.
    #[getter]
    fn tls(&self) -> bool {
        self.tls
    }
}

impl ChannelOptions {
    /// Whether the channel speaks TLS.
    pub fn uses_tls(&self) -> bool {
        self.tls
    }

    /// How long a session step resumes a broken stream; `None`: not at all.
    pub fn resume_timeout(&self) -> Option<Duration> {
        self.resume_timeout
    }

    /// How long a session step polls for its answer before it sleeps.
    pub fn busy_poll(&self) -> Duration {
        self.busy_poll
    }

    /// The metadata sent on every call.
    pub fn metadata_map(&self) -> PyResult<MetadataMap> {
        let mut md = MetadataMap::new();
        for (k, v) in &self.metadata {
            let key = k
                .parse::<AsciiMetadataKey>()
                .map_err(|e| PyValueError::new_err(format!("metadata key {k:?}: {e}")))?;
            let value = v
                .parse::<AsciiMetadataValue>()
                .map_err(|e| PyValueError::new_err(format!("metadata value of {k:?}: {e}")))?;
            md.append(key, value);
        }
        Ok(md)
    }

    /// The endpoint for `authority` (`host:port`) with these settings.
    pub fn endpoint(&self, target: &str, authority: &str) -> PyResult<Endpoint> {
        let scheme = if self.tls { "https" } else { "http" };
        let mut endpoint = Endpoint::from_shared(format!("{scheme}://{authority}"))
            .map_err(|e| PyValueError::new_err(format!("target {target:?}: {e}")))?
            .tcp_nodelay(true)
            .connect_timeout(Duration::from_secs(10))
            .keep_alive_while_idle(false)
            .keep_alive_timeout(self.keepalive_timeout);
        if let Some(interval) = self.keepalive {
            endpoint = endpoint.http2_keep_alive_interval(interval);
        }
        if self.tls {
            let mut config = ClientTlsConfig::new().timeout(Duration::from_secs(10));
            config = match &self.root_certificates {
                Some(pem) => config.ca_certificate(Certificate::from_pem(pem)),
                None => config.with_native_roots(),
            };
            if let Some((chain, key)) = &self.identity {
                config = config.identity(Identity::from_pem(chain, key));
            }
            if let Some(name) = &self.server_name {
                config = config.domain_name(name.clone());
            }
            endpoint = endpoint
                .tls_config(config)
                .map_err(|e| PyValueError::new_err(format!("target {target:?}: TLS: {e}")))?;
        }
        Ok(endpoint)
    }
}
