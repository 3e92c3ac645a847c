use std::sync::atomic::Ordering;

use super::*;
use crate::core::{ActionSeq, TaskConfigInput};
use crate::store::testing::TestStore;
use crate::store::MemoryStore;

async fn registry_with(store: Arc<dyn crate::store::Store>, limits: Limits) -> Registry {
    Registry::open(store, limits).await.unwrap().0
}

async fn task(r: &Registry, id: &str, capacity: u32) -> Arc<TaskHandle> {
    r.create(
        DEFAULT_TENANT,
        id,
        &TaskConfigInput {
            num_actions: 2,
            pool_capacity: Some(capacity),
            min_pool_size: Some(1),
            start_step: Some(0),
            ..Default::default()
        },
        None,
    )
    .await
    .unwrap()
}

async fn open(r: &Registry, id: &str, num_envs: u32) -> Result<StreamSession, Error> {
    StreamSession::open(
        r,
        &OpenRequest {
            tenant: DEFAULT_TENANT,
            task_id: id,
            num_envs,
            ..Default::default()
        },
    )
    .await
}

/// A memory-backed registry with task "t" (capacity `capacity`) and a session of
/// `num_envs` environments on it.
async fn setup(capacity: u32, num_envs: u32) -> (Registry, Arc<TaskHandle>, StreamSession) {
    let r = registry_with(Arc::new(MemoryStore::new()), Limits::default()).await;
    let t = task(&r, "t", capacity).await;
    let s = open(&r, "t", num_envs).await.unwrap();
    (r, t, s)
}

/// The step index t of each entry of a batch's answer.
async fn steps_of(s: &mut StreamSession, b: &Batch<'_>) -> Vec<u64> {
    s.step(b)
        .await
        .unwrap()
        .outputs
        .iter()
        .map(|o| o.step)
        .collect()
}

fn field(e: Error) -> String {
    match e {
        Error::InvalidArgument { field, .. } => field,
        other => format!("{other:?}"),
    }
}

#[tokio::test]
async fn open_checks_its_request() {
    let r = registry_with(
        Arc::new(MemoryStore::new()),
        Limits {
            max_envs_per_stream: 4,
            ..Limits::default()
        },
    )
    .await;
    task(&r, "t", 2).await;
    assert_eq!(
        field(open(&r, "t", 0).await.err().unwrap()),
        "open.num_envs"
    );
    assert_eq!(
        field(open(&r, "a b", 1).await.err().unwrap()),
        "open.task_id"
    );
    assert_eq!(field(open(&r, "", 1).await.err().unwrap()), "open.task_id");
    assert!(
        matches!(open(&r, "t", 5).await, Err(Error::ResourceExhausted(m)) if m.contains("max_envs_per_stream"))
    );
    assert!(matches!(
        open(&r, "nope", 1).await,
        Err(Error::TaskNotFound { .. })
    ));
    let s = open(&r, "t", 4).await.unwrap();
    assert_eq!(s.num_envs(), 4);
    assert_eq!(s.task().stats().open_streams, 1);
    drop(s);
    assert_eq!(r.get(DEFAULT_TENANT, "t").unwrap().stats().open_streams, 0);
}

#[tokio::test]
async fn later_entries_of_a_batch_see_its_episode_ends_and_the_batch_commits_once() {
    let (_r, t, mut s) = setup(4, 2).await;
    // env 0 ends an episode of one step; env 1 then steps with the pool holding it.
    let b = Batch {
        env_ids: &[0, 1, 0],
        actions: &[1, 1, 0],
        rewards: &[3.0, 0.0, 0.0],
        terminated: &[true, false, true],
        ..Default::default()
    };
    let shaped = s.step(&b).await.unwrap();
    let o = shaped.outputs;
    assert_eq!(o.len(), 3);
    assert!(!o[0].knn_active, "the pool was empty for the first entry");
    assert!(
        o[1].knn_active,
        "the second entry sees the first one's episode"
    );
    // An exact match with the only (best) trajectory: r = e - sqrt(e).
    assert_eq!(o[1].knn_reward, 1f64.exp() - 0.5f64.exp());
    assert_eq!(shaped.pool_version, 2);
    assert_eq!(t.stats().episodes_completed, 2);
    assert_eq!(t.stats().steps_shaped, 3);
    // Env 1 is at t = 1, env 0 starts again at t = 0.
    let b = Batch {
        actions: &[0, 0],
        rewards: &[0.0, 0.0],
        ..Default::default()
    };
    let steps = steps_of(&mut s, &b).await;
    assert_eq!(steps, [0, 1]);
}

#[tokio::test]
async fn a_rejected_batch_changes_no_episode_and_no_pool() {
    let (_r, t, mut s) = setup(4, 2).await;
    let ok = Batch {
        actions: &[0, 1],
        rewards: &[1.0, 1.0],
        ..Default::default()
    };
    s.step(&ok).await.unwrap();
    // Entry 0 would end an episode, entry 1 is out of range: nothing is applied.
    let bad = Batch {
        actions: &[0, 7],
        rewards: &[1.0, 1.0],
        terminated: &[true, false],
        abandon: &[1],
        ..Default::default()
    };
    assert_eq!(field(s.step(&bad).await.err().unwrap()), "steps.actions[1]");
    let stats = t.stats();
    assert_eq!(
        (
            stats.pool_version,
            stats.episodes_completed,
            stats.steps_shaped
        ),
        (0, 0, 2)
    );
    let steps = steps_of(&mut s, &ok).await;
    assert_eq!(
        steps,
        [1, 1],
        "the rejected batch took no step and abandoned nothing"
    );
}

#[tokio::test]
async fn abandoned_episodes_restart_without_touching_the_pool() {
    let (_r, t, mut s) = setup(4, 3).await;
    let b = Batch {
        actions: &[0, 0, 0],
        rewards: &[1.0, 1.0, 1.0],
        ..Default::default()
    };
    s.step(&b).await.unwrap();
    s.step(&b).await.unwrap();
    // In the batch: env 2 is dropped before its entry, which is then t = 0.
    let with_abandon = Batch { abandon: &[2], ..b };
    let steps = steps_of(&mut s, &with_abandon).await;
    assert_eq!(steps, [2, 2, 0]);
    // On its own, between batches.
    s.abandon(&[0]).unwrap();
    assert_eq!(field(s.abandon(&[3]).err().unwrap()), "abandon[0]");
    assert_eq!(field(s.abandon(&[1, 1]).err().unwrap()), "abandon[1]");
    let steps = steps_of(&mut s, &b).await;
    assert_eq!(steps, [0, 3, 1]);
    let stats = t.stats();
    assert_eq!((stats.pool_version, stats.episodes_completed), (0, 0));
    // An abandon-only batch (no entries) is valid.
    let only = Batch {
        abandon: &[1],
        ..Default::default()
    };
    assert!(s.step(&only).await.unwrap().outputs.is_empty());
}

#[tokio::test]
async fn another_sessions_commit_is_seen_from_the_next_entry() {
    let r = registry_with(Arc::new(MemoryStore::new()), Limits::default()).await;
    task(&r, "t", 4).await;
    let mut a = open(&r, "t", 1).await.unwrap();
    let mut b = open(&r, "t", 1).await.unwrap();
    let step = Batch {
        actions: &[1],
        rewards: &[0.0],
        ..Default::default()
    };
    assert!(!b.step(&step).await.unwrap().outputs[0].knn_active);
    let end = Batch {
        terminated: &[true],
        ..step
    };
    // a's episode has 3 actions, so b's step t = 1 is inside L_min.
    a.step(&step).await.unwrap();
    a.step(&step).await.unwrap();
    a.step(&end).await.unwrap();
    let shaped = b.step(&step).await.unwrap();
    assert!(shaped.outputs[0].knn_active);
    assert_eq!(shaped.pool_version, 1);
}

#[tokio::test]
async fn a_store_failure_fails_the_batch_and_publishes_nothing() {
    let store = TestStore::new(false);
    let r = registry_with(store.clone(), Limits::default()).await;
    let t = task(&r, "t", 4).await;
    let mut s = open(&r, "t", 1).await.unwrap();
    store.fail.store(true, Ordering::SeqCst);
    let end = Batch {
        actions: &[1],
        rewards: &[0.0],
        terminated: &[true],
        ..Default::default()
    };
    assert!(matches!(s.step(&end).await, Err(Error::Storage(_))));
    assert_eq!(t.stats().pool_version, 0);
    assert_eq!(t.snapshot().len(), 0);
}

#[tokio::test]
async fn a_deleted_task_ends_its_sessions_with_not_found() {
    let r = registry_with(Arc::new(MemoryStore::new()), Limits::default()).await;
    task(&r, "t", 4).await;
    let mut s = open(&r, "t", 1).await.unwrap();
    r.delete(DEFAULT_TENANT, "t").await.unwrap();
    let b = Batch {
        actions: &[0],
        rewards: &[0.0],
        ..Default::default()
    };
    assert!(matches!(s.step(&b).await, Err(Error::TaskNotFound { .. })));
}

#[tokio::test]
async fn gated_potential_counts_only_where_knn_is_active() {
    let r = registry_with(Arc::new(MemoryStore::new()), Limits::default()).await;
    r.create(
        DEFAULT_TENANT,
        "g",
        &TaskConfigInput {
            num_actions: 2,
            pool_capacity: Some(1),
            start_step: Some(1),
            gate_potential: Some(true),
            beta: Some(1.0),
            ..Default::default()
        },
        None,
    )
    .await
    .unwrap();
    let mut s = open(&r, "g", 1).await.unwrap();
    let b = |done: bool| Batch {
        actions: &[0],
        rewards: &[0.0],
        terminated: if done { &[true] } else { &[] },
        values: &[1.0],
        next_values: &[2.0],
        ..Default::default()
    };
    // Empty pool: the kNN term is off, so F is gated to 0.
    let o = s.step(&b(false)).await.unwrap().outputs[0];
    assert_eq!((o.knn_active, o.potential, o.reward), (false, 0.0, 0.0));
    s.step(&b(false)).await.unwrap();
    s.step(&b(true)).await.unwrap();
    // Pool full (1 of 1); t = 0 < start_step: still gated.
    assert_eq!(s.step(&b(false)).await.unwrap().outputs[0].potential, 0.0);
    // t = 1: active, F = γ·2 − 1.
    let o = s.step(&b(false)).await.unwrap().outputs[0];
    assert!(o.knn_active);
    assert_eq!(o.potential, 0.99 * f64::from(2.0f32) - 1.0);
}

/// Resume (SPEC §9) and the no-double-commit rule.
mod resume;

/// Arbitrary, mostly invalid batches.
mod props;

#[tokio::test]
async fn stream_memory_is_bounded_per_stream_and_server_wide_and_released_on_drop() {
    // One env of a task with max_trajectory_len 10 and pool_capacity 2 reckons
    // 10 × 4 + 2 × 24 = 88 bytes.
    let r = registry_with(
        Arc::new(MemoryStore::new()),
        Limits {
            max_stream_bytes: 3 * 88,
            max_total_stream_bytes: 5 * 88,
            ..Limits::default()
        },
    )
    .await;
    let t = r
        .create(
            DEFAULT_TENANT,
            "t",
            &TaskConfigInput {
                num_actions: 2,
                pool_capacity: Some(2),
                max_trajectory_len: Some(10),
                ..Default::default()
            },
            None,
        )
        .await
        .unwrap();
    assert_eq!(t.config().env_bytes_bound(), 88);
    let exhausted = |res: Result<StreamSession, Error>, limit: &str| match res {
        Err(Error::ResourceExhausted(m)) => assert!(m.contains(limit), "{m}"),
        Err(other) => panic!("{other:?}"),
        Ok(_) => panic!("opened past {limit}"),
    };
    exhausted(open(&r, "t", 4).await, "max_stream_bytes = 264");
    assert_eq!(r.reserved_stream_bytes(), 0);
    let three = open(&r, "t", 3).await.unwrap();
    let two = open(&r, "t", 2).await.unwrap();
    assert_eq!(r.reserved_stream_bytes(), 5 * 88);
    exhausted(open(&r, "t", 1).await, "max_total_stream_bytes = 440");
    // A refused open holds nothing.
    assert_eq!(t.stats().open_streams, 2);
    assert_eq!(r.reserved_stream_bytes(), 5 * 88);
    drop(three);
    assert_eq!(r.reserved_stream_bytes(), 2 * 88);
    let again = open(&r, "t", 3).await.unwrap();
    drop((two, again));
    assert_eq!(r.reserved_stream_bytes(), 0);
}
