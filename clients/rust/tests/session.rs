//! The client against the real server binary on 127.0.0.1: a session's shaped rewards are
//! those of the same calls in-process; a session resumes across a server killed and
//! restarted (SPEC §9); TLS with an API key; failover to a second address; local
//! sessions (SPEC §13).

mod common;

use std::time::Duration;

use common::{create_request, free_port, shape_all, steps, Server};
use prost::Message;
use tamrm_client::tonic::Code;
use tamrm_client::{rpc, Channel, ChannelOptions, EngineStream, Session};

const NUM_ENVS: u32 = 3;

/// The rewards of `steps` on a fresh in-process registry (no network): the reference.
fn in_process(seed: u64, n: usize) -> Vec<Vec<f64>> {
    let rt = tamrm_client::runtime().unwrap();
    let (registry, service) = common::engine();
    let create = create_request("t").encode_to_vec();
    rt.block_on(rpc::serve(&service, "CreateTask", &create))
        .unwrap();
    let mut session = EngineStream::open(registry, rt, "t", NUM_ENVS, "").unwrap();
    shape_all(&mut session, &steps(seed, n, NUM_ENVS as usize))
}

fn open(channel: &Channel, task: &str) -> Session {
    channel.create_task(&create_request(task)).unwrap();
    channel.open(task, NUM_ENVS, "learner-1").unwrap()
}

#[test]
fn a_session_shapes_as_the_same_calls_in_process() {
    let server = Server::start(&[]);
    let channel = Channel::connect(&[&server.addr], ChannelOptions::new()).unwrap();
    channel.wait_ready(Duration::from_secs(10)).unwrap();
    let mut session = open(&channel, "t");
    let got = shape_all(&mut session, &steps(1, 40, NUM_ENVS as usize));
    assert_eq!(got, in_process(1, 40));
    // The episodes that ended are in the pool: shaping had something to compare with.
    assert!(session.pool_version() > 0);
    assert!(!channel.get_pool("t").unwrap().trajectories.is_empty());
    // The shaped rewards are not the environment's.
    let env: Vec<Vec<f64>> = steps(1, 40, NUM_ENVS as usize)
        .into_iter()
        .map(|s| s.rewards)
        .collect();
    assert_ne!(got, env);
    session.close();
    assert!(session.closed());
    let err = session.step(&steps(1, 1, 3)[0].batch()).unwrap_err();
    assert_eq!(err.status().map(|s| s.code()), Some(Code::Cancelled));
}

#[test]
fn a_rejected_batch_changes_nothing_and_the_session_goes_on() {
    let server = Server::start(&[]);
    let channel = Channel::connect(&[&server.addr], ChannelOptions::new()).unwrap();
    let mut session = open(&channel, "t");
    let all = steps(2, 10, NUM_ENVS as usize);
    let mut got = shape_all(&mut session, &all[..5]);
    let bad = tamrm_client::Batch {
        actions: &[7, 0, 0],
        rewards: &[0.0, 0.0, 0.0],
        ..Default::default()
    };
    let err = session.step(&bad).unwrap_err();
    let status = err.status().expect("a status");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(!session.closed());
    got.extend(shape_all(&mut session, &all[5..]));
    assert_eq!(got, in_process(2, 10));
}

#[test]
fn a_session_resumes_across_a_server_killed_and_restarted() {
    let data = tempfile::tempdir().unwrap();
    let data_dir = data.path().to_str().unwrap().to_string();
    let listen = format!("127.0.0.1:{}", free_port());
    let mut first = Server::start_on(&listen, &["--data-dir", &data_dir]);
    let options = ChannelOptions::new().resume_timeout(Some(Duration::from_secs(30)));
    let channel = Channel::connect(&[&first.addr], options).unwrap();
    let mut session = open(&channel, "t");
    let all = steps(3, 40, NUM_ENVS as usize);
    let mut got = shape_all(&mut session, &all[..15]);
    first.kill();
    // The next step blocks until a server is back on the same address and data dir.
    let restart = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(500));
        Server::start_on(&listen, &["--data-dir", &data_dir])
    });
    got.extend(shape_all(&mut session, &all[15..]));
    let _second = restart.join().unwrap();
    assert_eq!(got, in_process(3, 40));
}

#[test]
fn without_resume_a_broken_stream_is_unavailable_and_closes_the_session() {
    let mut server = Server::start(&[]);
    let options = ChannelOptions::new().resume_timeout(None);
    let channel = Channel::connect(&[&server.addr], options).unwrap();
    let mut session = open(&channel, "t");
    let all = steps(4, 2, NUM_ENVS as usize);
    session.step(&all[0].batch()).unwrap();
    server.kill();
    let err = session.step(&all[1].batch()).unwrap_err();
    assert_eq!(
        err.status().map(|s| s.code()),
        Some(Code::Unavailable),
        "{err}"
    );
    assert!(session.closed());
}

/// A CA, and a server certificate for 127.0.0.1 signed by it (PEM).
fn certificates() -> (String, String, String) {
    use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, IsCa, KeyPair};
    let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    let ca = CertifiedIssuer::self_signed(params, KeyPair::generate().unwrap()).unwrap();
    let key = KeyPair::generate().unwrap();
    let leaf = CertificateParams::new(vec!["127.0.0.1".to_string(), "localhost".into()])
        .unwrap()
        .signed_by(&key, &ca)
        .unwrap();
    (ca.pem(), leaf.pem(), key.serialize_pem())
}

/// The `[[keys]]` entry of `key` (the binary hashes it: `tamrm key --stdin`).
fn key_entry(key: &str) -> String {
    use std::io::Write;
    let mut child = std::process::Command::new(common::binary())
        .args(["key", "--stdin", "--tenant", "team-a", "--role", "admin"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(key.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success());
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn tls_with_an_api_key() {
    let dir = tempfile::tempdir().unwrap();
    let (ca, cert, key) = certificates();
    let write = |name: &str, text: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path.to_str().unwrap().to_string()
    };
    let api_key = "tamrm_test_key_of_the_rust_client";
    let (cert, key, keys) = (
        write("server.crt", &cert),
        write("server.key", &key),
        write("keys.toml", &key_entry(api_key)),
    );
    let server = Server::start(&["--tls-cert", &cert, "--tls-key", &key, "--api-keys", &keys]);
    let tls = || {
        ChannelOptions::new()
            .root_certificates(ca.as_bytes())
            .unwrap()
    };
    let channel = Channel::connect(&[&server.addr], tls().api_key(api_key)).unwrap();
    assert!(channel.tls());
    channel.wait_ready(Duration::from_secs(10)).unwrap();
    let mut session = open(&channel, "t");
    let got = shape_all(&mut session, &steps(5, 10, NUM_ENVS as usize));
    assert_eq!(got, in_process(5, 10));

    // No key: the server refuses; plaintext to a TLS server fails naming the cause.
    let keyless = Channel::connect(&[&server.addr], tls()).unwrap();
    let err = keyless.get_task("t").unwrap_err();
    assert_eq!(err.code(), Code::Unauthenticated, "{err:?}");
    let plain = Channel::connect(&[&server.addr], ChannelOptions::new().api_key(api_key)).unwrap();
    let err = plain.get_task("t").unwrap_err();
    assert_eq!(err.code(), Code::Unavailable, "{err:?}");
    // A bad PEM is refused when the options are made.
    assert!(matches!(
        ChannelOptions::new().root_certificates(&b"not a certificate"[..]),
        Err(tamrm_client::Error::Invalid(m)) if m.contains("root_certificates")
    ));
}

#[test]
fn calls_and_sessions_fail_over_to_the_next_address() {
    let dead = format!("127.0.0.1:{}", free_port());
    let server = Server::start(&[]);
    let channel = Channel::connect(&[dead.as_str(), &server.addr], ChannelOptions::new()).unwrap();
    channel.create_task(&create_request("t")).unwrap();
    assert_eq!(
        channel.get_task("t").unwrap().config.unwrap().num_actions,
        3
    );
    let mut session = channel.open("t", NUM_ENVS, "").unwrap();
    let got = shape_all(&mut session, &steps(6, 10, NUM_ENVS as usize));
    assert_eq!(got, in_process(6, 10));

    // Every address down: UNAVAILABLE, naming them.
    let other = format!("127.0.0.1:{}", free_port());
    let down = Channel::connect(&[dead.as_str(), &other], ChannelOptions::new()).unwrap();
    let err = down.get_task("t").unwrap_err();
    assert_eq!(err.code(), Code::Unavailable);
    assert!(
        err.message().contains(&dead) && err.message().contains(&other),
        "{err:?}"
    );
}

#[test]
fn a_local_session_shapes_as_a_shape_stream() {
    let server = Server::start(&[]);
    let channel = Channel::connect(&[&server.addr], ChannelOptions::new()).unwrap();
    channel.create_task(&create_request("t")).unwrap();
    let mut local = channel.follow("t", NUM_ENVS, "learner-1").unwrap();
    let got = shape_all(&mut local, &steps(7, 30, NUM_ENVS as usize));
    assert_eq!(got, in_process(7, 30));
    // Its episode ends reached the server's pool (a call waits for their acks).
    let pool = channel.get_pool("t").unwrap();
    assert_eq!(pool.pool_version, local.pool_version());
    assert!(!pool.trajectories.is_empty());
    local.close();
}
