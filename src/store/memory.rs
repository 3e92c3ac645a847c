use std::collections::HashMap;
use std::sync::Arc;

use parking_lot::Mutex;

use super::{apply_ops, Committed, Counters, PoolOp, Store, StoreError, StoredTask};
use crate::core::{Pool, TaskConfig};

/// Keeps nothing durable: state lives only in the server's memory and is lost at exit.
/// It remembers each task's pool version, so that a conditional commit planned against
/// a stale pool fails as it would with any other store.
#[derive(Debug, Default)]
pub struct MemoryStore {
    versions: Mutex<HashMap<String, u64>>,
}

impl MemoryStore {
    /// An empty store.
    pub fn new() -> MemoryStore {
        MemoryStore::default()
    }
}

/// Checks that `base` is the version `versions` holds for `id` (a task the store does not
/// know is at version 0, e.g. one restored by another store).
pub(super) fn check_version(id: &str, known: Option<u64>, base: &Pool) -> Result<(), StoreError> {
    let found = known.unwrap_or(0);
    if found != base.version() {
        return Err(StoreError::Conflict {
            task: id.to_string(),
            expected: base.version(),
            found,
        });
    }
    Ok(())
}

#[async_trait::async_trait]
impl Store for MemoryStore {
    fn describe(&self) -> String {
        "no --data-dir: tasks and pools are kept in memory only and are lost when the server exits"
            .to_string()
    }
    async fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        Ok(Vec::new())
    }
    async fn create_task(
        &self,
        id: &str,
        _: &TaskConfig,
    ) -> Result<Option<TaskConfig>, StoreError> {
        self.versions.lock().insert(id.to_string(), 0);
        Ok(None)
    }
    async fn delete_task(&self, id: &str) -> Result<(), StoreError> {
        self.versions.lock().remove(id);
        Ok(())
    }
    async fn commit(
        &self,
        id: &str,
        base: Arc<Pool>,
        ops: Vec<PoolOp>,
        _: Counters,
    ) -> Result<Committed, StoreError> {
        let mut versions = self.versions.lock();
        check_version(id, versions.get(id).copied(), &base)?;
        let (pool, changed) = apply_ops(&base, ops);
        versions.insert(id.to_string(), pool.version());
        Ok(Committed::new(Arc::new(pool), changed))
    }
    async fn save_counters(&self, _: &str, _: Arc<Pool>, _: Counters) -> Result<(), StoreError> {
        Ok(())
    }
}
