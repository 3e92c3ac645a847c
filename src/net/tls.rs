//! TLS (rustls, through tonic): the server's certificate, key and optional client CA
//! (mutual TLS), and the client side of `tamrm healthcheck`. The settings declare these
//! files (flags, variables, the config file's `[tls]`), the server uses them.
//!
//! The PEM files are read and parsed here, before tonic sees them, so that a missing,
//! unreadable or malformed file is reported by name (tonic's own errors name none).

use std::path::{Path, PathBuf};
use std::time::Duration;

use clap::Args;
use rustls_pki_types::pem::PemObject;
use rustls_pki_types::{CertificateDer, PrivateKeyDer};
use serde::Deserialize;
use tonic::transport::{Certificate, ClientTlsConfig, Identity, Server, ServerTlsConfig};

use super::chain;

/// How long a TLS handshake may take before the connection is dropped (a client that
/// connects and never speaks must not hold a task forever).
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// The server name `tamrm healthcheck` verifies the certificate against by default.
pub const DEFAULT_HEALTHCHECK_SERVER_NAME: &str = "localhost";

/// The TLS files of `tamrm serve`: flags, `TAMRM_TLS_*` variables and the config file's
/// `[tls]` table (`cert`, `key`, `client_ca`). TLS is on when `cert` and `key` are set.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsFiles {
    /// PEM certificate chain the server presents (leaf first); turns TLS on, needs
    /// --tls-key.
    #[arg(long = "tls-cert", env = "TAMRM_TLS_CERT", value_name = "FILE")]
    pub cert: Option<PathBuf>,
    /// PEM private key (PKCS#8, PKCS#1 or SEC1) of --tls-cert.
    #[arg(long = "tls-key", env = "TAMRM_TLS_KEY", value_name = "FILE")]
    pub key: Option<PathBuf>,
    /// PEM CA certificate(s) for mutual TLS: every client must present a certificate
    /// issued by one of them. Needs --tls-cert.
    #[arg(
        long = "tls-client-ca",
        env = "TAMRM_TLS_CLIENT_CA",
        value_name = "FILE"
    )]
    pub client_ca: Option<PathBuf>,
}

/// Sets each slot to its value where the value is set: one settings layer over the one
/// below it.
pub fn overlay<T: Clone, const N: usize>(pairs: [(&mut Option<T>, &Option<T>); N]) {
    for (slot, value) in pairs {
        if value.is_some() {
            slot.clone_from(value);
        }
    }
}

impl TlsFiles {
    /// Overlays the files `other` sets.
    pub fn apply(&mut self, other: &TlsFiles) {
        overlay([
            (&mut self.cert, &other.cert),
            (&mut self.key, &other.key),
            (&mut self.client_ca, &other.client_ca),
        ]);
    }

    /// Whether the server is to speak TLS.
    pub fn enabled(&self) -> bool {
        self.cert.is_some()
    }

    /// Checks that the files come as a usable combination (not their contents).
    pub fn check(&self) -> Result<(), String> {
        match (&self.cert, &self.key, &self.client_ca) {
            (Some(_), None, _) => Err("tls: a certificate (--tls-cert, TAMRM_TLS_CERT) needs its key (--tls-key, TAMRM_TLS_KEY)".into()),
            (None, Some(_), _) => Err("tls: a key (--tls-key, TAMRM_TLS_KEY) needs its certificate (--tls-cert, TAMRM_TLS_CERT)".into()),
            (None, None, Some(_)) => Err("tls: a client CA (--tls-client-ca, TAMRM_TLS_CLIENT_CA) needs TLS on: set --tls-cert and --tls-key".into()),
            _ => Ok(()),
        }
    }

    /// A line for the start log saying whether TLS and mutual TLS are on.
    pub fn describe(&self) -> String {
        match (&self.cert, &self.client_ca) {
            (None, _) => "TLS off: plaintext HTTP/2 (set --tls-cert and --tls-key for TLS)".into(),
            (Some(c), None) => format!("TLS on (certificate {})", c.display()),
            (Some(c), Some(ca)) => format!(
                "mutual TLS on (certificate {}; client certificates required, verified against {})",
                c.display(),
                ca.display()
            ),
        }
    }
}

/// A TLS file that cannot be used, by name.
#[derive(Debug, thiserror::Error)]
#[error("{what} {}: {problem}", file.display())]
pub struct TlsError {
    /// Which file it is ("TLS certificate", "TLS key", ...).
    pub what: &'static str,
    /// The file.
    pub file: PathBuf,
    /// What is wrong with it.
    pub problem: String,
}

fn read(what: &'static str, file: &Path) -> Result<Vec<u8>, TlsError> {
    std::fs::read(file).map_err(|e| TlsError {
        what,
        file: file.to_path_buf(),
        problem: format!("cannot read it: {e}"),
    })
}

/// Reads a PEM file that must hold at least one certificate; `what` names it in errors.
pub fn read_certs(what: &'static str, file: &Path) -> Result<Vec<u8>, TlsError> {
    let pem = read(what, file)?;
    let bad = |problem: String| TlsError {
        what,
        file: file.to_path_buf(),
        problem,
    };
    let certs = CertificateDer::pem_slice_iter(&pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| bad(format!("not a valid PEM certificate file ({e})")))?;
    if certs.is_empty() {
        return Err(bad(
            "no PEM certificate in it (expected -----BEGIN CERTIFICATE-----)".into(),
        ));
    }
    Ok(pem)
}

/// Reads a PEM file that must hold a private key; `what` names it in errors.
pub fn read_key(what: &'static str, file: &Path) -> Result<Vec<u8>, TlsError> {
    let pem = read(what, file)?;
    PrivateKeyDer::from_pem_slice(&pem).map_err(|e| TlsError {
        what,
        file: file.to_path_buf(),
        problem: format!("no usable PEM private key (PKCS#8, PKCS#1 or SEC1) in it ({e})"),
    })?;
    Ok(pem)
}

/// The server's TLS configuration, `None` when TLS is off. Every file is read and
/// checked here, and the certificate and key are checked to belong together.
pub fn server_config(files: &TlsFiles) -> Result<Option<ServerTlsConfig>, TlsError> {
    let (Some(cert_file), Some(key_file)) = (&files.cert, &files.key) else {
        return Ok(None);
    };
    let cert = read_certs("TLS certificate", cert_file)?;
    let key = read_key("TLS key", key_file)?;
    let mut config = ServerTlsConfig::new()
        .identity(Identity::from_pem(cert, key))
        .timeout(HANDSHAKE_TIMEOUT);
    if let Some(ca) = &files.client_ca {
        config = config.client_ca_root(Certificate::from_pem(read_certs("TLS client CA", ca)?));
    }
    // tonic builds the rustls configuration here: a key that does not match the
    // certificate (or a certificate rustls cannot use) fails now, not per connection.
    Server::builder()
        .tls_config(config.clone())
        .map_err(|e| TlsError {
            what: "TLS certificate",
            file: cert_file.clone(),
            problem: format!(
                "unusable with the key {}: {}",
                key_file.display(),
                chain(&e)
            ),
        })?;
    Ok(Some(config))
}

/// TLS settings of `tamrm healthcheck`: flags, `TAMRM_TLS_*` variables and the config
/// file's `[healthcheck]` table (`tls_ca`, `tls_server_name`, `tls_client_cert`,
/// `tls_client_key`). TLS is on when a CA is given, or when the server's own settings
/// (the same config file and environment) give it a certificate.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HealthcheckTls {
    /// PEM CA certificate(s) to verify the server with; turns TLS on [default: the
    /// server's own certificate file (--config's `[tls] cert`, TAMRM_TLS_CERT): right for
    /// a self-signed certificate or a file that holds its CA].
    #[arg(long, env = "TAMRM_TLS_CA", value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
    /// The name the server's certificate must be valid for [default: localhost].
    #[arg(long, env = "TAMRM_TLS_SERVER_NAME", value_name = "NAME")]
    pub tls_server_name: Option<String>,
    /// PEM client certificate for a mutual-TLS server (with --tls-client-key).
    #[arg(long, env = "TAMRM_TLS_CLIENT_CERT", value_name = "FILE")]
    pub tls_client_cert: Option<PathBuf>,
    /// PEM private key of --tls-client-cert.
    #[arg(long, env = "TAMRM_TLS_CLIENT_KEY", value_name = "FILE")]
    pub tls_client_key: Option<PathBuf>,
}

impl HealthcheckTls {
    /// Overlays the settings `other` sets.
    pub fn apply(&mut self, other: &HealthcheckTls) {
        overlay([
            (&mut self.tls_ca, &other.tls_ca),
            (&mut self.tls_client_cert, &other.tls_client_cert),
            (&mut self.tls_client_key, &other.tls_client_key),
        ]);
        overlay([(&mut self.tls_server_name, &other.tls_server_name)]);
    }

    /// The client TLS configuration to check a server whose TLS files are `server` (as
    /// its settings resolve them) with, `None` for plaintext.
    pub fn client_config(&self, server: &TlsFiles) -> Result<Option<ClientTlsConfig>, TlsError> {
        let ca = self
            .tls_ca
            .clone()
            .or_else(|| server.cert.clone())
            .filter(|p| !p.as_os_str().is_empty());
        let Some(ca) = ca else {
            return Ok(None);
        };
        let name = self
            .tls_server_name
            .as_deref()
            .unwrap_or(DEFAULT_HEALTHCHECK_SERVER_NAME);
        let mut config = ClientTlsConfig::new()
            .ca_certificate(Certificate::from_pem(read_certs("TLS CA", &ca)?))
            .domain_name(name)
            .timeout(HANDSHAKE_TIMEOUT);
        match (&self.tls_client_cert, &self.tls_client_key) {
            (Some(cert), Some(key)) => {
                let cert = read_certs("TLS client certificate", cert)?;
                config =
                    config.identity(Identity::from_pem(cert, read_key("TLS client key", key)?));
            }
            (None, None) => {}
            (Some(f), None) | (None, Some(f)) => {
                return Err(TlsError {
                    what: "TLS client identity",
                    file: f.clone(),
                    problem: "--tls-client-cert and --tls-client-key go together".into(),
                })
            }
        }
        Ok(Some(config))
    }
}
