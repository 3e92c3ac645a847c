//! What the benchmarks that start the real `tamrm` binary share (`followers.rs`,
//! `stopstart.rs`): finding the binary, starting it on a free 127.0.0.1 port (with a data
//! dir or not), its CPU time, stopping it, and the benches' `--flag value` arguments.
#![allow(dead_code)]

use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use tamrm::proto::shaping_client::ShapingClient;
use tonic::transport::Channel;

/// The binary under test: `TAMRM_BIN`, default `target/release/tamrm` (build it first).
pub fn binary() -> String {
    std::env::var("TAMRM_BIN").unwrap_or_else(|_| {
        concat!(env!("CARGO_MANIFEST_DIR"), "/target/release/tamrm").to_string()
    })
}

/// A running `tamrm serve`, killed (SIGKILL) when dropped unless it was stopped.
pub struct Server {
    child: Child,
    /// `127.0.0.1:PORT`.
    pub addr: String,
}

impl Server {
    /// Starts `tamrm serve` on a free port, with `--data-dir data_dir` if given, and
    /// `extra` flags.
    pub fn start(data_dir: Option<&Path>, extra: &[&str]) -> Server {
        let bin = binary();
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("free port")
            .port();
        let addr = format!("127.0.0.1:{port}");
        let mut cmd = Command::new(&bin);
        cmd.args(["serve", "--listen", &addr]).args(extra);
        if let Some(dir) = data_dir {
            cmd.arg("--data-dir").arg(dir);
        }
        let child = cmd
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {bin}: {e} (cargo build --release first)"));
        Server { child, addr }
    }

    /// `http://ADDR`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// A client, once the server accepts connections (it binds only after restoring
    /// every task of its data dir).
    pub async fn connect(&self) -> ShapingClient<Channel> {
        loop {
            match ShapingClient::connect(self.url()).await {
                Ok(c) => return c,
                Err(_) => tokio::time::sleep(Duration::from_millis(5)).await,
            }
        }
    }

    /// CPU seconds the server process has used (user + system).
    pub fn cpu_secs(&self) -> f64 {
        let stat =
            std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).unwrap_or_default();
        // Fields after the command name (which ends with ')'): utime is the 12th, stime
        // the 13th of those (fields 14 and 15 of the line).
        let rest = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
        let f: Vec<&str> = rest.split_whitespace().collect();
        let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        // The clock tick is 100 Hz on Linux (getconf CLK_TCK).
        (ticks(11) + ticks(12)) / 100.0
    }

    /// Sends SIGTERM and waits for the process to exit: its exit status and the time
    /// from the signal to the exit.
    pub fn terminate(&mut self) -> (ExitStatus, Duration) {
        let t = Instant::now();
        let sent = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .expect("kill -TERM");
        assert!(sent.success(), "kill -TERM {}", self.child.id());
        let status = self.child.wait().expect("wait for tamrm");
        (status, t.elapsed())
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The value after flag `name` in `args`, if any.
pub fn arg(args: &[String], name: &str) -> Option<String> {
    let i = args.iter().position(|a| a == name)?;
    args.get(i + 1).cloned()
}

/// The value after flag `name` parsed, or `default` when absent or unparsable.
pub fn arg_or<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> T {
    arg(args, name)
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}
