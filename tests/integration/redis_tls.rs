//! TLS to Redis (`rediss://`, `rediss-cluster://`) against real `redis-server`s that
//! speak TLS only (`--port 0 --tls-port P`) and ask every client for a certificate (Redis'
//! default `tls-auth-clients yes`), with certificates made in the test (rcgen): the store
//! verifies Redis against the CA file and presents its client certificate; a wrong CA, a
//! missing client certificate or plaintext fail fast with the reason; a Redis Cluster
//! whose nodes talk TLS to each other too; and two real `tamrm` binaries sharing a task
//! through a TLS Redis, configured by flags and by the config file.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rcgen::ExtendedKeyUsagePurpose;
use tamrm::core::{TaskConfig, TaskConfigInput};
use tamrm::store::{RedisOptions, RedisStore, RedisTls, Store};

use crate::common::*;
use crate::tls::{write, Ca};

/// The files of one test: a CA, the nodes' certificate (server and, between cluster
/// nodes, client), a client certificate of the same CA, and another CA.
struct Certs {
    dir: tempfile::TempDir,
    ca: PathBuf,
    node_cert: PathBuf,
    node_key: PathBuf,
    client_cert: PathBuf,
    client_key: PathBuf,
    other_ca: PathBuf,
}

impl Certs {
    fn new() -> Certs {
        let dir = tempfile::tempdir().unwrap();
        let ca = Ca::new("redis test CA");
        let node = ca.issue_for(
            &["localhost", "127.0.0.1"],
            vec![
                ExtendedKeyUsagePurpose::ServerAuth,
                ExtendedKeyUsagePurpose::ClientAuth,
            ],
        );
        let client = ca.client();
        let d = dir.path();
        Certs {
            ca: write(d, "ca.crt", &ca.pem()),
            node_cert: write(d, "node.crt", &node.cert),
            node_key: write(d, "node.key", &node.key),
            client_cert: write(d, "client.crt", &client.cert),
            client_key: write(d, "client.key", &client.key),
            other_ca: write(d, "other-ca.crt", &Ca::new("another CA").pem()),
            dir,
        }
    }

    /// The store's TLS files: this CA, with the client certificate or without.
    fn tls(&self, client: bool) -> RedisTls {
        RedisTls {
            ca: Some(self.ca.clone()),
            cert: client.then(|| self.client_cert.clone()),
            key: client.then(|| self.client_key.clone()),
        }
    }

    /// `redis-cli`'s TLS flags.
    fn cli_args(&self) -> Vec<String> {
        let p = |p: &PathBuf| p.to_str().unwrap().to_string();
        vec![
            "--tls".into(),
            "--cacert".into(),
            p(&self.ca),
            "--cert".into(),
            p(&self.client_cert),
            "--key".into(),
            p(&self.client_key),
        ]
    }
}

/// A port that is free, with `port + 10000` (a cluster node's bus port) free too.
fn free_port() -> u16 {
    loop {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        if port < 55000 && std::net::TcpListener::bind(("127.0.0.1", port + 10000)).is_ok() {
            return port;
        }
    }
}

/// A `redis-server` child speaking TLS only, on `port`.
struct TlsRedis {
    child: Child,
    port: u16,
    _dir: tempfile::TempDir,
}

impl TlsRedis {
    fn start(certs: &Certs, extra: &[&str]) -> TlsRedis {
        let port = free_port();
        let dir = tempfile::tempdir().unwrap();
        let child = Command::new("redis-server")
            .args(["--port", "0", "--tls-port", &port.to_string()])
            .args(["--bind", "127.0.0.1", "--save", "", "--appendonly", "no"])
            .arg("--tls-cert-file")
            .arg(&certs.node_cert)
            .arg("--tls-key-file")
            .arg(&certs.node_key)
            .arg("--tls-ca-cert-file")
            .arg(&certs.ca)
            .arg("--dir")
            .arg(dir.path())
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("redis-server (built with TLS) is needed: apt-get install -y redis-server");
        let r = TlsRedis {
            child,
            port,
            _dir: dir,
        };
        let deadline = Instant::now() + Duration::from_secs(20);
        while r.cli(certs, &["ping"]).trim() != "PONG" {
            assert!(
                Instant::now() < deadline,
                "redis-server with TLS did not answer"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        r
    }

    fn cli(&self, certs: &Certs, args: &[&str]) -> String {
        let out = Command::new("redis-cli")
            .args(["-h", "127.0.0.1", "-p", &self.port.to_string()])
            .args(certs.cli_args())
            .args(args)
            .output()
            .expect("redis-cli is needed: apt-get install -y redis-server");
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    fn url(&self) -> String {
        format!("rediss://127.0.0.1:{}", self.port)
    }
}

impl Drop for TlsRedis {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn config() -> TaskConfig {
    TaskConfig::resolve(&TaskConfigInput {
        num_actions: 3,
        pool_capacity: Some(8),
        ..Default::default()
    })
    .unwrap()
}

/// Opens a store at `url` with `tls`; the error's text if it fails, within 20 s.
async fn open(url: &str, tls: RedisTls) -> Result<RedisStore, String> {
    let mut options = RedisOptions::new(url);
    options.tls = tls;
    tokio::time::timeout(Duration::from_secs(20), RedisStore::open(&options))
        .await
        .map_err(|_| format!("{url}: no answer and no error within 20 s"))?
        .map_err(|e| e.to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_store_verifies_redis_by_its_ca_and_presents_its_client_certificate() {
    let certs = Certs::new();
    let redis = TlsRedis::start(&certs, &[]);
    let a = open(&redis.url(), certs.tls(true)).await.unwrap();
    a.create_task("t", &config()).await.unwrap();
    let b = open(&redis.url(), certs.tls(true)).await.unwrap();
    let ids: Vec<String> = b.load().await.unwrap().into_iter().map(|t| t.id).collect();
    assert_eq!(ids, ["t"], "a second connection over TLS sees the task");
    assert_eq!(redis.cli(&certs, &["exists", "tamrm:{t}:meta"]).trim(), "1");

    // Redis asks for a client certificate: without one, no connection.
    let e = open(&redis.url(), certs.tls(false)).await.unwrap_err();
    assert!(e.contains("connecting") && e.contains("Certificate"), "{e}");
    // Another CA: Redis' certificate is not trusted.
    let mut other = certs.tls(true);
    other.ca = Some(certs.other_ca.clone());
    let e = open(&redis.url(), other).await.unwrap_err();
    assert!(
        e.to_lowercase().contains("certificate") || e.contains("Issuer"),
        "{e}"
    );
    // Plaintext to the TLS port fails too (and does not hang).
    let plain = format!("redis://127.0.0.1:{}", redis.port);
    let e = open(&plain, RedisTls::default()).await.unwrap_err();
    assert!(e.contains("connecting") && !e.contains("no answer"), "{e}");
    // TLS files with a plaintext URL, a certificate without its key, a missing file:
    // each refused before connecting, by name.
    let e = open(&plain, certs.tls(true)).await.unwrap_err();
    assert!(e.contains("rediss://"), "{e}");
    let mut half = certs.tls(true);
    half.key = None;
    let e = open(&redis.url(), half).await.unwrap_err();
    assert!(
        e.contains("store_tls_cert") && e.contains("store_tls_key"),
        "{e}"
    );
    let mut missing = certs.tls(true);
    missing.ca = Some(certs.dir.path().join("nope.crt"));
    let e = open(&redis.url(), missing).await.unwrap_err();
    assert!(e.contains("Redis TLS CA") && e.contains("nope.crt"), "{e}");
}

/// A Redis Cluster whose nodes speak TLS only, to clients and to each other.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_redis_cluster_over_tls_holds_tasks_on_every_node() {
    let certs = Certs::new();
    let cluster = [
        "--cluster-enabled",
        "yes",
        "--tls-cluster",
        "yes",
        "--cluster-config-file",
        "nodes.conf",
        "--cluster-node-timeout",
        "1000",
    ];
    let nodes: Vec<TlsRedis> = (0..3).map(|_| TlsRedis::start(&certs, &cluster)).collect();
    let addrs: Vec<String> = nodes
        .iter()
        .map(|n| format!("127.0.0.1:{}", n.port))
        .collect();
    let out = Command::new("redis-cli")
        .args(certs.cli_args())
        .args(["--cluster", "create"])
        .args(&addrs)
        .args(["--cluster-replicas", "0", "--cluster-yes"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "redis-cli --cluster create: {}",
        String::from_utf8_lossy(&out.stdout)
    );
    let deadline = Instant::now() + Duration::from_secs(30);
    while !nodes.iter().all(|n| {
        n.cli(&certs, &["cluster", "info"])
            .contains("cluster_state:ok")
    }) {
        assert!(Instant::now() < deadline, "the TLS cluster did not come up");
        std::thread::sleep(Duration::from_millis(50));
    }
    let url = format!("rediss-cluster://{}", addrs.join(","));
    let a = open(&url, certs.tls(true)).await.unwrap();
    let ids: Vec<String> = (0..12).map(|i| format!("task-{i}")).collect();
    for id in &ids {
        a.create_task(id, &config()).await.unwrap();
    }
    let b = open(&url, certs.tls(true)).await.unwrap();
    let mut seen: Vec<String> = b.load().await.unwrap().into_iter().map(|t| t.id).collect();
    seen.sort();
    let mut want = ids.clone();
    want.sort();
    assert_eq!(seen, want);
    for n in &nodes {
        let keys: u64 = n.cli(&certs, &["dbsize"]).trim().parse().unwrap();
        assert!(keys > 0, "node {} holds no task", n.port);
    }
    let e = open(&url, certs.tls(false)).await.unwrap_err();
    assert!(e.contains("connecting") || e.contains("Cluster"), "{e}");
}

/// Two real servers share a task through a TLS Redis: one configured by flags, one by
/// its config file (`store_tls_*`); a server without the client certificate does not
/// start, nor one given TLS files for a plaintext URL.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn servers_share_tasks_through_a_tls_redis_configured_by_flags_or_file() {
    let certs = Certs::new();
    let redis = TlsRedis::start(&certs, &[]);
    let url = redis.url();
    let p = |p: &PathBuf| p.to_str().unwrap().to_string();
    let (ca, cert, key) = (p(&certs.ca), p(&certs.client_cert), p(&certs.client_key));
    let by_flags = [
        "--store",
        &url,
        "--store-tls-ca",
        &ca,
        "--store-tls-cert",
        &cert,
        "--store-tls-key",
        &key,
    ];
    let file = write(
        certs.dir.path(),
        "tamrm.toml",
        &format!(
            "store = \"{url}\"\nstore_tls_ca = \"{ca}\"\nstore_tls_cert = \"{cert}\"\nstore_tls_key = \"{key}\"\n"
        ),
    );
    let a = Binary::start(&by_flags);
    let b = Binary::start(&["--config", file.to_str().unwrap()]);
    let mut ca_client = connect(a.addr).await;
    let mut cb_client = connect(b.addr).await;
    create(&mut ca_client, "shared", discrete(2, 4, 1, 0, 1)).await;
    let seen = get_task(&mut cb_client, "shared").await;
    assert_eq!(seen.task_id, "shared");
    assert_eq!(redis.cli(&certs, &["scard", "tamrm:tasks"]).trim(), "1");

    // Without the client certificate: Redis refuses the connection, the start fails
    // (exit 1). TLS files with a plaintext URL: a settings error (exit 2).
    let plain = format!("redis://127.0.0.1:{}", redis.port);
    for (store, code, says) in [(url, 1, "Certificate"), (plain, 2, "rediss://")] {
        let ca = ca.clone();
        let (got, log) = tokio::task::spawn_blocking(move || {
            crate::tls::serve_fails(&["--store", &store, "--store-tls-ca", &ca])
        })
        .await
        .unwrap();
        assert_eq!(got, Some(code), "{log}");
        assert!(log.contains(says), "{log}");
    }
    for bin in [a, b] {
        let (status, log) = bin.terminate();
        assert!(status.success(), "{log}");
    }
}
