//! Task configuration (SPEC §1.1): defaults, ranges and the resolved form.

use serde::{Deserialize, Serialize};

/// Default `pool_capacity` (|D|).
pub const DEFAULT_POOL_CAPACITY: u32 = 20;
/// Default `start_step` (N).
pub const DEFAULT_START_STEP: u32 = 10;
/// Default `alpha` (weight of r(t)).
pub const DEFAULT_ALPHA: f64 = 0.8;
/// Default `beta` (weight of F).
pub const DEFAULT_BETA: f64 = 0.8;
/// Default `gamma` (discount in F).
pub const DEFAULT_GAMMA: f64 = 0.99;
/// Default `max_trajectory_len`.
pub const DEFAULT_MAX_TRAJECTORY_LEN: u32 = 100_000;

/// The action space of a task.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActionSpace {
    /// Integers `0..num_actions`, encoded one-hot.
    Discrete {
        /// n ≥ 1.
        num_actions: u32,
    },
    /// Vectors of `action_dim` finite floats.
    Continuous {
        /// m ≥ 1.
        action_dim: u32,
    },
}

impl ActionSpace {
    /// Floats per action for continuous spaces, 0 for discrete ones.
    pub fn action_dim(&self) -> usize {
        match *self {
            ActionSpace::Discrete { .. } => 0,
            ActionSpace::Continuous { action_dim } => action_dim as usize,
        }
    }

    /// Number of discrete actions, 0 for continuous spaces.
    pub fn num_actions(&self) -> usize {
        match *self {
            ActionSpace::Discrete { num_actions } => num_actions as usize,
            ActionSpace::Continuous { .. } => 0,
        }
    }
}

/// A task configuration as a client sends it: `None` means "use the default".
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TaskConfigInput {
    /// Discrete action count, 0 if not discrete.
    pub num_actions: u32,
    /// Continuous action dimension, 0 if not continuous.
    pub action_dim: u32,
    /// |D|.
    pub pool_capacity: Option<u32>,
    /// Neighbours.
    pub k: Option<u32>,
    /// N.
    pub start_step: Option<u32>,
    /// Minimum pool size for the kNN term.
    pub min_pool_size: Option<u32>,
    /// α.
    pub alpha: Option<f64>,
    /// β.
    pub beta: Option<f64>,
    /// γ.
    pub gamma: Option<f64>,
    /// Cap on recorded actions per episode.
    pub max_trajectory_len: Option<u32>,
}

/// A configuration value outside its range. `field` is the `TaskConfig` field name.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("config.{field}: {message}")]
pub struct ConfigError {
    /// The offending field, as named in the proto.
    pub field: &'static str,
    /// What is wrong with it.
    pub message: String,
}

fn bad(field: &'static str, message: impl Into<String>) -> ConfigError {
    ConfigError {
        field,
        message: message.into(),
    }
}

/// A fully resolved, validated task configuration (every default filled in).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TaskConfig {
    /// Discrete or continuous actions.
    pub action_space: ActionSpace,
    /// |D| ≥ 1.
    pub pool_capacity: u32,
    /// 1 ≤ k ≤ pool_capacity.
    pub k: u32,
    /// N ≥ 0.
    pub start_step: u32,
    /// 1 ≤ min_pool_size ≤ pool_capacity.
    pub min_pool_size: u32,
    /// α, finite.
    pub alpha: f64,
    /// β, finite.
    pub beta: f64,
    /// 0 ≤ γ ≤ 1.
    pub gamma: f64,
    /// ≥ 1.
    pub max_trajectory_len: u32,
}

impl TaskConfig {
    /// Fills in defaults and checks every range of SPEC §1.1.
    pub fn resolve(input: &TaskConfigInput) -> Result<TaskConfig, ConfigError> {
        let action_space = match (input.num_actions, input.action_dim) {
            (0, 0) => {
                return Err(bad(
                    "num_actions",
                    "exactly one of num_actions and action_dim must be non-zero (both are 0)",
                ))
            }
            (n, 0) => ActionSpace::Discrete { num_actions: n },
            (0, m) => ActionSpace::Continuous { action_dim: m },
            (_, _) => {
                return Err(bad(
                    "action_dim",
                    "exactly one of num_actions and action_dim must be non-zero (both are set)",
                ))
            }
        };
        let pool_capacity = input.pool_capacity.unwrap_or(DEFAULT_POOL_CAPACITY);
        if pool_capacity < 1 {
            return Err(bad("pool_capacity", "must be >= 1"));
        }
        let k = input.k.unwrap_or(pool_capacity);
        if k < 1 || k > pool_capacity {
            return Err(bad(
                "k",
                format!("must be in 1..={pool_capacity} (pool_capacity), got {k}"),
            ));
        }
        let min_pool_size = input.min_pool_size.unwrap_or(pool_capacity);
        if min_pool_size < 1 || min_pool_size > pool_capacity {
            return Err(bad(
                "min_pool_size",
                format!("must be in 1..={pool_capacity} (pool_capacity), got {min_pool_size}"),
            ));
        }
        let alpha = input.alpha.unwrap_or(DEFAULT_ALPHA);
        if !alpha.is_finite() {
            return Err(bad("alpha", format!("must be finite, got {alpha}")));
        }
        let beta = input.beta.unwrap_or(DEFAULT_BETA);
        if !beta.is_finite() {
            return Err(bad("beta", format!("must be finite, got {beta}")));
        }
        let gamma = input.gamma.unwrap_or(DEFAULT_GAMMA);
        if !(0.0..=1.0).contains(&gamma) {
            return Err(bad("gamma", format!("must be in [0, 1], got {gamma}")));
        }
        let max_trajectory_len = input
            .max_trajectory_len
            .unwrap_or(DEFAULT_MAX_TRAJECTORY_LEN);
        if max_trajectory_len < 1 {
            return Err(bad("max_trajectory_len", "must be >= 1"));
        }
        Ok(TaskConfig {
            action_space,
            pool_capacity,
            k,
            start_step: input.start_step.unwrap_or(DEFAULT_START_STEP),
            min_pool_size,
            alpha,
            beta,
            gamma,
            max_trajectory_len,
        })
    }

    /// The resolved configuration as an input with every field set (round-trips through
    /// [`TaskConfig::resolve`]).
    pub fn to_input(&self) -> TaskConfigInput {
        TaskConfigInput {
            num_actions: self.action_space.num_actions() as u32,
            action_dim: self.action_space.action_dim() as u32,
            pool_capacity: Some(self.pool_capacity),
            k: Some(self.k),
            start_step: Some(self.start_step),
            min_pool_size: Some(self.min_pool_size),
            alpha: Some(self.alpha),
            beta: Some(self.beta),
            gamma: Some(self.gamma),
            max_trajectory_len: Some(self.max_trajectory_len),
        }
    }

    /// Whether two resolved configs are the same (floats compared bit for bit).
    pub fn same_as(&self, other: &TaskConfig) -> bool {
        self.action_space == other.action_space
            && self.pool_capacity == other.pool_capacity
            && self.k == other.k
            && self.start_step == other.start_step
            && self.min_pool_size == other.min_pool_size
            && self.alpha.to_bits() == other.alpha.to_bits()
            && self.beta.to_bits() == other.beta.to_bits()
            && self.gamma.to_bits() == other.gamma.to_bits()
            && self.max_trajectory_len == other.max_trajectory_len
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn discrete(n: u32) -> TaskConfigInput {
        TaskConfigInput {
            num_actions: n,
            ..Default::default()
        }
    }

    #[test]
    fn defaults_follow_the_spec() {
        let c = TaskConfig::resolve(&discrete(4)).unwrap();
        assert_eq!(c.pool_capacity, 20);
        assert_eq!(c.k, 20);
        assert_eq!(c.min_pool_size, 20);
        assert_eq!(c.start_step, 10);
        assert_eq!((c.alpha, c.beta, c.gamma), (0.8, 0.8, 0.99));
        assert_eq!(c.max_trajectory_len, 100_000);
        let c = TaskConfig::resolve(&TaskConfigInput {
            pool_capacity: Some(7),
            ..discrete(2)
        })
        .unwrap();
        assert_eq!((c.k, c.min_pool_size), (7, 7));
        assert_eq!(TaskConfig::resolve(&c.to_input()).unwrap(), c);
    }

    #[test]
    fn each_out_of_range_value_names_its_field() {
        let cases: Vec<(TaskConfigInput, &str)> = vec![
            (TaskConfigInput::default(), "num_actions"),
            (
                TaskConfigInput {
                    num_actions: 2,
                    action_dim: 3,
                    ..Default::default()
                },
                "action_dim",
            ),
            (
                TaskConfigInput {
                    pool_capacity: Some(0),
                    ..discrete(2)
                },
                "pool_capacity",
            ),
            (
                TaskConfigInput {
                    k: Some(0),
                    ..discrete(2)
                },
                "k",
            ),
            (
                TaskConfigInput {
                    pool_capacity: Some(3),
                    k: Some(4),
                    ..discrete(2)
                },
                "k",
            ),
            (
                TaskConfigInput {
                    min_pool_size: Some(0),
                    ..discrete(2)
                },
                "min_pool_size",
            ),
            (
                TaskConfigInput {
                    min_pool_size: Some(21),
                    ..discrete(2)
                },
                "min_pool_size",
            ),
            (
                TaskConfigInput {
                    alpha: Some(f64::NAN),
                    ..discrete(2)
                },
                "alpha",
            ),
            (
                TaskConfigInput {
                    beta: Some(f64::INFINITY),
                    ..discrete(2)
                },
                "beta",
            ),
            (
                TaskConfigInput {
                    gamma: Some(1.5),
                    ..discrete(2)
                },
                "gamma",
            ),
            (
                TaskConfigInput {
                    gamma: Some(-0.1),
                    ..discrete(2)
                },
                "gamma",
            ),
            (
                TaskConfigInput {
                    gamma: Some(f64::NAN),
                    ..discrete(2)
                },
                "gamma",
            ),
            (
                TaskConfigInput {
                    max_trajectory_len: Some(0),
                    ..discrete(2)
                },
                "max_trajectory_len",
            ),
        ];
        for (input, field) in cases {
            let err = TaskConfig::resolve(&input).unwrap_err();
            assert_eq!(err.field, field, "{input:?} -> {err}");
        }
    }
}
