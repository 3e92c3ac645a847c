//! Faults of the machine and the network, each against real processes: a data dir whose
//! disk fills up, a replica cut off from its Redis (a network partition), and a Redis
//! killed with `appendfsync everysec`. What each shows is in docs/deployment.md's fault
//! matrix.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tonic::Code;

use crate::common::{
    self, connect, create, discrete, get_pool, try_add_discrete as try_add, Binary, Client,
    RedisServer,
};

async fn eventually<F, Fut>(what: &str, within: Duration, mut f: F)
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let deadline = Instant::now() + within;
    while !f().await {
        assert!(Instant::now() < deadline, "never within {within:?}: {what}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A small tmpfs mounted for one test (needs root, as CI has), unmounted on drop.
struct SmallDisk {
    dir: tempfile::TempDir,
}

impl SmallDisk {
    fn mount(bytes: u64) -> SmallDisk {
        let dir = tempfile::tempdir().unwrap();
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={bytes}"), "tmpfs"])
            .arg(dir.path())
            .output()
            .expect("mount(8)");
        assert!(
            out.status.success(),
            "the full-disk test mounts a small tmpfs and needs root: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        SmallDisk { dir }
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Fills what is left with one file; returns its path.
    fn fill(&self) -> PathBuf {
        use std::io::Write;
        let path = self.path().join("filler");
        let mut f = std::fs::File::create(&path).unwrap();
        let chunk = vec![7u8; 4096];
        while f.write_all(&chunk).is_ok() {}
        // What is left is smaller than a page: fill it too.
        while f.write_all(&[7u8]).is_ok() {}
        path
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(self.dir.path()).status();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_fails_the_change_not_the_server_and_nothing_acknowledged_is_lost() {
    let disk = SmallDisk::mount(8 << 20);
    let data = disk.path().join("data");
    let data_arg = data.to_str().unwrap().to_string();
    let server = Binary::start(&["--data-dir", &data_arg]);
    let mut c = connect(server.addr).await;
    create(&mut c, "t", discrete(3, 8, 2, 1, 2)).await;
    let long: Vec<u32> = (0..2000).map(|i| i % 3).collect();
    for i in 0..6u32 {
        try_add(&mut c, "t", &long, f64::from(i)).await.unwrap();
    }
    let before = get_pool(&mut c, "t").await;

    let filler = disk.fill();
    let err = try_add(&mut c, "t", &long, 100.0).await.unwrap_err();
    assert_eq!(err.code(), Code::Internal, "{err:?}");
    assert!(
        err.message().contains("change not applied") && err.message().contains("No space left"),
        "the status says the change failed and why: {err:?}"
    );
    assert_eq!(
        get_pool(&mut c, "t").await,
        before,
        "a failed change changes nothing"
    );
    // Reads and steps go on while the disk is full.
    let (mut s, _) = common::Stream::open(&mut c, "t", 2).await.unwrap();
    let shaped = s
        .step(common::batch(&[0, 1], &[1.0, 1.0], &[false, false]))
        .await
        .expect("steps without an episode end need no disk");
    assert_eq!(shaped.pool_version, before.pool_version);
    // An episode end that would enter the pool (it has room) needs the disk: its
    // stream ends with the same status.
    let err = s
        .step(common::batch(&[0, 1], &[1.0, 1.0], &[true, true]))
        .await
        .expect_err("an episode end that changes the pool is refused");
    assert_eq!(err.code(), Code::Internal, "{err:?}");
    assert!(err.message().contains("No space left"), "{err:?}");
    drop(s);
    assert_eq!(get_pool(&mut c, "t").await, before);

    std::fs::remove_file(filler).unwrap();
    let after = try_add(&mut c, "t", &long, 100.0)
        .await
        .expect("with space again, the same change commits");
    assert_eq!(after, before.pool_version + 1);
    let want = get_pool(&mut c, "t").await;

    // kill -9, then a start from the data dir: every acknowledged change is there.
    drop(server);
    let server = Binary::start(&["--data-dir", &data_arg]);
    let mut c = connect(server.addr).await;
    assert_eq!(get_pool(&mut c, "t").await, want);
}

/// A TCP proxy between a replica and Redis that can partition them: while cut, it
/// forwards nothing (open connections stall, as behind a dropped route, and new ones are
/// accepted and then ignored); healed, new connections go through.
struct Partition {
    addr: std::net::SocketAddr,
    cut: Arc<AtomicBool>,
    task: tokio::task::JoinHandle<()>,
}

impl Partition {
    async fn start(upstream: std::net::SocketAddr) -> Partition {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let cut = Arc::new(AtomicBool::new(false));
        let flag = cut.clone();
        let task = tokio::spawn(async move {
            while let Ok((inbound, _)) = listener.accept().await {
                let cut = flag.clone();
                tokio::spawn(async move {
                    if cut.load(Ordering::SeqCst) {
                        return swallow(inbound).await;
                    }
                    let Ok(outbound) = TcpStream::connect(upstream).await else {
                        return;
                    };
                    let (ri, wi) = inbound.into_split();
                    let (ro, wo) = outbound.into_split();
                    let cut2 = cut.clone();
                    tokio::join!(pipe(ri, wo, cut), pipe(ro, wi, cut2));
                });
            }
        });
        Partition { addr, cut, task }
    }

    fn set_cut(&self, cut: bool) {
        self.cut.store(cut, Ordering::SeqCst);
    }
}

impl Drop for Partition {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Copies until the partition is cut; from then on it reads and drops (the connection
/// stays open and silent, as behind a partition).
async fn pipe(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    cut: Arc<AtomicBool>,
) {
    let mut buf = vec![0u8; 16 << 10];
    let mut dead = false;
    loop {
        let n = match from.read(&mut buf).await {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        dead |= cut.load(Ordering::SeqCst);
        if !dead && to.write_all(&buf[..n]).await.is_err() {
            return;
        }
    }
}

async fn swallow(mut s: TcpStream) {
    let mut buf = vec![0u8; 4096];
    while matches!(s.read(&mut buf).await, Ok(n) if n > 0) {}
}

async fn replica(url: String) -> tamrm::server::RunningServer {
    common::start_server(None, move |s| {
        s.store = Some(url);
        s.store_poll_ms = 200;
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replica_cut_off_from_redis_refuses_changes_in_bounded_time_and_catches_up() {
    let redis = RedisServer::start();
    let upstream = format!("127.0.0.1:{}", redis.port).parse().unwrap();
    let partition = Partition::start(upstream).await;
    let a = replica(format!("redis://{}", partition.addr)).await;
    let b = replica(redis.url()).await;
    let (mut ca, mut cb) = (connect(a.addr()).await, connect(b.addr()).await);
    create(&mut ca, "t", discrete(3, 4, 2, 1, 2)).await;
    for i in 0..4u32 {
        try_add(&mut ca, "t", &[i % 3, 1], f64::from(i))
            .await
            .unwrap();
    }
    let before = get_pool(&mut ca, "t").await;

    partition.set_cut(true);
    let t0 = Instant::now();
    let err = try_add(&mut ca, "t", &[2, 2], 50.0).await.unwrap_err();
    let waited = t0.elapsed();
    assert_eq!(err.code(), Code::Unavailable, "{err:?}");
    assert!(
        waited < Duration::from_secs(30),
        "a change on a cut-off replica is refused within the store's timeouts, not held: {waited:?}"
    );
    // Reads on the cut-off replica answer from its last pool.
    assert_eq!(get_pool(&mut ca, "t").await, before);
    // The other side of the partition goes on.
    let v = try_add(&mut cb, "t", &[0, 0], 60.0).await.unwrap();
    assert_eq!(
        v,
        before.pool_version + 1,
        "the refused change was not applied"
    );

    partition.set_cut(false);
    let want = get_pool(&mut cb, "t").await;
    eventually(
        "the healed replica holds the pool committed during the partition",
        Duration::from_secs(30),
        || {
            let mut ca = ca.clone();
            let want = want.clone();
            async move { get_pool(&mut ca, "t").await == want }
        },
    )
    .await;
    eventually(
        "the healed replica commits again",
        Duration::from_secs(30),
        || {
            let mut ca = ca.clone();
            async move { try_add(&mut ca, "t", &[1, 1], 70.0).await.is_ok() }
        },
    )
    .await;
    let both = get_pool(&mut ca, "t").await;
    assert_eq!(both.pool_version, want.pool_version + 1);
    eventually("the other replica sees it", Duration::from_secs(10), || {
        let mut cb = cb.clone();
        let both = both.clone();
        async move { get_pool(&mut cb, "t").await == both }
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_redis_loses_its_last_writes_replicas_follow_what_redis_has() {
    // With `appendfsync everysec` (or `no`) a kill -9 of Redis may lose up to a second
    // of writes it acknowledged. Simulated exactly: this Redis persists only when told
    // (SAVE), so a kill -9 loses every write after the last SAVE.
    let mut redis = RedisServer::start_with_args(&["--appendonly", "no"]);
    let a = replica(redis.url()).await;
    let mut ca = connect(a.addr()).await;
    create(&mut ca, "t", discrete(3, 4, 2, 1, 2)).await;
    for i in 0..4u32 {
        try_add(&mut ca, "t", &[i % 3, 1], f64::from(i))
            .await
            .unwrap();
    }
    let kept = get_pool(&mut ca, "t").await;
    assert_eq!(redis.cli(&["SAVE"]).trim(), "OK");
    for i in 0..3u32 {
        try_add(&mut ca, "t", &[2, i % 3], 10.0 + f64::from(i))
            .await
            .unwrap();
    }
    let lost = get_pool(&mut ca, "t").await;
    assert!(lost.pool_version > kept.pool_version);
    redis.restart();

    // A fresh replica reads what Redis has; the old one converges on it rather than
    // serving the pool Redis lost, and commits on top of it.
    let fresh = replica(redis.url()).await;
    let mut cf = connect(fresh.addr()).await;
    assert_eq!(
        get_pool(&mut cf, "t").await,
        kept,
        "Redis came back with its last save"
    );
    let v = eventually_ok(&mut ca, "t").await;
    assert_eq!(
        v,
        kept.pool_version + 1,
        "committed on top of what Redis has"
    );
    // The fresh replica learns of it (notification or poll).
    eventually(
        "the fresh replica sees the commit",
        Duration::from_secs(10),
        || {
            let mut cf = cf.clone();
            async move { get_pool(&mut cf, "t").await.pool_version == v }
        },
    )
    .await;
    let now = get_pool(&mut cf, "t").await;
    assert_eq!(
        get_pool(&mut ca, "t").await,
        now,
        "the old replica follows Redis"
    );
}

/// Retries a change on `c` until it commits (the replica reconnects by itself).
async fn eventually_ok(c: &mut Client, id: &str) -> u64 {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        match try_add(c, id, &[1, 2], 99.0).await {
            Ok(v) => return v,
            Err(e) => assert!(Instant::now() < deadline, "never committed again: {e:?}"),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}
