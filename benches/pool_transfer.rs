//! `tamrm pool export` and `tamrm pool import` of a large pool (docs/benchmarks.md, "Pool
//! export and import").
//!
//! `cargo bench --bench pool_transfer` starts the real `tamrm` binary (`TAMRM_BIN`,
//! default `target/release/tamrm`; build it first) twice, fills one task of the first with
//! `--trajectories N` (default 100 000) trajectories of `--actions L` (default 100)
//! discrete actions by AddTrajectory (256 in flight), then times, as a user runs them,
//! the command-line processes from spawn to exit:
//!
//! - **export**: `tamrm pool export bench -o FILE` from the first server;
//! - **import**: `tamrm pool import FILE` into the second (a new task: CreateTask, then
//!   one AddTrajectory per trajectory, in order, each checked).
//!
//! `--store memory|data-dir` (default `memory`) picks where the second server keeps the
//! pool: with `data-dir` every AddTrajectory of the import waits for its commit to be
//! synced. `--import-max M` imports only when N ≤ M (default 100 000): each AddTrajectory
//! costs the server time in proportion to the pool's size, so an import of a large pool
//! takes minutes (docs/benchmarks.md). One markdown row per run: N, L, the file's size,
//! export and import seconds and trajectories per second.

use std::process::Command;
use std::time::Instant;

use futures::StreamExt;
use tamrm::proto;

#[path = "common/server.rs"]
mod server;
use server::{arg, arg_or, binary, Server};

/// AddTrajectory calls in flight while filling.
const IN_FLIGHT: usize = 256;

fn run(args: &[&str]) -> f64 {
    let t = Instant::now();
    let out = Command::new(binary())
        .args(args)
        .output()
        .expect("run tamrm");
    let secs = t.elapsed().as_secs_f64();
    assert!(
        out.status.success(),
        "tamrm {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    secs
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n: u32 = arg_or(&args, "--trajectories", 100_000);
    let len: u32 = arg_or(&args, "--actions", 100);
    let store = arg(&args, "--store").unwrap_or_else(|| "memory".into());
    let import_max: u32 = arg_or(&args, "--import-max", 100_000);
    let cap = n.to_string();
    let limits = ["--max-pool-capacity", cap.as_str()];
    let dir = tempfile::tempdir().unwrap();
    let from = Server::start(None, &limits);
    let to = match store.as_str() {
        "memory" => Server::start(None, &limits),
        "data-dir" => Server::start(Some(&dir.path().join("data")), &limits),
        other => panic!("--store {other}: expected memory or data-dir"),
    };
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let fill = runtime.block_on(async {
        let mut c = from
            .connect()
            .await
            .max_decoding_message_size(1 << 30)
            .max_encoding_message_size(1 << 30);
        c.create_task(proto::CreateTaskRequest {
            task_id: "bench".into(),
            config: Some(proto::TaskConfig {
                num_actions: 8,
                pool_capacity: Some(n),
                k: Some(1),
                min_pool_size: Some(1),
                max_trajectory_len: Some(len),
                ..Default::default()
            }),
        })
        .await
        .expect("create");
        to.connect().await;
        let t = Instant::now();
        let calls = (0..n).map(|j| {
            let mut c = c.clone();
            async move {
                let r = c
                    .add_trajectory(proto::AddTrajectoryRequest {
                        task_id: "bench".into(),
                        trajectory: Some(proto::Trajectory {
                            actions: (0..len).map(|i| (i * 7 + j) % 8).collect(),
                            score: f64::from(j) * 0.37 - 1e4,
                            ..Default::default()
                        }),
                    })
                    .await
                    .expect("add trajectory");
                assert!(r.into_inner().inserted);
            }
        });
        futures::stream::iter(calls)
            .buffer_unordered(IN_FLIGHT)
            .collect::<Vec<()>>()
            .await;
        t.elapsed().as_secs_f64()
    });
    let file = dir.path().join("pool.jsonl");
    let f = file.to_str().unwrap();
    let export = run(&["pool", "export", "bench", "-o", f, "--server", &from.addr]);
    let bytes = std::fs::metadata(&file).unwrap().len();
    if n > import_max {
        println!("filled {n} trajectories by AddTrajectory in {fill:.1} s");
        println!(
            "| {n} × {len} | — | {:.1} MB | {export:.2} s ({:.0}/s) | not run (--import-max {import_max}) |",
            bytes as f64 / 1e6,
            f64::from(n) / export
        );
        return;
    }
    let import = run(&["pool", "import", f, "--server", &to.addr]);
    runtime.block_on(async {
        let mut c = to.connect().await;
        let task = c
            .get_task(proto::GetTaskRequest {
                task_id: "bench".into(),
            })
            .await
            .expect("the imported task")
            .into_inner();
        assert_eq!(
            task.stats.unwrap().pool_size,
            n,
            "every trajectory imported"
        );
    });
    println!("filled {n} trajectories by AddTrajectory in {fill:.1} s");
    println!("| trajectories × actions | store imported into | file | export | import |");
    println!("|---|---|---|---|---|");
    println!(
        "| {n} × {len} | {store} | {:.1} MB | {export:.2} s ({:.0}/s) | {import:.2} s ({:.0}/s) |",
        bytes as f64 / 1e6,
        f64::from(n) / export,
        f64::from(n) / import,
    );
}
