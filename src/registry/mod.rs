//! Every task of a server: creation (idempotent), lookup, listing, deletion, limits, and
//! the refresh of pool snapshots from a store shared with other servers.
//!
//! Tasks are per tenant (SPEC §11): every call names the tenant, and nothing here lets
//! one tenant's call see another's tasks (lookups, listings and the "did you mean" hint
//! of a miss stay within the tenant). Without credentials every caller is
//! [`DEFAULT_TENANT`].
//!
//! Locking: the task map is a `DashMap` (sharded; lookups never wait on other tasks).
//! Create and delete are serialised by one admin lock, which the step path never touches.
//! Per-task locking is described in [`task`].

mod group;
mod over;
mod task;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use dashmap::DashMap;
use tokio::sync::Mutex;

pub use task::{StreamGuard, TaskHandle, TaskStats, Writer};

use crate::core::{Pool, TaskConfig, TaskConfigInput};
use crate::error::Error;
use crate::limits::Limits;
use crate::store::{Counters, Store, StoreError};

// The task-key format is the leaf module `task_key`'s (the error type uses it too); the
// registry's tasks are keyed by it.
pub use crate::task_key::{split_key, task_key, DEFAULT_TENANT};

/// Every task of the server.
pub struct Registry {
    tasks: DashMap<String, Arc<TaskHandle>>,
    admin: Mutex<()>,
    store: Arc<dyn Store>,
    limits: Limits,
    /// Bytes reserved by the open Shape streams (bounded by `max_total_stream_bytes`).
    stream_bytes: Arc<AtomicU64>,
}

/// Memory reserved for one open stream out of the server's budget; released when dropped.
#[derive(Debug)]
pub struct StreamBytes {
    reserved: Arc<AtomicU64>,
    bytes: u64,
}

impl Drop for StreamBytes {
    fn drop(&mut self) {
        self.reserved.fetch_sub(self.bytes, Ordering::Relaxed);
    }
}

/// What [`Registry::open`] restored.
#[derive(Debug, Clone, Copy, Default)]
pub struct Restored {
    /// Tasks restored.
    pub tasks: usize,
    /// Trajectories restored over all pools.
    pub trajectories: usize,
    /// Restored tasks whose config is past this server's limits, served read-only.
    pub read_only: usize,
}

pub use over::over_limits;

impl Registry {
    /// Loads every task of `store`.
    pub async fn open(
        store: Arc<dyn Store>,
        limits: Limits,
    ) -> Result<(Registry, Restored), StoreError> {
        let tasks = DashMap::new();
        let mut restored = Restored::default();
        for t in store.load().await? {
            restored.tasks += 1;
            restored.trajectories += t.pool.len();
            let handle = TaskHandle::new(t.id.clone(), t.config, t.pool, t.counters, store.clone())
                .limited_by(&limits);
            restored.read_only += usize::from(handle.read_only().is_some());
            tasks.insert(t.id, Arc::new(handle));
        }
        if tasks.len() > limits.max_tasks {
            tracing::warn!(
                tasks = tasks.len(),
                max_tasks = limits.max_tasks,
                "the store holds more tasks than max_tasks: all are served, and CreateTask is refused until some are deleted"
            );
        }
        Ok((
            Registry {
                tasks,
                admin: Mutex::new(()),
                store,
                limits,
                stream_bytes: Arc::default(),
            },
            restored,
        ))
    }

    /// The server limits.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Reserves `bytes` (a stream's reckoning, `max_stream_bytes`) out of the server's
    /// budget for open streams, `max_total_stream_bytes`, until the value is dropped.
    pub fn reserve_stream_bytes(&self, bytes: u64) -> Result<StreamBytes, Error> {
        let max = self.limits.max_total_stream_bytes;
        self.stream_bytes
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |held| {
                held.checked_add(bytes).filter(|&total| total <= max)
            })
            .map_err(|held| {
                Error::ResourceExhausted(format!(
                    "open: this stream reckons {bytes} bytes and the open streams hold \
                     {held}: past this server's limit max_total_stream_bytes = {max}"
                ))
            })?;
        Ok(StreamBytes {
            reserved: self.stream_bytes.clone(),
            bytes,
        })
    }

    /// Bytes the open streams have reserved (see [`Registry::reserve_stream_bytes`]).
    pub fn reserved_stream_bytes(&self) -> u64 {
        self.stream_bytes.load(Ordering::Relaxed)
    }

    /// The syncs the store issued since it was opened ([`Store::syncs`]).
    pub fn store_syncs(&self) -> Option<u64> {
        self.store.syncs()
    }

    /// The store's one-line description, for the start-up log.
    pub fn describe_store(&self) -> String {
        self.store.describe()
    }

    /// Creates `tenant`'s task `id`, or returns the existing one if its resolved config is
    /// the same. `tenant_max_tasks` is the tenant's quota of tasks, if it has one.
    pub async fn create(
        &self,
        tenant: &str,
        id: &str,
        input: &TaskConfigInput,
        tenant_max_tasks: Option<usize>,
    ) -> Result<Arc<TaskHandle>, Error> {
        let config = TaskConfig::resolve(input)
            .map_err(|e| Error::invalid(format!("config.{}", e.field), e.message))?;
        let key = task_key(tenant, id);
        let _admin = self.admin.lock().await;
        let held = self.tasks.get(&key).map(|t| t.clone());
        if let Some(existing) = held.filter(|t| t.check_live().is_ok()) {
            // A store shared with other servers decides: another server may have deleted
            // the task before its notification came.
            let gone = matches!(
                existing.check_with_store().await,
                Err(Error::TaskNotFound { .. })
            );
            if !gone {
                return if existing.config().same_as(&config) {
                    Ok(existing)
                } else {
                    Err(Error::AlreadyExists {
                        id: id.to_string(),
                        detail: existing.config().diff(&config, input).join("; "),
                    })
                };
            }
        }
        if let Some(m) = over_limits(&self.limits, &config) {
            return Err(Error::ResourceExhausted(m));
        }
        if self.tasks.len() >= self.limits.max_tasks {
            return Err(Error::ResourceExhausted(format!(
                "task limit reached: this server holds at most max_tasks = {} tasks",
                self.limits.max_tasks
            )));
        }
        if let Some(max) = tenant_max_tasks {
            // A store shared with other servers counts the tenant's tasks on every
            // replica and takes the task's place in one step (a task there already adds
            // none); otherwise the tasks held here are all there are.
            let fits = match self.store.reserve_task(&key, tenant, max).await? {
                Some(fits) => fits,
                None => self.count(tenant) < max,
            };
            if !fits {
                return Err(Error::ResourceExhausted(format!(
                    "task quota reached: tenant {tenant:?} may hold at most max_tasks = {max} tasks"
                )));
            }
        }
        if let Some(stored) = self.store.create_task(&key, &config).await? {
            // A store shared with other servers: another server created this task.
            if !stored.same_as(&config) {
                return Err(Error::AlreadyExists {
                    id: id.to_string(),
                    detail: stored.diff(&config, input).join("; "),
                });
            }
            return self.adopt(tenant, id).await;
        }
        let handle = Arc::new(TaskHandle::new(
            key.clone(),
            config,
            Pool::new(config.pool_capacity as usize),
            Counters::default(),
            self.store.clone(),
        ));
        self.tasks.insert(key, handle.clone());
        Ok(handle)
    }

    /// Looks `tenant`'s task `id` up among the tasks this server holds.
    pub fn get(&self, tenant: &str, id: &str) -> Result<Arc<TaskHandle>, Error> {
        self.tasks
            .get(&task_key(tenant, id))
            .map(|t| t.clone())
            .filter(|t| t.check_live().is_ok())
            .ok_or_else(|| Error::TaskNotFound {
                id: id.to_string(),
                hint: self.closest(tenant, id),
            })
    }

    /// Looks `tenant`'s task `id` up; with a store shared with other servers, a task
    /// this server does not hold (created elsewhere) is loaded from the store (SPEC §10:
    /// usable on every server once its creation is acknowledged).
    pub async fn lookup(&self, tenant: &str, id: &str) -> Result<Arc<TaskHandle>, Error> {
        match self.get(tenant, id) {
            Err(Error::TaskNotFound { .. }) if self.store.is_shared() => {
                self.adopt(tenant, id).await
            }
            found => found,
        }
    }

    /// Loads `tenant`'s task `id` from a shared store into this server, replacing a
    /// handle of a deleted incarnation.
    async fn adopt(&self, tenant: &str, id: &str) -> Result<Arc<TaskHandle>, Error> {
        let key = task_key(tenant, id);
        let Some(t) = self.store.load_task(&key).await? else {
            if let Some((_, stale)) = self.tasks.remove(&key) {
                stale.mark_deleted();
            }
            return Err(Error::TaskNotFound {
                id: id.to_string(),
                hint: self.closest(tenant, id),
            });
        };
        let handle = Arc::new(
            TaskHandle::new(
                key.clone(),
                t.config,
                t.pool,
                t.counters,
                self.store.clone(),
            )
            .limited_by(&self.limits),
        );
        let entry = self.tasks.entry(key).and_modify(|held| {
            if held.check_live().is_err() {
                *held = handle.clone();
            }
        });
        Ok(entry.or_insert(handle).clone())
    }

    /// With a shared store: loads the tasks others created, forgets those they deleted.
    async fn sync_with_store(&self) -> Result<(), Error> {
        let Some(keys) = self.store.task_ids().await? else {
            return Ok(());
        };
        let known: std::collections::HashSet<&str> = keys.iter().map(String::as_str).collect();
        self.tasks.retain(|key, t| {
            let keep = known.contains(key.as_str());
            if !keep {
                t.mark_deleted();
            }
            keep
        });
        for key in &keys {
            if !self.tasks.contains_key(key) {
                let (tenant, id) = split_key(key);
                match self.adopt(tenant, id).await {
                    Ok(_) | Err(Error::TaskNotFound { .. }) => {}
                    Err(e) => return Err(e),
                }
            }
        }
        Ok(())
    }

    /// Forgets a task another server deleted: its open streams end with NOT_FOUND.
    fn forget(&self, key: &str) {
        if let Some((_, t)) = self.tasks.remove(key) {
            t.mark_deleted();
        }
    }

    /// `tenant`'s existing id closest to `id` by edit distance, if it is a typo away (at
    /// most a third of the id's length, and at most 3 edits). Looked at only on a miss.
    fn closest(&self, tenant: &str, id: &str) -> Option<String> {
        let max = (id.chars().count() / 3).clamp(1, 3);
        self.tasks
            .iter()
            .filter(|e| e.value().tenant() == tenant)
            .map(|e| {
                (
                    edit_distance(id, e.value().id()),
                    e.value().id().to_string(),
                )
            })
            .filter(|(d, _)| *d <= max)
            .min()
            .map(|(_, k)| k)
    }

    /// `tenant`'s tasks, ordered by id (with a shared store: the store's tasks).
    pub async fn list(&self, tenant: &str) -> Result<Vec<Arc<TaskHandle>>, Error> {
        self.sync_with_store().await?;
        Ok(self.held(tenant))
    }

    /// `tenant`'s tasks this server holds, ordered by id.
    pub fn held(&self, tenant: &str) -> Vec<Arc<TaskHandle>> {
        let mut v: Vec<_> = self
            .tasks
            .iter()
            .filter(|e| e.value().tenant() == tenant)
            .map(|e| e.value().clone())
            .collect();
        v.sort_by(|a, b| a.id().cmp(b.id()));
        v
    }

    /// How many tasks the server holds, over every tenant.
    pub fn len(&self) -> usize {
        self.tasks.len()
    }

    /// Whether the server holds no task.
    pub fn is_empty(&self) -> bool {
        self.tasks.is_empty()
    }

    /// How many tasks `tenant` holds.
    pub fn count(&self, tenant: &str) -> usize {
        self.tasks
            .iter()
            .filter(|e| e.value().tenant() == tenant)
            .count()
    }

    /// Every task of every tenant, ordered by key (counters, the metrics' pool gauges).
    pub fn all(&self) -> Vec<Arc<TaskHandle>> {
        let mut v: Vec<_> = self.tasks.iter().map(|e| e.value().clone()).collect();
        v.sort_by(|a, b| a.key().cmp(b.key()));
        v
    }

    /// Deletes `tenant`'s task `id`; its open streams fail with NOT_FOUND at their next batch.
    pub async fn delete(&self, tenant: &str, id: &str) -> Result<(), Error> {
        let _admin = self.admin.lock().await;
        let handle = self.lookup(tenant, id).await?;
        let _writer = handle.lock_for_delete().await;
        match self.store.delete_task(handle.key()).await {
            Ok(()) => {}
            Err(StoreError::Gone { .. }) => {
                self.forget(handle.key());
                return Err(Error::not_found(id));
            }
            Err(e) => return Err(e.into()),
        }
        handle.mark_deleted();
        self.tasks.remove(handle.key());
        Ok(())
    }

    /// The server is stopping: the store may cut background work short.
    pub fn stopping(&self) {
        self.store.stopping();
    }

    /// Persists every task's counters at once (a data dir logs them in one group).
    pub async fn flush_counters(&self) {
        let tasks = self.all();
        let flushes = tasks.iter().map(|task| async move {
            if let Err(e) = task.flush_counters().await {
                tracing::warn!(task = task.key(), error = %e, "could not persist counters");
            }
        });
        futures::future::join_all(flushes).await;
    }

    /// For a store shared with other servers: every `every`, writes the counters of each
    /// task this server counted steps or episodes in since the last time, and takes in
    /// the other servers' ([`TaskHandle::sync_counters`]). `None` (and nothing runs) for a
    /// store only this server writes.
    pub fn sync_counters_every(
        self: &Arc<Self>,
        every: std::time::Duration,
    ) -> Option<tokio::task::JoinHandle<()>> {
        if !self.store.is_shared() {
            return None;
        }
        let registry = Arc::downgrade(self);
        Some(tokio::spawn(async move {
            let mut tick = tokio::time::interval(every);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tick.tick().await;
                let Some(registry) = registry.upgrade() else {
                    return;
                };
                for task in registry.all().into_iter().filter(|t| t.counters_changed()) {
                    if let Err(e) = task.sync_counters().await {
                        tracing::debug!(task = task.key(), error = %e, "could not sync the task's counters; retried at the next tick");
                    }
                }
            }
        }))
    }

    /// For a store shared with other servers: refreshes this server's snapshot of a pool
    /// whenever the store announces a newer version, and follows the store back when it
    /// announces an older one than this server published and still has it once this
    /// server's commits are done (the store lost changes). Returns `None` (and does nothing)
    /// for a store only this server writes. Runs until the store's notifications end.
    pub fn watch_changes(self: &Arc<Self>) -> Option<tokio::task::JoinHandle<()>> {
        let mut changes = self.store.changes()?;
        let registry = Arc::downgrade(self);
        Some(tokio::spawn(async move {
            use tokio::sync::broadcast::error::RecvError;
            loop {
                let change = match changes.recv().await {
                    Ok(c) => c,
                    Err(RecvError::Lagged(n)) => {
                        tracing::warn!(missed = n, "missed pool change notifications");
                        continue;
                    }
                    Err(RecvError::Closed) => return,
                };
                let Some(registry) = registry.upgrade() else {
                    return;
                };
                if change.deleted {
                    registry.forget(&change.task);
                    continue;
                }
                let Some(task) = registry.tasks.get(&change.task).map(|t| t.clone()) else {
                    continue;
                };
                if change.version < task.published_version() {
                    // Older than this server's own commit, or a store that went back.
                    if let Err(e) = task.follow_store_back().await {
                        tracing::warn!(task = %change.task, error = %e, "could not check a pool against the store");
                    }
                    continue;
                }
                if change.version == task.published_version() {
                    continue;
                }
                match registry.store.load_pool(&change.task).await {
                    Ok(Some(pool)) => task.refresh(pool),
                    Ok(None) => {}
                    Err(e) => {
                        tracing::warn!(task = %change.task, error = %e, "could not refresh a pool")
                    }
                }
            }
        }))
    }
}

/// Levenshtein distance over characters.
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut prev = row[0];
        row[0] = i + 1;
        for (j, &cb) in b.iter().enumerate() {
            let cur = row[j + 1];
            row[j + 1] = (prev + usize::from(ca != cb)).min(row[j] + 1).min(cur + 1);
            prev = cur;
        }
    }
    row[b.len()]
}

#[cfg(test)]
mod tests;
