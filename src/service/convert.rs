//! Mapping between protobuf messages and the library's types (configs, tasks, pools,
//! trajectories, step batches and their answers). Validation lives in the layers below:
//! this module only moves fields.

use crate::core::{ActionCount, ActionSeq, Pool, TaskConfig, TaskConfigInput, Trajectory};
use crate::error::Error;
use crate::proto;
use crate::registry::TaskHandle;
use crate::session::{Batch, Resume, Shaped};

macro_rules! config_conversions {
    ($($(#[doc = $doc:literal])* $name:ident : $ty:ty,)*
     ; $($(#[doc = $ndoc:literal])* $new:ident : $nty:ty,)*) => {
        /// The client's config with unset fields as `None`.
        pub fn config_input(c: Option<&proto::TaskConfig>) -> TaskConfigInput {
            let Some(c) = c else {
                return TaskConfigInput::default();
            };
            TaskConfigInput {
                num_actions: c.num_actions,
                action_dim: c.action_dim,
                $($name: c.$name,)*
                $($new: c.$new,)*
            }
        }

        /// A resolved config with every field set.
        pub fn config_proto(c: &TaskConfig) -> proto::TaskConfig {
            let i = c.to_input();
            proto::TaskConfig {
                num_actions: i.num_actions,
                action_dim: i.action_dim,
                $($name: i.$name,)*
                $($new: i.$new,)*
            }
        }
    };
}
crate::task_config_fields!(config_conversions);

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
        next_seq: pool.next_seq(),
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
    let mut actions = config
        .action_space
        .to_seq(t.actions, t.action_vectors, ActionCount::AtLeastOne)
        .map_err(|e| Error::invalid(e.field("trajectory."), e.message))?;
    actions.truncate(config.max_trajectory_len as usize);
    Ok((actions, t.score))
}

/// A borrowed view of a `StepBatch` for the session layer. `scores` is scratch space
/// for the episode-score map as `(entry, score)` pairs.
pub fn batch_view<'a>(b: &'a proto::StepBatch, scores: &'a mut Vec<(u32, f64)>) -> Batch<'a> {
    scores.clear();
    scores.extend(b.episode_scores.iter().map(|(&i, &s)| (i, s)));
    Batch {
        env_ids: &b.env_ids,
        actions: &b.actions,
        action_vectors: &b.action_vectors,
        rewards: &b.rewards,
        terminated: &b.terminated,
        truncated: &b.truncated,
        values: &b.values,
        next_values: &b.next_values,
        q_values: &b.q_values,
        next_q_values: &b.next_q_values,
        episode_scores: scores,
        abandon: &b.abandon,
    }
}

/// Borrowed views of `Open.resume` for the session layer.
pub fn resume_views(r: &[proto::EnvResume]) -> Vec<Resume<'_>> {
    r.iter()
        .map(|r| Resume {
            env_id: r.env_id,
            actions: &r.actions,
            action_vectors: &r.action_vectors,
            reward_sum: r.reward_sum,
            episode: r.episode,
        })
        .collect()
}

/// The answer to one batch.
pub fn shaped_proto(s: &Shaped<'_>) -> proto::ShapedBatch {
    let o = s.outputs;
    proto::ShapedBatch {
        rewards: o.iter().map(|o| o.reward).collect(),
        knn_rewards: o.iter().map(|o| o.knn_reward).collect(),
        potentials: o.iter().map(|o| o.potential).collect(),
        steps: o
            .iter()
            .map(|o| u32::try_from(o.step).unwrap_or(u32::MAX))
            .collect(),
        knn_active: o.iter().map(|o| o.knn_active).collect(),
        pool_version: s.pool_version,
    }
}

#[cfg(test)]
mod tests;
