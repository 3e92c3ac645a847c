//! [`RedisStore`] itself: the [`Store`] methods, each one script or one atomic read, and
//! what this server knows of the tasks it holds (which creation of each, and the counters
//! it last added to Redis).

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use dashmap::DashMap;
use redis::AsyncCommands;
use tokio::sync::broadcast;

use super::codec::{decode_task, encode_config, field, stored_config};
use super::conn::{connect, unavailable, Conn};
use super::keys::{Keys, CHANNEL, TASKS};
use super::ledger::{reserve_task, RedisLedger};
use super::scripts::{CommitAnswer, CommitCall, Scripts};
use super::tls::RedisTls;
use super::url::redact;
use super::watch::watch;
use crate::core::{Pool, TaskConfig};
use crate::store::{
    apply_ops, Committed, Counters, GroupCommitted, PoolChanged, PoolOp, Store, StoreError,
    StoredTask,
};

/// How to reach Redis and how fresh snapshots are kept.
#[derive(Debug, Clone)]
pub struct RedisOptions {
    /// `redis://[[user]:password@]host:port[/db]`, or
    /// `redis-cluster://[[user]:password@]host:port[,host:port...]` (see
    /// [`RedisTarget`](super::RedisTarget)).
    pub url: String,
    /// Every server reads every task's version this often, as a backstop for lost
    /// notifications: the bound on how stale a snapshot can be while notifications are
    /// lost (they normally arrive within a round trip).
    pub poll_interval: Duration,
    /// How long the no-double-commit record of a client is kept after its last commit.
    pub ended_ttl: Duration,
    /// TLS files for a `rediss://` or `rediss-cluster://` URL (none: the system's roots,
    /// no client certificate).
    pub tls: RedisTls,
}

impl RedisOptions {
    /// `url` with the defaults: a 1 s poll, a 24 h end record.
    pub fn new(url: impl Into<String>) -> RedisOptions {
        RedisOptions {
            url: url.into(),
            poll_interval: Duration::from_secs(1),
            ended_ttl: Duration::from_secs(24 * 3600),
            tls: RedisTls::default(),
        }
    }
}

/// What this server knows of a task it holds: which creation, and the counters it last
/// added to Redis (commits send the increments since).
#[derive(Debug, Clone)]
pub(super) struct Held {
    /// Names this creation of the task.
    pub incarnation: String,
    /// The counters as this server last wrote them.
    pub written: Counters,
}

/// Task configs and pools in Redis; see the [module documentation](super).
pub struct RedisStore {
    what: String,
    conn: Conn,
    scripts: Scripts,
    held: Arc<DashMap<String, Held>>,
    ended_ttl: Duration,
    tx: broadcast::Sender<PoolChanged>,
    watcher: tokio::task::JoinHandle<()>,
}

impl Drop for RedisStore {
    fn drop(&mut self) {
        self.watcher.abort();
    }
}

impl std::fmt::Debug for RedisStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.what)
    }
}

impl RedisStore {
    /// Connects (failing if Redis does not answer) and starts following changes.
    pub async fn open(options: &RedisOptions) -> Result<RedisStore, StoreError> {
        let what = format!("redis {}", redact(&options.url));
        let (conn, subscribers) = connect(&what, &options.url, &options.tls).await?;
        let (tx, _) = broadcast::channel(1024);
        let held = Arc::new(DashMap::new());
        let watcher = tokio::spawn(watch(
            subscribers,
            conn.clone(),
            held.clone(),
            tx.clone(),
            options.poll_interval,
        ));
        Ok(RedisStore {
            what,
            conn,
            scripts: Scripts::new(),
            held,
            ended_ttl: options.ended_ttl,
            tx,
            watcher,
        })
    }

    /// The tenants' quotas shared by every server of this store; leases of `lease`.
    pub fn ledger(&self, lease: Duration) -> RedisLedger {
        RedisLedger::new(self.what.clone(), self.conn.clone(), lease)
    }

    fn fail(&self, doing: &str, e: redis::RedisError) -> StoreError {
        unavailable(&self.what, doing, e)
    }

    fn incarnation(&self, task: &str) -> Result<String, StoreError> {
        self.held
            .get(task)
            .map(|h| h.incarnation.clone())
            .ok_or_else(|| StoreError::Gone {
                task: task.to_string(),
            })
    }

    /// The increments of `counters` since this server last wrote them.
    fn delta(&self, task: &str, counters: Counters) -> Counters {
        let written = self.held.get(task).map(|h| h.written).unwrap_or(counters);
        Counters {
            episodes_completed: counters
                .episodes_completed
                .saturating_sub(written.episodes_completed),
            steps_shaped: counters.steps_shaped.saturating_sub(written.steps_shaped),
        }
    }

    fn wrote(&self, task: &str, counters: Counters) {
        if let Some(mut h) = self.held.get_mut(task) {
            h.written = counters;
        }
    }

    /// Runs the COMMIT script: the task's pool version before and after, its next seq
    /// before, and per offer 1 (stored), 0 (not stored) or 2 (a re-sent end, not counted).
    /// `Gone` if the task (this incarnation of it) is not in Redis.
    async fn run_commit(
        &self,
        task: &str,
        ops: &[PoolOp],
        counters: Counters,
    ) -> Result<CommitAnswer, StoreError> {
        let incarnation = self.incarnation(task)?;
        let call = CommitCall {
            task,
            incarnation: &incarnation,
            ops,
            delta: self.delta(task, counters),
            ended_ttl: self.ended_ttl,
        };
        let out: Vec<u64> = call
            .invocation(&self.scripts.commit)
            .invoke_async(&mut self.conn.clone())
            .await
            .map_err(|e| self.fail("committing", e))?;
        let Some(answer) = CommitAnswer::read(&out) else {
            self.held.remove(task);
            return Err(StoreError::Gone {
                task: task.to_string(),
            });
        };
        // The script did not count the re-sent ends; the handle takes them back from its
        // own count too (`TaskHandle::commit_ends`), so the next increment stays exact.
        self.wrote(
            task,
            Counters {
                episodes_completed: counters
                    .episodes_completed
                    .saturating_sub(answer.resent as u64),
                ..counters
            },
        );
        Ok(answer)
    }

    /// [`Store::commit`], with the script's decision per op (1 stored, 0 not, 2 re-sent).
    async fn commit_ops(
        &self,
        id: &str,
        base: Arc<Pool>,
        ops: Vec<PoolOp>,
        counters: Counters,
    ) -> Result<(Committed, Vec<u64>), StoreError> {
        let CommitAnswer {
            before,
            after,
            seq_before,
            decided,
            resent,
        } = self.run_commit(id, &ops, counters).await?;
        let changed: Vec<bool> = decided.iter().map(|&c| c == 1).collect();
        if before == base.version() && seq_before == base.next_seq() && resent == 0 {
            // Nobody changed the pool since `base`: the same rule gives the same pool here.
            let (pool, local) = apply_ops(&base, ops);
            if pool.version() == after && local == changed {
                return Ok((Committed::new(Arc::new(pool), changed), decided));
            }
            tracing::warn!(
                task = id,
                "Redis decided a commit differently; reloading the pool"
            );
        }
        // Another server changed the pool meanwhile: read the result (or a newer pool).
        let pool = self.load_pool(id).await?.ok_or_else(|| StoreError::Gone {
            task: id.to_string(),
        })?;
        let committed = Committed {
            pool: Arc::new(pool),
            changed,
            version: after,
            resent,
        };
        Ok((committed, decided))
    }

    /// Reads a task's meta and trajectories in one atomic round trip: the task and its
    /// incarnation, `None` if there is no such task.
    async fn read(&self, task: &str) -> Result<Option<(StoredTask, String)>, StoreError> {
        let keys = Keys::of(task);
        let (meta, traj): (HashMap<String, Vec<u8>>, HashMap<u64, Vec<u8>>) = redis::pipe()
            .atomic()
            .hgetall(&keys.meta)
            .hgetall(&keys.traj)
            .query_async(&mut self.conn.clone())
            .await
            .map_err(|e| self.fail("loading", e))?;
        if meta.is_empty() {
            return Ok(None);
        }
        let incarnation =
            String::from_utf8_lossy(field(&meta, "incarnation").unwrap_or(b"")).into_owned();
        decode_task(task, &meta, traj)
            .map(|t| Some((t, incarnation)))
            .map_err(|message| StoreError::Io {
                path: format!("{} key {}", self.what, keys.meta).into(),
                message,
            })
    }
}

/// A name for a new creation of a task: distinct from any earlier one of the same id.
fn new_incarnation() -> String {
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    format!("{nanos:x}{:x}", std::process::id())
}
#[async_trait::async_trait]
impl Store for RedisStore {
    fn describe(&self) -> String {
        format!(
            "tasks and pools in {} (shared by every server using it)",
            self.what
        )
    }

    async fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        let keys = self.task_ids().await?.unwrap_or_default();
        let mut tasks = Vec::with_capacity(keys.len());
        for key in keys {
            if let Some(t) = self.load_task(&key).await? {
                tasks.push(t);
            }
        }
        Ok(tasks)
    }

    async fn create_task(
        &self,
        id: &str,
        config: &TaskConfig,
    ) -> Result<Option<TaskConfig>, StoreError> {
        let keys = Keys::of(id);
        let mut conn = self.conn.clone();
        // The index first: a key in it may lack a task, never the reverse.
        let _: i64 = conn
            .sadd(TASKS, id)
            .await
            .map_err(|e| self.fail("creating", e))?;
        let json = encode_config(config).map_err(|e| StoreError::new(&self.what, e))?;
        let (created, stored, incarnation): (u8, Vec<u8>, String) = self
            .scripts
            .create
            .key(&keys.meta)
            .key(&keys.traj)
            .key(&keys.scores)
            .arg(json)
            .arg(config.pool_capacity)
            .arg(new_incarnation())
            .invoke_async(&mut conn)
            .await
            .map_err(|e| self.fail("creating", e))?;
        if created == 1 {
            self.held.insert(
                id.to_string(),
                Held {
                    incarnation,
                    written: Counters::default(),
                },
            );
            return Ok(None);
        }
        let existing = stored_config(&stored).map_err(|message| StoreError::Io {
            path: format!("{} key {}", self.what, keys.meta).into(),
            message,
        })?;
        Ok(Some(existing))
    }

    async fn delete_task(&self, id: &str) -> Result<(), StoreError> {
        let incarnation = self.incarnation(id)?;
        let keys = Keys::of(id);
        let mut conn = self.conn.clone();
        let deleted: u8 = self
            .scripts
            .delete
            .key(&keys.meta)
            .key(&keys.traj)
            .key(&keys.scores)
            .arg(&incarnation)
            .arg(CHANNEL)
            .arg(id)
            .invoke_async(&mut conn)
            .await
            .map_err(|e| self.fail("deleting", e))?;
        self.held.remove(id);
        if deleted == 0 {
            return Err(StoreError::Gone {
                task: id.to_string(),
            });
        }
        let _: i64 = conn
            .srem(TASKS, id)
            .await
            .map_err(|e| self.fail("deleting", e))?;
        Ok(())
    }

    async fn commit(
        &self,
        id: &str,
        base: Arc<Pool>,
        ops: Vec<PoolOp>,
        counters: Counters,
    ) -> Result<Committed, StoreError> {
        Ok(self.commit_ops(id, base, ops, counters).await?.0)
    }

    /// One script for the whole group; the script says which offers were re-sent ends, so
    /// each part gets its own.
    async fn commit_group(
        &self,
        id: &str,
        base: Arc<Pool>,
        parts: Vec<Vec<PoolOp>>,
        counters: Counters,
    ) -> Result<GroupCommitted, StoreError> {
        let lens: Vec<usize> = parts.iter().map(Vec::len).collect();
        let ops = parts.into_iter().flatten().collect();
        let (committed, decided) = self.commit_ops(id, base, ops, counters).await?;
        let mut at = 0;
        let resent = lens
            .iter()
            .map(|&n| {
                let part = decided.get(at..at + n).unwrap_or_default();
                at += n;
                part.iter().filter(|&&d| d == 2).count()
            })
            .collect();
        Ok(GroupCommitted {
            committed,
            resent: Some(resent),
        })
    }

    async fn save_counters(
        &self,
        id: &str,
        _pool: Arc<Pool>,
        counters: Counters,
    ) -> Result<(), StoreError> {
        match self.run_commit(id, &[], counters).await {
            Ok(_) | Err(StoreError::Gone { .. }) => Ok(()),
            Err(e) => Err(e),
        }
    }

    async fn load_pool(&self, id: &str) -> Result<Option<Pool>, StoreError> {
        Ok(self.load_task(id).await?.map(|t| t.pool))
    }

    fn changes(&self) -> Option<broadcast::Receiver<PoolChanged>> {
        Some(self.tx.subscribe())
    }

    fn is_shared(&self) -> bool {
        true
    }

    async fn load_task(&self, id: &str) -> Result<Option<StoredTask>, StoreError> {
        let Some((t, incarnation)) = self.read(id).await? else {
            return Ok(None);
        };
        let held = self.held.get(id).map(|h| h.incarnation.clone());
        if held.as_ref() != Some(&incarnation) {
            // A task new to this server: its counters so far are others' increments.
            self.held.insert(
                id.to_string(),
                Held {
                    incarnation,
                    written: t.counters,
                },
            );
        }
        Ok(Some(t))
    }

    async fn task_ids(&self) -> Result<Option<Vec<String>>, StoreError> {
        let mut keys: Vec<String> = self
            .conn
            .clone()
            .smembers(TASKS)
            .await
            .map_err(|e| self.fail("listing", e))?;
        keys.sort();
        Ok(Some(keys))
    }

    async fn reserve_task(
        &self,
        id: &str,
        tenant: &str,
        max: usize,
    ) -> Result<Option<bool>, StoreError> {
        let reserved = reserve_task(&mut self.conn.clone(), id, tenant, max).await;
        Ok(Some(
            reserved.map_err(|e| self.fail("reserving a task", e))?,
        ))
    }

    async fn sync_counters(
        &self,
        id: &str,
        counters: Counters,
    ) -> Result<Option<Counters>, StoreError> {
        if self.delta(id, counters) != Counters::default() {
            self.run_commit(id, &[], counters).await?;
        }
        let (incarnation, episodes, steps): (Option<String>, Option<u64>, Option<u64>) = self
            .conn
            .clone()
            .hmget(
                Keys::of(id).meta,
                &["incarnation", "episodes_completed", "steps_shaped"],
            )
            .await
            .map_err(|e| self.fail("reading the counters", e))?;
        // Deleted (or deleted and created again) on another server, and the notification
        // not here yet: gone, not a task with no counters (SPEC §10).
        if incarnation.as_deref() != Some(self.incarnation(id)?.as_str()) {
            return Err(StoreError::Gone {
                task: id.to_string(),
            });
        }
        let totals = Counters {
            episodes_completed: episodes.unwrap_or(0),
            steps_shaped: steps.unwrap_or(0),
        };
        // The caller takes the others' increments in: its counters are the totals now.
        self.wrote(id, totals);
        Ok(Some(totals))
    }

    async fn ended_episodes(&self, id: &str, client: &str) -> Result<Vec<(u32, u64)>, StoreError> {
        let incarnation = self.incarnation(id)?;
        let ended: HashMap<u32, u64> = self
            .conn
            .clone()
            .hgetall(Keys::ended(id, &incarnation, client))
            .await
            .map_err(|e| self.fail("reading the end record", e))?;
        Ok(ended.into_iter().collect())
    }
}
