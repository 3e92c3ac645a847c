//! The client's view of each environment's episode: the step index, the abandons not yet
//! sent, and (on a remote stream) what resuming the episode on a new stream takes
//! (SPEC §9: its actions so far, Σ R, and the number of episodes the env has ended).

use tamrm::proto;
use tamrm::session::Batch;

use crate::answer::Answer;

/// Per-environment episode state of one stream, as the client sees it (a [`crate::Session`]
/// keeps one; a [`crate::Transport`] reads it to resume).
#[derive(Debug)]
pub struct Tracker {
    /// Actions per step of a continuous task (0: discrete).
    action_dim: usize,
    /// Whether to keep each episode's actions (for a remote stream's resume).
    keep_actions: bool,
    /// Per env: steps sent in the current episode.
    steps: Vec<u64>,
    actions: Vec<Vec<u32>>,
    vectors: Vec<Vec<f32>>,
    reward_sums: Vec<f64>,
    ended: Vec<u64>,
    /// Abandoned envs not yet sent (they travel with the next batch that has entries).
    abandon_pending: Vec<u32>,
    /// Sent abandons whose answer must show the env starting over.
    unconfirmed: Vec<bool>,
}

impl Tracker {
    /// The state of `num_envs` environments at t = 0; `action_dim` 0 for a discrete task;
    /// `keep_actions` when the transport resumes episodes (it needs their actions).
    pub fn new(num_envs: usize, action_dim: usize, keep_actions: bool) -> Tracker {
        Tracker {
            action_dim,
            keep_actions,
            steps: vec![0; num_envs],
            actions: vec![Vec::new(); num_envs],
            vectors: vec![Vec::new(); num_envs],
            reward_sums: vec![0.0; num_envs],
            ended: vec![0; num_envs],
            abandon_pending: Vec::new(),
            unconfirmed: vec![false; num_envs],
        }
    }

    /// Environments of the stream.
    pub fn num_envs(&self) -> usize {
        self.steps.len()
    }

    /// Per env: steps sent in its current episode.
    pub fn steps(&self) -> &[u64] {
        &self.steps
    }

    /// Records abandons (checked by the caller: in range, none twice).
    pub(crate) fn abandon(&mut self, envs: &[u32]) {
        for &e in envs {
            if !self.abandon_pending.contains(&e) {
                self.abandon_pending.push(e);
            }
            let e = e as usize;
            self.steps[e] = 0;
            self.actions[e].clear();
            self.vectors[e].clear();
            self.reward_sums[e] = 0.0;
        }
    }

    /// Moves the pending abandons into the batch about to be sent.
    pub(crate) fn take_abandons(&mut self, into: &mut Vec<u32>) {
        into.clear();
        into.append(&mut self.abandon_pending);
        for &e in into.iter() {
            self.unconfirmed[e as usize] = true;
        }
    }

    /// Puts abandons back after a batch that was not applied.
    pub(crate) fn restore_abandons(&mut self, sent: &[u32]) {
        for &e in sent {
            if !self.abandon_pending.contains(&e) {
                self.abandon_pending.push(e);
            }
            self.unconfirmed[e as usize] = false;
        }
    }

    /// Whether a sent abandon was ignored (a server older than SPEC v1.1 §12): the env's
    /// first entry of the answer went on with the dropped episode. Returns that env.
    pub(crate) fn ignored_abandon(
        &mut self,
        batch: &Batch<'_>,
        answer: &Answer,
    ) -> Option<(usize, i64)> {
        if !self.unconfirmed.iter().any(|&u| u) {
            return None;
        }
        let mut result = None;
        for i in 0..batch.len() {
            let env = batch.env_of(i);
            if self.unconfirmed[env] {
                self.unconfirmed[env] = false;
                if answer.steps[i] != 0 && result.is_none() {
                    result = Some((env, answer.steps[i]));
                }
            }
        }
        result
    }

    /// Records an answered batch.
    pub(crate) fn record(&mut self, batch: &Batch<'_>, answer: &Answer) {
        let dim = self.action_dim;
        for i in 0..batch.len() {
            let env = batch.env_of(i);
            if batch.ends(i) {
                self.steps[env] = 0;
                self.ended[env] += 1;
                self.actions[env].clear();
                self.vectors[env].clear();
                self.reward_sums[env] = 0.0;
                continue;
            }
            self.steps[env] = answer.steps[i] as u64 + 1;
            if self.keep_actions {
                if dim == 0 {
                    self.actions[env].push(batch.actions[i]);
                } else {
                    let row = &batch.action_vectors[i * dim..(i + 1) * dim];
                    self.vectors[env].extend_from_slice(row);
                }
                self.reward_sums[env] += batch.rewards[i];
            }
        }
    }

    /// A closed stream's episodes are discarded (SPEC §6): nothing to resume.
    pub(crate) fn discard_episodes(&mut self) {
        for e in 0..self.num_envs() {
            self.steps[e] = 0;
            self.actions[e].clear();
            self.vectors[e].clear();
            self.reward_sums[e] = 0.0;
        }
        self.abandon_pending.clear();
        self.unconfirmed.iter_mut().for_each(|u| *u = false);
    }

    /// `Open.resume`: every env, with its episode in progress (none at t = 0) and its
    /// episode counter. Even an env at t = 0 with no ended episode is listed: the server
    /// numbers an env not listed after the last end it committed for it, so an env whose
    /// first episode ended in the batch being re-sent would otherwise get a new number
    /// and be committed twice.
    pub fn resume(&self) -> Vec<proto::EnvResume> {
        (0..self.num_envs())
            .map(|e| proto::EnvResume {
                env_id: e as u32,
                actions: self.actions[e].clone(),
                action_vectors: self.vectors[e].clone(),
                reward_sum: self.reward_sums[e],
                episode: self.ended[e],
            })
            .collect()
    }

    /// After a (re-)open: the pending abandons were not resumed, so they start anew.
    pub(crate) fn reopened(&mut self) {
        self.abandon_pending.clear();
        self.unconfirmed.iter_mut().for_each(|u| *u = false);
        for e in 0..self.num_envs() {
            self.steps[e] = match self.vectors[e].len().checked_div(self.action_dim) {
                Some(steps) => steps as u64,
                None => self.actions[e].len() as u64,
            };
        }
    }
}
