//! One task: its immutable config, its published pool, its counters, and the path by
//! which its pool changes.
//!
//! The pool is published as an `Arc<Pool>` behind a `RwLock` that is only ever held for
//! a pointer copy or swap: the step path takes a snapshot and shapes without any lock,
//! and notices a newer pool with one atomic load.
//!
//! Pool changes of one task are *planned* one at a time, under its writer lock, against
//! the planned pool: the published pool plus every change queued or in flight. A writer
//! queues its operations and releases the lock at once; it does not hold it across the
//! store's commit. One leader at a time commits everything queued meanwhile, in planning
//! order, as one store commit (one record and one sync on the disk store, one script on
//! Redis) against the last committed pool, publishes the result, and answers each writer
//! with its own slice; no answer is sent before the store acknowledged its group (SPEC
//! §10). The leader is the writer that found no group in flight: it commits its own
//! change inline, and hands what queued meanwhile to a task of its own that commits group
//! after group until the queue is empty (`group.rs`). A failed group fails every request
//! in it and every request planned on top of it, and publishes nothing. Readers keep
//! shaping against the published pool meanwhile.
//!
//! Long file: planning, leading a group, publishing and refreshing from the store all
//! read and write the same private fields of the handle (the writer lock, the planned
//! and published pools, the queue); split, they would need those fields made visible to
//! the registry. The group's own state machine is already in `group.rs`.

use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;

use parking_lot::RwLock;
use tokio::sync::{oneshot, Mutex, Notify, OwnedMutexGuard};

use super::group::{self, Commits, Detached, Planned, Request};
use crate::core::{ActionSeq, Pool, TaskConfig};
use crate::error::Error;
use crate::limits::Limits;
use crate::store::{Committed, Counters, EndedEpisodes, GroupCommitted, PoolOp, Store, StoreError};

/// Live statistics of a task (the proto's `TaskStats`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TaskStats {
    /// Trajectories in the pool.
    pub pool_size: usize,
    /// Pool version.
    pub pool_version: u64,
    /// L_min, 0 if empty.
    pub min_length: usize,
    /// Highest stored score, 0 if empty.
    pub best_score: f64,
    /// Lowest stored score, 0 if empty.
    pub worst_score: f64,
    /// Episodes ended by streams.
    pub episodes_completed: u64,
    /// Entries shaped.
    pub steps_shaped: u64,
    /// Open Shape streams.
    pub open_streams: u32,
}

/// One task of the registry.
pub struct TaskHandle {
    /// The registry's and the store's key: [`super::task_key`] of tenant and id.
    key: String,
    config: TaskConfig,
    /// The published pool; the lock is held only to copy or swap the `Arc`.
    pool: RwLock<Arc<Pool>>,
    /// Serialises the planning of pool changes (and deletion) of this task.
    writer: Arc<Mutex<()>>,
    /// The changes planned and not yet acknowledged, and who commits them.
    commits: parking_lot::Mutex<Commits>,
    /// Woken whenever no group is in flight any more.
    idle: Notify,
    /// Version of the published pool, so the step path can notice a change with one load.
    published: AtomicU64,
    deleted: AtomicBool,
    episodes_completed: AtomicU64,
    steps_shaped: AtomicU64,
    open_streams: AtomicU32,
    store: Arc<dyn Store>,
    /// Per client id: per env, the number of episodes whose end was committed (SPEC §9).
    ended: parking_lot::Mutex<EndedEpisodes>,
    /// The counters after the last [`TaskHandle::sync_counters`].
    synced: parking_lot::Mutex<Counters>,
    /// Announces every publish (the new version) and the deletion, for followers.
    changes: tokio::sync::watch::Sender<u64>,
    /// Set when the task's config is past this server's limits: why.
    read_only: Option<String>,
}

/// Decrements a task's open-stream count when dropped.
pub struct StreamGuard(Arc<TaskHandle>);

impl Drop for StreamGuard {
    fn drop(&mut self) {
        self.0.open_streams.fetch_sub(1, Ordering::Relaxed);
    }
}

/// The right to plan a change of a task's pool, with the pool to plan against.
pub struct Writer {
    _guard: OwnedMutexGuard<()>,
    task: Arc<TaskHandle>,
    /// The task's count of failed groups when the lock was taken.
    epoch: u64,
    base: std::sync::OnceLock<Arc<Pool>>,
}

impl Writer {
    /// The pool the change is planned against: the published pool plus every change
    /// queued or in flight (their commits come first). Made on first use: a writer that
    /// only queues operations, which the store decides, needs none.
    pub fn base(&self) -> &Arc<Pool> {
        self.base.get_or_init(|| self.task.planned_pool())
    }
}

impl TaskHandle {
    pub(super) fn new(
        key: String,
        config: TaskConfig,
        pool: Pool,
        counters: Counters,
        store: Arc<dyn Store>,
    ) -> Self {
        TaskHandle {
            key,
            config,
            published: AtomicU64::new(pool.version()),
            pool: RwLock::new(Arc::new(pool)),
            writer: Arc::new(Mutex::new(())),
            commits: parking_lot::Mutex::new(Commits::default()),
            idle: Notify::new(),
            deleted: AtomicBool::new(false),
            episodes_completed: AtomicU64::new(counters.episodes_completed),
            steps_shaped: AtomicU64::new(counters.steps_shaped),
            open_streams: AtomicU32::new(0),
            store,
            ended: parking_lot::Mutex::new(EndedEpisodes::default()),
            synced: parking_lot::Mutex::new(counters),
            changes: tokio::sync::watch::Sender::new(0),
            read_only: None,
        }
    }

    /// A task restored from the store or adopted from another server: if its config is
    /// past `limits`, it is served read-only (steps, reads and DeleteTask go on; every
    /// change of its pool is refused naming the limit), with a warning in the log.
    pub(super) fn limited_by(mut self, limits: &Limits) -> Self {
        if let Some(why) = super::over_limits(limits, &self.config) {
            tracing::warn!(
                task = %self.key,
                reason = %why,
                "a stored task is past this server's limits: served read-only (its pool is not changed) until the limit is raised or the task deleted"
            );
            self.read_only = Some(why);
        }
        self
    }

    /// Why the task is read-only on this server, if it is ([`TaskHandle::limited_by`]).
    pub fn read_only(&self) -> Option<&str> {
        self.read_only.as_deref()
    }

    /// The task id, as its tenant names it (what clients send and see).
    pub fn id(&self) -> &str {
        super::split_key(&self.key).1
    }

    /// The tenant that owns the task (SPEC §11).
    pub fn tenant(&self) -> &str {
        super::split_key(&self.key).0
    }

    /// The key of the task in the registry and the store: tenant and id in one string
    /// (see [`super::task_key`]).
    pub fn key(&self) -> &str {
        &self.key
    }

    /// The resolved configuration.
    pub fn config(&self) -> &TaskConfig {
        &self.config
    }

    fn counters(&self) -> Counters {
        Counters {
            episodes_completed: self.episodes_completed.load(Ordering::Relaxed),
            steps_shaped: self.steps_shaped.load(Ordering::Relaxed),
        }
    }

    /// `NOT_FOUND` once the task was deleted.
    pub fn check_live(&self) -> Result<(), Error> {
        if self.deleted.load(Ordering::Acquire) {
            Err(Error::not_found(self.id()))
        } else {
            Ok(())
        }
    }

    pub(super) fn mark_deleted(&self) {
        self.deleted.store(true, Ordering::Release);
        self.changes.send_modify(|_| {});
    }

    /// A receiver woken at every publish of a new pool and at the task's deletion (then
    /// [`TaskHandle::check_live`] fails): what a follower (SPEC §13) waits on.
    pub fn subscribe(&self) -> tokio::sync::watch::Receiver<u64> {
        self.changes.subscribe()
    }

    /// The published pool (a pointer copy).
    pub fn snapshot(&self) -> Arc<Pool> {
        self.pool.read().clone()
    }

    /// The version of the published pool (one atomic load).
    pub fn published_version(&self) -> u64 {
        self.published.load(Ordering::Acquire)
    }

    /// Live statistics.
    pub fn stats(&self) -> TaskStats {
        let pool = self.snapshot();
        let (worst, best) = pool.score_range().unwrap_or((0.0, 0.0));
        TaskStats {
            pool_size: pool.len(),
            pool_version: pool.version(),
            min_length: pool.l_min(),
            best_score: best,
            worst_score: worst,
            episodes_completed: self.episodes_completed.load(Ordering::Relaxed),
            steps_shaped: self.steps_shaped.load(Ordering::Relaxed),
            open_streams: self.open_streams.load(Ordering::Relaxed),
        }
    }

    /// A consistent copy of the pool (cheap: trajectories are shared).
    pub fn pool_snapshot(&self) -> Result<Arc<Pool>, Error> {
        self.check_live()?;
        Ok(self.snapshot())
    }

    /// Registers an open stream; the count drops when the guard does.
    pub fn open_stream(self: &Arc<Self>) -> Result<StreamGuard, Error> {
        self.check_live()?;
        self.open_streams.fetch_add(1, Ordering::Relaxed);
        Ok(StreamGuard(self.clone()))
    }

    /// Counts shaped entries.
    pub fn count_steps(&self, n: usize) {
        self.steps_shaped.fetch_add(n as u64, Ordering::Relaxed);
    }

    /// Counts an ended episode.
    pub fn count_episode(&self) {
        self.episodes_completed.fetch_add(1, Ordering::Relaxed);
    }

    /// Waits for the right to plan a change of the pool.
    pub async fn writer(self: &Arc<Self>) -> Result<Writer, Error> {
        let guard = self.writer.clone().lock_owned().await;
        self.check_live()?;
        let epoch = self.commits.lock().epoch;
        Ok(Writer {
            _guard: guard,
            task: self.clone(),
            epoch,
            base: std::sync::OnceLock::new(),
        })
    }

    /// The planned pool (called with the writer lock held, so nothing is queued
    /// meanwhile): the published pool when nothing is queued or in flight.
    fn planned_pool(&self) -> Arc<Pool> {
        let planned = self
            .commits
            .lock()
            .planned
            .as_mut()
            .map(Planned::materialise);
        planned.unwrap_or_else(|| self.snapshot())
    }

    /// The writer lock, once no group is in flight (and none can start while it is held):
    /// for what must not overlap a commit of the task (deletion, counters).
    async fn quiet(&self) -> OwnedMutexGuard<()> {
        let guard = self.writer.clone().lock_owned().await;
        loop {
            let idle = self.idle.notified();
            tokio::pin!(idle);
            idle.as_mut().enable();
            if !self.commits.lock().leading {
                return guard;
            }
            idle.await;
        }
    }

    fn publish(&self, pool: Arc<Pool>) {
        self.publish_if(pool, |new, published| new >= published);
    }

    /// Publishes `pool` if `take(its version, the published version)`.
    fn publish_if(&self, pool: Arc<Pool>, take: impl FnOnce(u64, u64) -> bool) {
        let version = pool.version();
        let mut slot = self.pool.write();
        // A refresh from a shared store may race a commit's publish: never go back
        // (unless the store itself did: [`TaskHandle::follow_store_back`]).
        if take(version, slot.version()) {
            *slot = pool;
            self.published.store(version, Ordering::Release);
            drop(slot);
            self.changes.send_replace(version);
        }
    }

    /// Publishes the pool of a shared store that is *behind* the published one: the
    /// store lost changes it had acknowledged (a Redis restarted without its last
    /// writes, under `appendfsync everysec` or `no`). The store is the one place the
    /// pool is decided, so this server follows it rather than serve a pool no other
    /// server has, and says so in the log.
    fn went_back(&self, pool: Arc<Pool>) {
        let (theirs, ours) = (pool.version(), self.published_version());
        tracing::warn!(
            task = %self.key,
            store_version = theirs,
            published_version = ours,
            "the store's pool is behind the one this server published: the store lost changes it had acknowledged; following the store"
        );
        self.publish_if(pool, |new, published| new < published);
    }

    /// On a shared store, as a stream opens: publishes the store's pool if it is newer
    /// than the published one. A learner that moves here from another server (its stream
    /// broke) must go on from every change that server acknowledged, which this server
    /// may not have been told of yet (the store's notices take up to `store_poll_ms`). A
    /// store out of reach leaves this server's pool (with a warning), as for every step.
    pub async fn catch_up_with_store(&self) {
        match self.store.load_pool(&self.key).await {
            Ok(Some(pool)) => self.refresh(pool),
            Ok(None) => {}
            Err(e) => {
                tracing::warn!(task = %self.key, error = %e, "could not read the task's pool from the store; going on with this server's")
            }
        }
    }

    /// On a shared store that announced a version below the published one: follows the
    /// store's pool if it is behind once no commit of this server is in flight. A notice
    /// older than this server's own commit is usually late news only (the store is never
    /// behind what was published unless it lost changes), so the store is read first
    /// without holding up commits, and again under the writer lock only if it looks
    /// behind.
    pub async fn follow_store_back(&self) -> Result<(), StoreError> {
        match self.store.load_pool(&self.key).await? {
            Some(pool) if pool.version() < self.published_version() => {}
            _ => return Ok(()),
        }
        let _writer = self.quiet().await;
        if let Some(pool) = self.store.load_pool(&self.key).await? {
            if pool.version() < self.published_version() {
                self.went_back(Arc::new(pool));
            }
        }
        Ok(())
    }

    /// Whether episode `number` of `env` of `client` was already committed, or is being
    /// committed (queued or in flight: then it is not to be offered again either).
    pub fn already_ended(&self, client: &str, env: u32, number: u64) -> bool {
        // The committed record first: a group moves its ends there before it forgets them
        // as pending.
        self.ended.lock().contains(client, env, number)
            || self.commits.lock().pending.contains(client, env, number)
    }

    /// Per env, how many episode ends of `client` were committed (the number of its next
    /// episode), as far as this server knows; see [`TaskHandle::learn_ended`].
    pub fn ended_counts(&self, client: &str) -> Vec<(u32, u64)> {
        self.ended.lock().counts(client)
    }

    /// Learns from the store which episode ends of `client` it committed: a store shared
    /// with other servers (a stream that broke on another server is resumed here), or a
    /// data dir this server (or an earlier run of it) wrote (SPEC §9).
    pub async fn learn_ended(&self, client: &str) -> Result<(), Error> {
        let ends = self.store.ended_episodes(&self.key, client).await;
        let ends = self.gone_is_not_found(ends)?;
        if !ends.is_empty() {
            // Stored as counts: episode `n - 1` is the last one ended.
            self.ended.lock().merge(client, ends);
        }
        Ok(())
    }

    /// A task the store no longer has is deleted here too (another server deleted it);
    /// the error itself becomes `NOT_FOUND` in `From<StoreError> for Error`.
    fn gone_is_not_found<T>(&self, r: Result<T, StoreError>) -> Result<T, Error> {
        r.map_err(|e| self.store_error(e))
    }

    fn store_error(&self, e: StoreError) -> Error {
        if matches!(e, StoreError::Gone { .. }) {
            self.mark_deleted();
        }
        e.into()
    }

    /// [`TaskHandle::commit`] for the episode ends of a batch: with `marks = (client,
    /// [(env, episode)])` they count as being committed from now on
    /// ([`TaskHandle::already_ended`]) and are remembered as committed once the store
    /// acknowledged them; offers the store found re-sent (`resent`) are taken back from
    /// `episodes_completed`.
    pub async fn commit_ends(
        self: &Arc<Self>,
        writer: Writer,
        ops: Vec<PoolOp>,
        marks: Option<(&str, &[(u32, u64)])>,
    ) -> Result<Committed, Error> {
        self.submit(writer, ops, marks).await
    }

    /// Commits `ops` (planned against `writer.base()`) to the store, together with the
    /// changes planned before and after them that wait for the store at the same time, and
    /// publishes the pool the store returns. The writer lock is released once they are
    /// queued. The answer is this commit's own: `changed` per op, the version right after
    /// its own changes, the pool after its group. Nothing is published if the store fails,
    /// and then every change planned on top of this one fails too.
    pub async fn commit(
        self: &Arc<Self>,
        writer: Writer,
        ops: Vec<PoolOp>,
    ) -> Result<Committed, Error> {
        self.submit(writer, ops, None).await
    }

    async fn submit(
        self: &Arc<Self>,
        writer: Writer,
        ops: Vec<PoolOp>,
        marks: Option<(&str, &[(u32, u64)])>,
    ) -> Result<Committed, Error> {
        if let (Some(why), false) = (&self.read_only, ops.is_empty()) {
            return Err(Error::ResourceExhausted(format!(
                "task {:?} is read-only on this server, its pool cannot change: {why} \
                 (the task was stored before the limit was lowered; raise the limit or delete the task)",
                self.id()
            )));
        }
        let (answer, answered) = oneshot::channel();
        let lead = {
            let mut c = self.commits.lock();
            if c.epoch != writer.epoch {
                // Planned against changes of a group that failed since.
                let failure = c.failure.clone().unwrap_or_else(|| {
                    StoreError::new(&self.key, "a commit planned before this one failed")
                });
                drop(c);
                return Err(self.store_error(failure));
            }
            if c.planned.is_none() && ops.is_empty() {
                // Nothing to commit, and nothing queued or in flight under the base.
                drop(c);
                return Ok(Committed::new(writer.base().clone(), Vec::new()));
            }
            c.last += 1;
            let number = c.last;
            let planned = ops.clone();
            match c.planned.as_mut() {
                Some(p) => p.tail.push((number, planned)),
                None => {
                    // Nothing queued or in flight: the published pool holds every earlier
                    // change (and is the base the writer saw, if it looked).
                    c.planned = Some(Planned {
                        base: self.snapshot(),
                        through: number - 1,
                        tail: vec![(number, planned)],
                    })
                }
            }
            let marks = marks
                .filter(|(_, ends)| !ends.is_empty())
                .map(|(client, ends)| (Arc::<str>::from(client), ends.to_vec()));
            if let Some((client, ends)) = &marks {
                c.pending.add(number, client, ends);
            }
            let request = Request {
                number,
                ops,
                marks,
                answer,
            };
            if c.leading {
                c.queue.push(request);
                None
            } else {
                c.leading = true;
                Some(vec![request])
            }
        };
        // Planned and queued: the next writer plans on top of it.
        drop(writer);
        if let Some(group) = lead {
            Detached::new(self.clone().lead(group, true)).await;
        }
        answered.await.unwrap_or_else(|_| {
            Err(Error::Storage(StoreError::new(
                &self.key,
                "the commit was abandoned before the store answered (the server is stopping)",
            )))
        })
    }

    /// Commits `group`, then what queued meanwhile, group after group, until the queue is
    /// empty. With `hand_off` (the leader is a writer waiting for its own answer, which
    /// the first group holds), the groups after the first go to a task of their own.
    async fn lead(self: Arc<Self>, mut group: Vec<Request>, hand_off: bool) {
        let mut leader = Leader {
            task: &self,
            done: false,
        };
        loop {
            if !self.commit_group(group).await {
                break;
            }
            let next = {
                let mut c = self.commits.lock();
                if c.queue.is_empty() {
                    // The published pool is the planned one now.
                    c.planned = None;
                    c.leading = false;
                    None
                } else {
                    Some(std::mem::take(&mut c.queue))
                }
            };
            let Some(next) = next else {
                self.idle.notify_waiters();
                break;
            };
            if hand_off {
                if let Ok(runtime) = tokio::runtime::Handle::try_current() {
                    runtime.spawn(self.clone().drain(next));
                    break;
                }
            }
            group = next;
        }
        leader.done = true;
    }

    /// [`TaskHandle::lead`] without hand-off, for a task of its own.
    fn drain(
        self: Arc<Self>,
        group: Vec<Request>,
    ) -> std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>> {
        Box::pin(self.lead(group, false))
    }

    /// Commits one group as one store commit against the last committed pool, publishes
    /// the result and answers every request in it. Returns `false` if the store failed
    /// (then every request in it and every request queued fails).
    async fn commit_group(&self, mut group: Vec<Request>) -> bool {
        let base = self.snapshot();
        let base_version = base.version();
        let parts: Vec<Vec<PoolOp>> = group
            .iter_mut()
            .map(|r| std::mem::take(&mut r.ops))
            .collect();
        let lens: Vec<usize> = parts.iter().map(Vec::len).collect();
        let done = if lens.iter().all(|&n| n == 0) {
            // Only writers that planned nothing, waiting for the changes under their base.
            Ok(GroupCommitted {
                committed: Committed::new(base, Vec::new()),
                resent: Some(vec![0; lens.len()]),
            })
        } else {
            self.store
                .commit_group(&self.key, base, parts, self.counters())
                .await
        };
        let done = match done {
            Ok(done) => done,
            Err(e) => {
                let queued = self.commits.lock().fail(e.clone());
                self.idle.notify_waiters();
                for r in group.into_iter().chain(queued) {
                    let _ = r.answer.send(Err(self.store_error(e.clone())));
                }
                return false;
            }
        };
        if done.committed.pool.version() < base_version {
            self.went_back(done.committed.pool.clone());
        } else {
            self.publish(done.committed.pool.clone());
        }
        if let Some(last) = group.last() {
            if let Some(p) = self.commits.lock().planned.as_mut() {
                // What is still planned is now on top of the committed pool.
                p.committed(last.number, &done.committed.pool);
            }
        }
        if done.committed.resent > 0 {
            // Ends another server committed meanwhile (SPEC §9): counted by the writers as
            // they planned them, but they are no episodes completed here.
            self.episodes_completed
                .fetch_sub(done.committed.resent as u64, Ordering::Relaxed);
        }
        let marked: Vec<bool> = group.iter().map(|r| r.marks.is_some()).collect();
        let answers = group::split(&done, &lens, &marked);
        {
            let mut ended = self.ended.lock();
            for (client, ends) in group.iter().filter_map(|r| r.marks.as_ref()) {
                let counts = ends
                    .iter()
                    .map(|&(env, number)| (env, number.saturating_add(1)));
                ended.merge(client, counts);
            }
        }
        if let Some(last) = group.last() {
            self.commits.lock().pending.release(last.number);
        }
        for (r, a) in group.into_iter().zip(answers) {
            // The writer may have gone (a cancelled call); the commit stands regardless.
            let _ = r.answer.send(Ok(a));
        }
        true
    }

    /// Publishes a newer pool learnt from the store (a change made by another server).
    pub fn refresh(&self, pool: Pool) {
        self.publish(Arc::new(pool));
    }

    /// Offers a trajectory (SPEC §6). Returns whether it was stored, and the version after.
    pub async fn offer(
        self: &Arc<Self>,
        actions: ActionSeq,
        score: f64,
    ) -> Result<(bool, u64), Error> {
        let writer = self.writer().await?;
        let c = self
            .commit(
                writer,
                vec![PoolOp::Offer {
                    actions,
                    score,
                    end: None,
                }],
            )
            .await?;
        Ok((c.changed.first().copied().unwrap_or(false), c.version))
    }

    /// Empties the pool (bumping its version). Returns the version after.
    pub async fn reset_pool(self: &Arc<Self>) -> Result<u64, Error> {
        let writer = self.writer().await?;
        Ok(self.commit(writer, vec![PoolOp::Reset]).await?.version)
    }

    /// Persists the counters (at shutdown).
    pub async fn flush_counters(&self) -> Result<(), StoreError> {
        let _writer = self.quiet().await;
        if self.deleted.load(Ordering::Acquire) {
            return Ok(());
        }
        self.store
            .save_counters(&self.key, self.snapshot(), self.counters())
            .await
    }

    /// [`TaskHandle::sync_counters`] before an answer about the task: fails only when the
    /// store no longer has it (`TaskNotFound`: another server deleted it, and it is marked
    /// deleted here); a store that cannot be reached leaves this server's counters.
    pub async fn check_with_store(&self) -> Result<(), Error> {
        match self.sync_counters().await {
            Err(e @ Error::TaskNotFound { .. }) => Err(e),
            Err(e) => {
                tracing::warn!(task = %self.key(), error = %e, "could not sync the task's counters; answering this server's");
                Ok(())
            }
            Ok(()) => Ok(()),
        }
    }

    /// On a store shared with other servers: writes this server's counter increments and
    /// takes in the other servers' (as of their last write), so that every replica
    /// reports the task's totals (SPEC §10). Nothing for other stores.
    pub async fn sync_counters(&self) -> Result<(), Error> {
        if !self.store.is_shared() {
            return Ok(());
        }
        let _writer = self.quiet().await;
        if self.deleted.load(Ordering::Acquire) {
            return Ok(());
        }
        let local = self.counters();
        let totals = self.store.sync_counters(&self.key, local).await;
        if let Some(totals) = self.gone_is_not_found(totals)? {
            // Added, not stored: streams count steps without the writer lock.
            let others = |t: u64, l: u64| t.saturating_sub(l);
            self.episodes_completed.fetch_add(
                others(totals.episodes_completed, local.episodes_completed),
                Ordering::Relaxed,
            );
            self.steps_shaped.fetch_add(
                others(totals.steps_shaped, local.steps_shaped),
                Ordering::Relaxed,
            );
        }
        *self.synced.lock() = self.counters();
        Ok(())
    }

    /// Whether this server counted steps or episodes since the last
    /// [`TaskHandle::sync_counters`].
    pub fn counters_changed(&self) -> bool {
        *self.synced.lock() != self.counters()
    }

    /// The writer lock once no commit is in flight, for deleting the task.
    pub(super) async fn lock_for_delete(&self) -> OwnedMutexGuard<()> {
        self.quiet().await
    }

    /// Requests queued behind the group in flight (for tests that make groups).
    #[cfg(test)]
    pub(super) fn queued(&self) -> usize {
        self.commits.lock().queue.len()
    }

    /// The planned pool's parts: the last request its base holds, the requests of its
    /// tail (for tests).
    #[cfg(test)]
    pub(super) fn planned_parts(&self) -> Option<(u64, Vec<u64>)> {
        let c = self.commits.lock();
        let p = c.planned.as_ref()?;
        Some((p.through, p.tail.iter().map(|t| t.0).collect()))
    }
}

/// Marks a leader that stopped before its queue was empty (its task was dropped, at
/// shutdown): what was queued behind it fails, as after a failed group, so that nothing
/// waits for a leader that is gone.
struct Leader<'a> {
    task: &'a TaskHandle,
    done: bool,
}

impl Drop for Leader<'_> {
    fn drop(&mut self) {
        if self.done {
            return;
        }
        let e = StoreError::new(
            &self.task.key,
            "a commit was interrupted (the server is stopping)",
        );
        let queued = self.task.commits.lock().fail(e.clone());
        self.task.idle.notify_waiters();
        for r in queued {
            let _ = r.answer.send(Err(e.clone().into()));
        }
    }
}
