//! TLS and mutual TLS on a real socket, with certificates made in the test (rcgen): the
//! server behind `--tls-cert`/`--tls-key` (and `--tls-client-ca`) through the lingering
//! incoming wrapper, tonic clients that trust the right CA, another CA, or speak
//! plaintext, `tamrm healthcheck` over TLS, and the start errors for bad files.

use crate::common::*;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, DnType, ExtendedKeyUsagePurpose, IsCa,
    KeyPair,
};
use tamrm::net::tls::TlsFiles;
use tamrm::proto::shaping_client::ShapingClient;
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity};

/// A certificate authority made for one test.
pub(crate) struct Ca {
    issuer: CertifiedIssuer<'static, KeyPair>,
}

/// A PEM certificate (with its chain) and its key.
pub(crate) struct Pem {
    pub(crate) cert: String,
    pub(crate) key: String,
}

impl Ca {
    pub(crate) fn new(name: &str) -> Ca {
        let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params.distinguished_name.push(DnType::CommonName, name);
        let issuer = CertifiedIssuer::self_signed(params, KeyPair::generate().unwrap()).unwrap();
        Ca { issuer }
    }

    pub(crate) fn pem(&self) -> String {
        self.issuer.pem()
    }

    /// A leaf for `names`, its file holding the leaf then this CA (a full chain).
    fn issue(&self, names: &[&str], usage: ExtendedKeyUsagePurpose) -> Pem {
        self.issue_for(names, vec![usage])
    }

    /// A leaf for `names` good for each of `usages` (a Redis Cluster node's certificate
    /// is both a server's and, towards the other nodes, a client's).
    pub(crate) fn issue_for(&self, names: &[&str], usages: Vec<ExtendedKeyUsagePurpose>) -> Pem {
        let names: Vec<String> = names.iter().map(|s| s.to_string()).collect();
        let mut params = CertificateParams::new(names).unwrap();
        params.extended_key_usages = usages;
        let key = KeyPair::generate().unwrap();
        let cert = params.signed_by(&key, &self.issuer).unwrap();
        Pem {
            cert: format!("{}{}", cert.pem(), self.pem()),
            key: key.serialize_pem(),
        }
    }

    pub(crate) fn server(&self) -> Pem {
        self.issue(
            &["localhost", "127.0.0.1"],
            ExtendedKeyUsagePurpose::ServerAuth,
        )
    }

    pub(crate) fn client(&self) -> Pem {
        self.issue(&["trainer"], ExtendedKeyUsagePurpose::ClientAuth)
    }
}

pub(crate) fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

/// A server with TLS (and with `client_ca`, mutual TLS); returns its CA and files dir.
async fn tls_server(
    dir: &Path,
    client_ca: Option<&Ca>,
) -> (tamrm::server::RunningServer, Ca, TlsFiles) {
    let ca = Ca::new("tamrm test CA");
    let server = ca.server();
    let files = TlsFiles {
        cert: Some(write(dir, "server.crt", &server.cert)),
        key: Some(write(dir, "server.key", &server.key)),
        client_ca: client_ca.map(|c| write(dir, "clients-ca.crt", &c.pem())),
    };
    let f = files.clone();
    let running = start_server(None, move |s| s.tls = f).await;
    (running, ca, files)
}

/// A TLS client config trusting `ca_pem`, presenting `identity` if any.
fn client_tls(ca_pem: &str, identity: Option<&Pem>) -> ClientTlsConfig {
    let mut c = ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(ca_pem))
        .domain_name("localhost");
    if let Some(id) = identity {
        c = c.identity(Identity::from_pem(&id.cert, &id.key));
    }
    c
}

/// Connects and makes one unary call (ListTasks), all within 10 s; the error text
/// includes the sources, where tonic keeps the TLS detail.
async fn call(addr: SocketAddr, tls: Option<ClientTlsConfig>) -> Result<usize, String> {
    let attempt = async {
        let scheme = if tls.is_some() { "https" } else { "http" };
        let mut endpoint = Endpoint::from_shared(format!("{scheme}://{addr}")).unwrap();
        if let Some(t) = tls {
            endpoint = endpoint.tls_config(t).map_err(|e| chain(&e))?;
        }
        let channel = endpoint.connect().await.map_err(|e| chain(&e))?;
        let answer = ShapingClient::new(channel)
            .list_tasks(tamrm::proto::ListTasksRequest::default())
            .await
            .map_err(|s| format!("{s:?}"))?;
        Ok(answer.into_inner().tasks.len())
    };
    tokio::time::timeout(Duration::from_secs(10), attempt)
        .await
        .unwrap_or_else(|_| Err("hung: no answer and no error within 10 s".into()))
}

fn chain(e: &dyn std::error::Error) -> String {
    tamrm::net::chain(e)
}

#[tokio::test(flavor = "multi_thread")]
async fn a_client_trusting_the_ca_shapes_over_tls() {
    let dir = tempfile::tempdir().unwrap();
    let (server, ca, _) = tls_server(dir.path(), None).await;
    let addr = server.addr();
    assert_eq!(call(addr, Some(client_tls(&ca.pem(), None))).await, Ok(0));

    // A Shape stream through TLS and the lingering connections.
    let channel = Endpoint::from_shared(format!("https://{addr}"))
        .unwrap()
        .tls_config(client_tls(&ca.pem(), None))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut client = ShapingClient::new(channel);
    create(&mut client, "tls", discrete(2, 10, 1, 0, 1)).await;
    let (mut stream, _) = Stream::open(&mut client, "tls", 1).await.unwrap();
    let shaped = stream.step(batch(&[1], &[1.0], &[true])).await.unwrap();
    assert_eq!(shaped.rewards.len(), 1);
    drop(stream.close());
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_client_trusting_another_ca_is_refused_by_its_own_check() {
    let dir = tempfile::tempdir().unwrap();
    let (server, _, _) = tls_server(dir.path(), None).await;
    let other = Ca::new("another CA");
    let err = call(server.addr(), Some(client_tls(&other.pem(), None)))
        .await
        .unwrap_err();
    assert!(
        err.contains("certificate") && !err.contains("hung"),
        "not a certificate error: {err}"
    );
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn plaintext_and_tls_do_not_mix_and_fail_fast() {
    let dir = tempfile::tempdir().unwrap();
    let (server, ca, _) = tls_server(dir.path(), None).await;
    let err = call(server.addr(), None).await.unwrap_err();
    assert!(!err.contains("hung"), "{err}");
    server.shutdown().await;

    let plain = start_server(None, |_| {}).await;
    let err = call(plain.addr(), Some(client_tls(&ca.pem(), None)))
        .await
        .unwrap_err();
    assert!(!err.contains("hung"), "{err}");
    assert!(
        err.to_lowercase().contains("tls") || err.contains("corrupt"),
        "{err}"
    );
    plain.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn mutual_tls_admits_only_clients_of_the_client_ca() {
    let dir = tempfile::tempdir().unwrap();
    let clients = Ca::new("clients CA");
    let (server, ca, _) = tls_server(dir.path(), Some(&clients)).await;
    let addr = server.addr();

    let none = call(addr, Some(client_tls(&ca.pem(), None))).await;
    assert!(matches!(&none, Err(e) if !e.contains("hung")), "{none:?}");

    let stranger = Ca::new("stranger CA").client();
    let other = call(addr, Some(client_tls(&ca.pem(), Some(&stranger)))).await;
    assert!(matches!(&other, Err(e) if !e.contains("hung")), "{other:?}");

    let good = clients.client();
    assert_eq!(
        call(addr, Some(client_tls(&ca.pem(), Some(&good)))).await,
        Ok(0)
    );
    server.shutdown().await;
}

/// `tamrm healthcheck` with `envs` set and `args`; (exit success, stderr).
fn healthcheck(args: &[&str], envs: &[(&str, &Path)]) -> (bool, String) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_tamrm"));
    cmd.arg("healthcheck").args(args);
    for var in [
        "TAMRM_CONFIG",
        "TAMRM_LISTEN",
        "TAMRM_TLS_CERT",
        "TAMRM_TLS_KEY",
        "TAMRM_TLS_CLIENT_CA",
        "TAMRM_TLS_CA",
        "TAMRM_TLS_SERVER_NAME",
        "TAMRM_TLS_CLIENT_CERT",
        "TAMRM_TLS_CLIENT_KEY",
    ] {
        cmd.env_remove(var);
    }
    for (k, v) in envs {
        cmd.env(k, v);
    }
    let out = cmd.output().expect("run tamrm healthcheck");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[tokio::test(flavor = "multi_thread")]
async fn healthcheck_speaks_tls_with_the_servers_certificate_file_as_ca() {
    let dir = tempfile::tempdir().unwrap();
    let clients = Ca::new("clients CA");
    let (server, _, files) = tls_server(dir.path(), Some(&clients)).await;
    let addr = server.addr().to_string();
    let cert = files.cert.clone().unwrap();
    let id = clients.client();
    let id_cert = write(dir.path(), "hc.crt", &id.cert);
    let id_key = write(dir.path(), "hc.key", &id.key);
    let other_ca = write(dir.path(), "other.crt", &Ca::new("other").pem());
    let (a, c, ic, ik, oc) = (addr.clone(), cert.clone(), id_cert, id_key, other_ca);
    let results = tokio::task::spawn_blocking(move || {
        [
            // As in the container: TAMRM_TLS_CERT (the server's chain) is the CA.
            healthcheck(
                &["--addr", &a],
                &[
                    ("TAMRM_TLS_CERT", &c),
                    ("TAMRM_TLS_CLIENT_CERT", &ic),
                    ("TAMRM_TLS_CLIENT_KEY", &ik),
                ],
            ),
            // Without a client certificate, the mutual-TLS server refuses.
            healthcheck(&["--addr", &a, "--tls-ca", c.to_str().unwrap()], &[]),
            // Another CA: the server's certificate is not trusted.
            healthcheck(
                &["--addr", &a, "--tls-ca", oc.to_str().unwrap()],
                &[
                    ("TAMRM_TLS_CLIENT_CERT", &ic),
                    ("TAMRM_TLS_CLIENT_KEY", &ik),
                ],
            ),
            // Plaintext against TLS.
            healthcheck(&["--addr", &a, "--timeout-secs", "5"], &[]),
        ]
    })
    .await
    .unwrap();
    assert!(results[0].0, "TLS healthcheck failed: {}", results[0].1);
    for (ok, err) in &results[1..] {
        assert!(!ok && err.contains("unhealthy"), "{err}");
        assert!(
            !err.contains("no answer within"),
            "hung instead of failing: {err}"
        );
    }
    assert!(results[2].1.contains("certificate"), "{}", results[2].1);
    server.shutdown().await;
}

/// A port nobody listens on now.
pub(crate) fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// `tamrm healthcheck --config FILE` reads the server's own config file, as `tamrm serve`
/// does: the address it listens on and its `[tls]` certificate (the CA by default), with
/// no other flag or variable; `TAMRM_CONFIG` does the same. A wrong CA, from a flag or the
/// file's `[healthcheck]` table, fails; without the file it speaks plaintext and fails.
#[tokio::test(flavor = "multi_thread")]
async fn healthcheck_reads_the_servers_config_file_with_its_tls() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pem = Ca::new("tamrm test CA").server();
    let (cert, key) = (
        write(d, "server.crt", &pem.cert),
        write(d, "server.key", &pem.key),
    );
    let other = write(d, "other.crt", &Ca::new("other").pem());
    let served = format!(
        "listen = \"127.0.0.1:{}\"\n[tls]\ncert = \"{}\"\nkey = \"{}\"\n",
        free_port(),
        cert.display(),
        key.display()
    );
    let config = write(d, "tamrm.toml", &served);
    let wrong = format!("{served}[healthcheck]\ntls_ca = \"{}\"\n", other.display());
    let wrong = write(d, "wrong-ca.toml", &wrong);
    let server = tokio::task::spawn_blocking({
        let config = config.clone();
        move || Binary::start_listening_as_told(&["--config", config.to_str().unwrap()])
    })
    .await
    .unwrap();
    let addr = server.addr.to_string();
    let results = tokio::task::spawn_blocking(move || {
        let (c, w, o) = (
            config.to_str().unwrap(),
            wrong.to_str().unwrap(),
            other.to_str().unwrap(),
        );
        [
            healthcheck(&["--config", c], &[]),
            healthcheck(&[], &[("TAMRM_CONFIG", Path::new(c))]),
            healthcheck(&["--config", c, "--tls-ca", o], &[]),
            healthcheck(&["--config", w], &[]),
            healthcheck(&["--addr", &addr, "--timeout-secs", "5"], &[]),
        ]
    })
    .await
    .unwrap();
    for (ok, err) in &results[..2] {
        assert!(ok, "the healthcheck with the config file failed: {err}");
    }
    for (ok, err) in &results[2..] {
        assert!(!ok && err.contains("unhealthy"), "{err}");
        assert!(
            !err.contains("no answer within"),
            "hung instead of failing: {err}"
        );
    }
    for (_, err) in &results[2..4] {
        assert!(err.contains("certificate"), "{err}");
    }
    let (status, log) = server.terminate();
    assert!(status.success(), "{log}");
}

/// `tamrm serve` with `args`: it must exit by itself within 20 s; (exit code, stderr).
pub(crate) fn serve_fails(args: &[&str]) -> (Option<i32>, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_tamrm"))
        .args(["serve", "--listen", "127.0.0.1:0"])
        .args(args)
        .env_remove("TAMRM_TLS_CERT")
        .env_remove("TAMRM_TLS_KEY")
        .env_remove("TAMRM_TLS_CLIENT_CA")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn tamrm");
    let deadline = Instant::now() + Duration::from_secs(20);
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("tamrm serve {args:?} started instead of failing");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bad_tls_files_stop_the_start_with_exit_2_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let ca = Ca::new("tamrm test CA");
    let good = ca.server();
    let other = ca.server();
    let cert = write(dir.path(), "server.crt", &good.cert);
    let key = write(dir.path(), "server.key", &good.key);
    let wrong_key = write(dir.path(), "other.key", &other.key);
    let garbage = write(dir.path(), "garbage.pem", "not a certificate\n");
    let missing = dir.path().join("missing.crt");
    let (c, k) = (cert.to_str().unwrap(), key.to_str().unwrap());
    let (w, g, m) = (
        wrong_key.to_str().unwrap(),
        garbage.to_str().unwrap(),
        missing.to_str().unwrap(),
    );
    let cases: [(&[&str], &str); 7] = [
        (&["--tls-cert", c], "--tls-key"),
        (&["--tls-key", k], "--tls-cert"),
        (&["--tls-client-ca", c], "--tls-cert"),
        (&["--tls-cert", m, "--tls-key", k], m),
        (&["--tls-cert", g, "--tls-key", k], g),
        (&["--tls-cert", c, "--tls-key", g], g),
        (&["--tls-cert", c, "--tls-key", k, "--tls-client-ca", g], g),
    ];
    for (args, named) in cases {
        let (code, err) = serve_fails(args);
        assert_eq!(code, Some(2), "{args:?}: {err}");
        assert!(
            err.contains(named),
            "{args:?}: the error does not name {named}: {err}"
        );
    }
    let (code, err) = serve_fails(&["--tls-cert", c, "--tls-key", w]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains(c) && err.contains(w), "{err}");
}
