//! Where task configs and pools live, behind the small async [`Store`] trait.
//!
//! The registry asks the store to *commit* a pool change before it makes the change
//! visible: a change the store did not acknowledge is never applied, so every change a
//! response reports is durable (for a durable store) when the response is sent.
//!
//! A commit is conditional: it carries the operations of SPEC §6 ([`PoolOp`]: offer an
//! episode, reset) and the version of the pool the caller planned against. The store
//! applies the operations against *its* current pool and returns the resulting pool. A
//! store that is the only writer of its pools (memory, disk) checks that the versions
//! agree and reports [`StoreError::Conflict`] otherwise; a store shared by several
//! servers (e.g. Redis) decides §6 atomically against the shared pool, and announces
//! changes through [`Store::changes`] so that every server refreshes its snapshot.
//!
//! - [`MemoryStore`]: nothing is persisted; state is lost at exit.
//! - [`DiskStore`]: one directory per task under a data dir; see `docs/storage.md`.
//! - [`RedisStore`]: tasks and pools in Redis, shared by any number of servers; see
//!   `docs/scaling.md`.

mod disk;
mod ends;
// A leaf module (nothing of the crate), so that `crate::error` can use it.
pub(crate) mod error;
mod memory;
mod redis;
#[cfg(test)]
pub(crate) mod testing;

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::core::{ActionSeq, Pool, TaskConfig};

pub use disk::{DiskStore, RepairReport, FORMAT_VERSION};
pub use ends::{EndedEpisodes, MAX_REMEMBERED_CLIENTS};
pub use error::StoreError;
pub use memory::MemoryStore;
pub use redis::{RedisLedger, RedisOptions, RedisStore, RedisTarget, RedisTls};

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

/// One pool operation of SPEC §6, decided by the store against its current pool.
#[derive(Debug, Clone, PartialEq)]
pub enum PoolOp {
    /// Offer a finished episode (or a seeded trajectory): insert while the pool is not
    /// full, else replace the lowest score if this one is strictly greater, else discard.
    Offer {
        /// The recorded actions (non-empty).
        actions: ActionSeq,
        /// The episode score (finite).
        score: f64,
        /// For an episode end of a client that named itself (SPEC §9), which one: a store
        /// shared by several servers skips an end it already committed. `None` for
        /// seeded trajectories and anonymous clients.
        end: Option<EndMark>,
    },
    /// Remove every trajectory.
    Reset,
}

/// Names an episode end for the no-double-commit rule of SPEC §9: (client, env, episode).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EndMark {
    /// The client's id (non-empty).
    pub client: Arc<str>,
    /// The environment.
    pub env: u32,
    /// The number of the episode (episodes the env ended before it).
    pub episode: u64,
}

/// What a commit did.
#[derive(Debug, Clone)]
pub struct Committed {
    /// The pool after the commit (with its new version).
    pub pool: Arc<Pool>,
    /// Per operation, in order: whether it changed the pool.
    pub changed: Vec<bool>,
    /// The pool version right after this commit's own changes. A store shared with other
    /// servers may return a `pool` that already holds later changes of theirs, with a
    /// higher version; this one is the commit's own (SPEC §10: one version per change).
    pub version: u64,
    /// How many of the offers were episode ends the store already had committed (by
    /// another server, after this one last learnt the client's record): not offered,
    /// and not counted in `episodes_completed`. Always 0 for a store that is not shared:
    /// the server itself decides re-sent ends before committing (SPEC §9).
    pub resent: usize,
}

impl Committed {
    /// A commit whose result is `pool` itself (nobody else changed it meanwhile).
    pub fn new(pool: Arc<Pool>, changed: Vec<bool>) -> Committed {
        let version = pool.version();
        Committed {
            pool,
            changed,
            version,
            resent: 0,
        }
    }
}

/// What a commit of several requests' operations at once (a group commit, see
/// [`Store::commit_group`]) did: the commit of their concatenation, and how many of each
/// request's offers were re-sent ends.
#[derive(Debug, Clone)]
pub struct GroupCommitted {
    /// The commit of every part's operations, in order, as one.
    pub committed: Committed,
    /// Per part, how many of its offers were episode ends the store already had committed
    /// (`committed.resent` split by part); `None` when the store cannot tell which part
    /// they were in (then only the total is known).
    pub resent: Option<Vec<usize>>,
}

/// A pool changed in the store (by this server or another one), or its task was deleted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PoolChanged {
    /// The task id.
    pub task: String,
    /// The pool version after the change (0 for a deletion).
    pub version: u64,
    /// The task was deleted.
    pub deleted: bool,
}

/// Applies `ops` in order to a copy of `base` (SPEC §6), as a store that owns its pools
/// does. Returns the new pool and, per op, whether it changed the pool. The pool is laid
/// out by step once, at the end, from `base`'s layout (a group of changes costs one
/// layout, not one each).
pub fn apply_ops(base: &Pool, ops: Vec<PoolOp>) -> (Pool, Vec<bool>) {
    let mut pool = base.clone();
    let changed: Vec<bool> = ops
        .into_iter()
        .map(|op| {
            let change = match op {
                PoolOp::Offer { actions, score, .. } => pool.plan_offer(actions, score),
                PoolOp::Reset => Some(pool.plan_reset()),
            };
            change.map(|c| pool.apply_without_layout(&c)).is_some()
        })
        .collect();
    if changed.contains(&true) {
        pool.lay_out_from(base);
    }
    (pool, changed)
}

/// Persistence of task configs and pools. Calls for one task are serialised by the
/// registry (commits of one task never overlap on one server: it commits the changes
/// planned meanwhile together, [`Store::commit_group`]); calls for different tasks may
/// run at once. Every method may do I/O and is async: blocking implementations move
/// their work off the async executor themselves.
#[async_trait::async_trait]
pub trait Store: Send + Sync + 'static {
    /// One line saying where state lives, for the start-up log.
    fn describe(&self) -> String;
    /// Every stored task. Fails, naming the file, on anything corrupt or truncated.
    async fn load(&self) -> Result<Vec<StoredTask>, StoreError>;
    /// Persists a new task with an empty pool. A store shared by several servers creates
    /// it only if no server did: it returns the config of a task that already exists
    /// (`Some`) and changes nothing then.
    async fn create_task(
        &self,
        id: &str,
        config: &TaskConfig,
    ) -> Result<Option<TaskConfig>, StoreError>;
    /// Removes a task and its pool.
    async fn delete_task(&self, id: &str) -> Result<(), StoreError>;
    /// Applies `ops` against the store's current pool of `id`, atomically, and persists
    /// the result with `counters`. `base` is the pool the caller planned against; a store
    /// whose pool has another version fails with [`StoreError::Conflict`] (a store shared
    /// by several servers decides against the shared pool instead). Nothing is changed on
    /// error.
    async fn commit(
        &self,
        id: &str,
        base: Arc<Pool>,
        ops: Vec<PoolOp>,
        counters: Counters,
    ) -> Result<Committed, StoreError>;
    /// [`Store::commit`] of several requests' operations at once (group commit): the
    /// parts, in order, are committed as one (one record and one sync for a durable store,
    /// one atomic update for a shared one), exactly as their concatenation would be. The
    /// default does just that; a store that can tell which part a re-sent end belonged to
    /// says so in [`GroupCommitted::resent`].
    async fn commit_group(
        &self,
        id: &str,
        base: Arc<Pool>,
        parts: Vec<Vec<PoolOp>>,
        counters: Counters,
    ) -> Result<GroupCommitted, StoreError> {
        let lens: Vec<usize> = parts.iter().map(Vec::len).collect();
        let ops = parts.into_iter().flatten().collect();
        let committed = self.commit(id, base, ops, counters).await?;
        let resent = match (committed.resent, lens.len()) {
            (0, n) => Some(vec![0; n]),
            (all, 1) => Some(vec![all]),
            _ => None,
        };
        Ok(GroupCommitted { committed, resent })
    }
    /// The server is stopping (and will then save every task's counters, and close the
    /// store): a store may cut background work short. The data dir abandons a
    /// compaction in progress and starts no other (its log holds every change), so that
    /// a stop never waits for snapshots to be written.
    fn stopping(&self) {}
    /// The server has stopped: every change is committed (counters included) and nothing
    /// more will be. A data dir records that it stopped cleanly, so that the next start
    /// can tell a log cut short from a crash's torn write (docs/storage.md).
    async fn stopped(&self) -> Result<(), StoreError> {
        Ok(())
    }
    /// Persists the counters without a pool change.
    async fn save_counters(
        &self,
        id: &str,
        pool: Arc<Pool>,
        counters: Counters,
    ) -> Result<(), StoreError>;
    /// The store's current pool of `id` (for a server refreshing its snapshot after a
    /// change elsewhere). Stores that are the only writer of their pools need not
    /// implement it.
    async fn load_pool(&self, id: &str) -> Result<Option<Pool>, StoreError> {
        let _ = id;
        Ok(None)
    }
    /// Notifications of pool changes and deletions made through this store by any
    /// server, for stores shared by several servers; `None` for a store only this server
    /// writes. A shared store delivers every change within its documented staleness
    /// bound (notifications, with a poll as backstop).
    fn changes(&self) -> Option<tokio::sync::broadcast::Receiver<PoolChanged>> {
        None
    }
    /// Every fsync and fdatasync the store has issued since it was opened, for a store
    /// that syncs files (the disk store); `None` for others.
    fn syncs(&self) -> Option<u64> {
        None
    }
    /// Whether other servers may create, change and delete tasks in this store (then the
    /// registry asks it about tasks it does not know, and lists from it).
    fn is_shared(&self) -> bool {
        false
    }
    /// One task as stored now, `None` if the store has no task `id` (shared stores;
    /// others answer `None`).
    async fn load_task(&self, id: &str) -> Result<Option<StoredTask>, StoreError> {
        let _ = id;
        Ok(None)
    }
    /// The ids of every stored task (shared stores; others answer `None`).
    async fn task_ids(&self) -> Result<Option<Vec<String>>, StoreError> {
        Ok(None)
    }
    /// For a store shared with other servers: takes a place for task `id` of `tenant` in
    /// the store's task index, atomically with the check that the tenant holds fewer than
    /// `max` tasks there (the task quota over every server, racing creates included):
    /// `Some(true)` if the task has its place (taken now, or there already), `Some(false)`
    /// if the tenant holds `max` tasks. `None` for a store only this server writes (the
    /// registry counts the tasks it holds).
    async fn reserve_task(
        &self,
        id: &str,
        tenant: &str,
        max: usize,
    ) -> Result<Option<bool>, StoreError> {
        let _ = (id, tenant, max);
        Ok(None)
    }
    /// The episode ends of `client` the store committed on task `id`, as (env, episodes
    /// ended): what a server resuming that client's stream must not commit again
    /// (SPEC §9): a shared store's, or a data dir's from before a restart. The memory
    /// store answers nothing (the registry itself remembers what this process did).
    async fn ended_episodes(&self, id: &str, client: &str) -> Result<Vec<(u32, u64)>, StoreError> {
        let _ = (id, client);
        Ok(Vec::new())
    }
    /// For a store shared with other servers: writes this server's counter increments of
    /// task `id` (`counters` are its totals as this server knows them) and answers the
    /// task's totals over every server, as they have written them, which this server
    /// then reports. `None` for a store only this server writes (its counters are the
    /// totals).
    async fn sync_counters(
        &self,
        id: &str,
        counters: Counters,
    ) -> Result<Option<Counters>, StoreError> {
        let _ = (id, counters);
        Ok(None)
    }
}

#[cfg(test)]
mod tests;
