//! Commits of pool changes through a task's commit path (the path of a Shape or Follow
//! stream's episode end and of `AddTrajectory`: the writer lock, planning, the group
//! commit, the store), side by side in one run: 1, 8 and 64 streams on ONE task and on
//! separate tasks (one each), for the memory store, a data dir and Redis (a
//! `redis-server` child, `appendfsync always`). Per configuration: changes per second,
//! commit latency p50/p99, store commits per change (a task's changes that wait while a
//! commit of it is in flight are committed together) and syncs per change (the data dir's
//! own count; Redis's `fdatasync`s counted by `strace` on a second, untimed
//! `redis-server`, when strace is installed).
//!
//! `cargo bench --bench commits` (a few seconds to a minute), `-- --quick` for a short
//! run, `-- --capacity N` for pools of N trajectories (default 20, SPEC §1.1's default).
//! Every stream commits 200-action episodes one after the other, each scoring higher than
//! every earlier one of its task, so every offer is a change (an insert, then a
//! replacement once the pool is full); the configurations are interleaved round by round,
//! so that all of them see the same noise of a shared machine. Data dirs (and Redis's
//! directories) go under `$TAMRM_BENCH_DIR` if set, else the system temp dir: put it on
//! the disk you want to measure (tmpfs makes every sync free).

use std::fs::File;
use std::net::TcpListener;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tamrm::core::{Pool, TaskConfig, TaskConfigInput};
use tamrm::limits::Limits;
use tamrm::registry::{Registry, DEFAULT_TENANT};
use tamrm::store::{
    Committed, Counters, DiskStore, GroupCommitted, MemoryStore, PoolChanged, PoolOp, RedisOptions,
    RedisStore, Store, StoreError, StoredTask,
};

#[path = "common/commits.rs"]
#[allow(dead_code)]
mod common;
use common::{episode, EPISODE_LEN};

const STREAMS: [usize; 3] = [1, 8, 64];

fn bench_dir() -> tempfile::TempDir {
    match std::env::var_os("TAMRM_BENCH_DIR") {
        Some(d) => tempfile::tempdir_in(d).expect("TAMRM_BENCH_DIR is writable"),
        None => tempfile::tempdir().expect("temp dir"),
    }
}

/// A store that counts the commits the registry makes (a group counts once).
struct Counted {
    inner: Arc<dyn Store>,
    commits: AtomicU64,
}

#[async_trait::async_trait]
impl Store for Counted {
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
        self.commits.fetch_add(1, Ordering::Relaxed);
        self.inner.commit(id, base, ops, counters).await
    }
    async fn commit_group(
        &self,
        id: &str,
        base: Arc<Pool>,
        parts: Vec<Vec<PoolOp>>,
        counters: Counters,
    ) -> Result<GroupCommitted, StoreError> {
        self.commits.fetch_add(1, Ordering::Relaxed);
        self.inner.commit_group(id, base, parts, counters).await
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

/// A `redis-server` child with `appendfsync always`, optionally under `strace` counting
/// its `fsync`/`fdatasync` calls into a file.
struct Redis {
    child: Child,
    port: u16,
    trace: Option<PathBuf>,
    _dir: tempfile::TempDir,
}

impl Redis {
    fn start(traced: bool) -> Option<Redis> {
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .ok()?
            .port();
        let dir = bench_dir();
        let trace = traced.then(|| dir.path().join("syncs.trace"));
        let mut cmd = match &trace {
            Some(file) => {
                let mut c = Command::new("strace");
                c.args([
                    "-f",
                    "-qq",
                    "--seccomp-bpf",
                    "-e",
                    "trace=fsync,fdatasync",
                    "-o",
                ])
                .arg(file)
                .arg("redis-server");
                c
            }
            None => Command::new("redis-server"),
        };
        let redis_dir = dir.path().join("redis");
        std::fs::create_dir_all(&redis_dir).ok()?;
        let child = cmd
            .args([
                "--port",
                &port.to_string(),
                "--bind",
                "127.0.0.1",
                "--save",
                "",
            ])
            .args(["--appendonly", "yes", "--appendfsync", "always"])
            .arg("--dir")
            .arg(&redis_dir)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .ok()?;
        let mut redis = Redis {
            child,
            port,
            trace,
            _dir: dir,
        };
        let deadline = Instant::now() + Duration::from_secs(20);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            if Instant::now() > deadline || redis.child.try_wait().ok().flatten().is_some() {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        Some(redis)
    }

    fn url(&self) -> String {
        format!("redis://127.0.0.1:{}", self.port)
    }
}

/// The `fsync`s and `fdatasync`s strace has written to `trace` so far.
fn traced_syncs(trace: &Path) -> Option<u64> {
    let text = std::fs::read_to_string(trace).ok()?;
    let calls = text
        .lines()
        .filter(|l| (l.contains("fdatasync(") || l.contains("fsync(")) && !l.contains("resumed>"))
        .count();
    Some(calls as u64)
}

impl Drop for Redis {
    /// Shuts the server down (killing `strace` would leave its tracee running).
    fn drop(&mut self) {
        use std::io::Write;
        if let Ok(mut conn) = std::net::TcpStream::connect(("127.0.0.1", self.port)) {
            let _ = conn.write_all(b"SHUTDOWN NOSAVE\r\n");
        }
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Backend {
    Memory,
    Disk,
    Redis,
}

impl Backend {
    fn name(self) -> &'static str {
        match self {
            Backend::Memory => "memory",
            Backend::Disk => "data dir",
            Backend::Redis => "Redis (appendfsync always)",
        }
    }
}

/// One configuration: a store, a number of streams, all on one task or one task each,
/// pools of `capacity`.
#[derive(Debug, Clone, Copy)]
struct Setup {
    backend: Backend,
    streams: usize,
    one_task: bool,
    capacity: u32,
}

impl Setup {
    fn tasks(&self) -> usize {
        if self.one_task {
            1
        } else {
            self.streams
        }
    }
}

/// One measured round of a configuration.
#[derive(Default)]
struct Round {
    changes: u64,
    wall: Duration,
    commits: u64,
    /// `None`: the store's syncs are not counted in this round.
    syncs: Option<u64>,
    latencies: Vec<Duration>,
}

/// The syncs a store has issued so far, if they are counted.
type SyncCount = Box<dyn Fn() -> Option<u64>>;

/// A fresh registry over the backend's store: the registry, the commit counter and the
/// syncs counted so far (the data dir's; the traced Redis's).
async fn open(
    backend: Backend,
    redis: Option<&Redis>,
    dir: &Path,
) -> (Registry, Arc<Counted>, SyncCount) {
    let (inner, syncs): (Arc<dyn Store>, SyncCount) = match backend {
        Backend::Memory => (Arc::new(MemoryStore::new()), Box::new(|| Some(0))),
        Backend::Disk => {
            let store = DiskStore::open(dir).expect("data dir");
            let counter = store.clone();
            (
                Arc::new(store),
                Box::new(move || Some(counter.sync_count())),
            )
        }
        Backend::Redis => {
            let redis = redis.expect("a redis-server");
            let store = RedisStore::open(&RedisOptions::new(redis.url()))
                .await
                .expect("Redis answers");
            let trace = redis.trace.clone();
            let count = move || traced_syncs(trace.as_deref()?);
            (Arc::new(store), Box::new(count))
        }
    };
    let counted = Arc::new(Counted {
        inner,
        commits: AtomicU64::new(0),
    });
    let (registry, _) = Registry::open(counted.clone(), Limits::default())
        .await
        .expect("registry");
    (registry, counted, syncs)
}

/// `total` changes from `setup.streams` streams (each commits its share one after the
/// other), on tasks named `tag`-i.
async fn round(
    setup: Setup,
    redis: Option<&Redis>,
    total: usize,
    tag: &str,
    count_syncs: bool,
) -> Round {
    let dir = bench_dir();
    let (registry, counted, syncs) = open(setup.backend, redis, dir.path()).await;
    let mut tasks = Vec::new();
    for i in 0..setup.tasks() {
        let id = format!("{tag}-{i}");
        let input = TaskConfigInput {
            num_actions: 4,
            pool_capacity: Some(setup.capacity),
            ..Default::default()
        };
        let t = registry
            .create(DEFAULT_TENANT, &id, &input, None)
            .await
            .expect("create");
        tasks.push(t);
    }
    let per = total / setup.streams;
    let (commits0, syncs0) = (counted.commits.load(Ordering::Relaxed), syncs());
    // Scores in planning order (taken under the task's writer lock): each offer beats
    // every trajectory of its pool, so each one is a change.
    let scores = Arc::new(AtomicU64::new(0));
    let t0 = Instant::now();
    let joins: Vec<_> = (0..setup.streams)
        .map(|s| {
            let task = tasks[if setup.one_task { 0 } else { s }].clone();
            let scores = scores.clone();
            tokio::spawn(async move {
                let mut lat = Vec::with_capacity(per);
                for _ in 0..per {
                    let t = Instant::now();
                    let w = task.writer().await.expect("writer");
                    let n = scores.fetch_add(1, Ordering::Relaxed);
                    let offer = PoolOp::Offer {
                        actions: episode(n as u32),
                        score: n as f64,
                        end: None,
                    };
                    let c = task.commit(w, vec![offer]).await.expect("commit");
                    lat.push(t.elapsed());
                    assert_eq!(c.changed, vec![true], "every offer is a change");
                }
                lat
            })
        })
        .collect();
    let mut latencies = Vec::with_capacity(total);
    for j in joins {
        latencies.extend(j.await.expect("stream"));
    }
    let wall = t0.elapsed();
    let changes: u64 = tasks.iter().map(|t| t.published_version()).sum();
    assert_eq!(
        changes,
        (per * setup.streams) as u64,
        "one version per change"
    );
    let commits = counted.commits.load(Ordering::Relaxed) - commits0;
    let syncs = match (count_syncs, syncs0, syncs()) {
        (true, Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    for i in 0..setup.tasks() {
        let _ = registry.delete(DEFAULT_TENANT, &format!("{tag}-{i}")).await;
    }
    Round {
        changes,
        wall,
        commits,
        syncs,
        latencies,
    }
}

/// The floor: one small append plus `fdatasync`, back to back.
fn fdatasync_floor(n: usize) -> Round {
    let dir = bench_dir();
    let f = File::create(dir.path().join("floor")).expect("floor file");
    let rec = [7u8; 1000];
    let mut latencies = Vec::with_capacity(n);
    let t0 = Instant::now();
    for i in 0..n {
        let t = Instant::now();
        f.write_all_at(&rec, (i * rec.len()) as u64).expect("write");
        f.sync_data().expect("fdatasync");
        latencies.push(t.elapsed());
    }
    Round {
        changes: n as u64,
        wall: t0.elapsed(),
        commits: n as u64,
        syncs: Some(n as u64),
        latencies,
    }
}

/// The results of one configuration over its rounds.
struct Row {
    name: String,
    streams: usize,
    tasks: String,
    per_sec: f64,
    p50_ms: f64,
    p99_ms: f64,
    commits_per_change: f64,
    syncs_per_change: Option<f64>,
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

fn summarise(
    name: &str,
    streams: usize,
    tasks: String,
    rounds: &[Round],
    synced: Option<&Round>,
) -> Row {
    let mut rates: Vec<f64> = rounds
        .iter()
        .map(|r| r.changes as f64 / r.wall.as_secs_f64())
        .collect();
    rates.sort_by(f64::total_cmp);
    let mut lat: Vec<f64> = rounds
        .iter()
        .flat_map(|r| r.latencies.iter().map(|d| d.as_secs_f64() * 1e3))
        .collect();
    lat.sort_by(f64::total_cmp);
    let (changes, commits) = rounds
        .iter()
        .fold((0, 0), |(c, k), r| (c + r.changes, k + r.commits));
    let counted: Vec<&Round> = match synced {
        Some(r) => vec![r],
        None => rounds.iter().filter(|r| r.syncs.is_some()).collect(),
    };
    let synced_changes: u64 = counted.iter().map(|r| r.changes).sum();
    let syncs: u64 = counted.iter().filter_map(|r| r.syncs).sum();
    Row {
        name: name.to_string(),
        streams,
        tasks,
        per_sec: quantile(&rates, 0.5),
        p50_ms: quantile(&lat, 0.5),
        p99_ms: quantile(&lat, 0.99),
        commits_per_change: commits as f64 / changes as f64,
        syncs_per_change: (!counted.is_empty() && synced_changes > 0)
            .then(|| syncs as f64 / synced_changes as f64),
    }
}

fn main() {
    // `cargo bench` passes `--bench`; `--quick` and `--capacity N` are the options.
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    let capacity: u32 = args
        .iter()
        .position(|a| a == "--capacity")
        .and_then(|i| args.get(i + 1))
        .map_or(20, |c| c.parse().expect("--capacity N"));
    let (rounds, total) = if quick { (2, 192) } else { (5, 960) };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let redis = Redis::start(false);
    let traced = redis.as_ref().and_then(|_| {
        let strace = Command::new("strace").arg("-V").output().is_ok();
        if strace {
            Redis::start(true)
        } else {
            None
        }
    });
    if redis.is_none() {
        eprintln!("redis-server is not on the PATH: the Redis rows are left out");
    } else if traced.is_none() {
        eprintln!("strace is not available: Redis's syncs are not counted");
    }
    let backends: Vec<Backend> = [Backend::Memory, Backend::Disk, Backend::Redis]
        .into_iter()
        .filter(|b| *b != Backend::Redis || redis.is_some())
        .collect();
    let mut setups = Vec::new();
    for &backend in &backends {
        for streams in STREAMS {
            for one_task in [true, false] {
                if streams > 1 || one_task {
                    setups.push(Setup {
                        backend,
                        streams,
                        one_task,
                        capacity,
                    });
                }
            }
        }
    }
    let mut results: Vec<Vec<Round>> = setups.iter().map(|_| Vec::new()).collect();
    let mut floor = Vec::new();
    for r in 0..rounds {
        floor.push(fdatasync_floor(total / 4));
        for (k, setup) in setups.iter().enumerate() {
            let tag = format!("r{r}c{k}");
            let done = rt.block_on(round(*setup, redis.as_ref(), total, &tag, true));
            results[k].push(done);
        }
    }
    // Redis's syncs, on the traced server: one untimed round per configuration.
    let mut redis_syncs: Vec<Option<Round>> = setups.iter().map(|_| None).collect();
    if let Some(traced) = &traced {
        for (k, setup) in setups.iter().enumerate() {
            if setup.backend == Backend::Redis {
                let tag = format!("traced-c{k}");
                let done = rt.block_on(round(*setup, Some(traced), total, &tag, true));
                redis_syncs[k] = Some(done).filter(|d| d.syncs.is_some());
            }
        }
    }
    let mut rows = vec![summarise(
        "fdatasync of a 1 KB append (floor)",
        1,
        "—".into(),
        &floor,
        None,
    )];
    for (k, setup) in setups.iter().enumerate() {
        let tasks = if setup.one_task {
            "one".to_string()
        } else {
            format!("{} (one each)", setup.tasks())
        };
        let synced = match setup.backend {
            Backend::Redis => redis_syncs[k].as_ref(),
            _ => None,
        };
        let mut row = summarise(
            setup.backend.name(),
            setup.streams,
            tasks,
            &results[k],
            synced,
        );
        if setup.backend == Backend::Redis && synced.is_none() {
            row.syncs_per_change = None;
        }
        rows.push(row);
    }
    println!(
        "pools of capacity {capacity}, episodes of {EPISODE_LEN} actions; {rounds} rounds of {total} changes per configuration (split over its streams); changes/s: median over rounds; latency: over every commit"
    );
    println!(
        "| store | streams | tasks | changes/s | commit p50 (ms) | commit p99 (ms) | store commits per change | syncs per change |\n|---|---:|---|---:|---:|---:|---:|---:|"
    );
    for r in &rows {
        let syncs = r
            .syncs_per_change
            .map_or("—".to_string(), |s| format!("{s:.3}"));
        println!(
            "| {} | {} | {} | {:.0} | {:.2} | {:.2} | {:.3} | {} |",
            r.name, r.streams, r.tasks, r.per_sec, r.p50_ms, r.p99_ms, r.commits_per_change, syncs
        );
    }
    for &backend in &backends {
        let find = |streams: usize, one: bool| {
            rows.iter()
                .zip(std::iter::once(None).chain(setups.iter().map(Some)))
                .find(|(_, s)| {
                    s.is_some_and(|s| {
                        s.backend == backend && s.streams == streams && s.one_task == one
                    })
                })
                .map(|(r, _)| r)
        };
        let (Some(one), Some(eight)) = (find(1, true), find(8, true)) else {
            continue;
        };
        let speedup = eight.per_sec / one.per_sec;
        let syncs = eight
            .syncs_per_change
            .map_or("not counted".to_string(), |s| {
                format!("{s:.2} syncs per change")
            });
        println!(
            "{}: 8 streams on one task: {syncs}, {speedup:.1}x the one-stream changes/s",
            backend.name()
        );
        if backend == Backend::Disk {
            let met = eight.syncs_per_change.is_some_and(|s| s <= 0.5) && speedup >= 3.0;
            println!(
                "target (data dir, 8 streams on one task: <= 0.5 syncs per change and >= 3x the one-stream changes/s): {}",
                if met { "met" } else { "not met" }
            );
        }
    }
}
