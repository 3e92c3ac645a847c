//! Action encoding, the per-step distance δ (SPEC §2), and the one validator of action
//! columns against a task's action space.

use super::config::ActionSpace;

/// One action, borrowed: a discrete index or a continuous vector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ActionRef<'a> {
    /// An index `< num_actions`.
    Discrete(u32),
    /// `action_dim` finite floats.
    Continuous(&'a [f32]),
}

/// A sequence of actions of one kind, stored compactly.
#[derive(Debug, Clone, PartialEq)]
pub enum ActionSeq {
    /// Discrete actions, one index per step.
    Discrete(Vec<u32>),
    /// Continuous actions, `dim` floats per step, row-major.
    Continuous {
        /// Floats per action (m ≥ 1).
        dim: usize,
        /// `len × dim` floats.
        data: Vec<f32>,
    },
}

impl ActionSeq {
    /// An empty sequence of actions of `space`.
    pub fn empty(space: ActionSpace) -> ActionSeq {
        match space {
            ActionSpace::Discrete { .. } => ActionSeq::Discrete(Vec::new()),
            ActionSpace::Continuous { action_dim } => ActionSeq::Continuous {
                dim: action_dim as usize,
                data: Vec::new(),
            },
        }
    }

    /// An empty sequence of the same kind (and dimension).
    pub fn empty_like(&self) -> ActionSeq {
        match self {
            ActionSeq::Discrete(_) => ActionSeq::Discrete(Vec::new()),
            ActionSeq::Continuous { dim, .. } => ActionSeq::Continuous {
                dim: *dim,
                data: Vec::new(),
            },
        }
    }

    /// Number of actions.
    pub fn len(&self) -> usize {
        match self {
            ActionSeq::Discrete(v) => v.len(),
            ActionSeq::Continuous { dim, data } => data.len() / dim,
        }
    }

    /// Whether there are no actions.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The action at step `j`. Panics if `j >= len()` (an internal invariant, never
    /// client-controlled: callers check lengths first).
    pub fn get(&self, j: usize) -> ActionRef<'_> {
        match self {
            ActionSeq::Discrete(v) => ActionRef::Discrete(v[j]),
            ActionSeq::Continuous { dim, data } => {
                ActionRef::Continuous(&data[j * dim..(j + 1) * dim])
            }
        }
    }

    /// Appends an action of the same kind (mismatched kinds are ignored: the service
    /// validates kinds before any step reaches the core).
    pub fn push(&mut self, a: ActionRef<'_>) {
        match (self, a) {
            (ActionSeq::Discrete(v), ActionRef::Discrete(x)) => v.push(x),
            (ActionSeq::Continuous { dim, data }, ActionRef::Continuous(x)) if x.len() == *dim => {
                data.extend_from_slice(x)
            }
            _ => debug_assert!(false, "action kind does not match the sequence"),
        }
    }

    /// Keeps the first `len` actions.
    pub fn truncate(&mut self, len: usize) {
        match self {
            ActionSeq::Discrete(v) => v.truncate(len),
            ActionSeq::Continuous { dim, data } => data.truncate(len * *dim),
        }
    }

    /// Removes every action, keeping the allocation.
    pub fn clear(&mut self) {
        self.truncate(0)
    }
}

/// A column of actions that breaks its task's action space: `column` is `"actions"` or
/// `"action_vectors"`, `index` the offending element when one is to blame. Callers prefix
/// the field path of their message (`steps.`, `trajectory.`, ...).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ActionError {
    /// `"actions"` (discrete) or `"action_vectors"` (continuous).
    pub column: &'static str,
    /// The offending element of the column, if one is to blame.
    pub index: Option<usize>,
    /// What is wrong.
    pub message: String,
}

impl ActionError {
    /// The field path under `prefix`, e.g. `steps.actions[3]`.
    pub fn field(&self, prefix: &str) -> String {
        match self.index {
            Some(i) => format!("{prefix}{}[{i}]", self.column),
            None => format!("{prefix}{}", self.column),
        }
    }
}

impl std::fmt::Display for ActionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.field(""), self.message)
    }
}

/// How many actions a column must hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ActionCount<'a> {
    /// Exactly this many; `what` explains where the number comes from (for the message).
    Exactly(usize, &'a str),
    /// Any number ≥ 1 (a stored or seeded trajectory).
    AtLeastOne,
    /// Any number, zero included (a resumed episode's prefix).
    Any,
}

fn action_error(column: &'static str, index: Option<usize>, message: String) -> ActionError {
    ActionError {
        column,
        index,
        message,
    }
}

impl ActionSpace {
    /// Checks a pair of action columns against this space — the one validator of actions
    /// for batches, trajectories, stored files and resumed episodes: the column of the
    /// other kind is empty, the length fits `count`, discrete actions are `< num_actions`
    /// and continuous ones finite. Returns the number of actions.
    pub fn check_actions(
        &self,
        actions: &[u32],
        action_vectors: &[f32],
        count: ActionCount<'_>,
    ) -> Result<usize, ActionError> {
        let len = match *self {
            ActionSpace::Discrete { num_actions } => {
                if !action_vectors.is_empty() {
                    return Err(action_error(
                        "action_vectors",
                        None,
                        "must be empty for a discrete task (use actions)".into(),
                    ));
                }
                if let ActionCount::Exactly(b, what) = count {
                    if actions.len() != b {
                        return Err(action_error(
                            "actions",
                            None,
                            format!("has {} entries, expected {b} = {what}", actions.len()),
                        ));
                    }
                }
                if let Some((i, a)) = actions.iter().enumerate().find(|(_, &a)| a >= num_actions) {
                    return Err(action_error(
                        "actions",
                        Some(i),
                        format!("action {a} out of range for num_actions {num_actions}"),
                    ));
                }
                actions.len()
            }
            ActionSpace::Continuous { action_dim } => {
                if !actions.is_empty() {
                    return Err(action_error(
                        "actions",
                        None,
                        "must be empty for a continuous task (use action_vectors)".into(),
                    ));
                }
                let m = action_dim as usize;
                match count {
                    ActionCount::Exactly(b, what) => {
                        if Some(action_vectors.len()) != b.checked_mul(m) {
                            return Err(action_error(
                                "action_vectors",
                                None,
                                format!(
                                    "has {} entries, expected {} = {what} x action_dim = {b} x {m}",
                                    action_vectors.len(),
                                    b.saturating_mul(m)
                                ),
                            ));
                        }
                    }
                    ActionCount::AtLeastOne | ActionCount::Any => {
                        if !action_vectors.len().is_multiple_of(m) {
                            return Err(action_error(
                                "action_vectors",
                                None,
                                format!(
                                    "length {} is not a multiple of action_dim {m}",
                                    action_vectors.len()
                                ),
                            ));
                        }
                    }
                }
                if let Some(i) = action_vectors.iter().position(|x| !x.is_finite()) {
                    return Err(action_error(
                        "action_vectors",
                        Some(i),
                        format!("must be finite, got {}", action_vectors[i]),
                    ));
                }
                action_vectors.len() / m
            }
        };
        Ok(len)
    }

    /// Checks a column pair like [`ActionSpace::check_actions`] and takes it as a sequence.
    pub fn to_seq(
        &self,
        actions: Vec<u32>,
        action_vectors: Vec<f32>,
        count: ActionCount<'_>,
    ) -> Result<ActionSeq, ActionError> {
        let len = self.check_actions(&actions, &action_vectors, count)?;
        if len == 0 && count == ActionCount::AtLeastOne {
            return Err(action_error(
                match self {
                    ActionSpace::Discrete { .. } => "actions",
                    ActionSpace::Continuous { .. } => "action_vectors",
                },
                None,
                "must hold at least one action".into(),
            ));
        }
        Ok(match *self {
            ActionSpace::Discrete { .. } => ActionSeq::Discrete(actions),
            ActionSpace::Continuous { action_dim } => ActionSeq::Continuous {
                dim: action_dim as usize,
                data: action_vectors,
            },
        })
    }
}

/// δ(a, a') = ‖e(a) − e(a')‖²: 0 or 2 for one-hot encoded discrete actions, the squared
/// Euclidean distance (in f64) for continuous ones.
#[inline]
pub fn delta(a: ActionRef<'_>, b: ActionRef<'_>) -> f64 {
    match (a, b) {
        (ActionRef::Discrete(x), ActionRef::Discrete(y)) => {
            if x == y {
                0.0
            } else {
                2.0
            }
        }
        (ActionRef::Continuous(x), ActionRef::Continuous(y)) => x
            .iter()
            .zip(y)
            .map(|(&p, &q)| {
                let d = f64::from(p) - f64::from(q);
                d * d
            })
            .sum(),
        _ => {
            debug_assert!(false, "delta between actions of different kinds");
            f64::NAN
        }
    }
}

#[cfg(test)]
mod tests;
