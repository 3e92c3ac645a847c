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

#[tokio::test]
async fn one_save_writes_every_lagging_snapshot_in_one_batch() {
    let dir = tempfile::tempdir().unwrap();
    let store = DiskStore::open(dir.path()).unwrap();
    store.load().await.unwrap();
    let config = TaskConfig::resolve(&crate::core::TaskConfigInput {
        num_actions: 2,
        pool_capacity: Some(8),
        ..Default::default()
    })
    .unwrap();
    let ids = ["a", "b", "c"];
    let mut pools = Vec::new();
    for id in ids {
        store.create_task(id, &config).await.unwrap();
        let mut pool = Arc::new(Pool::new(8));
        for i in 0..4u32 {
            let ops = vec![PoolOp::Offer {
                actions: crate::core::ActionSeq::Discrete(vec![i % 2; 3]),
                score: f64::from(i),
                end: None,
            }];
            pool = store
                .commit(id, pool, ops, Counters::default())
                .await
                .unwrap()
                .pool;
        }
        pools.push(pool);
    }
    let before = store.commit_stats().syncs;
    let counted = Counters {
        episodes_completed: 4,
        steps_shaped: 12,
    };
    store
        .save_counters("a", pools[0].clone(), counted)
        .await
        .unwrap();
    // 12 trajectory files, 3 traj/ dirs, 3 pool.json, 3 task dirs, the log: one batch
    // each, not one task after another; and nothing left for the other tasks.
    assert_eq!(store.commit_stats().syncs - before, 12 + 3 + 3 + 3 + 1);
    let after = store.commit_stats().syncs;
    for (id, pool) in ids.iter().zip(&pools).skip(1) {
        store
            .save_counters(id, pool.clone(), Counters::default())
            .await
            .unwrap();
    }
    assert_eq!(store.commit_stats().syncs, after, "already written");
    for id in ids {
        let traj = dir.path().join("tasks").join(dir_name(id)).join("traj");
        assert_eq!(fs::read_dir(traj).unwrap().count(), 4, "task {id}");
    }
    drop(store);
    let store = DiskStore::open(dir.path()).unwrap();
    let mut tasks = store.load().await.unwrap();
    tasks.sort_by(|x, y| x.id.cmp(&y.id));
    for (t, pool) in tasks.iter().zip(&pools) {
        assert_eq!(t.pool.seqs(), pool.seqs(), "task {}", t.id);
        assert_eq!(t.pool.version(), pool.version());
    }
    assert_eq!(tasks[0].counters, counted);
}
