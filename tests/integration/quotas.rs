//! Tenant quotas over replicas sharing one Redis store (docs/deployment.md, "Quotas with
//! replicas"): two real `tamrm` binaries on one real redis-server. A stream on one
//! replica takes the tenant's slot on the other (Shape and Follow alike), a replica
//! killed with SIGKILL gives its slots back within the lease time and one stopped
//! gracefully at once, the steps per second of both replicas together stay within the
//! one bucket, and racing creates on both make exactly `max_tasks` tasks.

use std::path::Path;
use std::time::{Duration, Instant};

use tonic::Code;

use crate::auth::{call, key, key_file, open, step};
use crate::common::*;
use tamrm::proto;

/// The lease time these tests give the replicas (`--store-lease-ms`).
const LEASE_MS: u64 = 1500;

/// A replica: the real binary on `redis`'s store with the key file `keys`.
fn replica(redis: &RedisServer, keys: &Path) -> Binary {
    replica_leasing(redis, keys, LEASE_MS)
}

/// A replica whose stream leases last `lease_ms`.
fn replica_leasing(redis: &RedisServer, keys: &Path, lease_ms: u64) -> Binary {
    let url = redis.url();
    let lease = lease_ms.to_string();
    Binary::start(&[
        "--store",
        &url,
        "--api-keys",
        keys.to_str().unwrap(),
        "--store-lease-ms",
        &lease,
    ])
}

fn follow_open(task: &str, client: &str) -> proto::FollowOpen {
    proto::FollowOpen {
        task_id: task.into(),
        num_envs: 1,
        client_id: client.into(),
    }
}

/// An open Shape stream: its requests and its answers.
type Shape = (
    tokio::sync::mpsc::Sender<proto::ShapeRequest>,
    tonic::Streaming<proto::ShapeResponse>,
);

/// Opens a Shape stream with `key` on `task`, retrying while the tenant's slots are taken,
/// for up to `within`: the stream, and the time it took.
async fn open_when_free(
    c: &mut Client,
    key: &str,
    task: &str,
    within: Duration,
) -> (Shape, Duration) {
    let started = Instant::now();
    loop {
        match open(c, Some(key), task, 1).await {
            Ok(s) => return (s, started.elapsed()),
            Err(e) if e.code() == Code::ResourceExhausted && started.elapsed() < within => {
                tokio::time::sleep(Duration::from_millis(20)).await
            }
            Err(e) => panic!("no slot after {:?}: {e:?}", started.elapsed()),
        }
    }
}

/// Two replicas A and B with leases of `lease_ms`, a tenant of one open stream (key
/// `q`) and its task `t`, and a Shape stream on A that holds the tenant's slot.
struct OneSlot {
    redis: RedisServer,
    _dir: tempfile::TempDir,
    q: String,
    a: Binary,
    b: Binary,
    ca: Client,
    cb: Client,
    held: Shape,
}

async fn one_slot_held_on_a(lease_ms: u64) -> OneSlot {
    let redis = RedisServer::start();
    let dir = tempfile::tempdir().unwrap();
    let keys = key_file(
        dir.path(),
        &[("q", "writer")],
        "[tenants.q]\nmax_open_streams = 1\n",
    );
    let q = key("q", "writer");
    let a = replica_leasing(&redis, &keys, lease_ms);
    let b = replica_leasing(&redis, &keys, lease_ms);
    let (mut ca, cb) = (connect(a.addr).await, connect(b.addr).await);
    call(&mut ca, "CreateTask", Some(&q), "t").await.unwrap();
    let (tx, mut rx) = open(&mut ca, Some(&q), "t", 1).await.unwrap();
    step(&tx, &mut rx, batch(&[1], &[1.0], &[false]))
        .await
        .unwrap();
    OneSlot {
        redis,
        _dir: dir,
        q,
        a,
        b,
        ca,
        cb,
        held: (tx, rx),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_stream_quota_holds_over_replicas_and_a_dead_replicas_leases_expire() {
    let OneSlot {
        mut redis,
        _dir,
        q,
        a,
        b: _b,
        mut ca,
        mut cb,
        held: (tx, rx),
    } = one_slot_held_on_a(LEASE_MS).await;

    // A Shape stream on A takes the tenant's one slot on B too, for both kinds of stream.
    let e = open(&mut cb, Some(&q), "t", 1).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(
        e.message().contains("max_open_streams = 1"),
        "{}",
        e.message()
    );
    let e = Follower::open_with(&mut cb, Some(&q), follow_open("t", "f"))
        .await
        .err()
        .expect("a Follow stream is a stream too");
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");

    // When it ends, B may open one: a Follow stream, which then holds the slot on A.
    drop((tx, rx));
    let deadline = Instant::now() + Duration::from_secs(10);
    let (follower, _) = loop {
        match Follower::open_with(&mut cb, Some(&q), follow_open("t", "f")).await {
            Ok(f) => break f,
            Err(e) if e.code() == Code::ResourceExhausted && Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(20)).await
            }
            Err(e) => panic!("the slot did not come back when the stream ended: {e:?}"),
        }
    };
    let e = open(&mut ca, Some(&q), "t", 1).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    drop(follower);
    let (held, _) = open_when_free(&mut ca, &q, "t", Duration::from_secs(10)).await;

    // A replica killed with SIGKILL gives nothing back; its lease expires within the
    // lease time (renewed every third of it), and B may open a stream then. Held open
    // for several renewals first: the lease outlives its first term while A lives.
    tokio::time::sleep(Duration::from_millis(2 * LEASE_MS)).await;
    let e = open(&mut cb, Some(&q), "t", 1).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "renewed: {e:?}");
    drop(a); // kill -9
    let (_on_b, took) = open_when_free(&mut cb, &q, "t", Duration::from_secs(30)).await;
    assert!(
        took <= Duration::from_millis(LEASE_MS) + Duration::from_secs(5),
        "B waited {took:?} for a lease of {LEASE_MS} ms"
    );
    drop(held);

    // Redis unreachable: no stream is let through unchecked, and the status says why.
    redis.kill();
    let e = open(&mut cb, Some(&q), "t", 1).await.unwrap_err();
    assert_eq!(e.code(), Code::Unavailable, "{e:?}");
    assert!(e.message().contains("max_open_streams"), "{}", e.message());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replica_stopped_gracefully_gives_its_leases_back_at_once() {
    // Leases of a minute: none expires while the test runs. (Every part is bound: what
    // a `..` leaves would be dropped here, Redis and B with it.)
    let OneSlot {
        redis: _redis,
        _dir,
        q,
        a,
        b: _b,
        ca: _ca,
        mut cb,
        held,
    } = one_slot_held_on_a(60_000).await;
    let e = open(&mut cb, Some(&q), "t", 1).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");

    // A rolling restart: A stops with the stream open, which it ends; its lease is given
    // back as it goes, so the learner's stream moves to B at once, not a lease time later.
    let (status, log) = tokio::task::spawn_blocking(move || a.terminate())
        .await
        .unwrap();
    assert!(status.success(), "{status:?}: {log}");
    drop(held);
    open_when_free(&mut cb, &q, "t", Duration::from_secs(10)).await;
}

/// How one client fared sending batches as fast as it could: entries accepted, batches
/// refused.
#[derive(Default, Debug)]
struct Sent {
    accepted: u64,
    refused: u64,
}

/// Sends batches of `entries` entries on task `task` through `c` until `until`,
/// opening a new stream after each refusal (a refused batch ends its stream).
async fn flood(mut c: Client, key: String, task: &str, entries: usize, until: Instant) -> Sent {
    let mut sent = Sent::default();
    let one = || {
        batch(
            &vec![0; entries],
            &vec![1.0; entries],
            &vec![false; entries],
        )
    };
    while Instant::now() < until {
        let (tx, mut rx) = open(&mut c, Some(&key), task, entries as u32)
            .await
            .unwrap();
        while Instant::now() < until {
            match step(&tx, &mut rx, one()).await {
                Ok(_) => sent.accepted += entries as u64,
                Err(e) => {
                    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
                    assert!(e.message().contains("max_steps_per_second"), "{e:?}");
                    sent.refused += 1;
                    break;
                }
            }
        }
    }
    sent
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn steps_per_second_hold_over_replicas_within_the_documented_slack() {
    const RATE: u64 = 500;
    const ENTRIES: usize = 20;
    let redis = RedisServer::start();
    let dir = tempfile::tempdir().unwrap();
    let keys = key_file(
        dir.path(),
        &[("s", "writer")],
        &format!("[tenants.s]\nmax_steps_per_second = {RATE}\n"),
    );
    let s = key("s", "writer");
    let (a, b) = (replica(&redis, &keys), replica(&redis, &keys));
    let (mut ca, cb) = (connect(a.addr).await, connect(b.addr).await);
    call(&mut ca, "CreateTask", Some(&s), "t").await.unwrap();

    // Both replicas flooded at once, each by a client offering far more than the rate.
    let started = Instant::now();
    let until = started + Duration::from_secs(3);
    let (on_a, on_b) = tokio::join!(
        flood(ca, s.clone(), "t", ENTRIES, until),
        flood(cb, s.clone(), "t", ENTRIES, until)
    );
    let wall = started.elapsed().as_secs_f64();
    let accepted = on_a.accepted + on_b.accepted;
    // Every accepted entry is a token of the one bucket in Redis, granted within the
    // wall time: at most a second's worth at the start plus the refill, plus what the
    // replicas' blocks may add (docs/deployment.md: one block of a tenth of a second per
    // replica; nothing here, as both start empty, but that is the documented bound).
    let block = RATE / 10;
    let bound = RATE as f64 * wall + RATE as f64 + 2.0 * block as f64;
    assert!(
        (accepted as f64) <= bound,
        "{accepted} entries accepted in {wall:.2} s at {RATE}/s over two replicas (bound {bound:.0}); A {on_a:?}, B {on_b:?}"
    );
    // Each replica alone would have let through nearly twice as much; both were held
    // back, and together they still had at least the first second's worth.
    assert!(
        on_a.refused > 0 && on_b.refused > 0,
        "A {on_a:?}, B {on_b:?}"
    );
    assert!(accepted >= RATE / 2, "A {on_a:?}, B {on_b:?}");
    eprintln!("steps quota over two replicas: {accepted} entries in {wall:.2} s at {RATE}/s (bound {bound:.0}); A {on_a:?}, B {on_b:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn racing_creates_on_two_replicas_make_exactly_max_tasks() {
    const MAX: usize = 3;
    let redis = RedisServer::start();
    let dir = tempfile::tempdir().unwrap();
    let keys = key_file(
        dir.path(),
        &[("m", "admin")],
        &format!("[tenants.m]\nmax_tasks = {MAX}\n"),
    );
    let m = key("m", "admin");
    let (a, b) = (replica(&redis, &keys), replica(&redis, &keys));
    let (ca, cb) = (connect(a.addr).await, connect(b.addr).await);
    // Several rounds, each a burst of creates of new ids on both replicas at once.
    for round in 0..3 {
        let mut creates = Vec::new();
        for i in 0..12 {
            let mut c = if i % 2 == 0 { ca.clone() } else { cb.clone() };
            let (m, id) = (m.clone(), format!("r{round}-{i}"));
            creates.push(tokio::spawn(async move {
                call(&mut c, "CreateTask", Some(&m), &id).await
            }));
        }
        let mut made = 0;
        for c in creates {
            match c.await.unwrap() {
                Ok(()) => made += 1,
                Err(e) => {
                    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
                    assert!(e.message().contains("max_tasks = 3"), "{}", e.message());
                }
            }
        }
        assert_eq!(made, MAX, "round {round}");
        let listed = cb
            .clone()
            .list_tasks(with_key(Some(&m), proto::ListTasksRequest {}))
            .await
            .unwrap()
            .into_inner()
            .tasks;
        assert_eq!(listed.len(), MAX, "round {round}: {listed:?}");
        for t in listed {
            call(&mut ca.clone(), "DeleteTask", Some(&m), &t.task_id)
                .await
                .unwrap();
        }
    }
}
