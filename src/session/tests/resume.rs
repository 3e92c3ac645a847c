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
