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
/// Default `gate_potential` (v1.1).
pub const DEFAULT_GATE_POTENTIAL: bool = false;
/// Default `require_score_spread` (v1.3): the paper's rule, active whatever the scores.
pub const DEFAULT_REQUIRE_SCORE_SPREAD: bool = false;

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

/// The optional fields of a task configuration (SPEC §1.1), each written once: calls
/// `$m!` with the list `doc name: type, ... ; doc name: type, ...` (the fields of the first
/// release; then the fields added since). Every per-field mapping (the input and
/// resolved structs, the proto conversion, comparisons, the diff) is generated from it,
/// and a test checks the list against the proto's `TaskConfig`.
#[doc(hidden)]
#[macro_export]
macro_rules! task_config_fields {
    ($m:ident) => {
        $m! {
            /// |D|, the most trajectories the pool keeps, ≥ 1 [20].
            pool_capacity: u32,
            /// Neighbours of the kNN reward, 1 ≤ k ≤ pool_capacity [= pool_capacity].
            k: u32,
            /// N ≥ 0: the first step index at which the kNN term may be non-zero [10].
            start_step: u32,
            /// The kNN term is active only with at least this many trajectories,
            /// 1 ≤ min_pool_size ≤ pool_capacity [= pool_capacity].
            min_pool_size: u32,
            /// α, the weight of the kNN term, finite [0.8].
            alpha: f64,
            /// β, the weight of the potential term, finite [0.8].
            beta: f64,
            /// γ of the potential term, 0 ≤ γ ≤ 1 [0.99].
            gamma: f64,
            /// Actions recorded per episode at most, ≥ 1 [100000].
            max_trajectory_len: u32,
            ;
            // Fields added after the first release: stored data that lacks them reads
            // them as their default.
            /// (v1.1) F counts only on steps where the kNN term is active [false].
            gate_potential: bool,
            /// (v1.3) The kNN term is active only while the pool's scores differ
            /// (S_max > S_min) [false].
            require_score_spread: bool,
        }
    };
}

/// Bit-exact equality of configuration values (floats compared bit for bit, so that an
/// idempotent `CreateTask` means exactly the same config).
trait SameBits {
    fn same_bits(&self, other: &Self) -> bool;
}
impl SameBits for u32 {
    fn same_bits(&self, other: &Self) -> bool {
        self == other
    }
}
impl SameBits for bool {
    fn same_bits(&self, other: &Self) -> bool {
        self == other
    }
}
impl SameBits for f64 {
    fn same_bits(&self, other: &Self) -> bool {
        self.to_bits() == other.to_bits()
    }
}

macro_rules! define_config_structs {
    ($($(#[doc = $doc:literal])* $name:ident : $ty:ty,)*
     ; $($(#[doc = $ndoc:literal])* $new:ident : $nty:ty,)*) => {
        /// A task configuration as a client sends it: `None` means "use the default".
        #[derive(Debug, Clone, Default, PartialEq)]
        pub struct TaskConfigInput {
            /// Discrete action count n, 0 if not discrete.
            pub num_actions: u32,
            /// Continuous action dimension m, 0 if not continuous.
            pub action_dim: u32,
            $($(#[doc = $doc])* pub $name: Option<$ty>,)*
            $($(#[doc = $ndoc])* pub $new: Option<$nty>,)*
        }

        /// A fully resolved, validated task configuration (every default filled in).
        /// Stored as JSON by the disk store: a field added after the first release reads
        /// as its default when missing, so older data stays readable.
        #[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
        pub struct TaskConfig {
            /// Discrete or continuous actions.
            pub action_space: ActionSpace,
            $($(#[doc = $doc])* pub $name: $ty,)*
            $($(#[doc = $ndoc])* #[serde(default)] pub $new: $nty,)*
        }

        impl TaskConfig {
            /// Every `TaskConfig` field name of the proto, in field-number order.
            pub const FIELD_NAMES: &'static [&'static str] =
                &["num_actions", "action_dim", $(stringify!($name),)* $(stringify!($new),)*];

            /// The resolved configuration as an input with every field set (round-trips
            /// through [`TaskConfig::resolve`]).
            pub fn to_input(&self) -> TaskConfigInput {
                TaskConfigInput {
                    num_actions: self.action_space.num_actions() as u32,
                    action_dim: self.action_space.action_dim() as u32,
                    $($name: Some(self.$name),)*
                    $($new: Some(self.$new),)*
                }
            }

            /// Whether two resolved configs are the same (floats compared bit for bit).
            pub fn same_as(&self, other: &TaskConfig) -> bool {
                self.action_space == other.action_space
                    $(&& self.$name.same_bits(&other.$name))*
                    $(&& self.$new.same_bits(&other.$new))*
            }

            /// The fields that differ, as `name: existing X, requested Y`, in the user's
            /// terms (values, not Rust's `Option`s). `sent` is the input `requested` was
            /// resolved from: a differing field it left unset is marked as a default, so
            /// the user learns why a field they never sent is named.
            pub fn diff(&self, requested: &TaskConfig, sent: &TaskConfigInput) -> Vec<String> {
                let default = |was_sent: bool| if was_sent { "" } else { " (not sent: the default)" };
                let mut out = Vec::new();
                let (a, b) = (self.action_space, requested.action_space);
                if a.num_actions() != b.num_actions() {
                    out.push(format!(
                        "num_actions: existing {}, requested {}",
                        a.num_actions(), b.num_actions()
                    ));
                }
                if a.action_dim() != b.action_dim() {
                    out.push(format!(
                        "action_dim: existing {}, requested {}",
                        a.action_dim(), b.action_dim()
                    ));
                }
                $(if !self.$name.same_bits(&requested.$name) {
                    out.push(format!(
                        "{}: existing {}, requested {}{}",
                        stringify!($name), self.$name, requested.$name,
                        default(sent.$name.is_some())
                    ));
                })*
                $(if !self.$new.same_bits(&requested.$new) {
                    out.push(format!(
                        "{}: existing {}, requested {}{}",
                        stringify!($new), self.$new, requested.$new,
                        default(sent.$new.is_some())
                    ));
                })*
                out
            }
        }
    };
}
task_config_fields!(define_config_structs);

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

/// Bytes one environment's episode state keeps per pool trajectory at most (its seq, its
/// distance or mismatch count, and the spare buffer a re-sync reuses).
pub const ENV_BYTES_PER_TRAJECTORY: u64 = 24;

impl ActionSpace {
    /// Bytes one recorded action takes: 4 for a discrete action, 4 per component of a
    /// continuous one.
    pub fn action_bytes(&self) -> u64 {
        4 * (self.action_dim().max(1) as u64)
    }
}

impl TaskConfig {
    /// The most bytes of actions the task's pool can hold: `pool_capacity` trajectories of
    /// `max_trajectory_len` actions (what the server limit `max_pool_bytes` bounds).
    pub fn pool_bytes_bound(&self) -> u64 {
        u64::from(self.pool_capacity)
            .saturating_mul(u64::from(self.max_trajectory_len))
            .saturating_mul(self.action_space.action_bytes())
    }

    /// The most bytes one environment of a Shape stream can hold: its episode's recorded
    /// actions (`max_trajectory_len` at most) and its state per pool trajectory.
    pub fn env_bytes_bound(&self) -> u64 {
        u64::from(self.max_trajectory_len)
            .saturating_mul(self.action_space.action_bytes())
            .saturating_add(u64::from(self.pool_capacity) * ENV_BYTES_PER_TRAJECTORY)
    }

    /// Checks a resolved configuration read back from storage against every range of
    /// SPEC §1.1, as [`TaskConfig::resolve`] checks a client's: stored data is never
    /// trusted to satisfy what the engine relies on (e.g. `k >= 1`).
    pub fn check(&self) -> Result<(), ConfigError> {
        let again = TaskConfig::resolve(&self.to_input())?;
        if again.same_as(self) {
            Ok(())
        } else {
            Err(bad(
                "config",
                "does not resolve to itself (a field out of its range)",
            ))
        }
    }

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
            gate_potential: input.gate_potential.unwrap_or(DEFAULT_GATE_POTENTIAL),
            require_score_spread: input
                .require_score_spread
                .unwrap_or(DEFAULT_REQUIRE_SCORE_SPREAD),
        })
    }
}

#[cfg(test)]
mod tests;
