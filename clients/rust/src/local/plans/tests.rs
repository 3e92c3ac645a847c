//! [`Unsettled::may_plan`] against a server simulated from SPEC §6: whatever others
//! change first, and wherever, the server's version after each end answered with its
//! plan is never below the plan's; with no one else, it is the plan's.

use std::sync::Arc;

use proptest::collection::vec;
use proptest::prelude::*;
use tamrm::core::{ActionSeq, Pool};
use tamrm::store::{apply_ops, PoolOp};
use tokio::sync::oneshot;

use super::{Plan, Unsettled};

fn offer(score: f64) -> PoolOp {
    PoolOp::Offer {
        actions: ActionSeq::Discrete(vec![0]),
        score,
        end: None,
    }
}

/// A score: continuous, or one of a few values (ties, where §6's "strictly greater"
/// decides).
fn score() -> impl Strategy<Value = f64> {
    prop_oneof![0.0..10.0f64, (0u8..4).prop_map(f64::from)]
}

/// Another client's change: an offer of this score, or (`None`) a reset.
fn other() -> impl Strategy<Value = Option<f64>> {
    prop_oneof![6 => score().prop_map(Some), 1 => Just(None)]
}

/// The learner plans `batches` on `start` while the rule lets it answer them with their
/// plans; the messages sent and the versions answered.
fn answered(start: &Pool, batches: Vec<Vec<f64>>) -> Vec<(Vec<PoolOp>, u64)> {
    let mut unsettled = Unsettled::default();
    let mut copy = Arc::new(start.clone());
    let mut sent = Vec::new();
    for scores in batches {
        let ops: Vec<PoolOp> = scores.into_iter().map(offer).collect();
        let plan = Plan::new(copy.clone(), &ops);
        if !unsettled.may_plan(&plan) {
            break; // this batch would wait for the server
        }
        let version = plan.planned.version();
        let (_reply, answer) = oneshot::channel();
        let committed = unsettled.plan(answer, plan);
        assert_eq!(committed.version, version);
        sent.push((ops, committed.version));
        copy = committed.pool;
    }
    sent
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]

    #[test]
    fn a_plan_never_reports_a_version_the_server_stays_below(
        capacity in 1usize..24,
        initial in vec(score(), 0..24),
        batches in vec(vec(score(), 1..5), 1..8),
        // Others' changes, each made before our message of that index (or after all).
        others in vec((0usize..8, other()), 0..10),
    ) {
        let start = apply_ops(&Pool::new(capacity), initial.into_iter().map(offer).collect()).0;
        let sent = answered(&start, batches);
        // The server: decides every message in order, others' changes in between.
        let mut server = start;
        let alone = others.iter().all(|&(at, _)| at >= sent.len());
        for (i, (ops, planned_version)) in sent.into_iter().enumerate() {
            for &(_, change) in others.iter().filter(|&&(at, _)| at == i) {
                let op = change.map_or(PoolOp::Reset, offer);
                server = apply_ops(&server, vec![op]).0;
            }
            server = apply_ops(&server, ops).0;
            prop_assert!(
                server.version() >= planned_version,
                "message {}: the server at {}, the plan at {}", i, server.version(), planned_version
            );
            if alone {
                prop_assert_eq!(server.version(), planned_version);
            }
        }
    }
}

/// A full pool of low scores: replacements that each beat most of it are answered with
/// their plans, several unanswered at once.
#[test]
fn replacements_of_much_lower_scores_need_not_wait() {
    let start = apply_ops(
        &Pool::new(20),
        (0..20).map(|i| offer(f64::from(i))).collect(),
    )
    .0;
    let sent = answered(&start, vec![vec![30.0, 31.0], vec![32.0], vec![33.0]]);
    assert_eq!(sent.len(), 3, "all three batches answered with their plans");
    assert_eq!(sent[2].1, start.version() + 4);
}

/// Replacements that barely beat the lowest score wait: one change of another learner
/// could make the server refuse both.
#[test]
fn replacements_of_the_lowest_scores_wait() {
    let start = apply_ops(
        &Pool::new(20),
        (0..20).map(|i| offer(f64::from(i))).collect(),
    )
    .0;
    let sent = answered(&start, vec![vec![0.5], vec![0.7]]);
    assert_eq!(
        sent.len(),
        1,
        "the second replacement waits for the first's ack"
    );
}

/// A small pool: with the ends unanswered and as many changes of others (a reset among
/// them) it could fill up again, so the second replacement waits however high it scores.
#[test]
fn in_a_small_pool_a_second_replacement_after_more_ends_waits() {
    let start = apply_ops(&Pool::new(2), vec![offer(0.0), offer(1.0)]).0;
    assert_eq!(answered(&start, vec![vec![10.0], vec![11.0]]).len(), 2);
    assert_eq!(
        answered(&start, vec![vec![10.0], vec![-1.0, 11.0]]).len(),
        1
    );
}
