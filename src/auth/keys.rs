//! The API key file (`--api-keys FILE`): which key hashes map to which tenant and role,
//! and each tenant's quotas. Keys are never in the file, only their SHA-256.
//!
//! ```toml
//! [[keys]]
//! tenant = "team-a"
//! role = "writer"          # reader | writer | admin
//! sha256 = "<hex SHA-256 of the key>"
//!
//! [tenants.team-a]         # optional; a tenant without an entry has no quotas
//! max_tasks = 10
//! max_open_streams = 8
//! max_steps_per_second = 200000
//! ```

use std::collections::{BTreeMap, HashSet};
use std::path::Path;

use serde::Deserialize;

use super::Role;

/// The longest tenant name.
pub const MAX_TENANT_LEN: usize = 64;

/// One `[[keys]]` entry, as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyEntry {
    tenant: String,
    role: Role,
    sha256: String,
    /// A label for the operator (e.g. who holds the key); never used for access.
    #[serde(default)]
    #[allow(dead_code)]
    name: Option<String>,
}

/// A tenant's quotas; `None` is unlimited (the server's own limits still apply).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Quotas {
    /// Tasks the tenant may hold at once.
    pub max_tasks: Option<usize>,
    /// Shape streams the tenant may have open at once.
    pub max_open_streams: Option<usize>,
    /// Step entries per second over all of the tenant's streams (a token bucket holding
    /// one second's worth).
    pub max_steps_per_second: Option<u64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFile {
    #[serde(default)]
    keys: Vec<KeyEntry>,
    #[serde(default)]
    tenants: BTreeMap<String, Quotas>,
}

/// One known key: the SHA-256 of the key, its tenant and role.
#[derive(Debug, Clone)]
pub struct Key {
    /// SHA-256 of the key's bytes.
    pub digest: [u8; 32],
    /// The tenant the key acts for.
    pub tenant: String,
    /// What the key may do.
    pub role: Role,
}

/// A parsed and checked key file.
#[derive(Debug, Clone, Default)]
pub struct KeyFile {
    /// Every key, in file order.
    pub keys: Vec<Key>,
    /// Quotas by tenant.
    pub quotas: BTreeMap<String, Quotas>,
}

/// Why a key file cannot be used; names the file and the entry.
#[derive(Debug, thiserror::Error)]
#[error("API key file {path}: {message}")]
pub struct KeyFileError {
    path: String,
    message: String,
}

impl KeyFile {
    /// Reads and checks `path`.
    pub fn read(path: &Path) -> Result<KeyFile, KeyFileError> {
        let fail = |message: String| KeyFileError {
            path: path.display().to_string(),
            message,
        };
        let text = std::fs::read_to_string(path).map_err(|e| fail(e.to_string()))?;
        KeyFile::parse(&text).map_err(fail)
    }

    /// Parses and checks the text of a key file.
    pub fn parse(text: &str) -> Result<KeyFile, String> {
        let raw: RawFile = toml::from_str(text).map_err(|e| e.to_string())?;
        let mut seen = HashSet::new();
        let mut keys = Vec::with_capacity(raw.keys.len());
        for (i, k) in raw.keys.into_iter().enumerate() {
            let at = format!("keys[{i}]");
            check_tenant(&k.tenant).map_err(|m| format!("{at}.tenant: {m}"))?;
            let digest = parse_digest(&k.sha256).map_err(|m| format!("{at}.sha256: {m}"))?;
            if !seen.insert(digest) {
                return Err(format!(
                    "{at}.sha256: the same key is listed twice (each key maps to one tenant and role)"
                ));
            }
            keys.push(Key {
                digest,
                tenant: k.tenant,
                role: k.role,
            });
        }
        for (tenant, q) in &raw.tenants {
            check_tenant(tenant).map_err(|m| format!("tenants.{tenant}: {m}"))?;
            if q.max_steps_per_second == Some(0) {
                return Err(format!(
                    "tenants.{tenant}.max_steps_per_second: must be >= 1 (leave it out for no limit)"
                ));
            }
        }
        Ok(KeyFile {
            keys,
            quotas: raw.tenants,
        })
    }
}

/// Tenant names: 1 to [`MAX_TENANT_LEN`] characters of `[A-Za-z0-9._-]` (no `@`: see
/// [`crate::task_key`]).
pub fn check_tenant(name: &str) -> Result<(), String> {
    if name.is_empty() || name.len() > MAX_TENANT_LEN {
        return Err(format!(
            "a tenant name has 1 to {MAX_TENANT_LEN} characters, got {}",
            name.len()
        ));
    }
    match name
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-')))
    {
        Some(c) => Err(format!(
            "{name:?}: character {c:?} not allowed (use A-Z a-z 0-9 . _ -)"
        )),
        None => Ok(()),
    }
}

fn parse_digest(hex: &str) -> Result<[u8; 32], String> {
    let hex = hex.trim();
    if hex.len() != 64 {
        return Err(format!(
            "expected 64 hex digits (the SHA-256 of the key, e.g. from `tamrm hash-key`), got {} characters",
            hex.len()
        ));
    }
    let mut out = [0u8; 32];
    for (i, pair) in hex.as_bytes().chunks(2).enumerate() {
        let digit = |b: u8| (b as char).to_digit(16);
        match (digit(pair[0]), digit(pair[1])) {
            (Some(h), Some(l)) => out[i] = (h * 16 + l) as u8,
            _ => return Err("not a hex string".to_string()),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests;
