//! The memory pool D of one task and its update rule (SPEC §6).
//!
//! A pool is changed in two phases so that storage can make a change durable before
//! anyone sees it: [`Pool::plan_offer`] / [`Pool::plan_reset`] describe the change
//! without touching the pool, [`Pool::apply`] performs it.

use std::sync::Arc;

use super::actions::ActionSeq;

/// One stored episode: its recorded actions, its score and its insertion number.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// a_0 … a_{L-1}, L ≥ 1.
    pub actions: ActionSeq,
    /// Episode score S (finite).
    pub score: f64,
    /// Insertion number, strictly increasing per task.
    pub seq: u64,
}

/// A planned change to a pool.
#[derive(Debug, Clone, PartialEq)]
pub enum PoolChange {
    /// Store `trajectory` (whose `seq` is already assigned), removing the trajectory with
    /// seq `replaces` if the pool is full.
    Insert {
        /// The new trajectory.
        trajectory: Arc<Trajectory>,
        /// The seq of the trajectory it replaces, if any.
        replaces: Option<u64>,
    },
    /// Remove every trajectory.
    Reset,
}

/// The memory pool of a task: at most `capacity` trajectories ordered by `seq`, with the
/// derived quantities every step needs (lengths, L_min, normalised scores) kept up to date.
#[derive(Debug, Clone)]
pub struct Pool {
    capacity: usize,
    trajectories: Vec<Arc<Trajectory>>,
    seqs: Vec<u64>,
    lens: Vec<usize>,
    xs: Vec<f64>,
    l_min: usize,
    /// The trajectories (indices) in the order x descending, then seq ascending (the
    /// order that breaks ties in P), so that a step need not sort by it.
    by_place: Vec<u32>,
    /// The inverse of `by_place`: each trajectory's place in that order.
    place_of: Vec<u32>,
    /// For a discrete pool, the actions laid out by step: row t holds every trajectory's
    /// action at t (in pool order), [`NO_ACTION`] where t ≥ L_i; `step_rows` rows. Empty
    /// (0 rows) if some trajectory is continuous or the padding would be too large.
    by_step: Arc<[u32]>,
    step_rows: usize,
    version: u64,
    next_seq: u64,
}

/// The entry of [`Pool::step_row`] for a trajectory that has no action at that step (no
/// valid discrete action equals it: actions are `< num_actions ≤ u32::MAX`).
pub(crate) const NO_ACTION: u32 = u32::MAX;

impl Pool {
    /// An empty pool of the given capacity (≥ 1).
    pub fn new(capacity: usize) -> Pool {
        Pool {
            capacity,
            trajectories: Vec::new(),
            seqs: Vec::new(),
            lens: Vec::new(),
            xs: Vec::new(),
            l_min: 0,
            by_place: Vec::new(),
            place_of: Vec::new(),
            by_step: Arc::from(Vec::new()),
            step_rows: 0,
            version: 0,
            next_seq: 1,
        }
    }

    /// Rebuilds a pool from stored parts, checking the invariants a well-formed pool has:
    /// at most `capacity` non-empty trajectories, seqs strictly increasing and below
    /// `next_seq`, finite scores.
    pub fn restore(
        capacity: usize,
        mut trajectories: Vec<Trajectory>,
        version: u64,
        next_seq: u64,
    ) -> Result<Pool, String> {
        if trajectories.len() > capacity {
            return Err(format!(
                "{} trajectories exceed pool_capacity {capacity}",
                trajectories.len()
            ));
        }
        trajectories.sort_by_key(|t| t.seq);
        for w in trajectories.windows(2) {
            if w[0].seq == w[1].seq {
                return Err(format!("duplicate trajectory seq {}", w[0].seq));
            }
        }
        for t in &trajectories {
            if t.seq >= next_seq {
                return Err(format!("trajectory seq {} >= next_seq {next_seq}", t.seq));
            }
            if t.actions.is_empty() {
                return Err(format!("trajectory seq {} has no actions", t.seq));
            }
            if !t.score.is_finite() {
                return Err(format!("trajectory seq {} has a non-finite score", t.seq));
            }
        }
        let mut pool = Pool::new(capacity);
        pool.trajectories = trajectories.into_iter().map(Arc::new).collect();
        pool.version = version;
        pool.next_seq = next_seq;
        pool.recompute();
        Ok(pool)
    }

    fn recompute(&mut self) {
        self.seqs = self.trajectories.iter().map(|t| t.seq).collect();
        self.lens = self.trajectories.iter().map(|t| t.actions.len()).collect();
        self.l_min = self.lens.iter().copied().min().unwrap_or(0);
        let (lo, hi) = self.score_range().unwrap_or((0.0, 0.0));
        self.xs = self
            .trajectories
            .iter()
            .map(|t| {
                if hi == lo {
                    1.0
                } else if (hi - lo).is_finite() {
                    (t.score - lo) / (hi - lo)
                } else {
                    // Finite scores whose range overflows f64 (e.g. ±1e308): the same
                    // ratio, halved to stay finite.
                    (t.score * 0.5 - lo * 0.5) / (hi * 0.5 - lo * 0.5)
                }
            })
            .collect();
        let mut idx: Vec<usize> = (0..self.xs.len()).collect();
        idx.sort_unstable_by(|&a, &b| {
            self.xs[b]
                .total_cmp(&self.xs[a])
                .then_with(|| self.seqs[a].cmp(&self.seqs[b]))
        });
        self.by_place = idx.iter().map(|&i| i as u32).collect();
        self.place_of = vec![0; idx.len()];
        for (place, &i) in idx.iter().enumerate() {
            self.place_of[i] = place as u32;
        }
        self.build_by_step();
    }

    /// Lays the actions of a discrete pool out by step (see `by_step`), unless the pool
    /// holds continuous actions or rows padded to the longest trajectory would take more
    /// than twice the actions themselves (plus a little).
    fn build_by_step(&mut self) {
        let n = self.trajectories.len();
        let l_max = self.lens.iter().copied().max().unwrap_or(0);
        let total: usize = self.lens.iter().sum();
        let discrete = self
            .trajectories
            .iter()
            .all(|t| matches!(t.actions, ActionSeq::Discrete(_)));
        let cells = n.saturating_mul(l_max);
        if !discrete || n > u32::MAX as usize || cells > total.saturating_mul(2) + (1 << 16) {
            self.by_step = Arc::from(Vec::new());
            self.step_rows = 0;
            return;
        }
        let mut rows = vec![NO_ACTION; cells];
        for (i, traj) in self.trajectories.iter().enumerate() {
            if let ActionSeq::Discrete(v) = &traj.actions {
                for (t, &a) in v.iter().enumerate() {
                    rows[t * n + i] = a;
                }
            }
        }
        self.by_step = Arc::from(rows);
        self.step_rows = l_max;
    }

    /// The change that offering an episode with these actions and this score would make:
    /// insert while not full, else replace the lowest score (lowest seq among equals) if
    /// `score` is strictly greater, else `None` (discarded). The actions must be non-empty.
    ///
    /// A non-finite score (only possible as an overflowing sum of finite rewards) is
    /// discarded: normalised scores would be undefined.
    pub fn plan_offer(&self, actions: ActionSeq, score: f64) -> Option<PoolChange> {
        if !score.is_finite() {
            return None;
        }
        let replaces = if self.trajectories.len() < self.capacity {
            None
        } else {
            // Lowest score; among equal scores the first in seq order, i.e. the lowest seq.
            let worst = self
                .trajectories
                .iter()
                .reduce(|a, b| if b.score < a.score { b } else { a })?;
            if score > worst.score {
                Some(worst.seq)
            } else {
                return None;
            }
        };
        Some(PoolChange::Insert {
            trajectory: Arc::new(Trajectory {
                actions,
                score,
                seq: self.next_seq,
            }),
            replaces,
        })
    }

    /// The change that `ResetPool` makes.
    pub fn plan_reset(&self) -> PoolChange {
        PoolChange::Reset
    }

    /// Performs a planned change and increments the version.
    pub fn apply(&mut self, change: &PoolChange) {
        match change {
            PoolChange::Insert {
                trajectory,
                replaces,
            } => {
                if let Some(seq) = replaces {
                    self.trajectories.retain(|t| t.seq != *seq);
                }
                self.next_seq = self.next_seq.max(trajectory.seq + 1);
                self.trajectories.push(trajectory.clone());
                self.trajectories.sort_by_key(|t| t.seq);
            }
            PoolChange::Reset => self.trajectories.clear(),
        }
        self.version += 1;
        self.recompute();
    }

    /// |D| at most.
    pub fn capacity(&self) -> usize {
        self.capacity
    }
    /// Trajectories stored now.
    pub fn len(&self) -> usize {
        self.trajectories.len()
    }
    /// Whether the pool is empty.
    pub fn is_empty(&self) -> bool {
        self.trajectories.is_empty()
    }
    /// The stored trajectories, by seq.
    pub fn trajectories(&self) -> &[Arc<Trajectory>] {
        &self.trajectories
    }
    /// Seqs, aligned with [`Pool::trajectories`].
    pub fn seqs(&self) -> &[u64] {
        &self.seqs
    }
    /// Lengths L_i, aligned with [`Pool::trajectories`].
    pub fn lens(&self) -> &[usize] {
        &self.lens
    }
    /// Normalised scores x_i (SPEC §3.2), aligned with [`Pool::trajectories`].
    pub fn xs(&self) -> &[f64] {
        &self.xs
    }
    /// The trajectories (indices) in the order x descending, then seq ascending.
    pub(crate) fn by_place(&self) -> &[u32] {
        &self.by_place
    }
    /// Each trajectory's place in [`Pool::by_place`], aligned with [`Pool::trajectories`].
    pub(crate) fn place_of(&self) -> &[u32] {
        &self.place_of
    }
    /// For a pool laid out by step ([`Pool::by_step`]): every trajectory's action at step
    /// `t` ([`NO_ACTION`] where t ≥ L_i), aligned with [`Pool::trajectories`]; `None` past
    /// the longest trajectory or if the pool is not laid out by step.
    pub(crate) fn step_row(&self, t: usize) -> Option<&[u32]> {
        let n = self.trajectories.len();
        if t < self.step_rows {
            self.by_step.get(t * n..(t + 1) * n)
        } else {
            None
        }
    }
    /// Whether the pool is laid out by step ([`Pool::step_row`]): all discrete, rows
    /// past the longest trajectory absent (no trajectory has an action there).
    pub(crate) fn by_step(&self) -> bool {
        self.step_rows > 0 || self.trajectories.is_empty()
    }
    /// L_min, 0 if empty.
    pub fn l_min(&self) -> usize {
        self.l_min
    }
    /// Incremented by every applied change.
    pub fn version(&self) -> u64 {
        self.version
    }
    /// The seq the next inserted trajectory gets.
    pub fn next_seq(&self) -> u64 {
        self.next_seq
    }
    /// (S_min, S_max), `None` if empty.
    pub fn score_range(&self) -> Option<(f64, f64)> {
        let mut it = self.trajectories.iter().map(|t| t.score);
        let first = it.next()?;
        Some(it.fold((first, first), |(lo, hi), s| (lo.min(s), hi.max(s))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn acts(v: &[u32]) -> ActionSeq {
        ActionSeq::Discrete(v.to_vec())
    }

    fn offer(pool: &mut Pool, len: usize, score: f64) -> Option<PoolChange> {
        let change = pool.plan_offer(acts(&vec![0; len]), score);
        if let Some(c) = &change {
            pool.apply(c);
        }
        change
    }

    #[test]
    fn inserts_until_full_then_replaces_strictly_better() {
        let mut p = Pool::new(2);
        assert!(offer(&mut p, 3, 1.0).is_some());
        assert!(offer(&mut p, 4, 1.0).is_some());
        assert_eq!(p.version(), 2);
        // Equal to the minimum: discarded, version unchanged.
        assert!(offer(&mut p, 5, 1.0).is_none());
        assert_eq!(p.version(), 2);
        // Better: replaces the lowest seq among the equal minima (seq 1).
        let c = offer(&mut p, 5, 2.0).unwrap();
        assert!(matches!(
            c,
            PoolChange::Insert {
                replaces: Some(1),
                ..
            }
        ));
        assert_eq!(p.seqs(), &[2, 3]);
        assert_eq!(p.l_min(), 4);
        assert_eq!(p.version(), 3);
    }

    #[test]
    fn normalised_scores_and_equal_scores() {
        let mut p = Pool::new(3);
        offer(&mut p, 1, 5.0);
        assert_eq!(p.xs(), &[1.0]);
        offer(&mut p, 1, 1.0);
        offer(&mut p, 1, 2.0);
        assert_eq!(p.xs(), &[1.0, 0.0, 0.25]);
        assert_eq!(p.score_range(), Some((1.0, 5.0)));
    }

    #[test]
    fn reset_empties_and_bumps_version_but_not_seq() {
        let mut p = Pool::new(3);
        offer(&mut p, 2, 1.0);
        p.apply(&p.plan_reset());
        assert!(p.is_empty());
        assert_eq!(p.version(), 2);
        assert_eq!(p.l_min(), 0);
        offer(&mut p, 2, 1.0);
        assert_eq!(p.seqs(), &[2]);
    }

    #[test]
    fn restore_rejects_malformed_pools() {
        let t = |seq| Trajectory {
            actions: acts(&[0]),
            score: 0.0,
            seq,
        };
        assert!(Pool::restore(1, vec![t(1), t(2)], 2, 3).is_err());
        assert!(Pool::restore(2, vec![t(1), t(1)], 2, 3).is_err());
        assert!(Pool::restore(2, vec![t(5)], 1, 3).is_err());
        let p = Pool::restore(2, vec![t(2), t(1)], 7, 3).unwrap();
        assert_eq!(p.seqs(), &[1, 2]);
        assert_eq!(p.version(), 7);
    }
}
