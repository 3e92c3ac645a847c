//! The server's per-batch work without the transport, repeatably: the loadgen's
//! throughput workload (`benches/loadgen.rs`) driven through the same code as a `Shape`
//! stream minus HTTP/2 and tokio's scheduling, on one thread. For each batch: encode the
//! client's `StepBatch`, decode it as the server does (`service::codec`), shape it, encode
//! the answer as the server does, decode it as the client does. `--echo` runs the echo
//! floor's answer instead (prost both ways, as tonic's generated code), `--prost` the
//! server with prost's codec.
//!
//! `cargo bench --bench session_path -- [--entries 256] [--streams 4] [--batches 2000]
//! [--echo | --prost]` prints CPU nanoseconds per entry (thread CPU time). Under
//! `valgrind --tool=callgrind` the instruction counts are the same on every run, whatever
//! else the machine does: the way to compare two versions of the hot path on a shared
//! machine (docs/benchmarks.md, "Server throughput").

use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use tamrm::core::{ActionSeq, TaskConfigInput};
use tamrm::limits::Limits;
use tamrm::proto;
use tamrm::registry::{Registry, DEFAULT_TENANT};
use tamrm::service::codec::{decode_request, encode_shaped};
use tamrm::service::convert::{batch_view, shaped_proto};
use tamrm::session::{OpenRequest, StreamSession};
use tamrm::store::MemoryStore;

#[path = "common/workload.rs"]
mod workload;
use workload::{echo, step_batch, thread_cpu_time, Rng};

fn arg<T: std::str::FromStr>(args: &[String], name: &str) -> Option<T> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
}

/// Which code answers a batch.
#[derive(Clone, Copy, PartialEq)]
enum Side {
    Server,
    ServerProst,
    Echo,
}

async fn run(entries: usize, streams: usize, batches: usize, side: Side) {
    let registry = Registry::open(Arc::new(MemoryStore::new()), Limits::default())
        .await
        .expect("registry")
        .0;
    let mut sessions = Vec::new();
    let mut rngs = Vec::new();
    for i in 0..streams {
        let id = format!("load-{i}");
        let task = registry
            .create(
                DEFAULT_TENANT,
                &id,
                &TaskConfigInput {
                    num_actions: 2,
                    pool_capacity: Some(30),
                    k: Some(20),
                    start_step: Some(0),
                    ..Default::default()
                },
                None,
            )
            .await
            .expect("create");
        let mut rng = Rng((0x51ed + i as u64) | 1);
        for _ in 0..30 {
            let len = 1000 + rng.below(1001) as usize;
            let actions = (0..len).map(|_| rng.below(2) as u32).collect();
            let score = 200.0 + rng.below(300_000) as f64 / 1000.0;
            task.offer(ActionSeq::Discrete(actions), score)
                .await
                .expect("seed");
        }
        let req = OpenRequest {
            task_id: &id,
            num_envs: entries as u32,
            ..Default::default()
        };
        sessions.push(StreamSession::open(&registry, &req).await.expect("open"));
        rngs.push(Rng((0x9e37_79b9 + i as u64) | 1));
    }
    let mut scores = Vec::new();
    let mut wire = Vec::new();
    let mut answer = bytes::BytesMut::new();
    let mut cpu = Duration::ZERO;
    // A hash of every answer's bits: two versions of the hot path must print the same.
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    let mut mix = |x: u64| hash = (hash ^ x).wrapping_mul(0x0000_0100_0000_01b3);
    for _ in 0..batches {
        for (session, rng) in sessions.iter_mut().zip(&mut rngs) {
            wire.clear();
            proto::ShapeRequest {
                kind: Some(proto::shape_request::Kind::Steps(step_batch(
                    rng, entries, 200, &mut 0,
                ))),
            }
            .encode(&mut wire)
            .expect("encode");
            let t0 = thread_cpu_time();
            match side {
                Side::Server => {
                    let batch = match decode_request(&wire).expect("decode").kind {
                        Some(proto::shape_request::Kind::Steps(b)) => b,
                        _ => unreachable!("a batch"),
                    };
                    let view = batch_view(&batch, &mut scores);
                    encode_shaped(&session.step(&view).await.expect("step"), &mut answer);
                }
                Side::ServerProst | Side::Echo => {
                    let batch = match proto::ShapeRequest::decode(wire.as_slice())
                        .expect("decode")
                        .kind
                    {
                        Some(proto::shape_request::Kind::Steps(b)) => b,
                        _ => unreachable!("a batch"),
                    };
                    let shaped = if side == Side::Echo {
                        echo(batch)
                    } else {
                        let view = batch_view(&batch, &mut scores);
                        shaped_proto(&session.step(&view).await.expect("step"))
                    };
                    proto::ShapeResponse {
                        kind: Some(proto::shape_response::Kind::Shaped(shaped)),
                    }
                    .encode(&mut answer)
                    .expect("encode");
                }
            }
            cpu += thread_cpu_time() - t0;
            let back = match proto::ShapeResponse::decode(&answer[..])
                .expect("decode")
                .kind
            {
                Some(proto::shape_response::Kind::Shaped(b)) => b,
                _ => unreachable!("an answer"),
            };
            answer.clear();
            for (((r, kr), p), (s, a)) in back
                .rewards
                .iter()
                .zip(&back.knn_rewards)
                .zip(&back.potentials)
                .zip(back.steps.iter().zip(&back.knn_active))
            {
                mix(r.to_bits());
                mix(kr.to_bits());
                mix(p.to_bits());
                mix(u64::from(*s) << 1 | u64::from(*a));
            }
            mix(back.pool_version);
        }
    }
    let n = (entries * streams * batches) as f64;
    println!(
        "{}: {entries} entries x {streams} streams x {batches} batches: {:.1} ns CPU per entry (answers' hash {hash:016x})",
        match side {
            Side::Server => "server",
            Side::ServerProst => "server (prost codec)",
            Side::Echo => "echo",
        },
        cpu.as_secs_f64() * 1e9 / n,
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let entries = arg(&args, "--entries").unwrap_or(256);
    let streams = arg(&args, "--streams").unwrap_or(4);
    let batches = arg(&args, "--batches").unwrap_or(2000);
    let side = if args.iter().any(|a| a == "--echo") {
        Side::Echo
    } else if args.iter().any(|a| a == "--prost") {
        Side::ServerProst
    } else {
        Side::Server
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(run(entries, streams, batches, side));
}
