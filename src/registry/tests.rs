use std::sync::atomic::Ordering;
use std::time::Duration;

use super::*;
use crate::core::ActionSeq;
use crate::store::testing::TestStore;
use crate::store::{apply_ops, MemoryStore, PoolOp};

fn discrete(n: u32, capacity: u32) -> TaskConfigInput {
    TaskConfigInput {
        num_actions: n,
        pool_capacity: Some(capacity),
        ..Default::default()
    }
}

async fn registry(limits: Limits) -> Registry {
    Registry::open(Arc::new(MemoryStore::new()), limits)
        .await
        .unwrap()
        .0
}

fn acts(v: &[u32]) -> ActionSeq {
    ActionSeq::Discrete(v.to_vec())
}

#[tokio::test]
async fn create_is_idempotent_and_names_what_differs() {
    let r = registry(Limits::default()).await;
    let a = r
        .create(DEFAULT_TENANT, "t", &discrete(2, 3), None)
        .await
        .unwrap();
    let b = r
        .create(DEFAULT_TENANT, "t", &discrete(2, 3), None)
        .await
        .unwrap();
    assert!(Arc::ptr_eq(&a, &b));
    let mut other = discrete(2, 3);
    other.alpha = Some(0.5);
    other.gate_potential = Some(true);
    match r.create(DEFAULT_TENANT, "t", &other, None).await {
        Err(Error::AlreadyExists { id, detail }) => {
            assert_eq!(id, "t");
            assert_eq!(
                detail,
                "alpha: existing 0.8, requested 0.5; gate_potential: existing false, requested true"
            );
            assert!(!detail.contains("Some("), "{detail}");
        }
        other => panic!(
            "expected ALREADY_EXISTS, got {:?}",
            other.map(|t| t.id().to_string())
        ),
    }
    // Validation comes first: an invalid config for an existing id is INVALID_ARGUMENT.
    let bad = TaskConfigInput {
        k: Some(9),
        ..discrete(2, 3)
    };
    assert!(matches!(
        r.create(DEFAULT_TENANT, "t", &bad, None).await,
        Err(Error::InvalidArgument { field, .. }) if field == "config.k"
    ));
}

#[tokio::test]
async fn max_pool_bytes_bounds_capacity_times_length_times_action_bytes() {
    // 4 trajectories × 10 actions × 4 bytes = 160 bytes (discrete); × 3 for action_dim 3.
    let r = registry(Limits {
        max_pool_bytes: 160,
        ..Limits::default()
    })
    .await;
    let config = |capacity, len, dim| TaskConfigInput {
        num_actions: if dim == 0 { 2 } else { 0 },
        action_dim: dim,
        pool_capacity: Some(capacity),
        max_trajectory_len: Some(len),
        ..Default::default()
    };
    r.create(DEFAULT_TENANT, "at", &config(4, 10, 0), None)
        .await
        .unwrap();
    r.create(DEFAULT_TENANT, "one-dim", &config(4, 10, 1), None)
        .await
        .unwrap();
    for (id, input) in [
        ("capacity", config(5, 10, 0)),
        ("length", config(4, 11, 0)),
        ("dim", config(4, 10, 3)),
        // The default max_trajectory_len (100000) is counted too.
        ("default-length", discrete(2, 1)),
    ] {
        match r.create(DEFAULT_TENANT, id, &input, None).await {
            Err(Error::ResourceExhausted(m)) => {
                assert!(m.contains("max_pool_bytes = 160"), "{id}: {m}");
                let bytes = TaskConfig::resolve(&input).unwrap().pool_bytes_bound();
                assert!(m.contains(&format!("up to {bytes} bytes")), "{id}: {m}");
            }
            Err(other) => panic!("{id}: {other:?}"),
            Ok(_) => panic!("{id}: created past max_pool_bytes"),
        }
    }
    assert_eq!(r.list(DEFAULT_TENANT).await.unwrap().len(), 2);
}

#[tokio::test]
async fn limits_are_resource_exhausted_and_change_nothing() {
    let r = registry(Limits {
        max_tasks: 1,
        max_pool_capacity: 5,
        ..Limits::default()
    })
    .await;
    assert!(matches!(
        r.create(DEFAULT_TENANT, "big", &discrete(2, 6), None).await,
        Err(Error::ResourceExhausted(m)) if m.contains("max_pool_capacity")
    ));
    r.create(DEFAULT_TENANT, "a", &discrete(2, 5), None)
        .await
        .unwrap();
    assert!(matches!(
        r.create(DEFAULT_TENANT, "b", &discrete(2, 5), None).await,
        Err(Error::ResourceExhausted(m)) if m.contains("max_tasks")
    ));
    assert_eq!(r.list(DEFAULT_TENANT).await.unwrap().len(), 1);
}

#[tokio::test]
async fn offers_resets_and_deletion() {
    let r = registry(Limits::default()).await;
    let t = r
        .create(DEFAULT_TENANT, "t", &discrete(2, 1), None)
        .await
        .unwrap();
    assert_eq!(t.offer(acts(&[0]), 1.0).await.unwrap(), (true, 1));
    assert_eq!(t.offer(acts(&[1]), 1.0).await.unwrap(), (false, 1));
    assert_eq!(t.offer(acts(&[1]), 2.0).await.unwrap(), (true, 2));
    assert_eq!(t.reset_pool().await.unwrap(), 3);
    assert_eq!(t.stats().pool_size, 0);
    r.create(DEFAULT_TENANT, "a", &discrete(2, 1), None)
        .await
        .unwrap();
    let ids: Vec<_> = r
        .list(DEFAULT_TENANT)
        .await
        .unwrap()
        .iter()
        .map(|t| t.id().to_string())
        .collect();
    assert_eq!(ids, ["a", "t"], "listed by id");
    r.delete(DEFAULT_TENANT, "t").await.unwrap();
    assert!(matches!(
        r.get(DEFAULT_TENANT, "t"),
        Err(Error::TaskNotFound { .. })
    ));
    assert!(matches!(
        t.offer(acts(&[0]), 5.0).await,
        Err(Error::TaskNotFound { .. })
    ));
    assert!(matches!(t.pool_snapshot(), Err(Error::TaskNotFound { .. })));
    assert!(matches!(
        r.delete(DEFAULT_TENANT, "t").await,
        Err(Error::TaskNotFound { .. })
    ));
}

#[tokio::test]
async fn a_failed_commit_publishes_nothing() {
    let store = TestStore::new(false);
    let r = Registry::open(store.clone(), Limits::default())
        .await
        .unwrap()
        .0;
    let t = r
        .create(DEFAULT_TENANT, "t", &discrete(2, 2), None)
        .await
        .unwrap();
    t.offer(acts(&[0]), 1.0).await.unwrap();
    store.fail.store(true, Ordering::SeqCst);
    assert!(matches!(
        t.offer(acts(&[1]), 2.0).await,
        Err(Error::Storage(_))
    ));
    assert!(matches!(t.reset_pool().await, Err(Error::Storage(_))));
    let s = t.stats();
    assert_eq!((s.pool_size, s.pool_version), (1, 1));
    store.fail.store(false, Ordering::SeqCst);
    assert_eq!(t.offer(acts(&[1]), 2.0).await.unwrap(), (true, 2));
}

#[tokio::test]
async fn open_streams_are_counted_until_their_guard_drops() {
    let r = registry(Limits::default()).await;
    let t = r
        .create(DEFAULT_TENANT, "t", &discrete(2, 2), None)
        .await
        .unwrap();
    let g1 = t.open_stream().unwrap();
    let g2 = t.open_stream().unwrap();
    assert_eq!(t.stats().open_streams, 2);
    drop(g1);
    assert_eq!(t.stats().open_streams, 1);
    drop(g2);
    assert_eq!(t.stats().open_streams, 0);
}

#[tokio::test]
async fn a_shared_store_change_refreshes_the_snapshot_and_never_goes_back() {
    let store = TestStore::new(true);
    let r = Arc::new(
        Registry::open(store.clone(), Limits::default())
            .await
            .unwrap()
            .0,
    );
    let watcher = r.watch_changes().expect("a shared store is watched");
    let t = r
        .create(DEFAULT_TENANT, "t", &discrete(2, 3), None)
        .await
        .unwrap();
    // "Another server" inserts two trajectories.
    let offer = |a: u32, s: f64| PoolOp::Offer {
        actions: acts(&[a, a]),
        score: s,
        end: None,
    };
    let (remote, _) = apply_ops(&t.snapshot(), vec![offer(0, 1.0), offer(1, 2.0)]);
    store.announce("t", remote.clone());
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    while t.published_version() != 2 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "snapshot not refreshed"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert_eq!(t.snapshot().seqs(), remote.seqs());
    // An older pool never replaces a newer one.
    t.refresh(Pool::new(3));
    assert_eq!(t.published_version(), 2);
    // A store only this server writes is not watched.
    let local = Arc::new(registry(Limits::default()).await);
    assert!(local.watch_changes().is_none());
    watcher.abort();
}

#[tokio::test]
async fn an_unknown_id_suggests_a_close_one() {
    let r = registry(Limits::default()).await;
    r.create(DEFAULT_TENANT, "cartpole", &discrete(2, 2), None)
        .await
        .unwrap();
    r.create(DEFAULT_TENANT, "maze/v1", &discrete(4, 2), None)
        .await
        .unwrap();
    let msg = |id: &str| {
        r.get(DEFAULT_TENANT, id)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default()
    };
    assert_eq!(
        msg("cartpol"),
        "task \"cartpol\" not found (did you mean \"cartpole\"?)"
    );
    assert_eq!(
        msg("maze/v2"),
        "task \"maze/v2\" not found (did you mean \"maze/v1\"?)"
    );
    assert_eq!(msg("mountaincar"), "task \"mountaincar\" not found");
    assert_eq!(edit_distance("kitten", "sitting"), 3);
    assert_eq!(edit_distance("", "ab"), 2);
}

#[tokio::test]
async fn tenants_have_their_own_tasks_and_never_see_the_others() {
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(crate::store::DiskStore::open(dir.path()).unwrap());
    let r = Registry::open(store, Limits::default()).await.unwrap().0;
    let a = r
        .create("team-a", "cartpole", &discrete(2, 2), None)
        .await
        .unwrap();
    // The same id with another config is another task, not ALREADY_EXISTS.
    let b = r
        .create("team-b", "cartpole", &discrete(3, 4), None)
        .await
        .unwrap();
    assert_eq!(
        (a.id(), a.tenant(), a.key()),
        ("cartpole", "team-a", "team-a@cartpole")
    );
    assert_eq!((b.id(), b.tenant()), ("cartpole", "team-b"));
    a.offer(acts(&[1, 0]), 5.0).await.unwrap();
    assert_eq!(b.stats().pool_size, 0, "a's pool change is not b's");
    r.create("team-a", "only-a", &discrete(2, 2), None)
        .await
        .unwrap();
    r.create(DEFAULT_TENANT, "legacy", &discrete(2, 2), None)
        .await
        .unwrap();

    let ids = |t: &str| {
        r.held(t)
            .iter()
            .map(|h| h.id().to_string())
            .collect::<Vec<_>>()
    };
    assert_eq!(ids("team-a"), ["cartpole", "only-a"]);
    assert_eq!(ids("team-b"), ["cartpole"]);
    assert_eq!(ids(DEFAULT_TENANT), ["legacy"]);
    assert_eq!(ids("team-c"), Vec::<String>::new());
    assert_eq!((r.count("team-a"), r.count("team-c")), (2, 0));

    // A miss looks the same whether another tenant has the id or nobody has, and
    // suggests only the caller's own ids.
    let miss = |t: &str, id: &str| r.get(t, id).err().map(|e| e.to_string()).unwrap();
    assert_eq!(miss("team-b", "only-a"), "task \"only-a\" not found");
    assert_eq!(miss("team-b", "only-b"), "task \"only-b\" not found");
    assert_eq!(
        miss("team-a", "only-b"),
        "task \"only-b\" not found (did you mean \"only-a\"?)"
    );
    assert!(matches!(
        r.delete("team-b", "only-a").await,
        Err(Error::TaskNotFound { .. })
    ));
    r.delete("team-b", "cartpole").await.unwrap();
    assert_eq!(r.get("team-a", "cartpole").unwrap().stats().pool_size, 1);

    // Keys survive a restart: the store holds tenant and id in one key.
    drop((a, b, r));
    let store = Arc::new(crate::store::DiskStore::open(dir.path()).unwrap());
    let (again, restored) = Registry::open(store, Limits::default()).await.unwrap();
    assert_eq!(restored.tasks, 3);
    assert_eq!(
        again.get("team-a", "cartpole").unwrap().stats().pool_size,
        1
    );
    assert_eq!(again.list(DEFAULT_TENANT).await.unwrap().len(), 1);
    assert!(again.get("team-b", "cartpole").is_err());
}

#[tokio::test]
async fn a_tenant_task_quota_counts_only_its_own_tasks() {
    let r = registry(Limits::default()).await;
    r.create("other", "x", &discrete(2, 2), None).await.unwrap();
    r.create("q", "a", &discrete(2, 2), Some(2)).await.unwrap();
    r.create("q", "b", &discrete(2, 2), Some(2)).await.unwrap();
    // Creating an existing task again is not a new task.
    r.create("q", "b", &discrete(2, 2), Some(2)).await.unwrap();
    match r.create("q", "c", &discrete(2, 2), Some(2)).await {
        Err(Error::ResourceExhausted(m)) => {
            assert!(m.contains("\"q\"") && m.contains("max_tasks = 2"), "{m}")
        }
        other => panic!(
            "expected the quota, got {:?}",
            other.map(|t| t.key().to_string())
        ),
    }
    r.delete("q", "a").await.unwrap();
    r.create("q", "c", &discrete(2, 2), Some(2)).await.unwrap();
}

mod group_commit;
