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
    /// dis_i over the steps taken so far (j < min(t, L_i)).
    dis: Vec<f64>,
    /// The previous `dis` allocation, reused by the next sync.
    spare: Vec<f64>,
}

/// Σ_{j<upto} δ(a_j, b_j) of two action sequences, summed in j order (the definition).
/// For discrete actions each term is 0 or 2, so the sum is exactly 2 × the number of
/// mismatches (an empty sum stays the empty sum).
fn prefix_distance(a: &ActionSeq, b: &ActionSeq, upto: usize) -> f64 {
    match (a, b) {
        (ActionSeq::Discrete(x), ActionSeq::Discrete(y)) if upto > 0 => {
            let mismatches = x[..upto]
                .iter()
                .zip(&y[..upto])
                .filter(|(p, q)| p != q)
                .count();
            2.0 * mismatches as f64
        }
        _ => (0..upto).map(|j| delta(a.get(j), b.get(j))).sum(),
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
        }
    }

    /// Index of the next step.
    pub fn t(&self) -> u64 {
        self.t
    }

    /// Brings `dis` in line with the pool's current contents.
    fn sync(&mut self, pool: &Pool) {
        if self.synced_version == Some(pool.version()) {
            return;
        }
        let mut dis = std::mem::take(&mut self.spare);
        dis.clear();
        dis.reserve(pool.len());
        let mut old = 0;
        for (traj, &seq) in pool.trajectories().iter().zip(pool.seqs()) {
            // Both lists are sorted by seq and seqs are never reused: a merge walk.
            while old < self.seqs.len() && self.seqs[old] < seq {
                old += 1;
            }
            if old < self.seqs.len() && self.seqs[old] == seq {
                dis.push(self.dis[old]);
            } else {
                let upto = (self.t as usize)
                    .min(traj.actions.len())
                    .min(self.recorded.len());
                dis.push(prefix_distance(&traj.actions, &self.recorded, upto));
            }
        }
        self.seqs.clear();
        self.seqs.extend_from_slice(pool.seqs());
        self.spare = std::mem::replace(&mut self.dis, dis);
        self.synced_version = Some(pool.version());
    }

    /// The distance update of step `t` for a discrete action against a discrete pool;
    /// `false` (nothing done) otherwise. With the pool laid out by step, one contiguous
    /// row holds every trajectory's action at t; each distance gets δ = 2 × mismatch
    /// (0 or 1, no branch on the comparison), exactly what [`delta`] gives. A trajectory
    /// shorter than t ([`NO_ACTION`]) gets + 0.0, which leaves its distance (≥ +0.0)
    /// unchanged. Without the layout, a first pass loads each trajectory's action into a
    /// mismatch column (so the cache-missing loads overlap) and a second adds.
    fn discrete_distances(
        &mut self,
        pool: &Pool,
        t: usize,
        action: ActionRef<'_>,
        scratch: &mut KnnScratch,
    ) -> bool {
        let ActionRef::Discrete(a) = action else {
            return false;
        };
        if pool.by_step() {
            if let Some(row) = pool.step_row(t) {
                for (d, &v) in self.dis.iter_mut().zip(row) {
                    let m = (v != a) & (v != NO_ACTION);
                    *d += 2.0 * f64::from(u8::from(m));
                }
            }
            return true;
        }
        let mismatch = &mut scratch.mismatch;
        mismatch.clear();
        let mut all_discrete = true;
        mismatch.extend(
            pool.trajectories()
                .iter()
                .zip(pool.lens())
                .map(|(traj, &len)| match &traj.actions {
                    ActionSeq::Discrete(v) if t < len => i32::from(v[t] != a),
                    ActionSeq::Discrete(_) => 0,
                    ActionSeq::Continuous { .. } => {
                        all_discrete = false;
                        0
                    }
                }),
        );
        if !all_discrete {
            return false;
        }
        for (d, &m) in self.dis.iter_mut().zip(mismatch.iter()) {
            *d += 2.0 * f64::from(m);
        }
        true
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
        let discrete = self.discrete_distances(pool, t, input.action, scratch);
        if !discrete {
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
            && t < cfg.max_trajectory_len as usize;
        let knn_reward = if active {
            let k = cfg.k as usize;
            let f = if discrete {
                knn_f_discrete(
                    &self.dis,
                    pool.xs(),
                    pool.places(),
                    pool.by_place(),
                    k,
                    scratch,
                )
            } else {
                None
            };
            reward_from_f(f.unwrap_or_else(|| knn_f(&self.dis, pool.xs(), pool.seqs(), k, scratch)))
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
            Some(EpisodeEnd { actions, score })
        } else {
            None
        };
        (output, end)
    }
}
