//! Durable commits: pool changes per second and syncs per change of the disk store, with
//! 1 and with 8 streams (tasks) committing at once, against the previous commit path
//! (re-enacted: its file steps, four syncs per change) and the disk's fdatasync latency.
//!
//! `cargo bench --bench commits` prints a table (medians over rounds). The data dirs are
//! created under `$TAMRM_BENCH_DIR` if set, else the system temp dir: put it on the disk
//! you want to measure (tmpfs makes every sync free).

use std::fs::{self, File};
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tamrm::store::{DiskStore, Store};

#[path = "common/commits.rs"]
mod common;
use common::{commit_episodes, config, EPISODE_LEN};

const ROUNDS: usize = 5;

fn bench_dir() -> tempfile::TempDir {
    match std::env::var_os("TAMRM_BENCH_DIR") {
        Some(d) => tempfile::tempdir_in(d).expect("TAMRM_BENCH_DIR is writable"),
        None => tempfile::tempdir().expect("temp dir"),
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// One measured round: changes, wall time, syncs, every commit's latency.
struct Round {
    changes: u64,
    wall: Duration,
    syncs: u64,
    latencies: Vec<Duration>,
}

/// The results of one configuration over its rounds.
struct Row {
    name: String,
    streams: usize,
    per_sec: f64,
    latency_ms: f64,
    syncs_per_change: f64,
}

fn summarise(name: &str, streams: usize, rounds: Vec<Round>) -> Row {
    let mut rates: Vec<f64> = rounds
        .iter()
        .map(|r| r.changes as f64 / r.wall.as_secs_f64())
        .collect();
    let mut lat: Vec<f64> = rounds
        .iter()
        .flat_map(|r| r.latencies.iter().map(|d| d.as_secs_f64() * 1e3))
        .collect();
    let (syncs, changes) = rounds
        .iter()
        .fold((0, 0), |(s, c), r| (s + r.syncs, c + r.changes));
    Row {
        name: name.to_string(),
        streams,
        per_sec: median(&mut rates),
        latency_ms: median(&mut lat),
        syncs_per_change: syncs as f64 / changes as f64,
    }
}

/// The group-commit store: `streams` tasks, each with its own committer, `per_stream`
/// changes each (every offer scores higher than the last, so every commit changes the
/// pool).
async fn new_path(streams: usize, per_stream: u32) -> Round {
    let dir = bench_dir();
    let store = DiskStore::open(dir.path()).expect("open");
    store.load().await.expect("load");
    for s in 0..streams {
        store
            .create_task(&format!("t{s}"), &config())
            .await
            .expect("create");
    }
    let before = store.commit_stats();
    let t0 = Instant::now();
    let mut joins = Vec::new();
    for s in 0..streams {
        let store: Arc<dyn Store> = Arc::new(store.clone());
        joins.push(tokio::spawn(commit_episodes(
            store,
            format!("t{s}"),
            per_stream,
        )));
    }
    let mut latencies = Vec::new();
    for j in joins {
        latencies.extend(j.await.expect("committer"));
    }
    let wall = t0.elapsed();
    let after = store.commit_stats();
    Round {
        changes: after.changes - before.changes,
        wall,
        syncs: after.syncs - before.syncs,
        latencies,
    }
}

/// The previous commit path's file steps for one inserted trajectory: the trajectory
/// file written and fsynced, `traj/` fsynced, `pool.json` written to a temporary file,
/// fsynced, renamed, the task directory fsynced.
fn old_commit(task: &Path, seq: u64, traj: &[u8], pool_json: &[u8]) -> std::io::Result<()> {
    let mut f = File::create(task.join("traj").join(format!("{seq:020}.traj")))?;
    f.write_all(traj)?;
    f.sync_all()?;
    File::open(task.join("traj"))?.sync_all()?;
    let tmp = task.join("pool.json.tmp");
    let mut f = File::create(&tmp)?;
    f.write_all(pool_json)?;
    f.sync_all()?;
    fs::rename(&tmp, task.join("pool.json"))?;
    File::open(task)?.sync_all()
}

/// The previous path, `streams` threads each on its own task directory.
fn old_path(streams: usize, per_stream: u32) -> Round {
    let dir = bench_dir();
    let t0 = Instant::now();
    let threads: Vec<_> = (0..streams)
        .map(|s| {
            let task: PathBuf = dir.path().join(format!("t{s}"));
            std::thread::spawn(move || {
                fs::create_dir_all(task.join("traj")).expect("task dir");
                // Sizes as the store writes them: 4 bytes per action plus a 48-byte
                // frame; pool.json grows by a seq per trajectory.
                let traj = vec![0u8; 4 * EPISODE_LEN as usize + 48];
                let mut lat = Vec::with_capacity(per_stream as usize);
                for i in 0..per_stream {
                    let seqs: Vec<String> = (1..=u64::from(i) + 1).map(|s| s.to_string()).collect();
                    let json = format!(
                        "{{\"format\": 1, \"pool_version\": {}, \"next_seq\": {}, \"seqs\": [{}], \"episodes_completed\": 0, \"steps_shaped\": 0}}",
                        i + 1,
                        i + 2,
                        seqs.join(", ")
                    );
                    let t = Instant::now();
                    old_commit(&task, u64::from(i) + 1, &traj, json.as_bytes()).expect("old commit");
                    lat.push(t.elapsed());
                }
                lat
            })
        })
        .collect();
    let mut latencies = Vec::new();
    for t in threads {
        latencies.extend(t.join().expect("thread"));
    }
    let wall = t0.elapsed();
    let changes = latencies.len() as u64;
    Round {
        changes,
        wall,
        syncs: 4 * changes,
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
        syncs: n as u64,
        latencies,
    }
}

fn main() {
    // `cargo bench` passes `--bench`; nothing else is understood.
    let quick = std::env::args().any(|a| a == "--quick");
    let (one, eight) = if quick { (40, 20) } else { (200, 100) };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    // Rounds interleave the configurations, so that all of them see the same noise of a
    // shared disk.
    let mut rounds: Vec<Vec<Round>> = (0..5).map(|_| Vec::new()).collect();
    for _ in 0..ROUNDS {
        rounds[0].push(fdatasync_floor(one as usize));
        for (k, (streams, per)) in [(1usize, one), (8, eight)].into_iter().enumerate() {
            rounds[1 + 2 * k].push(old_path(streams, per));
            rounds[2 + 2 * k].push(rt.block_on(new_path(streams, per)));
        }
    }
    let names = [
        ("fdatasync of a 1 KB append (floor)", 1),
        ("previous path (4 fsyncs per change)", 1),
        ("commit log, group commit", 1),
        ("previous path (4 fsyncs per change)", 8),
        ("commit log, group commit", 8),
    ];
    let rows: Vec<Row> = names
        .iter()
        .zip(rounds)
        .map(|(&(name, streams), r)| summarise(name, streams, r))
        .collect();
    println!(
        "episodes of {EPISODE_LEN} actions; {ROUNDS} rounds of {one} changes (1 stream) / 8 x {eight} (8 streams); medians"
    );
    println!(
        "| path | streams | changes/s | commit latency (ms) | syncs per change |\n|---|---:|---:|---:|---:|"
    );
    for r in &rows {
        println!(
            "| {} | {} | {:.0} | {:.2} | {:.3} |",
            r.name, r.streams, r.per_sec, r.latency_ms, r.syncs_per_change
        );
    }
    for streams in [1, 8] {
        let find = |prefix: &str| {
            rows.iter()
                .find(|r| r.streams == streams && r.name.starts_with(prefix))
                .map(|r| r.per_sec)
                .unwrap_or(f64::NAN)
        };
        println!(
            "{streams} stream(s): commit log / previous path = {:.1}x changes per second",
            find("commit log") / find("previous")
        );
    }
}
