//! One step's columns, from numpy arrays to the [`Batch`] a session shapes, with the
//! client-side checks that keep a bad number from ever reaching the server (SPEC §8: a rejected batch would end the stream).
//!
//! The Python side (`tamrm._session`) has already checked each argument's type and shape
//! and hands over C-ordered arrays of fixed dtypes (`int64` ids, actions and score rows,
//! `float64` rewards and scores, `bool` flags, `float32` or `float64` reals); the checks
//! here are per entry, and their messages are the Python client's
//! (`tamrm._batch._finite`).

use numpy::{PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyFloat;
use tamrm::session::Batch;

/// Why a number cannot be sent, in the Python client's words.
const NOT_FINITE: &str = "is not finite";
const NOT_F32: &str = "does not fit the 32-bit float it is sent as (|x| <= 3.403e+38)";

/// `tamrm.InvalidArgument`, raised for a number that cannot be sent (nothing is sent).
fn invalid_number(py: Python<'_>, name: &str, index: &str, value: f64, why: &str) -> PyErr {
    let repr = PyFloat::new(py, value)
        .repr()
        .map(|r| r.to_string())
        .unwrap_or_else(|_| value.to_string());
    let message =
        format!("{name}[{index}] = {repr} {why}; nothing was sent, the session is still usable");
    match py
        .import("tamrm._errors")
        .and_then(|m| m.getattr("InvalidArgument"))
        .and_then(|cls| cls.call1((message.clone(),)))
    {
        Ok(err) => PyErr::from_value(err),
        Err(_) => PyValueError::new_err(message),
    }
}

/// The `[i]` or `[i, j]` of flat index `flat` in an array of `shape`.
fn index_of(flat: usize, shape: &[usize]) -> String {
    let mut rest = flat;
    let mut parts = vec![0; shape.len().max(1)];
    for (d, &n) in shape.iter().enumerate().rev() {
        if n > 0 {
            parts[d] = rest % n;
            rest /= n;
        }
    }
    parts
        .iter()
        .map(|i| i.to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

fn wrong_dtype(name: &str, what: &str, obj: &Bound<'_, PyAny>) -> PyErr {
    let got = obj
        .getattr("dtype")
        .map(|d| d.to_string())
        .unwrap_or_else(|_| obj.get_type().to_string());
    PyTypeError::new_err(format!(
        "{name}: expected a numpy array of {what}, got {got}"
    ))
}

/// Appends the integers of `obj` (an `int64` array) to `out`.
fn ints(name: &str, obj: &Bound<'_, PyAny>, out: &mut Vec<i64>) -> PyResult<Vec<usize>> {
    let arr = obj
        .cast::<PyArrayDyn<i64>>()
        .map_err(|_| wrong_dtype(name, "int64", obj))?;
    let ro: PyReadonlyArrayDyn<'_, i64> = arr.readonly();
    out.extend(ro.as_array().iter().copied());
    Ok(ro.shape().to_vec())
}

/// Appends the booleans of `obj` (a `bool` array) to `out`.
fn flags(name: &str, obj: &Bound<'_, PyAny>, out: &mut Vec<bool>) -> PyResult<()> {
    let arr = obj
        .cast::<PyArrayDyn<bool>>()
        .map_err(|_| wrong_dtype(name, "bool", obj))?;
    out.extend(arr.readonly().as_array().iter().copied());
    Ok(())
}

/// Appends the reals of `obj` (a `float64` or `float32` array) to `out` as `f64`, with
/// the shape.
fn reals(name: &str, obj: &Bound<'_, PyAny>, out: &mut Vec<f64>) -> PyResult<Vec<usize>> {
    if let Ok(arr) = obj.cast::<PyArrayDyn<f64>>() {
        let ro = arr.readonly();
        out.extend(ro.as_array().iter().copied());
        Ok(ro.shape().to_vec())
    } else if let Ok(arr) = obj.cast::<PyArrayDyn<f32>>() {
        let ro = arr.readonly();
        out.extend(ro.as_array().iter().map(|&x| f64::from(x)));
        Ok(ro.shape().to_vec())
    } else {
        Err(wrong_dtype(name, "float64 or float32", obj))
    }
}

/// Checks that every number of `xs` can be sent (finite; within f32 range if `f32`).
fn check_finite(
    py: Python<'_>,
    name: &str,
    xs: &[f64],
    shape: &[usize],
    f32: bool,
) -> PyResult<()> {
    let bad = xs
        .iter()
        .position(|x| !x.is_finite() || (f32 && x.abs() > f64::from(f32::MAX)));
    match bad {
        None => Ok(()),
        Some(i) => {
            let v = xs[i];
            let why = if v.is_finite() { NOT_F32 } else { NOT_FINITE };
            Err(invalid_number(py, name, &index_of(i, shape), v, why))
        }
    }
}

fn to_f32(xs: &[f64], out: &mut Vec<f32>) {
    out.clear();
    out.extend(xs.iter().map(|&x| x as f32));
}

/// The task facts the checks need.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Shape {
    /// Environments of the stream.
    pub num_envs: usize,
    /// Discrete tasks: the number of actions; 0 for a continuous task.
    pub num_actions: u32,
}

/// One step's columns, owned (buffers reused from step to step).
#[derive(Debug, Default)]
pub(crate) struct Prepared {
    /// As given (empty: row i is env i).
    pub env_ids: Vec<u32>,
    pub actions: Vec<u32>,
    pub action_vectors: Vec<f32>,
    pub rewards: Vec<f64>,
    pub terminated: Vec<bool>,
    pub truncated: Vec<bool>,
    pub values: Vec<f32>,
    pub next_values: Vec<f32>,
    pub q_values: Vec<f32>,
    pub next_q_values: Vec<f32>,
    pub scores: Vec<(u32, f64)>,
    i64s: Vec<i64>,
    f64s: Vec<f64>,
    f64s2: Vec<f64>,
}

/// The Python arguments of one step (`None` for a column not given).
pub(crate) struct StepArgs<'a, 'py> {
    pub env_ids: Option<&'a Bound<'py, PyAny>>,
    pub actions: &'a Bound<'py, PyAny>,
    pub rewards: &'a Bound<'py, PyAny>,
    pub terminated: Option<&'a Bound<'py, PyAny>>,
    pub truncated: Option<&'a Bound<'py, PyAny>>,
    pub values: Option<(&'a Bound<'py, PyAny>, &'a Bound<'py, PyAny>)>,
    pub q_values: Option<(&'a Bound<'py, PyAny>, &'a Bound<'py, PyAny>)>,
    pub scores: Option<(&'a Bound<'py, PyAny>, &'a Bound<'py, PyAny>)>,
    /// `(terminated, truncated)` already as flags (instead of `terminated`/`truncated`).
    pub ends: Option<(&'a [bool], &'a [bool])>,
    /// V or Q of s and s' from the native critic (instead of `values`/`q_values`).
    pub critic: Option<CriticValues<'a>>,
}

/// The native critic's outputs for one step: V(s) and V(s') (`B` each), or with `q`
/// Q(s, ·) and Q(s', ·) (`B × outputs` each, row-major).
#[derive(Clone, Copy)]
pub(crate) struct CriticValues<'a> {
    pub before: &'a [f32],
    pub after: &'a [f32],
    pub q: bool,
    pub outputs: usize,
}

impl Prepared {
    /// Fills the columns from `args`, checking what the server would reject.
    pub fn fill(&mut self, py: Python<'_>, shape: Shape, args: &StepArgs<'_, '_>) -> PyResult<()> {
        self.clear();
        // Rewards define B.
        let dims = reals("rewards", args.rewards, &mut self.rewards)?;
        check_finite(py, "rewards", &self.rewards, &dims, false)?;
        let b = self.rewards.len();

        if let Some(ids) = args.env_ids {
            ints("env_ids", ids, &mut self.i64s)?;
            let n = shape.num_envs as i64;
            if self.i64s.iter().any(|&e| e < 0 || e >= n) {
                return Err(PyValueError::new_err(format!(
                    "env_ids must be in 0..{}",
                    shape.num_envs - 1
                )));
            }
            self.env_ids.extend(self.i64s.iter().map(|&e| e as u32));
        }
        self.len_is("env_ids", self.env_ids.len(), b, !self.env_ids.is_empty())?;
        if let Some(t) = args.terminated {
            flags("terminated", t, &mut self.terminated)?;
            self.len_is("terminated", self.terminated.len(), b, true)?;
        }
        if let Some(t) = args.truncated {
            flags("truncated", t, &mut self.truncated)?;
            self.len_is("truncated", self.truncated.len(), b, true)?;
        }

        if shape.num_actions > 0 {
            self.i64s.clear();
            ints("actions", args.actions, &mut self.i64s)?;
            let n = i64::from(shape.num_actions);
            if let Some(&bad) = self.i64s.iter().find(|&&a| a < 0 || a >= n) {
                let lo = self.i64s.iter().copied().min().unwrap_or(bad);
                let hi = self.i64s.iter().copied().max().unwrap_or(bad);
                return Err(PyValueError::new_err(format!(
                    "actions must be in 0..{}, got {}",
                    n - 1,
                    if lo < 0 { lo } else { hi }
                )));
            }
            self.actions.extend(self.i64s.iter().map(|&a| a as u32));
            self.len_is("actions", self.actions.len(), b, true)?;
        } else {
            let dims = reals("actions", args.actions, &mut self.f64s)?;
            check_finite(py, "actions", &self.f64s, &dims, true)?;
            to_f32(&self.f64s, &mut self.action_vectors);
        }

        if let Some((terminated, truncated)) = args.ends {
            self.terminated.extend_from_slice(terminated);
            self.truncated.extend_from_slice(truncated);
        }
        if let Some((v, nv)) = args.values {
            self.pair(py, ("values", v), ("next_values", nv), Column::Values)?;
        }
        if let Some(c) = args.critic {
            self.critic_pair(py, c)?;
        }
        if let Some((q, nq)) = args.q_values {
            self.pair(py, ("q_values", q), ("next_q_values", nq), Column::Q)?;
        }
        if let Some((rows, scores)) = args.scores {
            self.i64s.clear();
            self.f64s.clear();
            ints("episode_scores rows", rows, &mut self.i64s)?;
            reals("episode_scores", scores, &mut self.f64s)?;
            for (&row, &score) in self.i64s.iter().zip(&self.f64s) {
                if !score.is_finite() {
                    let index = row.to_string();
                    return Err(invalid_number(
                        py,
                        "episode_scores",
                        &index,
                        score,
                        NOT_FINITE,
                    ));
                }
                let row = u32::try_from(row).map_err(|_| {
                    PyValueError::new_err(format!("episode_scores row {row} is not a row index"))
                })?;
                self.scores.push((row, score));
            }
        }
        Ok(())
    }

    fn clear(&mut self) {
        self.env_ids.clear();
        self.actions.clear();
        self.action_vectors.clear();
        self.rewards.clear();
        self.terminated.clear();
        self.truncated.clear();
        self.values.clear();
        self.next_values.clear();
        self.q_values.clear();
        self.next_q_values.clear();
        self.scores.clear();
        self.i64s.clear();
        self.f64s.clear();
        self.f64s2.clear();
    }

    fn len_is(&self, name: &str, len: usize, b: usize, given: bool) -> PyResult<()> {
        if given && len != b {
            return Err(PyValueError::new_err(format!(
                "{name} must have shape ({b},), got ({len},)"
            )));
        }
        Ok(())
    }

    fn pair(
        &mut self,
        py: Python<'_>,
        (name, a): (&str, &Bound<'_, PyAny>),
        (next_name, b): (&str, &Bound<'_, PyAny>),
        column: Column,
    ) -> PyResult<()> {
        self.f64s.clear();
        self.f64s2.clear();
        let dims = reals(name, a, &mut self.f64s)?;
        check_finite(py, name, &self.f64s, &dims, true)?;
        let next_dims = reals(next_name, b, &mut self.f64s2)?;
        check_finite(py, next_name, &self.f64s2, &next_dims, true)?;
        let (x, nx) = match column {
            Column::Values => (&mut self.values, &mut self.next_values),
            Column::Q => (&mut self.q_values, &mut self.next_q_values),
        };
        to_f32(&self.f64s, x);
        to_f32(&self.f64s2, nx);
        Ok(())
    }

    /// The native critic's values, checked as `pair` checks the arrays (a float32 is
    /// always in range: only finiteness can fail).
    fn critic_pair(&mut self, py: Python<'_>, c: CriticValues<'_>) -> PyResult<()> {
        let (names, column) = if c.q {
            (["q_values", "next_q_values"], Column::Q)
        } else {
            (["values", "next_values"], Column::Values)
        };
        let rows = c.before.len() / c.outputs.max(1);
        let shape = if c.q {
            vec![rows, c.outputs]
        } else {
            vec![rows]
        };
        for (name, xs) in names.into_iter().zip([c.before, c.after]) {
            if let Some(i) = xs.iter().position(|x| !x.is_finite()) {
                let index = index_of(i, &shape);
                return Err(invalid_number(
                    py,
                    name,
                    &index,
                    f64::from(xs[i]),
                    NOT_FINITE,
                ));
            }
        }
        let (x, nx) = match column {
            Column::Values => (&mut self.values, &mut self.next_values),
            Column::Q => (&mut self.q_values, &mut self.next_q_values),
        };
        x.extend_from_slice(c.before);
        nx.extend_from_slice(c.after);
        Ok(())
    }

    /// The session layer's view of the columns.
    pub fn batch(&self) -> Batch<'_> {
        Batch {
            env_ids: &self.env_ids,
            actions: &self.actions,
            action_vectors: &self.action_vectors,
            rewards: &self.rewards,
            terminated: &self.terminated,
            truncated: &self.truncated,
            values: &self.values,
            next_values: &self.next_values,
            q_values: &self.q_values,
            next_q_values: &self.next_q_values,
            episode_scores: &self.scores,
            // The session adds the abandons it keeps.
            abandon: &[],
        }
    }
}

#[derive(Clone, Copy)]
enum Column {
    Values,
    Q,
}
