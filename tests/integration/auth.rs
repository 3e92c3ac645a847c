//! API keys, roles, tenants and quotas (SPEC §11) against a real server on 127.0.0.1:0:
//! the credential matrix, tenant isolation on every RPC (Shape included), quotas, the
//! key file read again on SIGHUP (ending the open streams of removed or lowered keys),
//! and data written before tenants existed.

use std::path::Path;
use std::time::{Duration, Instant};

use crate::common;
use crate::common::*;
use tamrm::auth::{hash_key, Role, SHAPING_ROLES};
use tamrm::proto::{self, shape_request, shape_response, ShapeRequest, ShapeResponse};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Request, Status};

/// The key of (tenant, role) in these tests.
pub(crate) fn key(tenant: &str, role: &str) -> String {
    format!("key-of-{tenant}-{role}")
}

pub(crate) fn key_file(dir: &Path, keys: &[(&str, &str)], extra: &str) -> std::path::PathBuf {
    let mut text = String::new();
    for (tenant, role) in keys {
        text += &format!(
            "[[keys]]\ntenant = \"{tenant}\"\nrole = \"{role}\"\nsha256 = \"{}\"\n",
            hash_key(key(tenant, role).as_bytes())
        );
    }
    let path = dir.join("keys.toml");
    std::fs::write(&path, text + extra).unwrap();
    path
}

/// `msg` with `authorization: Bearer <key>` (or no credential).
fn with<T>(key: Option<&str>, msg: T) -> Request<T> {
    let mut r = Request::new(msg);
    if let Some(k) = key {
        r.metadata_mut()
            .insert("authorization", format!("Bearer {k}").parse().unwrap());
    }
    r
}

fn task_id(id: &str) -> String {
    id.to_string()
}

/// Opens a Shape stream with `key` on `task` and returns it with the opened task.
pub(crate) async fn open(
    c: &mut Client,
    key: Option<&str>,
    task: &str,
    num_envs: u32,
) -> Result<(mpsc::Sender<ShapeRequest>, tonic::Streaming<ShapeResponse>), Status> {
    let (tx, rx) = mpsc::channel(8);
    tx.send(ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: task_id(task),
            num_envs,
            ..Default::default()
        })),
    })
    .await
    .unwrap();
    let mut answers = c
        .shape(with(key, ReceiverStream::new(rx)))
        .await?
        .into_inner();
    match answers.message().await? {
        Some(ShapeResponse {
            kind: Some(shape_response::Kind::Opened(t)),
        }) => {
            assert_eq!(t.task_id, task);
            Ok((tx, answers))
        }
        other => panic!("expected opened, got {other:?}"),
    }
}

pub(crate) async fn step(
    tx: &mpsc::Sender<ShapeRequest>,
    answers: &mut tonic::Streaming<ShapeResponse>,
    b: proto::StepBatch,
) -> Result<proto::ShapedBatch, Status> {
    let _ = tx
        .send(ShapeRequest {
            kind: Some(shape_request::Kind::Steps(b)),
        })
        .await;
    match answers.message().await? {
        Some(ShapeResponse {
            kind: Some(shape_response::Kind::Shaped(s)),
        }) => Ok(s),
        other => panic!("expected shaped, got {other:?}"),
    }
}

/// Calls the RPC `method` on task `task` with `key`; Ok(()) or the status.
pub(crate) async fn call(
    c: &mut Client,
    method: &str,
    key: Option<&str>,
    task: &str,
) -> Result<(), Status> {
    let id = task_id(task);
    match method {
        "CreateTask" => c
            .create_task(with(
                key,
                proto::CreateTaskRequest {
                    task_id: id,
                    config: Some(discrete(2, 4, 1, 0, 1)),
                },
            ))
            .await
            .map(drop),
        "GetTask" => c
            .get_task(with(key, proto::GetTaskRequest { task_id: id }))
            .await
            .map(drop),
        "ListTasks" => c
            .list_tasks(with(key, proto::ListTasksRequest {}))
            .await
            .map(drop),
        "DeleteTask" => c
            .delete_task(with(key, proto::DeleteTaskRequest { task_id: id }))
            .await
            .map(drop),
        "ResetPool" => c
            .reset_pool(with(key, proto::ResetPoolRequest { task_id: id }))
            .await
            .map(drop),
        "GetPool" => c
            .get_pool(with(key, proto::GetPoolRequest { task_id: id }))
            .await
            .map(drop),
        "AddTrajectory" => c
            .add_trajectory(with(
                key,
                proto::AddTrajectoryRequest {
                    task_id: id,
                    trajectory: Some(dtraj(&[1, 0], 1.0)),
                },
            ))
            .await
            .map(drop),
        "Shape" => {
            let (tx, mut rx) = open(c, key, task, 1).await?;
            step(&tx, &mut rx, batch(&[1], &[1.0], &[true]))
                .await
                .map(drop)
        }
        "Follow" => {
            let open = proto::FollowOpen {
                task_id: id,
                num_envs: 1,
                client_id: String::new(),
            };
            let (mut f, _) = Follower::open_with(c, key, open).await?;
            f.ends(vec![dend(0, 0, &[1], None, 1.0)], 1).await.map(drop)
        }
        other => panic!("no such RPC {other}"),
    }
}

const ROLES: [&str; 3] = ["reader", "writer", "admin"];

#[tokio::test]
async fn the_credential_matrix() {
    let dir = tempfile::tempdir().unwrap();
    let keys: Vec<(&str, &str)> = ROLES.iter().map(|r| ("team-a", *r)).collect();
    let file = key_file(dir.path(), &keys, "");
    let server = start_server(None, |s| s.api_keys = Some(file)).await;
    let mut c = connect(server.addr()).await;
    let admin = key("team-a", "admin");

    for (method, needed) in SHAPING_ROLES {
        // Each call finds the task it acts on.
        call(&mut c, "CreateTask", Some(&admin), "t").await.unwrap();
        for bad in [None, Some("not-a-known-key")] {
            let e = call(&mut c, method, bad, "t").await.unwrap_err();
            assert_eq!(
                e.code(),
                Code::Unauthenticated,
                "{method} with {bad:?}: {e:?}"
            );
        }
        // A malformed header is refused too.
        let mut r = Request::new(proto::ListTasksRequest {});
        r.metadata_mut()
            .insert("authorization", admin.parse().unwrap());
        assert_eq!(
            c.list_tasks(r).await.unwrap_err().code(),
            Code::Unauthenticated
        );
        for role in ROLES {
            call(&mut c, "CreateTask", Some(&admin), "t").await.unwrap();
            let k = key("team-a", role);
            let got = call(&mut c, method, Some(&k), "t").await;
            let allowed = match role {
                "reader" => Role::Reader,
                "writer" => Role::Writer,
                _ => Role::Admin,
            } >= *needed;
            if allowed {
                assert!(got.is_ok(), "{method} as {role}: {got:?}");
            } else {
                let e = got.unwrap_err();
                assert_eq!(
                    e.code(),
                    Code::PermissionDenied,
                    "{method} as {role}: {e:?}"
                );
                assert!(e.message().contains("needs role"), "{}", e.message());
                assert!(
                    !e.message().contains(&k),
                    "the key is echoed: {}",
                    e.message()
                );
            }
        }
    }

    // Health checks need no key.
    use tonic_health::pb::{health_client::HealthClient, HealthCheckRequest};
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{}", server.addr()))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let health = HealthClient::new(channel)
        .check(HealthCheckRequest {
            service: "tamrm.v1.Shaping".into(),
        })
        .await
        .unwrap();
    assert_eq!(health.into_inner().status, 1, "SERVING");
    server.shutdown().await;
}

/// Every RPC of one tenant on a task id that only the other tenant has answers exactly
/// what it answers for an id nobody has; same ids are separate tasks.
#[tokio::test]
async fn tenants_are_isolated_on_every_rpc() {
    let dir = tempfile::tempdir().unwrap();
    let file = key_file(dir.path(), &[("team-a", "admin"), ("team-b", "admin")], "");
    let server = start_server(None, |s| s.api_keys = Some(file)).await;
    let mut c = connect(server.addr()).await;
    let (a, b) = (key("team-a", "admin"), key("team-b", "admin"));

    // Both create "cartpole" with different configs: two tasks, no ALREADY_EXISTS.
    let cfg_a = discrete(2, 4, 1, 0, 1);
    let cfg_b = discrete(3, 2, 1, 0, 1);
    for (k, cfg) in [(&a, &cfg_a), (&b, &cfg_b)] {
        c.create_task(with(
            Some(k),
            proto::CreateTaskRequest {
                task_id: "cartpole".into(),
                config: Some(*cfg),
            },
        ))
        .await
        .unwrap();
    }
    call(&mut c, "CreateTask", Some(&a), "secret-of-a")
        .await
        .unwrap();
    let mut seen = Vec::new();
    for k in [&a, &b] {
        let t = c
            .get_task(with(
                Some(k),
                proto::GetTaskRequest {
                    task_id: "cartpole".into(),
                },
            ))
            .await
            .unwrap()
            .into_inner();
        seen.push((t.task_id, t.config.unwrap().num_actions));
    }
    assert_eq!(seen, [("cartpole".into(), 2), ("cartpole".into(), 3)]);

    let base = c.clone();
    let list = |k: &str| {
        let mut c = base.clone();
        let k = k.to_string();
        async move {
            c.list_tasks(with(Some(&k), proto::ListTasksRequest {}))
                .await
                .unwrap()
                .into_inner()
                .tasks
                .into_iter()
                .map(|t| t.task_id)
                .collect::<Vec<_>>()
        }
    };
    assert_eq!(list(&a).await, ["cartpole", "secret-of-a"]);
    assert_eq!(list(&b).await, ["cartpole"]);

    // Shaping on a's cartpole changes a's pool only; the answer names only a's task.
    let (tx, mut rx) = open(&mut c, Some(&a), "cartpole", 1).await.unwrap();
    let shaped = step(&tx, &mut rx, batch(&[1], &[1.0], &[true]))
        .await
        .unwrap();
    assert_eq!(shaped.pool_version, 1);
    drop(tx);
    let pool = |k: &str| {
        let mut c = base.clone();
        let k = k.to_string();
        async move {
            c.get_pool(with(
                Some(&k),
                proto::GetPoolRequest {
                    task_id: "cartpole".into(),
                },
            ))
            .await
            .unwrap()
            .into_inner()
        }
    };
    assert_eq!(pool(&a).await.trajectories.len(), 1);
    assert_eq!(pool(&b).await.trajectories.len(), 0);
    assert_eq!(pool(&a).await.task_id, "cartpole");

    // b on a's task: exactly what b gets for an id nobody has (the id differs only in
    // the message's id, so compare with the id swapped).
    for (method, _) in SHAPING_ROLES {
        if matches!(*method, "CreateTask" | "ListTasks") {
            continue;
        }
        let theirs = call(&mut c, method, Some(&b), "secret-of-a")
            .await
            .unwrap_err();
        let nobodys = call(&mut c, method, Some(&b), "secret-of-z")
            .await
            .unwrap_err();
        assert_eq!(theirs.code(), Code::NotFound, "{method}: {theirs:?}");
        assert_eq!(
            theirs.message().replace("secret-of-a", "ID"),
            nobodys.message().replace("secret-of-z", "ID"),
            "{method}"
        );
        // Nor does a near miss suggest a's id.
        let near = call(&mut c, method, Some(&b), "secret-of-ab")
            .await
            .unwrap_err();
        assert!(
            !near.message().contains("did you mean"),
            "{method}: {near:?}"
        );
    }
    // ... and a's task is untouched by all of that.
    assert_eq!(list(&a).await, ["cartpole", "secret-of-a"]);
    let near = call(&mut c, "GetTask", Some(&a), "secret-of-ab")
        .await
        .unwrap_err();
    assert!(
        near.message().contains("did you mean \"secret-of-a\""),
        "{near:?}"
    );

    // b deleting its cartpole leaves a's.
    call(&mut c, "DeleteTask", Some(&b), "cartpole")
        .await
        .unwrap();
    assert_eq!(list(&a).await, ["cartpole", "secret-of-a"]);
    assert_eq!(pool(&a).await.trajectories.len(), 1);
    server.shutdown().await;
}

#[tokio::test]
async fn quotas_answer_resource_exhausted() {
    let dir = tempfile::tempdir().unwrap();
    let file = key_file(
        dir.path(),
        &[("q", "admin"), ("free", "admin")],
        "[tenants.q]\nmax_tasks = 2\nmax_open_streams = 1\nmax_steps_per_second = 4\n",
    );
    let server = start_server(None, |s| s.api_keys = Some(file)).await;
    let mut c = connect(server.addr()).await;
    let (q, free) = (key("q", "admin"), key("free", "admin"));

    // Tasks.
    call(&mut c, "CreateTask", Some(&q), "a").await.unwrap();
    call(&mut c, "CreateTask", Some(&q), "b").await.unwrap();
    call(&mut c, "CreateTask", Some(&q), "b").await.unwrap();
    let e = call(&mut c, "CreateTask", Some(&q), "c").await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("max_tasks = 2"), "{}", e.message());
    for id in ["a", "b", "c"] {
        call(&mut c, "CreateTask", Some(&free), id).await.unwrap();
    }

    // Open streams: one at a time; the slot comes back when the stream ends.
    let (tx, mut rx) = open(&mut c, Some(&q), "a", 4).await.unwrap();
    let e = open(&mut c, Some(&q), "b", 1).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(
        e.message().contains("max_open_streams = 1"),
        "{}",
        e.message()
    );
    let other = open(&mut c, Some(&free), "a", 1).await;
    assert!(other.is_ok(), "another tenant's streams are not counted");

    // Steps per second: 4 per second, a batch of 5 never fits; 4 then 4 more at once
    // is over (the second needs a second of refill).
    let four = || batch(&[0, 1, 0, 1], &[1.0; 4], &[false; 4]);
    step(&tx, &mut rx, four()).await.unwrap();
    let e = step(&tx, &mut rx, four()).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(
        e.message().contains("max_steps_per_second = 4"),
        "{}",
        e.message()
    );
    drop(tx);
    let deadline = Instant::now() + Duration::from_secs(10);
    let (tx, mut rx) = loop {
        match open(&mut c, Some(&q), "b", 5).await {
            Ok(s) => break s,
            Err(e) if e.code() == Code::ResourceExhausted && Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(20)).await
            }
            Err(e) => panic!("the stream slot did not come back: {e:?}"),
        }
    };
    let five = batch(&[0; 5], &[1.0; 5], &[false; 5]);
    let e = step(&tx, &mut rx, five).await.unwrap_err();
    assert!(e.message().contains("can never fit"), "{}", e.message());
    server.shutdown().await;
}

/// Follow streams count against `max_open_streams` with Shape streams, and the steps a
/// follower reports against `max_steps_per_second`; a refused message commits nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn follow_streams_and_their_steps_count_against_the_quotas() {
    let dir = tempfile::tempdir().unwrap();
    let file = key_file(
        dir.path(),
        &[("q", "writer")],
        "[tenants.q]\nmax_open_streams = 1\nmax_steps_per_second = 4\n",
    );
    let server = start_server(None, |s| s.api_keys = Some(file)).await;
    let mut c = connect(server.addr()).await;
    let q = key("q", "writer");
    call(&mut c, "CreateTask", Some(&q), "a").await.unwrap();
    let open_msg = |client_id: &str| proto::FollowOpen {
        task_id: "a".into(),
        num_envs: 1,
        client_id: client_id.into(),
    };
    let pool = |c: &mut Client| {
        let mut c = c.clone();
        let q = q.clone();
        async move {
            c.get_pool(with(
                Some(&q),
                proto::GetPoolRequest {
                    task_id: "a".into(),
                },
            ))
            .await
            .unwrap()
            .into_inner()
        }
    };
    let steps_shaped = |c: &mut Client| {
        let mut c = c.clone();
        let q = q.clone();
        async move {
            c.get_task(with(
                Some(&q),
                proto::GetTaskRequest {
                    task_id: "a".into(),
                },
            ))
            .await
            .unwrap()
            .into_inner()
            .stats
            .unwrap()
            .steps_shaped
        }
    };

    // One stream at a time, whichever kind.
    let (mut f, _) = Follower::open_with(&mut c, Some(&q), open_msg("one"))
        .await
        .unwrap();
    let e = Follower::open_with(&mut c, Some(&q), open_msg("two"))
        .await
        .err()
        .expect("a second stream is over the quota");
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(
        e.message().contains("max_open_streams = 1"),
        "{}",
        e.message()
    );
    let e = open(&mut c, Some(&q), "a", 1).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");

    // Reported steps: 4 per second; 4 then 4 more at once is over, and the refused
    // message's end is not committed.
    f.ends(vec![dend(0, 0, &[1], None, 1.0)], 4).await.unwrap();
    let before = pool(&mut c).await;
    f.send(ends_msg(vec![dend(0, 1, &[0], None, 9.0)], 4)).await;
    let e = f.status().await;
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(
        e.message().contains("max_steps_per_second = 4"),
        "{}",
        e.message()
    );
    assert_eq!(pool(&mut c).await, before);
    assert_eq!(steps_shaped(&mut c).await, 4);

    // The slot comes back when the stream ends; more steps than a second's worth never fit.
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut f = loop {
        match Follower::open_with(&mut c, Some(&q), open_msg("one")).await {
            Ok((f, _)) => break f,
            Err(e) if e.code() == Code::ResourceExhausted && Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(20)).await
            }
            Err(e) => panic!("the stream slot did not come back: {e:?}"),
        }
    };
    f.send(ends_msg(Vec::new(), 5)).await;
    let e = f.status().await;
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("can never fit"), "{}", e.message());
    assert_eq!(steps_shaped(&mut c).await, 4);
    server.shutdown().await;
}

/// Tasks written before tenants existed (a server without keys) belong to the default
/// tenant once keys are on, and no other tenant sees them.
#[tokio::test]
async fn data_from_before_tenants_is_the_default_tenants() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let server = start_server(Some(&data), |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "legacy", discrete(2, 4, 1, 0, 1)).await;
    add(&mut c, "legacy", dtraj(&[1, 1, 0], 3.0)).await;
    server.shutdown().await;

    let file = key_file(
        dir.path(),
        &[("default", "reader"), ("team-a", "admin")],
        "",
    );
    let server = start_server(Some(&data), |s| s.api_keys = Some(file)).await;
    let mut c = connect(server.addr()).await;
    let pool = c
        .get_pool(with(
            Some(&key("default", "reader")),
            proto::GetPoolRequest {
                task_id: "legacy".into(),
            },
        ))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(pool.trajectories.len(), 1);
    let e = call(&mut c, "GetPool", Some(&key("team-a", "admin")), "legacy")
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    // A tenant's task written now is its own after a restart too.
    call(&mut c, "CreateTask", Some(&key("team-a", "admin")), "mine")
        .await
        .unwrap();
    server.shutdown().await;
    let file = dir.path().join("keys.toml");
    let server = start_server(Some(&data), |s| s.api_keys = Some(file)).await;
    let mut c = connect(server.addr()).await;
    call(&mut c, "GetTask", Some(&key("team-a", "admin")), "mine")
        .await
        .unwrap();
    let e = call(&mut c, "GetTask", Some(&key("default", "reader")), "mine")
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    server.shutdown().await;
}

/// A key file that is missing or invalid is a settings error: exit 2, naming the file
/// (docs/configuration.md), as for a bad TLS file.
#[test]
fn a_bad_key_file_stops_the_start_with_exit_2_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.toml");
    let garbage = dir.path().join("garbage.toml");
    std::fs::write(&garbage, "keys = [[[\n").unwrap();
    for file in [&missing, &garbage] {
        let path = file.to_str().unwrap();
        let (code, err) = crate::tls::serve_fails(&["--api-keys", path]);
        assert_eq!(code, Some(2), "{path}: {err}");
        assert!(err.contains(path), "the error does not name {path}: {err}");
    }
}

/// Writes a key file of (key, tenant, role) entries at `path`.
fn write_keys(path: &Path, keys: &[(&str, &str, &str)]) {
    let mut text = String::new();
    for (key, tenant, role) in keys {
        text += &format!(
            "[[keys]]\ntenant = \"{tenant}\"\nrole = \"{role}\"\nsha256 = \"{}\"\n",
            hash_key(key.as_bytes())
        );
    }
    std::fs::write(path, text).unwrap();
}

/// The first 8 hex digits of a key's SHA-256: how logs and messages name a key.
fn prefix(key: &str) -> String {
    hash_key(key.as_bytes())[..8].to_string()
}

fn hangup(bin: &Binary) {
    let pid = bin.child.id().to_string();
    assert!(std::process::Command::new("kill")
        .args(["-HUP", &pid])
        .status()
        .unwrap()
        .success());
}

/// The real binary reads its key file again on SIGHUP: a removed key stops working and
/// every open stream it authorised ends with UNAUTHENTICATED, idle or not; a key lowered
/// to reader ends its streams with PERMISSION_DENIED; the streams of a key lowered from
/// admin to writer (still enough) and of other keys go on, in the same episode; the log
/// names each key by tenant and hash prefix, never the key.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_ends_the_streams_of_removed_and_lowered_keys() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("keys.toml");
    let (admin, gone, low, other) = (
        "secret-admin-of-t",
        "secret-writer-of-t",
        "secret-writer-of-u",
        "secret-writer-of-v",
    );
    write_keys(
        &file,
        &[
            (admin, "t", "admin"),
            (gone, "t", "writer"),
            (low, "u", "writer"),
            (other, "v", "writer"),
        ],
    );
    let bin = Binary::start(&["--api-keys", file.to_str().unwrap()]);
    let mut c = connect(bin.addr).await;
    for (key, task) in [(admin, "x"), (low, "y"), (other, "z")] {
        call(&mut c, "CreateTask", Some(key), task).await.unwrap();
    }
    let first = || batch(&[0], &[1.0], &[false]);
    let (admin_tx, mut admin_rx) = open(&mut c, Some(admin), "x", 1).await.unwrap();
    step(&admin_tx, &mut admin_rx, first()).await.unwrap();
    let (other_tx, mut other_rx) = open(&mut c, Some(other), "z", 1).await.unwrap();
    step(&other_tx, &mut other_rx, first()).await.unwrap();
    // Two streams of the key to be removed: one that stepped, one idle since it opened.
    let (gone_tx, mut gone_rx) = open(&mut c, Some(gone), "x", 1).await.unwrap();
    step(&gone_tx, &mut gone_rx, first()).await.unwrap();
    let (_idle_tx, mut idle_rx) = open(&mut c, Some(gone), "x", 1).await.unwrap();
    let follow = |task: &str| proto::FollowOpen {
        task_id: task.into(),
        num_envs: 1,
        client_id: format!("learner-{task}"),
    };
    let (mut low_follow, _) = Follower::open_with(&mut c, Some(low), follow("y"))
        .await
        .unwrap();
    let (mut admin_follow, _) = Follower::open_with(&mut c, Some(admin), follow("x"))
        .await
        .unwrap();

    write_keys(
        &file,
        &[
            (admin, "t", "writer"),
            (low, "u", "reader"),
            (other, "v", "writer"),
        ],
    );
    hangup(&bin);
    // The idle streams end without a message from their clients.
    let e = tokio::time::timeout(Duration::from_secs(10), idle_rx.message())
        .await
        .expect("an idle stream of a removed key ends within 10 s")
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated, "{e:?}");
    assert!(
        e.message().contains("removed") && e.message().contains(&prefix(gone)),
        "{e:?}"
    );
    let e = low_follow.status().await;
    assert_eq!(e.code(), Code::PermissionDenied, "{e:?}");
    assert!(
        e.message().contains("role reader") && e.message().contains("Follow needs role writer"),
        "{e:?}"
    );
    // The removed key's other stream: its next batch is answered with the refusal.
    let e = step(&gone_tx, &mut gone_rx, first()).await.unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated, "{e:?}");

    // The streams of other keys, and of the key still writer, go on in their episodes.
    for (tx, rx) in [(&admin_tx, &mut admin_rx), (&other_tx, &mut other_rx)] {
        let shaped = step(tx, rx, batch(&[1], &[1.0], &[true])).await.unwrap();
        assert_eq!(shaped.steps, [1]);
    }
    admin_follow.ends(Vec::new(), 0).await.unwrap();
    // New calls see the new file.
    let e = call(&mut c, "GetTask", Some(gone), "x").await.unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated);
    call(&mut c, "GetTask", Some(low), "y").await.unwrap();
    let e = open(&mut c, Some(low), "y", 1).await.unwrap_err();
    assert_eq!(e.code(), Code::PermissionDenied);
    let e = call(&mut c, "DeleteTask", Some(admin), "x")
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::PermissionDenied);

    drop((admin_tx, admin_rx, other_tx, other_rx, admin_follow, c));
    let (status, log) = bin.terminate();
    assert!(status.success(), "{log}");
    assert!(log.contains("API key file read again"), "{log}");
    let said = |tenant: &str, key: &str, ended: usize| {
        log.lines().any(|l| {
            l.contains(&format!("tenant={tenant}"))
                && l.contains(&format!("key={}", prefix(key)))
                && l.contains(&format!("streams_ended={ended}"))
        })
    };
    assert!(said("t", gone, 2), "the removal is not logged: {log}");
    assert!(said("u", low, 1), "the lowering is not logged: {log}");
    assert!(said("t", admin, 0), "{log}");
    for key in [admin, gone, low, other] {
        assert!(!log.contains(key), "a key was logged: {log}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_task_quota_counts_the_tenants_tasks_on_every_replica() {
    let redis = common::RedisServer::start();
    let dir = tempfile::tempdir().unwrap();
    let file = key_file(
        dir.path(),
        &[("q", "admin")],
        "[tenants.q]\nmax_tasks = 2\n",
    );
    let url = redis.url();
    let replica = |url: String, file: std::path::PathBuf| {
        start_server(None, move |s| {
            s.api_keys = Some(file);
            s.store = Some(url);
        })
    };
    let a = replica(url.clone(), file.clone()).await;
    let b = replica(url, file).await;
    let (mut ca, mut cb) = (connect(a.addr()).await, connect(b.addr()).await);
    let q = key("q", "admin");
    call(&mut ca, "CreateTask", Some(&q), "a").await.unwrap();
    call(&mut ca, "CreateTask", Some(&q), "b").await.unwrap();
    // B holds none of them, but the store does: the tenant is at its quota.
    let e = call(&mut cb, "CreateTask", Some(&q), "c")
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("max_tasks = 2"), "{}", e.message());
    // Creating an existing task again is no new task, on any replica.
    call(&mut cb, "CreateTask", Some(&q), "b").await.unwrap();
    // A deletion on one replica frees the quota on the others.
    call(&mut ca, "DeleteTask", Some(&q), "a").await.unwrap();
    call(&mut cb, "CreateTask", Some(&q), "c").await.unwrap();
}
