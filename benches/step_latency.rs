//! Step latency of a Rust tonic client: the reference for the Python clients.
//!
//! `cargo bench --bench step_latency -- --addr HOST:PORT --envs N --steps M [--task ID]
//! [--warmup W]` opens one `Shape` stream on task `ID` (default `bench/step_latency`,
//! which must exist) of a running server with the generated client
//! (`tamrm::proto::shaping_client::ShapingClient`), sends `W` (default 200) untimed
//! `StepBatch`es of `N` entries, then `M` timed ones, each timed from building the batch
//! to receiving its `ShapedBatch`, and prints one JSON object (microseconds):
//! `{"client":"rust-tonic","envs":N,"steps":M,"p50_us":..,"p90_us":..,"p99_us":..,
//! "mean_us":..,"min_us":..,"max_us":..}`.
//!
//! The batch is what the Python benchmark sends (`clients/python/benchmarks/step_latency.py`):
//! random discrete actions (n = 2), reward 1, values 0.5 / 0.6, no episode ends (so the pool
//! does not change during the run). The transport is set up as in the Python client's native
//! extension: a 2-worker multi-threaded tokio runtime, `tcp_nodelay`, the loop driven by
//! `block_on` from the main thread.

use std::time::{Duration, Instant};

use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::{self, shape_request, shape_response, ShapeRequest};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::StreamExt;
use tonic::transport::Endpoint;

/// The action of entry `i`: bit 0 of SplitMix64's output, so runs are repeatable.
fn action(i: u64) -> u32 {
    let mut z = i.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    ((z ^ (z >> 31)) & 1) as u32
}

fn arg<T: std::str::FromStr>(args: &[String], name: &str) -> Option<T> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
}

fn batch(first: u64, n: usize) -> proto::StepBatch {
    proto::StepBatch {
        actions: (first..first + n as u64).map(action).collect(),
        rewards: vec![1.0; n],
        terminated: vec![false; n],
        truncated: vec![false; n],
        values: vec![0.5; n],
        next_values: vec![0.6; n],
        ..Default::default()
    }
}

fn percentile(sorted: &[Duration], q: f64) -> f64 {
    // Nearest rank, as numpy's "inverted_cdf": the same definition as the Python side.
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1].as_secs_f64() * 1e6
}

async fn run(addr: String, task: String, envs: u32, warmup: usize, steps: usize) -> Vec<Duration> {
    let channel = Endpoint::from_shared(format!("http://{addr}"))
        .expect("address")
        .tcp_nodelay(true)
        .connect()
        .await
        .expect("connect");
    let mut client = ShapingClient::new(channel);
    // The stream: Open first, then whatever the loop sends on `tx`.
    let open = ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: task,
            num_envs: envs,
            client_id: format!("step-latency-{}", std::process::id()),
            ..Default::default()
        })),
    };
    let (tx, rx) = mpsc::channel(2);
    let outbound = tokio_stream::once(open).chain(ReceiverStream::new(rx));
    let mut inbound = client.shape(outbound).await.expect("shape").into_inner();
    match inbound.message().await.expect("opened") {
        Some(proto::ShapeResponse {
            kind: Some(shape_response::Kind::Opened(_)),
        }) => {}
        other => panic!("expected Opened, got {other:?}"),
    }
    let n = envs as usize;
    let mut latencies = Vec::with_capacity(steps);
    for i in 0..warmup + steps {
        let t0 = Instant::now();
        tx.send(ShapeRequest {
            kind: Some(shape_request::Kind::Steps(batch((i * n) as u64, n))),
        })
        .await
        .expect("send");
        match inbound.message().await.expect("shaped") {
            Some(proto::ShapeResponse {
                kind: Some(shape_response::Kind::Shaped(b)),
            }) => assert_eq!(b.rewards.len(), n),
            other => panic!("unexpected {other:?}"),
        }
        let dt = t0.elapsed();
        if i >= warmup {
            latencies.push(dt);
        }
    }
    drop(tx);
    while let Ok(Some(_)) = inbound.message().await {}
    latencies
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(addr) = arg::<String>(&args, "--addr") else {
        // `cargo bench` without arguments (e.g. all benches at once): nothing to do.
        eprintln!("step_latency: pass --addr HOST:PORT --envs N --steps M (see the file's doc)");
        return;
    };
    let envs: u32 = arg(&args, "--envs").unwrap_or(16);
    let steps: usize = arg(&args, "--steps").unwrap_or(5000);
    let warmup: usize = arg(&args, "--warmup").unwrap_or(200);
    let task: String = arg(&args, "--task").unwrap_or_else(|| "bench/step_latency".into());
    assert!(envs >= 1 && steps >= 1, "--envs and --steps must be >= 1");
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let mut lat = rt.block_on(run(addr, task, envs, warmup, steps));
    let mean = lat.iter().map(Duration::as_secs_f64).sum::<f64>() / lat.len() as f64 * 1e6;
    lat.sort();
    println!(
        "{{\"client\":\"rust-tonic\",\"envs\":{envs},\"steps\":{steps},\"p50_us\":{:.2},\
         \"p90_us\":{:.2},\"p99_us\":{:.2},\"mean_us\":{mean:.2},\"min_us\":{:.2},\"max_us\":{:.2}}}",
        percentile(&lat, 0.50),
        percentile(&lat, 0.90),
        percentile(&lat, 0.99),
        lat[0].as_secs_f64() * 1e6,
        lat[lat.len() - 1].as_secs_f64() * 1e6,
    );
}
