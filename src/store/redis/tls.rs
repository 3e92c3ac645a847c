//! TLS to Redis (`rediss://`, `rediss-cluster://`): the CA the server's certificate is
//! verified against (the system's roots without one) and an optional client certificate
//! for a Redis that requires one (`tls-auth-clients yes`, its default).

use std::path::PathBuf;

use redis::{ClientTlsConfig, TlsCertificates};

use crate::net::tls::{overlay, read_certs, read_key, TlsError};

/// The TLS files of a `rediss://` store; every one optional.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RedisTls {
    /// PEM CA certificate(s) to verify Redis with, instead of the system's roots.
    pub ca: Option<PathBuf>,
    /// PEM client certificate (leaf first), for a Redis that asks for one; needs `key`.
    pub cert: Option<PathBuf>,
    /// PEM private key of `cert`.
    pub key: Option<PathBuf>,
}

impl RedisTls {
    /// Overlays the files `other` sets.
    pub fn apply(&mut self, other: &RedisTls) {
        overlay([
            (&mut self.ca, &other.ca),
            (&mut self.cert, &other.cert),
            (&mut self.key, &other.key),
        ]);
    }

    /// Whether no file is set.
    pub fn is_empty(&self) -> bool {
        self == &RedisTls::default()
    }

    /// Checks that the files come as a usable combination for a store URL with (`tls`)
    /// or without TLS: files need a `rediss://` URL, a certificate needs its key.
    pub fn check(&self, tls: bool) -> Result<(), String> {
        if !tls && !self.is_empty() {
            return Err("store_tls_ca, store_tls_cert and store_tls_key need TLS to Redis: a rediss:// or rediss-cluster:// store URL".into());
        }
        match (&self.cert, &self.key) {
            (Some(_), None) => Err("store_tls_cert (--store-tls-cert, TAMRM_STORE_TLS_CERT) needs its key: store_tls_key".into()),
            (None, Some(_)) => Err("store_tls_key (--store-tls-key, TAMRM_STORE_TLS_KEY) needs its certificate: store_tls_cert".into()),
            _ => Ok(()),
        }
    }

    /// Reads and checks the files, by name, as the Redis client takes them.
    pub(super) fn certificates(&self) -> Result<TlsCertificates, TlsError> {
        let root_cert = match &self.ca {
            Some(ca) => Some(read_certs("Redis TLS CA", ca)?),
            None => None,
        };
        let client_tls = match (&self.cert, &self.key) {
            (Some(cert), Some(key)) => Some(ClientTlsConfig {
                client_cert: read_certs("Redis TLS client certificate", cert)?,
                client_key: read_key("Redis TLS client key", key)?,
            }),
            _ => None,
        };
        Ok(TlsCertificates {
            client_tls,
            root_cert,
        })
    }
}
