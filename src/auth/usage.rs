//! A tenant's quotas and usage, across key file reloads: open streams and the
//! steps-per-second bucket, kept in this process or in a [`QuotaLedger`] shared with the
//! other replicas of a store.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Instant;

use parking_lot::{Mutex, RwLock};

use super::Quotas;
use crate::error::Error;
use crate::quota::{QuotaLedger, StepBlocks, StreamLease};

/// One of a tenant's open-stream slots, released when dropped.
pub struct StreamSlot(Slot);

/// Where a [`StreamSlot`] is counted.
enum Slot {
    /// In the tenant's counter in this process.
    Counted(Arc<TenantState>),
    /// As a lease in the shared ledger (given back by the lease's drop).
    Leased(#[allow(dead_code)] StreamLease),
}

impl std::fmt::Debug for StreamSlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.0 {
            Slot::Counted(t) => write!(f, "StreamSlot(counted, tenant {:?})", t.name),
            Slot::Leased(_) => f.write_str("StreamSlot(leased)"),
        }
    }
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        if let Slot::Counted(tenant) = &self.0 {
            tenant.open_streams.fetch_sub(1, Ordering::AcqRel);
        }
    }
}

/// A tenant's quotas and usage; lives across key file reloads.
pub(super) struct TenantState {
    pub(super) name: String,
    pub(super) quotas: RwLock<Quotas>,
    pub(super) open_streams: AtomicUsize,
    bucket: Mutex<Bucket>,
    /// The ledger shared with other replicas, if any (then `blocks` replaces `bucket`,
    /// and leases replace `open_streams` for a tenant with `max_open_streams`).
    ledger: Option<Arc<dyn QuotaLedger>>,
    blocks: StepBlocks,
}

/// A token bucket holding at most one second's worth of steps.
pub(super) struct Bucket {
    pub(super) tokens: f64,
    pub(super) at: Instant,
}

impl Bucket {
    /// Refills the bucket for the time since the last call at `rate` tokens per second
    /// (up to `rate`), then takes `n` tokens if it holds them.
    pub(super) fn take(&mut self, n: u64, rate: u64, now: Instant) -> bool {
        let rate = rate as f64;
        let refill = now.saturating_duration_since(self.at).as_secs_f64() * rate;
        self.tokens = (self.tokens + refill).min(rate);
        self.at = now;
        if self.tokens < n as f64 {
            return false;
        }
        self.tokens -= n as f64;
        true
    }
}

impl TenantState {
    pub(super) fn new(
        name: &str,
        quotas: Quotas,
        ledger: Option<Arc<dyn QuotaLedger>>,
    ) -> TenantState {
        TenantState {
            name: name.to_string(),
            ledger,
            blocks: StepBlocks::default(),
            bucket: Mutex::new(Bucket {
                tokens: quotas.max_steps_per_second.unwrap_or(0) as f64,
                at: Instant::now(),
            }),
            quotas: RwLock::new(quotas),
            open_streams: AtomicUsize::new(0),
        }
    }
}

impl TenantState {
    /// Takes one of the tenant's open-stream slots for as long as the returned guard
    /// lives (see [`Caller::open_stream`](super::Caller::open_stream)); `RESOURCE_EXHAUSTED` when the tenant has `max_open_streams` open (with a
    /// shared ledger: over every replica; `UNAVAILABLE` when the ledger cannot answer).
    pub(super) async fn open_stream(self: &Arc<Self>) -> Result<StreamSlot, Error> {
        let max = self.quotas.read().max_open_streams;
        if let (Some(ledger), Some(max)) = (&self.ledger, max) {
            return match ledger.open_stream(&self.name, max).await {
                Ok(Some(lease)) => Ok(StreamSlot(Slot::Leased(lease))),
                Ok(None) => Err(self.stream_quota_reached(max)),
                Err(e) => Err(Error::StoreUnavailable(format!(
                    "cannot check the stream quota of tenant {:?} (max_open_streams = {max}): {e}",
                    self.name
                ))),
            };
        }
        let open = &self.open_streams;
        let took = open.fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| match max {
            Some(m) if n >= m => None,
            _ => Some(n + 1),
        });
        match took {
            Ok(_) => Ok(StreamSlot(Slot::Counted(self.clone()))),
            Err(_) => Err(self.stream_quota_reached(max.unwrap_or_default())),
        }
    }

    fn stream_quota_reached(&self, max: usize) -> Error {
        Error::ResourceExhausted(format!(
            "stream quota reached: tenant {:?} may have at most max_open_streams = {max} streams (Shape and Follow) open",
            self.name,
        ))
    }

    /// Charges `entries` step entries to the tenant's steps-per-second bucket;
    /// `RESOURCE_EXHAUSTED` (nothing charged) when it does not hold that many. With a
    /// shared ledger the bucket is the ledger's, taken a block at a time (`UNAVAILABLE`
    /// when the ledger cannot answer).
    pub(super) async fn take_steps(&self, entries: usize) -> Result<(), Error> {
        let Some(rate) = self.quotas.read().max_steps_per_second else {
            return Ok(());
        };
        let entries = entries as u64;
        let over = |why: &str| {
            Err(Error::ResourceExhausted(format!(
                "step quota: tenant {:?} may shape at most max_steps_per_second = {rate} entries per second; {why}",
                self.name
            )))
        };
        if entries > rate {
            return over(&format!(
                "a batch of {entries} entries can never fit: send smaller batches"
            ));
        }
        let taken = match &self.ledger {
            None => self
                .bucket
                .lock()
                .take(entries, rate, Instant::now()),
            Some(ledger) => self
                .blocks
                .take(ledger, &self.name, rate, entries)
                .await
                .map_err(|e| {
                    Error::StoreUnavailable(format!(
                        "cannot check the step quota of tenant {:?} (max_steps_per_second = {rate}): {e}",
                        self.name
                    ))
                })?,
        };
        if !taken {
            return over("this batch is over it: slow down and reconnect");
        }
        Ok(())
    }
}
