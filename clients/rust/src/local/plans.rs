//! The episode ends a local session committed without waiting for their acks, and the
//! rule that says when a commit may be answered with its own plan ([`Unsettled::may_plan`];
//! why it keeps pool versions from going down: docs/decisions, "A local session's episode
//! end is acknowledged in the background").

use std::collections::VecDeque;
use std::sync::Arc;

use tamrm::core::Pool;
use tamrm::store::Committed;
use tonic::Status;

use super::driver::Answer;

/// An end (a message of ends) committed without waiting for its ack, and what the
/// learner planned of it.
pub(super) struct InFlight {
    pub(super) answer: Answer,
    /// The planned outcome of each end (whether it changed the pool)...
    pub(super) changed: Vec<bool>,
    /// ...and the version the plan reached: the ack must say the same, or the learner's
    /// copy went its own way (another learner's change came first at the server).
    pub(super) version: u64,
    /// Every change it planned is an insert (none replaces a trajectory).
    inserts_only: bool,
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

    /// Whether ends whose plan took `base` to `planned` with `changes` changes may be
    /// answered with that plan before the server's ack, so that whatever the server
    /// decides (other learners' changes may come first) its version after them is never
    /// below the plan's. So it is when the copy has not diverged and either
    /// - at most one planned change is unanswered: others' changes only add versions, and
    ///   the one change the server might decide otherwise is matched by the other's that
    ///   made it do so; or
    /// - every unanswered change is an insert (the copy had room): a pool with room takes
    ///   every end (SPEC §6), and each change of others takes at most one slot, so it
    ///   makes the server refuse at most one of these inserts and adds a version of its
    ///   own.
    pub(super) fn may_plan(&self, base: &Pool, planned: &Pool, changes: usize) -> bool {
        if self.diverged {
            return false;
        }
        self.changes() + changes <= 1
            || (inserts_only(base, planned, changes)
                && self.in_flight.iter().all(|f| f.inserts_only))
    }

    /// Keeps ends answered with their plan (`base` to `planned`) while their ack
    /// travels; their commit as the session takes it.
    pub(super) fn plan(
        &mut self,
        answer: Answer,
        base: &Pool,
        planned: Pool,
        changed: Vec<bool>,
    ) -> Committed {
        let changes = changed.iter().filter(|&&c| c).count();
        let pool = Arc::new(planned);
        self.in_flight.push_back(InFlight {
            answer,
            changed: changed.clone(),
            version: pool.version(),
            inserts_only: inserts_only(base, &pool, changes),
        });
        Committed {
            version: pool.version(),
            pool,
            changed,
            resent: 0,
        }
    }
}

/// Whether every one of the `changes` changes from `base` to `planned` is an insert (an
/// insert adds a trajectory, a replacement keeps the count).
fn inserts_only(base: &Pool, planned: &Pool, changes: usize) -> bool {
    planned.len().saturating_sub(base.len()) == changes
}

#[cfg(test)]
mod tests;
