//! Group commit within one task: what a [`super::TaskHandle`] keeps between planning a
//! change (under its writer lock) and the store's acknowledgement of it.
//!
//! A writer plans against the *planned* pool: the published pool plus every change queued
//! or in flight. It queues its operations and releases the writer lock; one leader at a
//! time commits everything queued, in planning order, as one store commit against the
//! last committed pool, publishes the result and answers each request with its own slice
//! of it. Applying the concatenated operations one by one to the last committed pool is
//! exactly what planning them one after the other did (SPEC §6 is deterministic), so the
//! group decides what sequential commits would have decided.

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use tokio::sync::oneshot;

use crate::core::Pool;
use crate::error::Error;
use crate::store::{Committed, GroupCommitted, PoolOp, StoreError};

/// The planned pool while changes are queued or in flight: `base` with the operations of
/// `tail` applied. `base` holds every request up to `through`; `tail` the later ones, per
/// request, in planning order. A writer that shapes against the planned pool (a Shape
/// stream's batch) applies the tail (without laying the pool out: it serves planning and
/// the rest of a batch, not the step path) and keeps the result as the base; writers that
/// only queue operations (Follow ends, `AddTrajectory`, `ResetPool`) never need it. When
/// a group is committed the base moves on to the committed pool, so the tail only ever
/// holds the requests not committed yet.
pub(super) struct Planned {
    pub base: Arc<Pool>,
    pub through: u64,
    pub tail: Vec<(u64, Vec<PoolOp>)>,
}

impl Planned {
    /// The planned pool: applies the tail to the base and keeps the result as the base.
    pub fn materialise(&mut self) -> Arc<Pool> {
        if let Some(&(last, _)) = self.tail.last() {
            let tail = std::mem::take(&mut self.tail);
            let ops = tail.into_iter().flat_map(|(_, ops)| ops);
            self.base = Arc::new(Planned::apply(&self.base, ops));
            self.through = last;
        }
        self.base.clone()
    }

    /// The group of requests up to `last` is committed, with `pool` as the result.
    pub fn committed(&mut self, last: u64, pool: &Arc<Pool>) {
        if self.through < last {
            self.base = pool.clone();
            self.through = last;
            self.tail.retain(|&(n, _)| n > last);
        }
    }

    /// `base` with `ops` applied in order (SPEC §6), as the store will apply them.
    pub fn apply(base: &Pool, ops: impl IntoIterator<Item = PoolOp>) -> Pool {
        let mut pool = base.clone();
        for op in ops {
            let change = match op {
                PoolOp::Offer { actions, score, .. } => pool.plan_offer(actions, score),
                PoolOp::Reset => Some(pool.plan_reset()),
            };
            if let Some(change) = change {
                pool.apply_without_layout(&change);
            }
        }
        pool
    }
}

/// The episode ends a request commits for a named client (SPEC §9): the client, and each
/// (env, episode).
pub(super) type Marks = (Arc<str>, Vec<(u32, u64)>);

/// One writer's planned change, waiting for its group's commit.
pub(super) struct Request {
    /// Its place in planning order (from 1).
    pub number: u64,
    pub ops: Vec<PoolOp>,
    pub marks: Option<Marks>,
    pub answer: oneshot::Sender<Result<Committed, Error>>,
}

/// Episode ends of requests queued or in flight, per client and env: the episodes ended
/// with them and the number of the last request that named them. A writer must not offer
/// them again (SPEC §9) although they are not committed yet; they move to the record of
/// committed ends when their group is acknowledged, and are forgotten when it fails
/// (every request planned on top of it fails too).
#[derive(Default)]
pub(super) struct Pending(HashMap<Arc<str>, HashMap<u32, (u64, u64)>>);

impl Pending {
    /// Request `number` ends `(env, episode)` of `client`.
    pub fn add(&mut self, number: u64, client: &Arc<str>, ends: &[(u32, u64)]) {
        let envs = self.0.entry(client.clone()).or_default();
        for &(env, episode) in ends {
            let e = envs.entry(env).or_insert((0, number));
            *e = (e.0.max(episode.saturating_add(1)), e.1.max(number));
        }
    }

    /// Whether a queued or in-flight request ends episode `number` of `env` of `client`
    /// (or a later one).
    pub fn contains(&self, client: &str, env: u32, number: u64) -> bool {
        self.0
            .get(client)
            .and_then(|envs| envs.get(&env))
            .is_some_and(|&(count, _)| count > number)
    }

    /// Forgets what requests up to `number` named (their group was acknowledged: the
    /// record of committed ends has them now).
    pub fn release(&mut self, number: u64) {
        self.0.retain(|_, envs| {
            envs.retain(|_, &mut (_, by)| by > number);
            !envs.is_empty()
        });
    }

    pub fn clear(&mut self) {
        self.0.clear();
    }
}

/// A task's commits between planning and acknowledgement.
#[derive(Default)]
pub(super) struct Commits {
    /// `None` when nothing is queued or in flight: writers then plan against the published
    /// pool.
    pub planned: Option<Planned>,
    /// Requests waiting for the next group, in planning order.
    pub queue: Vec<Request>,
    /// A leader is committing a group; it takes the queue after it.
    pub leading: bool,
    /// Bumped by every failed group: a writer that took its base before can commit
    /// nothing (its plan assumed the failed changes).
    pub epoch: u64,
    /// Why the last group failed, for those writers.
    pub failure: Option<StoreError>,
    pub pending: Pending,
    /// The number of the last request queued.
    pub last: u64,
}

impl Commits {
    /// A group failed with `error`: forgets what was planned on top of it and returns the
    /// queued requests, which fail too.
    pub fn fail(&mut self, error: StoreError) -> Vec<Request> {
        self.epoch += 1;
        self.failure = Some(error);
        self.planned = None;
        self.pending.clear();
        self.leading = false;
        std::mem::take(&mut self.queue)
    }
}

/// Each request's answer out of its group's commit: its own slice of `changed`, its own
/// version (the version after the group minus the changes after its slice: one version
/// per change), the group's pool, and its own re-sent ends. `lens` is the number of
/// operations of each request; `marked` whether it carries episode ends of a named client
/// (the only offers a store can find re-sent): when the store cannot say whose re-sent
/// ends they were, each of those requests is answered with all of them, so that none of
/// them goes on as if none were re-sent.
pub(super) fn split(done: &GroupCommitted, lens: &[usize], marked: &[bool]) -> Vec<Committed> {
    let c = &done.committed;
    let changes = |v: &[bool]| v.iter().filter(|&&x| x).count() as u64;
    let total = changes(&c.changed);
    let mut answers = Vec::with_capacity(lens.len());
    let (mut at, mut so_far) = (0, 0);
    for (i, &n) in lens.iter().enumerate() {
        let end = (at + n).min(c.changed.len());
        let changed = c.changed[at.min(end)..end].to_vec();
        at += n;
        so_far += changes(&changed);
        let resent = match &done.resent {
            Some(per_part) => per_part.get(i).copied().unwrap_or(0),
            None if marked.get(i).copied().unwrap_or(false) => c.resent,
            None => 0,
        };
        answers.push(Committed {
            pool: c.pool.clone(),
            changed,
            version: c.version.saturating_sub(total - so_far),
            resent,
        });
    }
    answers
}

/// A future that, dropped before it finished (its caller was cancelled), is handed to the
/// runtime to finish: a group commit, once started, runs to its end (the store commits,
/// the pool is published, every request is answered) whoever stopped waiting for it.
pub(super) struct Detached(Option<Pin<Box<dyn Future<Output = ()> + Send + 'static>>>);

impl Detached {
    pub fn new(f: impl Future<Output = ()> + Send + 'static) -> Detached {
        Detached(Some(Box::pin(f)))
    }
}

impl Future for Detached {
    type Output = ();

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
        let Some(f) = self.0.as_mut() else {
            return Poll::Ready(());
        };
        if f.as_mut().poll(cx).is_pending() {
            return Poll::Pending;
        }
        self.0 = None;
        Poll::Ready(())
    }
}

impl Drop for Detached {
    fn drop(&mut self) {
        if let Some(f) = self.0.take() {
            if let Ok(runtime) = tokio::runtime::Handle::try_current() {
                runtime.spawn(f);
            }
        }
    }
}

#[cfg(test)]
mod tests;
