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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stop_logs_counters_in_one_group_and_writes_no_snapshot() {
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
    let counted = |n: u64| Counters {
        episodes_completed: n,
        steps_shaped: 10 * n,
    };
    let before = store.commit_stats();
    store.stopping();
    let saves = ids
        .iter()
        .zip(&pools)
        .enumerate()
        .map(|(i, (id, pool))| store.save_counters(id, pool.clone(), counted(i as u64 + 1)));
    for r in futures::future::join_all(saves).await {
        r.unwrap();
    }
    let after = store.commit_stats();
    // One sync per group: all three when they queue together, never more than one each.
    assert!(after.syncs - before.syncs <= 3, "{before:?} {after:?}");
    assert_eq!(after.changes, before.changes, "counters change no pool");
    for id in ids {
        let traj = dir.path().join("tasks").join(dir_name(id)).join("traj");
        assert_eq!(
            fs::read_dir(traj).unwrap().count(),
            0,
            "no snapshot of {id}"
        );
    }
    drop(store);
    let store = DiskStore::open(dir.path()).unwrap();
    let mut tasks = store.load().await.unwrap();
    tasks.sort_by(|x, y| x.id.cmp(&y.id));
    for (i, (t, pool)) in tasks.iter().zip(&pools).enumerate() {
        assert_eq!(t.pool.seqs(), pool.seqs(), "task {}", t.id);
        assert_eq!(t.pool.version(), pool.version());
        assert_eq!(t.counters, counted(i as u64 + 1));
    }
    // A start writes no snapshot either, and the counters are durable: saving them
    // again costs nothing.
    let syncs = store.commit_stats().syncs;
    for (i, (t, pool)) in tasks.iter().zip(&pools).enumerate() {
        store
            .save_counters(&t.id, pool.clone(), counted(i as u64 + 1))
            .await
            .unwrap();
    }
    assert_eq!(store.commit_stats().syncs, syncs);
    for id in ids {
        let traj = dir.path().join("tasks").join(dir_name(id)).join("traj");
        assert_eq!(
            fs::read_dir(traj).unwrap().count(),
            0,
            "no snapshot of {id}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stop_cuts_a_compaction_short_and_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let store = DiskStore::open(dir.path()).unwrap();
    store.load().await.unwrap();
    let config = TaskConfig::resolve(&crate::core::TaskConfigInput {
        num_actions: 3,
        pool_capacity: Some(50),
        ..Default::default()
    })
    .unwrap();
    store.create_task("t", &config).await.unwrap();
    let mut pool = Arc::new(Pool::new(50));
    for i in 0..20u32 {
        let ops = vec![PoolOp::Offer {
            actions: crate::core::ActionSeq::Discrete(vec![i % 3; 4]),
            score: f64::from(i),
            end: None,
        }];
        pool = store
            .commit("t", pool, ops, Counters::default())
            .await
            .unwrap()
            .pool;
    }
    let log = dir.path().join(LOG_FILE);
    let logged = fs::read(&log).unwrap();
    store.stopping();
    let e = store.compact().await.unwrap_err().to_string();
    assert!(e.contains("the server is stopping"), "{e}");
    assert_eq!(fs::read(&log).unwrap(), logged, "the log is kept whole");
    let traj = dir.path().join("tasks").join(dir_name("t")).join("traj");
    assert_eq!(fs::read_dir(&traj).unwrap().count(), 0, "no file written");
    drop(store);
    let store = DiskStore::open(dir.path()).unwrap();
    let tasks = store.load().await.unwrap();
    assert_eq!(tasks[0].pool.seqs(), pool.seqs());
    assert_eq!(tasks[0].pool.version(), 20);
}
