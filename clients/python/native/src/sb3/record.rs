//! What `ShapedVecEnv` records of a shaped step, one implementation for both of its
//! paths: the fast one ([`super::vecstep`]) and the general one (Python, through
//! `_native.record_step`).

use numpy::{PyArray1, PyArray2, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::intern;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::arrays::info_dicts;

/// Rows of the wrapper's `_acc` (per env) and `_ended`: R_meta, r(t), F, knn_active, R.
pub(crate) const SUMS: usize = 5;

/// One shaped vector step as the wrapper records it: the answer's columns, the
/// environment rewards sent, the pool version after the step.
pub(crate) struct Shaped<'a> {
    pub(crate) r_meta: &'a [f64],
    pub(crate) knn_rewards: &'a [f64],
    pub(crate) potentials: &'a [f64],
    pub(crate) knn_active: &'a [bool],
    pub(crate) steps: &'a [i64],
    pub(crate) env_rewards: &'a [f64],
    pub(crate) pool_version: u64,
}

/// The one implementation of what `ShapedVecEnv` records of a shaped step, on both of its
/// paths: the step added into the per-episode sums (`_acc`) and `_env_steps`, the six
/// info keys, and for every env whose episode ended (`done`) its sums into
/// `info["shaped_episode"]` and `_ended`, then zeroed with its column of `_taken`.
/// `(alpha, beta)` are the task's weights (the episode's terms are reported weighted).
pub(crate) fn record(
    py: Python<'_>,
    env: &Bound<'_, PyAny>,
    infos: &[Bound<'_, PyDict>],
    done: &[bool],
    shaped: &Shaped<'_>,
    (alpha, beta): (f64, f64),
) -> PyResult<()> {
    let n = done.len();
    let columns = [
        shaped.r_meta.len(),
        shaped.knn_rewards.len(),
        shaped.potentials.len(),
        shaped.knn_active.len(),
        shaped.steps.len(),
        shaped.env_rewards.len(),
        infos.len(),
    ];
    if columns.iter().any(|&len| len != n) {
        return Err(PyValueError::new_err(format!(
            "ShapedVecEnv: a step's columns must all have num_envs = {n} rows, got {columns:?}"
        )));
    }
    let acc = env
        .getattr(intern!(py, "_acc"))?
        .cast_into::<PyArray2<f64>>()?;
    let mut acc_rw = acc.try_readwrite()?;
    let (Ok(acc), true) = (acc_rw.as_slice_mut(), acc.shape() == [SUMS, n]) else {
        return Err(PyValueError::new_err(
            "ShapedVecEnv: _acc is not a C-ordered (5, num_envs) array",
        ));
    };
    for i in 0..n {
        acc[i] += shaped.r_meta[i];
        acc[n + i] += shaped.knn_rewards[i];
        acc[2 * n + i] += shaped.potentials[i];
        acc[3 * n + i] += if shaped.knn_active[i] { 1.0 } else { 0.0 };
        acc[4 * n + i] += shaped.env_rewards[i];
    }
    for (i, info) in infos.iter().enumerate() {
        info.set_item(intern!(py, "original_reward"), shaped.env_rewards[i])?;
        info.set_item(intern!(py, "knn_reward"), shaped.knn_rewards[i])?;
        info.set_item(intern!(py, "potential"), shaped.potentials[i])?;
        info.set_item(intern!(py, "shaping_step"), shaped.steps[i])?;
        info.set_item(intern!(py, "knn_active"), shaped.knn_active[i])?;
        info.set_item(intern!(py, "pool_version"), shaped.pool_version)?;
    }
    if done.iter().any(|&d| d) {
        let taken = env
            .getattr(intern!(py, "_taken"))?
            .cast_into::<PyArray2<f64>>()?;
        let ended = env
            .getattr(intern!(py, "_ended"))?
            .cast_into::<PyArray1<f64>>()?;
        let mut taken_rw = taken.try_readwrite()?;
        let mut ended_rw = ended.try_readwrite()?;
        let (Ok(taken), Ok(ended)) = (taken_rw.as_slice_mut(), ended_rw.as_slice_mut()) else {
            return Err(PyValueError::new_err(
                "ShapedVecEnv: _taken and _ended must be C-ordered",
            ));
        };
        if taken.len() != SUMS * n || ended.len() != SUMS {
            return Err(PyValueError::new_err(
                "ShapedVecEnv: _taken or _ended has the wrong shape",
            ));
        }
        for i in (0..n).filter(|&i| done[i]) {
            let episode = PyDict::new(py);
            episode.set_item(intern!(py, "r"), acc[i])?;
            episode.set_item(intern!(py, "knn"), alpha * acc[n + i])?;
            episode.set_item(intern!(py, "potential"), beta * acc[2 * n + i])?;
            episode.set_item(intern!(py, "l"), shaped.steps[i] + 1)?;
            infos[i].set_item(intern!(py, "shaped_episode"), episode)?;
            for (j, sum) in ended.iter_mut().enumerate() {
                let k = j * n + i;
                *sum += acc[k] - taken[k];
                acc[k] = 0.0;
                taken[k] = 0.0;
            }
        }
    }
    drop(acc_rw);
    let counted: u64 = env.getattr(intern!(py, "_env_steps"))?.extract()?;
    env.setattr(intern!(py, "_env_steps"), counted + n as u64)
}

/// `tamrm._native.record_step(env, infos, dones, env_rewards, result, alpha, beta)`:
/// what `ShapedVecEnv`'s general path records of a step it shaped (see [`record`]), the
/// same code as its fast path's. `result` is the session's `StepResult`; the arrays are
/// read in any dtype numpy converts to the canonical ones.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub fn record_step(
    py: Python<'_>,
    env: &Bound<'_, PyAny>,
    infos: &Bound<'_, PyAny>,
    dones: &Bound<'_, PyAny>,
    env_rewards: &Bound<'_, PyAny>,
    result: &Bound<'_, PyAny>,
    alpha: f64,
    beta: f64,
) -> PyResult<()> {
    fn column<T: numpy::Element + Copy>(obj: &Bound<'_, PyAny>) -> PyResult<Vec<T>> {
        let np = obj.py().import(intern!(obj.py(), "numpy"))?;
        let array = np
            .call_method1(
                intern!(obj.py(), "asarray"),
                (obj, numpy::dtype::<T>(obj.py())),
            )?
            .cast_into::<PyArray1<T>>()?;
        let values = array.readonly().as_array().iter().copied().collect();
        Ok(values)
    }
    let done: Vec<bool> = column(dones)?;
    let n = done.len();
    let Some(info_dicts) = info_dicts(infos, n) else {
        return Err(pyo3::exceptions::PyTypeError::new_err(format!(
            "ShapedVecEnv: infos must be a list or tuple of {n} dicts"
        )));
    };
    let r_meta: Vec<f64> = column(&result.getattr(intern!(py, "rewards"))?)?;
    let knn_rewards: Vec<f64> = column(&result.getattr(intern!(py, "knn_rewards"))?)?;
    let potentials: Vec<f64> = column(&result.getattr(intern!(py, "potentials"))?)?;
    let knn_active: Vec<bool> = column(&result.getattr(intern!(py, "knn_active"))?)?;
    let steps: Vec<i64> = column(&result.getattr(intern!(py, "steps"))?)?;
    let env_rewards: Vec<f64> = column(env_rewards)?;
    let shaped = Shaped {
        r_meta: &r_meta,
        knn_rewards: &knn_rewards,
        potentials: &potentials,
        knn_active: &knn_active,
        steps: &steps,
        env_rewards: &env_rewards,
        pool_version: result.getattr(intern!(py, "pool_version"))?.extract()?,
    };
    record(py, env, &info_dicts, &done, &shaped, (alpha, beta))
}
