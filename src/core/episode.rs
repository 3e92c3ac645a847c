//! The per-environment episode state and the incremental shaping of one step
//! (SPEC §2–§5).
//!
//! An [`Episode`] keeps `dis_i(t)` for every trajectory of the pool version it last saw,
//! so a step costs O(|D|) plus the top-k selection, independent of t. When the pool has
//! changed since the previous step (another stream inserted, replaced or reset), the
//! distances are re-aligned by seq: kept for trajectories still there, computed once from
//! the recorded prefix for new ones (O(t) once per new trajectory).

use super::actions::{delta, ActionRef, ActionSeq};
use super::config::{ActionSpace, TaskConfig};
use super::knn::{knn_f, knn_f_discrete, reward_from_f, KnnScratch};
use super::pool::{Pool, NO_ACTION};
use super::potential::{potential, Values};

/// One environment step as the core needs it (already validated).
#[derive(Debug, Clone, Copy)]
pub struct StepInput<'a> {
    /// The action taken at this step.
    pub action: ActionRef<'a>,
    /// The environment reward R (finite).
    pub reward: f64,
    /// The step reached a terminal state.
    pub terminated: bool,
    /// The step hit a time limit (or was otherwise cut off).
    pub truncated: bool,
    /// Value estimates for the potential term.
    pub values: Values<'a>,
    /// Client-supplied episode score; only meaningful on an episode's last step.
    pub score: Option<f64>,
}

/// The shaped reward of one step and its parts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepOutput {
    /// R_meta = R + α·r(t) + β·F.
    pub reward: f64,
    /// r(t).
    pub knn_reward: f64,
    /// F.
    pub potential: f64,
    /// t, the step index within the episode.
    pub step: u64,
    /// Whether the kNN term was active.
    pub knn_active: bool,
}

/// A finished episode, ready to be offered to the pool.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeEnd {
    /// The first `min(L, max_trajectory_len)` actions.
    pub actions: ActionSeq,
    /// The client score, or the sum of the episode's environment rewards.
    pub score: f64,
}

/// Episode state of one environment.
#[derive(Debug, Clone)]
pub struct Episode {
    /// Index of the next step (= steps taken so far in this episode).
    t: u64,
    /// Actions recorded so far (capped at max_trajectory_len).
    recorded: ActionSeq,
    /// Σ R over the episode.
    reward_sum: f64,
    /// The pool version `seqs`/`dis` are aligned with; `None` before the first sync.
    synced_version: Option<u64>,
    /// Seqs of the trajectories `dis` refers to.
    seqs: Vec<u64>,
    /// Continuous tasks: dis_i over the steps taken so far (j < min(t, L_i)).
    dis: Vec<f64>,
    /// The previous `dis` allocation, reused by the next sync.
    spare: Vec<f64>,
    /// Discrete tasks: the number of mismatches m_i over the steps taken so far, so
    /// dis_i = 2·m_i exactly (a sum of 0s and 2s below 2^33 is exact in f64).
    ms: Vec<u32>,
    /// The previous `ms` allocation, reused by the next sync.
    spare_ms: Vec<u32>,
    /// The k-th smallest of `ms` at the last kNN step since the counts were last reset
    /// or realigned: a lower bound on it now, which finds it faster (`knn_f_discrete`).
    kth: Option<u32>,
}

/// Σ_{j<upto} δ(a_j, b_j) of two continuous action sequences, summed in j order (the
/// definition).
fn prefix_distance(a: &ActionSeq, b: &ActionSeq, upto: usize) -> f64 {
    (0..upto).map(|j| delta(a.get(j), b.get(j))).sum()
}

/// The number of j < upto where two discrete action sequences differ (δ = 2 there, 0
/// elsewhere, so the definition's distance is exactly 2 × this count). `upto` is at most
/// `max_trajectory_len` (a `u32`), so the count fits. A continuous `a` (never in a
/// discrete task's pool) counts every step as a mismatch.
fn prefix_mismatches(a: &ActionSeq, b: &[u32], upto: usize) -> u32 {
    match a {
        // A u32 sum (it cannot overflow, see above): four lanes per vector, where a
        // usize count has two.
        ActionSeq::Discrete(x) => x[..upto]
            .iter()
            .zip(&b[..upto])
            .map(|(p, q)| u32::from(p != q))
            .sum(),
        ActionSeq::Continuous { .. } => u32::try_from(upto).unwrap_or(u32::MAX),
    }
}

impl Episode {
    /// A fresh episode (t = 0) for a task with actions of `space`.
    pub fn new(space: ActionSpace) -> Episode {
        Episode {
            t: 0,
            recorded: ActionSeq::empty(space),
            reward_sum: 0.0,
            synced_version: None,
            seqs: Vec::new(),
            dis: Vec::new(),
            spare: Vec::new(),
            ms: Vec::new(),
            spare_ms: Vec::new(),
            kth: None,
        }
    }

    /// The episode a client resumes (SPEC §9): it has taken `actions` (all t of them) and
    /// earned `reward_sum`. Only the first `max_trajectory_len` actions are recorded, as
    /// in an uninterrupted episode; the distances to the pool are computed from them at
    /// the next step, so every later value equals the uninterrupted stream's.
    pub fn resume(mut actions: ActionSeq, reward_sum: f64, max_trajectory_len: u32) -> Episode {
        let t = actions.len() as u64;
        actions.truncate(max_trajectory_len as usize);
        Episode {
            t,
            recorded: actions,
            reward_sum,
            synced_version: None,
            seqs: Vec::new(),
            dis: Vec::new(),
            spare: Vec::new(),
            ms: Vec::new(),
            spare_ms: Vec::new(),
            kth: None,
        }
    }

    /// Index of the next step.
    pub fn t(&self) -> u64 {
        self.t
    }

    /// Recorded actions that the first sync with a pool compares with every trajectory
    /// (a resumed episode's prefix); 0 once synced. The next step's work grows with this
    /// times the pool's size.
    pub fn pending_sync_len(&self) -> usize {
        if self.synced_version.is_none() {
            self.recorded.len()
        } else {
            0
        }
    }

    /// Brings `dis` (or `ms`) in line with the pool's current contents.
    fn sync(&mut self, pool: &Pool) {
        if self.synced_version == Some(pool.version()) {
            return;
        }
        if let ActionSeq::Discrete(recorded) = &self.recorded {
            let mut ms = std::mem::take(&mut self.spare_ms);
            realign(&self.seqs, &self.ms, pool, &mut ms, |traj| {
                let upto = (self.t as usize).min(traj.len()).min(recorded.len());
                prefix_mismatches(traj, recorded, upto)
            });
            self.spare_ms = std::mem::replace(&mut self.ms, ms);
            // Realigned counts may be smaller than the remembered k-th one.
            self.kth = None;
        } else {
            let mut dis = std::mem::take(&mut self.spare);
            realign(&self.seqs, &self.dis, pool, &mut dis, |traj| {
                let upto = (self.t as usize).min(traj.len()).min(self.recorded.len());
                prefix_distance(traj, &self.recorded, upto)
            });
            self.spare = std::mem::replace(&mut self.dis, dis);
        }
        self.seqs.clear();
        self.seqs.extend_from_slice(pool.seqs());
        self.synced_version = Some(pool.version());
    }

    /// The mismatch update of step `t` for a discrete action. With the pool laid out by
    /// step, one contiguous row holds every trajectory's action at t; each count gets
    /// (v ≠ a) ∧ (v ≠ [`NO_ACTION`]) (no branch on the comparison): a trajectory shorter
    /// than t keeps its count, as its distance gets no term. Without the layout, each
    /// trajectory's action is read from its own sequence.
    fn discrete_counts(&mut self, pool: &Pool, t: usize, a: u32) {
        if pool.by_step() {
            if let Some(row) = pool.step_row(t) {
                for (m, &v) in self.ms.iter_mut().zip(row) {
                    *m += u32::from((v != a) & (v != NO_ACTION));
                }
            }
            return;
        }
        for ((m, traj), &len) in self.ms.iter_mut().zip(pool.trajectories()).zip(pool.lens()) {
            *m += match &traj.actions {
                ActionSeq::Discrete(v) if t < len => u32::from(v[t] != a),
                ActionSeq::Discrete(_) => 0,
                ActionSeq::Continuous { .. } => u32::from(t < len),
            };
        }
    }

    /// Shapes one step against `pool` as it is now, and returns the finished episode if
    /// this step ended it (the caller offers it to the pool after this step was shaped).
    pub fn step(
        &mut self,
        cfg: &TaskConfig,
        pool: &Pool,
        input: &StepInput<'_>,
        scratch: &mut KnnScratch,
    ) -> (StepOutput, Option<EpisodeEnd>) {
        self.sync(pool);
        let t = self.t as usize;
        let discrete = matches!(self.recorded, ActionSeq::Discrete(_));
        if discrete {
            match input.action {
                ActionRef::Discrete(a) => self.discrete_counts(pool, t, a),
                ActionRef::Continuous(_) => {
                    debug_assert!(false, "a continuous action in a discrete episode");
                }
            }
        } else {
            for ((d, traj), &len) in self
                .dis
                .iter_mut()
                .zip(pool.trajectories())
                .zip(pool.lens())
            {
                if t < len {
                    *d += delta(traj.actions.get(t), input.action);
                }
            }
        }
        if t < cfg.max_trajectory_len as usize {
            self.recorded.push(input.action);
        }
        self.reward_sum += input.reward;

        let active = pool.len() >= cfg.min_pool_size as usize
            && t >= cfg.start_step as usize
            && t < pool.l_min()
            && t < cfg.max_trajectory_len as usize
            // (v1.3) A pool whose scores are all equal says nothing about what worked.
            && (!cfg.require_score_spread || pool.has_score_spread());
        let knn_reward = if active {
            let k = cfg.k as usize;
            let f = if discrete {
                knn_f_discrete(
                    &self.ms,
                    pool.xs(),
                    pool.by_place(),
                    pool.place_of(),
                    k,
                    scratch,
                    &mut self.kth,
                )
            } else {
                knn_f(&self.dis, pool.xs(), pool.seqs(), k, scratch)
            };
            reward_from_f(f)
        } else {
            0.0
        };
        // With gate_potential (v1.1), F counts only where the kNN term does.
        let f = if cfg.gate_potential && !active {
            0.0
        } else {
            potential(input.values, cfg.gamma, input.terminated)
        };
        let output = StepOutput {
            reward: input.reward + cfg.alpha * knn_reward + cfg.beta * f,
            knn_reward,
            potential: f,
            step: self.t,
            knn_active: active,
        };
        self.t += 1;

        let end = if input.terminated || input.truncated {
            let score = input.score.unwrap_or(self.reward_sum);
            let fresh = self.recorded.empty_like();
            let actions = std::mem::replace(&mut self.recorded, fresh);
            self.t = 0;
            self.reward_sum = 0.0;
            // Every distance of the empty prefix is 0; the seqs stay valid.
            self.dis.iter_mut().for_each(|d| *d = 0.0);
            self.ms.iter_mut().for_each(|m| *m = 0);
            self.kth = None;
            Some(EpisodeEnd { actions, score })
        } else {
            None
        };
        (output, end)
    }
}

/// Fills `out` with one value per trajectory of `pool`: the one kept in `old` (aligned
/// with `old_seqs`) for trajectories still there, `fresh(actions)` for new ones.
fn realign<T: Copy>(
    old_seqs: &[u64],
    old: &[T],
    pool: &Pool,
    out: &mut Vec<T>,
    mut fresh: impl FnMut(&ActionSeq) -> T,
) {
    out.clear();
    out.reserve(pool.len());
    let mut j = 0;
    for (traj, &seq) in pool.trajectories().iter().zip(pool.seqs()) {
        // Both lists are sorted by seq and seqs are never reused: a merge walk.
        while j < old_seqs.len() && old_seqs[j] < seq {
            j += 1;
        }
        if j < old_seqs.len() && old_seqs[j] == seq {
            out.push(old[j]);
        } else {
            out.push(fresh(&traj.actions));
        }
    }
}
