use super::*;

#[tokio::test]
async fn shutdown_writes_only_the_tasks_that_changed_since_their_snapshot() {
    let dir = tempfile::tempdir().unwrap();
    let store = DiskStore::open(dir.path()).unwrap();
    store.load().await.unwrap();
    let config = TaskConfig::resolve(&crate::core::TaskConfigInput {
        num_actions: 2,
        ..Default::default()
    })
    .unwrap();
    for id in ["a", "b", "c"] {
        store.create_task(id, &config).await.unwrap();
    }
    let pool = Arc::new(Pool::new(config.pool_capacity as usize));
    let syncs = || store.commit_stats().syncs;
    let before = syncs();
    for id in ["a", "b", "c"] {
        store
            .save_counters(id, pool.clone(), Counters::default())
            .await
            .unwrap();
    }
    assert_eq!(syncs(), before, "idle tasks cost no sync at shutdown");
    let counted = Counters {
        episodes_completed: 0,
        steps_shaped: 5,
    };
    store
        .save_counters("b", pool.clone(), counted)
        .await
        .unwrap();
    assert!(syncs() > before, "new counters are written");
    let after = syncs();
    store.save_counters("b", pool, counted).await.unwrap();
    assert_eq!(syncs(), after, "and only once");
    drop(store);
    let store = DiskStore::open(dir.path()).unwrap();
    let b = store.load().await.unwrap();
    let b = b.iter().find(|t| t.id == "b").unwrap();
    assert_eq!(b.counters, counted);
}

#[test]
fn a_data_dir_opens_once_at_a_time() {
    let dir = tempfile::tempdir().unwrap();
    let first = DiskStore::open(dir.path()).unwrap();
    let e = DiskStore::open(dir.path()).unwrap_err().to_string();
    assert!(e.contains("in use by another tamrm process"), "{e}");
    drop(first);
    DiskStore::open(dir.path()).expect("the lock is released with the store");
}
