//! The server's limits hold for tasks it did not create itself: tasks restored from a data
//! dir written under higher limits, and tasks adopted from a Redis store another replica
//! created them in. Such a task past `max_pool_capacity` / `max_pool_bytes` is served
//! read-only (docs/configuration.md, docs/decisions/stored-tasks-past-a-limit-are-read-only.md).

use tamrm::proto;
use tonic::Code;

use crate::common::{
    self, batch, connect, create, discrete, get_pool, try_add_discrete as try_add, Binary,
    RedisServer,
};

/// Refused as a read-only task's change: RESOURCE_EXHAUSTED naming the limit.
fn assert_read_only(e: &tonic::Status, limit: &str) {
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(
        e.message().contains("read-only") && e.message().contains(limit),
        "the status says the task is read-only and names the limit: {e:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restored_task_past_a_lowered_limit_is_served_read_only() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let data = data.to_str().unwrap();
    let server = Binary::start(&["--data-dir", data]);
    let mut c = connect(server.addr).await;
    create(&mut c, "big", discrete(3, 100, 2, 1, 2)).await;
    create(&mut c, "small", discrete(3, 8, 2, 1, 2)).await;
    for i in 0..3u32 {
        for id in ["big", "small"] {
            try_add(&mut c, id, &[i % 3, 1, 2], f64::from(i))
                .await
                .unwrap();
        }
    }
    let (big, small) = (
        get_pool(&mut c, "big").await,
        get_pool(&mut c, "small").await,
    );
    let (status, _) = server.terminate();
    assert!(status.success());

    // The same data dir under a lower max_pool_capacity.
    let server = Binary::start(&["--data-dir", data, "--max-pool-capacity", "50"]);
    let mut c = connect(server.addr).await;
    assert_eq!(get_pool(&mut c, "big").await, big, "reads go on");
    let e = try_add(&mut c, "big", &[0, 0], 9.0).await.unwrap_err();
    assert_read_only(&e, "max_pool_capacity = 50");
    // A task within the limits is untouched.
    assert_eq!(
        try_add(&mut c, "small", &[0, 0], 9.0).await.unwrap(),
        small.pool_version + 1
    );
    // Steps are shaped against the pool; an episode end that would enter it is refused.
    let (mut s, _) = common::Stream::open(&mut c, "big", 2).await.unwrap();
    let shaped = s
        .step(batch(&[0, 1], &[1.0, 1.0], &[false, false]))
        .await
        .expect("steps need no change");
    assert_eq!(shaped.pool_version, big.pool_version);
    let e = s
        .step(batch(&[2, 2], &[1.0, 1.0], &[true, true]))
        .await
        .expect_err("an end that enters the pool is a change");
    assert_read_only(&e, "max_pool_capacity = 50");
    drop(s);
    assert_eq!(
        get_pool(&mut c, "big").await,
        big,
        "nothing changed the pool"
    );
    // A new task past the limit is refused as always; deleting the old one works.
    let e = c
        .create_task(proto::CreateTaskRequest {
            task_id: "big2".into(),
            config: Some(discrete(3, 100, 2, 1, 2)),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    c.delete_task(proto::DeleteTaskRequest {
        task_id: "big".into(),
    })
    .await
    .expect("a read-only task can be deleted");
    let (status, log) = server.terminate();
    assert!(status.success());
    assert!(
        log.lines().any(|l| l.contains("read-only")
            && l.contains("big")
            && l.contains("max_pool_capacity")),
        "the start warns, naming the task and the limit:\n{log}"
    );

    // Stream and task limits hold for restored tasks too: `small` is the one left.
    let server = Binary::start(&[
        "--data-dir",
        data,
        "--max-stream-bytes",
        "64",
        "--max-tasks",
        "1",
    ]);
    let mut c = connect(server.addr).await;
    let Err(e) = common::Stream::open(&mut c, "small", 1).await else {
        panic!("a stream past max_stream_bytes opened on a restored task");
    };
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("max_stream_bytes"), "{e:?}");
    let e = c
        .create_task(proto::CreateTaskRequest {
            task_id: "other".into(),
            config: Some(discrete(3, 8, 2, 1, 2)),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("max_tasks"), "{e:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_task_adopted_from_redis_past_a_replicas_limit_is_read_only_there() {
    let redis = RedisServer::start();
    let url = redis.url();
    let roomy = common::start_server(None, |s| s.store = Some(url.clone())).await;
    let url2 = redis.url();
    let strict = common::start_server(None, move |s| {
        s.store = Some(url2);
        s.limits.max_pool_bytes = 1024;
    })
    .await;
    let (mut ca, mut cb) = (connect(roomy.addr()).await, connect(strict.addr()).await);
    create(&mut ca, "t", discrete(3, 100, 2, 1, 2)).await;
    try_add(&mut ca, "t", &[0, 1, 2], 1.0).await.unwrap();
    let pool = get_pool(&mut ca, "t").await;

    assert_eq!(
        get_pool(&mut cb, "t").await,
        pool,
        "the strict replica serves reads"
    );
    let e = try_add(&mut cb, "t", &[1, 1], 5.0).await.unwrap_err();
    assert_read_only(&e, "max_pool_bytes = 1024");
    // The replica whose limits allow it goes on changing the pool, and the strict one
    // follows.
    let v = try_add(&mut ca, "t", &[2, 2], 6.0).await.unwrap();
    assert_eq!(v, pool.pool_version + 1);
    let want = get_pool(&mut ca, "t").await;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    while get_pool(&mut cb, "t").await != want {
        assert!(
            std::time::Instant::now() < deadline,
            "the strict replica never followed"
        );
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
}
