//! Soak under abuse (docs/soak.md): the real `tamrm` binary (a child process,
//! `--data-dir`, loopback only) under 256 concurrent streams over several tasks for a
//! bounded time, with well-behaved learners and abusers mixed in:
//!
//! - *learners* (200 streams): batches of 1–64 envs, episodes of random length; one batch
//!   in 50 is invalid (an action out of range, a NaN reward, mismatched lengths), which must
//!   end the stream with INVALID_ARGUMENT naming the field, after which the learner opens a
//!   new stream;
//! - *droppers* (16): open, send a few batches, then vanish mid-stream (the connection is
//!   dropped without a half-close);
//! - *silent* (16): open the RPC and never send a message, not even `Open`: the server must
//!   close them with UNAVAILABLE after `stream_idle_timeout_secs`;
//! - *slow readers* (16): send batches and never read an answer: they must be held back
//!   (HTTP/2 flow control and the server's bounded answer queue), not buffered without end;
//! - *oversized* (8): send a message over `max_message_bytes`: RESOURCE_EXHAUSTED.
//!
//! Every status is checked against what its behaviour expects; anything else counts as an
//! unexpected error. The server's resident memory (VmRSS) is sampled every second, and
//! batch latency is kept per window. At the end every pool is read and checked against
//! SPEC §6 (size, seqs, actions). The report (markdown) is printed and the exit status is
//! non-zero if a figure is off: an unexpected error, memory grown more than 10 % after
//! warm-up (the first fifth of the run), p99 latency of the second half over 3x the
//! first half's, a pool breaking §6, or abusers not held back.
//!
//! `cargo bench --bench soak -- --secs 1800` (default 60). Data dir under
//! `$TAMRM_BENCH_DIR` if set, else the system temp dir.

use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use parking_lot::Mutex;
use prost::Message;
use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::{self, shape_request, shape_response, ShapeRequest};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::Code;

const TASKS: usize = 8;
const NUM_ACTIONS: u32 = 4;
const CAPACITY: u32 = 16;
const LEARNERS: usize = 200;
const DROPPERS: usize = 16;
const SILENT: usize = 16;
const SLOW: usize = 16;
const OVERSIZED: usize = 8;
const IDLE_SECS: u64 = 5;
const MAX_MESSAGE: usize = 1 << 20;

/// xorshift64*, for repeatable runs without extra dependencies.
struct Rng(u64);
impl Rng {
    fn below(&mut self, n: u64) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) % n
    }
}

/// What the run saw.
#[derive(Default)]
struct Tally {
    batches: AtomicU64,
    entries: AtomicU64,
    invalid_sent: AtomicU64,
    invalid_refused: AtomicU64,
    streams_opened: AtomicU64,
    dropped: AtomicU64,
    silent_closed: AtomicU64,
    oversized_refused: AtomicU64,
    slow_sent: AtomicU64,
    slow_held_back: AtomicU64,
    unexpected: AtomicU64,
    /// The first few unexpected statuses, for the report.
    examples: Mutex<Vec<String>>,
    /// Per window of the run: batch latencies (µs).
    windows: Mutex<Vec<Vec<u32>>>,
}

impl Tally {
    fn unexpected(&self, what: String) {
        self.unexpected.fetch_add(1, Ordering::Relaxed);
        let mut e = self.examples.lock();
        if e.len() < 10 {
            e.push(what);
        }
    }

    fn latency(&self, window: usize, d: Duration) {
        let mut w = self.windows.lock();
        if w.len() <= window {
            w.resize(window + 1, Vec::new());
        }
        w[window].push(d.as_micros().min(u128::from(u32::MAX)) as u32);
    }
}

struct Server {
    child: Child,
    addr: String,
    _dir: tempfile::TempDir,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_server() -> Server {
    let dir = match std::env::var_os("TAMRM_BENCH_DIR") {
        Some(d) => tempfile::tempdir_in(d),
        None => tempfile::tempdir(),
    }
    .expect("a temp dir");
    let port_file = dir.path().join("port");
    let child = Command::new(env!("CARGO_BIN_EXE_tamrm"))
        .args(["serve", "--listen", "127.0.0.1:0", "--port-file"])
        .arg(&port_file)
        .arg("--data-dir")
        .arg(dir.path().join("data"))
        .env("TAMRM_STREAM_IDLE_TIMEOUT_SECS", IDLE_SECS.to_string())
        .env("TAMRM_MAX_MESSAGE_BYTES", MAX_MESSAGE.to_string())
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn tamrm");
    let deadline = Instant::now() + Duration::from_secs(30);
    let addr = loop {
        if let Some(a) = std::fs::read_to_string(&port_file)
            .ok()
            .filter(|s| s.trim().parse::<std::net::SocketAddr>().is_ok())
        {
            break a.trim().to_string();
        }
        assert!(
            Instant::now() < deadline,
            "tamrm did not write its port file"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    Server {
        child,
        addr,
        _dir: dir,
    }
}

/// The server's resident memory, KiB.
fn rss_kib(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse().ok())
        })
        .unwrap_or(0)
}

/// A connection of its own (each abuser its own, so that dropping it is abrupt).
async fn connect(addr: &str) -> ShapingClient<Channel> {
    let channel = Channel::from_shared(format!("http://{addr}"))
        .expect("an address")
        .connect()
        .await
        .expect("connect");
    ShapingClient::new(channel)
        .max_decoding_message_size(usize::MAX)
        .max_encoding_message_size(usize::MAX)
}

fn task_id(i: usize) -> String {
    format!("soak-{i}")
}

fn open(task: &str, num_envs: u32) -> ShapeRequest {
    ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: task.into(),
            num_envs,
            ..Default::default()
        })),
    }
}

/// A batch for every env of `n`; `bad` makes it invalid in one of three ways: an action
/// out of range, a NaN reward, one `terminated` too many.
fn batch(rng: &mut Rng, n: u32, bad: Option<u64>) -> ShapeRequest {
    let mut b = proto::StepBatch {
        env_ids: (0..n).collect(),
        actions: (0..n)
            .map(|_| rng.below(u64::from(NUM_ACTIONS)) as u32)
            .collect(),
        rewards: (0..n).map(|_| rng.below(5) as f64 - 1.0).collect(),
        terminated: (0..n).map(|_| rng.below(40) == 0).collect(),
        truncated: (0..n).map(|_| rng.below(200) == 0).collect(),
        ..Default::default()
    };
    match bad {
        Some(0) => b.actions[0] = NUM_ACTIONS + 3,
        Some(1) => b.rewards[0] = f64::NAN,
        Some(_) => b.terminated.push(false),
        None => {}
    }
    ShapeRequest {
        kind: Some(shape_request::Kind::Steps(b)),
    }
}

/// Opens a stream: the sender of its requests and its answers.
async fn shape(
    c: &mut ShapingClient<Channel>,
    first: ShapeRequest,
) -> Result<
    (
        mpsc::Sender<ShapeRequest>,
        tonic::Streaming<proto::ShapeResponse>,
    ),
    tonic::Status,
> {
    let (tx, rx) = mpsc::channel(1);
    tx.send(first)
        .await
        .map_err(|_| tonic::Status::cancelled("closed"))?;
    let answers = c.shape(ReceiverStream::new(rx)).await?.into_inner();
    Ok((tx, answers))
}

struct Run {
    tally: Arc<Tally>,
    addr: String,
    start: Instant,
    end: Instant,
    window: Duration,
}

impl Run {
    fn window_of(&self, t: Instant) -> usize {
        (t.duration_since(self.start).as_secs_f64() / self.window.as_secs_f64()) as usize
    }

    fn going(&self) -> bool {
        Instant::now() < self.end
    }
}

/// A well-behaved learner that sends an invalid batch now and then.
async fn learner(run: Arc<Run>, seed: u64) {
    let mut rng = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1);
    let mut c = connect(&run.addr).await;
    while run.going() {
        let n = [1, 2, 4, 8, 16, 32, 64][rng.below(7) as usize];
        let task = task_id(rng.below(TASKS as u64) as usize);
        let (tx, mut answers) = match shape(&mut c, open(&task, n)).await {
            Ok(s) => s,
            Err(e) => {
                run.tally.unexpected(format!("open: {e:?}"));
                continue;
            }
        };
        match answers.message().await {
            Ok(Some(proto::ShapeResponse {
                kind: Some(shape_response::Kind::Opened(_)),
            })) => {}
            other => {
                run.tally.unexpected(format!("opened: {other:?}"));
                continue;
            }
        }
        run.tally.streams_opened.fetch_add(1, Ordering::Relaxed);
        // A stream lives for 20–500 batches.
        let length = 20 + rng.below(480);
        for _ in 0..length {
            if !run.going() {
                break;
            }
            let bad = (rng.below(50) == 0).then(|| rng.below(3));
            let sent = Instant::now();
            if tx.send(batch(&mut rng, n, bad)).await.is_err() {
                run.tally.unexpected("the request stream closed".into());
                break;
            }
            match (answers.message().await, bad) {
                (Ok(Some(_)), None) => {
                    run.tally.latency(run.window_of(sent), sent.elapsed());
                    run.tally.batches.fetch_add(1, Ordering::Relaxed);
                    run.tally.entries.fetch_add(u64::from(n), Ordering::Relaxed);
                }
                (Err(s), Some(kind)) => {
                    run.tally.invalid_sent.fetch_add(1, Ordering::Relaxed);
                    let field =
                        ["steps.actions", "steps.rewards", "steps.terminated"][kind as usize];
                    if s.code() == Code::InvalidArgument && s.message().contains(field) {
                        run.tally.invalid_refused.fetch_add(1, Ordering::Relaxed);
                    } else {
                        run.tally
                            .unexpected(format!("invalid batch ({field}): {s:?}"));
                    }
                    break;
                }
                (other, bad) => {
                    run.tally
                        .unexpected(format!("batch (invalid: {bad:?}): {other:?}"));
                    break;
                }
            }
        }
    }
}

/// Opens, sends a few batches, and drops its connection mid-stream.
async fn dropper(run: Arc<Run>, seed: u64) {
    let mut rng = Rng(seed | 1);
    while run.going() {
        let mut c = connect(&run.addr).await;
        let task = task_id(rng.below(TASKS as u64) as usize);
        if let Ok((tx, mut answers)) = shape(&mut c, open(&task, 4)).await {
            let _ = answers.message().await;
            for _ in 0..rng.below(20) {
                let _ = tx.send(batch(&mut rng, 4, None)).await;
                if rng.below(2) == 0 {
                    let _ = answers.message().await;
                }
            }
            run.tally.dropped.fetch_add(1, Ordering::Relaxed);
        }
        drop(c); // the connection goes with its last handle: no half-close
        tokio::time::sleep(Duration::from_millis(rng.below(200))).await;
    }
}

/// Opens the RPC and never sends: the server must end it after its idle timeout.
async fn silent(run: Arc<Run>) {
    while run.going() {
        let mut c = connect(&run.addr).await;
        let (tx, rx) = mpsc::channel::<ShapeRequest>(1);
        let opened = Instant::now();
        match c.shape(ReceiverStream::new(rx)).await {
            Ok(r) => {
                let mut answers = r.into_inner();
                let end =
                    tokio::time::timeout(Duration::from_secs(IDLE_SECS * 4), answers.message())
                        .await;
                match end {
                    Ok(Err(s)) if s.code() == Code::Unavailable && s.message().contains("idle") => {
                        let waited = opened.elapsed();
                        if waited + Duration::from_millis(500) < Duration::from_secs(IDLE_SECS) {
                            run.tally
                                .unexpected(format!("closed early after {waited:?}"));
                        } else {
                            run.tally.silent_closed.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    other => run.tally.unexpected(format!("silent stream: {other:?}")),
                }
            }
            Err(e) => run.tally.unexpected(format!("silent open: {e:?}")),
        }
        drop(tx);
    }
}

/// Sends as fast as it can and never reads: how far it gets is the server's buffering.
async fn slow_reader(run: Arc<Run>, seed: u64) -> u64 {
    let mut rng = Rng(seed | 1);
    let mut c = connect(&run.addr).await;
    let task = task_id(rng.below(TASKS as u64) as usize);
    let Ok((tx, answers)) = shape(&mut c, open(&task, 64)).await else {
        run.tally.unexpected("slow reader: open".into());
        return 0;
    };
    let mut sent = 0u64;
    // Sends until the stream stops taking messages for 2 s (held back) or the run ends.
    while run.going() {
        match tokio::time::timeout(Duration::from_secs(2), tx.send(batch(&mut rng, 64, None))).await
        {
            Ok(Ok(())) => sent += 1,
            Ok(Err(_)) => break,
            Err(_) => {
                // Held back: wait until the end without reading.
                run.tally.slow_held_back.fetch_add(1, Ordering::Relaxed);
                tokio::time::sleep(run.end.saturating_duration_since(Instant::now())).await;
                break;
            }
        }
    }
    run.tally.slow_sent.fetch_add(sent, Ordering::Relaxed);
    drop(answers);
    sent
}

/// Sends a message over the server's limit, now and then.
async fn oversized(run: Arc<Run>) {
    let mut c = connect(&run.addr).await;
    let n = (MAX_MESSAGE / 8 + 1024) as u32;
    while run.going() {
        let req = ShapeRequest {
            kind: Some(shape_request::Kind::Steps(proto::StepBatch {
                env_ids: (0..n).collect(),
                actions: vec![0; n as usize],
                rewards: vec![1.0; n as usize],
                ..Default::default()
            })),
        };
        match shape(&mut c, open(&task_id(0), 1)).await {
            Ok((tx, mut answers)) => {
                let _ = answers.message().await;
                let _ = tx.send(req).await;
                match answers.message().await {
                    Err(s) if s.code() == Code::ResourceExhausted => {
                        run.tally.oversized_refused.fetch_add(1, Ordering::Relaxed);
                    }
                    other => run.tally.unexpected(format!("oversized: {other:?}")),
                }
            }
            Err(e) => run.tally.unexpected(format!("oversized open: {e:?}")),
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

fn pct(v: &mut [u32], p: f64) -> u32 {
    if v.is_empty() {
        return 0;
    }
    v.sort_unstable();
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// Checks every pool against SPEC §6; the problems found.
async fn check_pools(addr: &str) -> Vec<String> {
    let mut c = connect(addr).await;
    let mut problems = Vec::new();
    for i in 0..TASKS {
        let id = task_id(i);
        let pool = match c
            .get_pool(proto::GetPoolRequest {
                task_id: id.clone(),
            })
            .await
        {
            Ok(p) => p.into_inner(),
            Err(e) => {
                problems.push(format!("{id}: GetPool {e:?}"));
                continue;
            }
        };
        if pool.trajectories.len() > CAPACITY as usize {
            problems.push(format!("{id}: {} trajectories", pool.trajectories.len()));
        }
        let seqs: Vec<u64> = pool.trajectories.iter().map(|t| t.seq).collect();
        if seqs.windows(2).any(|w| w[0] >= w[1]) {
            problems.push(format!("{id}: seqs {seqs:?}"));
        }
        for t in &pool.trajectories {
            if t.actions.is_empty() || t.actions.iter().any(|&a| a >= NUM_ACTIONS) {
                problems.push(format!("{id}: trajectory {} actions", t.seq));
            }
            if !t.score.is_finite() {
                problems.push(format!("{id}: trajectory {} score", t.seq));
            }
        }
        if pool.trajectories.len() < CAPACITY as usize {
            problems.push(format!(
                "{id}: only {} trajectories after the soak (the pool should be full)",
                pool.trajectories.len()
            ));
        }
    }
    problems
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let secs: u64 = args
        .iter()
        .position(|a| a == "--secs")
        .and_then(|i| args.get(i + 1))
        .and_then(|s| s.parse().ok())
        .unwrap_or(60);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let server = start_server();
    let pid = server.child.id();
    let code = rt.block_on(async {
        let mut admin = connect(&server.addr).await;
        for i in 0..TASKS {
            admin
                .create_task(proto::CreateTaskRequest {
                    task_id: task_id(i),
                    config: Some(proto::TaskConfig {
                        num_actions: NUM_ACTIONS,
                        pool_capacity: Some(CAPACITY),
                        k: Some(3),
                        start_step: Some(2),
                        min_pool_size: Some(4),
                        ..Default::default()
                    }),
                })
                .await
                .expect("create a task");
        }
        let start = Instant::now();
        let window = Duration::from_secs((secs / 10).max(1));
        let run = Arc::new(Run {
            tally: Arc::new(Tally::default()),
            addr: server.addr.clone(),
            start,
            end: start + Duration::from_secs(secs),
            window,
        });
        let mut joins = Vec::new();
        for i in 0..LEARNERS {
            joins.push(tokio::spawn(learner(run.clone(), i as u64 + 1)));
        }
        for i in 0..DROPPERS {
            joins.push(tokio::spawn(dropper(run.clone(), 1000 + i as u64)));
        }
        for _ in 0..SILENT {
            joins.push(tokio::spawn(silent(run.clone())));
        }
        let mut slow = Vec::new();
        for i in 0..SLOW {
            slow.push(tokio::spawn(slow_reader(run.clone(), 2000 + i as u64)));
        }
        for _ in 0..OVERSIZED {
            joins.push(tokio::spawn(oversized(run.clone())));
        }
        // Memory, every second.
        let mut rss = Vec::new();
        while run.going() {
            rss.push((start.elapsed().as_secs_f64(), rss_kib(pid)));
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        rss.push((start.elapsed().as_secs_f64(), rss_kib(pid)));
        for j in joins {
            let _ = tokio::time::timeout(Duration::from_secs(IDLE_SECS * 6), j).await;
        }
        let mut slow_sent = Vec::new();
        for j in slow {
            slow_sent.push(j.await.unwrap_or(0));
        }
        let problems = check_pools(&server.addr).await;
        let t = &run.tally;

        // Memory after warm-up (the first fifth of the run): growth of the last fifth's
        // median over the second fifth's.
        let fifth = |k: usize| -> u64 {
            let lo = secs as f64 * k as f64 / 5.0;
            let hi = secs as f64 * (k + 1) as f64 / 5.0;
            let mut v: Vec<u64> = rss.iter().filter(|(s, _)| *s >= lo && *s < hi).map(|r| r.1).collect();
            v.sort_unstable();
            v.get(v.len() / 2).copied().unwrap_or(0)
        };
        let (warm, last) = (fifth(1), fifth(4));
        let growth = if warm == 0 { 0.0 } else { (last as f64 / warm as f64 - 1.0) * 100.0 };
        let peak = rss.iter().map(|r| r.1).max().unwrap_or(0);

        println!("# Soak: {secs} s, {} streams at once, {TASKS} tasks", LEARNERS + DROPPERS + SILENT + SLOW + OVERSIZED);
        println!();
        println!("| figure | value |");
        println!("|---|---|");
        println!("| batches answered (learners) | {} |", t.batches.load(Ordering::Relaxed));
        println!("| env-steps shaped (learners) | {} |", t.entries.load(Ordering::Relaxed));
        println!("| learner streams opened | {} |", t.streams_opened.load(Ordering::Relaxed));
        println!(
            "| invalid batches refused with INVALID_ARGUMENT naming the field | {} of {} |",
            t.invalid_refused.load(Ordering::Relaxed),
            t.invalid_sent.load(Ordering::Relaxed)
        );
        println!("| streams dropped mid-stream | {} |", t.dropped.load(Ordering::Relaxed));
        println!(
            "| silent streams closed by the server after {IDLE_SECS} s idle | {} |",
            t.silent_closed.load(Ordering::Relaxed)
        );
        println!(
            "| oversized messages refused (RESOURCE_EXHAUSTED) | {} |",
            t.oversized_refused.load(Ordering::Relaxed)
        );
        slow_sent.sort_unstable();
        let held = t.slow_held_back.load(Ordering::Relaxed);
        println!(
            "| slow readers held back (no send accepted for 2 s) | {held} of {SLOW} |"
        );
        println!(
            "| batches (64 envs, ~{} B each) a slow reader got in before being held back: median, max | {}, {} |",
            batch(&mut Rng(1), 64, None).encoded_len(),
            slow_sent.get(slow_sent.len() / 2).copied().unwrap_or(0),
            slow_sent.last().copied().unwrap_or(0)
        );
        println!("| unexpected errors | {} |", t.unexpected.load(Ordering::Relaxed));
        println!(
            "| server RSS: after warm-up, at the end, growth, peak | {} MiB, {} MiB, {growth:+.1} %, {} MiB |",
            warm / 1024,
            last / 1024,
            peak / 1024
        );
        println!("| pools breaking SPEC §6 | {} |", problems.len());
        println!();
        println!("| window | batches | p50 µs | p99 µs |");
        println!("|---|---|---|---|");
        let mut p99s = Vec::new();
        for (i, w) in t.windows.lock().iter_mut().enumerate() {
            let (p50, p99) = (pct(w, 0.5), pct(w, 0.99));
            if !w.is_empty() {
                p99s.push(p99);
            }
            println!("| {}–{} s | {} | {p50} | {p99} |", i as u64 * window.as_secs(), (i as u64 + 1) * window.as_secs(), w.len());
        }
        for e in t.examples.lock().iter() {
            println!("unexpected: {e}");
        }
        for p in &problems {
            println!("pool: {p}");
        }
        // Latency stable: the median p99 of the windows of the second half at most 3x
        // that of the first half after warm-up (the first window).
        let half = |w: &[u32]| -> u32 {
            let mut v = w.to_vec();
            v.sort_unstable();
            v.get(v.len() / 2).copied().unwrap_or(0)
        };
        let warm_p99s = p99s.get(1..).unwrap_or(&[]);
        let mid = warm_p99s.len() / 2;
        let (early, late) = (half(&warm_p99s[..mid]), half(&warm_p99s[mid..]));
        let stable = early == 0 || late <= early.saturating_mul(3);
        println!(
            "| p99 batch latency, median over windows: first half after warm-up, second half | {early} µs, {late} µs |"
        );
        if !stable {
            println!("p99 latency grew more than 3x");
        }
        let held_back = held == SLOW as u64;
        if !held_back {
            println!("slow readers were not all held back");
        }
        let ok = t.unexpected.load(Ordering::Relaxed) == 0
            && problems.is_empty()
            && growth <= 10.0
            && held_back
            && stable
            && t.silent_closed.load(Ordering::Relaxed) > 0
            && t.oversized_refused.load(Ordering::Relaxed) > 0
            && t.invalid_refused.load(Ordering::Relaxed) > 0;
        println!();
        println!("verdict: {}", if ok { "PASS" } else { "FAIL" });
        i32::from(!ok)
    });
    drop(server);
    std::process::exit(code);
}
