//! [`RedisStore`]: task configs and pools in Redis (or Valkey), shared by any number of
//! servers (SPEC §10). `docs/scaling.md` describes the layout, the guarantees and the
//! staleness bound.
//!
//! Layout, for a task key `K` (see [`crate::registry::task_key`]); every key of a task
//! carries the hash tag `{K}`, so a task lives in one Redis Cluster slot:
//! - `tamrm:{K}:meta`, a hash: `config` (JSON), `capacity`, `version`, `next_seq`,
//!   `incarnation` (names this creation of `K`, so that a server holding a deleted task
//!   never writes into a new task of the same id), `episodes_completed`, `steps_shaped`;
//! - `tamrm:{K}:traj`, a hash seq → the trajectory in the disk format's bytes (with seq 0:
//!   the field is its seq), and `tamrm:{K}:scores`, a hash seq → its score, for the update
//!   rule to read without decoding trajectories;
//! - `tamrm:{K}:ended:<incarnation>:<client>`, a hash env → episodes ended: the record of
//!   the no-double-commit rule of SPEC §9, expiring after `ended_ttl` without commits;
//! - `tamrm:tasks`, the set of every task key (the only key outside a task's slot; it is
//!   written before a creation and after a deletion, so a key in it may have no task,
//!   never the reverse).
//!
//! Every change is one Lua script, atomic in Redis: the §6 update decided against the
//! pool in Redis, the version bump, the counters, the end record and a `PUBLISH` on
//! `tamrm:changes`. Every server subscribes, and also polls the versions every
//! `poll_interval` as a backstop for notifications lost while disconnected.
//!
//! Redis Cluster (`redis-cluster://`): every script and every atomic read touches the keys
//! of one task only, so each runs on the node holding the task's slot; tasks spread over
//! the nodes by their hash tags. `tamrm:tasks` lives in the slot of its own name. Changes
//! are published with the classic `PUBLISH`, which a cluster delivers on every node, so a
//! server subscribes on any one node (the next seed node when that one fails).

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use dashmap::DashMap;
use futures::StreamExt;
use redis::aio::{ConnectionLike, ConnectionManager};
use redis::cluster_async::ClusterConnection;
use redis::{AsyncCommands, Cmd, Pipeline, RedisFuture, Script, Value};
use serde::{Deserialize, Serialize};
use tokio::sync::broadcast;

use super::disk::{decode_trajectory_bytes, encode_trajectory};
use super::{
    apply_ops, Committed, Counters, GroupCommitted, PoolChanged, PoolOp, Store, StoreError,
    StoredTask,
};
use crate::core::{Pool, TaskConfig, Trajectory};

/// The set of every task key.
const TASKS: &str = "tamrm:tasks";
/// The channel of pool changes and deletions.
const CHANNEL: &str = "tamrm:changes";
/// Version of the task's JSON config in Redis.
const CONFIG_FORMAT: u32 = 1;

/// Where the store's Redis is, parsed from its URL (the one place that knows the URL
/// forms; settings check a URL with [`RedisTarget::parse`] too).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RedisTarget {
    /// `redis://[[user]:password@]host:port[/db]`: one Redis (or Valkey) server.
    Node(String),
    /// `redis-cluster://[[user]:password@]host:port[,host:port...]`: the seed nodes of a
    /// Redis Cluster, each as a `redis://` URL with the credentials.
    Cluster(Vec<String>),
}

impl RedisTarget {
    /// Parses a store URL; errors name the problem and never show a password.
    pub fn parse(url: &str) -> Result<RedisTarget, String> {
        if url.starts_with("rediss://") || url.starts_with("rediss-cluster://") {
            return Err(
                "TLS to Redis (rediss://) is not supported by this build; use redis:// or redis-cluster:// on a private network or through a TLS tunnel (docs/scaling.md)".into(),
            );
        }
        if let Some(rest) = url.strip_prefix("redis://") {
            if rest.is_empty() || rest.starts_with('/') {
                return Err("redis:// needs a host: redis://HOST:PORT[/DB]".into());
            }
            return Ok(RedisTarget::Node(url.to_string()));
        }
        let Some(rest) = url.strip_prefix("redis-cluster://") else {
            return Err(format!(
                "expected a redis:// or redis-cluster:// URL, got {:?}",
                redact(url)
            ));
        };
        let (credentials, hosts) = match rest.rfind('@') {
            Some(at) => rest.split_at(at + 1),
            None => ("", rest),
        };
        let hosts = hosts.strip_suffix('/').unwrap_or(hosts);
        if hosts.contains('/') || hosts.contains('?') {
            return Err(
                "redis-cluster:// takes HOST:PORT[,HOST:PORT...] only: a Redis Cluster has database 0 only and no options here".into(),
            );
        }
        let nodes = hosts
            .split(',')
            .map(|node| {
                let port = node.rsplit_once(':').map(|(host, port)| (host, port.parse::<u16>()));
                match port {
                    Some((host, Ok(_))) if !host.is_empty() => {
                        Ok(format!("redis://{credentials}{node}"))
                    }
                    _ => Err(format!(
                        "redis-cluster://: {node:?} is not HOST:PORT (give every seed node with its port, separated by commas)"
                    )),
                }
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(RedisTarget::Cluster(nodes))
    }
}

/// A connection to one server or to a cluster; both multiplex requests and reconnect by
/// themselves.
#[derive(Clone)]
enum Conn {
    Node(ConnectionManager),
    Cluster(ClusterConnection),
}

impl ConnectionLike for Conn {
    fn req_packed_command<'a>(&'a mut self, cmd: &'a Cmd) -> RedisFuture<'a, Value> {
        match self {
            Conn::Node(c) => c.req_packed_command(cmd),
            Conn::Cluster(c) => c.req_packed_command(cmd),
        }
    }

    fn req_packed_commands<'a>(
        &'a mut self,
        pipeline: &'a Pipeline,
        offset: usize,
        count: usize,
    ) -> RedisFuture<'a, Vec<Value>> {
        match self {
            Conn::Node(c) => c.req_packed_commands(pipeline, offset, count),
            Conn::Cluster(c) => c.req_packed_commands(pipeline, offset, count),
        }
    }

    fn get_db(&self) -> i64 {
        match self {
            Conn::Node(c) => c.get_db(),
            Conn::Cluster(c) => c.get_db(),
        }
    }
}

/// How to reach Redis and how fresh snapshots are kept.
#[derive(Debug, Clone)]
pub struct RedisOptions {
    /// `redis://[[user]:password@]host:port[/db]`, or
    /// `redis-cluster://[[user]:password@]host:port[,host:port...]` (see [`RedisTarget`]).
    pub url: String,
    /// Every server reads every task's version this often, as a backstop for lost
    /// notifications: the bound on how stale a snapshot can be while notifications are
    /// lost (they normally arrive within a round trip).
    pub poll_interval: Duration,
    /// How long the no-double-commit record of a client is kept after its last commit.
    pub ended_ttl: Duration,
}

impl RedisOptions {
    /// `url` with the defaults: a 1 s poll, a 24 h end record.
    pub fn new(url: impl Into<String>) -> RedisOptions {
        RedisOptions {
            url: url.into(),
            poll_interval: Duration::from_secs(1),
            ended_ttl: Duration::from_secs(24 * 3600),
        }
    }
}

/// The JSON of `meta.config`.
#[derive(Serialize, Deserialize)]
struct ConfigJson {
    format: u32,
    config: TaskConfig,
}

/// Creates the task unless one exists; answers {created, config, incarnation}.
const CREATE: &str = r#"
local existing = redis.call('HGET', KEYS[1], 'config')
if existing then
  return {0, existing, redis.call('HGET', KEYS[1], 'incarnation')}
end
redis.call('DEL', KEYS[2], KEYS[3])
redis.call('HSET', KEYS[1], 'config', ARGV[1], 'capacity', ARGV[2], 'version', 0,
  'next_seq', 1, 'incarnation', ARGV[3], 'episodes_completed', 0, 'steps_shaped', 0)
return {1, ARGV[1], ARGV[3]}
"#;

/// Deletes the task if it is the incarnation named; answers 1, or 0 if it is gone.
const DELETE: &str = r#"
if redis.call('HGET', KEYS[1], 'incarnation') ~= ARGV[1] then return 0 end
redis.call('DEL', KEYS[1], KEYS[2], KEYS[3])
redis.call('PUBLISH', ARGV[2], 'deleted ' .. ARGV[1] .. ' ' .. ARGV[3])
return 1
"#;

/// The §6 update of a commit (of one request, or of a group of them: their operations
/// one after the other), atomically. KEYS: meta, traj, scores, then the end record of
/// each client whose episode ends the commit carries (a group may carry several
/// clients'). ARGV: incarnation, channel, task key, Δepisodes, Δsteps, end-record TTL
/// (s), number of ops, then per op: kind ('offer' / 'reset'), score, trajectory bytes,
/// env, episodes ended with this one (the episode's number + 1, saturating), and which of
/// the end records it goes to (1-based among them; env, count and record are '' for no
/// end record). Answers {1, version before, version after, next_seq before, per op 1
/// changed / 0 not / 2 a re-sent end}, or {0} if the task is gone. Episode counts are
/// u64 in decimal, compared as such (`at_least`): Lua's numbers are doubles, exact only
/// below 2^53.
const COMMIT: &str = r#"
local function at_least(a, b)
  if #a ~= #b then return #a > #b end
  return a >= b
end
if redis.call('HGET', KEYS[1], 'incarnation') ~= ARGV[1] then return {0} end
local m = redis.call('HMGET', KEYS[1], 'capacity', 'version', 'next_seq')
local cap, version, next_seq = tonumber(m[1]), tonumber(m[2]), tonumber(m[3])
local before, seq_before = version, next_seq
local out = {1, before, 0, seq_before}
local marked = {}
local resent = 0
local i = 8
for op = 1, tonumber(ARGV[7]) do
  local kind = ARGV[i]
  local changed = 0
  if kind == 'reset' then
    redis.call('DEL', KEYS[2], KEYS[3])
    version = version + 1
    changed = 1
  else
    local score, env, count = tonumber(ARGV[i + 1]), ARGV[i + 3], ARGV[i + 4]
    local record = nil
    if env ~= '' then record = 3 + tonumber(ARGV[i + 5]) end
    local dup = false
    if record then
      local n = redis.call('HGET', KEYS[record], env)
      dup = n ~= false and at_least(n, count)
    end
    if dup then
      changed = 2
      resent = resent + 1
    else
      local size = redis.call('HLEN', KEYS[3])
      local replaces = nil
      local insert = size < cap
      if not insert then
        local all = redis.call('HGETALL', KEYS[3])
        local worst, worst_seq = nil, nil
        for j = 1, #all, 2 do
          local s, q = tonumber(all[j + 1]), tonumber(all[j])
          if worst == nil or s < worst or (s == worst and q < worst_seq) then
            worst, worst_seq = s, q
          end
        end
        if score > worst then
          insert, replaces = true, worst_seq
        end
      end
      if insert then
        if replaces then
          redis.call('HDEL', KEYS[2], replaces)
          redis.call('HDEL', KEYS[3], replaces)
        end
        redis.call('HSET', KEYS[2], next_seq, ARGV[i + 2])
        redis.call('HSET', KEYS[3], next_seq, ARGV[i + 1])
        next_seq = next_seq + 1
        version = version + 1
        changed = 1
      end
      if record then
        redis.call('HSET', KEYS[record], env, count)
        marked[record] = true
      end
    end
  end
  out[#out + 1] = changed
  i = i + 6
end
redis.call('HSET', KEYS[1], 'version', version, 'next_seq', next_seq)
-- Δepisodes counted the re-sent ends too: they are not episodes completed.
redis.call('HINCRBY', KEYS[1], 'episodes_completed', math.max(0, tonumber(ARGV[4]) - resent))
redis.call('HINCRBY', KEYS[1], 'steps_shaped', ARGV[5])
for record in pairs(marked) do redis.call('EXPIRE', KEYS[record], ARGV[6]) end
if version ~= before then
  redis.call('PUBLISH', ARGV[2], version .. ' ' .. ARGV[1] .. ' ' .. ARGV[3])
end
out[3] = version
return out
"#;

/// The keys of one task.
struct Keys {
    meta: String,
    traj: String,
    scores: String,
}

impl Keys {
    fn of(task: &str) -> Keys {
        Keys {
            meta: format!("tamrm:{{{task}}}:meta"),
            traj: format!("tamrm:{{{task}}}:traj"),
            scores: format!("tamrm:{{{task}}}:scores"),
        }
    }

    fn ended(task: &str, incarnation: &str, client: &str) -> String {
        format!("tamrm:{{{task}}}:ended:{incarnation}:{client}")
    }
}

/// What this server knows of a task it holds: which creation, and the counters it last
/// added to Redis (commits send the increments since).
#[derive(Debug, Clone)]
struct Held {
    incarnation: String,
    written: Counters,
}

/// Task configs and pools in Redis; see the module documentation.
pub struct RedisStore {
    what: String,
    conn: Conn,
    create: Script,
    delete: Script,
    commit: Script,
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

/// `url` without its password, for logs and errors.
fn redact(url: &str) -> String {
    match (url.find("://"), url.rfind('@')) {
        (Some(s), Some(at)) if at > s => format!("{}://***@{}", &url[..s], &url[at + 1..]),
        _ => url.to_string(),
    }
}

/// The COMMIT script's answer (see [`RedisStore::run_commit`]).
struct CommitAnswer {
    before: u64,
    after: u64,
    seq_before: u64,
    /// Per offer: 1 stored, 0 not stored, 2 a re-sent end.
    decided: Vec<u64>,
    /// The offers that were re-sent ends (2 in `decided`).
    resent: usize,
}

impl RedisStore {
    /// Connects (failing if Redis does not answer) and starts following changes.
    pub async fn open(options: &RedisOptions) -> Result<RedisStore, StoreError> {
        let what = format!("redis {}", redact(&options.url));
        let bad_url = |message: String| StoreError::Io {
            path: what.clone().into(),
            message,
        };
        let open_client = |url: &str| {
            redis::Client::open(url).map_err(|e| bad_url(format!("not a Redis URL: {e}")))
        };
        let (connect, timeout) = (Duration::from_secs(5), Duration::from_secs(10));
        let (mut conn, subscribers) = match RedisTarget::parse(&options.url).map_err(bad_url)? {
            RedisTarget::Node(url) => {
                let client = open_client(&url)?;
                let config = redis::aio::ConnectionManagerConfig::new()
                    .set_connection_timeout(Some(connect))
                    .set_response_timeout(Some(timeout))
                    .set_max_delay(Duration::from_secs(2));
                let conn = client
                    .get_connection_manager_with_config(config)
                    .await
                    .map_err(|e| unavailable(&what, "connecting", e))?;
                (Conn::Node(conn), vec![client])
            }
            RedisTarget::Cluster(nodes) => {
                let conn = redis::cluster::ClusterClientBuilder::new(nodes.clone())
                    .connection_timeout(connect)
                    .response_timeout(timeout)
                    .build()
                    .map_err(|e| bad_url(format!("not a Redis Cluster URL: {e}")))?
                    .get_async_connection()
                    .await
                    .map_err(|e| unavailable(&what, "connecting", e))?;
                let subscribers = nodes
                    .iter()
                    .map(|n| open_client(n))
                    .collect::<Result<Vec<_>, _>>()?;
                (Conn::Cluster(conn), subscribers)
            }
        };
        let _: Value = redis::cmd("PING")
            .query_async(&mut conn)
            .await
            .map_err(|e| unavailable(&what, "connecting", e))?;
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
            create: Script::new(CREATE),
            delete: Script::new(DELETE),
            commit: Script::new(COMMIT),
            held,
            ended_ttl: options.ended_ttl,
            tx,
            watcher,
        })
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
        let keys = Keys::of(task);
        // The clients whose end records the commit touches, in order of first mention (a
        // group commit carries the ends of every writer in it).
        let mut clients: Vec<&Arc<str>> = Vec::new();
        for op in ops {
            if let PoolOp::Offer { end: Some(e), .. } = op {
                if !clients.contains(&&e.client) {
                    clients.push(&e.client);
                }
            }
        }
        let delta = self.delta(task, counters);
        let mut inv = self.commit.prepare_invoke();
        inv.key(&keys.meta).key(&keys.traj).key(&keys.scores);
        for client in &clients {
            inv.key(Keys::ended(task, &incarnation, client));
        }
        inv.arg(&incarnation)
            .arg(CHANNEL)
            .arg(task)
            .arg(delta.episodes_completed)
            .arg(delta.steps_shaped)
            .arg(self.ended_ttl.as_secs().max(1))
            .arg(ops.len());
        for op in ops {
            match op {
                PoolOp::Reset => {
                    inv.arg("reset").arg("").arg("").arg("").arg("").arg("");
                }
                PoolOp::Offer {
                    actions,
                    score,
                    end,
                } => {
                    let bytes = encode_trajectory(&Trajectory {
                        actions: actions.clone(),
                        score: *score,
                        seq: 0,
                    });
                    let (env, count, record) = match end {
                        Some(e) => {
                            let record =
                                clients.iter().position(|c| **c == e.client).unwrap_or(0) + 1;
                            (
                                e.env.to_string(),
                                e.episode.saturating_add(1).to_string(),
                                record.to_string(),
                            )
                        }
                        None => (String::new(), String::new(), String::new()),
                    };
                    inv.arg("offer")
                        .arg(score_text(*score))
                        .arg(bytes)
                        .arg(env)
                        .arg(count)
                        .arg(record);
                }
            }
        }
        let out: Vec<u64> = inv
            .invoke_async(&mut self.conn.clone())
            .await
            .map_err(|e| self.fail("committing", e))?;
        let answer = match out.as_slice() {
            [1, before, after, seq_before, decided @ ..] => CommitAnswer {
                before: *before,
                after: *after,
                seq_before: *seq_before,
                resent: decided.iter().filter(|&&c| c == 2).count(),
                decided: decided.to_vec(),
            },
            _ => {
                self.held.remove(task);
                return Err(StoreError::Gone {
                    task: task.to_string(),
                });
            }
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

/// A score as Lua reads it back exactly (shortest round-trip digits).
fn score_text(score: f64) -> String {
    format!("{score:e}")
}

fn unavailable(what: &str, doing: &str, e: redis::RedisError) -> StoreError {
    let message = e.to_string();
    let down = matches!(
        e.kind(),
        redis::ErrorKind::ClusterConnectionNotFound
            | redis::ErrorKind::Server(
                redis::ServerErrorKind::ClusterDown
                    | redis::ServerErrorKind::TryAgain
                    | redis::ServerErrorKind::MasterDown
                    | redis::ServerErrorKind::BusyLoading
            )
    );
    if down
        || e.is_io_error()
        || e.is_connection_refusal()
        || e.is_timeout()
        || e.is_connection_dropped()
    {
        StoreError::Unavailable {
            what: format!("{what} ({doing})"),
            message,
        }
    } else {
        StoreError::Io {
            path: what.into(),
            message: format!("{doing}: {message}"),
        }
    }
}

fn field<'a>(meta: &'a HashMap<String, Vec<u8>>, name: &str) -> Result<&'a [u8], String> {
    meta.get(name)
        .map(Vec::as_slice)
        .ok_or_else(|| format!("field {name:?} is missing"))
}

fn number(meta: &HashMap<String, Vec<u8>>, name: &str) -> Result<u64, String> {
    std::str::from_utf8(field(meta, name)?)
        .ok()
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| format!("field {name:?} is not a number"))
}

/// A task from its meta hash and trajectories, checked as the disk store checks files.
fn decode_task(
    task: &str,
    meta: &HashMap<String, Vec<u8>>,
    traj: HashMap<u64, Vec<u8>>,
) -> Result<StoredTask, String> {
    let json: ConfigJson = serde_json::from_slice(field(meta, "config")?)
        .map_err(|e| format!("field \"config\": {e}"))?;
    if json.format != CONFIG_FORMAT {
        return Err(format!(
            "config format {} is not supported by this build (format {CONFIG_FORMAT})",
            json.format
        ));
    }
    let config = json.config;
    config
        .check()
        .map_err(|e| format!("field \"config\": config.{}: {}", e.field, e.message))?;
    let trajectories = traj
        .into_iter()
        .map(|(seq, bytes)| {
            decode_trajectory_bytes(&bytes, &config)
                .map(|t| Trajectory { seq, ..t })
                .map_err(|e| format!("trajectory {seq}: {e}"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let pool = Pool::restore(
        config.pool_capacity as usize,
        trajectories,
        number(meta, "version")?,
        number(meta, "next_seq")?,
    )?;
    Ok(StoredTask {
        id: task.to_string(),
        config,
        pool,
        counters: Counters {
            episodes_completed: number(meta, "episodes_completed")?,
            steps_shaped: number(meta, "steps_shaped")?,
        },
    })
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
        let json = serde_json::to_string(&ConfigJson {
            format: CONFIG_FORMAT,
            config: *config,
        })
        .map_err(|e| StoreError::new(&self.what, e))?;
        let (created, stored, incarnation): (u8, Vec<u8>, String) = self
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
        let existing: ConfigJson = serde_json::from_slice(&stored).map_err(|e| StoreError::Io {
            path: format!("{} key {}", self.what, keys.meta).into(),
            message: format!("field \"config\": {e}"),
        })?;
        Ok(Some(existing.config))
    }

    async fn delete_task(&self, id: &str) -> Result<(), StoreError> {
        let incarnation = self.incarnation(id)?;
        let keys = Keys::of(id);
        let mut conn = self.conn.clone();
        let deleted: u8 = self
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

/// Follows `tamrm:changes` (subscribed on one of `subscribers`, the next one when it
/// fails) and polls every held task's version each `poll`, announcing on `tx` every newer
/// version and every deletion of a held incarnation.
async fn watch(
    subscribers: Vec<redis::Client>,
    mut conn: Conn,
    held: Arc<DashMap<String, Held>>,
    tx: broadcast::Sender<PoolChanged>,
    poll: Duration,
) {
    let mut messages = None;
    let mut next = 0;
    let mut tick = tokio::time::interval(poll);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        if messages.is_none() {
            messages = subscribe(&subscribers, &mut next).await;
        }
        let message = async {
            match messages.as_mut() {
                Some(m) => m.next().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            m = message => match m {
                Some(m) => announce(&held, &tx, m.get_payload_bytes()),
                None => messages = None,
            },
            _ = tick.tick() => {
                if let Err(e) = poll_versions(&mut conn, &held, &tx).await {
                    tracing::warn!(error = %e, "could not poll pool versions in Redis");
                }
                if messages.is_none() {
                    messages = subscribe(&subscribers, &mut next).await;
                }
            }
        }
    }
}

/// Subscribes on `subscribers[*next]`, moving `next` on to the following one if that
/// fails (a cluster delivers every `PUBLISH` on every node).
async fn subscribe(
    subscribers: &[redis::Client],
    next: &mut usize,
) -> Option<redis::aio::PubSubStream> {
    let client = subscribers.get(*next % subscribers.len().max(1))?;
    let subscribed = async {
        let mut pubsub = client.get_async_pubsub().await?;
        pubsub.subscribe(CHANNEL).await?;
        Ok::<_, redis::RedisError>(pubsub.into_on_message())
    };
    match subscribed.await {
        Ok(stream) => Some(stream),
        Err(e) => {
            tracing::warn!(error = %e, "could not subscribe to Redis notifications");
            *next = next.wrapping_add(1);
            None
        }
    }
}

/// Parses `<version|deleted> <incarnation> <task>` and announces it if it concerns a held
/// incarnation.
fn announce(held: &DashMap<String, Held>, tx: &broadcast::Sender<PoolChanged>, payload: &[u8]) {
    let text = String::from_utf8_lossy(payload);
    let mut parts = text.splitn(3, ' ');
    let (Some(what), Some(incarnation), Some(task)) = (parts.next(), parts.next(), parts.next())
    else {
        return;
    };
    let Some(ours) = held.get(task).map(|h| h.incarnation.clone()) else {
        return;
    };
    if what == "deleted" {
        if ours == incarnation {
            held.remove(task);
            let _ = tx.send(deleted(task));
        }
    } else if ours != incarnation {
        // A new task of the same id: the one this server holds was deleted.
        held.remove(task);
        let _ = tx.send(deleted(task));
    } else if let Ok(version) = what.parse() {
        let _ = tx.send(PoolChanged {
            task: task.to_string(),
            version,
            deleted: false,
        });
    }
}

fn deleted(task: &str) -> PoolChanged {
    PoolChanged {
        task: task.to_string(),
        version: 0,
        deleted: true,
    }
}

/// The versions and incarnations of every held task, requested all at once (one round
/// trip on one server; one per node holding them on a cluster, where a pipeline cannot
/// span slots).
async fn poll_versions(
    conn: &mut Conn,
    held: &DashMap<String, Held>,
    tx: &broadcast::Sender<PoolChanged>,
) -> Result<(), redis::RedisError> {
    let tasks: Vec<(String, String)> = held
        .iter()
        .map(|h| (h.key().clone(), h.incarnation.clone()))
        .collect();
    let rows = futures::future::join_all(tasks.iter().map(|(task, _)| {
        let mut conn = conn.clone();
        async move {
            redis::cmd("HMGET")
                .arg(Keys::of(task).meta)
                .arg("version")
                .arg("incarnation")
                .query_async::<(Option<u64>, Option<String>)>(&mut conn)
                .await
        }
    }))
    .await;
    for ((task, ours), row) in tasks.iter().zip(rows) {
        match row? {
            (Some(version), Some(inc)) if &inc == ours => {
                let _ = tx.send(PoolChanged {
                    task: task.clone(),
                    version,
                    deleted: false,
                });
            }
            _ => {
                held.remove(task);
                let _ = tx.send(deleted(task));
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn passwords_are_not_shown() {
        assert_eq!(redact("redis://:s3cret@h:6379/0"), "redis://***@h:6379/0");
        assert_eq!(redact("redis://h:6379"), "redis://h:6379");
    }

    #[test]
    fn store_urls_name_one_server_or_the_seed_nodes_of_a_cluster() {
        assert_eq!(
            RedisTarget::parse("redis://:pw@h:6379/2"),
            Ok(RedisTarget::Node("redis://:pw@h:6379/2".into()))
        );
        assert_eq!(
            RedisTarget::parse("redis-cluster://u:pw@a:7000,b:7001/"),
            Ok(RedisTarget::Cluster(vec![
                "redis://u:pw@a:7000".into(),
                "redis://u:pw@b:7001".into()
            ]))
        );
        assert_eq!(
            RedisTarget::parse("redis-cluster://[::1]:7000"),
            Ok(RedisTarget::Cluster(vec!["redis://[::1]:7000".into()]))
        );
        for bad in [
            "redis://",
            "redis-cluster://",
            "redis-cluster://a:7000,,b:7001",
            "redis-cluster://a",
            "redis-cluster://a:port",
            "redis-cluster://:7000",
            "redis-cluster://a:7000/3",
            "redis-cluster://a:7000?x=1",
            "rediss://h:1",
            "http://:pw@h:1",
        ] {
            let e = RedisTarget::parse(bad).unwrap_err();
            assert!(!e.contains("pw"), "{bad}: {e}");
        }
    }

    #[test]
    fn scores_are_written_as_lua_reads_them_back() {
        for s in [0.1, -0.0, 1e-300, f64::MAX, -123.456, 5e-324] {
            let text = score_text(s);
            assert_eq!(
                text.parse::<f64>().unwrap().to_bits(),
                s.to_bits(),
                "{text}"
            );
        }
    }

    #[test]
    fn keys_of_a_task_share_its_hash_tag() {
        let k = Keys::of("acme@cart");
        for key in [
            &k.meta,
            &k.traj,
            &k.scores,
            &Keys::ended("acme@cart", "i", "c"),
        ] {
            assert!(key.contains("{acme@cart}"), "{key}");
        }
    }
}
