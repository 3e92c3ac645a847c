//! Stop and start time of a data-dir server against its workload (docs/storage.md, "Stop
//! and start time").
//!
//! `cargo bench --bench stopstart` starts the real `tamrm` binary (`TAMRM_BIN`, default
//! `target/release/tamrm`; build it first) with a fresh data dir, fills it through the
//! gRPC API, then per run:
//!
//! - **stop after a burst**: SIGTERM right after the fill (every change is in the commit
//!   log, none in the snapshots yet), timed from the signal to the process's exit;
//! - **start**: the binary started again, timed from the spawn until `ListTasks` reports
//!   every task with its full pool, versions and counters as they were before the stop
//!   (the server binds only once it has restored every task);
//! - **stop, idle**: SIGTERM again, nothing changed since the start;
//! - **start after kill -9**: a second fill into a fresh data dir, SIGKILL, then the start
//!   timed the same way (what recovery costs).
//!
//! Workloads (per trajectory count N, `--trajectories 1000,10000,100000`): one pool of N
//! filled by AddTrajectory (10 actions each); N/100 tasks of 100 filled by AddTrajectory;
//! N/100 tasks of 100 filled by Shape streams ending episodes (10 steps, named clients, so
//! that their ends are recorded too); N/10 000-action episodes in tasks of 100 (at most
//! 10 000 of them: 400 MB of actions). One markdown row per workload: the medians over
//! `--runs` runs (default 3) and the fill time of the last run.
//!
//! `--quick` (CI): N = 1 000, one run, long episodes of 1 000 actions.

use std::path::Path;
use std::process::ExitStatus;
use std::time::{Duration, Instant};

use futures::StreamExt;
use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::{self, shape_request, shape_response};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

#[path = "common/server.rs"]
mod server;
use server::{arg, arg_or, Server};

/// Requests in flight while filling.
const IN_FLIGHT: usize = 256;
/// Environments of one Shape stream (one per trajectory of a task of 100).
const ENVS: u32 = 100;
/// Shape streams open at once while filling.
const STREAMS: usize = 16;

/// How the pools are filled.
#[derive(Clone, Copy, PartialEq)]
enum Fill {
    AddTrajectory,
    Shape,
}

/// One workload: `tasks` tasks whose pools of `per_task` trajectories of `actions`
/// actions each are filled by `fill`.
#[derive(Clone, Copy)]
struct Workload {
    tasks: u32,
    per_task: u32,
    actions: u32,
    fill: Fill,
}

impl Workload {
    fn trajectories(&self) -> u64 {
        u64::from(self.tasks) * u64::from(self.per_task)
    }

    fn describe(&self) -> String {
        let pools = if self.tasks == 1 {
            "one pool".to_string()
        } else {
            format!("{} tasks of {}", self.tasks, self.per_task)
        };
        let fill = match self.fill {
            Fill::AddTrajectory => "AddTrajectory",
            Fill::Shape => "Shape episode ends",
        };
        format!(
            "{} trajectories, {pools}, {} actions, {fill}",
            self.trajectories(),
            self.actions
        )
    }

    fn task_id(i: u32) -> String {
        format!("task-{i:06}")
    }

    fn config(&self) -> proto::TaskConfig {
        proto::TaskConfig {
            num_actions: 4,
            pool_capacity: Some(self.per_task),
            k: Some(self.per_task.min(8)),
            min_pool_size: Some(1),
            max_trajectory_len: Some(self.actions),
            ..Default::default()
        }
    }
}

/// The grid for trajectory counts `ns`.
fn grid(ns: &[u64], long_actions: u32) -> Vec<Workload> {
    let mut out = Vec::new();
    for &n in ns {
        let n = u32::try_from(n).expect("trajectories fit u32");
        let tasks = (n / 100).max(1);
        out.push(Workload {
            tasks: 1,
            per_task: n,
            actions: 10,
            fill: Fill::AddTrajectory,
        });
        out.push(Workload {
            tasks,
            per_task: 100,
            actions: 10,
            fill: Fill::AddTrajectory,
        });
        out.push(Workload {
            tasks,
            per_task: 100,
            actions: 10,
            fill: Fill::Shape,
        });
        if n <= 10_000 {
            out.push(Workload {
                tasks,
                per_task: 100,
                actions: long_actions,
                fill: Fill::AddTrajectory,
            });
        }
    }
    out
}

/// Server flags every run uses: room for the workloads' pools and tasks.
const SERVER_FLAGS: &[&str] = &[
    "--max-pool-capacity",
    "100000",
    "--max-tasks",
    "10000",
    "--shutdown-grace-secs",
    "30",
];

async fn create_tasks(client: &mut ShapingClient<Channel>, w: &Workload) {
    let calls = (0..w.tasks).map(|i| {
        let mut c = client.clone();
        let config = w.config();
        async move {
            c.create_task(proto::CreateTaskRequest {
                task_id: Workload::task_id(i),
                config: Some(config),
            })
            .await
            .expect("create task");
        }
    });
    futures::stream::iter(calls)
        .buffer_unordered(IN_FLIGHT)
        .collect::<Vec<()>>()
        .await;
}

/// Trajectory `j` of a task: distinct actions, score `j` (so every insert is kept).
fn actions(j: u32, len: u32) -> Vec<u32> {
    (0..len).map(|a| (j.wrapping_mul(31) + a) % 4).collect()
}

async fn fill_add(client: &ShapingClient<Channel>, w: &Workload) {
    let calls = (0..w.tasks).flat_map(|i| (0..w.per_task).map(move |j| (i, j)));
    let calls = calls.map(|(i, j)| {
        let mut c = client.clone();
        let len = w.actions;
        async move {
            let r = c
                .add_trajectory(proto::AddTrajectoryRequest {
                    task_id: Workload::task_id(i),
                    trajectory: Some(proto::Trajectory {
                        actions: actions(j, len),
                        score: f64::from(j),
                        ..Default::default()
                    }),
                })
                .await
                .expect("add trajectory")
                .into_inner();
            assert!(
                r.inserted,
                "a trajectory of a pool not yet full was refused"
            );
        }
    });
    futures::stream::iter(calls)
        .buffer_unordered(IN_FLIGHT)
        .collect::<Vec<()>>()
        .await;
}

/// One Shape stream per task, `ENVS` environments each ending one episode of
/// `w.actions` steps.
async fn fill_shape(client: &ShapingClient<Channel>, w: &Workload) {
    let streams = (0..w.tasks).map(|i| {
        let mut c = client.clone();
        let steps = w.actions;
        async move {
            let (tx, rx) = mpsc::channel(steps as usize + 1);
            let open = proto::Open {
                task_id: Workload::task_id(i),
                num_envs: ENVS,
                client_id: format!("bench-{i}"),
                ..Default::default()
            };
            tx.send(proto::ShapeRequest {
                kind: Some(shape_request::Kind::Open(open)),
            })
            .await
            .expect("send open");
            for t in 0..steps {
                let batch = proto::StepBatch {
                    actions: (0..ENVS).map(|e| (e + t) % 4).collect(),
                    rewards: (0..ENVS).map(f64::from).collect(),
                    terminated: vec![t + 1 == steps; ENVS as usize],
                    ..Default::default()
                };
                tx.send(proto::ShapeRequest {
                    kind: Some(shape_request::Kind::Steps(batch)),
                })
                .await
                .expect("send batch");
            }
            drop(tx);
            let mut inbound = c
                .shape(ReceiverStream::new(rx))
                .await
                .expect("shape")
                .into_inner();
            let mut answered = 0;
            while let Some(m) = inbound.message().await.expect("shape answer") {
                if let Some(shape_response::Kind::Shaped(_)) = m.kind {
                    answered += 1;
                }
            }
            assert_eq!(answered, steps, "every batch answered");
        }
    });
    futures::stream::iter(streams)
        .buffer_unordered(STREAMS)
        .collect::<Vec<()>>()
        .await;
}

/// What a restart must restore: per task, (id, pool size, version, episodes, steps).
type State = Vec<(String, u32, u64, u64, u64)>;

async fn state(client: &mut ShapingClient<Channel>) -> State {
    let tasks = client
        .list_tasks(proto::ListTasksRequest {})
        .await
        .expect("list tasks")
        .into_inner()
        .tasks;
    tasks
        .into_iter()
        .map(|t| {
            let s = t.stats.unwrap_or_default();
            (
                t.task_id,
                s.pool_size,
                s.pool_version,
                s.episodes_completed,
                s.steps_shaped,
            )
        })
        .collect()
}

/// Starts a server over `dir` and fills it; the server and the fill time.
async fn start_filled(dir: &Path, w: &Workload) -> (Server, Duration, State) {
    let server = Server::start(Some(dir), SERVER_FLAGS);
    let mut client = server.connect().await;
    let t = Instant::now();
    create_tasks(&mut client, w).await;
    match w.fill {
        Fill::AddTrajectory => fill_add(&client, w).await,
        Fill::Shape => fill_shape(&client, w).await,
    }
    let filled = t.elapsed();
    let s = state(&mut client).await;
    let total: u64 = s.iter().map(|t| u64::from(t.1)).sum();
    assert_eq!(total, w.trajectories(), "the pools hold every trajectory");
    (server, filled, s)
}

/// Starts a server over `dir`; the time until it reports `want`.
async fn timed_start(dir: &Path, want: &State) -> (Server, Duration) {
    let t = Instant::now();
    let server = Server::start(Some(dir), SERVER_FLAGS);
    let mut client = server.connect().await;
    let got = state(&mut client).await;
    let took = t.elapsed();
    assert!(
        got == *want,
        "the restart did not restore every task, pool and counter"
    );
    (server, took)
}

fn stopped(r: (ExitStatus, Duration)) -> Duration {
    assert!(r.0.success(), "tamrm exited with {} after SIGTERM", r.0);
    r.1
}

/// One run: (stop after burst, start, stop idle, start after kill -9, fill).
async fn run(w: &Workload) -> [Duration; 5] {
    let dir = tempfile::tempdir().expect("tempdir");
    let (mut server, fill, want) = start_filled(dir.path(), w).await;
    let stop_burst = stopped(server.terminate());
    let (mut server, start) = timed_start(dir.path(), &want).await;
    let stop_idle = stopped(server.terminate());
    drop(server);
    drop(dir);
    let dir = tempfile::tempdir().expect("tempdir");
    let (server, _, want) = start_filled(dir.path(), w).await;
    drop(server); // SIGKILL
    let (_server, start_crash) = timed_start(dir.path(), &want).await;
    [stop_burst, start, stop_idle, start_crash, fill]
}

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

fn secs(d: Duration) -> String {
    format!("{:.2}", d.as_secs_f64())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    let ns: Vec<u64> = arg(&args, "--trajectories")
        .map(|v| {
            v.split(',')
                .map(|n| n.trim().parse().expect("--trajectories N,N,..."))
                .collect()
        })
        .unwrap_or_else(|| {
            if quick {
                vec![1_000]
            } else {
                vec![1_000, 10_000, 100_000]
            }
        });
    let runs: usize = arg_or(&args, "--runs", if quick { 1 } else { 3 });
    let long = if quick { 1_000 } else { 10_000 };
    let only: Option<String> = arg(&args, "--only");
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    println!(
        "| workload | stop after a burst (s) | start (s) | stop, idle (s) | start after kill -9 (s) | fill (s) |"
    );
    println!("|---|---:|---:|---:|---:|---:|");
    for w in grid(&ns, long) {
        let name = w.describe();
        if only.as_ref().is_some_and(|o| !name.contains(o.as_str())) {
            continue;
        }
        let results: Vec<[Duration; 5]> = (0..runs.max(1)).map(|_| rt.block_on(run(&w))).collect();
        let col = |i: usize| median(results.iter().map(|r| r[i]).collect());
        println!(
            "| {name} | {} | {} | {} | {} | {} |",
            secs(col(0)),
            secs(col(1)),
            secs(col(2)),
            secs(col(3)),
            secs(results.last().expect("a run")[4]),
        );
    }
}
