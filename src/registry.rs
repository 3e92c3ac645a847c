//! Tasks, their pools, and the step path.
//!
//! Locking: the task map is a `DashMap` (sharded; lookups never wait on other tasks).
//! Each task publishes its pool as an `Arc<Pool>` behind a `RwLock` that is only ever held
//! for a pointer copy or swap: a stream takes a snapshot at the start of a batch and
//! shapes without any lock. Pool changes of one task are serialised by the task's
//! `persist` mutex: the writer builds the next pool privately, persists it (fsync), then
//! swaps it in. Readers keep shaping against the previous pool during the fsync, and see
//! the change from their next step after the swap. Streams on different tasks share no
//! lock at all. Create/delete are serialised by one admin mutex, which the step path never
//! touches.

use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;

use dashmap::DashMap;
use parking_lot::{Mutex, RwLock};

use crate::core::{
    ActionSeq, Episode, KnnScratch, Pool, StepInput, StepOutput, TaskConfig, TaskConfigInput,
};
use crate::error::Error;
use crate::store::{Counters, Store, StoreError};

/// Server limits. Requests past them are answered `RESOURCE_EXHAUSTED`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// Tasks the server holds at most.
    pub max_tasks: usize,
    /// `num_envs` of one Shape stream at most.
    pub max_envs_per_stream: u32,
    /// Entries of one StepBatch at most.
    pub max_batch_entries: usize,
    /// Size of one gRPC message at most, in bytes (either direction).
    pub max_message_bytes: usize,
    /// `pool_capacity` of a task at most.
    pub max_pool_capacity: u32,
}

impl Default for Limits {
    fn default() -> Limits {
        Limits {
            max_tasks: 10_000,
            max_envs_per_stream: 4_096,
            max_batch_entries: 65_536,
            max_message_bytes: 64 * 1024 * 1024,
            max_pool_capacity: 10_000,
        }
    }
}

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

/// One task: immutable config, its pool and counters.
pub struct TaskHandle {
    id: String,
    config: TaskConfig,
    /// The published pool; the lock is held only to copy or swap the `Arc`.
    pool: RwLock<Arc<Pool>>,
    /// Serialises pool changes (and deletion) of this task.
    persist: Mutex<()>,
    /// Version of the published pool, so the step path can notice a change with one load.
    published: AtomicU64,
    deleted: AtomicBool,
    episodes_completed: AtomicU64,
    steps_shaped: AtomicU64,
    open_streams: AtomicU32,
    store: Arc<dyn Store>,
}

/// Decrements a task's open-stream count when dropped.
pub struct StreamGuard(Arc<TaskHandle>);

impl Drop for StreamGuard {
    fn drop(&mut self) {
        self.0.open_streams.fetch_sub(1, Ordering::Relaxed);
    }
}

impl TaskHandle {
    fn new(
        id: String,
        config: TaskConfig,
        pool: Pool,
        counters: Counters,
        store: Arc<dyn Store>,
    ) -> Self {
        TaskHandle {
            id,
            config,
            published: AtomicU64::new(pool.version()),
            pool: RwLock::new(Arc::new(pool)),
            persist: Mutex::new(()),
            deleted: AtomicBool::new(false),
            episodes_completed: AtomicU64::new(counters.episodes_completed),
            steps_shaped: AtomicU64::new(counters.steps_shaped),
            open_streams: AtomicU32::new(0),
            store,
        }
    }

    /// The task id.
    pub fn id(&self) -> &str {
        &self.id
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

    fn check_live(&self) -> Result<(), Error> {
        if self.deleted.load(Ordering::Acquire) {
            Err(Error::TaskNotFound(self.id.clone()))
        } else {
            Ok(())
        }
    }

    fn current(&self) -> Arc<Pool> {
        self.pool.read().clone()
    }

    /// Live statistics.
    pub fn stats(&self) -> TaskStats {
        let pool = self.current();
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
        Ok(self.current())
    }

    /// Registers an open stream; the count drops when the guard does.
    pub fn open_stream(self: &Arc<Self>) -> Result<StreamGuard, Error> {
        self.check_live()?;
        self.open_streams.fetch_add(1, Ordering::Relaxed);
        Ok(StreamGuard(self.clone()))
    }

    /// Persists `next` (built from `base` while holding `persist`) and publishes it.
    fn publish(&self, base: &Pool, next: Arc<Pool>) -> Result<(), Error> {
        self.store.commit(&self.id, base, &next, self.counters())?;
        let version = next.version();
        *self.pool.write() = next;
        self.published.store(version, Ordering::Release);
        Ok(())
    }

    /// Applies one planned change: plan against the latest pool, persist, publish.
    fn change(
        &self,
        plan: impl FnOnce(&Pool) -> Option<crate::core::PoolChange>,
    ) -> Result<(bool, u64), Error> {
        let _persist = self.persist.lock();
        self.check_live()?;
        let base = self.current();
        let Some(change) = plan(&base) else {
            return Ok((false, base.version()));
        };
        let mut next = Pool::clone(&base);
        next.apply(&change);
        let version = next.version();
        self.publish(&base, Arc::new(next))?;
        Ok((true, version))
    }

    /// Offers a trajectory (SPEC §6). Returns whether it was stored, and the version after.
    pub fn offer(&self, actions: ActionSeq, score: f64) -> Result<(bool, u64), Error> {
        self.change(|pool| pool.plan_offer(actions, score))
    }

    /// Empties the pool (bumping its version).
    pub fn reset_pool(&self) -> Result<u64, Error> {
        self.change(|pool| Some(pool.plan_reset())).map(|(_, v)| v)
    }

    /// Shapes a validated batch: `entries[i] = (env, step)`, processed in order against
    /// the pool as it is at each entry (a change another stream publishes mid-batch is
    /// seen from the next entry on). Appends one output per entry and returns the pool
    /// version after the batch.
    ///
    /// The first episode end of the batch takes the task's `persist` lock; from then on
    /// the batch works on a private copy of the latest pool, offering each finished
    /// episode to it right after its step is shaped (so later entries of the batch see
    /// it), and at the end of the batch persists all of its changes in one commit and
    /// publishes them. Other streams shape against the previous pool until then.
    pub fn shape_batch(
        &self,
        episodes: &mut [Episode],
        entries: &[(usize, StepInput<'_>)],
        scratch: &mut KnnScratch,
        out: &mut Vec<StepOutput>,
    ) -> Result<u64, Error> {
        self.check_live()?;
        let mut pool = self.current();
        let mut writer: Option<(parking_lot::MutexGuard<'_, ()>, Arc<Pool>)> = None;
        for (env, input) in entries {
            if writer.is_none() && self.published.load(Ordering::Acquire) != pool.version() {
                // Another stream committed a change: this step sees it.
                pool = self.current();
            }
            let (output, end) = episodes[*env].step(&self.config, &pool, input, scratch);
            out.push(output);
            if let Some(end) = end {
                self.episodes_completed.fetch_add(1, Ordering::Relaxed);
                if writer.is_none() {
                    let guard = self.persist.lock();
                    self.check_live()?;
                    pool = self.current();
                    writer = Some((guard, pool.clone()));
                }
                if let Some(change) = pool.plan_offer(end.actions, end.score) {
                    Arc::make_mut(&mut pool).apply(&change);
                }
            }
        }
        self.steps_shaped
            .fetch_add(entries.len() as u64, Ordering::Relaxed);
        if let Some((_guard, base)) = writer {
            if pool.version() != base.version() {
                self.publish(&base, pool.clone())?;
            }
        }
        Ok(pool.version())
    }

    /// Persists the counters (at shutdown).
    pub fn flush_counters(&self) -> Result<(), StoreError> {
        let _persist = self.persist.lock();
        let pool = self.current();
        if self.deleted.load(Ordering::Acquire) {
            return Ok(());
        }
        self.store.save_counters(&self.id, &pool, self.counters())
    }
}

/// Every task of the server.
pub struct Registry {
    tasks: DashMap<String, Arc<TaskHandle>>,
    admin: Mutex<()>,
    store: Arc<dyn Store>,
    limits: Limits,
}

/// What [`Registry::open`] restored.
#[derive(Debug, Clone, Copy, Default)]
pub struct Restored {
    /// Tasks restored.
    pub tasks: usize,
    /// Trajectories restored over all pools.
    pub trajectories: usize,
}

impl Registry {
    /// Loads every task of `store`.
    pub fn open(store: Arc<dyn Store>, limits: Limits) -> Result<(Registry, Restored), StoreError> {
        let tasks = DashMap::new();
        let mut restored = Restored::default();
        for t in store.load()? {
            restored.tasks += 1;
            restored.trajectories += t.pool.len();
            let handle = TaskHandle::new(t.id.clone(), t.config, t.pool, t.counters, store.clone());
            tasks.insert(t.id, Arc::new(handle));
        }
        Ok((
            Registry {
                tasks,
                admin: Mutex::new(()),
                store,
                limits,
            },
            restored,
        ))
    }

    /// The server limits.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Whether the store does blocking disk I/O.
    pub fn is_durable(&self) -> bool {
        self.store.is_durable()
    }

    /// Creates a task, or returns the existing one if its resolved config is the same.
    pub fn create(&self, id: &str, input: &TaskConfigInput) -> Result<Arc<TaskHandle>, Error> {
        let config = TaskConfig::resolve(input)
            .map_err(|e| Error::invalid(format!("config.{}", e.field), e.message))?;
        let _admin = self.admin.lock();
        if let Some(existing) = self.tasks.get(id) {
            return if existing.config.same_as(&config) {
                Ok(existing.clone())
            } else {
                Err(Error::AlreadyExists {
                    id: id.to_string(),
                    detail: config_diff(&existing.config, &config),
                })
            };
        }
        if config.pool_capacity > self.limits.max_pool_capacity {
            return Err(Error::ResourceExhausted(format!(
                "config.pool_capacity: {} exceeds this server's limit max_pool_capacity = {}",
                config.pool_capacity, self.limits.max_pool_capacity
            )));
        }
        if self.tasks.len() >= self.limits.max_tasks {
            return Err(Error::ResourceExhausted(format!(
                "task limit reached: this server holds at most max_tasks = {} tasks",
                self.limits.max_tasks
            )));
        }
        self.store.create_task(id, &config)?;
        let handle = Arc::new(TaskHandle::new(
            id.to_string(),
            config,
            Pool::new(config.pool_capacity as usize),
            Counters::default(),
            self.store.clone(),
        ));
        self.tasks.insert(id.to_string(), handle.clone());
        Ok(handle)
    }

    /// Looks a task up.
    pub fn get(&self, id: &str) -> Result<Arc<TaskHandle>, Error> {
        self.tasks
            .get(id)
            .map(|t| t.clone())
            .ok_or_else(|| Error::TaskNotFound(id.to_string()))
    }

    /// Every task, ordered by id.
    pub fn list(&self) -> Vec<Arc<TaskHandle>> {
        let mut v: Vec<_> = self.tasks.iter().map(|e| e.value().clone()).collect();
        v.sort_by(|a, b| a.id.cmp(&b.id));
        v
    }

    /// Deletes a task; its open streams fail with NOT_FOUND at their next batch.
    pub fn delete(&self, id: &str) -> Result<(), Error> {
        let _admin = self.admin.lock();
        let handle = self.get(id)?;
        let _persist = handle.persist.lock();
        self.store.delete_task(id)?;
        handle.deleted.store(true, Ordering::Release);
        self.tasks.remove(id);
        Ok(())
    }

    /// Persists every task's counters (at graceful shutdown).
    pub fn flush_counters(&self) {
        for task in self.list() {
            if let Err(e) = task.flush_counters() {
                tracing::warn!(task = task.id(), error = %e, "could not persist counters");
            }
        }
    }
}

fn config_diff(a: &TaskConfig, b: &TaskConfig) -> String {
    let (a, b) = (a.to_input(), b.to_input());
    let mut diffs = Vec::new();
    macro_rules! cmp {
        ($($f:ident),*) => {$(
            if format!("{:?}", a.$f) != format!("{:?}", b.$f) {
                diffs.push(format!("{}: existing {:?}, requested {:?}", stringify!($f), a.$f, b.$f));
            }
        )*};
    }
    cmp!(
        num_actions,
        action_dim,
        pool_capacity,
        k,
        start_step,
        min_pool_size,
        alpha,
        beta,
        gamma,
        max_trajectory_len
    );
    diffs.join("; ")
}
