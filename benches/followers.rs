//! Load generator for local sessions (SPEC §13): many learners following one task.
//!
//! `cargo bench --bench followers` starts the real `tamrm` binary (`TAMRM_BIN`, default
//! `target/release/tamrm`; build it first) on 127.0.0.1 and runs `--learners` simulated
//! learners (default 1 000) on ONE task, each a `Follow` stream that checks every update
//! follows the version it holds (one in 50 also applies them with the client's own code,
//! `Pool::with_update`; all 1 000 doing so would measure this machine's two cores rebuilding
//! 1 000 pools per change, not the server) and ends an episode every
//! `--interval-ms` on average (exponential gaps; 100 actions, a score that grows with time
//! so that most ends change the pool), for `--secs` seconds. Printed per store (memory,
//! then `--data-dir`) as one markdown row:
//!
//! - commits/s: episode ends acknowledged per second, and pool changes per second;
//! - ack latency p50/p99: from sending an end to its ack (the learner's wait at an end);
//! - staleness p50/p99: from the ack of a change to its arrival at every other learner
//!   (sampled: every 8th version), what SPEC §10's bound is about;
//! - server CPU: the server process's CPU time over the wall time (of 2 cores here),
//!   from /proc; the learners run in this process, on the same machine.
//!
//! Flags (after `--`): `--learners N`, `--interval-ms MS`, `--secs S`, `--connections C`
//! (HTTP/2 connections the learners share; default 50), `--quick` (100 learners, 3 s),
//! `--store memory|dir|both`.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use parking_lot::Mutex;
use tamrm::core::{ActionSeq, Pool, Trajectory};
use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::{self, follow_request, follow_response};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

#[path = "common/server.rs"]
mod server;
#[path = "common/workload.rs"]
mod workload;
use server::{arg, arg_or, Server};
use workload::Rng;

const TASK: &str = "followers";
const CAPACITY: u32 = 20;
/// One learner in this many applies the updates to its copy of the pool (the others,
/// which share this machine's two cores with the server, keep only its version).
const VERIFIED: usize = 50;

/// What every learner records.
#[derive(Default)]
struct Record {
    acks: Vec<Duration>,
    ends: u64,
    /// Per learner: (version now held, when it arrived).
    arrivals: Vec<(u64, Instant)>,
}

/// When each pool version was acknowledged to the learner that made it.
type AckTimes = Arc<Mutex<HashMap<u64, Instant>>>;

fn trajectory(t: proto::Trajectory) -> Arc<Trajectory> {
    Arc::new(Trajectory {
        actions: ActionSeq::Discrete(t.actions),
        score: t.score,
        seq: t.seq,
    })
}

#[allow(clippy::too_many_arguments)]
async fn learner(
    channel: Channel,
    id: usize,
    interval: Duration,
    start: Instant,
    until: Instant,
    acked: AckTimes,
    record: Arc<Mutex<Record>>,
) {
    let mut client = ShapingClient::new(channel);
    let (tx, rx) = mpsc::channel(8);
    tx.send(proto::FollowRequest {
        kind: Some(follow_request::Kind::Open(proto::FollowOpen {
            task_id: TASK.into(),
            num_envs: 1,
            client_id: format!("learner-{id}"),
        })),
    })
    .await
    .expect("send open");
    let mut inbound = client
        .follow(ReceiverStream::new(rx))
        .await
        .expect("follow")
        .into_inner();
    let mut pool: Option<Pool> = None;
    let mut rng = Rng(0x9e37_79b9 ^ ((id as u64 + 1) * 0x2545_f491));
    let gap = |rng: &mut Rng| {
        // Exponential with mean `interval`.
        let u = (rng.below(1 << 20) as f64 + 0.5) / f64::from(1 << 20);
        interval.mul_f64(-u.ln())
    };
    let mut next_end = tokio::time::Instant::now() + gap(&mut rng);
    let mut sent_at: Option<Instant> = None;
    let mut episode = 0u64;
    let mut local = Record::default();
    loop {
        tokio::select! {
            _ = tokio::time::sleep_until(next_end.min(until.into())), if sent_at.is_none() => {
                if Instant::now() >= until {
                    break;
                }
                let score = start.elapsed().as_secs_f64() * 1000.0 + rng.below(1000) as f64 / 1000.0;
                let msg = proto::EpisodeEnds {
                    ends: vec![proto::EpisodeEnd {
                        env_id: 0,
                        episode,
                        actions: (0..100).map(|_| rng.below(2) as u32).collect(),
                        score: Some(score),
                        ..Default::default()
                    }],
                    steps: 100,
                };
                episode += 1;
                sent_at = Some(Instant::now());
                if tx.send(proto::FollowRequest { kind: Some(follow_request::Kind::Ends(msg)) }).await.is_err() {
                    break;
                }
            }
            msg = inbound.message() => {
                let Ok(Some(proto::FollowResponse { kind: Some(kind) })) = msg else { break };
                let now = Instant::now();
                match kind {
                    follow_response::Kind::Opened(_) => {}
                    follow_response::Kind::Snapshot(p) => {
                        let ts = p.trajectories.into_iter().map(|t| (*trajectory(t)).clone()).collect();
                        let restored = Pool::restore(CAPACITY as usize, ts, p.pool_version, p.next_seq).expect("snapshot");
                        local.arrivals.push((restored.version(), now));
                        pool = Some(restored);
                    }
                    follow_response::Kind::Update(u) => {
                        let held = pool.as_mut().expect("snapshot first");
                        assert_eq!(u.base_version, held.version(), "an update with a gap");
                        local.arrivals.push((u.pool_version, now));
                        if id.is_multiple_of(VERIFIED) {
                            let added = u.added.into_iter().map(trajectory).collect();
                            *held = held.with_update(&u.removed, added, u.pool_version, u.next_seq).expect("update applies");
                        } else {
                            // A real learner applies every update; simulated ones (all on
                            // this machine) keep only the version, but for one in VERIFIED.
                            *held = Pool::restore(CAPACITY as usize, Vec::new(), u.pool_version, u.next_seq).expect("version");
                        }
                    }
                    follow_response::Kind::Ack(ack) => {
                        let Some(sent) = sent_at.take() else { continue };
                        local.acks.push(now - sent);
                        local.ends += 1;
                        if ack.changed.first() == Some(&true) {
                            acked.lock().insert(ack.versions[0], now);
                        }
                        next_end = tokio::time::Instant::now() + gap(&mut rng);
                    }
                }
            }
        }
    }
    drop(tx);
    let mut r = record.lock();
    r.acks.extend(local.acks);
    r.ends += local.ends;
    r.arrivals.extend(
        local
            .arrivals
            .drain(..)
            .map(|(v, t)| (v | (id as u64) << 48, t)),
    );
}

fn pct(sorted: &[Duration], p: f64) -> Duration {
    if sorted.is_empty() {
        return Duration::ZERO;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn ms(d: Duration) -> String {
    format!("{:.2}", d.as_secs_f64() * 1e3)
}

async fn run(durable: bool, learners: usize, connections: usize, interval: Duration, secs: f64) {
    let dir = tempfile::tempdir().expect("tempdir");
    let server = Server::start(durable.then_some(dir.path()), &[]);
    let url = server.url();
    let mut admin = server.connect().await;
    admin
        .create_task(proto::CreateTaskRequest {
            task_id: TASK.into(),
            config: Some(proto::TaskConfig {
                num_actions: 2,
                pool_capacity: Some(CAPACITY),
                ..Default::default()
            }),
        })
        .await
        .expect("create task");
    let mut channels = Vec::new();
    for _ in 0..connections.max(1) {
        channels.push(
            Channel::from_shared(url.clone())
                .expect("url")
                .connect()
                .await
                .expect("connect"),
        );
    }
    let acked: AckTimes = Arc::default();
    let record = Arc::new(Mutex::new(Record::default()));
    let start = Instant::now();
    let until = start + Duration::from_secs_f64(secs);
    let cpu0 = server.cpu_secs();
    let handles: Vec<_> = (0..learners)
        .map(|i| {
            tokio::spawn(learner(
                channels[i % channels.len()].clone(),
                i,
                interval,
                start,
                until,
                acked.clone(),
                record.clone(),
            ))
        })
        .collect();
    for h in handles {
        let _ = h.await;
    }
    let wall = start.elapsed().as_secs_f64();
    let cpu = server.cpu_secs() - cpu0;
    let task = admin
        .get_task(proto::GetTaskRequest {
            task_id: TASK.into(),
        })
        .await
        .expect("get task")
        .into_inner();
    let stats = task.stats.unwrap_or_default();
    let r = record.lock();
    assert_eq!(
        stats.episodes_completed, r.ends,
        "every acked end is counted once"
    );
    let mut acks = r.acks.clone();
    acks.sort();
    // Staleness: for sampled versions, from the ack to its arrival at each other learner.
    let acked = acked.lock();
    let mut first_at: HashMap<u64, Vec<(u64, Instant)>> = HashMap::new();
    for &(key, t) in &r.arrivals {
        first_at
            .entry(key >> 48)
            .or_default()
            .push((key & ((1 << 48) - 1), t));
    }
    let mut stale = Vec::new();
    for arrivals in first_at.values() {
        let mut held = 0u64;
        for &(v, t) in arrivals {
            for version in (held + 1)..=v {
                if version % 8 == 0 {
                    if let Some(&at) = acked.get(&version) {
                        stale.push(t.saturating_duration_since(at));
                    }
                }
            }
            held = held.max(v);
        }
    }
    stale.sort();
    println!(
        "| {} | {learners} | {:.0} ms | {:.0} | {:.0} | {} / {} | {} / {} | {:.0} % |",
        if durable { "data dir" } else { "memory" },
        interval.as_secs_f64() * 1e3,
        r.ends as f64 / wall,
        stats.pool_version as f64 / wall,
        ms(pct(&acks, 0.5)),
        ms(pct(&acks, 0.99)),
        ms(pct(&stale, 0.5)),
        ms(pct(&stale, 0.99)),
        cpu / wall * 100.0,
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let quick = args.iter().any(|a| a == "--quick");
    let learners = arg_or(&args, "--learners", if quick { 100 } else { 1000 });
    let interval = Duration::from_millis(arg_or(&args, "--interval-ms", 5000));
    let secs: f64 = arg_or(&args, "--secs", if quick { 3.0 } else { 20.0 });
    let connections = arg_or(&args, "--connections", 50);
    let stores = arg(&args, "--store").unwrap_or_else(|| "both".into());
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    println!(
        "| store | learners | mean gap between a learner's ends | ends/s | pool changes/s \
         | ack p50 / p99 (ms) | staleness p50 / p99 (ms) | server CPU |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for durable in [false, true] {
        if (durable && stores == "memory") || (!durable && stores == "dir") {
            continue;
        }
        rt.block_on(run(durable, learners, connections, interval, secs));
    }
}
