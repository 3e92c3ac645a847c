//! The potential-based term F = γ·V(s') − V(s) (SPEC §4).

/// Value estimates sent with one step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Values<'a> {
    /// No values: F = 0.
    None,
    /// V(s) and V(s').
    State {
        /// V(s).
        value: f32,
        /// V(s').
        next_value: f32,
    },
    /// Q(s, ·) and Q(s', ·); V = max over actions.
    Q {
        /// Q(s, ·), n entries.
        q: &'a [f32],
        /// Q(s', ·), n entries.
        next_q: &'a [f32],
    },
}

fn max_q(q: &[f32]) -> f64 {
    q.iter()
        .map(|&x| f64::from(x))
        .fold(f64::NEG_INFINITY, f64::max)
}

/// F = γ·V(s') − V(s), with V(s') = 0 when the step `terminated` the episode (a terminal
/// state has potential 0) and the sent V(s') used when it was only truncated. F = 0 when
/// no values were sent. Values are widened from f32 to f64 as sent.
pub fn potential(values: Values<'_>, gamma: f64, terminated: bool) -> f64 {
    let (v, v_next) = match values {
        Values::None => return 0.0,
        Values::State { value, next_value } => (f64::from(value), f64::from(next_value)),
        Values::Q { q, next_q } => (max_q(q), max_q(next_q)),
    };
    let v_next = if terminated { 0.0 } else { v_next };
    gamma * v_next - v
}

#[cfg(test)]
mod tests;
