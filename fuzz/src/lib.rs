//! The fuzz harness (docs/fuzzing.md): the real `tamrm.v1.Shaping` service, as the server
//! assembles it (`ShapingRoutes`: the Shape stream's codec and the generated
//! `ShapingServer`, their message size limits, and the status remapping of
//! `tamrm::service::status`), driven in-process with raw gRPC frames through
//! `tower::Service::call`, against a live registry; and the checks made after every
//! message:
//!
//! - no status that means a bug of ours (`INTERNAL`, `UNKNOWN`, `DATA_LOSS`), no panic
//!   (libFuzzer reports it), no hang (each answer is awaited for at most 10 s);
//! - every pool satisfies SPEC §6: at most `pool_capacity` trajectories, seqs strictly
//!   increasing and below `next_seq`, actions of the task's action space, finite scores,
//!   a version that never goes back;
//! - a request that failed changed no pool;
//! - every shaped number is finite.

use std::collections::HashMap;
use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use bytes::{Buf, BufMut, Bytes, BytesMut};
use http_body_util::BodyExt;
use prost::Message;
use tamrm::core::{ActionSeq, ActionSpace, Pool};
use tamrm::limits::Limits;
use tamrm::proto::{self, shape_response, ShapeResponse};
use tamrm::registry::{Registry, DEFAULT_TENANT};
use tamrm::service::status::remap_response_headers;
use tamrm::service::{ShapingRoutes, ShapingService};
use tamrm::store::{MemoryStore, Store};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tonic::{Code, Status};
use tower::Service;

/// The limits of the fuzzed server: the defaults, with messages capped at 8 KiB so that
/// inputs can reach the size limit.
pub fn limits() -> Limits {
    Limits {
        max_message_bytes: 8 * 1024,
        max_batch_entries: 256,
        max_envs_per_stream: 64,
        max_tasks: 16,
        ..Limits::default()
    }
}

/// The tasks every run starts with: `d` discrete (3 actions, pool of 3, k 2, N 1), `c`
/// continuous (2-dimensional), `g` discrete with the potential gated and the kNN term
/// waiting for a spread of scores (SPEC v1.3).
pub fn task_configs() -> Vec<(&'static str, proto::TaskConfig)> {
    vec![
        (
            "d",
            proto::TaskConfig {
                num_actions: 3,
                pool_capacity: Some(3),
                k: Some(2),
                start_step: Some(1),
                min_pool_size: Some(1),
                ..Default::default()
            },
        ),
        (
            "c",
            proto::TaskConfig {
                action_dim: 2,
                pool_capacity: Some(2),
                k: Some(1),
                start_step: Some(0),
                min_pool_size: Some(1),
                ..Default::default()
            },
        ),
        (
            "g",
            proto::TaskConfig {
                num_actions: 4,
                pool_capacity: Some(4),
                k: Some(3),
                start_step: Some(2),
                min_pool_size: Some(4),
                gate_potential: Some(true),
                require_score_spread: Some(true),
                max_trajectory_len: Some(64),
                ..Default::default()
            },
        ),
    ]
}

/// The single-threaded runtime every input runs on.
pub fn runtime() -> &'static tokio::runtime::Runtime {
    static RT: std::sync::OnceLock<tokio::runtime::Runtime> = std::sync::OnceLock::new();
    RT.get_or_init(|| {
        tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .expect("a tokio runtime")
    })
}

/// The gRPC service under test, the way `tamrm::server` stacks it.
#[derive(Clone)]
pub struct Harness {
    pub registry: Arc<Registry>,
    svc: ShapingRoutes,
    /// The last version seen per task (a version never goes back).
    seen: HashMap<String, u64>,
}

/// What one request got: the messages answered and the final status.
#[derive(Debug)]
pub struct Answer {
    pub messages: Vec<Bytes>,
    pub status: Status,
}

/// A gRPC frame: uncompressed flag, big-endian length, the message.
pub fn frame(msg: &[u8]) -> Bytes {
    let mut b = BytesMut::with_capacity(msg.len() + 5);
    b.put_u8(0);
    b.put_u32(msg.len() as u32);
    b.put_slice(msg);
    b.freeze()
}

/// Splits `data` into length-prefixed chunks: a little-endian u16 length, then that many
/// bytes (fewer at the end of the input).
pub fn chunks(mut data: &[u8]) -> Vec<&[u8]> {
    let mut out = Vec::new();
    while data.len() >= 2 {
        let n = usize::from(u16::from_le_bytes([data[0], data[1]]));
        data = &data[2..];
        let n = n.min(data.len());
        out.push(&data[..n]);
        data = &data[n..];
    }
    out
}

/// The inverse of [`chunks`], for seeds.
pub fn join_chunks(parts: &[Vec<u8>]) -> Vec<u8> {
    let mut out = Vec::new();
    for p in parts {
        out.extend_from_slice(&(p.len() as u16).to_le_bytes());
        out.extend_from_slice(p);
    }
    out
}

/// A code that only a bug of ours may produce.
pub fn assert_not_ours(what: &str, status: &Status) {
    assert!(
        !matches!(
            status.code(),
            Code::Internal | Code::Unknown | Code::DataLoss
        ),
        "{what}: {:?} {}",
        status.code(),
        status.message()
    );
}

/// A snapshot of every pool: key → (version, seqs).
pub type Pools = HashMap<String, (u64, Vec<u64>)>;

/// Checks one pool against SPEC §6 and the task's action space.
pub fn check_pool(key: &str, pool: &Pool, space: ActionSpace, max_len: usize) {
    assert!(pool.len() <= pool.capacity(), "{key}: over capacity");
    for w in pool.seqs().windows(2) {
        assert!(w[0] < w[1], "{key}: seqs not increasing {:?}", pool.seqs());
    }
    for t in pool.trajectories() {
        assert!(t.seq < pool.next_seq(), "{key}: seq {} >= next_seq", t.seq);
        assert!(t.score.is_finite(), "{key}: score {}", t.score);
        assert!(!t.actions.is_empty(), "{key}: empty trajectory");
        assert!(t.actions.len() <= max_len, "{key}: longer than the limit");
        match (&t.actions, space) {
            (ActionSeq::Discrete(a), ActionSpace::Discrete { num_actions }) => {
                assert!(
                    a.iter().all(|&x| x < num_actions),
                    "{key}: action out of range"
                );
            }
            (ActionSeq::Continuous { dim, data }, ActionSpace::Continuous { action_dim }) => {
                assert_eq!(*dim, action_dim as usize, "{key}: action dim");
                assert!(
                    data.iter().all(|x| x.is_finite()),
                    "{key}: non-finite action"
                );
            }
            _ => panic!("{key}: a trajectory of the wrong action space"),
        }
    }
}

impl Harness {
    /// A fresh in-memory registry with [`task_configs`] created through `CreateTask`.
    pub async fn new() -> Harness {
        Harness::with_store(Arc::new(MemoryStore::new())).await
    }

    /// A fresh registry over `store` (its tasks restored), with [`task_configs`] created.
    pub async fn with_store(store: Arc<dyn Store>) -> Harness {
        let mut h = Harness::over(store).await;
        for (id, config) in task_configs() {
            let req = proto::CreateTaskRequest {
                task_id: id.into(),
                config: Some(config),
            };
            let a = h.unary("CreateTask", &req.encode_to_vec()).await;
            assert_eq!(a.status.code(), Code::Ok, "{:?}", a.status);
        }
        h.check();
        h
    }

    /// A registry over `store` with the tasks it restores, nothing created.
    pub async fn over(store: Arc<dyn Store>) -> Harness {
        let limits = limits();
        let (registry, _) = Registry::open(store, limits)
            .await
            .expect("the registry opens");
        let registry = Arc::new(registry);
        let service = ShapingService::new(registry.clone(), CancellationToken::new());
        let svc = ShapingRoutes::new(service, limits.max_message_bytes);
        Harness {
            registry,
            svc,
            seen: HashMap::new(),
        }
    }

    /// Every pool's version and seqs.
    pub fn pools(&self) -> Pools {
        self.registry
            .held(DEFAULT_TENANT)
            .iter()
            .map(|t| {
                let p = t.snapshot();
                (t.key().to_string(), (p.version(), p.seqs().to_vec()))
            })
            .collect()
    }

    /// Checks every pool (SPEC §6) and that no version went back; the pools. A task
    /// deleted since the last check is forgotten: one created again under its id starts
    /// at version 0.
    pub fn check(&mut self) -> Pools {
        let held = self.registry.held(DEFAULT_TENANT);
        self.seen
            .retain(|k, _| held.iter().any(|t| t.key() == k.as_str()));
        for t in held {
            let p = t.snapshot();
            let c = t.config();
            check_pool(t.key(), &p, c.action_space, c.max_trajectory_len as usize);
            let seen = self.seen.entry(t.key().to_string()).or_insert(0);
            assert!(p.version() >= *seen, "{}: version went back", t.key());
            *seen = p.version();
        }
        self.pools()
    }

    fn request(path: &str, body: tonic::body::Body) -> http::Request<tonic::body::Body> {
        http::Request::builder()
            .method("POST")
            .uri(format!("http://fuzz/tamrm.v1.Shaping/{path}"))
            .header("content-type", "application/grpc")
            .header("te", "trailers")
            .body(body)
            .expect("a request")
    }

    /// Calls a unary method with `msg` as the request's bytes.
    pub async fn unary(&mut self, method: &str, msg: &[u8]) -> Answer {
        let body = tonic::body::Body::new(http_body_util::Full::new(frame(msg)));
        let res = self.call(method, body).await;
        let mut reader = Reader::new(res);
        let mut messages = Vec::new();
        loop {
            match bounded(reader.next()).await {
                Item::Message(m) => messages.push(m),
                Item::End(status) => return Answer { messages, status },
            }
        }
    }

    async fn call(
        &mut self,
        method: &str,
        body: tonic::body::Body,
    ) -> http::Response<tonic::body::Body> {
        let svc = tower::ServiceExt::<http::Request<tonic::body::Body>>::ready(&mut self.svc)
            .await
            .unwrap_or_else(|e: Infallible| match e {});
        let res = bounded(svc.call(Harness::request(method, body)))
            .await
            .unwrap_or_else(|e: Infallible| match e {});
        remap_response_headers(res)
    }

    /// Opens a `Shape` stream.
    pub async fn stream(&mut self) -> Stream {
        let (tx, rx) = mpsc::channel::<Result<http_body::Frame<Bytes>, Infallible>>(4);
        let body = tonic::body::Body::new(http_body_util::StreamBody::new(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        ));
        let res = self.call("Shape", body).await;
        Stream {
            tx: Some(tx),
            reader: Reader::new(res),
            ended: None,
        }
    }
}

/// One open `Shape` stream, driven in lockstep: one message sent, one answer read.
pub struct Stream {
    tx: Option<mpsc::Sender<Result<http_body::Frame<Bytes>, Infallible>>>,
    reader: Reader,
    /// The final status, once the stream ended.
    pub ended: Option<Status>,
}

impl Stream {
    /// Sends `msg` (raw bytes of a `ShapeRequest`) and reads its answer: `Some` response,
    /// or `None` if the stream ended (its status in `ended`).
    pub async fn send(&mut self, msg: &[u8]) -> Option<ShapeResponse> {
        if self.ended.is_some() {
            return None;
        }
        if let Some(tx) = &self.tx {
            // The server may have stopped reading (the stream ended): then the answer below
            // is the end.
            let _ = tx.send(Ok(http_body::Frame::data(frame(msg)))).await;
        }
        match bounded(self.reader.next()).await {
            Item::Message(m) => {
                Some(ShapeResponse::decode(m).expect("the server's answers decode"))
            }
            Item::End(status) => {
                self.ended = Some(status);
                None
            }
        }
    }

    /// Half-closes and reads the end.
    pub async fn close(&mut self) -> Status {
        self.tx = None;
        while self.ended.is_none() {
            if let Item::End(s) = bounded(self.reader.next()).await {
                self.ended = Some(s);
            }
        }
        self.ended.clone().unwrap_or_else(|| Status::ok(""))
    }
}

/// Checks a shaped answer: finite numbers, one output per entry.
pub fn check_answer(answer: &ShapeResponse) {
    if let Some(shape_response::Kind::Shaped(s)) = &answer.kind {
        let n = s.rewards.len();
        assert!(
            s.knn_rewards.len() == n && s.potentials.len() == n && s.steps.len() == n,
            "one output per entry"
        );
        for (name, xs) in [
            ("rewards", &s.rewards),
            ("knn_rewards", &s.knn_rewards),
            ("potentials", &s.potentials),
        ] {
            for (i, x) in xs.iter().enumerate() {
                assert!(x.is_finite(), "{name}[{i}] = {x}");
            }
        }
    }
}

pub mod seeds;
pub mod targets;

enum Item {
    Message(Bytes),
    End(Status),
}

/// Reads gRPC messages and the final status from a response.
struct Reader {
    headers_status: Option<Status>,
    body: tonic::body::Body,
    buf: BytesMut,
    done: bool,
}

impl Reader {
    fn new(res: http::Response<tonic::body::Body>) -> Reader {
        let headers_status = Status::from_header_map(res.headers());
        Reader {
            headers_status,
            body: res.into_body(),
            buf: BytesMut::new(),
            done: false,
        }
    }

    async fn next(&mut self) -> Item {
        if let Some(s) = self.headers_status.take() {
            if s.code() != Code::Ok {
                self.done = true;
                return Item::End(s);
            }
        }
        loop {
            if self.buf.len() >= 5 {
                let n = u32::from_be_bytes([self.buf[1], self.buf[2], self.buf[3], self.buf[4]])
                    as usize;
                if self.buf.len() >= 5 + n {
                    self.buf.advance(5);
                    return Item::Message(self.buf.split_to(n).freeze());
                }
            }
            if self.done {
                return Item::End(Status::unknown("the response ended without a status"));
            }
            match self.body.frame().await {
                Some(Ok(f)) => match f.into_data() {
                    Ok(d) => self.buf.extend_from_slice(&d),
                    Err(f) => {
                        if let Ok(trailers) = f.into_trailers() {
                            self.done = true;
                            return Item::End(
                                Status::from_header_map(&trailers).unwrap_or_else(|| {
                                    Status::unknown("trailers without a status")
                                }),
                            );
                        }
                    }
                },
                Some(Err(e)) => {
                    self.done = true;
                    return Item::End(Status::unknown(format!("response body error: {e}")));
                }
                None => {
                    self.done = true;
                    return Item::End(Status::unknown("the response ended without trailers"));
                }
            }
        }
    }
}

/// Awaits `f` for at most 10 s: longer is a hang, a bug.
async fn bounded<F: std::future::Future>(f: F) -> F::Output {
    tokio::time::timeout(Duration::from_secs(10), f)
        .await
        .expect("the server answers within 10 s (a hang otherwise)")
}
