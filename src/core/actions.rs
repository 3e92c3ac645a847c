//! Action encoding and the per-step distance δ (SPEC §2).

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
    /// An empty sequence for an action space with `action_dim` floats per action
    /// (0 means discrete).
    pub fn empty(action_dim: usize) -> ActionSeq {
        if action_dim == 0 {
            ActionSeq::Discrete(Vec::new())
        } else {
            ActionSeq::Continuous {
                dim: action_dim,
                data: Vec::new(),
            }
        }
    }

    /// An empty sequence of the same kind (and dimension).
    pub fn empty_like(&self) -> ActionSeq {
        match self {
            ActionSeq::Discrete(_) => ActionSeq::Discrete(Vec::new()),
            ActionSeq::Continuous { dim, .. } => ActionSeq::empty(*dim),
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
mod tests {
    use super::*;

    #[test]
    fn one_hot_distance_is_zero_or_two() {
        assert_eq!(delta(ActionRef::Discrete(3), ActionRef::Discrete(3)), 0.0);
        assert_eq!(delta(ActionRef::Discrete(0), ActionRef::Discrete(3)), 2.0);
    }

    #[test]
    fn continuous_distance_is_squared_euclidean() {
        let d = delta(
            ActionRef::Continuous(&[1.0, -2.0]),
            ActionRef::Continuous(&[0.5, 1.0]),
        );
        assert_eq!(d, 0.25 + 9.0);
    }

    #[test]
    fn sequences_push_get_truncate() {
        let mut s = ActionSeq::empty(2);
        s.push(ActionRef::Continuous(&[1.0, 2.0]));
        s.push(ActionRef::Continuous(&[3.0, 4.0]));
        assert_eq!(s.len(), 2);
        assert_eq!(s.get(1), ActionRef::Continuous(&[3.0, 4.0]));
        s.truncate(1);
        assert_eq!(s.len(), 1);
        let mut d = ActionSeq::empty(0);
        d.push(ActionRef::Discrete(5));
        assert_eq!(d.get(0), ActionRef::Discrete(5));
    }
}
