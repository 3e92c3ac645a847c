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
    by_step: Arc<Vec<u32>>,
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
            by_step: Arc::default(),
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
        trajectories: Vec<Trajectory>,
        version: u64,
        next_seq: u64,
    ) -> Result<Pool, String> {
        let trajectories = trajectories.into_iter().map(Arc::new).collect();
        Pool::from_parts(capacity, trajectories, version, next_seq)
    }

    /// [`Pool::restore`] from shared trajectories.
    fn from_parts(
        capacity: usize,
        mut trajectories: Vec<Arc<Trajectory>>,
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
        pool.trajectories = trajectories;
        pool.version = version;
        pool.next_seq = next_seq;
        pool.recompute();
        Ok(pool)
    }

    /// What changed from this pool to `newer`, a later version of the same task's pool
    /// (SPEC §13 updates): the seqs of the trajectories it no longer has, and the
    /// trajectories it gained, both by seq.
    pub fn diff(&self, newer: &Pool) -> (Vec<u64>, Vec<Arc<Trajectory>>) {
        let (old, new) = (&self.seqs, &newer.seqs);
        let (mut removed, mut added) = (Vec::new(), Vec::new());
        let (mut i, mut j) = (0, 0);
        // Both are ordered by seq: one merge walk.
        while i < old.len() || j < new.len() {
            match (old.get(i), new.get(j)) {
                (Some(a), Some(b)) if a == b => (i, j) = (i + 1, j + 1),
                (Some(a), Some(b)) if a < b => {
                    removed.push(*a);
                    i += 1;
                }
                (Some(a), None) => {
                    removed.push(*a);
                    i += 1;
                }
                _ => {
                    added.push(newer.trajectories[j].clone());
                    j += 1;
                }
            }
        }
        (removed, added)
    }

    /// This pool with an update applied (what [`Pool::diff`] gave to this pool's
    /// version): the trajectories of `removed` seqs gone, `added` in, at `version` and
    /// `next_seq`. The result is checked as [`Pool::restore`] checks; a seq in `removed`
    /// that the pool does not hold, or an added seq it already holds, is an error.
    pub fn with_update(
        &self,
        removed: &[u64],
        added: Vec<Arc<Trajectory>>,
        version: u64,
        next_seq: u64,
    ) -> Result<Pool, String> {
        if let Some(seq) = removed.iter().find(|s| !self.seqs.contains(s)) {
            return Err(format!(
                "the update removes seq {seq}, which the pool does not hold"
            ));
        }
        let mut trajectories: Vec<Arc<Trajectory>> = self
            .trajectories
            .iter()
            .filter(|t| !removed.contains(&t.seq))
            .cloned()
            .collect();
        trajectories.extend(added);
        Pool::from_parts(self.capacity, trajectories, version, next_seq)
    }

    fn recompute(&mut self) {
        self.recompute_derived();
        self.build_by_step();
    }

    /// Everything derived from the trajectories but the by-step layout.
    fn recompute_derived(&mut self) {
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
    }

    /// The discrete trajectories' actions, if every trajectory is discrete and rows padded
    /// to the longest one would take at most twice the actions themselves (plus a
    /// little): the condition for laying the pool out by step.
    fn step_columns(&self) -> Option<Vec<&[u32]>> {
        let n = self.trajectories.len();
        let l_max = self.lens.iter().copied().max().unwrap_or(0);
        let total: usize = self.lens.iter().sum();
        let cells = n.saturating_mul(l_max);
        if n > u32::MAX as usize || cells > total.saturating_mul(2) + (1 << 16) {
            return None;
        }
        self.trajectories
            .iter()
            .map(|t| match &t.actions {
                ActionSeq::Discrete(v) => Some(v.as_slice()),
                ActionSeq::Continuous { .. } => None,
            })
            .collect()
    }

    /// Lays the actions of a discrete pool out by step (see `by_step`), unless
    /// [`Pool::step_columns`] says not to. Row by row: the writes are sequential.
    fn build_by_step(&mut self) {
        let Some(cols) = self.step_columns() else {
            self.by_step = Arc::default();
            self.step_rows = 0;
            return;
        };
        let l_max = self.lens.iter().copied().max().unwrap_or(0);
        let mut rows = Vec::with_capacity(cols.len() * l_max);
        for t in 0..l_max {
            rows.extend(cols.iter().map(|c| c.get(t).copied().unwrap_or(NO_ACTION)));
        }
        self.by_step = Arc::new(rows);
        self.step_rows = l_max;
    }

    /// The by-step layout after an insert that appended the last trajectory and, if
    /// `removed` is set, removed the one at that index, from the layout before it (`old`,
    /// `old_rows` rows of `old_n`): its rows without the removed column, plus the new
    /// one. The same cells as [`Pool::build_by_step`], copied a row at a time.
    fn update_by_step(
        &mut self,
        old: &[u32],
        old_n: usize,
        old_rows: usize,
        removed: Option<usize>,
    ) {
        let n = self.trajectories.len();
        let laid_out = old_rows > 0 || old_n == 0;
        let (Some(cols), true) = (self.step_columns(), laid_out) else {
            return self.build_by_step();
        };
        let (Some(&new), Some(p)) = (cols.last(), removed.or(Some(old_n))) else {
            return self.build_by_step();
        };
        if n != old_n + 1 - usize::from(removed.is_some()) || p > old_n {
            return self.build_by_step();
        }
        let l_max = self.lens.iter().copied().max().unwrap_or(0);
        let mut rows = Vec::with_capacity(n * l_max);
        for t in 0..l_max {
            match old.get(t * old_n..(t + 1) * old_n).filter(|_| t < old_rows) {
                Some(row) => {
                    rows.extend_from_slice(&row[..p]);
                    rows.extend_from_slice(row.get(p + 1..).unwrap_or_default());
                }
                None => rows.resize(rows.len() + n - 1, NO_ACTION),
            }
            rows.push(new.get(t).copied().unwrap_or(NO_ACTION));
        }
        self.by_step = Arc::new(rows);
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
        self.apply_with(change, true);
    }

    /// [`Pool::apply`] without laying the pool out by step: the same pool, whose steps
    /// read each trajectory's action from its own sequence. For a private copy that
    /// serves a few steps (the rest of a batch after an episode end) before the store's
    /// pool replaces it: laying out costs O(|D| × L_max).
    pub fn apply_without_layout(&mut self, change: &PoolChange) {
        self.apply_with(change, false);
    }

    /// Lays the pool out by step after changes applied to `before` with
    /// [`Pool::apply_without_layout`]: the pool [`Pool::apply`] would have made of them,
    /// for the cost of one change. From `before`'s layout when it has one: its rows
    /// without the columns of the trajectories that left, plus the new ones (inserts
    /// append: seqs increase), copied a row at a time; the same cells as
    /// [`Pool::build_by_step`].
    pub fn lay_out_from(&mut self, before: &Pool) {
        let old_n = before.trajectories.len();
        let laid_out = before.step_rows > 0 || old_n == 0;
        let Some(cols) = self.step_columns().filter(|_| laid_out) else {
            return self.build_by_step();
        };
        // The trajectories `before` still has here come first, in order; the rest are new.
        let mut kept = Vec::with_capacity(old_n);
        for (i, seq) in before.seqs.iter().enumerate() {
            if self.seqs.get(kept.len()) == Some(seq) {
                kept.push(i);
            }
        }
        let fresh = kept.len();
        if self.seqs[fresh..].iter().any(|&s| s < before.next_seq) {
            return self.build_by_step();
        }
        // Runs of consecutive kept columns, each copied as one slice.
        let runs: Vec<(usize, usize)> = kept
            .chunk_by(|a, b| b == &(a + 1))
            .map(|run| (run[0], run[run.len() - 1] + 1))
            .collect();
        let n = self.trajectories.len();
        let l_max = self.lens.iter().copied().max().unwrap_or(0);
        let mut rows = Vec::with_capacity(n * l_max);
        for t in 0..l_max {
            let old_row = before
                .by_step
                .get(t * old_n..(t + 1) * old_n)
                .filter(|_| t < before.step_rows);
            match old_row {
                Some(row) => runs
                    .iter()
                    .for_each(|&(a, b)| rows.extend_from_slice(&row[a..b])),
                None => rows.resize(rows.len() + fresh, NO_ACTION),
            }
            rows.extend(
                cols[fresh..]
                    .iter()
                    .map(|c| c.get(t).copied().unwrap_or(NO_ACTION)),
            );
        }
        self.by_step = Arc::new(rows);
        self.step_rows = l_max;
    }

    fn apply_with(&mut self, change: &PoolChange, lay_out: bool) {
        match change {
            PoolChange::Insert {
                trajectory,
                replaces,
            } => {
                let old_n = self.trajectories.len();
                let removed = replaces.and_then(|seq| self.seqs.iter().position(|&s| s == seq));
                if let Some(seq) = replaces {
                    self.trajectories.retain(|t| t.seq != *seq);
                }
                self.next_seq = self.next_seq.max(trajectory.seq + 1);
                // Seqs increase: the new trajectory is normally the last one.
                let last = self
                    .trajectories
                    .last()
                    .is_none_or(|t| t.seq < trajectory.seq);
                self.trajectories.push(trajectory.clone());
                self.trajectories.sort_by_key(|t| t.seq);
                self.version += 1;
                self.recompute_derived();
                let old = std::mem::take(&mut self.by_step);
                if !lay_out {
                    self.step_rows = 0;
                } else if last && removed.is_some() == replaces.is_some() {
                    self.update_by_step(&old, old_n, self.step_rows, removed);
                } else {
                    self.build_by_step();
                }
            }
            PoolChange::Reset => {
                self.trajectories.clear();
                self.version += 1;
                self.recompute();
            }
        }
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
    fn the_by_step_layout_after_a_change_is_the_one_built_from_scratch() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = |m: u64| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state % m
        };
        for capacity in [1, 2, 5, 30] {
            let mut p = Pool::new(capacity);
            for _ in 0..200 {
                // Lengths up to 3000 with a few short ones: some pools are too ragged to
                // lay out, and the longest trajectory is sometimes the one replaced.
                let len = if next(4) == 0 {
                    1 + next(5)
                } else {
                    1 + next(3000)
                } as usize;
                let actions = (0..len).map(|_| next(3) as u32).collect();
                if let Some(c) = p.plan_offer(ActionSeq::Discrete(actions), next(50) as f64) {
                    let mut unlaid = p.clone();
                    unlaid.apply_without_layout(&c);
                    p.apply(&c);
                    assert_eq!(
                        (
                            unlaid.version(),
                            unlaid.seqs(),
                            unlaid.lens(),
                            unlaid.l_min()
                        ),
                        (p.version(), p.seqs(), p.lens(), p.l_min())
                    );
                    assert_eq!((unlaid.xs(), unlaid.by_place()), (p.xs(), p.by_place()));
                    assert!(!unlaid.by_step() && unlaid.step_row(0).is_none());
                }
                if next(40) == 0 {
                    p.apply(&p.plan_reset());
                }
                let mut fresh = p.clone();
                fresh.build_by_step();
                assert_eq!(p.step_rows, fresh.step_rows);
                assert_eq!(p.by_step, fresh.by_step);
                assert_eq!(p.by_step(), fresh.by_step());
                let mut places: Vec<u32> = p.by_place.clone();
                places.sort_unstable();
                assert!(places.iter().enumerate().all(|(i, &x)| x as usize == i));
                for (place, &i) in p.by_place().iter().enumerate() {
                    assert_eq!(p.place_of()[i as usize] as usize, place);
                }
            }
        }
    }

    #[test]
    fn laying_out_several_changes_at_once_gives_the_cells_of_a_full_layout() {
        let mut state = 0x51af_d7ed_558c_cd1du64;
        let mut next = |m: u64| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state % m
        };
        for capacity in [1, 2, 5, 30] {
            let mut p = Pool::new(capacity);
            for _ in 0..150 {
                let before = p.clone();
                for _ in 0..next(6) {
                    if next(25) == 0 {
                        p.apply_without_layout(&p.plan_reset());
                        continue;
                    }
                    // Mostly alike lengths, sometimes a ragged one (no layout then).
                    let len = if next(6) == 0 {
                        1 + next(3000)
                    } else {
                        20 + next(10)
                    } as usize;
                    let actions = (0..len).map(|_| next(3) as u32).collect();
                    if let Some(c) = p.plan_offer(ActionSeq::Discrete(actions), next(50) as f64) {
                        p.apply_without_layout(&c);
                    }
                }
                p.lay_out_from(&before);
                let mut fresh = p.clone();
                fresh.build_by_step();
                assert_eq!(p.step_rows, fresh.step_rows);
                assert_eq!(p.by_step, fresh.by_step);
            }
        }
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
