//! [`Unsettled::may_plan`] against a server simulated from SPEC §6: whatever others
//! change first, and wherever, the server's version after each end answered with its
//! plan is never below the plan's; with no one else, it is the plan's.

use proptest::collection::vec;
use proptest::prelude::*;
use tamrm::core::{ActionSeq, Pool};
use tamrm::store::{apply_ops, PoolOp};
use tokio::sync::oneshot;

use super::Unsettled;

fn offer(score: f64) -> PoolOp {
    PoolOp::Offer {
        actions: ActionSeq::Discrete(vec![0]),
        score,
        end: None,
    }
}

/// Another client's change: an offer of this score, or (`None`) a reset.
fn other() -> impl Strategy<Value = Option<f64>> {
    prop_oneof![4 => (0.0..10.0f64).prop_map(Some), 1 => Just(None)]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn a_plan_never_reports_a_version_the_server_stays_below(
        capacity in 1usize..8,
        initial in vec(0.0..10.0f64, 0..8),
        batches in vec(vec(0.0..10.0f64, 1..4), 1..5),
        // Others' changes, each made before our message of that index (or after all).
        others in vec((0usize..5, other()), 0..6),
    ) {
        let start = apply_ops(&Pool::new(capacity), initial.into_iter().map(offer).collect()).0;
        // The learner: plans its batches on its copy while they may be answered so.
        let mut unsettled = Unsettled::default();
        let mut copy = start.clone();
        let mut sent = Vec::new();
        for scores in batches {
            let ops: Vec<PoolOp> = scores.into_iter().map(offer).collect();
            let (planned, changed) = apply_ops(&copy, ops.clone());
            let changes = changed.iter().filter(|&&c| c).count();
            if !unsettled.may_plan(&copy, &planned, changes) {
                break; // this batch would wait for the server
            }
            let (_reply, answer) = oneshot::channel();
            let committed = unsettled.plan(answer, &copy, planned.clone(), changed);
            prop_assert_eq!(committed.version, planned.version());
            sent.push((ops, committed.version));
            copy = planned;
        }
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
