//! A step batch as the session layer sees it (columnar, borrowed, transport-free) and its
//! validation (SPEC §7, §8, §12): the whole batch is checked before any of it is applied,
//! and every error names the offending field (`steps.<column>[<entry>]`).

use crate::core::{ActionCount, ActionRef, ActionSpace, StepInput, TaskConfig, Values};
use crate::error::Error;
use crate::limits::Limits;

/// One `StepBatch`, borrowed from whatever carried it (a protobuf message, numpy arrays).
/// Column meanings and lengths are those of the proto's `StepBatch`; B = `rewards.len()`.
#[derive(Debug, Clone, Copy, Default)]
pub struct Batch<'a> {
    /// The environment of each entry; empty means entry i is env i.
    pub env_ids: &'a [u32],
    /// Discrete actions, B entries.
    pub actions: &'a [u32],
    /// Continuous actions, B × action_dim.
    pub action_vectors: &'a [f32],
    /// Environment rewards R, B entries (defines B).
    pub rewards: &'a [f64],
    /// B entries, or empty for all false.
    pub terminated: &'a [bool],
    /// B entries, or empty for all false.
    pub truncated: &'a [bool],
    /// V(s), B entries or empty (with `next_values`).
    pub values: &'a [f32],
    /// V(s'), B entries or empty (with `values`).
    pub next_values: &'a [f32],
    /// Q(s, ·), B × n or empty (with `next_q_values`).
    pub q_values: &'a [f32],
    /// Q(s', ·), B × n or empty (with `q_values`).
    pub next_q_values: &'a [f32],
    /// `(entry index, score)` for entries that end an episode, each index at most once.
    pub episode_scores: &'a [(u32, f64)],
    /// Environments whose current episode is dropped before the entries (SPEC §12).
    pub abandon: &'a [u32],
}

/// A validated batch: one `(env, step)` per entry, in request order.
pub type Entries<'a> = Vec<(usize, StepInput<'a>)>;

fn invalid(field: impl Into<String>, message: impl Into<String>) -> Error {
    Error::invalid(field, message)
}

fn finite_f32(field: &str, xs: &[f32]) -> Result<(), Error> {
    match xs.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(invalid(
            format!("steps.{field}[{i}]"),
            format!("must be finite, got {}", xs[i]),
        )),
        None => Ok(()),
    }
}

fn len_is(field: &str, len: usize, expected: usize, what: &str) -> Result<(), Error> {
    if len == expected {
        Ok(())
    } else {
        Err(invalid(
            format!("steps.{field}"),
            format!("has {len} entries, expected {expected} ({what})"),
        ))
    }
}

/// Environment ids listed in `ids` (under `field`) are each `< num_envs` and distinct.
pub(crate) fn check_env_list(field: &str, ids: &[u32], num_envs: usize) -> Result<(), Error> {
    let mut seen = vec![false; if ids.is_empty() { 0 } else { num_envs }];
    for (i, &e) in ids.iter().enumerate() {
        let Some(slot) = seen.get_mut(e as usize) else {
            return Err(invalid(
                format!("{field}[{i}]"),
                format!("env {e} out of range: the stream was opened with num_envs = {num_envs}"),
            ));
        };
        if std::mem::replace(slot, true) {
            return Err(invalid(
                format!("{field}[{i}]"),
                format!("env {e} is listed twice"),
            ));
        }
    }
    Ok(())
}

impl<'a> Batch<'a> {
    /// B, the number of entries.
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    /// Whether the batch has no entries (it may still abandon episodes).
    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }

    /// The environment of entry `i` (entry i is env i when `env_ids` is empty).
    pub fn env_of(&self, i: usize) -> usize {
        self.env_ids.get(i).map_or(i, |&e| e as usize)
    }

    /// Whether entry `i` ends an episode.
    pub fn ends(&self, i: usize) -> bool {
        self.terminated.get(i).copied().unwrap_or(false)
            || self.truncated.get(i).copied().unwrap_or(false)
    }

    /// Whether any entry ends an episode (only then can the batch change the pool).
    pub fn ends_any(&self) -> bool {
        self.terminated.iter().chain(self.truncated).any(|&d| d)
    }

    /// Checks the whole batch for a stream of `num_envs` environments on a task with
    /// `config`, and returns its entries. Nothing is applied on error.
    pub fn validate(
        &self,
        config: &TaskConfig,
        num_envs: usize,
        limits: &Limits,
    ) -> Result<Entries<'a>, Error> {
        self.check_size(limits)?;
        self.check_envs(num_envs)?;
        self.check_rewards_and_flags()?;
        self.check_actions(&config.action_space)?;
        let values = self.check_values(&config.action_space)?;
        self.check_scores()?;
        Ok(self.entries(&config.action_space, values))
    }

    /// The batch and its answer fit the server's limits.
    fn check_size(&self, limits: &Limits) -> Result<(), Error> {
        let b = self.len();
        if b > limits.max_batch_entries {
            return Err(Error::ResourceExhausted(format!(
                "steps: {b} entries exceed this server's limit max_batch_entries = {}",
                limits.max_batch_entries
            )));
        }
        // The answer carries per entry three doubles, a varint step (at most 5 bytes) and
        // a bool, plus framing: refuse, before applying anything, a batch whose answer
        // could not be sent.
        let answer_bytes = b.saturating_mul(3 * 8 + 5 + 1).saturating_add(64);
        if answer_bytes > limits.max_message_bytes {
            return Err(Error::ResourceExhausted(format!(
                "steps: the answer to {b} entries (up to {answer_bytes} bytes) would exceed this server's limit max_message_bytes = {}",
                limits.max_message_bytes
            )));
        }
        Ok(())
    }

    /// `env_ids` (or the implicit ids) and `abandon` name environments of the stream.
    fn check_envs(&self, num_envs: usize) -> Result<(), Error> {
        let b = self.len();
        if self.env_ids.is_empty() {
            if b > num_envs {
                return Err(invalid(
                    "steps.env_ids",
                    format!(
                        "is empty, so entry i is env i, but the batch has {b} entries for {num_envs} envs"
                    ),
                ));
            }
        } else {
            len_is(
                "env_ids",
                self.env_ids.len(),
                b,
                "one per entry = len(rewards)",
            )?;
            if let Some((i, e)) = self
                .env_ids
                .iter()
                .enumerate()
                .find(|(_, &e)| e as usize >= num_envs)
            {
                return Err(invalid(
                    format!("steps.env_ids[{i}]"),
                    format!(
                        "env {e} out of range: the stream was opened with num_envs = {num_envs}"
                    ),
                ));
            }
        }
        check_env_list("steps.abandon", self.abandon, num_envs)
    }

    /// Rewards are finite; the done flags have one entry each, or none.
    fn check_rewards_and_flags(&self) -> Result<(), Error> {
        if let Some(i) = self.rewards.iter().position(|r| !r.is_finite()) {
            return Err(invalid(
                format!("steps.rewards[{i}]"),
                format!("must be finite, got {}", self.rewards[i]),
            ));
        }
        for (field, col) in [
            ("terminated", self.terminated),
            ("truncated", self.truncated),
        ] {
            if !col.is_empty() {
                len_is(
                    field,
                    col.len(),
                    self.len(),
                    "one per entry, or empty for all false",
                )?;
            }
        }
        Ok(())
    }

    /// Actions fit the task's action space, one per entry.
    fn check_actions(&self, space: &ActionSpace) -> Result<(), Error> {
        space
            .check_actions(
                self.actions,
                self.action_vectors,
                ActionCount::Exactly(self.len(), "len(rewards)"),
            )
            .map(|_| ())
            .map_err(|e| invalid(e.field("steps."), e.message))
    }

    /// Values or Q-values (not both), with their lengths, finite. Returns which were sent.
    fn check_values(&self, space: &ActionSpace) -> Result<SentValues, Error> {
        let b = self.len();
        let has_values = !self.values.is_empty() || !self.next_values.is_empty();
        let has_q = !self.q_values.is_empty() || !self.next_q_values.is_empty();
        if has_values && has_q {
            return Err(invalid(
                "steps.q_values",
                "send either values/next_values or q_values/next_q_values, not both",
            ));
        }
        if has_values {
            let what = "one per entry, or both values and next_values empty";
            len_is("values", self.values.len(), b, what)?;
            len_is("next_values", self.next_values.len(), b, what)?;
            finite_f32("values", self.values)?;
            finite_f32("next_values", self.next_values)?;
            return Ok(SentValues::State);
        }
        if has_q {
            let n = space.num_actions();
            if n == 0 {
                return Err(invalid(
                    "steps.q_values",
                    "Q-values need a discrete task (num_actions > 0); send values/next_values",
                ));
            }
            let what = format!("len(rewards) x num_actions = {b} x {n}, or both empty");
            len_is("q_values", self.q_values.len(), b * n, &what)?;
            len_is("next_q_values", self.next_q_values.len(), b * n, &what)?;
            finite_f32("q_values", self.q_values)?;
            finite_f32("next_q_values", self.next_q_values)?;
            return Ok(SentValues::Q(n));
        }
        Ok(SentValues::None)
    }

    /// Scores only on entries that end an episode, finite, each entry at most once.
    fn check_scores(&self) -> Result<(), Error> {
        let b = self.len();
        let mut seen = vec![false; if self.episode_scores.is_empty() { 0 } else { b }];
        for &(i, score) in self.episode_scores {
            let i = i as usize;
            // Only an error names the field: no string per valid score.
            let field = || format!("steps.episode_scores[{i}]");
            let Some(slot) = seen.get_mut(i) else {
                return Err(invalid(
                    field(),
                    format!("entry index out of range: the batch has {b} entries"),
                ));
            };
            if std::mem::replace(slot, true) {
                return Err(invalid(field(), "entry has more than one score"));
            }
            if !self.ends(i) {
                return Err(invalid(
                    field(),
                    "a score is only allowed on an entry that ends an episode (terminated or truncated)",
                ));
            }
            if !score.is_finite() {
                return Err(invalid(field(), format!("must be finite, got {score}")));
            }
        }
        Ok(())
    }

    /// The entries of a batch that passed every check.
    fn entries(&self, space: &ActionSpace, values: SentValues) -> Entries<'a> {
        let m = space.action_dim();
        let mut out: Entries<'a> = (0..self.len())
            .map(|i| {
                let env = self.env_of(i);
                let action = if m == 0 {
                    ActionRef::Discrete(self.actions[i])
                } else {
                    ActionRef::Continuous(&self.action_vectors[i * m..(i + 1) * m])
                };
                let values = match values {
                    SentValues::None => Values::None,
                    SentValues::State => Values::State {
                        value: self.values[i],
                        next_value: self.next_values[i],
                    },
                    SentValues::Q(n) => Values::Q {
                        q: &self.q_values[i * n..(i + 1) * n],
                        next_q: &self.next_q_values[i * n..(i + 1) * n],
                    },
                };
                let step = StepInput {
                    action,
                    reward: self.rewards[i],
                    terminated: self.terminated.get(i).copied().unwrap_or(false),
                    truncated: self.truncated.get(i).copied().unwrap_or(false),
                    values,
                    score: None,
                };
                (env, step)
            })
            .collect();
        for &(i, score) in self.episode_scores {
            out[i as usize].1.score = Some(score);
        }
        out
    }
}

/// Which value columns a batch sent.
#[derive(Debug, Clone, Copy)]
enum SentValues {
    None,
    State,
    /// Q-values, n per entry.
    Q(usize),
}

#[cfg(test)]
mod tests;
