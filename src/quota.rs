//! Tenant quotas shared by the replicas of one store: the [`QuotaLedger`] seam between
//! the auth layer, which decides, and a shared store that keeps the usage of every replica
//! (Redis: `store::redis::ledger`), and [`StepBlocks`], the local side of a shared
//! steps-per-second bucket.
//!
//! Without a ledger (the memory and data-dir stores, or one server alone) the auth layer
//! keeps each tenant's usage in its own process, as it always did: an atomic counter of
//! open streams and a local token bucket, with no await on the step path. With one:
//! - open streams are **leases** in the ledger, taken when a stream opens (refused past
//!   `max_open_streams` over every replica), given back when it ends, and renewed while
//!   it lasts, so that a replica that dies without giving them back loses them within the
//!   ledger's lease time;
//! - steps are taken from the ledger's token bucket in **blocks** (a tenth of a second's
//!   worth, or the batch if larger) into a local bucket, so a batch costs the ledger a
//!   round trip only when the local tokens run out. A replica holds at most one block it
//!   has not spent yet: over any interval the tenant's replicas together accept at most
//!   the single-server bound plus one block per replica (docs/deployment.md, "Quotas with
//!   replicas").
//!
//! The task quota is not here: it must be checked atomically with the creation of the
//! task in the store's task index (`Store::reserve_task`).
//!
//! A leaf module: it uses nothing of the crate, so the auth layer (which may not use the
//! store) and the store (which may not use the auth layer) can both use it.

use std::sync::Arc;

use parking_lot::Mutex;

/// Why the ledger could not answer: its store cannot be reached or failed.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{0}")]
pub struct LedgerError(pub String);

/// A lease on one of a tenant's open streams in a [`QuotaLedger`], given back when
/// dropped (what it holds is the ledger's).
pub struct StreamLease(#[allow(dead_code)] Box<dyn Send + Sync>);

impl StreamLease {
    /// A lease that holds `guard`, whose drop gives the lease back.
    pub fn new(guard: impl Send + Sync + 'static) -> StreamLease {
        StreamLease(Box::new(guard))
    }
}

impl std::fmt::Debug for StreamLease {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("StreamLease")
    }
}

/// Per-tenant usage kept for every replica that shares it.
#[async_trait::async_trait]
pub trait QuotaLedger: Send + Sync + 'static {
    /// One line saying where the usage lives, for the start-up log.
    fn describe(&self) -> String;

    /// Takes a lease on one of `tenant`'s open streams if the tenant holds fewer than
    /// `max` live leases over every replica; `Ok(None)` if it holds `max`.
    async fn open_stream(
        &self,
        tenant: &str,
        max: usize,
    ) -> Result<Option<StreamLease>, LedgerError>;

    /// Takes step tokens from `tenant`'s bucket, which refills at `rate` tokens per second
    /// up to `rate`: `want` tokens if it holds them, else all it holds if that is at least
    /// `need`; else none. Answers how many it took (0, or from `need` to `want`).
    async fn take_steps(
        &self,
        tenant: &str,
        rate: u64,
        need: u64,
        want: u64,
    ) -> Result<u64, LedgerError>;
}

/// The block of step tokens one replica takes from a ledger at a time: a tenth of a
/// second's worth at `rate` (at least one).
pub fn block_of(rate: u64) -> u64 {
    (rate / 10).max(1)
}

/// The local side of a tenant's shared steps-per-second bucket on one replica: tokens
/// taken from the ledger and not spent yet (at most one block after any take).
#[derive(Default)]
pub struct StepBlocks {
    /// Tokens held locally.
    held: Mutex<u64>,
    /// Serialises this replica's takes from the ledger for the tenant, so that it holds
    /// one block at most (the step path does not wait on it while it holds tokens).
    fetch: tokio::sync::Mutex<()>,
}

impl StepBlocks {
    /// Takes `n` tokens for `tenant` at `rate`: from the local tokens when they suffice
    /// (no await), else from `ledger`, in a block. `Ok(false)` (nothing spent) when the
    /// ledger's bucket does not hold what is missing.
    pub async fn take(
        &self,
        ledger: &Arc<dyn QuotaLedger>,
        tenant: &str,
        rate: u64,
        n: u64,
    ) -> Result<bool, LedgerError> {
        if self.take_held(n) {
            return Ok(true);
        }
        let _fetching = self.fetch.lock().await;
        // Another stream of the tenant may have fetched meanwhile.
        let need = {
            let mut held = self.held.lock();
            if *held >= n {
                *held -= n;
                return Ok(true);
            }
            n - *held
        };
        let want = need.max(block_of(rate));
        let got = ledger.take_steps(tenant, rate, need, want).await?;
        let mut held = self.held.lock();
        *held += got;
        if *held < n {
            return Ok(false);
        }
        *held -= n;
        Ok(true)
    }

    /// Takes `n` of the local tokens if they suffice.
    fn take_held(&self, n: u64) -> bool {
        let mut held = self.held.lock();
        if *held < n {
            return false;
        }
        *held -= n;
        true
    }

    /// The tokens held locally.
    pub fn held(&self) -> u64 {
        *self.held.lock()
    }
}

#[cfg(test)]
pub(crate) mod testing;
#[cfg(test)]
mod tests;
