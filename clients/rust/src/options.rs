//! How a [`crate::Channel`] connects: TLS, HTTP/2 keepalive, the metadata sent on every
//! call (an API key), how long a session resumes, as one value. A new connection setting
//! is a new field here, not a new argument threaded through every constructor.

use std::sync::Arc;
use std::time::Duration;

use rustls_pki_types::pem::PemObject;
use rustls_pki_types::{CertificateDer, PrivateKeyDer};
use tonic::metadata::{AsciiMetadataKey, AsciiMetadataValue, MetadataMap};
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity};

use crate::error::{BoxError, Error};

/// A check run while a call waits (every 100 ms): an error ends the wait, and the
/// session, with [`Error::Interrupted`]. The Python client checks for a Ctrl-C here.
pub type Interrupt = Arc<dyn Fn() -> Result<(), BoxError> + Send + Sync>;

/// The longest [`ChannelOptions::busy_poll`] accepted: one second.
pub const MAX_BUSY_POLL: Duration = Duration::from_secs(1);

/// How long a step resumes a broken session by default.
pub const DEFAULT_RESUME_TIMEOUT: Duration = Duration::from_secs(60);

/// Connection settings of a channel. The setters that take PEM check it at once: a
/// malformed file is an [`Error::Invalid`] then, not a failed connection later.
#[derive(Clone)]
pub struct ChannelOptions {
    metadata: Vec<(String, String)>,
    tls: bool,
    root_certificates: Option<Vec<u8>>,
    identity: Option<(Vec<u8>, Vec<u8>)>,
    server_name: Option<String>,
    keepalive: Option<Duration>,
    keepalive_timeout: Duration,
    resume_timeout: Option<Duration>,
    busy_poll: Duration,
    interrupt: Option<Interrupt>,
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
            interrupt: None,
        }
    }
}

impl std::fmt::Debug for ChannelOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // No metadata values: they hold the API key.
        let keys: Vec<&str> = self.metadata.iter().map(|(k, _)| k.as_str()).collect();
        f.debug_struct("ChannelOptions")
            .field("metadata_keys", &keys)
            .field("tls", &self.tls)
            .field("server_name", &self.server_name)
            .field("keepalive", &self.keepalive)
            .field("keepalive_timeout", &self.keepalive_timeout)
            .field("resume_timeout", &self.resume_timeout)
            .field("busy_poll", &self.busy_poll)
            .finish_non_exhaustive()
    }
}

fn check_certs(name: &str, pem: &[u8]) -> Result<(), Error> {
    let certs = CertificateDer::pem_slice_iter(pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| Error::Invalid(format!("{name}: not valid PEM certificates ({e})")))?;
    if certs.is_empty() {
        return Err(Error::Invalid(format!(
            "{name}: no PEM certificate in it (expected -----BEGIN CERTIFICATE-----)"
        )));
    }
    Ok(())
}

impl ChannelOptions {
    /// The defaults: plaintext, keepalive every 30 s, sessions resume for 60 s.
    pub fn new() -> ChannelOptions {
        ChannelOptions::default()
    }

    /// Sends `key: value` on every call (checked by [`ChannelOptions::check`]).
    pub fn metadata(mut self, key: impl Into<String>, value: impl Into<String>) -> Self {
        self.metadata.push((key.into(), value.into()));
        self
    }

    /// Sends `authorization: Bearer <key>` on every call (a server with `--api-keys`).
    pub fn api_key(self, key: &str) -> Self {
        self.metadata("authorization", format!("Bearer {key}"))
    }

    /// Speaks TLS; without [`ChannelOptions::root_certificates`] the system's CA store is
    /// trusted.
    pub fn tls(mut self, on: bool) -> Self {
        self.tls = on;
        self
    }

    /// Trusts the CA certificates of `pem` (the file's contents); turns TLS on.
    pub fn root_certificates(mut self, pem: impl Into<Vec<u8>>) -> Result<Self, Error> {
        let pem = pem.into();
        check_certs("root_certificates", &pem)?;
        self.root_certificates = Some(pem);
        self.tls = true;
        Ok(self)
    }

    /// A client certificate for mutual TLS (`certificate_chain` and `private_key` in
    /// PEM); turns TLS on.
    pub fn identity(
        mut self,
        certificate_chain: impl Into<Vec<u8>>,
        private_key: impl Into<Vec<u8>>,
    ) -> Result<Self, Error> {
        let (chain, key) = (certificate_chain.into(), private_key.into());
        check_certs("certificate_chain", &chain)?;
        PrivateKeyDer::from_pem_slice(&key).map_err(|e| {
            Error::Invalid(format!(
                "private_key: no PEM private key (PKCS#8, PKCS#1 or SEC1) in it ({e})"
            ))
        })?;
        self.identity = Some((chain, key));
        self.tls = true;
        Ok(self)
    }

    /// The name the server's certificate must hold, instead of the address's host.
    pub fn server_name(mut self, name: impl Into<String>) -> Self {
        self.server_name = Some(name.into());
        self
    }

    /// The HTTP/2 keepalive ping interval (`None`: no pings).
    pub fn keepalive(mut self, interval: Option<Duration>) -> Self {
        self.keepalive = interval;
        self
    }

    /// How long a keepalive ping may go unanswered before the connection is closed.
    pub fn keepalive_timeout(mut self, timeout: Duration) -> Self {
        self.keepalive_timeout = timeout;
        self
    }

    /// How long a session step keeps trying to resume a broken stream (SPEC §9); `None`:
    /// it fails at once.
    pub fn resume_timeout(mut self, timeout: Option<Duration>) -> Self {
        self.resume_timeout = timeout;
        self
    }

    /// How long a session step polls for its answer before it sleeps (at most
    /// [`MAX_BUSY_POLL`]; zero, the default: it sleeps at once).
    pub fn busy_poll(mut self, poll: Duration) -> Result<Self, Error> {
        if poll > MAX_BUSY_POLL {
            return Err(Error::Invalid(format!(
                "busy_poll_us must be at most {} (one second), got {}",
                MAX_BUSY_POLL.as_micros(),
                poll.as_micros()
            )));
        }
        self.busy_poll = poll;
        Ok(self)
    }

    /// A check run while calls wait (see [`Interrupt`]).
    pub fn interrupt(mut self, check: Interrupt) -> Self {
        self.interrupt = Some(check);
        self
    }

    /// Checks what the setters could not alone: a server name needs TLS, and the metadata
    /// must be valid ASCII metadata.
    pub fn check(&self) -> Result<(), Error> {
        if self.server_name.is_some() && !self.tls {
            return Err(Error::Invalid("tls_server_name needs TLS".into()));
        }
        self.metadata_map().map(drop)
    }

    /// Whether the channel speaks TLS.
    pub fn uses_tls(&self) -> bool {
        self.tls
    }

    /// How long a session step resumes a broken stream; `None`: not at all.
    pub fn resume_timeout_value(&self) -> Option<Duration> {
        self.resume_timeout
    }

    pub(crate) fn busy_poll_value(&self) -> Duration {
        self.busy_poll
    }

    pub(crate) fn interrupt_check(&self) -> Option<Interrupt> {
        self.interrupt.clone()
    }

    /// The metadata sent on every call.
    pub(crate) fn metadata_map(&self) -> Result<MetadataMap, Error> {
        let mut md = MetadataMap::new();
        for (k, v) in &self.metadata {
            let key = k
                .parse::<AsciiMetadataKey>()
                .map_err(|e| Error::Invalid(format!("metadata key {k:?}: {e}")))?;
            let value = v
                .parse::<AsciiMetadataValue>()
                .map_err(|e| Error::Invalid(format!("metadata value of {k:?}: {e}")))?;
            md.append(key, value);
        }
        Ok(md)
    }

    /// The endpoint for `authority` (`host:port`) with these settings.
    pub(crate) fn endpoint(&self, target: &str, authority: &str) -> Result<Endpoint, Error> {
        let scheme = if self.tls { "https" } else { "http" };
        let mut endpoint = Endpoint::from_shared(format!("{scheme}://{authority}"))
            .map_err(|e| Error::Invalid(format!("target {target:?}: {e}")))?
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
                .map_err(|e| Error::Invalid(format!("target {target:?}: TLS: {e}")))?;
        }
        Ok(endpoint)
    }
}
