//! A [`Store`] decorator that times every commit (`tamrm_store_commit_seconds`: one per
//! group of a task's changes committed together) and counts the pool operations that
//! changed a pool (`tamrm_pool_changes_total`); every other call goes straight through.

use std::sync::Arc;
use std::time::Instant;

use crate::core::{Pool, TaskConfig};
use crate::store::{
    Committed, Counters, GroupCommitted, PoolChanged, PoolOp, Store, StoreError, StoredTask,
};

use super::Metrics;

/// `inner`, with its commits measured into a [`Metrics`].
pub struct MeteredStore {
    inner: Arc<dyn Store>,
    metrics: Arc<Metrics>,
}

impl MeteredStore {
    /// Wraps `inner`.
    pub fn new(inner: Arc<dyn Store>, metrics: Arc<Metrics>) -> MeteredStore {
        MeteredStore { inner, metrics }
    }
}

#[async_trait::async_trait]
impl Store for MeteredStore {
    fn describe(&self) -> String {
        self.inner.describe()
    }

    async fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        self.inner.load().await
    }

    async fn create_task(
        &self,
        id: &str,
        config: &TaskConfig,
    ) -> Result<Option<TaskConfig>, StoreError> {
        self.inner.create_task(id, config).await
    }

    async fn delete_task(&self, id: &str) -> Result<(), StoreError> {
        self.inner.delete_task(id).await
    }

    async fn commit(
        &self,
        id: &str,
        base: Arc<Pool>,
        ops: Vec<PoolOp>,
        counters: Counters,
    ) -> Result<Committed, StoreError> {
        let start = Instant::now();
        let committed = self.inner.commit(id, base, ops, counters).await?;
        let changes = committed.changed.iter().filter(|&&c| c).count();
        self.metrics.commit(id, start.elapsed(), changes);
        Ok(committed)
    }

    async fn commit_group(
        &self,
        id: &str,
        base: Arc<Pool>,
        parts: Vec<Vec<PoolOp>>,
        counters: Counters,
    ) -> Result<GroupCommitted, StoreError> {
        let start = Instant::now();
        let done = self.inner.commit_group(id, base, parts, counters).await?;
        let changes = done.committed.changed.iter().filter(|&&c| c).count();
        self.metrics.commit(id, start.elapsed(), changes);
        Ok(done)
    }

    fn stopping(&self) {
        self.inner.stopping()
    }

    async fn stopped(&self) -> Result<(), StoreError> {
        self.inner.stopped().await
    }

    async fn save_counters(
        &self,
        id: &str,
        pool: Arc<Pool>,
        counters: Counters,
    ) -> Result<(), StoreError> {
        self.inner.save_counters(id, pool, counters).await
    }

    async fn load_pool(&self, id: &str) -> Result<Option<Pool>, StoreError> {
        self.inner.load_pool(id).await
    }

    fn changes(&self) -> Option<tokio::sync::broadcast::Receiver<PoolChanged>> {
        self.inner.changes()
    }

    fn syncs(&self) -> Option<u64> {
        self.inner.syncs()
    }

    fn is_shared(&self) -> bool {
        self.inner.is_shared()
    }

    async fn load_task(&self, id: &str) -> Result<Option<StoredTask>, StoreError> {
        self.inner.load_task(id).await
    }

    async fn task_ids(&self) -> Result<Option<Vec<String>>, StoreError> {
        self.inner.task_ids().await
    }

    async fn reserve_task(
        &self,
        id: &str,
        tenant: &str,
        max: usize,
    ) -> Result<Option<bool>, StoreError> {
        self.inner.reserve_task(id, tenant, max).await
    }

    async fn ended_episodes(&self, id: &str, client: &str) -> Result<Vec<(u32, u64)>, StoreError> {
        self.inner.ended_episodes(id, client).await
    }

    async fn sync_counters(
        &self,
        id: &str,
        counters: Counters,
    ) -> Result<Option<Counters>, StoreError> {
        self.inner.sync_counters(id, counters).await
    }
}

/// `store`, measured into `metrics` when there are metrics.
pub fn metered(store: Arc<dyn Store>, metrics: Option<&Arc<Metrics>>) -> Arc<dyn Store> {
    match metrics {
        Some(m) => Arc::new(MeteredStore::new(store, m.clone())),
        None => store,
    }
}
