//! Credentials, roles, tenants and quotas (SPEC §11).
//!
//! With `--api-keys FILE` every RPC but the health checks carries
//! `authorization: Bearer <key>`. [`Access::authorize`] hashes the key (SHA-256), compares
//! the hash with every known one in constant time, and checks the key's role against the
//! RPC's ([`SHAPING_ROLES`], the one table). The [`AuthLayer`] does this for every request
//! before any handler runs and hands the handler a [`Caller`]: the tenant whose tasks the
//! call sees, and the tenant's quotas. Without a key file every caller is
//! [`Caller::open`]: the default tenant with every right (the server says so at start).
//!
//! The key file is read again by [`Access::reload`] (on SIGHUP); usage counters (open
//! streams, the steps-per-second bucket) carry over.
//!
//! Usage is kept in this process, unless [`Access::open_with`] is given a
//! [`QuotaLedger`] shared with the other replicas of a store: then a tenant's open streams
//! (with `max_open_streams`) are leases in the ledger, and its steps (with
//! `max_steps_per_second`) come from the ledger's bucket a block at a time
//! ([`crate::quota`]); the step path awaits the ledger only when its block runs out. An open stream whose key the reload
//! removes, or whose role it lowers below the stream's, ends at once ([`StreamWatch`]);
//! the other streams keep going.

mod grant;
mod keys;
mod layer;
mod usage;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use dashmap::DashMap;
use parking_lot::RwLock;
use serde::Deserialize;
use sha2::{Digest, Sha256};
use subtle::{ConditionallySelectable, ConstantTimeEq};
use tokio_util::sync::CancellationToken;

pub use grant::StreamWatch;
pub use keys::{check_tenant, Key, KeyFile, KeyFileError, Quotas, MAX_TENANT_LEN};
pub use layer::AuthLayer;

use grant::Grant;
pub use usage::StreamSlot;
use usage::TenantState;

use crate::error::Error;
use crate::quota::QuotaLedger;
use crate::task_key::DEFAULT_TENANT;

/// What a key may do. Each role includes the ones before it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// GetTask, ListTasks, GetPool.
    Reader,
    /// Reader, plus CreateTask, Shape, Follow, AddTrajectory.
    Writer,
    /// Writer, plus DeleteTask, ResetPool.
    Admin,
}

impl Role {
    /// The name used in key files and messages.
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Reader => "reader",
            Role::Writer => "writer",
            Role::Admin => "admin",
        }
    }
}

/// The role each `tamrm.v1.Shaping` RPC needs (SPEC §11). A test checks that it lists
/// every RPC of the proto.
pub const SHAPING_ROLES: &[(&str, Role)] = &[
    ("GetTask", Role::Reader),
    ("ListTasks", Role::Reader),
    ("GetPool", Role::Reader),
    ("CreateTask", Role::Writer),
    ("Shape", Role::Writer),
    ("Follow", Role::Writer),
    ("AddTrajectory", Role::Writer),
    ("DeleteTask", Role::Admin),
    ("ResetPool", Role::Admin),
];

/// The streaming RPCs of [`SHAPING_ROLES`].
pub const STREAMING_RPCS: &[&str] = &["Shape", "Follow"];

/// The unary RPCs: every one of [`SHAPING_ROLES`] but the streams.
pub fn unary_rpcs() -> impl Iterator<Item = &'static str> {
    SHAPING_ROLES
        .iter()
        .map(|(rpc, _)| *rpc)
        .filter(|rpc| !STREAMING_RPCS.contains(rpc))
}

/// What a request without credentials is told, wherever it is refused.
pub const MISSING_CREDENTIALS: &str =
    "missing credentials: this server needs the metadata `authorization: Bearer <key>`";

/// The gRPC health service, which needs no credential.
const HEALTH_SERVICE: &str = "grpc.health.v1.Health";

/// What a request to `path` (`/package.Service/Method`) needs: `None` for health checks;
/// otherwise the role. Server reflection and unknown paths need any valid key.
pub fn needed_role(path: &str) -> Option<Role> {
    let (service, method) = path
        .strip_prefix('/')
        .and_then(|p| p.split_once('/'))
        .unwrap_or(("", ""));
    if service == HEALTH_SERVICE {
        return None;
    }
    if service == crate::proto::shaping_server::SERVICE_NAME {
        if let Some((_, role)) = SHAPING_ROLES.iter().find(|(m, _)| *m == method) {
            return Some(*role);
        }
    }
    Some(Role::Reader)
}

/// Who makes a call: the tenant whose tasks it sees, its role, and the tenant's quotas.
#[derive(Clone)]
pub struct Caller {
    role: Role,
    tenant: Arc<TenantState>,
    /// The key's standing across reloads; `None` for [`Caller::open`].
    grant: Option<Arc<Grant>>,
}

impl std::fmt::Debug for Caller {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Caller")
            .field("tenant", &self.tenant.name)
            .field("role", &self.role)
            .finish()
    }
}

impl Caller {
    /// The caller of a server without credentials (and of the embedded engine): the
    /// default tenant, admin, no quotas.
    pub fn open() -> Caller {
        Caller {
            role: Role::Admin,
            tenant: Arc::new(TenantState::new(DEFAULT_TENANT, Quotas::default(), None)),
            grant: None,
        }
    }

    /// Watches a stream of the streaming RPC `rpc` (one of [`STREAMING_RPCS`]): the
    /// watch ends when `shutdown` is cancelled or when a key file reload removes the
    /// caller's key or lowers its role below the one `rpc` needs.
    pub fn watch_stream(&self, rpc: &'static str, shutdown: &CancellationToken) -> StreamWatch {
        let needed = SHAPING_ROLES
            .iter()
            .find(|(m, _)| *m == rpc)
            .map_or(Role::Admin, |(_, r)| *r);
        StreamWatch::new(self.grant.as_ref(), needed, rpc, shutdown)
    }

    /// The caller's tenant.
    pub fn tenant(&self) -> &str {
        &self.tenant.name
    }

    /// The caller's role.
    pub fn role(&self) -> Role {
        self.role
    }

    /// The tenant's quota of tasks, if any.
    pub fn max_tasks(&self) -> Option<usize> {
        self.tenant.quotas.read().max_tasks
    }

    /// Takes one of the tenant's open-stream slots for as long as the returned guard
    /// lives; `RESOURCE_EXHAUSTED` when the tenant has `max_open_streams` open (with a
    /// shared ledger: over every replica; `UNAVAILABLE` when the ledger cannot answer).
    pub async fn open_stream(&self) -> Result<StreamSlot, Error> {
        self.tenant.open_stream().await
    }

    /// Charges `entries` step entries to the tenant's steps-per-second bucket;
    /// `RESOURCE_EXHAUSTED` (nothing charged) when it does not hold that many. With a
    /// shared ledger the bucket is the ledger's, taken a block at a time (`UNAVAILABLE`
    /// when the ledger cannot answer).
    pub async fn take_steps(&self, entries: usize) -> Result<(), Error> {
        self.tenant.take_steps(entries).await
    }
}

/// The known keys: the SHA-256 of each, and who it makes the caller.
struct KeySet {
    keys: Vec<([u8; 32], Caller)>,
}

/// The key file's keys and every tenant's quotas and usage.
pub struct Access {
    path: PathBuf,
    keys: RwLock<Arc<KeySet>>,
    tenants: DashMap<String, Arc<TenantState>>,
    ledger: Option<Arc<dyn QuotaLedger>>,
}

impl Access {
    /// Reads the key file at `path`; usage is kept in this process.
    pub fn open(path: &Path) -> Result<Access, KeyFileError> {
        Access::open_with(path, None)
    }

    /// Reads the key file at `path`; the stream and step quotas are kept in `ledger`
    /// (shared with the other replicas of a store) if given, else in this process.
    pub fn open_with(
        path: &Path,
        ledger: Option<Arc<dyn QuotaLedger>>,
    ) -> Result<Access, KeyFileError> {
        let access = Access {
            path: path.to_path_buf(),
            keys: RwLock::new(Arc::new(KeySet { keys: Vec::new() })),
            tenants: DashMap::new(),
            ledger,
        };
        access.install(KeyFile::read(path)?);
        Ok(access)
    }

    /// Reads the key file again; on an error the keys in force stay. Returns the number
    /// of keys and of tenants now in force.
    pub fn reload(&self) -> Result<(usize, usize), KeyFileError> {
        let file = KeyFile::read(&self.path)?;
        Ok(self.install(file))
    }

    /// The key file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Puts `file` in force: keeps the tenants' usage, keeps each key's grant while the
    /// key stays with the same tenant (with its new role), and ends the streams of the
    /// keys it removes or lowers.
    fn install(&self, file: KeyFile) -> (usize, usize) {
        let old = self.keys.read().clone();
        let mut tenants = std::collections::BTreeSet::new();
        for t in file
            .keys
            .iter()
            .map(|k| &k.tenant)
            .chain(file.quotas.keys())
        {
            tenants.insert(t.as_str());
        }
        for t in &tenants {
            let quotas = file.quotas.get(*t).copied().unwrap_or_default();
            match self.tenants.get(*t) {
                Some(state) => *state.quotas.write() = quotas,
                None => {
                    let state = TenantState::new(t, quotas, self.ledger.clone());
                    self.tenants.insert(t.to_string(), Arc::new(state));
                }
            }
        }
        let keys = file
            .keys
            .iter()
            .map(|k| {
                let tenant = self
                    .tenants
                    .entry(k.tenant.clone())
                    .or_insert_with(|| {
                        let ledger = self.ledger.clone();
                        let state = TenantState::new(&k.tenant, Quotas::default(), ledger);
                        Arc::new(state)
                    })
                    .clone();
                let kept = old
                    .keys
                    .iter()
                    .find(|(d, c)| *d == k.digest && c.tenant.name == k.tenant)
                    .and_then(|(_, c)| c.grant.clone());
                let grant = kept.unwrap_or_else(|| Grant::new(&k.digest, &k.tenant, k.role));
                (
                    k.digest,
                    Caller {
                        role: k.role,
                        tenant,
                        grant: Some(grant),
                    },
                )
            })
            .collect();
        let set = KeySet { keys };
        let counts = (set.keys.len(), tenants.len());
        *self.keys.write() = Arc::new(set);
        let new = self.keys.read().clone();
        for (digest, caller) in &old.keys {
            let Some(grant) = &caller.grant else { continue };
            let now = new
                .keys
                .iter()
                .find(|(d, c)| d == digest && c.tenant.name == grant.tenant())
                .map(|(_, c)| c.role);
            grant.set_role(now);
        }
        counts
    }

    /// Decides a request to `path` carrying the `authorization` metadata value
    /// `authorization`: `Ok(None)` for a health check, `Ok(Some(caller))` for a key whose
    /// role suffices; otherwise [`Error::Unauthenticated`] (no, a malformed or an unknown
    /// key) or [`Error::PermissionDenied`] (a known key beyond its role). The key is compared by its SHA-256 with
    /// every known hash, in constant time, and is neither kept nor logged.
    pub fn authorize(
        &self,
        path: &str,
        authorization: Option<&[u8]>,
    ) -> Result<Option<Caller>, Error> {
        let Some(needed) = needed_role(path) else {
            return Ok(None);
        };
        let key = bearer(authorization)?;
        let digest: [u8; 32] = Sha256::digest(key).into();
        let set = self.keys.read().clone();
        let mut found = subtle::Choice::from(0);
        let mut index = 0u64;
        for (i, (known, _)) in set.keys.iter().enumerate() {
            let eq = known.ct_eq(&digest);
            index.conditional_assign(&(i as u64), eq);
            found |= eq;
        }
        if !bool::from(found) {
            return Err(Error::Unauthenticated(
                "unknown API key (the server's --api-keys file does not list it)".into(),
            ));
        }
        let caller = set
            .keys
            .get(index as usize)
            .map(|(_, c)| c.clone())
            .ok_or_else(|| Error::Unauthenticated("unknown API key".into()))?;
        if caller.role < needed {
            return Err(Error::PermissionDenied(format!(
                "the key of tenant {:?} has role {}; {path} needs role {} or above",
                caller.tenant(),
                caller.role.as_str(),
                needed.as_str(),
            )));
        }
        Ok(Some(caller))
    }
}

/// The key of an `authorization: Bearer <key>` value.
fn bearer(value: Option<&[u8]>) -> Result<&[u8], Error> {
    let value = value.ok_or_else(|| Error::Unauthenticated(MISSING_CREDENTIALS.into()))?;
    let scheme = b"bearer ";
    let key = match value.get(..scheme.len()) {
        Some(p) if p.eq_ignore_ascii_case(scheme) => &value[scheme.len()..],
        _ => {
            return Err(Error::Unauthenticated(
                "the authorization metadata must be `Bearer <key>`".into(),
            ))
        }
    };
    let key = key.trim_ascii();
    if key.is_empty() {
        return Err(Error::Unauthenticated(
            "the authorization metadata holds an empty key".into(),
        ));
    }
    Ok(key)
}

/// A new random key: 32 bytes from the operating system's generator, as 64 hex digits
/// prefixed `tamrm_` (so a leaked key is easy to recognise and search for).
pub fn new_key() -> std::io::Result<String> {
    use std::io::Read;
    let mut bytes = [0u8; 32];
    std::fs::File::open("/dev/urandom")?.read_exact(&mut bytes)?;
    Ok(format!("tamrm_{}", hex(&bytes)))
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The SHA-256 of `key` in lowercase hex, as the key file wants it.
pub fn hash_key(key: &[u8]) -> String {
    hex(&Sha256::digest(key))
}

#[cfg(test)]
mod tests;
