use super::*;

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
    let mut first = open(&r, "t", 1).await.unwrap();
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
        tenant: DEFAULT_TENANT,
        task_id: "t",
        num_envs: 1,
        resume: &resume,
        ..Default::default()
    };
    let mut resumed = StreamSession::open(&r, &req).await.unwrap();
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
        tenant: DEFAULT_TENANT,
        task_id: "t",
        num_envs: 1,
        resume,
        client_id: "client-1",
        ..Default::default()
    };
    let mut s = StreamSession::open(&r, &with_client(&[])).await.unwrap();
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
    let mut s = StreamSession::open(&r, &with_client(&BEFORE))
        .await
        .unwrap();
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
            tenant: DEFAULT_TENANT,
            client_id: "client-2",
            ..with_client(&BEFORE)
        },
    )
    .await
    .unwrap();
    other.step(&one(&[0], &[1.0], true)).await.unwrap();
    assert_eq!(t.stats().pool_version, 3);
}

/// A registry on the data dir `dir` (the store is closed when the registry goes, without
/// a snapshot: as after kill -9).
async fn on_disk(dir: &std::path::Path) -> (Registry, crate::store::DiskStore) {
    let store = crate::store::DiskStore::open(dir).unwrap();
    (
        registry_with(Arc::new(store.clone()), Limits::default()).await,
        store,
    )
}

/// `client-1`'s session on task "t" of `r`: a first open (`None`), or one resuming env 0
/// at episode `number` with `actions` so far (none: at its step 0).
async fn client_1(r: &Registry, resume: Option<(&'static [u32], u64)>) -> StreamSession {
    let (actions, episode) = resume.unwrap_or_default();
    let listed = [Resume {
        env_id: 0,
        actions,
        action_vectors: &[],
        reward_sum: actions.len() as f64,
        episode,
    }];
    let req = OpenRequest {
        tenant: DEFAULT_TENANT,
        task_id: "t",
        num_envs: 1,
        resume: if resume.is_some() { &listed } else { &[] },
        client_id: "client-1",
        ..Default::default()
    };
    StreamSession::open(r, &req).await.unwrap()
}

#[tokio::test]
async fn a_data_dir_server_restarted_does_not_commit_a_re_sent_end_again() {
    let dir = tempfile::tempdir().unwrap();
    {
        let (r, _store) = on_disk(dir.path()).await;
        let t = task(&r, "t", 3).await;
        let mut s = client_1(&r, None).await;
        s.step(&one(&[1], &[1.0], false)).await.unwrap();
        s.step(&one(&[0], &[1.0], true)).await.unwrap();
        assert_eq!(t.stats().pool_version, 1);
    } // "crash": no graceful shutdown, the answer was lost
    let (r, store) = on_disk(dir.path()).await;
    let t = r.get(DEFAULT_TENANT, "t").unwrap();
    assert_eq!(t.stats().pool_version, 1, "the commit survived");
    let mut s = client_1(&r, Some((&[1], 0))).await;
    let again = s.step(&one(&[0], &[1.0], true)).await.unwrap();
    assert_eq!(again.outputs[0].step, 1, "shaped as the same step");
    assert_eq!(
        again.pool_version, 1,
        "not committed twice after the restart"
    );
    assert_eq!(t.snapshot().len(), 1);
    // The next episode (number 1) is committed as usual, and so is another client's.
    s.step(&one(&[1], &[5.0], true)).await.unwrap();
    assert_eq!(t.stats().pool_version, 2);
    // The record survives a compaction too (folded into ends.json, the log emptied).
    r.flush_counters().await;
    drop((s, t, r, store));
    let (r, _store) = on_disk(dir.path()).await;
    let t = r.get(DEFAULT_TENANT, "t").unwrap();
    let mut s = client_1(&r, Some((&[1], 1))).await;
    s.step(&one(&[0], &[5.0], true)).await.unwrap();
    assert_eq!(
        t.stats().pool_version,
        2,
        "episode 1's end is not committed again"
    );
}

#[tokio::test]
async fn a_discarded_end_is_remembered_across_a_restart() {
    for graceful in [true, false] {
        let dir = tempfile::tempdir().unwrap();
        {
            let (r, store) = on_disk(dir.path()).await;
            let t = task(&r, "t", 1).await;
            t.offer(ActionSeq::Discrete(vec![1, 1]), 100.0)
                .await
                .unwrap();
            let groups = store.commit_stats().groups;
            let mut s = client_1(&r, None).await;
            let out = s.step(&one(&[0], &[1.0], true)).await.unwrap();
            assert_eq!(out.pool_version, 1, "discarded: the pool is full of better");
            if graceful {
                r.flush_counters().await;
            } else {
                // Logged in the background: wait for its group (no answer waits for it).
                let start = std::time::Instant::now();
                while store.commit_stats().groups == groups {
                    assert!(start.elapsed().as_secs() < 10, "the end was never logged");
                    tokio::time::sleep(std::time::Duration::from_millis(1)).await;
                }
            }
        }
        let (r, _store) = on_disk(dir.path()).await;
        let t = r.get(DEFAULT_TENANT, "t").unwrap();
        t.reset_pool().await.unwrap();
        let version = t.stats().pool_version;
        // Re-sent after the restart, into an empty pool that would take it.
        let mut s = client_1(&r, Some((&[], 0))).await;
        s.step(&one(&[0], &[1.0], true)).await.unwrap();
        assert_eq!(
            (t.stats().pool_version, t.snapshot().len()),
            (version, 0),
            "graceful {graceful}: a discarded end is not offered again"
        );
    }
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
            tenant: DEFAULT_TENANT,
            task_id: "t",
            num_envs: 2,
            resume: list,
            ..Default::default()
        };
        assert_eq!(
            field(StreamSession::open(&r, &req).await.err().unwrap()),
            want,
            "case {i}"
        );
    }
    assert_eq!(t.stats().open_streams, 0);
}

/// `client-1`'s session on task "t" of `r` with `num_envs` envs, listing `resume`.
async fn client_1_listing(r: &Registry, num_envs: u32, resume: &[Resume<'_>]) -> StreamSession {
    let req = OpenRequest {
        tenant: DEFAULT_TENANT,
        task_id: "t",
        num_envs,
        resume,
        client_id: "client-1",
        ..Default::default()
    };
    StreamSession::open(r, &req).await.unwrap()
}

/// An end of env `env` (of 2): its only entry in the batch.
fn end_of<'a>(env: u32, action: &'static [u32], reward: &'a [f64]) -> Batch<'a> {
    Batch {
        env_ids: if env == 0 { &[0] } else { &[1] },
        actions: action,
        rewards: reward,
        terminated: &[true],
        ..Default::default()
    }
}

#[tokio::test]
async fn an_env_not_listed_starts_the_episode_after_its_last_committed_end() {
    // SPEC §9: "Environments not listed start new episodes." Numbered from 0 again, a new
    // episode of an env that already ended some under this client id would be taken for
    // a re-send of an old one and dropped.
    let (r, t, _) = setup(10, 2).await;
    let mut s = client_1_listing(&r, 2, &[]).await;
    s.step(&end_of(1, &[1], &[1.0])).await.unwrap();
    s.step(&end_of(1, &[0], &[2.0])).await.unwrap();
    s.step(&one(&[1], &[1.0], false)).await.unwrap(); // env 0, mid-episode
    assert_eq!(t.stats().pool_version, 2);
    drop(s);
    // Resumed listing only the env in the middle of an episode.
    let mid = [Resume {
        env_id: 0,
        actions: &[1],
        reward_sum: 1.0,
        ..Default::default()
    }];
    for (i, listed) in [&mid[..], &[]].into_iter().enumerate() {
        let mut s = client_1_listing(&r, 2, listed).await;
        let out = s.step(&end_of(1, &[1], &[3.0 + i as f64])).await.unwrap();
        assert_eq!(
            out.pool_version,
            3 + i as u64,
            "open {i}: a new episode, stored"
        );
        assert_eq!(t.stats().episodes_completed, 3 + i as u64);
    }
    // A re-send of env 1's last end, listed with its number (3), is still not committed.
    let last = [Resume {
        env_id: 1,
        episode: 3,
        ..Default::default()
    }];
    let mut s = client_1_listing(&r, 2, &last).await;
    assert_eq!(
        s.step(&end_of(1, &[1], &[4.0])).await.unwrap().pool_version,
        4
    );
    assert_eq!(t.stats().episodes_completed, 4);
}

#[tokio::test]
async fn a_restarted_data_dir_server_knows_the_record_without_a_resume_list() {
    // The record of committed ends is read back at every open with a client id, not only
    // at a resume: numbering an env not listed needs it as much as checking a re-send.
    let dir = tempfile::tempdir().unwrap();
    {
        let (r, _store) = on_disk(dir.path()).await;
        let t = task(&r, "t", 10).await;
        let mut s = client_1(&r, None).await;
        s.step(&one(&[1], &[1.0], true)).await.unwrap();
        assert_eq!(t.stats().pool_version, 1);
    } // kill -9
    let (r, _store) = on_disk(dir.path()).await;
    let t = r.get(DEFAULT_TENANT, "t").unwrap();
    // Env 0 not listed: its next end is episode 1, a new one.
    let mut s = client_1(&r, None).await;
    assert_eq!(
        s.step(&one(&[0], &[2.0], true)).await.unwrap().pool_version,
        2
    );
    drop(s);
    // Re-sent with its number, episode 1 is recognised (numbered 0 after the restart, it
    // would have been recorded as episode 0 and this re-send committed again).
    let mut s = client_1(&r, Some((&[], 1))).await;
    assert_eq!(
        s.step(&one(&[0], &[2.0], true)).await.unwrap().pool_version,
        2
    );
    assert_eq!((t.snapshot().len(), t.stats().episodes_completed), (2, 2));
}
