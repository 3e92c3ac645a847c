//! Arbitrary, mostly invalid batches: either the whole batch is
//! applied or none of it; a rejection names a field of the batch; other streams on the
//! task are unaffected.

use proptest::prelude::*;

use super::*;
use crate::core::TaskConfig;

/// A batch's columns, owned, each of a random (often wrong) length and content.
#[derive(Debug, Clone)]
struct Cols {
    env_ids: Vec<u32>,
    actions: Vec<u32>,
    rewards: Vec<f64>,
    terminated: Vec<bool>,
    truncated: Vec<bool>,
    values: Vec<f32>,
    next_values: Vec<f32>,
    q_values: Vec<f32>,
    next_q_values: Vec<f32>,
    episode_scores: Vec<(u32, f64)>,
    abandon: Vec<u32>,
    action_vectors: Vec<f32>,
}

impl Cols {
    fn batch(&self) -> Batch<'_> {
        Batch {
            env_ids: &self.env_ids,
            actions: &self.actions,
            action_vectors: &self.action_vectors,
            rewards: &self.rewards,
            terminated: &self.terminated,
            truncated: &self.truncated,
            values: &self.values,
            next_values: &self.next_values,
            q_values: &self.q_values,
            next_q_values: &self.next_q_values,
            episode_scores: &self.episode_scores,
            abandon: &self.abandon,
        }
    }
}

/// One way to break a valid batch.
#[derive(Debug, Clone)]
enum Break {
    /// Drop the last element of a column (0..12 picks which).
    Shorten(usize),
    /// Put a non-finite number into a column.
    NonFinite(usize),
    /// An action or env id out of range.
    OutOfRange(bool),
    /// A score on an entry that does not end its episode (or past the end).
    StrayScore(u32),
    /// Abandon an env twice, or one out of range.
    BadAbandon(bool),
    /// Q-values next to values.
    BothValueKinds,
}

fn apply(c: &mut Cols, b: &Break) {
    match *b {
        Break::Shorten(i) => {
            match i % 8 {
                0 => c.env_ids.truncate(c.env_ids.len().saturating_sub(1)),
                1 => c.actions.truncate(c.actions.len().saturating_sub(1)),
                2 => c.rewards.truncate(c.rewards.len().saturating_sub(1)),
                3 => c.terminated.truncate(c.terminated.len().saturating_sub(1)),
                4 => c.truncated.truncate(c.truncated.len().saturating_sub(1)),
                5 => c.values.truncate(c.values.len().saturating_sub(1)),
                6 => c
                    .next_values
                    .truncate(c.next_values.len().saturating_sub(1)),
                _ => c.actions.push(0),
            };
        }
        Break::NonFinite(i) => match i % 3 {
            0 => c.rewards.iter_mut().for_each(|r| *r = f64::NAN),
            1 => c.values.iter_mut().for_each(|v| *v = f32::INFINITY),
            _ => c
                .episode_scores
                .iter_mut()
                .for_each(|s| s.1 = f64::NEG_INFINITY),
        },
        Break::OutOfRange(action) => {
            if action {
                c.actions.iter_mut().for_each(|a| *a = 2);
            } else if !c.env_ids.is_empty() {
                c.env_ids[0] = 3;
            } else {
                c.env_ids = vec![3; c.rewards.len()];
            }
        }
        Break::StrayScore(i) => c.episode_scores.push((i, 1.0)),
        Break::BadAbandon(twice) => c.abandon = if twice { vec![1, 1] } else { vec![3] },
        Break::BothValueKinds => {
            c.q_values = vec![0.0; c.rewards.len() * 2];
            c.next_q_values = vec![0.0; c.rewards.len() * 2];
            if c.values.is_empty() {
                c.values = vec![0.0; c.rewards.len()];
                c.next_values = vec![0.0; c.rewards.len()];
            }
        }
    }
}

fn breaks() -> impl Strategy<Value = Break> {
    prop_oneof![
        (0usize..12).prop_map(Break::Shorten),
        (0usize..3).prop_map(Break::NonFinite),
        any::<bool>().prop_map(Break::OutOfRange),
        (0u32..5).prop_map(Break::StrayScore),
        any::<bool>().prop_map(Break::BadAbandon),
        Just(Break::BothValueKinds),
    ]
}

/// A valid batch for a 3-env stream of a 2-action task, then 0 to 2 breaks.
fn cols() -> impl Strategy<Value = Cols> {
    (0usize..=3)
        .prop_flat_map(|b| {
            (
                prop::collection::vec(0u32..2, b),
                prop::collection::vec(-2.0..2.0f64, b),
                prop::collection::vec(prop::bool::weighted(0.3), b),
                any::<bool>(),
                any::<bool>(),
                prop::collection::vec(0u32..3, 0..=1),
                prop::collection::vec(breaks(), 0..=2),
            )
        })
        .prop_map(
            |(actions, rewards, terminated, explicit_ids, with_values, abandon, brk)| {
                let b = rewards.len();
                let ends: Vec<u32> = (0..b as u32).filter(|&i| terminated[i as usize]).collect();
                let mut c = Cols {
                    env_ids: if explicit_ids {
                        (0..b as u32).rev().collect()
                    } else {
                        vec![]
                    },
                    actions,
                    rewards,
                    terminated,
                    truncated: vec![],
                    values: if with_values { vec![0.5; b] } else { vec![] },
                    next_values: if with_values { vec![0.25; b] } else { vec![] },
                    q_values: vec![],
                    next_q_values: vec![],
                    episode_scores: ends.iter().take(1).map(|&i| (i, 2.0)).collect(),
                    abandon,
                    action_vectors: vec![],
                };
                for k in &brk {
                    apply(&mut c, k);
                }
                c
            },
        )
}

/// What a batch may change: every episode's t, the pool and the counters.
fn state(s: &StreamSession) -> (Vec<u64>, u64, Vec<u64>, u64, u64) {
    let t = s.task();
    let stats = t.stats();
    (
        s.episodes.iter().map(|e| e.t()).collect(),
        stats.pool_version,
        t.snapshot().seqs().to_vec(),
        stats.episodes_completed,
        stats.steps_shaped,
    )
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    #[test]
    fn a_batch_is_applied_whole_or_not_at_all(batches in prop::collection::vec(cols(), 1..6)) {
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        rt.block_on(async {
            let (r, _t, mut s) = setup(2, 3).await;
            let mut witness = open(&r, "t", 1).await.unwrap();
            let probe = Batch { actions: &[1], rewards: &[0.0], ..Default::default() };
            for cols in &batches {
                let batch = cols.batch();
                let before = state(&s);
                match s.step(&batch).await {
                    Ok(shaped) => {
                        prop_assert_eq!(shaped.outputs.len(), batch.len());
                        let after = state(&s);
                        prop_assert_eq!(after.4, before.4 + batch.len() as u64);
                    }
                    Err(Error::InvalidArgument { field, message }) => {
                        prop_assert!(field.starts_with("steps."), "{}: {}", field, message);
                        prop_assert!(!message.is_empty());
                        prop_assert_eq!(state(&s), before, "a rejected batch changed something");
                    }
                    Err(other) => prop_assert!(false, "unexpected error {:?}", other),
                }
                // The other stream on the task goes on.
                let w = witness.step(&probe).await;
                prop_assert!(w.is_ok(), "witness failed: {:?}", w.err());
            }
            Ok(())
        })?;
    }
}

#[test]
fn the_generator_makes_both_valid_and_invalid_batches() {
    use proptest::strategy::ValueTree;
    let mut runner = proptest::test_runner::TestRunner::deterministic();
    let config = TaskConfig::resolve(&TaskConfigInput {
        num_actions: 2,
        ..Default::default()
    })
    .unwrap();
    let (mut ok, mut bad) = (0, 0);
    for _ in 0..500 {
        let cols = cols().new_tree(&mut runner).unwrap().current();
        match cols.batch().validate(&config, 3, &Limits::default()) {
            Ok(_) => ok += 1,
            Err(_) => bad += 1,
        }
    }
    assert!(ok >= 25 && bad >= 25, "valid {ok}, invalid {bad}");
}
