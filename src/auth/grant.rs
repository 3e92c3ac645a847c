//! What a key may do now, shared by every stream the key opened: a key file reload that
//! removes the key or lowers its role below what a stream needs ends that stream at once
//! (between two of its messages, idle or not), with `UNAUTHENTICATED` or
//! `PERMISSION_DENIED`.
//!
//! Each known key has one [`Grant`], kept across reloads for as long as the key stays in
//! the file with the same tenant. A stream registers itself with its key's grant when it
//! opens ([`StreamWatch`]); the reload that takes the key away (or lowers its role below
//! the stream's need) cancels the stream's token. The stream already waits on a token
//! between messages (the server's shutdown, of which the stream's token is a child), so
//! the step path does no more work than before: no lock and no extra load per message.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;

use parking_lot::Mutex;
use tokio_util::sync::CancellationToken;

use super::Role;
use crate::error::Error;

/// The value of [`Grant::role`] once the key is no longer in the key file.
const REMOVED: u8 = u8::MAX;

fn role_code(role: Role) -> u8 {
    match role {
        Role::Reader => 0,
        Role::Writer => 1,
        Role::Admin => 2,
    }
}

fn role_of(code: u8) -> Option<Role> {
    match code {
        0 => Some(Role::Reader),
        1 => Some(Role::Writer),
        2 => Some(Role::Admin),
        _ => None,
    }
}

/// One key's standing: its tenant, the first 8 hex digits of its SHA-256 (the name logs
/// and messages give it; never the key), its current role, and the streams it opened.
pub(super) struct Grant {
    tenant: String,
    prefix: String,
    role: AtomicU8,
    streams: Mutex<Streams>,
}

/// The open streams of one key: an id, the role each needs, its token.
#[derive(Default)]
struct Streams {
    next: u64,
    open: Vec<(u64, Role, CancellationToken)>,
}

impl Grant {
    /// The grant of a key with SHA-256 `digest` for `tenant` with `role`.
    pub(super) fn new(digest: &[u8; 32], tenant: &str, role: Role) -> Arc<Grant> {
        Arc::new(Grant {
            tenant: tenant.to_string(),
            prefix: super::hex(&digest[..4]),
            role: AtomicU8::new(role_code(role)),
            streams: Mutex::new(Streams::default()),
        })
    }

    /// The key's tenant.
    pub(super) fn tenant(&self) -> &str {
        &self.tenant
    }

    /// Sets the key's role (`None`: the key was removed) and ends the open streams that
    /// need more; logs, by tenant and hash prefix, how many ended. Returns that number.
    pub(super) fn set_role(&self, role: Option<Role>) -> usize {
        let code = role.map_or(REMOVED, role_code);
        if self.role.swap(code, Ordering::AcqRel) == code {
            return 0;
        }
        let mut streams = self.streams.lock();
        let before = streams.open.len();
        streams.open.retain(|(_, needed, token)| {
            let keep = role.is_some_and(|r| r >= *needed);
            if !keep {
                token.cancel();
            }
            keep
        });
        let ended = before - streams.open.len();
        match role {
            None => tracing::info!(
                tenant = %self.tenant,
                key = %self.prefix,
                streams_ended = ended,
                "API key removed from the key file: its open streams end (UNAUTHENTICATED)"
            ),
            Some(r) => tracing::info!(
                tenant = %self.tenant,
                key = %self.prefix,
                role = r.as_str(),
                streams_ended = ended,
                "API key's role changed: its open streams that need more end (PERMISSION_DENIED)"
            ),
        }
        ended
    }

    /// Why a stream needing `needed` may no longer go on, if it may not.
    fn refusal(&self, needed: Role, rpc: &str) -> Option<Error> {
        match role_of(self.role.load(Ordering::Acquire)) {
            None => Some(Error::Unauthenticated(format!(
                "the API key of this {rpc} stream (tenant {:?}, SHA-256 {}…) was removed from the server's key file; the stream is closed",
                self.tenant, self.prefix
            ))),
            Some(r) if r < needed => Some(Error::PermissionDenied(format!(
                "the API key of this {rpc} stream (tenant {:?}, SHA-256 {}…) now has role {}; {rpc} needs role {} or above; the stream is closed",
                self.tenant,
                self.prefix,
                r.as_str(),
                needed.as_str()
            ))),
            Some(_) => None,
        }
    }
}

/// An open stream's watch over its key and the server's shutdown: [`StreamWatch::ended`]
/// completes when either takes the stream away, and [`StreamWatch::why`] says which.
/// Dropping it unregisters the stream from its key.
pub struct StreamWatch {
    token: CancellationToken,
    shutdown: CancellationToken,
    grant: Option<(Arc<Grant>, u64)>,
    needed: Role,
    rpc: &'static str,
}

impl StreamWatch {
    /// Watches a stream of the RPC `rpc`, which needs `needed`, opened with `grant`'s key
    /// (`None`: a server without keys, where only `shutdown` ends streams).
    pub(super) fn new(
        grant: Option<&Arc<Grant>>,
        needed: Role,
        rpc: &'static str,
        shutdown: &CancellationToken,
    ) -> StreamWatch {
        let token = shutdown.child_token();
        let grant = grant.map(|g| {
            let mut streams = g.streams.lock();
            let id = streams.next;
            streams.next += 1;
            streams.open.push((id, needed, token.clone()));
            (g.clone(), id)
        });
        let watch = StreamWatch {
            token,
            shutdown: shutdown.clone(),
            grant,
            needed,
            rpc,
        };
        // A reload between the authorisation and the registration is seen here.
        if watch.refusal().is_some() {
            watch.token.cancel();
        }
        watch
    }

    fn refusal(&self) -> Option<Error> {
        self.grant
            .as_ref()
            .and_then(|(g, _)| g.refusal(self.needed, self.rpc))
    }

    /// Completes when the server shuts down or the stream's key no longer allows it.
    pub async fn ended(&self) {
        self.token.cancelled().await
    }

    /// Why [`StreamWatch::ended`] completed: the key's refusal (`UNAUTHENTICATED`,
    /// `PERMISSION_DENIED`), else the shutdown.
    pub fn why(&self) -> Error {
        if let Some(refusal) = self.refusal() {
            if let Some((g, _)) = &self.grant {
                tracing::info!(tenant = %g.tenant, key = %g.prefix, rpc = self.rpc, "stream ended: its API key no longer allows it");
            }
            return refusal;
        }
        if self.shutdown.is_cancelled() {
            return Error::ShuttingDown;
        }
        // The key was taken away, then given back before the stream looked.
        Error::PermissionDenied(format!(
            "the API key of this {} stream lost its role while the stream was open; the stream is closed",
            self.rpc
        ))
    }
}

impl Drop for StreamWatch {
    fn drop(&mut self) {
        if let Some((g, id)) = &self.grant {
            g.streams.lock().open.retain(|(i, _, _)| i != id);
        }
    }
}

#[cfg(test)]
mod tests;
