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
        id,
        &TaskConfigInput {
            num_actions: 2,
            pool_capacity: Some(capacity),
            min_pool_size: Some(1),
            start_step: Some(0),
            ..Default::default()
        },
    )
    .await
    .unwrap()
}

fn open(r: &Registry, id: &str, num_envs: u32) -> Result<StreamSession, Error> {
    StreamSession::open(
        r,
        &OpenRequest {
            task_id: id,
            num_envs,
            ..Default::default()
        },
    )
}

/// A memory-backed registry with task "t" (capacity `capacity`) and a session of
/// `num_envs` environments on it.
async fn setup(capacity: u32, num_envs: u32) -> (Registry, Arc<TaskHandle>, StreamSession) {
    let r = registry_with(Arc::new(MemoryStore::new()), Limits::default()).await;
    let t = task(&r, "t", capacity).await;
    let s = open(&r, "t", num_envs).unwrap();
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
    assert_eq!(field(open(&r, "t", 0).err().unwrap()), "open.num_envs");
    assert_eq!(field(open(&r, "a b", 1).err().unwrap()), "open.task_id");
    assert_eq!(field(open(&r, "", 1).err().unwrap()), "open.task_id");
    assert!(
        matches!(open(&r, "t", 5), Err(Error::ResourceExhausted(m)) if m.contains("max_envs_per_stream"))
    );
    assert!(matches!(
        open(&r, "nope", 1),
        Err(Error::TaskNotFound { .. })
    ));
    let s = open(&r, "t", 4).unwrap();
    assert_eq!(s.num_envs(), 4);
    assert_eq!(s.task().stats().open_streams, 1);
    drop(s);
    assert_eq!(r.get("t").unwrap().stats().open_streams, 0);
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
    let mut a = open(&r, "t", 1).unwrap();
    let mut b = open(&r, "t", 1).unwrap();
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
    let mut s = open(&r, "t", 1).unwrap();
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
    let mut s = open(&r, "t", 1).unwrap();
    r.delete("t").await.unwrap();
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
        "g",
        &TaskConfigInput {
            num_actions: 2,
            pool_capacity: Some(1),
            start_step: Some(1),
            gate_potential: Some(true),
            beta: Some(1.0),
            ..Default::default()
        },
    )
    .await
    .unwrap();
    let mut s = open(&r, "g", 1).unwrap();
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

/// A one-entry batch for env 0.
fn one(action: &'static [u32], reward: &'static [f64], done: bool) -> Batch<'static> {
    Batch {
        actions: action,
        rewards: reward,
        terminated: if done { &[true] } else { &[] },
        ..Default::default()
    }
}

#[tokio::test]
async fn a_resumed_episode_continues_exactly_as_an_uninterrupted_one() {
    let (r, t, mut whole) = setup(3, 1).await;
    for (acts, score) in [
        (&[0u32, 1, 1, 0, 1][..], 1.0),
        (&[1, 1, 0, 0][..], 2.0),
        (&[0, 0, 0, 1, 1, 1][..], 0.5),
    ] {
        t.offer(ActionSeq::Discrete(acts.to_vec()), score)
            .await
            .unwrap();
    }
    let actions: [&'static [u32]; 6] = [&[1], &[1], &[0], &[0], &[1], &[0]];
    let mut want = Vec::new();
    for a in actions {
        want.push(whole.step(&one(a, &[0.5], false)).await.unwrap().outputs[0]);
    }
    // The same episode, broken after 3 steps and resumed on a new stream.
    let mut first = open(&r, "t", 1).unwrap();
    for a in &actions[..3] {
        first.step(&one(a, &[0.5], false)).await.unwrap();
    }
    drop(first);
    let resume = [Resume {
        env_id: 0,
        actions: &[1, 1, 0],
        reward_sum: 1.5,
        ..Default::default()
    }];
    let req = OpenRequest {
        task_id: "t",
        num_envs: 1,
        resume: &resume,
        ..Default::default()
    };
    let mut resumed = StreamSession::open(&r, &req).unwrap();
    for (j, a) in actions[3..].iter().enumerate() {
        let got = resumed.step(&one(a, &[0.5], false)).await.unwrap().outputs[0];
        assert_eq!(got, want[3 + j], "step {}", 3 + j);
    }
    // Its end stores the whole episode with the carried reward sum as its score.
    resumed.step(&one(&[1], &[0.5], true)).await.unwrap();
    let pool = t.snapshot();
    let stored = pool
        .trajectories()
        .iter()
        .find(|t| t.score == 3.5)
        .expect("stored");
    assert_eq!(
        stored.actions,
        ActionSeq::Discrete(vec![1, 1, 0, 0, 1, 0, 1])
    );
}

#[tokio::test]
async fn a_re_sent_episode_end_is_committed_once_per_client() {
    let (r, t, _) = setup(4, 1).await;
    let with_client = |resume: &'static [Resume<'static>]| OpenRequest {
        task_id: "t",
        num_envs: 1,
        resume,
        client_id: "client-1",
    };
    let mut s = StreamSession::open(&r, &with_client(&[])).unwrap();
    s.step(&one(&[1], &[1.0], false)).await.unwrap();
    s.step(&one(&[0], &[1.0], true)).await.unwrap();
    assert_eq!(t.stats().pool_version, 1);
    // The answer was "lost": the client resumes the episode as it was before the batch
    // and re-sends it.
    drop(s);
    const BEFORE: [Resume<'static>; 1] = [Resume {
        env_id: 0,
        actions: &[1],
        action_vectors: &[],
        reward_sum: 1.0,
        episode: 0,
    }];
    let mut s = StreamSession::open(&r, &with_client(&BEFORE)).unwrap();
    let again = s.step(&one(&[0], &[1.0], true)).await.unwrap();
    assert_eq!(again.outputs[0].step, 1, "shaped as the same step");
    assert_eq!(again.pool_version, 1, "not committed twice");
    assert_eq!(t.stats().episodes_completed, 1);
    // The next episode (number 1) is committed as usual.
    s.step(&one(&[1], &[5.0], true)).await.unwrap();
    assert_eq!(t.stats().pool_version, 2);
    // Another client, or none, is not affected by client-1's record.
    let mut other = StreamSession::open(
        &r,
        &OpenRequest {
            client_id: "client-2",
            ..with_client(&BEFORE)
        },
    )
    .unwrap();
    other.step(&one(&[0], &[1.0], true)).await.unwrap();
    assert_eq!(t.stats().pool_version, 3);
}

#[tokio::test]
async fn an_invalid_resume_opens_nothing_and_names_the_field() {
    let (r, t, s) = setup(4, 1).await;
    drop(s);
    let cases: [(Resume<'static>, &str); 5] = [
        (
            Resume {
                env_id: 2,
                ..Default::default()
            },
            "open.resume[0].env_id",
        ),
        (
            Resume {
                actions: &[0, 2],
                ..Default::default()
            },
            "open.resume[0].actions[1]",
        ),
        (
            Resume {
                action_vectors: &[0.5],
                ..Default::default()
            },
            "open.resume[0].action_vectors",
        ),
        (
            Resume {
                reward_sum: f64::NAN,
                ..Default::default()
            },
            "open.resume[0].reward_sum",
        ),
        (
            Resume {
                env_id: 1,
                actions: &[0],
                ..Default::default()
            },
            "open.resume[1].env_id",
        ),
    ];
    for (i, (bad, want)) in cases.into_iter().enumerate() {
        let list = [
            Resume {
                env_id: 1,
                ..Default::default()
            },
            bad,
        ];
        let list = if i == 4 { &list[..] } else { &list[1..] };
        let req = OpenRequest {
            task_id: "t",
            num_envs: 2,
            resume: list,
            ..Default::default()
        };
        assert_eq!(
            field(StreamSession::open(&r, &req).err().unwrap()),
            want,
            "case {i}"
        );
    }
    assert_eq!(t.stats().open_streams, 0);
}
