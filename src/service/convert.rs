//! Mapping between protobuf messages and core types, with the validation of everything
//! that is not a step batch (task ids, configs, trajectories).

use crate::core::{ActionSeq, ActionSpace, Pool, TaskConfig, TaskConfigInput, Trajectory};
use crate::error::Error;
use crate::proto;
use crate::registry::TaskHandle;

/// Task ids: 1–128 characters of `[A-Za-z0-9._:/-]`.
pub fn validate_task_id(field: &str, id: &str) -> Result<(), Error> {
    if id.is_empty() || id.len() > 128 {
        return Err(Error::invalid(
            field,
            format!("task ids are 1-128 characters, got {}", id.len()),
        ));
    }
    if let Some(c) = id
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | ':' | '/' | '-')))
    {
        return Err(Error::invalid(
            field,
            format!("task ids use only [A-Za-z0-9._:/-], found {c:?}"),
        ));
    }
    Ok(())
}

/// The client's config with unset fields as `None`.
pub fn config_input(c: Option<&proto::TaskConfig>) -> TaskConfigInput {
    let Some(c) = c else {
        return TaskConfigInput::default();
    };
    TaskConfigInput {
        num_actions: c.num_actions,
        action_dim: c.action_dim,
        pool_capacity: c.pool_capacity,
        k: c.k,
        start_step: c.start_step,
        min_pool_size: c.min_pool_size,
        alpha: c.alpha,
        beta: c.beta,
        gamma: c.gamma,
        max_trajectory_len: c.max_trajectory_len,
    }
}

/// A resolved config with every field set.
pub fn config_proto(c: &TaskConfig) -> proto::TaskConfig {
    let i = c.to_input();
    proto::TaskConfig {
        num_actions: i.num_actions,
        action_dim: i.action_dim,
        pool_capacity: i.pool_capacity,
        k: i.k,
        start_step: i.start_step,
        min_pool_size: i.min_pool_size,
        alpha: i.alpha,
        beta: i.beta,
        gamma: i.gamma,
        max_trajectory_len: i.max_trajectory_len,
    }
}

fn sat_u32(x: usize) -> u32 {
    u32::try_from(x).unwrap_or(u32::MAX)
}

/// A task with its live stats.
pub fn task_proto(t: &TaskHandle) -> proto::Task {
    let s = t.stats();
    proto::Task {
        task_id: t.id().to_string(),
        config: Some(config_proto(t.config())),
        stats: Some(proto::TaskStats {
            pool_size: sat_u32(s.pool_size),
            pool_version: s.pool_version,
            min_length: sat_u32(s.min_length),
            best_score: s.best_score,
            worst_score: s.worst_score,
            episodes_completed: s.episodes_completed,
            steps_shaped: s.steps_shaped,
            open_streams: s.open_streams,
        }),
    }
}

/// A stored trajectory.
pub fn trajectory_proto(t: &Trajectory) -> proto::Trajectory {
    let (actions, action_vectors) = match &t.actions {
        ActionSeq::Discrete(v) => (v.clone(), Vec::new()),
        ActionSeq::Continuous { data, .. } => (Vec::new(), data.clone()),
    };
    proto::Trajectory {
        actions,
        action_vectors,
        score: t.score,
        seq: t.seq,
    }
}

/// A pool, trajectories by seq.
pub fn pool_proto(task_id: &str, pool: &Pool) -> proto::Pool {
    proto::Pool {
        task_id: task_id.to_string(),
        pool_version: pool.version(),
        trajectories: pool
            .trajectories()
            .iter()
            .map(|t| trajectory_proto(t))
            .collect(),
    }
}

/// Validates a client trajectory for `config` and returns its actions (truncated to
/// `max_trajectory_len`) and score.
pub fn trajectory_input(
    config: &TaskConfig,
    t: Option<proto::Trajectory>,
) -> Result<(ActionSeq, f64), Error> {
    let t = t.ok_or_else(|| Error::invalid("trajectory", "is required"))?;
    if !t.score.is_finite() {
        return Err(Error::invalid(
            "trajectory.score",
            format!("must be finite, got {}", t.score),
        ));
    }
    let mut actions = match config.action_space {
        ActionSpace::Discrete { num_actions } => {
            if !t.action_vectors.is_empty() {
                return Err(Error::invalid(
                    "trajectory.action_vectors",
                    "must be empty for a discrete task (use actions)",
                ));
            }
            if let Some((i, a)) = t
                .actions
                .iter()
                .enumerate()
                .find(|(_, &a)| a >= num_actions)
            {
                return Err(Error::invalid(
                    format!("trajectory.actions[{i}]"),
                    format!("action {a} out of range for num_actions {num_actions}"),
                ));
            }
            ActionSeq::Discrete(t.actions)
        }
        ActionSpace::Continuous { action_dim } => {
            if !t.actions.is_empty() {
                return Err(Error::invalid(
                    "trajectory.actions",
                    "must be empty for a continuous task (use action_vectors)",
                ));
            }
            let m = action_dim as usize;
            if t.action_vectors.len() % m != 0 {
                return Err(Error::invalid(
                    "trajectory.action_vectors",
                    format!(
                        "length {} is not a multiple of action_dim {m}",
                        t.action_vectors.len()
                    ),
                ));
            }
            if let Some(i) = t.action_vectors.iter().position(|x| !x.is_finite()) {
                return Err(Error::invalid(
                    format!("trajectory.action_vectors[{i}]"),
                    format!("must be finite, got {}", t.action_vectors[i]),
                ));
            }
            ActionSeq::Continuous {
                dim: m,
                data: t.action_vectors,
            }
        }
    };
    if actions.is_empty() {
        return Err(Error::invalid(
            "trajectory",
            "must have at least one action",
        ));
    }
    actions.truncate(config.max_trajectory_len as usize);
    Ok((actions, t.score))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn task_ids() {
        assert!(validate_task_id("t", "maze/v1:seed-0_a.b").is_ok());
        assert!(validate_task_id("t", &"a".repeat(128)).is_ok());
        assert!(validate_task_id("t", &"a".repeat(129)).is_err());
        assert!(validate_task_id("t", "").is_err());
        assert!(validate_task_id("t", "a b").is_err());
        assert!(validate_task_id("t", "é").is_err());
    }
}
