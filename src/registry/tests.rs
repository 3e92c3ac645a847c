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
    let a = r.create("t", &discrete(2, 3)).await.unwrap();
    let b = r.create("t", &discrete(2, 3)).await.unwrap();
    assert!(Arc::ptr_eq(&a, &b));
    let mut other = discrete(2, 3);
    other.alpha = Some(0.5);
    other.gate_potential = Some(true);
    match r.create("t", &other).await {
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
        r.create("t", &bad).await,
        Err(Error::InvalidArgument { field, .. }) if field == "config.k"
    ));
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
        r.create("big", &discrete(2, 6)).await,
        Err(Error::ResourceExhausted(m)) if m.contains("max_pool_capacity")
    ));
    r.create("a", &discrete(2, 5)).await.unwrap();
    assert!(matches!(
        r.create("b", &discrete(2, 5)).await,
        Err(Error::ResourceExhausted(m)) if m.contains("max_tasks")
    ));
    assert_eq!(r.list().len(), 1);
}

#[tokio::test]
async fn offers_resets_and_deletion() {
    let r = registry(Limits::default()).await;
    let t = r.create("t", &discrete(2, 1)).await.unwrap();
    assert_eq!(t.offer(acts(&[0]), 1.0).await.unwrap(), (true, 1));
    assert_eq!(t.offer(acts(&[1]), 1.0).await.unwrap(), (false, 1));
    assert_eq!(t.offer(acts(&[1]), 2.0).await.unwrap(), (true, 2));
    assert_eq!(t.reset_pool().await.unwrap(), 3);
    assert_eq!(t.stats().pool_size, 0);
    r.create("a", &discrete(2, 1)).await.unwrap();
    let ids: Vec<_> = r.list().iter().map(|t| t.id().to_string()).collect();
    assert_eq!(ids, ["a", "t"], "listed by id");
    r.delete("t").await.unwrap();
    assert!(matches!(r.get("t"), Err(Error::TaskNotFound { .. })));
    assert!(matches!(
        t.offer(acts(&[0]), 5.0).await,
        Err(Error::TaskNotFound { .. })
    ));
    assert!(matches!(t.pool_snapshot(), Err(Error::TaskNotFound { .. })));
    assert!(matches!(
        r.delete("t").await,
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
    let t = r.create("t", &discrete(2, 2)).await.unwrap();
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
    let t = r.create("t", &discrete(2, 2)).await.unwrap();
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
    let t = r.create("t", &discrete(2, 3)).await.unwrap();
    // "Another server" inserts two trajectories.
    let offer = |a: u32, s: f64| PoolOp::Offer {
        actions: acts(&[a, a]),
        score: s,
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
    r.create("cartpole", &discrete(2, 2)).await.unwrap();
    r.create("maze/v1", &discrete(4, 2)).await.unwrap();
    let msg = |id: &str| r.get(id).err().map(|e| e.to_string()).unwrap_or_default();
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
