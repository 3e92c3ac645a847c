//! Validation of a `StepBatch` (SPEC §7, §8): the whole batch is checked before any of it
//! is applied, and every error names the offending field and entry.

use crate::core::{ActionRef, ActionSpace, StepInput, TaskConfig, Values};
use crate::error::Error;
use crate::proto::StepBatch;
use crate::registry::Limits;

fn finite_f32(field: &str, xs: &[f32]) -> Result<(), Error> {
    match xs.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(Error::invalid(
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
        Err(Error::invalid(
            format!("steps.{field}"),
            format!("has {len} entries, expected {expected} ({what})"),
        ))
    }
}

/// Checks `batch` for a stream of `num_envs` envs on a task with `config`, and returns the
/// entries as `(env, step)` in request order.
pub fn step_entries<'a>(
    batch: &'a StepBatch,
    config: &TaskConfig,
    num_envs: usize,
    limits: &Limits,
) -> Result<Vec<(usize, StepInput<'a>)>, Error> {
    let b = batch.rewards.len();
    if b > limits.max_batch_entries {
        return Err(Error::ResourceExhausted(format!(
            "steps: {b} entries exceed this server's limit max_batch_entries = {}",
            limits.max_batch_entries
        )));
    }
    // The answer carries per entry three doubles, a varint step (at most 5 bytes) and a
    // bool, plus framing: refuse, before applying anything, a batch whose answer could
    // not be sent.
    let answer_bytes = b.saturating_mul(3 * 8 + 5 + 1).saturating_add(64);
    if answer_bytes > limits.max_message_bytes {
        return Err(Error::ResourceExhausted(format!(
            "steps: the answer to {b} entries (up to {answer_bytes} bytes) would exceed this server's limit max_message_bytes = {}",
            limits.max_message_bytes
        )));
    }
    if batch.env_ids.is_empty() {
        if b > num_envs {
            return Err(Error::invalid(
                "steps.env_ids",
                format!(
                    "is empty, so entry i is env i, but the batch has {b} entries for {num_envs} envs"
                ),
            ));
        }
    } else {
        len_is(
            "env_ids",
            batch.env_ids.len(),
            b,
            "one per entry = len(rewards)",
        )?;
        if let Some((i, e)) = batch
            .env_ids
            .iter()
            .enumerate()
            .find(|(_, &e)| e as usize >= num_envs)
        {
            return Err(Error::invalid(
                format!("steps.env_ids[{i}]"),
                format!("env {e} out of range: the stream was opened with num_envs = {num_envs}"),
            ));
        }
    }
    if let Some(i) = batch.rewards.iter().position(|r| !r.is_finite()) {
        return Err(Error::invalid(
            format!("steps.rewards[{i}]"),
            format!("must be finite, got {}", batch.rewards[i]),
        ));
    }
    for (field, col) in [
        ("terminated", &batch.terminated),
        ("truncated", &batch.truncated),
    ] {
        if !col.is_empty() {
            len_is(field, col.len(), b, "one per entry, or empty for all false")?;
        }
    }
    let n = config.action_space.num_actions();
    match config.action_space {
        ActionSpace::Discrete { num_actions } => {
            if !batch.action_vectors.is_empty() {
                return Err(Error::invalid(
                    "steps.action_vectors",
                    "must be empty for a discrete task (use actions)",
                ));
            }
            len_is(
                "actions",
                batch.actions.len(),
                b,
                "one per entry = len(rewards)",
            )?;
            if let Some((i, a)) = batch
                .actions
                .iter()
                .enumerate()
                .find(|(_, &a)| a >= num_actions)
            {
                return Err(Error::invalid(
                    format!("steps.actions[{i}]"),
                    format!("action {a} out of range for num_actions {num_actions}"),
                ));
            }
        }
        ActionSpace::Continuous { action_dim } => {
            if !batch.actions.is_empty() {
                return Err(Error::invalid(
                    "steps.actions",
                    "must be empty for a continuous task (use action_vectors)",
                ));
            }
            let m = action_dim as usize;
            len_is(
                "action_vectors",
                batch.action_vectors.len(),
                b * m,
                &format!("len(rewards) x action_dim = {b} x {m}"),
            )?;
            finite_f32("action_vectors", &batch.action_vectors)?;
        }
    }
    let has_values = !batch.values.is_empty() || !batch.next_values.is_empty();
    let has_q = !batch.q_values.is_empty() || !batch.next_q_values.is_empty();
    if has_values && has_q {
        return Err(Error::invalid(
            "steps.q_values",
            "send either values/next_values or q_values/next_q_values, not both",
        ));
    }
    if has_values {
        len_is(
            "values",
            batch.values.len(),
            b,
            "one per entry, or both values and next_values empty",
        )?;
        len_is(
            "next_values",
            batch.next_values.len(),
            b,
            "one per entry, or both values and next_values empty",
        )?;
        finite_f32("values", &batch.values)?;
        finite_f32("next_values", &batch.next_values)?;
    }
    if has_q {
        if n == 0 {
            return Err(Error::invalid(
                "steps.q_values",
                "Q-values need a discrete task (num_actions > 0); send values/next_values",
            ));
        }
        let what = format!("len(rewards) x num_actions = {b} x {n}, or both empty");
        len_is("q_values", batch.q_values.len(), b * n, &what)?;
        len_is("next_q_values", batch.next_q_values.len(), b * n, &what)?;
        finite_f32("q_values", &batch.q_values)?;
        finite_f32("next_q_values", &batch.next_q_values)?;
    }
    let ends = |i: usize| {
        batch.terminated.get(i).copied().unwrap_or(false)
            || batch.truncated.get(i).copied().unwrap_or(false)
    };
    for (&i, &score) in &batch.episode_scores {
        let i = i as usize;
        if i >= b {
            return Err(Error::invalid(
                format!("steps.episode_scores[{i}]"),
                format!("entry index out of range: the batch has {b} entries"),
            ));
        }
        if !ends(i) {
            return Err(Error::invalid(
                format!("steps.episode_scores[{i}]"),
                "a score is only allowed on an entry that ends an episode (terminated or truncated)",
            ));
        }
        if !score.is_finite() {
            return Err(Error::invalid(
                format!("steps.episode_scores[{i}]"),
                format!("must be finite, got {score}"),
            ));
        }
    }

    let m = config.action_space.action_dim();
    Ok((0..b)
        .map(|i| {
            let env = batch.env_ids.get(i).map_or(i, |&e| e as usize);
            let action = if m == 0 {
                ActionRef::Discrete(batch.actions[i])
            } else {
                ActionRef::Continuous(&batch.action_vectors[i * m..(i + 1) * m])
            };
            let values = if has_values {
                Values::State {
                    value: batch.values[i],
                    next_value: batch.next_values[i],
                }
            } else if has_q {
                Values::Q {
                    q: &batch.q_values[i * n..(i + 1) * n],
                    next_q: &batch.next_q_values[i * n..(i + 1) * n],
                }
            } else {
                Values::None
            };
            let step = StepInput {
                action,
                reward: batch.rewards[i],
                terminated: batch.terminated.get(i).copied().unwrap_or(false),
                truncated: batch.truncated.get(i).copied().unwrap_or(false),
                values,
                score: batch.episode_scores.get(&(i as u32)).copied(),
            };
            (env, step)
        })
        .collect())
}
