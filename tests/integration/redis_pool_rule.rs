//! The pool update of SPEC §6 as Redis runs it (`src/store/redis/commit.lua`, a copy of
//! the rule in Lua) decides exactly what the library's does (`core::Pool::plan_offer`,
//! through `store::apply_ops`): insert while not full, else replace the lowest score (the
//! lowest seq among equal scores) if the offer's is strictly greater, else discard; one
//! version and one seq per change. Random pools and random offers against a real
//! `redis-server` started on a free port.

use std::sync::Arc;

use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use tamrm::core::{ActionSeq, Pool, TaskConfig, TaskConfigInput};
use tamrm::store::{apply_ops, Counters, PoolOp, RedisOptions, RedisStore, Store};

use crate::common::RedisServer;

/// An operation of a case.
#[derive(Debug, Clone)]
enum Op {
    Offer { actions: Vec<u32>, score: f64 },
    Reset,
}

impl Op {
    fn pool_op(&self) -> PoolOp {
        match self {
            Op::Offer { actions, score } => PoolOp::Offer {
                actions: ActionSeq::Discrete(actions.clone()),
                score: *score,
                end: None,
            },
            Op::Reset => PoolOp::Reset,
        }
    }
}

/// Scores that tie often, that differ in their last bit only, of either sign, zeros of
/// both signs, subnormal and huge, and now and then any finite number.
fn score() -> impl Strategy<Value = f64> {
    let one_up = f64::from_bits(1.0f64.to_bits() + 1);
    prop_oneof![
        8 => prop::sample::select(vec![
            -3.0, -1.0, -0.0, 0.0, 1.0, one_up, 2.5, 5e-324, -1e300, 1e300,
        ]),
        1 => prop::num::f64::NORMAL | prop::num::f64::SUBNORMAL | prop::num::f64::ZERO,
    ]
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        20 => (prop::collection::vec(0u32..4, 1..5), score())
            .prop_map(|(actions, score)| Op::Offer { actions, score }),
        1 => Just(Op::Reset),
    ]
}

/// A task's capacity and its commits, each the parts of one group commit (the ops of
/// several requests, committed by one script run).
fn case() -> impl Strategy<Value = (u32, Vec<Vec<Vec<Op>>>)> {
    let part = prop::collection::vec(op(), 0..6);
    let commit = prop::collection::vec(part, 1..4);
    (1u32..7, prop::collection::vec(commit, 1..8))
}

fn config(capacity: u32) -> TaskConfig {
    TaskConfig::resolve(&TaskConfigInput {
        num_actions: 4,
        pool_capacity: Some(capacity),
        k: Some(1),
        ..Default::default()
    })
    .unwrap()
}

/// What a pool holds: version, next seq, and each trajectory's seq, actions and score
/// bits.
type Contents = (u64, u64, Vec<(u64, Vec<u32>, u64)>);

fn contents(pool: &Pool) -> Contents {
    let trajectories = pool
        .trajectories()
        .iter()
        .map(|t| match &t.actions {
            ActionSeq::Discrete(a) => (t.seq, a.clone(), t.score.to_bits()),
            ActionSeq::Continuous { .. } => unreachable!("a discrete task"),
        })
        .collect();
    (pool.version(), pool.next_seq(), trajectories)
}

/// Runs the commits of one case on a new task and checks every step against the model.
async fn check(
    store: &RedisStore,
    id: &str,
    capacity: u32,
    commits: Vec<Vec<Vec<Op>>>,
) -> Result<(), TestCaseError> {
    store.create_task(id, &config(capacity)).await.unwrap();
    let mut model = Pool::new(capacity as usize);
    for (i, parts) in commits.iter().enumerate() {
        let parts: Vec<Vec<PoolOp>> = parts
            .iter()
            .map(|p| p.iter().map(Op::pool_op).collect())
            .collect();
        let (want, want_changed) = apply_ops(&model, parts.concat());
        let got = store
            .commit_group(id, Arc::new(model), parts, Counters::default())
            .await
            .unwrap()
            .committed;
        prop_assert_eq!(&got.changed, &want_changed, "commit {}: changed per op", i);
        prop_assert_eq!(got.version, want.version(), "commit {}: version", i);
        // The pool as Redis holds it now, read back and decoded.
        let stored = store.load_pool(id).await.unwrap().expect("the task exists");
        prop_assert_eq!(contents(&stored), contents(&want), "commit {}: pool", i);
        prop_assert_eq!(stored.capacity(), capacity as usize);
        model = want;
    }
    store.delete_task(id).await.unwrap();
    Ok(())
}

#[test]
fn redis_decides_every_pool_update_as_the_library_does() {
    let redis = RedisServer::start();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let store = rt
        .block_on(RedisStore::open(&RedisOptions::new(redis.url())))
        .unwrap();
    let mut runner = TestRunner::new(Config {
        cases: 256,
        failure_persistence: None,
        ..Config::default()
    });
    let n = std::cell::Cell::new(0);
    runner
        .run(&case(), |(capacity, commits)| {
            n.set(n.get() + 1);
            let id = format!("t{}", n.get());
            rt.block_on(check(&store, &id, capacity, commits))
        })
        .unwrap();
}
