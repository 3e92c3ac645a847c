//! The memory pool D of one task and its update rule (SPEC §6).
//!
//! Long file: the pool, its update rule and the layouts derived for the kNN step (by
//! place, by step) are one invariant, kept by the same few methods.
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
    /// (S_min, S_max), `None` if empty: kept with the other derived quantities, so a step
    /// reads it in O(1) (`require_score_spread`).
    score_range: Option<(f64, f64)>,
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
            score_range: None,
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
        self.recompute_derived(None);
        self.build_by_step();
    }

    /// Everything derived from the trajectories but the by-step layout. `order`, if
    /// given, lists every trajectory (index) once, in an order close to the new one (the
    /// previous pool's, with the change applied): the sort then costs O(|D|) instead of
    /// O(|D| log |D|). The result does not depend on it: the order sorted by is total.
    fn recompute_derived(&mut self, order: Option<Vec<usize>>) {
        self.seqs = self.trajectories.iter().map(|t| t.seq).collect();
        self.lens = self.trajectories.iter().map(|t| t.actions.len()).collect();
        self.l_min = self.lens.iter().copied().min().unwrap_or(0);
        self.score_range = self
            .trajectories
            .iter()
            .map(|t| t.score)
            .fold(None, |r, s| {
                let (lo, hi) = r.unwrap_or((s, s));
                Some((lo.min(s), hi.max(s)))
            });
        let (lo, hi) = self.score_range.unwrap_or((0.0, 0.0));
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
        let mut idx: Vec<usize> = order
            .filter(|o| o.len() == self.xs.len())
            .unwrap_or_else(|| (0..self.xs.len()).collect());
        // Stable (runs are merged, so a nearly sorted order sorts in linear time); with
        // seqs unique, any sort gives the same order.
        idx.sort_by(|&a, &b| {
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
                // The previous order without the one removed, the new one last.
                let order = last.then(|| {
                    let mut o: Vec<usize> = self
                        .by_place
                        .iter()
                        .map(|&i| i as usize)
                        .filter(|&i| Some(i) != removed)
                        .map(|i| i - usize::from(removed.is_some_and(|r| i > r)))
                        .collect();
                    o.push(self.trajectories.len());
                    o
                });
                self.trajectories.push(trajectory.clone());
                self.trajectories.sort_by_key(|t| t.seq);
                self.version += 1;
                self.recompute_derived(order);
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
        self.score_range
    }
    /// Whether the pool's scores differ, S_max > S_min (SPEC v1.3 §3, the condition
    /// `require_score_spread` adds); false for an empty pool. O(1).
    pub fn has_score_spread(&self) -> bool {
        self.score_range.is_some_and(|(lo, hi)| hi > lo)
    }
}

#[cfg(test)]
mod tests;
