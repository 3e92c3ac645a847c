use super::{Counters, Store, StoreError, StoredTask};
use crate::core::{Pool, TaskConfig};

/// Keeps nothing: every change is accepted and forgotten, so state lives only in the
/// server's memory and is lost at exit.
#[derive(Debug, Default, Clone, Copy)]
pub struct MemoryStore;

impl Store for MemoryStore {
    fn describe(&self) -> String {
        "no --data-dir: tasks and pools are kept in memory only and are lost when the server exits"
            .to_string()
    }
    fn is_durable(&self) -> bool {
        false
    }
    fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        Ok(Vec::new())
    }
    fn create_task(&self, _: &str, _: &TaskConfig) -> Result<(), StoreError> {
        Ok(())
    }
    fn delete_task(&self, _: &str) -> Result<(), StoreError> {
        Ok(())
    }
    fn commit(&self, _: &str, _: &Pool, _: &Pool, _: Counters) -> Result<(), StoreError> {
        Ok(())
    }
    fn save_counters(&self, _: &str, _: &Pool, _: Counters) -> Result<(), StoreError> {
        Ok(())
    }
}
