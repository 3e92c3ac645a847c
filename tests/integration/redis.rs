//! Many servers, one pool (SPEC §10) and resume across them (§9), against a real
//! `redis-server` started by the tests on a free port, and against a real three-node
//! Redis Cluster: replicas are real servers on 127.0.0.1:0 (in-process, or the real
//! binary where a test kills one with -9).

use std::time::{Duration, Instant};

use crate::common;
use crate::common::{
    batch, connect, create, discrete, dtraj, get_pool, get_task, Binary, Client, RedisCluster,
    RedisServer, Stream,
};
use tamrm::proto::{self, shape_request, shape_response, ShapeRequest, ShapeResponse};
use tamrm::server::RunningServer;
use tonic::Code;

/// A replica of the shared store: an in-process server using the store at `url`.
async fn replica(url: &str) -> RunningServer {
    let url = url.to_string();
    common::start_server(None, move |s| {
        s.store = Some(url);
        s.store_poll_ms = 200;
    })
    .await
}

/// A deterministic vector-env run: `n` batches of 2 envs, episodes of random length.
fn script(seed: u64, n: usize) -> Vec<proto::StepBatch> {
    let mut x = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let mut next = move |m: u64| {
        x = x
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (x >> 33) % m
    };
    (0..n)
        .map(|_| {
            let actions: Vec<u32> = (0..2).map(|_| next(3) as u32).collect();
            let rewards: Vec<f64> = (0..2).map(|_| next(7) as f64 - 2.0).collect();
            let ends: Vec<bool> = (0..2).map(|_| next(5) == 0).collect();
            batch(&actions, &rewards, &ends)
        })
        .collect()
}

async fn run(c: &mut Client, id: &str, batches: &[proto::StepBatch]) -> Vec<proto::ShapedBatch> {
    let (mut s, _) = Stream::open(c, id, 2).await.unwrap();
    let mut out = Vec::new();
    for b in batches {
        out.push(s.step(b.clone()).await.unwrap());
    }
    out
}

/// Retries `f` until it holds, for at most 10 s (changes from another replica arrive
/// within the staleness bound).
async fn eventually<F, Fut>(what: &str, mut f: F)
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = bool>,
{
    let deadline = Instant::now() + Duration::from_secs(10);
    while !f().await {
        assert!(Instant::now() < deadline, "never: {what}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_through_a_replica_gets_exactly_the_rewards_of_a_lone_server() {
    let redis = RedisServer::start();
    stream_through_a_replica(&redis.url()).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_through_a_cluster_replica_gets_exactly_the_rewards_of_a_lone_server() {
    let cluster = RedisCluster::start(3);
    stream_through_a_replica(&cluster.url()).await;
}

async fn stream_through_a_replica(url: &str) {
    let shared = replica(url).await;
    let alone = common::start_server(None, |_| {}).await;
    let (mut r, mut m) = (connect(shared.addr()).await, connect(alone.addr()).await);
    for c in [&mut r, &mut m] {
        create(c, "t", discrete(3, 3, 2, 1, 2)).await;
    }
    let batches = script(7, 300);
    let (got, want) = (
        run(&mut r, "t", &batches).await,
        run(&mut m, "t", &batches).await,
    );
    assert!(
        want.last().unwrap().pool_version > 5,
        "the pool changed often"
    );
    assert_eq!(got, want);
    assert_eq!(get_pool(&mut r, "t").await, get_pool(&mut m, "t").await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_replicas_lose_no_update_and_count_each_change_once() {
    let redis = RedisServer::start();
    two_replicas_lose_no_update(&redis.url()).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_replicas_on_a_cluster_lose_no_update_and_count_each_change_once() {
    let cluster = RedisCluster::start(3);
    two_replicas_lose_no_update(&cluster.url()).await;
}

async fn two_replicas_lose_no_update(url: &str) {
    let (a, b) = (replica(url).await, replica(url).await);
    let (mut ca, mut cb) = (connect(a.addr()).await, connect(b.addr()).await);
    create(&mut ca, "t", discrete(3, 3, 2, 1, 2)).await;
    // Concurrent offers through both replicas to a small pool: every stored offer got a
    // version of its own, with no gap and no repeat.
    let offer = |mut c: Client, side: u32| async move {
        let mut stored = Vec::new();
        for i in 0..60u32 {
            let score = f64::from((i * 7 + side * 3) % 23);
            let r = common::add(&mut c, "t", dtraj(&[side, i % 3], score)).await;
            if r.inserted {
                stored.push(r.pool_version);
            }
        }
        stored
    };
    let (sa, sb) = tokio::join!(offer(ca.clone(), 0), offer(cb.clone(), 1));
    let mut versions: Vec<u64> = sa.iter().chain(&sb).copied().collect();
    versions.sort();
    let n = versions.len() as u64;
    assert_eq!(versions, (1..=n).collect::<Vec<_>>());
    for c in [&mut ca, &mut cb] {
        let c = c.clone();
        eventually("both replicas see the last version", || {
            let mut c = c.clone();
            async move { get_task(&mut c, "t").await.stats.unwrap().pool_version == n }
        })
        .await;
    }
    // Streams on both replicas, every episode stored (a pool large enough): the version
    // is the number of episodes ended on either.
    create(&mut ca, "big", discrete(3, 500, 2, 1, 2)).await;
    let (sa, sb) = (script(1, 150), script(2, 150));
    let (ra, rb) = tokio::join!(run(&mut ca, "big", &sa), run(&mut cb, "big", &sb));
    let ends =
        |b: &[proto::StepBatch]| b.iter().flat_map(|x| &x.terminated).filter(|t| **t).count();
    let total = (ends(&sa) + ends(&sb)) as u64;
    assert!(ra.len() == 150 && rb.len() == 150);
    // The last answers on each side report every change of its own; B's snapshot holds
    // A's last changes within the staleness bound.
    let last = ra[149].pool_version.max(rb[149].pool_version);
    assert!(last <= total);
    for c in [&ca, &cb] {
        let c = c.clone();
        eventually("each replica's pool holds every episode of both", || {
            let mut c = c.clone();
            async move { get_pool(&mut c, "big").await.pool_version == total }
        })
        .await;
    }
    let pool = get_pool(&mut cb, "big").await;
    assert_eq!(pool.trajectories.len() as u64, total);
    assert_eq!(pool, get_pool(&mut ca, "big").await);
    // A reset through B is one change, seen by A.
    let v = cb
        .reset_pool(proto::ResetPoolRequest {
            task_id: "big".into(),
        })
        .await
        .unwrap()
        .into_inner()
        .stats
        .unwrap()
        .pool_version;
    assert_eq!(v, total + 1);
    let c = ca.clone();
    eventually("A sees the reset", || {
        let mut c = c.clone();
        async move { get_pool(&mut c, "big").await.trajectories.is_empty() }
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_task_created_on_one_replica_is_usable_at_once_on_another() {
    let redis = RedisServer::start();
    created_on_one_usable_on_another(&redis.url()).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_task_created_on_one_cluster_replica_is_usable_at_once_on_another() {
    let cluster = RedisCluster::start(3);
    created_on_one_usable_on_another(&cluster.url()).await;
}

async fn created_on_one_usable_on_another(url: &str) {
    let (a, b) = (replica(url).await, replica(url).await);
    let (mut ca, mut cb) = (connect(a.addr()).await, connect(b.addr()).await);
    create(&mut ca, "t", discrete(3, 3, 2, 1, 2)).await;
    assert_eq!(get_task(&mut cb, "t").await.task_id, "t");
    let (mut s, _) = Stream::open(&mut cb, "t", 1).await.unwrap();
    let answer = s.step(batch(&[1], &[1.0], &[true])).await.unwrap();
    assert_eq!(answer.pool_version, 1);
    // The same config again through B is the same task; another is refused.
    create(&mut cb, "t", discrete(3, 3, 2, 1, 2)).await;
    let err = cb
        .create_task(proto::CreateTaskRequest {
            task_id: "t".into(),
            config: Some(discrete(4, 3, 2, 1, 2)),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::AlreadyExists, "{err:?}");
    assert!(err.message().contains("num_actions"), "{}", err.message());
    // Listings are the store's.
    create(&mut cb, "u", discrete(2, 3, 2, 1, 2)).await;
    let ids: Vec<String> = ca
        .list_tasks(proto::ListTasksRequest {})
        .await
        .unwrap()
        .into_inner()
        .tasks
        .into_iter()
        .map(|t| t.task_id)
        .collect();
    assert_eq!(ids, ["t", "u"]);
    // A deletion on A ends B's stream and B's lookups.
    ca.delete_task(proto::DeleteTaskRequest {
        task_id: "t".into(),
    })
    .await
    .unwrap();
    let c = cb.clone();
    eventually("B forgets the deleted task", || {
        let mut c = c.clone();
        async move {
            c.get_task(proto::GetTaskRequest {
                task_id: "t".into(),
            })
            .await
            .is_err_and(|e| e.code() == Code::NotFound)
        }
    })
    .await;
    let err = s.step(batch(&[1], &[1.0], &[false])).await.unwrap_err();
    assert_eq!(err.code(), Code::NotFound, "{err:?}");
    // Re-created with another config: a new task everywhere.
    create(&mut cb, "t", discrete(5, 3, 2, 1, 2)).await;
    assert_eq!(get_task(&mut ca, "t").await.config.unwrap().num_actions, 5);
}

/// SPEC §10: `GetTask` and `CreateTask` on a replica that holds a task another server
/// deleted (or deleted and created again) answer the store's state, not the replica's
/// copy, even before it hears of the deletion. The deletion is made behind the replicas'
/// backs (no notification; the 200 ms poll is the only other way they learn of it).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_task_deleted_elsewhere_is_gone_at_once_for_get_task_and_create_task() {
    let redis = RedisServer::start();
    let (a, b) = (replica(&redis.url()).await, replica(&redis.url()).await);
    let (mut ca, mut cb) = (connect(a.addr()).await, connect(b.addr()).await);
    let delete_unannounced = || {
        let keys = ["tamrm:{t}:meta", "tamrm:{t}:traj", "tamrm:{t}:scores"];
        assert_eq!(redis.cli(&[&["DEL"][..], &keys].concat()).trim(), "1");
        redis.cli(&["SREM", "tamrm:tasks", "t"]);
    };
    for round in 0..3 {
        create(&mut ca, "t", discrete(3, 3, 2, 1, 2)).await;
        assert_eq!(get_task(&mut cb, "t").await.config.unwrap().num_actions, 3);
        delete_unannounced();
        let err = cb
            .get_task(proto::GetTaskRequest {
                task_id: "t".into(),
            })
            .await
            .unwrap_err();
        assert_eq!(err.code(), Code::NotFound, "round {round}: {err:?}");
        // Created again with another config: B answers the new task.
        create(&mut ca, "t", discrete(3, 3, 2, 1, 2)).await;
        assert_eq!(get_task(&mut cb, "t").await.config.unwrap().num_actions, 3);
        delete_unannounced();
        create(&mut ca, "t", discrete(4, 3, 2, 1, 2)).await;
        let task = get_task(&mut cb, "t").await;
        assert_eq!(task.config.unwrap().num_actions, 4, "round {round}");
        delete_unannounced();
    }
}

/// Each env's current episode, as a resuming client keeps it.
#[derive(Clone, Default)]
struct Episodes {
    actions: [Vec<u32>; 2],
    reward_sum: [f64; 2],
    ended: [u64; 2],
}

impl Episodes {
    fn record(&mut self, b: &proto::StepBatch) {
        for e in 0..2 {
            self.actions[e].push(b.actions[e]);
            self.reward_sum[e] += b.rewards[e];
            if b.terminated[e] {
                self.actions[e].clear();
                self.reward_sum[e] = 0.0;
                self.ended[e] += 1;
            }
        }
    }

    fn resume(&self) -> Vec<proto::EnvResume> {
        (0..2)
            .map(|e| proto::EnvResume {
                env_id: e as u32,
                actions: self.actions[e].clone(),
                reward_sum: self.reward_sum[e],
                episode: self.ended[e],
                ..Default::default()
            })
            .collect()
    }
}

async fn open_resumed(c: &mut Client, id: &str, eps: &Episodes) -> Stream {
    let mut s = Stream::raw(c).await.unwrap();
    s.send(ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: id.into(),
            num_envs: 2,
            resume: eps.resume(),
            client_id: "client-7".into(),
        })),
    })
    .await;
    match s.recv().await.unwrap() {
        Some(ShapeResponse {
            kind: Some(shape_response::Kind::Opened(_)),
        }) => s,
        other => panic!("expected opened, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_kill_9_of_its_replica_a_client_resumes_on_another_with_the_same_rewards() {
    let redis = RedisServer::start();
    let alone = common::start_server(None, |_| {}).await;
    let mut m = connect(alone.addr()).await;
    create(&mut m, "t", discrete(3, 3, 2, 1, 2)).await;
    let batches = script(11, 200);
    let want = run(&mut m, "t", &batches).await;
    // The batch after which A dies: one that ends an episode, answered, whose answer the
    // client then "loses" and sends again on B.
    let k = (60..200)
        .find(|&i| batches[i].terminated.iter().any(|t| *t))
        .unwrap();

    let url = redis.url();
    let args = ["--store", url.as_str(), "--store-poll-ms", "200"];
    let a = Binary::start(&args);
    let b = Binary::start(&args);
    let (mut ca, mut cb) = (connect(a.addr).await, connect(b.addr).await);
    create(&mut ca, "t", discrete(3, 3, 2, 1, 2)).await;
    let mut eps = Episodes::default();
    let mut s = open_resumed(&mut ca, "t", &eps).await;
    for (i, b) in batches.iter().enumerate().take(k + 1) {
        assert_eq!(s.step(b.clone()).await.unwrap(), want[i], "batch {i} on A");
        if i < k {
            eps.record(b);
        }
    }
    drop(a); // kill -9
    drop(s);
    let mut s = open_resumed(&mut cb, "t", &eps).await;
    // The re-sent batch: A committed its episode end before dying, so B does not commit
    // it again (the version is the uninterrupted one). Its steps are shaped against the
    // pool as it is now, which holds that episode already (SPEC §9: "with the same pool").
    let again = s.step(batches[k].clone()).await.unwrap();
    assert_eq!(
        again.pool_version, want[k].pool_version,
        "not committed twice"
    );
    assert_eq!(again.steps, want[k].steps);
    // Every later batch: exactly the uninterrupted stream's answers.
    for (i, b) in batches.iter().enumerate().skip(k + 1) {
        assert_eq!(s.step(b.clone()).await.unwrap(), want[i], "batch {i} on B");
    }
    assert_eq!(get_pool(&mut cb, "t").await, get_pool(&mut m, "t").await);
    drop(b);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nothing_acknowledged_is_lost_when_redis_is_killed() {
    let mut redis = RedisServer::start();
    let r = replica(&redis.url()).await;
    let mut c = connect(r.addr()).await;
    create(&mut c, "t", discrete(3, 4, 2, 1, 2)).await;
    for i in 0..12u32 {
        common::add(&mut c, "t", dtraj(&[i % 3, 1], f64::from(i % 5))).await;
    }
    run(&mut c, "t", &script(3, 80)).await;
    let before = get_pool(&mut c, "t").await;
    redis.kill();
    let err = c
        .add_trajectory(proto::AddTrajectoryRequest {
            task_id: "t".into(),
            trajectory: Some(dtraj(&[1], 100.0)),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::Unavailable, "{err:?}");
    assert_eq!(
        get_pool(&mut c, "t").await,
        before,
        "a failed commit changes nothing"
    );
    redis.restart();
    // A new replica finds every acknowledged change.
    let fresh = replica(&redis.url()).await;
    let mut f = connect(fresh.addr()).await;
    assert_eq!(get_pool(&mut f, "t").await, before);
    // The old one reconnects by itself.
    let c2 = c.clone();
    eventually("the replica commits again", || {
        let mut c = c2.clone();
        async move {
            c.add_trajectory(proto::AddTrajectoryRequest {
                task_id: "t".into(),
                trajectory: Some(dtraj(&[1], 100.0)),
            })
            .await
            .is_ok()
        }
    })
    .await;
    eventually("the fresh replica sees that commit", || {
        let mut f = f.clone();
        async move { get_pool(&mut f, "t").await.pool_version == before.pool_version + 1 }
    })
    .await;
    assert_eq!(
        get_pool(&mut c, "t").await.pool_version,
        before.pool_version + 1
    );
}

/// Adds an offer of `score`; whether the call succeeded.
async fn try_add(c: &mut Client, id: &str, score: f64) -> Result<u64, tonic::Status> {
    c.add_trajectory(proto::AddTrajectoryRequest {
        task_id: id.into(),
        trajectory: Some(dtraj(&[1, 2], score)),
    })
    .await
    .map(|r| r.into_inner().pool_version)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cluster_spreads_tasks_and_loses_nothing_acknowledged_when_a_node_is_killed() {
    let mut cluster = RedisCluster::start(3);
    let url = cluster.url();
    let r = replica(&url).await;
    let mut c = connect(r.addr()).await;
    let ids: Vec<String> = (0..9).map(|i| format!("task-{i}")).collect();
    for (i, id) in ids.iter().enumerate() {
        create(&mut c, id, discrete(3, 4, 2, 1, 2)).await;
        for j in 0..6u32 {
            common::add(
                &mut c,
                id,
                dtraj(&[j % 3, 1], f64::from((j + i as u32) % 5)),
            )
            .await;
        }
    }
    run(&mut c, "task-0", &script(5, 60)).await;
    // Every key of a task is in its slot; the tasks spread over all three nodes.
    let home: Vec<usize> = ids
        .iter()
        .map(|id| cluster.node_of(&format!("tamrm:{{{id}}}:meta")))
        .collect();
    for n in 0..3 {
        assert!(home.contains(&n), "node {n} holds no task: {home:?}");
        let keys = cluster.nodes[n].cli(&["--scan", "--pattern", "tamrm:{*"]);
        for key in keys.lines() {
            let id = key.split(['{', '}']).nth(1).unwrap();
            let i = ids.iter().position(|t| t == id).unwrap();
            assert_eq!(home[i], n, "{key} is on node {n}");
        }
    }
    let mut before = Vec::new();
    for id in &ids {
        before.push(get_pool(&mut c, id).await);
    }
    let victim = home[0];
    let (down, up) = (
        &ids[home.iter().position(|&h| h == victim).unwrap()],
        &ids[home.iter().position(|&h| h != victim).unwrap()],
    );
    cluster.nodes[victim].kill();
    // A task on the dead node cannot change; one on a live node still can.
    let c2 = c.clone();
    let down2 = down.clone();
    eventually(
        "a commit to a task on the dead node fails UNAVAILABLE",
        || {
            let mut c = c2.clone();
            let id = down2.clone();
            async move {
                try_add(&mut c, &id, 100.0)
                    .await
                    .is_err_and(|e| e.code() == Code::Unavailable)
            }
        },
    )
    .await;
    let up_index = ids.iter().position(|t| t == up).unwrap();
    let c2 = c.clone();
    let up2 = up.clone();
    eventually("a task on a live node takes commits", || {
        let mut c = c2.clone();
        let id = up2.clone();
        async move { try_add(&mut c, &id, 100.0).await.is_ok() }
    })
    .await;
    before[up_index] = get_pool(&mut c, up).await;
    cluster.nodes[victim].restart();
    cluster.wait_up();
    // A fresh replica finds every acknowledged change of every task.
    let fresh = replica(&url).await;
    let mut f = connect(fresh.addr()).await;
    for (id, pool) in ids.iter().zip(&before) {
        let down_index = ids.iter().position(|t| t == down).unwrap();
        let got = get_pool(&mut f, id).await;
        if id == down {
            // A commit that failed while the node was down changed nothing.
            assert_eq!(got, before[down_index], "{id}");
        } else {
            assert_eq!(&got, pool, "{id}");
        }
    }
    // The old replica commits to the restarted node again by itself.
    let c2 = c.clone();
    let down2 = down.clone();
    eventually("the replica commits to the restarted node", || {
        let mut c = c2.clone();
        let id = down2.clone();
        async move { try_add(&mut c, &id, 100.0).await.is_ok() }
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn episode_numbers_past_2_to_the_53_are_recorded_exactly() {
    // Lua's numbers are doubles: counts above 2^53 must not go through them (a count
    // stored as "9.2233720368547758e+18" broke every later resume of that client).
    let redis = RedisServer::start();
    let r = replica(&redis.url()).await;
    let mut c = connect(r.addr()).await;
    create(&mut c, "t", discrete(3, 8, 2, 1, 2)).await;
    let mut eps = Episodes {
        ended: [(1 << 63) + 5, (1 << 53) + 1],
        ..Default::default()
    };
    let both_end = batch(&[0, 1], &[1.0, 2.0], &[true, true]);
    let mut s = open_resumed(&mut c, "t", &eps).await;
    assert_eq!(s.step(both_end.clone()).await.unwrap().pool_version, 2);
    // The answer is "lost": the same batch again, from the same state, commits nothing.
    drop(s);
    let mut s = open_resumed(&mut c, "t", &eps).await;
    assert_eq!(s.step(both_end.clone()).await.unwrap().pool_version, 2);
    // The next episodes (one past each) are new ends.
    eps.record(&both_end);
    drop(s);
    let mut s = open_resumed(&mut c, "t", &eps).await;
    assert_eq!(s.step(both_end.clone()).await.unwrap().pool_version, 4);
    assert_eq!(get_task(&mut c, "t").await.stats.unwrap().pool_version, 4);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_replica_reports_the_counters_of_every_replica() {
    let redis = RedisServer::start();
    let (a, b) = (replica(&redis.url()).await, replica(&redis.url()).await);
    let (mut ca, mut cb) = (connect(a.addr()).await, connect(b.addr()).await);
    create(&mut ca, "t", discrete(3, 4, 2, 1, 2)).await;
    let counters = |task: proto::Task| {
        let s = task.stats.unwrap();
        (s.episodes_completed, s.steps_shaped)
    };
    // A: 5 batches of 2 envs, both ending: 10 episodes, 10 steps.
    let (mut s, _) = Stream::open(&mut ca, "t", 2).await.unwrap();
    for i in 0..5 {
        let r = i as f64;
        s.step(batch(&[0, 1], &[r, r + 0.5], &[true, true]))
            .await
            .unwrap();
    }
    assert_eq!(counters(get_task(&mut ca, "t").await), (10, 10));
    eventually("B reports A's counters", || {
        let mut c = cb.clone();
        async move { counters(get_task(&mut c, "t").await) == (10, 10) }
    })
    .await;
    // B: steps that end no episode (no commit carries them) reach A too.
    let (mut s, _) = Stream::open(&mut cb, "t", 2).await.unwrap();
    for _ in 0..3 {
        s.step(batch(&[2, 2], &[0.0, 0.0], &[false, false]))
            .await
            .unwrap();
    }
    eventually("A reports B's steps", || {
        let mut c = ca.clone();
        async move { counters(get_task(&mut c, "t").await) == (10, 16) }
    })
    .await;
    assert_eq!(counters(get_task(&mut cb, "t").await), (10, 16));
    let late = replica(&redis.url()).await;
    let mut cl = connect(late.addr()).await;
    assert_eq!(counters(get_task(&mut cl, "t").await), (10, 16));
}

/// SPEC §9 and §10: a client resumes on B while A is still committing the batch whose
/// answer it lost. B learnt the client's record before A's commit, so it plans the re-sent
/// end as new; Redis refuses it as a re-send. Then the rest of B's batch was shaped
/// against a pool that never existed: the stream fails with UNAVAILABLE (resume and
/// re-send), the refused end is not counted, and the re-sent batch on a resumed stream
/// gets A's answer exactly.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_end_another_replica_committed_meanwhile_fails_the_stream_not_the_pool() {
    let redis = RedisServer::start();
    let (a, b) = (replica(&redis.url()).await, replica(&redis.url()).await);
    let (mut ca, mut cb) = (connect(a.addr()).await, connect(b.addr()).await);
    create(&mut ca, "t", discrete(3, 4, 2, 0, 1)).await;
    common::add(&mut ca, "t", dtraj(&[1, 0, 2], 1.0)).await;
    eventually("B sees the pool", || {
        let mut c = cb.clone();
        async move { get_pool(&mut c, "t").await.pool_version == 1 }
    })
    .await;
    // Env 0 is in its episode 4 at t = 2; env 1 at t = 0 of its episode 0.
    let mut eps = Episodes::default();
    eps.actions[0] = vec![1, 1];
    eps.reward_sum[0] = 2.0;
    eps.ended[0] = 4;
    // The lost batch: env 0's episode ends, env 1 steps.
    let lost = batch(&[1, 1], &[1.0, 0.5], &[true, false]);
    let mut on_b = open_resumed(&mut cb, "t", &eps).await;
    let mut on_a = open_resumed(&mut ca, "t", &eps).await;
    let answer_a = on_a.step(lost.clone()).await.unwrap();
    assert_eq!(answer_a.pool_version, 2, "A stored the end");
    let e = on_b.step(lost.clone()).await.unwrap_err();
    assert_eq!(e.code(), Code::Unavailable, "{e:?}");
    assert!(e.message().contains("resume the stream"), "{}", e.message());
    // One copy stored, counted once, on either replica.
    let episodes = |task: proto::Task| task.stats.unwrap().episodes_completed;
    for c in [&mut ca, &mut cb] {
        let pool = get_pool(c, "t").await;
        assert_eq!(pool.pool_version, 2);
        let stored: Vec<_> = pool.trajectories.iter().map(|t| t.score).collect();
        assert_eq!(stored, [1.0, 3.0], "the end once, not twice");
    }
    for c in [ca.clone(), cb.clone()] {
        eventually("one episode completed", || {
            let mut c = c.clone();
            async move { episodes(get_task(&mut c, "t").await) == 1 }
        })
        .await;
    }
    // Resumed on B (which now learns A's commit) and re-sent: A's answer, bit for bit.
    let mut on_b = open_resumed(&mut cb, "t", &eps).await;
    assert_eq!(on_b.step(lost).await.unwrap(), answer_a);
    assert_eq!(get_pool(&mut cb, "t").await.pool_version, 2);
    assert_eq!(episodes(get_task(&mut ca, "t").await), 1);
}

/// A group commit through Redis: the ends of several clients' requests, one script for
/// all of them (each client's end record written), and a re-sent end attributed to the
/// request that carried it, not to the others of its group.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_script_commits_a_group_and_names_whose_ends_were_re_sent() {
    use std::sync::Arc;
    use tamrm::core::{ActionSeq, Pool, TaskConfig, TaskConfigInput};
    use tamrm::store::{Counters, EndMark, PoolOp, RedisOptions, RedisStore, Store};

    let redis = RedisServer::start();
    let store = RedisStore::open(&RedisOptions::new(redis.url()))
        .await
        .unwrap();
    let config = TaskConfig::resolve(&TaskConfigInput {
        num_actions: 3,
        pool_capacity: Some(8),
        ..Default::default()
    })
    .unwrap();
    store.create_task("g", &config).await.unwrap();
    let end = |client: &str, env: u32, episode: u64, score: f64| PoolOp::Offer {
        actions: ActionSeq::Discrete(vec![env % 3, 1]),
        score,
        end: Some(EndMark {
            client: Arc::from(client),
            env,
            episode,
        }),
    };
    let scripts = || -> u64 {
        let info = redis.cli(&["INFO", "commandstats"]);
        info.lines()
            .filter(|l| l.starts_with("cmdstat_evalsha:") || l.starts_with("cmdstat_eval:"))
            .filter_map(|l| {
                l.split("calls=")
                    .nth(1)?
                    .split(',')
                    .next()?
                    .parse::<u64>()
                    .ok()
            })
            .sum()
    };
    let parts = vec![
        vec![end("a", 0, 0, 1.0)],
        vec![end("b", 0, 0, 2.0), end("b", 1, 0, 3.0)],
    ];
    let base = Arc::new(Pool::new(8));
    let done = store
        .commit_group("g", base, parts, Counters::default())
        .await
        .unwrap();
    assert_eq!(done.committed.changed, vec![true; 3]);
    assert_eq!((done.committed.version, done.resent), (3, Some(vec![0, 0])));
    assert_eq!(store.ended_episodes("g", "a").await.unwrap(), vec![(0, 1)]);
    let mut b = store.ended_episodes("g", "b").await.unwrap();
    b.sort_unstable();
    assert_eq!(
        b,
        vec![(0, 1), (1, 1)],
        "every client's record, not the first's only"
    );
    // b's env 1 episode 0 again (a re-send), with a's next end and c's first one.
    let before = scripts();
    let parts = vec![
        vec![end("a", 0, 1, 4.0)],
        vec![end("b", 1, 0, 3.0)],
        vec![end("c", 5, 0, 5.0)],
    ];
    let done = store
        .commit_group("g", done.committed.pool, parts, Counters::default())
        .await
        .unwrap();
    assert_eq!(scripts() - before, 1, "one script for the group");
    assert_eq!(done.committed.changed, vec![true, false, true]);
    assert_eq!(done.resent, Some(vec![0, 1, 0]));
    assert_eq!((done.committed.version, done.committed.resent), (5, 1));
    assert_eq!(done.committed.pool.version(), 5);
    assert_eq!(store.ended_episodes("g", "c").await.unwrap(), vec![(5, 1)]);
}
