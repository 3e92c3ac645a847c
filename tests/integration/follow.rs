//! The Follow stream (SPEC §13) against a real server on 127.0.0.1:0: a learner's copy of
//! the pool (a snapshot, then gap-free updates, whoever changed the pool), its episode ends
//! decided exactly as a Shape stream's (and shaping at the learner bit for bit as a Shape
//! stream), no double commit (§9), bad input (§8), deletion and idle streams, durability
//! across a crash, and replicas sharing a Redis store (§10). Roles, tenants and quotas of
//! Follow are in `auth.rs`.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use crate::common::*;
use tamrm::core::{
    ActionRef, ActionSeq, ActionSpace, Episode, KnnScratch, Pool, StepInput, TaskConfig,
    Trajectory, Values,
};
use tamrm::proto::{self, follow_request, FollowRequest};
use tamrm::service::convert::config_input;
use tonic::Code;

// ---------------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------------

/// ResetPool; panics on an error status.
async fn reset(c: &mut Client, id: &str) -> proto::Task {
    c.reset_pool(proto::ResetPoolRequest { task_id: id.into() })
        .await
        .unwrap_or_else(|e| panic!("reset_pool {id}: {e}"))
        .into_inner()
}

/// The pool of `id` as GetPool answers it, under another task id (to compare twins).
async fn pool_as(c: &mut Client, id: &str, as_id: &str) -> proto::Pool {
    proto::Pool {
        task_id: as_id.into(),
        ..get_pool(c, id).await
    }
}

fn stats(t: &proto::Task) -> proto::TaskStats {
    t.stats.expect("a task has stats")
}

/// A continuous task config with everything explicit.
fn continuous(
    m: u32,
    capacity: u32,
    k: u32,
    start_step: u32,
    min_pool_size: u32,
) -> proto::TaskConfig {
    proto::TaskConfig {
        num_actions: 0,
        action_dim: m,
        ..discrete(0, capacity, k, start_step, min_pool_size)
    }
}

/// An episode as both a learner (one `EpisodeEnd`) and a Shape stream (its steps) report
/// it: its actions, their rewards, and the client's score if it has one.
#[derive(Debug, Clone)]
struct Ep {
    env: u32,
    episode: u64,
    /// Discrete actions, or `len × m` floats.
    actions: Vec<u32>,
    vectors: Vec<f32>,
    rewards: Vec<f64>,
    score: Option<f64>,
}

impl Ep {
    /// A discrete episode with these rewards, one per action (`(j + env) % n` at step j).
    fn discrete(env: u32, episode: u64, n: u32, rewards: &[f64], score: Option<f64>) -> Ep {
        Ep {
            env,
            episode,
            actions: (0..rewards.len() as u32).map(|j| (j + env) % n).collect(),
            vectors: Vec::new(),
            rewards: rewards.to_vec(),
            score,
        }
    }

    /// A continuous episode (dimension 2) with these rewards, one per action.
    fn continuous(env: u32, episode: u64, rewards: &[f64], score: Option<f64>) -> Ep {
        let vectors = (0..rewards.len())
            .flat_map(|j| [j as f32 * 0.25, -0.5 * env as f32])
            .collect();
        Ep {
            env,
            episode,
            actions: Vec::new(),
            vectors,
            rewards: rewards.to_vec(),
            score,
        }
    }

    fn len(&self) -> usize {
        self.rewards.len()
    }

    /// Σ R in step order, as the server sums a Shape episode's rewards.
    fn reward_sum(&self) -> f64 {
        self.rewards.iter().fold(0.0, |s, r| s + r)
    }

    fn end(&self) -> proto::EpisodeEnd {
        proto::EpisodeEnd {
            env_id: self.env,
            episode: self.episode,
            actions: self.actions.clone(),
            action_vectors: self.vectors.clone(),
            score: self.score,
            reward_sum: self.reward_sum(),
        }
    }

    /// Step `j` of the episode as a one-entry batch (the last one terminates it, with the
    /// client's score if it has one).
    fn step(&self, j: usize) -> proto::StepBatch {
        let last = j + 1 == self.len();
        let m = self.vectors.len() / self.len();
        proto::StepBatch {
            env_ids: vec![self.env],
            actions: self.actions.get(j).map(|&a| vec![a]).unwrap_or_default(),
            action_vectors: if m > 0 {
                self.vectors[j * m..(j + 1) * m].to_vec()
            } else {
                Vec::new()
            },
            rewards: vec![self.rewards[j]],
            terminated: vec![last],
            episode_scores: match self.score {
                Some(s) if last => HashMap::from([(0, s)]),
                _ => HashMap::new(),
            },
            ..Default::default()
        }
    }
}

/// Plays `eps` one after the other through a Shape stream of `num_envs` envs on `id`;
/// returns the pool version after each episode's last step.
async fn shape_episodes(c: &mut Client, id: &str, num_envs: u32, eps: &[Ep]) -> Vec<u64> {
    let (mut s, _) = Stream::open(c, id, num_envs).await.unwrap();
    let mut versions = Vec::new();
    for ep in eps {
        let mut last = None;
        for j in 0..ep.len() {
            last = Some(s.step(ep.step(j)).await.unwrap());
        }
        versions.push(last.unwrap().pool_version);
    }
    versions
}

/// What every test of a bad message checks afterwards: the pool and the task's stats are
/// those of before.
async fn unchanged(c: &mut Client, id: &str, pool: &proto::Pool, task: &proto::Task, ctx: &str) {
    assert_eq!(&get_pool(c, id).await, pool, "{ctx}: the pool changed");
    let now = stats(&get_task(c, id).await);
    let before = stats(task);
    assert_eq!(
        (now.pool_version, now.episodes_completed, now.steps_shaped),
        (
            before.pool_version,
            before.episodes_completed,
            before.steps_shaped
        ),
        "{ctx}: the stats changed"
    );
}

// ---------------------------------------------------------------------------------------
// The pool as the learner holds it
// ---------------------------------------------------------------------------------------

/// `opened` and the snapshot first; then every change made elsewhere (AddTrajectory
/// inserts and replacements, a Shape stream's episode end, ResetPool, a burst the follower
/// does not read at once) reaches the follower as updates (or a snapshot after the reset)
/// that leave its copy exactly as GetPool answers, never with a gap.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_follower_holds_the_pool_through_every_change_made_elsewhere() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(3, 3, 2, 0, 1)).await;
    add(&mut c, "t", dtraj(&[0, 1, 2], 1.0)).await;
    add(&mut c, "t", dtraj(&[2, 2], 2.0)).await;

    let (mut f, task) = Follower::open(&mut c, "t", 1, "").await.unwrap();
    assert_eq!(task.config, get_task(&mut c, "t").await.config);
    let s = stats(&task);
    assert_eq!((s.pool_size, s.pool_version, s.open_streams), (2, 2, 1));
    let pool = get_pool(&mut c, "t").await;
    assert_eq!((pool.pool_version, pool.next_seq), (2, 3));
    assert_eq!(f.pool, pool, "the opening snapshot");
    f.assert_quiet(Duration::from_millis(200)).await;

    // An insert: one update, 2 -> 3, adding seq 3.
    assert!(add(&mut c, "t", dtraj(&[1], 0.5)).await.inserted);
    f.until_version(3).await;
    let u = f.updates.last().unwrap().clone();
    assert_eq!((u.base_version, u.pool_version, u.next_seq), (2, 3, 4));
    assert!(u.removed.is_empty());
    assert_eq!(u.added.len(), 1);
    assert_eq!((u.added[0].seq, &u.added[0].actions[..]), (3, &[1][..]));
    assert_eq!(f.pool, get_pool(&mut c, "t").await);

    // A replacement of the lowest score (seq 3).
    assert!(add(&mut c, "t", dtraj(&[0], 3.0)).await.inserted);
    f.until_version(4).await;
    let u = f.updates.last().unwrap();
    assert_eq!((u.base_version, u.pool_version), (3, 4));
    assert_eq!(u.removed, [3]);
    assert_eq!(u.added.iter().map(|t| t.seq).collect::<Vec<_>>(), [4]);
    assert_eq!(f.pool, get_pool(&mut c, "t").await);

    // A discarded offer changes nothing: nothing is sent.
    assert!(!add(&mut c, "t", dtraj(&[0], 0.1)).await.inserted);
    f.assert_quiet(Duration::from_millis(300)).await;

    // A Shape stream's episode end replaces the lowest score (seq 1, 1.0).
    let (mut s, _) = Stream::open(&mut c, "t", 1).await.unwrap();
    s.step(batch(&[1], &[0.0], &[false])).await.unwrap();
    let ended = s
        .step(proto::StepBatch {
            episode_scores: HashMap::from([(0, 9.0)]),
            ..batch(&[2], &[0.0], &[true])
        })
        .await
        .unwrap();
    assert_eq!(ended.pool_version, 5);
    f.until_version(5).await;
    let u = f.updates.last().unwrap();
    assert_eq!((u.base_version, u.pool_version, u.next_seq), (4, 5, 6));
    assert_eq!(u.removed, [1]);
    assert_eq!(u.added.len(), 1);
    assert_eq!(
        (u.added[0].seq, &u.added[0].actions[..], u.added[0].score),
        (5, &[1, 2][..], 9.0)
    );
    assert_eq!(f.pool, get_pool(&mut c, "t").await);
    assert_eq!(f.snapshots, 1, "no snapshot for changes an update carries");

    // ResetPool: the whole pool goes, a snapshot replaces the copy; seqs are not reused.
    reset(&mut c, "t").await;
    f.until_version(6).await;
    assert_eq!(f.snapshots, 2, "a reset is sent as a snapshot");
    assert!(f.pool.trajectories.is_empty());
    assert_eq!(f.pool.next_seq, 6);
    assert_eq!(f.pool, get_pool(&mut c, "t").await);

    // A burst while the follower does not read: it catches up, with no gap (the helper
    // checks every update's base), maybe several changes per update.
    for i in 0..30u32 {
        add(&mut c, "t", dtraj(&[i % 3, (i / 3) % 3], f64::from(i % 7))).await;
    }
    let pool = get_pool(&mut c, "t").await;
    f.until_version(pool.pool_version).await;
    assert_eq!(f.pool, pool);
    // The Shape stream's next steps see the same pool as the follower's copy.
    assert_eq!(
        s.step(batch(&[0], &[0.0], &[false]))
            .await
            .unwrap()
            .pool_version,
        f.pool.pool_version
    );
    drop(s);
    server.shutdown().await;
}

// ---------------------------------------------------------------------------------------
// Episode ends
// ---------------------------------------------------------------------------------------

/// The same episodes, ended through one `EpisodeEnds` on a Follow stream and through a
/// Shape stream on a twin task: the same pool (actions truncated to max_trajectory_len,
/// the client's score or else Σ R, seqs, version), the same counters; the ack says per end
/// what the Shape stream's pool versions say, and the update carrying the changes comes
/// before it.
async fn ends_as_shape(config: proto::TaskConfig, eps: Vec<Ep>, want_changed: &[bool]) {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    for id in ["f", "s"] {
        create(&mut c, id, config).await;
        if config.num_actions > 0 {
            add(&mut c, id, dtraj(&[0, 1], 1.0)).await;
            add(&mut c, id, dtraj(&[1, 1, 1], 2.0)).await;
        } else {
            add(&mut c, id, ctraj(&[0.0, 0.5, 0.25, -1.0], 1.0)).await;
            add(&mut c, id, ctraj(&[1.0, 1.0], 2.0)).await;
        }
    }
    let steps: usize = eps.iter().map(Ep::len).sum();

    let (mut f, _) = Follower::open(&mut c, "f", 3, "learner").await.unwrap();
    assert_eq!(f.pool.pool_version, 2);
    let ack = f
        .ends(eps.iter().map(Ep::end).collect(), steps as u64)
        .await
        .unwrap();
    let versions = shape_episodes(&mut c, "s", 3, &eps).await;

    // The twin's pool, seq for seq, bit for bit.
    let pool = get_pool(&mut c, "f").await;
    assert_eq!(pool, pool_as(&mut c, "s", "f").await);
    assert_eq!(f.pool, pool, "the follower's copy when the ack arrived");
    let max_len = config.max_trajectory_len.unwrap() as usize;
    for t in &pool.trajectories {
        let len = t.actions.len().max(t.action_vectors.len() / 2);
        assert!(len <= max_len, "{t:?} is not truncated");
    }
    assert!(
        eps.iter().any(|e| e.len() > max_len),
        "the scenario truncates"
    );

    // The ack: per end, what the twin's versions tell.
    let mut before = 2;
    let changed: Vec<bool> = versions
        .iter()
        .map(|&v| {
            let c = v > before;
            before = v;
            c
        })
        .collect();
    assert_eq!(ack.changed, changed);
    assert_eq!(ack.changed, want_changed);
    assert_eq!(ack.versions, versions);
    assert_eq!(ack.resent, vec![false; eps.len()]);
    assert_eq!(ack.pool_version, *versions.last().unwrap());
    assert_eq!(ack.pool_version, pool.pool_version);
    // The changes came in one update (nothing else changed the pool), before the ack.
    assert_eq!(f.updates.len(), 1, "{:?}", f.updates);
    assert_eq!(f.updates[0].base_version, 2);
    assert_eq!(f.updates[0].pool_version, ack.pool_version);

    // The counters: every end is an episode completed, the reported steps are shaped.
    let (sf, ss) = (
        stats(&get_task(&mut c, "f").await),
        stats(&get_task(&mut c, "s").await),
    );
    assert_eq!(sf.episodes_completed, eps.len() as u64);
    assert_eq!(sf.steps_shaped, steps as u64);
    assert_eq!(
        (
            sf.episodes_completed,
            sf.steps_shaped,
            sf.pool_size,
            sf.min_length
        ),
        (
            ss.episodes_completed,
            ss.steps_shaped,
            ss.pool_size,
            ss.min_length
        )
    );
    assert_eq!(
        (sf.best_score.to_bits(), sf.worst_score.to_bits()),
        (ss.best_score.to_bits(), ss.worst_score.to_bits())
    );
    server.shutdown().await;
}

/// Pool capacity 3, seeded with scores 1 and 2, max_trajectory_len 4: an insert (Σ R), a
/// replacement by a truncated episode with a client score, a discard (Σ R too low), a
/// discard at a score equal to the lowest, a replacement (Σ R), and a discard where the
/// client's score (low) wins over a high Σ R.
fn scenario(ep: impl Fn(u32, u64, &[f64], Option<f64>) -> Ep) -> (Vec<Ep>, Vec<bool>) {
    let eps = vec![
        ep(0, 0, &[1.0, 0.5], None),
        ep(1, 0, &[0.0; 7], Some(5.0)),
        ep(0, 1, &[0.5, 0.0, 0.0], None),
        ep(2, 0, &[1.0; 5], Some(1.5)),
        ep(2, 1, &[3.0], None),
        ep(1, 1, &[25.0; 4], Some(-1.0)),
    ];
    (eps, vec![true, true, false, false, true, false])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn discrete_ends_are_decided_as_a_shape_stream_decides_them() {
    let config = proto::TaskConfig {
        max_trajectory_len: Some(4),
        ..discrete(3, 3, 2, 0, 1)
    };
    let (eps, changed) = scenario(|env, number, r, s| Ep::discrete(env, number, 3, r, s));
    ends_as_shape(config, eps, &changed).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn continuous_ends_are_decided_as_a_shape_stream_decides_them() {
    let config = proto::TaskConfig {
        max_trajectory_len: Some(4),
        ..continuous(2, 3, 2, 0, 1)
    };
    let (eps, changed) = scenario(Ep::continuous);
    ends_as_shape(config, eps, &changed).await;
}

/// The learner's copy as a `tamrm::core` pool.
fn core_pool(p: &proto::Pool, capacity: usize, space: ActionSpace) -> Pool {
    let trajectories = p
        .trajectories
        .iter()
        .map(|t| Trajectory {
            actions: match space {
                ActionSpace::Discrete { .. } => ActionSeq::Discrete(t.actions.clone()),
                ActionSpace::Continuous { action_dim } => ActionSeq::Continuous {
                    dim: action_dim as usize,
                    data: t.action_vectors.clone(),
                },
            },
            score: t.score,
            seq: t.seq,
        })
        .collect();
    Pool::restore(capacity, trajectories, p.pool_version, p.next_seq).expect("a valid pool")
}

/// SPEC §13: a learner alone that shapes its steps in process against its followed copy,
/// sending each episode end and applying the updates before its next step, gets exactly,
/// bit for bit, what a Shape stream on a twin task answers, and leaves the same pool.
async fn lone_learner(config: proto::TaskConfig, seed: u64) {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    for id in ["f", "s"] {
        create(&mut c, id, config).await;
    }
    let (mut f, task) = Follower::open(&mut c, "f", 2, "learner").await.unwrap();
    let (mut s, _) = Stream::open(&mut c, "s", 2).await.unwrap();
    let cfg = TaskConfig::resolve(&config_input(task.config.as_ref())).unwrap();
    let space = cfg.action_space;
    let capacity = cfg.pool_capacity as usize;
    let mut local = core_pool(&f.pool, capacity, space);
    let mut episodes = [Episode::new(space), Episode::new(space)];
    let mut numbers = [0u64; 2];
    let mut sums = [0.0f64; 2];
    let mut scratch = KnnScratch::default();
    let mut unreported = 0u64;
    let mut x = seed;
    let mut next = move |m: u64| {
        x = x
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (x >> 33) % m
    };
    let (mut ends, mut active) = (0, 0);
    for i in 0..400 {
        let env = next(2) as usize;
        let m = space.action_dim();
        let (action, vector): (u32, Vec<f32>) = if m == 0 {
            (next(space.num_actions() as u64) as u32, Vec::new())
        } else {
            (0, (0..m).map(|_| next(3) as f32 * 0.5 - 0.5).collect())
        };
        let reward = next(5) as f64 * 0.5 - 1.0;
        let (terminated, truncated) = match next(12) {
            0 => (true, false),
            1 => (false, true),
            _ => (false, false),
        };
        let score = (terminated || truncated)
            .then(|| next(3))
            .filter(|&k| k > 0)
            .map(|k| k as f64 * 1.5 - 2.0);
        let (value, next_value) = (next(7) as f32 * 0.25, next(7) as f32 * 0.25);

        let shaped = s
            .step(proto::StepBatch {
                env_ids: vec![env as u32],
                actions: if m == 0 { vec![action] } else { Vec::new() },
                action_vectors: vector.clone(),
                rewards: vec![reward],
                terminated: vec![terminated],
                truncated: vec![truncated],
                values: vec![value],
                next_values: vec![next_value],
                episode_scores: score.map(|v| HashMap::from([(0, v)])).unwrap_or_default(),
                ..Default::default()
            })
            .await
            .unwrap();

        if local.version() != f.pool.pool_version {
            local = core_pool(&f.pool, capacity, space);
        }
        let input = StepInput {
            action: if m == 0 {
                ActionRef::Discrete(action)
            } else {
                ActionRef::Continuous(&vector)
            },
            reward,
            terminated,
            truncated,
            values: Values::State { value, next_value },
            score,
        };
        let (out, end) = episodes[env].step(&cfg, &local, &input, &mut scratch);
        sums[env] += reward;
        unreported += 1;
        let ctx = format!("step {i}, env {env}: local {out:?}, shaped {shaped:?}");
        assert_eq!(out.reward.to_bits(), shaped.rewards[0].to_bits(), "{ctx}");
        assert_eq!(
            out.knn_reward.to_bits(),
            shaped.knn_rewards[0].to_bits(),
            "{ctx}"
        );
        assert_eq!(
            out.potential.to_bits(),
            shaped.potentials[0].to_bits(),
            "{ctx}"
        );
        assert_eq!(
            (out.step, out.knn_active),
            (u64::from(shaped.steps[0]), shaped.knn_active[0]),
            "{ctx}"
        );
        active += usize::from(out.knn_active);
        if let Some(end) = end {
            ends += 1;
            let (actions, action_vectors) = match end.actions {
                ActionSeq::Discrete(v) => (v, Vec::new()),
                ActionSeq::Continuous { data, .. } => (Vec::new(), data),
            };
            let ack = f
                .ends(
                    vec![proto::EpisodeEnd {
                        env_id: env as u32,
                        episode: numbers[env],
                        actions,
                        action_vectors,
                        score,
                        reward_sum: sums[env],
                    }],
                    unreported,
                )
                .await
                .unwrap();
            assert_eq!(ack.pool_version, shaped.pool_version, "{ctx}");
            assert_eq!(ack.versions, [shaped.pool_version], "{ctx}");
            assert_eq!(f.pool.pool_version, shaped.pool_version, "{ctx}");
            numbers[env] += 1;
            sums[env] = 0.0;
            unreported = 0;
        }
    }
    assert!(
        ends >= 30 && active >= 50,
        "{ends} ends, {active} active steps"
    );
    assert_eq!(get_pool(&mut c, "f").await, pool_as(&mut c, "s", "f").await);
    f.ends(Vec::new(), unreported).await.unwrap();
    let (sf, ss) = (
        stats(&get_task(&mut c, "f").await),
        stats(&get_task(&mut c, "s").await),
    );
    assert_eq!(
        (sf.episodes_completed, sf.steps_shaped),
        (ss.episodes_completed, ss.steps_shaped)
    );
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lone_discrete_learner_shapes_bit_for_bit_as_a_shape_stream() {
    let config = proto::TaskConfig {
        max_trajectory_len: Some(9),
        ..discrete(3, 4, 2, 1, 2)
    };
    lone_learner(config, 7).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lone_continuous_learner_shapes_bit_for_bit_as_a_shape_stream() {
    let config = proto::TaskConfig {
        max_trajectory_len: Some(9),
        ..continuous(2, 4, 3, 0, 2)
    };
    lone_learner(config, 11).await;
}

// ---------------------------------------------------------------------------------------
// No double commit (SPEC §9)
// ---------------------------------------------------------------------------------------

/// Ends re-sent under the same client id, later on the same stream or on a new one, are
/// acknowledged as resent and commit and count nothing; the client id scopes this.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn resent_ends_are_never_committed_twice() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(3, 10, 2, 0, 1)).await;
    let ends = || {
        vec![
            dend(0, 0, &[0, 1], None, 1.0),
            dend(1, 0, &[2], Some(4.0), 0.0),
        ]
    };

    let (mut f, _) = Follower::open(&mut c, "t", 2, "client-1").await.unwrap();
    let ack = f.ends(ends(), 3).await.unwrap();
    assert_eq!(
        (ack.changed, ack.versions, ack.resent, ack.pool_version),
        (vec![true, true], vec![1, 2], vec![false, false], 2)
    );
    let pool = get_pool(&mut c, "t").await;
    let task = get_task(&mut c, "t").await;
    assert_eq!(
        (stats(&task).episodes_completed, stats(&task).steps_shaped),
        (2, 3)
    );

    // The same stream, a later message.
    let ack = f.ends(ends(), 0).await.unwrap();
    assert_eq!(
        (ack.changed, ack.versions, ack.resent, ack.pool_version),
        (vec![false, false], vec![2, 2], vec![true, true], 2)
    );
    unchanged(&mut c, "t", &pool, &task, "re-sent on the same stream").await;
    assert_eq!(f.pool, pool);

    // A new stream of the same client (the first one lost).
    drop(f);
    let (mut f, _) = Follower::open(&mut c, "t", 2, "client-1").await.unwrap();
    let ack = f.ends(ends(), 0).await.unwrap();
    assert_eq!(
        (ack.changed, ack.resent, ack.pool_version),
        (vec![false, false], vec![true, true], 2)
    );
    unchanged(&mut c, "t", &pool, &task, "re-sent on a new stream").await;

    // A re-sent end and a new one in one message: only the new one is committed.
    let mut mixed = ends();
    mixed.insert(1, dend(0, 1, &[1, 1, 1], None, 0.5));
    let ack = f.ends(mixed, 3).await.unwrap();
    assert_eq!(
        (ack.changed, ack.versions, ack.resent, ack.pool_version),
        (
            vec![false, true, false],
            vec![2, 3, 3],
            vec![true, false, true],
            3
        )
    );
    let t = stats(&get_task(&mut c, "t").await);
    assert_eq!((t.episodes_completed, t.steps_shaped), (3, 6));

    // Another client's (env, episode) are its own; without a client id nothing is
    // remembered.
    let (mut g, _) = Follower::open(&mut c, "t", 2, "client-2").await.unwrap();
    let ack = g.ends(ends(), 0).await.unwrap();
    assert_eq!(
        (ack.changed, ack.resent),
        (vec![true, true], vec![false, false])
    );
    let (mut h, _) = Follower::open(&mut c, "t", 2, "").await.unwrap();
    for _ in 0..2 {
        let ack = h.ends(ends()[..1].to_vec(), 0).await.unwrap();
        assert_eq!((ack.changed, ack.resent), (vec![true], vec![false]));
    }
    let t = stats(&get_task(&mut c, "t").await);
    assert_eq!((t.episodes_completed, t.pool_version), (7, 7));
    // Every follower holds the pool (the others' changes came as updates).
    let pool = get_pool(&mut c, "t").await;
    for x in [&mut f, &mut g, &mut h] {
        x.until_version(7).await;
        assert_eq!(x.pool, pool);
    }
    server.shutdown().await;
}

// ---------------------------------------------------------------------------------------
// Bad input (SPEC §8)
// ---------------------------------------------------------------------------------------

/// Each bad message gets INVALID_ARGUMENT naming the field, ends the stream, and commits
/// nothing (not even the valid end before the bad one); another follower is unaffected.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_ends_are_refused_naming_the_field_and_commit_nothing() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "d", discrete(3, 3, 2, 0, 1)).await;
    add(&mut c, "d", dtraj(&[0, 1], 1.0)).await;
    create(&mut c, "c", continuous(2, 3, 2, 0, 1)).await;
    add(&mut c, "c", ctraj(&[0.0, 1.0], 1.0)).await;
    let (mut watcher, _) = Follower::open(&mut c, "d", 2, "watcher").await.unwrap();

    let good_d = || dend(0, 0, &[2, 2, 2], Some(10.0), 0.0);
    let good_c = || proto::EpisodeEnd {
        action_vectors: vec![0.5, 0.5],
        ..dend(0, 0, &[], Some(10.0), 0.0)
    };
    let big = tamrm::session::MAX_REPORTED_STEPS + 1;
    #[rustfmt::skip]
    let cases: Vec<(&str, &str, Vec<proto::EpisodeEnd>, u64, &str)> = vec![
        ("d", "env_id >= num_envs", vec![good_d(), dend(2, 0, &[0], None, 0.0)], 1, "ends.ends[1].env_id"),
        ("d", "no actions", vec![good_d(), dend(1, 0, &[], None, 0.0)], 1, "ends.ends[1].actions"),
        ("d", "action out of range", vec![good_d(), dend(1, 0, &[0, 3], None, 0.0)], 1, "ends.ends[1].actions[1]"),
        ("d", "vectors on a discrete task", vec![good_d(), proto::EpisodeEnd { action_vectors: vec![0.5], ..dend(1, 0, &[0], None, 0.0) }], 1, "ends.ends[1].action_vectors"),
        ("d", "NaN score", vec![good_d(), dend(1, 0, &[0], Some(f64::NAN), 0.0)], 1, "ends.ends[1].score"),
        ("d", "infinite score", vec![good_d(), dend(1, 0, &[0], Some(f64::NEG_INFINITY), 0.0)], 1, "ends.ends[1].score"),
        ("d", "infinite reward_sum", vec![good_d(), dend(1, 0, &[0], None, f64::INFINITY)], 1, "ends.ends[1].reward_sum"),
        ("d", "NaN reward_sum with a score", vec![good_d(), dend(1, 0, &[0], Some(1.0), f64::NAN)], 1, "ends.ends[1].reward_sum"),
        ("d", "an episode listed twice", vec![good_d(), dend(0, 0, &[1], None, 0.0)], 1, "ends.ends[1].episode"),
        ("d", "too many steps", vec![good_d()], big, "ends.steps"),
        ("c", "wrong action_vectors length", vec![good_c(), proto::EpisodeEnd { action_vectors: vec![0.5; 3], ..dend(1, 0, &[], None, 0.0) }], 1, "ends.ends[1].action_vectors"),
        ("c", "no action vectors", vec![good_c(), dend(1, 0, &[], None, 0.0)], 1, "ends.ends[1].action_vectors"),
        ("c", "non-finite action vector", vec![good_c(), proto::EpisodeEnd { action_vectors: vec![0.5, f32::NAN], ..dend(1, 0, &[], None, 0.0) }], 1, "ends.ends[1].action_vectors[1]"),
        ("c", "actions on a continuous task", vec![good_c(), dend(1, 0, &[0], None, 0.0)], 1, "ends.ends[1].actions"),
    ];
    for (id, what, ends, steps, field) in cases {
        let pool = get_pool(&mut c, id).await;
        let task = get_task(&mut c, id).await;
        let (mut f, _) = Follower::open(&mut c, id, 2, "bad").await.unwrap();
        // A good message first: the stream works until the bad one.
        f.ends(Vec::new(), 0).await.unwrap();
        f.send(ends_msg(ends, steps)).await;
        let e = f.status().await;
        assert_eq!(e.code(), Code::InvalidArgument, "{what}: {e:?}");
        assert!(
            e.message().starts_with(&format!("{field}:")),
            "{what}: the message does not name {field}: {}",
            e.message()
        );
        unchanged(&mut c, id, &pool, &task, what).await;
    }
    // The valid ends listed first were not marked committed either: sent alone now, they
    // are committed.
    for (id, good) in [("d", good_d()), ("c", good_c())] {
        let (mut f, _) = Follower::open(&mut c, id, 2, "bad").await.unwrap();
        let ack = f.ends(vec![good], 1).await.unwrap();
        assert_eq!(
            (ack.changed, ack.resent, ack.pool_version),
            (vec![true], vec![false], 2),
            "{id}"
        );
    }
    // The watcher saw only that last change.
    watcher.until_version(2).await;
    assert_eq!(watcher.updates.len(), 1);
    assert_eq!(watcher.pool, get_pool(&mut c, "d").await);
    let ack = watcher
        .ends(vec![dend(1, 0, &[1], None, 0.0)], 1)
        .await
        .unwrap();
    assert_eq!(ack.resent, [false]);
    server.shutdown().await;
}

/// What opens a Follow stream is checked: the first message must be `open`, and only the
/// first; the task must exist; num_envs >= 1 and within the server's limit; a message must
/// set `open` or `ends`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_open_is_refused() {
    let server = start_server(None, |s| s.limits.max_envs_per_stream = 8).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(3, 3, 2, 0, 1)).await;
    add(&mut c, "t", dtraj(&[0, 1], 1.0)).await;
    let pool = get_pool(&mut c, "t").await;
    let task = get_task(&mut c, "t").await;
    let open = |task_id: &str, num_envs: u32| FollowRequest {
        kind: Some(follow_request::Kind::Open(proto::FollowOpen {
            task_id: task_id.into(),
            num_envs,
            client_id: "x".into(),
        })),
    };
    let ends = || ends_msg(vec![dend(0, 0, &[1], Some(5.0), 0.0)], 1);
    #[rustfmt::skip]
    let cases: Vec<(&str, Vec<FollowRequest>, Code, &str)> = vec![
        ("ends first", vec![ends()], Code::InvalidArgument, "open:"),
        ("an empty message first", vec![FollowRequest { kind: None }], Code::InvalidArgument, "kind:"),
        ("a second open", vec![open("t", 1), open("t", 1)], Code::InvalidArgument, "open:"),
        ("an empty message later", vec![open("t", 1), FollowRequest { kind: None }], Code::InvalidArgument, "kind:"),
        ("an unknown task", vec![open("nope", 1)], Code::NotFound, "task \"nope\" not found"),
        ("a malformed task id", vec![open("no spaces", 1)], Code::InvalidArgument, "open.task_id:"),
        ("num_envs = 0", vec![open("t", 0)], Code::InvalidArgument, "open.num_envs:"),
        ("num_envs over the limit", vec![open("t", 9)], Code::ResourceExhausted, "max_envs_per_stream = 8"),
    ];
    for (what, msgs, code, says) in cases {
        let mut f = Follower::raw(&mut c).await.unwrap();
        for m in msgs {
            f.send(m).await;
        }
        let e = loop {
            match f.recv().await {
                Err(e) => break e,
                Ok(Some(proto::FollowResponse {
                    kind:
                        Some(
                            proto::follow_response::Kind::Opened(_)
                            | proto::follow_response::Kind::Snapshot(_),
                        ),
                })) => continue,
                other => panic!("{what}: expected an error, got {other:?}"),
            }
        };
        assert_eq!(e.code(), code, "{what}: {e:?}");
        assert!(e.message().contains(says), "{what}: {}", e.message());
        unchanged(&mut c, "t", &pool, &task, what).await;
    }
    // A stream closed before its first message.
    let f = Follower::raw(&mut c).await.unwrap();
    drop(f.tx);
    let mut rx = f.rx;
    let e = rx.message().await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(e.message().starts_with("open:"), "{}", e.message());
    wait_open_streams(&mut c, "t", 0).await;
    server.shutdown().await;
}

// ---------------------------------------------------------------------------------------
// Deletion, idle streams, open streams
// ---------------------------------------------------------------------------------------

/// DeleteTask ends a Follow stream with NOT_FOUND at once, without the learner sending
/// anything; a follower of another task goes on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deleting_the_task_ends_its_follow_streams_with_not_found() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "gone", discrete(2, 2, 1, 0, 1)).await;
    create(&mut c, "kept", discrete(2, 2, 1, 0, 1)).await;
    let (mut f, _) = Follower::open(&mut c, "gone", 1, "").await.unwrap();
    let (mut other, _) = Follower::open(&mut c, "kept", 1, "").await.unwrap();
    f.ends(vec![dend(0, 0, &[1], None, 1.0)], 1).await.unwrap();
    c.delete_task(proto::DeleteTaskRequest {
        task_id: "gone".into(),
    })
    .await
    .unwrap();
    let e = f.status().await;
    assert_eq!(e.code(), Code::NotFound, "{e:?}");
    assert!(e.message().contains("\"gone\""), "{}", e.message());
    // A task created again under the id is another task: the old stream is not revived,
    // and a new follower gets the new, empty pool.
    create(&mut c, "gone", discrete(2, 2, 1, 0, 1)).await;
    let (g, _) = Follower::open(&mut c, "gone", 1, "").await.unwrap();
    assert!(g.pool.trajectories.is_empty());
    assert_eq!(g.pool.pool_version, 0);
    let ack = other
        .ends(vec![dend(0, 0, &[1], None, 1.0)], 1)
        .await
        .unwrap();
    assert_eq!(ack.changed, [true]);
    server.shutdown().await;
}

/// `stream_idle_timeout_secs`: a follower that sends nothing is closed with UNAVAILABLE
/// naming the setting, and stops counting as open; one that sends empty EpisodeEnds stays
/// open. `open_streams` counts a Follow stream while it is open.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_follow_streams_are_closed_and_counted_while_open() {
    let server = start_server(None, |s| s.limits.stream_idle_timeout_secs = 1).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(2, 2, 1, 0, 1)).await;
    let start = Instant::now();
    let (mut quiet, task) = Follower::open(&mut c, "t", 1, "").await.unwrap();
    assert_eq!(stats(&task).open_streams, 1);
    let (mut busy, _) = Follower::open(&mut c, "t", 1, "").await.unwrap();
    assert_eq!(stats(&get_task(&mut c, "t").await).open_streams, 2);

    // Meanwhile the busy one keeps itself open with empty messages (acked at the
    // current version).
    let keep_open = async {
        for _ in 0..6 {
            tokio::time::sleep(Duration::from_millis(400)).await;
            let ack = busy.ends(Vec::new(), 0).await.unwrap();
            assert_eq!(ack.pool_version, 0);
            assert!(ack.changed.is_empty() && ack.versions.is_empty() && ack.resent.is_empty());
        }
    };
    let closed = async {
        let e = quiet.status().await;
        (e, start.elapsed())
    };
    let ((e, after), ()) = tokio::join!(closed, keep_open);
    assert_eq!(e.code(), Code::Unavailable, "{e:?}");
    assert!(
        e.message().contains("stream_idle_timeout_secs"),
        "{}",
        e.message()
    );
    assert!(
        after >= Duration::from_millis(900),
        "closed after {after:?}"
    );
    wait_open_streams(&mut c, "t", 1).await;
    // A half-closed follower ends cleanly and stops counting.
    drop(busy.tx);
    assert!(busy.rx.message().await.unwrap().is_none());
    wait_open_streams(&mut c, "t", 0).await;
    server.shutdown().await;
}

// ---------------------------------------------------------------------------------------
// Durability (a --data-dir server)
// ---------------------------------------------------------------------------------------

/// Ends acknowledged through Follow are on disk: after a SIGKILL the restarted server has
/// the same pool, and the same ends re-sent under the same client id are resent.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acked_ends_survive_a_crash_and_stay_committed_once() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let bin = Binary::start(&["--data-dir", data.to_str().unwrap()]);
    let mut c = connect(bin.addr).await;
    create(&mut c, "t", discrete(3, 3, 2, 0, 1)).await;
    add(&mut c, "t", dtraj(&[0, 0], 0.5)).await;
    let ends = || {
        vec![
            dend(0, 0, &[0, 1, 2], None, 2.0),
            dend(1, 0, &[2], Some(3.0), 0.0),
            dend(0, 1, &[1, 1], None, 4.0),
        ]
    };
    let (mut f, _) = Follower::open(&mut c, "t", 2, "durable").await.unwrap();
    let ack = f.ends(ends(), 6).await.unwrap();
    assert_eq!(ack.changed, [true, true, true]);
    assert_eq!(ack.pool_version, 4);
    let before = get_pool(&mut c, "t").await;
    assert_eq!(f.pool, before);
    // Crash: SIGKILL with the stream open.
    drop(bin);
    drop(f);

    let bin = Binary::start(&["--data-dir", data.to_str().unwrap()]);
    let mut c = connect(bin.addr).await;
    assert_eq!(get_pool(&mut c, "t").await, before);
    let (mut f, _) = Follower::open(&mut c, "t", 2, "durable").await.unwrap();
    assert_eq!(f.pool, before);
    let ack = f.ends(ends(), 0).await.unwrap();
    assert_eq!(ack.resent, [true, true, true]);
    assert_eq!(ack.changed, [false, false, false]);
    assert_eq!(ack.pool_version, 4);
    assert_eq!(get_pool(&mut c, "t").await, before);
    // The client's next episode is committed, with the next seq.
    let ack = f
        .ends(vec![dend(1, 1, &[0], Some(9.0), 0.0)], 1)
        .await
        .unwrap();
    assert_eq!((ack.changed, ack.resent), (vec![true], vec![false]));
    assert_eq!(f.pool.trajectories.last().unwrap().seq, before.next_seq);
    drop((f, c));
    let (status, log) = bin.terminate();
    assert!(status.success(), "{log}");
}

// ---------------------------------------------------------------------------------------
// Replicas sharing a Redis store (SPEC §10)
// ---------------------------------------------------------------------------------------

async fn replica(url: &str) -> tamrm::server::RunningServer {
    let url = url.to_string();
    start_server(None, move |s| {
        s.store = Some(url);
        s.store_poll_ms = 200;
    })
    .await
}

/// A follower on replica A sees, as updates within the staleness bound, the ends another
/// learner commits through a Follow stream on replica B (and a reset made on B); both
/// followers hold GetPool's pool. The client's ends re-sent on A are resent.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_follower_on_one_replica_sees_ends_committed_through_another() {
    let redis = RedisServer::start();
    let (a, b) = (replica(&redis.url()).await, replica(&redis.url()).await);
    let (mut ca, mut cb) = (connect(a.addr()).await, connect(b.addr()).await);
    create(&mut ca, "t", discrete(3, 3, 2, 0, 1)).await;
    add(&mut ca, "t", dtraj(&[0, 1, 2], 1.0)).await;
    add(&mut ca, "t", dtraj(&[2], 2.0)).await;

    let (mut fa, _) = Follower::open(&mut ca, "t", 1, "").await.unwrap();
    let (mut fb, _) = Follower::open(&mut cb, "t", 2, "learner").await.unwrap();
    assert_eq!(fa.pool, fb.pool);
    assert_eq!(fa.pool.pool_version, 2);
    let ends = || {
        vec![
            dend(0, 0, &[1, 1], None, 1.5),
            dend(1, 0, &[0], Some(5.0), 0.0),
        ]
    };
    let ack = fb.ends(ends(), 3).await.unwrap();
    assert_eq!(
        (ack.changed, ack.versions, ack.pool_version),
        (vec![true, true], vec![3, 4], 4)
    );
    let started = Instant::now();
    fa.until_version(4).await;
    assert!(started.elapsed() < Duration::from_secs(5));
    assert!(!fa.updates.is_empty(), "the change came as updates");
    let pool = get_pool(&mut cb, "t").await;
    assert_eq!(fb.pool, pool);
    assert_eq!(fa.pool, pool);
    assert_eq!(get_pool(&mut ca, "t").await, pool);

    // The same client on replica A: its ends were committed (on B), so they are resent.
    let (mut again, _) = Follower::open(&mut ca, "t", 2, "learner").await.unwrap();
    assert_eq!(again.pool, pool);
    let ack = again.ends(ends(), 0).await.unwrap();
    assert_eq!(
        (ack.changed, ack.resent, ack.pool_version),
        (vec![false, false], vec![true, true], 4)
    );

    // A reset on B reaches A's follower as a snapshot.
    reset(&mut cb, "t").await;
    fa.until_version(5).await;
    assert!(fa.pool.trajectories.is_empty());
    assert_eq!(fa.pool, get_pool(&mut ca, "t").await);
    fb.until_version(5).await;
    assert_eq!(fb.pool, fa.pool);
}

/// Two streams of one client on two replicas (one opened before the other committed): an
/// end committed through B and then sent through A is not committed again, and A's answer
/// does not claim it as a fresh end: either an ack that says resent, or UNAVAILABLE (the
/// learner re-opens and re-sends, and then gets resent).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_end_committed_meanwhile_through_another_replica_is_not_committed_again() {
    let redis = RedisServer::start();
    let (a, b) = (replica(&redis.url()).await, replica(&redis.url()).await);
    let (mut ca, mut cb) = (connect(a.addr()).await, connect(b.addr()).await);
    create(&mut ca, "t", discrete(3, 5, 2, 0, 1)).await;
    let (mut fa, _) = Follower::open(&mut ca, "t", 1, "racer").await.unwrap();
    let (mut fb, _) = Follower::open(&mut cb, "t", 1, "racer").await.unwrap();
    let ends = || vec![dend(0, 0, &[1, 2], None, 1.0)];
    let ack = fb.ends(ends(), 2).await.unwrap();
    assert_eq!((ack.changed, ack.resent), (vec![true], vec![false]));
    let pool = get_pool(&mut cb, "t").await;
    assert_eq!(pool.pool_version, 1);

    match fa.ends(ends(), 0).await {
        Ok(ack) => {
            assert_eq!((ack.changed, ack.resent), (vec![false], vec![true]));
        }
        Err(e) => {
            assert_eq!(e.code(), Code::Unavailable, "{e:?}");
            let (mut again, _) = Follower::open(&mut ca, "t", 1, "racer").await.unwrap();
            let ack = again.ends(ends(), 0).await.unwrap();
            assert_eq!((ack.changed, ack.resent), (vec![false], vec![true]));
        }
    }
    assert_eq!(get_pool(&mut ca, "t").await, pool);
    assert_eq!(get_pool(&mut cb, "t").await, pool);
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (ta, tb) = (get_task(&mut ca, "t").await, get_task(&mut cb, "t").await);
        let counted = [ta, tb].map(|t| stats(&t).episodes_completed);
        if counted == [1, 1] {
            break;
        }
        assert!(
            counted.iter().all(|&n| n <= 1),
            "counted twice: {counted:?}"
        );
        assert!(Instant::now() < deadline, "episodes_completed: {counted:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
