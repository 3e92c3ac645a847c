//! Shared helpers for integration tests: a real server on a real socket.
#![allow(dead_code)]

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::{
    self, follow_request, follow_response, shape_request, shape_response, FollowRequest,
    FollowResponse, ShapeRequest, ShapeResponse,
};
use tamrm::server::RunningServer;
use tamrm::settings::Settings;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::Streaming;

pub type Client = ShapingClient<Channel>;

/// Starts an in-process server on 127.0.0.1:0 with the given settings tweaks.
pub async fn start_server(
    data_dir: Option<&Path>,
    tweak: impl FnOnce(&mut Settings),
) -> RunningServer {
    let mut settings = Settings {
        listen: "127.0.0.1:0".parse().unwrap(),
        data_dir: data_dir.map(Path::to_path_buf),
        shutdown_grace_secs: 10,
        ..Settings::default()
    };
    tweak(&mut settings);
    tamrm::server::start(&settings)
        .await
        .expect("server starts")
}

pub async fn connect(addr: std::net::SocketAddr) -> Client {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        match ShapingClient::connect(format!("http://{addr}")).await {
            Ok(c) => {
                return c
                    .max_decoding_message_size(256 << 20)
                    .max_encoding_message_size(256 << 20)
            }
            Err(e) if Instant::now() > deadline => panic!("cannot connect to {addr}: {e}"),
            Err(_) => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    }
}

/// A discrete task config with everything explicit.
pub fn discrete(
    n: u32,
    capacity: u32,
    k: u32,
    start_step: u32,
    min_pool_size: u32,
) -> proto::TaskConfig {
    proto::TaskConfig {
        num_actions: n,
        pool_capacity: Some(capacity),
        k: Some(k),
        start_step: Some(start_step),
        min_pool_size: Some(min_pool_size),
        ..Default::default()
    }
}

pub async fn create(client: &mut Client, id: &str, config: proto::TaskConfig) -> proto::Task {
    client
        .create_task(proto::CreateTaskRequest {
            task_id: id.into(),
            config: Some(config),
        })
        .await
        .expect("create_task")
        .into_inner()
}

/// GetTask; panics on an error status.
pub async fn get_task(c: &mut Client, id: &str) -> proto::Task {
    c.get_task(proto::GetTaskRequest { task_id: id.into() })
        .await
        .unwrap_or_else(|e| panic!("get_task {id}: {e}"))
        .into_inner()
}

/// GetPool; panics on an error status.
pub async fn get_pool(c: &mut Client, id: &str) -> proto::Pool {
    c.get_pool(proto::GetPoolRequest { task_id: id.into() })
        .await
        .unwrap_or_else(|e| panic!("get_pool {id}: {e}"))
        .into_inner()
}

/// AddTrajectory; panics on an error status.
pub async fn add(c: &mut Client, id: &str, t: proto::Trajectory) -> proto::AddTrajectoryResponse {
    c.add_trajectory(proto::AddTrajectoryRequest {
        task_id: id.into(),
        trajectory: Some(t),
    })
    .await
    .unwrap_or_else(|e| panic!("add_trajectory {id}: {e}"))
    .into_inner()
}

/// A discrete trajectory (its `seq` is set to a value the server must ignore).
/// AddTrajectory of a discrete trajectory: the pool version after, or the status.
pub async fn try_add_discrete(
    c: &mut Client,
    id: &str,
    actions: &[u32],
    score: f64,
) -> Result<u64, tonic::Status> {
    c.add_trajectory(proto::AddTrajectoryRequest {
        task_id: id.into(),
        trajectory: Some(dtraj(actions, score)),
    })
    .await
    .map(|r| r.into_inner().pool_version)
}

pub fn dtraj(actions: &[u32], score: f64) -> proto::Trajectory {
    proto::Trajectory {
        actions: actions.to_vec(),
        score,
        seq: 999_999,
        ..Default::default()
    }
}

/// A continuous trajectory: `L * action_dim` floats, row-major.
pub fn ctraj(action_vectors: &[f32], score: f64) -> proto::Trajectory {
    proto::Trajectory {
        action_vectors: action_vectors.to_vec(),
        score,
        ..Default::default()
    }
}

/// Waits until the task's `open_streams` stat equals `want` (a liveness bound, generous
/// for a loaded CI machine).
pub async fn wait_open_streams(c: &mut Client, id: &str, want: u32) {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let got = get_task(c, id).await.stats.unwrap().open_streams;
        if got == want {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "open_streams of {id} stays {got}, expected {want}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// One open Shape stream driven step by step.
pub struct Stream {
    pub tx: mpsc::Sender<ShapeRequest>,
    pub rx: Streaming<ShapeResponse>,
}

impl Stream {
    /// Opens a stream (sends Open) and returns it with the `opened` task, or the error status.
    pub async fn open(
        client: &mut Client,
        task_id: &str,
        num_envs: u32,
    ) -> Result<(Stream, proto::Task), tonic::Status> {
        let (tx, rx) = mpsc::channel(16);
        tx.send(ShapeRequest {
            kind: Some(shape_request::Kind::Open(proto::Open {
                task_id: task_id.into(),
                num_envs,
                ..Default::default()
            })),
        })
        .await
        .unwrap();
        let mut rx = client.shape(ReceiverStream::new(rx)).await?.into_inner();
        match rx.message().await? {
            Some(ShapeResponse {
                kind: Some(shape_response::Kind::Opened(task)),
            }) => Ok((Stream { tx, rx }, task)),
            other => panic!("expected opened, got {other:?}"),
        }
    }

    /// Opens a raw stream without sending anything.
    pub async fn raw(client: &mut Client) -> Result<Stream, tonic::Status> {
        let (tx, rx) = mpsc::channel(16);
        let rx = client.shape(ReceiverStream::new(rx)).await?.into_inner();
        Ok(Stream { tx, rx })
    }

    pub async fn send(&self, req: ShapeRequest) {
        // The server may already have closed the stream; the error shows up on recv.
        let _ = self.tx.send(req).await;
    }

    pub async fn recv(&mut self) -> Result<Option<ShapeResponse>, tonic::Status> {
        self.rx.message().await
    }

    /// Sends one batch and returns its shaped answer or the error status.
    pub async fn step(
        &mut self,
        batch: proto::StepBatch,
    ) -> Result<proto::ShapedBatch, tonic::Status> {
        self.send(ShapeRequest {
            kind: Some(shape_request::Kind::Steps(batch)),
        })
        .await;
        match self.rx.message().await? {
            Some(ShapeResponse {
                kind: Some(shape_response::Kind::Shaped(b)),
            }) => Ok(b),
            other => panic!("expected shaped, got {other:?}"),
        }
    }

    /// Half-closes the request side.
    pub fn close(self) -> Streaming<ShapeResponse> {
        drop(self.tx);
        self.rx
    }
}

/// One open Follow stream (SPEC §13) with the learner's copy of the task's pool: the
/// snapshot it opened with, every later snapshot and update applied as a learner must
/// (an update only to the version it was made for: a gap panics).
pub struct Follower {
    pub tx: mpsc::Sender<FollowRequest>,
    pub rx: Streaming<FollowResponse>,
    /// The copy: the task id of the snapshot, the pool at the version last received.
    pub pool: proto::Pool,
    /// Updates and snapshots received (the opening snapshot included).
    pub updates: Vec<proto::PoolUpdate>,
    pub snapshots: usize,
}

/// `msg` with `authorization: Bearer <key>`, or without a credential.
pub fn with_key<T>(key: Option<&str>, msg: T) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    if let Some(k) = key {
        r.metadata_mut()
            .insert("authorization", format!("Bearer {k}").parse().unwrap());
    }
    r
}

/// A message of episode ends.
pub fn ends_msg(ends: Vec<proto::EpisodeEnd>, steps: u64) -> FollowRequest {
    FollowRequest {
        kind: Some(follow_request::Kind::Ends(proto::EpisodeEnds {
            ends,
            steps,
        })),
    }
}

/// A discrete episode end: score unset unless `score` is.
pub fn dend(
    env_id: u32,
    episode: u64,
    actions: &[u32],
    score: Option<f64>,
    reward_sum: f64,
) -> proto::EpisodeEnd {
    proto::EpisodeEnd {
        env_id,
        episode,
        actions: actions.to_vec(),
        score,
        reward_sum,
        ..Default::default()
    }
}

impl Follower {
    /// Opens a Follow stream (no credential) and takes its `opened` task and snapshot.
    pub async fn open(
        client: &mut Client,
        task_id: &str,
        num_envs: u32,
        client_id: &str,
    ) -> Result<(Follower, proto::Task), tonic::Status> {
        let open = proto::FollowOpen {
            task_id: task_id.into(),
            num_envs,
            client_id: client_id.into(),
        };
        Follower::open_with(client, None, open).await
    }

    /// Opens a Follow stream with `key` and takes its `opened` task and snapshot.
    pub async fn open_with(
        client: &mut Client,
        key: Option<&str>,
        open: proto::FollowOpen,
    ) -> Result<(Follower, proto::Task), tonic::Status> {
        let task_id = open.task_id.clone();
        let mut f = Follower::raw_with(client, key).await?;
        f.send(FollowRequest {
            kind: Some(follow_request::Kind::Open(open)),
        })
        .await;
        let task = match f.rx.message().await? {
            Some(FollowResponse {
                kind: Some(follow_response::Kind::Opened(task)),
            }) => task,
            other => panic!("expected opened, got {other:?}"),
        };
        assert_eq!(task.task_id, task_id);
        match f.rx.message().await? {
            Some(FollowResponse {
                kind: Some(follow_response::Kind::Snapshot(pool)),
            }) => {
                assert_eq!(pool.task_id, task_id);
                f.pool = pool;
                f.snapshots = 1;
            }
            other => panic!("expected the opening snapshot, got {other:?}"),
        }
        Ok((f, task))
    }

    /// A Follow stream on which nothing is sent yet.
    pub async fn raw(client: &mut Client) -> Result<Follower, tonic::Status> {
        Follower::raw_with(client, None).await
    }

    async fn raw_with(client: &mut Client, key: Option<&str>) -> Result<Follower, tonic::Status> {
        let (tx, rx) = mpsc::channel(16);
        let rx = client
            .follow(with_key(key, ReceiverStream::new(rx)))
            .await?
            .into_inner();
        Ok(Follower {
            tx,
            rx,
            pool: proto::Pool::default(),
            updates: Vec::new(),
            snapshots: 0,
        })
    }

    pub async fn send(&self, req: FollowRequest) {
        // The server may already have closed the stream; the error shows up on recv.
        let _ = self.tx.send(req).await;
    }

    pub async fn recv(&mut self) -> Result<Option<FollowResponse>, tonic::Status> {
        self.rx.message().await
    }

    /// Applies a snapshot or an update to the copy, as a learner does; panics on anything
    /// else, and on an update that does not fit the copy (a gap, a seq it does not hold,
    /// one it holds added again).
    pub fn apply(&mut self, kind: follow_response::Kind) {
        match kind {
            follow_response::Kind::Snapshot(pool) => {
                assert!(
                    pool.pool_version >= self.pool.pool_version,
                    "a snapshot at {} after {}",
                    pool.pool_version,
                    self.pool.pool_version
                );
                assert!(pool.trajectories.windows(2).all(|w| w[0].seq < w[1].seq));
                self.pool = pool;
                self.snapshots += 1;
            }
            follow_response::Kind::Update(u) => {
                assert_eq!(
                    u.base_version, self.pool.pool_version,
                    "an update from version {} to a copy at {}: a gap",
                    u.base_version, self.pool.pool_version
                );
                assert!(u.pool_version > u.base_version, "{u:?}");
                assert!(u.next_seq >= self.pool.next_seq, "{u:?}");
                let trajs = &mut self.pool.trajectories;
                for seq in &u.removed {
                    let before = trajs.len();
                    trajs.retain(|t| t.seq != *seq);
                    assert_eq!(trajs.len() + 1, before, "removed seq {seq} is not held");
                }
                for t in &u.added {
                    assert!(
                        trajs.iter().all(|h| h.seq != t.seq),
                        "added seq {} is already held",
                        t.seq
                    );
                    assert!(t.seq < u.next_seq, "{u:?}");
                    trajs.push(t.clone());
                }
                trajs.sort_by_key(|t| t.seq);
                self.pool.pool_version = u.pool_version;
                self.pool.next_seq = u.next_seq;
                self.updates.push(u);
            }
            other => panic!("expected a snapshot or an update, got {other:?}"),
        }
    }

    /// Receives until an ack, applying the news before it; checks that the copy then
    /// holds at least the ack's version (its changes came first).
    pub async fn ack(&mut self) -> Result<proto::EndsAck, tonic::Status> {
        loop {
            match self.rx.message().await? {
                Some(FollowResponse {
                    kind: Some(follow_response::Kind::Ack(ack)),
                }) => {
                    assert!(
                        self.pool.pool_version >= ack.pool_version,
                        "the ack at version {} came before the updates (copy at {})",
                        ack.pool_version,
                        self.pool.pool_version
                    );
                    return Ok(ack);
                }
                Some(FollowResponse { kind: Some(kind) }) => self.apply(kind),
                other => panic!("expected an ack, got {other:?}"),
            }
        }
    }

    /// Sends one message of ends and returns its ack (the news before it applied).
    pub async fn ends(
        &mut self,
        ends: Vec<proto::EpisodeEnd>,
        steps: u64,
    ) -> Result<proto::EndsAck, tonic::Status> {
        self.send(ends_msg(ends, steps)).await;
        self.ack().await
    }

    /// Applies news until the copy holds version `version` or later (within 10 s).
    pub async fn until_version(&mut self, version: u64) {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        while self.pool.pool_version < version {
            let msg = tokio::time::timeout_at(deadline, self.rx.message())
                .await
                .unwrap_or_else(|_| {
                    panic!(
                        "the follower stays at version {}, expected {version}",
                        self.pool.pool_version
                    )
                });
            match msg {
                Ok(Some(FollowResponse { kind: Some(kind) })) => self.apply(kind),
                other => panic!("expected news, got {other:?}"),
            }
        }
    }

    /// Nothing arrives for `quiet` (the server has nothing to send).
    pub async fn assert_quiet(&mut self, quiet: Duration) {
        if let Ok(msg) = tokio::time::timeout(quiet, self.rx.message()).await {
            panic!("expected nothing, got {msg:?}");
        }
    }

    /// The status the stream ends with (news before it applied), within 10 s.
    pub async fn status(&mut self) -> tonic::Status {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        loop {
            let msg = tokio::time::timeout_at(deadline, self.rx.message())
                .await
                .expect("the stream ends within 10 s");
            match msg {
                Err(status) => return status,
                Ok(Some(FollowResponse {
                    kind:
                        Some(
                            kind @ (follow_response::Kind::Snapshot(_)
                            | follow_response::Kind::Update(_)),
                        ),
                })) => self.apply(kind),
                other => panic!("expected an error status, got {other:?}"),
            }
        }
    }
}

/// A batch of discrete steps: one entry per env in order.
pub fn batch(actions: &[u32], rewards: &[f64], terminated: &[bool]) -> proto::StepBatch {
    proto::StepBatch {
        actions: actions.to_vec(),
        rewards: rewards.to_vec(),
        terminated: terminated.to_vec(),
        ..Default::default()
    }
}

/// The real `tamrm` binary as a child process.
pub struct Binary {
    pub child: Child,
    pub addr: std::net::SocketAddr,
}

impl Binary {
    /// `tamrm serve --listen 127.0.0.1:0 ARGS`.
    pub fn start(args: &[&str]) -> Binary {
        Binary::start_listening_as_told(&[&["--listen", "127.0.0.1:0"][..], args].concat())
    }

    /// `tamrm serve ARGS`, listening where the arguments (or a config file) say.
    pub fn start_listening_as_told(args: &[&str]) -> Binary {
        let dir = tempfile::tempdir().unwrap();
        let port_file = dir.path().join("port");
        let child = Command::new(env!("CARGO_BIN_EXE_tamrm"))
            .arg("serve")
            .arg("--port-file")
            .arg(&port_file)
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn tamrm");
        let deadline = Instant::now() + Duration::from_secs(20);
        let addr = loop {
            if let Ok(s) = std::fs::read_to_string(&port_file) {
                if let Ok(a) = s.trim().parse() {
                    break a;
                }
            }
            assert!(
                Instant::now() < deadline,
                "tamrm did not write its port file"
            );
            std::thread::sleep(Duration::from_millis(20));
        };
        std::mem::forget(dir);
        Binary { child, addr }
    }

    /// Sends SIGTERM and waits for the exit status, with a timeout.
    pub fn terminate(mut self) -> (std::process::ExitStatus, String) {
        let pid = self.child.id().to_string();
        Command::new("kill").args(["-TERM", &pid]).status().unwrap();
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                let mut err = String::new();
                use std::io::Read;
                self.child
                    .stderr
                    .take()
                    .unwrap()
                    .read_to_string(&mut err)
                    .unwrap();
                return (status, err);
            }
            assert!(
                Instant::now() < deadline,
                "tamrm did not exit after SIGTERM"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Binary {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A `redis-server` child process of a test, on a free port, with its own directory and
/// the durable settings of docs/scaling.md (`appendonly yes`, `appendfsync always`).
pub struct RedisServer {
    child: Option<Child>,
    pub port: u16,
    pub dir: tempfile::TempDir,
    extra: Vec<String>,
}

impl RedisServer {
    /// Starts one; panics with a clear message if `redis-server` is not installed.
    pub fn start() -> RedisServer {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        RedisServer::start_with(port, Vec::new())
    }

    /// Starts one with `extra` arguments after the durable ones (a later argument wins).
    pub fn start_with_args(extra: &[&str]) -> RedisServer {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        RedisServer::start_with(port, extra.iter().map(|s| s.to_string()).collect())
    }

    fn start_with(port: u16, extra: Vec<String>) -> RedisServer {
        let mut r = RedisServer {
            child: None,
            port,
            dir: tempfile::tempdir().unwrap(),
            extra,
        };
        r.spawn();
        r
    }

    /// `redis://127.0.0.1:PORT`.
    pub fn url(&self) -> String {
        format!("redis://127.0.0.1:{}", self.port)
    }

    fn spawn(&mut self) {
        let child = Command::new("redis-server")
            .args(["--port", &self.port.to_string(), "--bind", "127.0.0.1"])
            .arg("--dir")
            .arg(self.dir.path())
            .args([
                "--appendonly",
                "yes",
                "--appendfsync",
                "always",
                "--save",
                "",
            ])
            .args(&self.extra)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("redis-server is needed by these tests: apt-get install -y redis-server");
        self.child = Some(child);
        let deadline = Instant::now() + Duration::from_secs(20);
        while !self.pings() {
            assert!(Instant::now() < deadline, "redis-server did not answer");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn pings(&self) -> bool {
        use std::io::{Read, Write};
        let Ok(mut s) = std::net::TcpStream::connect(("127.0.0.1", self.port)) else {
            return false;
        };
        let mut buf = [0u8; 64];
        s.write_all(b"PING\r\n").is_ok()
            && s.read(&mut buf)
                .is_ok_and(|n| buf[..n].starts_with(b"+PONG"))
    }

    /// The answer of `redis-cli` to `args` on this server.
    pub fn cli(&self, args: &[&str]) -> String {
        let out = Command::new("redis-cli")
            .args(["-h", "127.0.0.1", "-p", &self.port.to_string()])
            .args(args)
            .output()
            .expect("redis-cli is needed by these tests: apt-get install -y redis-server");
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// kill -9.
    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// Starts it again on the same port and directory (after [`RedisServer::kill`]).
    pub fn restart(&mut self) {
        self.kill();
        self.spawn();
    }
}

/// A Redis Cluster of `redis-server` children (primaries only), formed with
/// `redis-cli --cluster create`: slots 0-16383 split evenly in node order.
pub struct RedisCluster {
    pub nodes: Vec<RedisServer>,
}

impl RedisCluster {
    /// Starts `n` nodes on free ports (each with its cluster bus port, +10000, free too)
    /// and waits for the cluster to be up. Nodes keep serving the slots they hold when
    /// another is down (`cluster-require-full-coverage no`).
    pub fn start(n: usize) -> RedisCluster {
        use std::sync::atomic::{AtomicU32, Ordering};
        // Tests of one process run in parallel: each candidate port is tried once.
        static TRIED: AtomicU32 = AtomicU32::new(0);
        let free = |p: u16| std::net::TcpListener::bind(("127.0.0.1", p)).is_ok();
        let offset = (std::process::id() % 1000) * 20;
        let mut nodes = Vec::new();
        while nodes.len() < n {
            let tried = TRIED.fetch_add(1, Ordering::Relaxed);
            let port = u16::try_from(20000 + (offset + tried) % 30000).expect("below 50000");
            if !(free(port) && free(port + 10000)) {
                continue;
            }
            let extra = [
                "--cluster-enabled",
                "yes",
                "--cluster-config-file",
                "nodes.conf",
                "--cluster-node-timeout",
                "1000",
                "--cluster-require-full-coverage",
                "no",
            ];
            nodes.push(RedisServer::start_with(
                port,
                extra.iter().map(|s| s.to_string()).collect(),
            ));
        }
        let addrs: Vec<String> = nodes
            .iter()
            .map(|r| format!("127.0.0.1:{}", r.port))
            .collect();
        let out = Command::new("redis-cli")
            .args(["--cluster", "create"])
            .args(&addrs)
            .args(["--cluster-replicas", "0", "--cluster-yes"])
            .output()
            .expect("redis-cli is needed by these tests: apt-get install -y redis-server");
        assert!(
            out.status.success(),
            "redis-cli --cluster create: {}",
            String::from_utf8_lossy(&out.stdout)
        );
        let c = RedisCluster { nodes };
        c.wait_up();
        c
    }

    /// Waits until every node reports `cluster_state:ok`.
    pub fn wait_up(&self) {
        let deadline = Instant::now() + Duration::from_secs(30);
        while !self
            .nodes
            .iter()
            .all(|r| r.cli(&["cluster", "info"]).contains("cluster_state:ok"))
        {
            assert!(
                Instant::now() < deadline,
                "the Redis Cluster did not come up"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// `redis-cluster://` with every node as a seed.
    pub fn url(&self) -> String {
        let nodes: Vec<String> = self
            .nodes
            .iter()
            .map(|r| format!("127.0.0.1:{}", r.port))
            .collect();
        format!("redis-cluster://{}", nodes.join(","))
    }

    /// The index of the node serving `key`'s slot, from `CLUSTER NODES`.
    pub fn node_of(&self, key: &str) -> usize {
        let up = self.nodes.iter().find(|r| r.pings()).expect("a node is up");
        let slot: u32 = up
            .cli(&["cluster", "keyslot", key])
            .trim()
            .parse()
            .expect("a slot number");
        for line in up.cli(&["cluster", "nodes"]).lines() {
            let fields: Vec<&str> = line.split_whitespace().collect();
            let Some(port) = fields
                .get(1)
                .and_then(|a| a.split('@').next())
                .and_then(|a| a.rsplit(':').next())
                .and_then(|p| p.parse::<u16>().ok())
            else {
                continue;
            };
            let serves = fields.iter().skip(8).any(|range| {
                let (a, b) = range.split_once('-').unwrap_or((range, range));
                matches!((a.parse::<u32>(), b.parse::<u32>()), (Ok(a), Ok(b)) if a <= slot && slot <= b)
            });
            if serves {
                if let Some(i) = self.nodes.iter().position(|r| r.port == port) {
                    return i;
                }
            }
        }
        panic!("no node serves slot {slot}");
    }
}

impl Drop for RedisServer {
    fn drop(&mut self) {
        self.kill();
    }
}
