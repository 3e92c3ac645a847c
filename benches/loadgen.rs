//! Load generator: real server on 127.0.0.1:0, real gRPC clients, several scenarios.
//!
//! `cargo bench --bench loadgen` prints a markdown table of round-trip latency per
//! `StepBatch` (median, p99) and aggregate entry throughput. Client and server share the
//! machine, so absolute numbers are a lower bound on what a dedicated server does; the
//! ratios between scenarios are the point (see docs/benchmarks.md).

use std::time::{Duration, Instant};

use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::{self, shape_request, shape_response, ShapeRequest};
use tamrm::settings::Settings;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

/// A tiny deterministic PRNG (xorshift64*), so runs are repeatable without extra deps.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

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

async fn drive(
    addr: std::net::SocketAddr,
    task: String,
    envs: u32,
    episode_len: u64,
    batches: usize,
    seed: u64,
) -> (Vec<Duration>, usize, u64) {
    let mut client = ShapingClient::connect(format!("http://{addr}"))
        .await
        .expect("connect");
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
    let mut lat = Vec::with_capacity(batches);
    let mut episodes = 0;
    for _ in 0..batches {
        let n = envs as usize;
        let mut terminated = Vec::with_capacity(n);
        for _ in 0..n {
            let end = rng.below(episode_len) == 0;
            episodes += u64::from(end);
            terminated.push(end);
        }
        let batch = proto::StepBatch {
            actions: (0..n).map(|_| rng.below(2) as u32).collect(),
            rewards: (0..n).map(|_| 1.0).collect(),
            terminated,
            values: (0..n).map(|_| 0.5).collect(),
            next_values: (0..n).map(|_| 0.6).collect(),
            ..Default::default()
        };
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
        lat.push(t0.elapsed());
    }
    (lat, batches * envs as usize, episodes)
}

async fn run(s: &Scenario) -> Outcome {
    let dir = tempfile::tempdir().expect("tempdir");
    let settings = Settings {
        listen: "127.0.0.1:0".parse().expect("addr"),
        data_dir: s.durable.then(|| dir.path().to_path_buf()),
        ..Settings::default()
    };
    let server = tamrm::server::start(&settings).await.expect("server");
    let addr = server.addr();
    let mut admin = ShapingClient::connect(format!("http://{addr}"))
        .await
        .expect("connect");
    let tasks = if s.distinct_tasks { s.streams } else { 1 };
    for i in 0..tasks {
        admin
            .create_task(proto::CreateTaskRequest {
                task_id: format!("load-{i}"),
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
    let t0 = Instant::now();
    let handles: Vec<_> = (0..s.streams)
        .map(|i| {
            let task = format!("load-{}", if s.distinct_tasks { i } else { 0 });
            tokio::spawn(drive(
                addr,
                task,
                s.envs,
                s.episode_len,
                s.batches,
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
        let (lat, entries, episodes) = h.await.expect("stream task");
        out.latencies.extend(lat);
        out.entries += entries;
        out.episodes += episodes;
    }
    out.wall = t0.elapsed();
    server.shutdown().await;
    out
}

fn pct(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let b = if quick { 200 } else { 2000 };
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
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
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
