//! What a local session's store and the driver of its Follow stream share: the followed
//! pool and how the driver reports to the store.

use std::sync::Arc;

use parking_lot::Mutex;
use tamrm::core::{Pool, TaskConfig};
use tamrm::store::PoolChanged;
use tokio::sync::broadcast;
use tonic::Status;

/// What the store and its driver share.
pub(crate) struct Shared {
    /// The task's key in the local registry (its id: the default tenant).
    pub(crate) key: String,
    pub(crate) config: TaskConfig,
    /// The followed pool: the server's, as of the last update received.
    pub(crate) pool: Mutex<Arc<Pool>>,
    pub(crate) changes: broadcast::Sender<PoolChanged>,
    /// The status of the last failure the server answered, for the session's error.
    pub(crate) failure: Mutex<Option<Status>>,
    /// Why the driver ended, if the server refused the stream for good.
    pub(crate) ended: Mutex<Option<Status>>,
    /// Woken whenever the driver answers a message (for [`super::FollowStore::wait_acks`]).
    pub(crate) answered: tokio::sync::Notify,
}

impl Shared {
    /// Takes `pool` as the followed pool and tells the registry.
    pub(crate) fn set_pool(&self, pool: Pool) {
        let version = pool.version();
        *self.pool.lock() = Arc::new(pool);
        let _ = self.changes.send(PoolChanged {
            task: self.key.clone(),
            version,
            deleted: false,
        });
    }
}
