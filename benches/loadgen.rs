//! Load generator: real server on 127.0.0.1:0, real gRPC clients, several scenarios.
//!
//! `cargo bench --bench loadgen` prints two markdown tables:
//!
//! 1. scenarios: round-trip latency per `StepBatch` (median, p99) and aggregate entry
//!    throughput, memory and data-dir stores;
//! 2. server throughput against an echo floor: env-steps/s of the server at 1/16/256
//!    entries per batch × 1/4 streams, side by side with a bare tonic service that
//!    answers each `StepBatch` with a `ShapedBatch` of the same size and does nothing
//!    else. Echo and server runs alternate, `--reps` times; the table gives medians.
//!
//! Flags (after `--`): `--quick` (10× fewer batches, shorter windows, 3 reps),
//! `--scenarios` or `--throughput` (only that table), `--reps N`, `--secs S` (length of
//! one throughput window), `--case ENTRIES,STREAMS` and `--side echo|server` (one row,
//! one side: for profiling), `--metrics` (the server with Prometheus metrics on, at
//! 127.0.0.1:0, never scraped: the cost of recording). Client and server share the machine, so absolute numbers are
//! a lower bound on what a dedicated server does; the ratios are the point (see
//! docs/benchmarks.md).

use std::sync::Arc;
use std::time::{Duration, Instant};

use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::shaping_server::{Shaping, ShapingServer};
use tamrm::proto::{self, shape_request, shape_response, ShapeRequest, ShapeResponse};
use tamrm::settings::Settings;
use tokio::sync::{mpsc, Barrier};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};

// The server runs in this process: give it the binary's allocator.
#[cfg(feature = "mimalloc")]
#[global_allocator]
static ALLOCATOR: tamrm::ServerAllocator = tamrm::ServerAllocator;

#[path = "common/workload.rs"]
mod workload;
use workload::{echo, step_batch, Rng};

struct Scenario {
    name: &'static str,
    streams: usize,
    distinct_tasks: bool,
    envs: u32,
    durable: bool,
    /// Mean episode length (episodes end with probability 1/len per step).
    episode_len: u64,
    batches: usize,
}

struct Outcome {
    latencies: Vec<Duration>,
    entries: usize,
    wall: Duration,
    episodes: u64,
}

/// How long one stream sends batches.
#[derive(Clone, Copy)]
enum Until {
    Batches(usize),
    /// For this long after every stream of the run has opened.
    Window(Duration),
}

/// What one stream did.
struct Driven {
    latencies: Vec<Duration>,
    entries: usize,
    episodes: u64,
    /// From the common start (after every stream opened) to the last answer.
    elapsed: Duration,
}

async fn drive(
    addr: std::net::SocketAddr,
    task: String,
    envs: u32,
    episode_len: u64,
    until: Until,
    start: Arc<Barrier>,
    seed: u64,
) -> Driven {
    let mut client = ShapingClient::connect(format!("http://{addr}"))
        .await
        .expect("connect")
        .max_decoding_message_size(64 << 20);
    let (tx, rx) = mpsc::channel(4);
    tx.send(ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: task,
            num_envs: envs,
            ..Default::default()
        })),
    })
    .await
    .expect("send open");
    let mut inbound = client
        .shape(ReceiverStream::new(rx))
        .await
        .expect("shape")
        .into_inner();
    inbound.message().await.expect("opened");
    let mut rng = Rng(seed | 1);
    let n = envs as usize;
    let mut out = Driven {
        latencies: Vec::new(),
        entries: 0,
        episodes: 0,
        elapsed: Duration::ZERO,
    };
    start.wait().await;
    let t_start = Instant::now();
    let mut sent = 0;
    loop {
        match until {
            Until::Batches(b) if sent >= b => break,
            Until::Window(w) if t_start.elapsed() >= w => break,
            _ => {}
        }
        let batch = step_batch(&mut rng, n, episode_len, &mut out.episodes);
        let t0 = Instant::now();
        tx.send(ShapeRequest {
            kind: Some(shape_request::Kind::Steps(batch)),
        })
        .await
        .expect("send");
        match inbound.message().await.expect("shaped") {
            Some(proto::ShapeResponse {
                kind: Some(shape_response::Kind::Shaped(b)),
            }) => {
                assert_eq!(b.rewards.len(), n)
            }
            other => panic!("unexpected {other:?}"),
        }
        out.latencies.push(t0.elapsed());
        sent += 1;
    }
    out.entries = sent * n;
    out.elapsed = t_start.elapsed();
    out
}

/// Task `load-{i}` as every run creates it: discrete n = 2, |D| = 30, k = 20, kNN from
/// step 0.
async fn create_task(admin: &mut ShapingClient<tonic::transport::Channel>, id: &str) {
    admin
        .create_task(proto::CreateTaskRequest {
            task_id: id.to_string(),
            config: Some(proto::TaskConfig {
                num_actions: 2,
                pool_capacity: Some(30),
                k: Some(20),
                start_step: Some(0),
                ..Default::default()
            }),
        })
        .await
        .expect("create");
}

/// Fills the pool of `id` with 30 random trajectories of 1 000–2 000 actions and scores
/// 200–500, so the kNN term is active from the first batch.
async fn seed_pool(admin: &mut ShapingClient<tonic::transport::Channel>, id: &str, seed: u64) {
    let mut rng = Rng(seed | 1);
    for _ in 0..30 {
        let len = 1000 + rng.below(1001) as usize;
        admin
            .add_trajectory(proto::AddTrajectoryRequest {
                task_id: id.to_string(),
                trajectory: Some(proto::Trajectory {
                    actions: (0..len).map(|_| rng.below(2) as u32).collect(),
                    score: 200.0 + rng.below(300_000) as f64 / 1000.0,
                    ..Default::default()
                }),
            })
            .await
            .expect("add trajectory");
    }
}

/// Runs `streams` streams against `addr` (on tasks `tasks(i)`) and merges their results.
async fn drive_all(
    addr: std::net::SocketAddr,
    streams: usize,
    tasks: impl Fn(usize) -> String,
    envs: u32,
    episode_len: u64,
    until: Until,
) -> Outcome {
    let start = Arc::new(Barrier::new(streams));
    let handles: Vec<_> = (0..streams)
        .map(|i| {
            tokio::spawn(drive(
                addr,
                tasks(i),
                envs,
                episode_len,
                until,
                start.clone(),
                0x9e37_79b9 + i as u64,
            ))
        })
        .collect();
    let mut out = Outcome {
        latencies: Vec::new(),
        entries: 0,
        wall: Duration::ZERO,
        episodes: 0,
    };
    for h in handles {
        let d = h.await.expect("stream task");
        out.latencies.extend(d.latencies);
        out.entries += d.entries;
        out.episodes += d.episodes;
        out.wall = out.wall.max(d.elapsed);
    }
    out
}

async fn run(s: &Scenario) -> Outcome {
    let dir = tempfile::tempdir().expect("tempdir");
    let settings = Settings {
        listen: "127.0.0.1:0".parse().expect("addr"),
        data_dir: s.durable.then(|| dir.path().to_path_buf()),
        metrics_listen: metrics_listen(),
        ..Settings::default()
    };
    let server = tamrm::server::start(&settings).await.expect("server");
    let addr = server.addr();
    let mut admin = ShapingClient::connect(format!("http://{addr}"))
        .await
        .expect("connect");
    let tasks = if s.distinct_tasks { s.streams } else { 1 };
    for i in 0..tasks {
        create_task(&mut admin, &format!("load-{i}")).await;
    }
    let distinct = s.distinct_tasks;
    let out = drive_all(
        addr,
        s.streams,
        |i| format!("load-{}", if distinct { i } else { 0 }),
        s.envs,
        s.episode_len,
        Until::Batches(s.batches),
    )
    .await;
    server.shutdown().await;
    out
}

/// The echo floor: a bare tonic `Shape` that answers every `StepBatch` with a
/// `ShapedBatch` of the same number of entries built from the request's own columns
/// (the same spawned task and channel as the real service, no session, no core).
struct Echo;

#[tonic::async_trait]
impl Shaping for Echo {
    async fn create_task(
        &self,
        _: Request<proto::CreateTaskRequest>,
    ) -> Result<Response<proto::Task>, Status> {
        Err(Status::unimplemented("echo"))
    }
    async fn get_task(
        &self,
        _: Request<proto::GetTaskRequest>,
    ) -> Result<Response<proto::Task>, Status> {
        Err(Status::unimplemented("echo"))
    }
    async fn list_tasks(
        &self,
        _: Request<proto::ListTasksRequest>,
    ) -> Result<Response<proto::ListTasksResponse>, Status> {
        Err(Status::unimplemented("echo"))
    }
    async fn delete_task(
        &self,
        _: Request<proto::DeleteTaskRequest>,
    ) -> Result<Response<proto::DeleteTaskResponse>, Status> {
        Err(Status::unimplemented("echo"))
    }
    async fn reset_pool(
        &self,
        _: Request<proto::ResetPoolRequest>,
    ) -> Result<Response<proto::Task>, Status> {
        Err(Status::unimplemented("echo"))
    }
    async fn get_pool(
        &self,
        _: Request<proto::GetPoolRequest>,
    ) -> Result<Response<proto::Pool>, Status> {
        Err(Status::unimplemented("echo"))
    }
    async fn add_trajectory(
        &self,
        _: Request<proto::AddTrajectoryRequest>,
    ) -> Result<Response<proto::AddTrajectoryResponse>, Status> {
        Err(Status::unimplemented("echo"))
    }

    type ShapeStream = ReceiverStream<Result<ShapeResponse, Status>>;

    async fn shape(
        &self,
        request: Request<Streaming<ShapeRequest>>,
    ) -> Result<Response<Self::ShapeStream>, Status> {
        let mut inbound = request.into_inner();
        let (tx, rx) = mpsc::channel(2);
        tokio::spawn(async move {
            while let Ok(Some(ShapeRequest { kind: Some(kind) })) = inbound.message().await {
                let kind = match kind {
                    shape_request::Kind::Open(_) => {
                        shape_response::Kind::Opened(proto::Task::default())
                    }
                    shape_request::Kind::Steps(b) => shape_response::Kind::Shaped(echo(b)),
                };
                let msg = ShapeResponse { kind: Some(kind) };
                if tx.send(Ok(msg)).await.is_err() {
                    break;
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    type FollowStream = ReceiverStream<Result<proto::FollowResponse, Status>>;

    async fn follow(
        &self,
        _: Request<Streaming<proto::FollowRequest>>,
    ) -> Result<Response<Self::FollowStream>, Status> {
        Err(Status::unimplemented("echo"))
    }
}

/// One throughput window: `streams` streams of `envs` entries per batch, each on its
/// own task, against the echo floor or the real server (memory store, seeded pools).
/// Returns env-steps (entries) per second.
async fn throughput(echo: bool, streams: usize, envs: u32, window: Duration) -> f64 {
    let stop = tokio_util::sync::CancellationToken::new();
    let (addr, server, echo_task) = if echo {
        let incoming =
            tonic::transport::server::TcpIncoming::bind("127.0.0.1:0".parse().expect("addr"))
                .expect("bind")
                .with_nodelay(Some(true));
        let addr = incoming.local_addr().expect("addr");
        let signal = stop.clone();
        let task = tokio::spawn(
            tonic::transport::Server::builder()
                .add_service(ShapingServer::new(Echo))
                .serve_with_incoming_shutdown(incoming, async move { signal.cancelled().await }),
        );
        (addr, None, Some(task))
    } else {
        let settings = Settings {
            listen: "127.0.0.1:0".parse().expect("addr"),
            metrics_listen: metrics_listen(),
            ..Settings::default()
        };
        let server = tamrm::server::start(&settings).await.expect("server");
        let addr = server.addr();
        let mut admin = ShapingClient::connect(format!("http://{addr}"))
            .await
            .expect("connect");
        for i in 0..streams {
            let id = format!("load-{i}");
            create_task(&mut admin, &id).await;
            seed_pool(&mut admin, &id, 0x51ed + i as u64).await;
        }
        (addr, Some(server), None)
    };
    let out = drive_all(
        addr,
        streams,
        |i| format!("load-{i}"),
        envs,
        200,
        Until::Window(window),
    )
    .await;
    if let Some(server) = server {
        server.shutdown().await;
    }
    stop.cancel();
    if let Some(task) = echo_task {
        let _ = task.await;
    }
    out.entries as f64 / out.wall.as_secs_f64()
}

fn pct(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn median(xs: &mut [f64]) -> f64 {
    xs.sort_by(f64::total_cmp);
    let n = xs.len();
    if n % 2 == 1 {
        xs[n / 2]
    } else {
        (xs[n / 2 - 1] + xs[n / 2]) / 2.0
    }
}

fn arg_value(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

fn scenarios_table(rt: &tokio::runtime::Runtime, b: usize) {
    let scenarios = [
        Scenario {
            name: "1 stream x 16 envs, memory",
            streams: 1,
            distinct_tasks: true,
            envs: 16,
            durable: false,
            episode_len: 200,
            batches: b,
        },
        Scenario {
            name: "4 streams x 16 envs, 4 tasks, memory",
            streams: 4,
            distinct_tasks: true,
            envs: 16,
            durable: false,
            episode_len: 200,
            batches: b,
        },
        Scenario {
            name: "4 streams x 16 envs, 1 shared task, memory",
            streams: 4,
            distinct_tasks: false,
            envs: 16,
            durable: false,
            episode_len: 200,
            batches: b,
        },
        Scenario {
            name: "1 stream x 16 envs, data dir (fsync)",
            streams: 1,
            distinct_tasks: true,
            envs: 16,
            durable: true,
            episode_len: 200,
            batches: b / 2,
        },
        Scenario {
            name: "4 streams x 16 envs, 1 shared task, data dir (fsync)",
            streams: 4,
            distinct_tasks: false,
            envs: 16,
            durable: true,
            episode_len: 200,
            batches: b / 2,
        },
    ];
    println!(
        "| scenario | batches | episodes ended | median RTT (µs) | p99 RTT (µs) | entries/s |"
    );
    println!("|---|---|---|---|---|---|");
    for s in &scenarios {
        let mut o = rt.block_on(run(s));
        o.latencies.sort();
        println!(
            "| {} | {} | {} | {:.0} | {:.0} | {:.0} |",
            s.name,
            o.latencies.len(),
            o.episodes,
            pct(&o.latencies, 0.5).as_secs_f64() * 1e6,
            pct(&o.latencies, 0.99).as_secs_f64() * 1e6,
            o.entries as f64 / o.wall.as_secs_f64()
        );
    }
}

/// Which rows and sides of the throughput table to run (`--case ENTRIES,STREAMS`,
/// `--side echo|server`, for profiling one of them).
struct Filter {
    case: Option<(u32, usize)>,
    side: Option<bool>,
}

fn throughput_table(rt: &tokio::runtime::Runtime, reps: usize, window: Duration, f: &Filter) {
    println!(
        "| entries/batch | streams | echo env-steps/s | server env-steps/s | server / echo (median, min–max) |"
    );
    println!("|---:|---:|---:|---:|---|");
    for envs in [1u32, 16, 256] {
        for streams in [1usize, 4] {
            if f.case.is_some_and(|c| c != (envs, streams)) {
                continue;
            }
            let side = |echo: bool| {
                if f.side.is_some_and(|s| s != echo) {
                    return f64::NAN;
                }
                rt.block_on(throughput(echo, streams, envs, window))
            };
            let (mut echo, mut server, mut ratio) = (Vec::new(), Vec::new(), Vec::new());
            for _ in 0..reps {
                let e = side(true);
                let s = side(false);
                echo.push(e);
                server.push(s);
                ratio.push(s / e);
            }
            let (lo, hi) = ratio
                .iter()
                .fold((f64::INFINITY, 0f64), |(lo, hi), &r| (lo.min(r), hi.max(r)));
            println!(
                "| {envs} | {streams} | {:.0} | {:.0} | {:.2} ({lo:.2}–{hi:.2}) |",
                median(&mut echo),
                median(&mut server),
                median(&mut ratio),
            );
        }
    }
}

/// `--metrics`: the server records Prometheus metrics (on 127.0.0.1:0).
fn metrics_listen() -> Option<std::net::SocketAddr> {
    std::env::args()
        .any(|a| a == "--metrics")
        .then(|| "127.0.0.1:0".parse().expect("addr"))
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let has = |flag: &str| args.iter().any(|a| a == flag);
    let quick = has("--quick");
    let (only_scenarios, only_throughput) = (has("--scenarios"), has("--throughput"));
    let reps = arg_value(&args, "--reps")
        .and_then(|v| v.parse().ok())
        .unwrap_or(if quick { 3 } else { 5 });
    let secs: f64 = arg_value(&args, "--secs")
        .and_then(|v| v.parse().ok())
        .unwrap_or(if quick { 0.3 } else { 1.0 });
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    if !only_throughput {
        scenarios_table(&rt, if quick { 200 } else { 2000 });
    }
    if !only_scenarios {
        if !only_throughput {
            println!();
        }
        let filter = Filter {
            case: arg_value(&args, "--case").and_then(|c| {
                let (e, s) = c.split_once(',')?;
                Some((e.parse().ok()?, s.parse().ok()?))
            }),
            side: arg_value(&args, "--side").map(|s| s == "echo"),
        };
        throughput_table(&rt, reps, Duration::from_secs_f64(secs), &filter);
    }
}
