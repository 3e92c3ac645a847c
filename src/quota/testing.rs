//! A [`QuotaLedger`] in memory for unit tests, shared by several callers as by several
//! replicas: leases counted, steps from a bucket that never refills (it holds what the
//! test gives it), every take counted; `down` makes every call fail.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;

use parking_lot::Mutex;

use super::{LedgerError, QuotaLedger, StreamLease};

/// See the [module documentation](self).
#[derive(Default)]
pub(crate) struct FixedLedger {
    /// Live leases.
    pub leases: Arc<AtomicUsize>,
    /// Step tokens left.
    pub tokens: Mutex<u64>,
    /// Takes of step tokens asked.
    pub calls: AtomicU64,
    /// Every call fails while set.
    pub down: AtomicBool,
}

impl FixedLedger {
    /// A ledger holding `tokens` step tokens.
    pub fn with_tokens(tokens: u64) -> Arc<FixedLedger> {
        Arc::new(FixedLedger {
            tokens: Mutex::new(tokens),
            ..FixedLedger::default()
        })
    }

    fn check(&self) -> Result<(), LedgerError> {
        match self.down.load(Ordering::Acquire) {
            true => Err(LedgerError("redis is down".into())),
            false => Ok(()),
        }
    }
}

/// A lease of a [`FixedLedger`].
struct Lease(Arc<AtomicUsize>);

impl Drop for Lease {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

#[async_trait::async_trait]
impl QuotaLedger for FixedLedger {
    fn describe(&self) -> String {
        "a fixed ledger in memory".into()
    }

    async fn open_stream(
        &self,
        _tenant: &str,
        max: usize,
    ) -> Result<Option<StreamLease>, LedgerError> {
        self.check()?;
        let took = self
            .leases
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < max).then_some(n + 1)
            });
        Ok(took
            .is_ok()
            .then(|| StreamLease::new(Lease(self.leases.clone()))))
    }

    async fn take_steps(
        &self,
        _tenant: &str,
        _rate: u64,
        need: u64,
        want: u64,
    ) -> Result<u64, LedgerError> {
        self.check()?;
        self.calls.fetch_add(1, Ordering::Relaxed);
        let mut t = self.tokens.lock();
        let got = if *t < need { 0 } else { want.min(*t) };
        *t -= got;
        Ok(got)
    }
}
