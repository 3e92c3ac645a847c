//! Helpers of the client's integration tests: the real `tamrm` binary ($TAMRM_BIN, else
//! the workspace's target/release/tamrm) on 127.0.0.1, and the steps the tests send.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use std::sync::Arc;

use tamrm::limits::Limits;
use tamrm::registry::Registry;
use tamrm::service::ShapingService;
use tamrm::store::{MemoryStore, Store};
use tamrm_client::{proto, Batch};
use tokio_util::sync::CancellationToken;

/// The server binary the tests run.
pub fn binary() -> PathBuf {
    match std::env::var_os("TAMRM_BIN") {
        Some(bin) => PathBuf::from(bin),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target/release/tamrm"),
    }
}

/// A running `tamrm serve`, killed when dropped.
pub struct Server {
    child: Child,
    /// The address it listens on (`host:port`).
    pub addr: String,
    _dir: tempfile::TempDir,
}

impl Server {
    /// `tamrm serve --listen 127.0.0.1:0 ARGS`; waits for its "listening on" line.
    pub fn start(args: &[&str]) -> Server {
        Server::start_on("127.0.0.1:0", args)
    }

    /// `tamrm serve --listen LISTEN ARGS`; waits for its "listening on" line.
    pub fn start_on(listen: &str, args: &[&str]) -> Server {
        let bin = binary();
        assert!(
            bin.is_file(),
            "no server binary at {} (cargo build --release, or set TAMRM_BIN)",
            bin.display()
        );
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("stderr");
        let mut cmd = Command::new(&bin);
        for (var, _) in std::env::vars() {
            if var.starts_with("TAMRM_") {
                cmd.env_remove(var);
            }
        }
        let child = cmd
            .env("RUST_LOG", "info")
            .args(["serve", "--listen", listen])
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .expect("spawn tamrm");
        let mut server = Server {
            child,
            addr: String::new(),
            _dir: dir,
        };
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let text = std::fs::read_to_string(&log).unwrap_or_default();
            if let Some(at) = text.find("listening on ") {
                let rest = &text[at + "listening on ".len()..];
                server.addr = rest.split_whitespace().next().unwrap().to_string();
                return server;
            }
            if let Some(status) = server.child.try_wait().unwrap() {
                panic!("tamrm exited ({status}) before listening: {text}");
            }
            assert!(Instant::now() < deadline, "tamrm is not listening: {text}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Kills the server at once (SIGKILL): its streams break without an end.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A free TCP port on 127.0.0.1 (for a server restarted on the same address).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// The discrete task the tests shape: 3 actions, a small pool that fills at once.
pub fn create_request(task_id: &str) -> proto::CreateTaskRequest {
    proto::CreateTaskRequest {
        task_id: task_id.into(),
        config: Some(proto::TaskConfig {
            num_actions: 3,
            pool_capacity: Some(4),
            k: Some(2),
            start_step: Some(1),
            min_pool_size: Some(1),
            ..Default::default()
        }),
    }
}

/// One step of `num_envs` environments: actions, rewards, terminated.
pub struct Step {
    pub actions: Vec<u32>,
    pub rewards: Vec<f64>,
    pub terminated: Vec<bool>,
}

impl Step {
    /// The columns of the step.
    pub fn batch(&self) -> Batch<'_> {
        Batch {
            actions: &self.actions,
            rewards: &self.rewards,
            terminated: &self.terminated,
            ..Batch::default()
        }
    }
}

/// `n` steps of `num_envs` environments from `seed` (a small deterministic generator:
/// the same seed gives the same steps), episodes ending now and then.
pub fn steps(seed: u64, n: usize, num_envs: usize) -> Vec<Step> {
    let mut state = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 33) as u32
    };
    (0..n)
        .map(|_| Step {
            actions: (0..num_envs).map(|_| next() % 3).collect(),
            rewards: (0..num_envs)
                .map(|_| f64::from(next() % 1000) / 100.0 - 5.0)
                .collect(),
            terminated: (0..num_envs).map(|_| next() % 5 == 0).collect(),
        })
        .collect()
}

/// The shaped rewards of `steps` through `session`, step by step.
pub fn shape_all(session: &mut tamrm_client::Session, steps: &[Step]) -> Vec<Vec<f64>> {
    steps
        .iter()
        .map(|s| session.step(&s.batch()).expect("step").rewards)
        .collect()
}

/// An in-process registry over a memory store, and the server's service on it (no
/// network): what the Python client's `tamrm.Engine` is.
pub fn engine() -> (Arc<Registry>, ShapingService) {
    let rt = tamrm_client::runtime().unwrap();
    let store: Arc<dyn Store> = Arc::new(MemoryStore::new());
    let (registry, _) = rt
        .block_on(Registry::open(store, Limits::default()))
        .unwrap();
    let registry = Arc::new(registry);
    let service = ShapingService::new(registry.clone(), CancellationToken::new());
    (registry, service)
}
