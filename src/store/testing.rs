//! Stores for unit tests of the layers above: one whose commits can be made to fail, held
//! or slowed down (so that a task's changes queue up behind one in flight), and one that
//! plays a store shared with other servers (announcing changes made "elsewhere").

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;

use parking_lot::Mutex;
use tokio::sync::{broadcast, Notify};

use super::{Committed, Counters, MemoryStore, PoolChanged, PoolOp, Store, StoreError, StoredTask};
use crate::core::{Pool, TaskConfig};

/// A [`MemoryStore`] whose commits fail while `fail` is set, wait while held
/// ([`TestStore::hold`]) and yield `yields` times first, and which can announce pool
/// changes made by "another server" (`announce`), serving that pool from `load_pool`.
#[derive(Debug)]
pub struct TestStore {
    inner: MemoryStore,
    /// Commits fail while set (checked once the commit is let through).
    pub fail: AtomicBool,
    /// Commits started (each group of a task's changes is one).
    pub commits: AtomicUsize,
    /// How many times a commit yields to the runtime before it commits.
    pub yields: AtomicUsize,
    held: AtomicBool,
    /// Releases so far: a commit waiting at a release goes through, even if the store is
    /// held again right after.
    releases: AtomicUsize,
    released: Notify,
    remote: Mutex<Option<Pool>>,
    tx: broadcast::Sender<PoolChanged>,
    shared: bool,
}

impl TestStore {
    /// A store only this server writes (`shared` false) or one that announces changes.
    pub fn new(shared: bool) -> Arc<TestStore> {
        Arc::new(TestStore {
            inner: MemoryStore::new(),
            fail: AtomicBool::new(false),
            commits: AtomicUsize::new(0),
            yields: AtomicUsize::new(0),
            held: AtomicBool::new(false),
            releases: AtomicUsize::new(0),
            released: Notify::new(),
            remote: Mutex::new(None),
            tx: broadcast::channel(16).0,
            shared,
        })
    }

    /// Commits wait from now on, until [`TestStore::release`].
    pub fn hold(&self) {
        self.held.store(true, Ordering::SeqCst);
    }

    /// Lets the waiting commits through, and later ones until [`TestStore::hold`].
    pub fn release(&self) {
        self.held.store(false, Ordering::SeqCst);
        self.releases.fetch_add(1, Ordering::SeqCst);
        self.released.notify_waiters();
    }

    /// Waits until `n` commits have started (panics after 10 s).
    pub async fn started(&self, n: usize) {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        while self.commits.load(Ordering::SeqCst) < n {
            assert!(
                std::time::Instant::now() < deadline,
                "{n} commits never started"
            );
            tokio::task::yield_now().await;
        }
    }

    /// Plays a change made by another server: `pool` is now the store's pool of `task`.
    pub fn announce(&self, task: &str, pool: Pool) {
        let version = pool.version();
        *self.remote.lock() = Some(pool);
        let _ = self.tx.send(PoolChanged {
            task: task.to_string(),
            version,
            deleted: false,
        });
    }
}

#[async_trait::async_trait]
impl Store for TestStore {
    fn describe(&self) -> String {
        "test store".into()
    }
    async fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        Ok(Vec::new())
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
        self.commits.fetch_add(1, Ordering::SeqCst);
        for _ in 0..self.yields.load(Ordering::SeqCst) {
            tokio::task::yield_now().await;
        }
        let entered = self.releases.load(Ordering::SeqCst);
        loop {
            let released = self.released.notified();
            tokio::pin!(released);
            released.as_mut().enable();
            if !self.held.load(Ordering::SeqCst) || self.releases.load(Ordering::SeqCst) != entered
            {
                break;
            }
            released.await;
        }
        if self.fail.load(Ordering::SeqCst) {
            return Err(StoreError::new(id, "injected failure"));
        }
        self.inner.commit(id, base, ops, counters).await
    }
    async fn save_counters(&self, _: &str, _: Arc<Pool>, _: Counters) -> Result<(), StoreError> {
        Ok(())
    }
    async fn load_pool(&self, _: &str) -> Result<Option<Pool>, StoreError> {
        Ok(self.remote.lock().clone())
    }
    fn changes(&self) -> Option<broadcast::Receiver<PoolChanged>> {
        self.shared.then(|| self.tx.subscribe())
    }
}
