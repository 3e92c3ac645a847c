//! One task: its immutable config, its published pool, its counters, and the serialised
//! path by which its pool changes.
//!
//! The pool is published as an `Arc<Pool>` behind a `RwLock` that is only ever held for
//! a pointer copy or swap: the step path takes a snapshot and shapes without any lock,
//! and notices a newer pool with one atomic load. Pool changes of one task are
//! serialised by its writer lock: the writer plans against the latest pool, the store
//! commits (fsync, or the shared store's atomic update), then the result is published.
//! Readers keep shaping against the previous pool meanwhile.

use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;

use parking_lot::RwLock;
use tokio::sync::{Mutex, OwnedMutexGuard};

use crate::core::{ActionSeq, Pool, TaskConfig};
use crate::error::Error;
use crate::store::{Committed, Counters, EndedEpisodes, PoolOp, Store, StoreError};

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
    /// Serialises pool changes (and deletion) of this task.
    writer: Arc<Mutex<()>>,
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
}

/// Decrements a task's open-stream count when dropped.
pub struct StreamGuard(Arc<TaskHandle>);

impl Drop for StreamGuard {
    fn drop(&mut self) {
        self.0.open_streams.fetch_sub(1, Ordering::Relaxed);
    }
}

/// The right to change a task's pool, with the pool to plan against (the latest).
pub struct Writer {
    _guard: OwnedMutexGuard<()>,
    base: Arc<Pool>,
}

impl Writer {
    /// The pool the change is planned against: the latest published one.
    pub fn base(&self) -> &Arc<Pool> {
        &self.base
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
            deleted: AtomicBool::new(false),
            episodes_completed: AtomicU64::new(counters.episodes_completed),
            steps_shaped: AtomicU64::new(counters.steps_shaped),
            open_streams: AtomicU32::new(0),
            store,
            ended: parking_lot::Mutex::new(EndedEpisodes::default()),
            synced: parking_lot::Mutex::new(counters),
            changes: tokio::sync::watch::Sender::new(0),
        }
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

    /// Waits for the right to change the pool.
    pub async fn writer(&self) -> Result<Writer, Error> {
        let guard = self.writer.clone().lock_owned().await;
        self.check_live()?;
        Ok(Writer {
            _guard: guard,
            base: self.snapshot(),
        })
    }

    fn publish(&self, pool: Arc<Pool>) {
        let version = pool.version();
        let mut slot = self.pool.write();
        // A refresh from a shared store may race a commit's publish: never go back.
        if version >= slot.version() {
            *slot = pool;
            self.published.store(version, Ordering::Release);
            drop(slot);
            self.changes.send_replace(version);
        }
    }

    /// Whether episode `number` of `env` of `client` was already committed.
    pub fn already_ended(&self, client: &str, env: u32, number: u64) -> bool {
        self.ended.lock().contains(client, env, number)
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
        r.map_err(|e| {
            if matches!(e, StoreError::Gone { .. }) {
                self.mark_deleted();
            }
            e.into()
        })
    }

    /// [`TaskHandle::commit`] for the episode ends of a batch: with `marks = (client,
    /// [(env, episode)])` they are remembered as committed (while the writer lock is
    /// still held) once the store acknowledged them.
    pub async fn commit_ends(
        &self,
        writer: Writer,
        ops: Vec<PoolOp>,
        marks: Option<(&str, &[(u32, u64)])>,
    ) -> Result<Committed, Error> {
        let committed = self.commit_locked(&writer, ops).await?;
        if committed.resent > 0 {
            // Ends another server committed meanwhile (SPEC §9): counted by the stream as
            // it planned them, but they are no episodes completed here.
            self.episodes_completed
                .fetch_sub(committed.resent as u64, Ordering::Relaxed);
        }
        if let Some((client, ends)) = marks {
            let counts = ends
                .iter()
                .map(|&(env, number)| (env, number.saturating_add(1)));
            self.ended.lock().merge(client, counts);
        }
        drop(writer);
        Ok(committed)
    }

    /// Commits `ops` (planned against `writer.base()`) to the store, then publishes the
    /// pool the store returns. Nothing is published if the store fails.
    pub async fn commit(&self, writer: Writer, ops: Vec<PoolOp>) -> Result<Committed, Error> {
        self.commit_locked(&writer, ops).await
    }

    async fn commit_locked(&self, writer: &Writer, ops: Vec<PoolOp>) -> Result<Committed, Error> {
        if ops.is_empty() {
            return Ok(Committed::new(writer.base.clone(), Vec::new()));
        }
        let committed = self
            .store
            .commit(&self.key, writer.base.clone(), ops, self.counters())
            .await;
        let committed = self.gone_is_not_found(committed)?;
        self.publish(committed.pool.clone());
        Ok(committed)
    }

    /// Publishes a newer pool learnt from the store (a change made by another server).
    pub fn refresh(&self, pool: Pool) {
        self.publish(Arc::new(pool));
    }

    /// Offers a trajectory (SPEC §6). Returns whether it was stored, and the version after.
    pub async fn offer(&self, actions: ActionSeq, score: f64) -> Result<(bool, u64), Error> {
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
    pub async fn reset_pool(&self) -> Result<u64, Error> {
        let writer = self.writer().await?;
        Ok(self.commit(writer, vec![PoolOp::Reset]).await?.version)
    }

    /// Persists the counters (at shutdown).
    pub async fn flush_counters(&self) -> Result<(), StoreError> {
        let _writer = self.writer.clone().lock_owned().await;
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
        let _writer = self.writer.clone().lock_owned().await;
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

    pub(super) async fn lock_for_delete(&self) -> OwnedMutexGuard<()> {
        self.writer.clone().lock_owned().await
    }
}
