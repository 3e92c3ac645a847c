//! The shared store against the disk store, side by side in one run (docs/scaling.md):
//! commit latency (p50/p99) of one pool change through `RedisStore` (a `redis-server`
//! child on a free port, `appendfsync always` and `everysec`) and through `DiskStore`
//! (group commit), with 1 and 8 committers; and the staleness of a second server's
//! snapshot: the time from a commit's acknowledgement on store A to the change
//! notification on store B (another connection, as another replica would have). The
//! same commits through a three-node Redis Cluster (`appendfsync always`; tasks spread
//! over the nodes by their hash tags) show what sharding adds per commit and in total.
//!
//! `cargo bench --bench redis_store` (needs `redis-server` on the PATH); `--quick` for a
//! short run. Data dirs go under `$TAMRM_BENCH_DIR` if set, else the system temp dir.

use std::net::TcpListener;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tamrm::core::Pool;
use tamrm::store::{Counters, DiskStore, PoolOp, RedisOptions, RedisStore, Store};

#[path = "common/commits.rs"]
mod common;
use common::{commit_episodes, config, episode};

fn tmp() -> tempfile::TempDir {
    match std::env::var_os("TAMRM_BENCH_DIR") {
        Some(d) => tempfile::tempdir_in(d).expect("TAMRM_BENCH_DIR is writable"),
        None => tempfile::tempdir().expect("temp dir"),
    }
}

/// A `redis-server` child with `appendfsync` = `fsync`.
struct Redis {
    child: Child,
    port: u16,
    _dir: tempfile::TempDir,
}

impl Redis {
    fn start(fsync: &str) -> Redis {
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("free port")
            .port();
        Redis::start_on(port, fsync, &[])
    }

    fn start_on(port: u16, fsync: &str, extra: &[&str]) -> Redis {
        let dir = tmp();
        let child = Command::new("redis-server")
            .args([
                "--port",
                &port.to_string(),
                "--bind",
                "127.0.0.1",
                "--save",
                "",
            ])
            .args(["--appendonly", "yes", "--appendfsync", fsync])
            .args(extra)
            .arg("--dir")
            .arg(dir.path())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("redis-server on the PATH (apt-get install -y redis-server)");
        let deadline = Instant::now() + Duration::from_secs(20);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(Instant::now() < deadline, "redis-server did not start");
            std::thread::sleep(Duration::from_millis(20));
        }
        Redis {
            child,
            port,
            _dir: dir,
        }
    }

    /// Three primaries formed into a cluster by `redis-cli --cluster create`; the URL.
    fn cluster(fsync: &str) -> (Vec<Redis>, String) {
        let free = |p: u16| TcpListener::bind(("127.0.0.1", p)).is_ok();
        let extra = [
            "--cluster-enabled",
            "yes",
            "--cluster-config-file",
            "nodes.conf",
        ];
        let mut nodes = Vec::new();
        let mut port = 21000 + (std::process::id() % 500) as u16 * 40;
        while nodes.len() < 3 {
            port += 1;
            if free(port) && free(port + 10000) {
                nodes.push(Redis::start_on(port, fsync, &extra));
            }
        }
        let addrs: Vec<String> = nodes
            .iter()
            .map(|r| format!("127.0.0.1:{}", r.port))
            .collect();
        let ok = Command::new("redis-cli")
            .args(["--cluster", "create"])
            .args(&addrs)
            .args(["--cluster-replicas", "0", "--cluster-yes"])
            .stdout(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        assert!(ok, "redis-cli --cluster create failed");
        let deadline = Instant::now() + Duration::from_secs(30);
        for r in &nodes {
            loop {
                let info = Command::new("redis-cli")
                    .args(["-p", &r.port.to_string(), "cluster", "info"])
                    .output()
                    .expect("redis-cli");
                if String::from_utf8_lossy(&info.stdout).contains("cluster_state:ok") {
                    break;
                }
                assert!(Instant::now() < deadline, "the cluster did not come up");
                std::thread::sleep(Duration::from_millis(50));
            }
        }
        let url = format!("redis-cluster://{}", addrs.join(","));
        (nodes, url)
    }

    fn url(&self) -> String {
        format!("redis://127.0.0.1:{}", self.port)
    }
}

impl Drop for Redis {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Every commit's latency and the commits per second, `committers` tasks committing `per`
/// changes each at once.
async fn commits(store: Arc<dyn Store>, committers: usize, per: u32, tag: &str) -> (Vec<f64>, f64) {
    for s in 0..committers {
        store
            .create_task(&format!("{tag}{s}"), &config())
            .await
            .expect("create");
    }
    let t0 = Instant::now();
    let mut joins = Vec::new();
    for s in 0..committers {
        joins.push(tokio::spawn(commit_episodes(
            store.clone(),
            format!("{tag}{s}"),
            per,
        )));
    }
    let mut all = Vec::new();
    for j in joins {
        let lat = j.await.expect("committer");
        all.extend(lat.iter().map(|d| d.as_secs_f64() * 1e3));
    }
    let rate = all.len() as f64 / t0.elapsed().as_secs_f64();
    (all, rate)
}

/// Milliseconds from the acknowledgement of a commit on `a` to its notification on `b`.
async fn staleness(a: &RedisStore, b: &RedisStore, n: u32) -> Vec<f64> {
    a.create_task("stale", &config()).await.expect("create");
    b.load_task("stale").await.expect("load").expect("the task");
    let mut rx = b.changes().expect("a shared store notifies");
    let mut pool = Arc::new(Pool::new(1000));
    let mut out = Vec::new();
    for i in 0..n {
        let ops = vec![PoolOp::Offer {
            actions: episode(i),
            score: f64::from(i),
            end: None,
        }];
        let c = a
            .commit("stale", pool, ops, Counters::default())
            .await
            .expect("commit");
        let acked = Instant::now();
        let want = c.version;
        pool = c.pool;
        loop {
            let change = tokio::time::timeout(Duration::from_secs(5), rx.recv())
                .await
                .expect("a notification within 5 s")
                .expect("notifications");
            if change.task == "stale" && change.version >= want {
                break;
            }
        }
        out.push(acked.elapsed().as_secs_f64() * 1e3);
    }
    out
}

fn pct(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() as f64 - 1.0) * p).round() as usize]
}

fn row(name: &str, committers: usize, (mut lat, rate): (Vec<f64>, f64)) {
    let n = lat.len();
    println!(
        "| {name} | {committers} | {n} | {:.3} | {:.3} | {rate:.0} |",
        pct(&mut lat, 0.5),
        pct(&mut lat, 0.99)
    );
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let (one, eight) = if quick { (50, 20) } else { (500, 200) };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        let always = Redis::start("always");
        let everysec = Redis::start("everysec");
        let open = |url: String| async move {
            let mut o = RedisOptions::new(url);
            o.poll_interval = Duration::from_secs(1);
            Arc::new(RedisStore::open(&o).await.expect("connect to redis"))
        };
        let (ra, re) = (open(always.url()).await, open(everysec.url()).await);
        let (_nodes, cluster_url) = Redis::cluster("always");
        let rc = open(cluster_url).await;
        let dir = tmp();
        let disk = Arc::new(DiskStore::open(dir.path()).expect("open data dir"));
        disk.load().await.expect("load");
        println!("| store | committers | commits | p50 ms | p99 ms | commits/s |");
        println!("|---|---|---|---|---|---|");
        // Interleaved, so that every store sees the same noise.
        for (committers, per) in [(1usize, one), (8, eight)] {
            let tag = format!("c{committers}-");
            let d = commits(disk.clone(), committers, per, &tag).await;
            let a = commits(ra.clone(), committers, per, &tag).await;
            let e = commits(re.clone(), committers, per, &tag).await;
            let c = commits(rc.clone(), committers, per, &tag).await;
            row("disk (group commit, fdatasync)", committers, d);
            row("Redis, appendfsync always", committers, a);
            row("Redis, appendfsync everysec", committers, e);
            row("Redis Cluster (3 primaries), appendfsync always", committers, c);
        }
        let b = open(always.url()).await;
        let mut s = staleness(&ra, &b, if quick { 50 } else { 500 }).await;
        println!();
        println!(
            "staleness (ack on A -> notification on B, {} changes): p50 {:.3} ms, p99 {:.3} ms, max {:.3} ms",
            s.len(),
            pct(&mut s, 0.5),
            pct(&mut s, 0.99),
            pct(&mut s, 1.0)
        );
    });
}
