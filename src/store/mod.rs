//! Where task configs and pools live, behind the small [`Store`] trait.
//!
//! The registry calls the store *before* it makes a change visible: a change that the
//! store could not persist is never applied, so every change a response reports is on
//! disk (for a durable store) when the response is sent. Calls for one task are
//! serialised by the registry; streams keep shaping against the previous pool meanwhile.
//!
//! - [`MemoryStore`]: nothing is persisted; state is lost at exit.
//! - [`DiskStore`]: one directory per task under a data dir; see `docs/storage.md`.

mod disk;
mod memory;

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::core::{Pool, TaskConfig};

pub use disk::{DiskStore, FORMAT_VERSION};
pub use memory::MemoryStore;

/// Per-task counters kept alongside the pool (persisted with every pool change and at
/// graceful shutdown; a crash may lose the increments since the last write).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Counters {
    /// Episodes ended by Shape streams.
    pub episodes_completed: u64,
    /// Step entries shaped.
    pub steps_shaped: u64,
}

/// A task as restored from a store.
#[derive(Debug, Clone)]
pub struct StoredTask {
    /// The task id.
    pub id: String,
    /// Its resolved configuration.
    pub config: TaskConfig,
    /// Its pool, with version and next seq.
    pub pool: Pool,
    /// Its counters.
    pub counters: Counters,
}

/// A storage failure. `path` names the file or directory concerned.
#[derive(Debug, thiserror::Error)]
#[error("{}: {message}", path.display())]
pub struct StoreError {
    /// The file or directory concerned.
    pub path: PathBuf,
    /// What went wrong.
    pub message: String,
}

impl StoreError {
    pub(crate) fn new(path: impl Into<PathBuf>, message: impl std::fmt::Display) -> StoreError {
        StoreError {
            path: path.into(),
            message: message.to_string(),
        }
    }
}

/// Persistence of task configs and pools. Implementations are called with the task's pool
/// write lock held, so calls for one task never overlap; calls for different tasks may.
pub trait Store: Send + Sync + 'static {
    /// One line saying where state lives, for the start-up log.
    fn describe(&self) -> String;
    /// Whether calls do blocking disk I/O (the server then keeps them off the async
    /// executor's threads).
    fn is_durable(&self) -> bool;
    /// Every stored task. Fails, naming the file, on anything corrupt or truncated.
    fn load(&self) -> Result<Vec<StoredTask>, StoreError>;
    /// Persists a new task with an empty pool.
    fn create_task(&self, id: &str, config: &TaskConfig) -> Result<(), StoreError>;
    /// Removes a task and its pool.
    fn delete_task(&self, id: &str) -> Result<(), StoreError>;
    /// Persists the pool going from `before` (the last committed state) to `after`: one or
    /// more inserts/replacements, or a reset. Trajectories are immutable and identified by
    /// seq, so the difference of the two seq sets says what to write and what to remove.
    fn commit(
        &self,
        id: &str,
        before: &Pool,
        after: &Pool,
        counters: Counters,
    ) -> Result<(), StoreError>;
    /// Persists the counters (and the pool manifest they live in) without a pool change.
    fn save_counters(&self, id: &str, pool: &Pool, counters: Counters) -> Result<(), StoreError>;
}
