//! The episode ends a local session committed without waiting for their acks, and the
//! rule that says when a commit may be answered with its own plan ([`Unsettled::may_plan`];
//! why it keeps pool versions from going down: docs/decisions, "A local session's episode
//! end is acknowledged in the background").

use std::collections::VecDeque;
use std::sync::Arc;

use tamrm::core::Pool;
use tamrm::store::{apply_ops, Committed, PoolOp};
use tonic::Status;

use super::driver::Answer;

/// A commit's ends as the learner plans them on its copy (SPEC §6), before the server
/// decides them.
pub(super) struct Plan {
    /// The copy the ends were planned against.
    pub(super) base: Arc<Pool>,
    pub(super) planned: Pool,
    /// Per end, whether the plan changes the pool with it.
    pub(super) changed: Vec<bool>,
    /// How many changes of others each planned change outlasts (the least over them,
    /// `usize::MAX` with none): the free slots and the trajectories of lower score in
    /// the copy it meets. Each change of another learner takes at most one of them, so
    /// with fewer of those than this before it, the server makes the change too.
    margin: usize,
}

impl Plan {
    /// Plans `ops` on `base`.
    pub(super) fn new(base: Arc<Pool>, ops: &[PoolOp]) -> Plan {
        let (planned, changed) = apply_ops(&base, ops.to_vec());
        let margin = margin(&base, ops, &changed);
        Plan {
            base,
            planned,
            changed,
            margin,
        }
    }

    /// The changes it plans.
    pub(super) fn changes(&self) -> usize {
        self.changed.iter().filter(|&&c| c).count()
    }

    /// Whether every change it plans is an insert (an insert adds a trajectory, a
    /// replacement keeps the count).
    fn inserts_only(&self) -> bool {
        self.planned.len().saturating_sub(self.base.len()) == self.changes()
    }
}

/// [`Plan::margin`]: §6 played on the scores alone (which of equal lowest scores a
/// replacement removes does not matter to the scores that remain).
fn margin(base: &Pool, ops: &[PoolOp], changed: &[bool]) -> usize {
    if !changed.contains(&true) {
        return usize::MAX;
    }
    let capacity = base.capacity();
    let mut scores: Vec<f64> = base.trajectories().iter().map(|t| t.score).collect();
    scores.sort_by(f64::total_cmp);
    let mut least = usize::MAX;
    for (op, &change) in ops.iter().zip(changed) {
        let PoolOp::Offer { score, .. } = *op else {
            // (A local session commits only offers; a reset outlasts nothing.)
            return 0;
        };
        let below = scores.partition_point(|&s| s < score);
        if change {
            least = least.min(capacity - scores.len() + below);
            if scores.len() == capacity {
                scores.remove(0);
            }
            let at = scores.partition_point(|&s| s < score);
            scores.insert(at, score);
        }
    }
    least
}

/// An end (a message of ends) committed without waiting for its ack, and what the
/// learner planned of it.
pub(super) struct InFlight {
    pub(super) answer: Answer,
    /// The planned outcome of each end (whether it changed the pool)...
    pub(super) changed: Vec<bool>,
    /// ...and the version the plan reached: the ack must say the same, or the learner's
    /// copy went its own way (another learner's change came first at the server).
    pub(super) version: u64,
    /// The pool the plan reached: the next plan continues from it or not.
    pool: Arc<Pool>,
    /// Every change it planned is an insert (none replaces a trajectory).
    inserts_only: bool,
    /// [`Plan::margin`].
    margin: usize,
}

impl InFlight {
    fn changes(&self) -> usize {
        self.changed.iter().filter(|&&c| c).count()
    }
}

/// The ends committed without waiting for their acks, in the order they were sent.
#[derive(Default)]
pub(super) struct Unsettled {
    pub(super) in_flight: VecDeque<InFlight>,
    /// The first failure of one of them not yet reported (for the session's next step).
    pub(super) failed: Option<Status>,
    /// An ack did not match its plan (or an end failed): the learner's copy holds a change
    /// the server did not make, and takes the server's pool once nothing is in flight.
    pub(super) diverged: bool,
}

impl Unsettled {
    /// The changes planned by the ends still in flight.
    pub(super) fn changes(&self) -> usize {
        self.in_flight.iter().map(InFlight::changes).sum()
    }

    /// Whether `plan` may be answered before the server's ack, so that whatever the
    /// server decides (other learners' changes may come first) its version after these
    /// ends is never below the plan's. So it is when the copy has not diverged and
    /// - at most one planned change is unanswered: others' changes only add versions, and
    ///   the one change the server might decide otherwise is matched by the other's that
    ///   made it do so; or
    /// - every unanswered change is an insert (the copy had room): a pool with room takes
    ///   every end (SPEC §6), and each change of others takes at most one slot, so it
    ///   makes the server refuse at most one of these inserts and adds a version of its
    ///   own; or
    /// - the plan continues the plans in flight, and each of the `u` unanswered changes
    ///   outlasts `u` changes of others ([`Plan::margin`]): with fewer than `u` of those
    ///   the server makes every one of them, with `u` or more it is at least as far; and
    ///   the pool has room for more than the unanswered ends and `u` together, so that
    ///   after a reset (a change of others too) it takes every end that follows.
    pub(super) fn may_plan(&self, plan: &Plan) -> bool {
        if self.diverged {
            return false;
        }
        let u = self.changes() + plan.changes();
        // (Ends that change nothing come after every unanswered change: they can only
        // add versions.)
        if plan.changes() == 0
            || u <= 1
            || (plan.inserts_only() && self.in_flight.iter().all(|f| f.inserts_only))
        {
            return true;
        }
        let continues = self
            .in_flight
            .back()
            .is_none_or(|f| Arc::ptr_eq(&f.pool, &plan.base));
        let ends = self
            .in_flight
            .iter()
            .map(|f| f.changed.len())
            .sum::<usize>()
            + plan.changed.len();
        continues
            && u + ends <= plan.base.capacity() + 2
            && plan.margin >= u
            && self.in_flight.iter().all(|f| f.margin >= u)
    }

    /// Keeps ends answered with their plan while their ack travels; their commit as the
    /// session takes it.
    pub(super) fn plan(&mut self, answer: Answer, plan: Plan) -> Committed {
        let inserts_only = plan.inserts_only();
        let pool = Arc::new(plan.planned);
        self.in_flight.push_back(InFlight {
            answer,
            changed: plan.changed.clone(),
            version: pool.version(),
            pool: pool.clone(),
            inserts_only,
            margin: plan.margin,
        });
        Committed {
            version: pool.version(),
            pool,
            changed: plan.changed,
            resent: 0,
        }
    }
}

#[cfg(test)]
mod tests;
