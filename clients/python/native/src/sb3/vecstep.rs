//! `tamrm.sb3.ShapedVecEnv`'s fast path: one Stable-Baselines3 vector step shaped in one
//! native call, with no Python code of ours in the training loop's step.
//!
//! [`VecStep::step`] takes what the wrapped `VecEnv.step_wait` returned and does all of
//! `ShapedVecEnv`'s per-step work: it splits `dones` into terminated and truncated (by
//! `TimeLimit.truncated`), evaluates the model's critic natively ([`super::mlp`]), shapes the
//! step on the session, adds the answer into the wrapper's per-episode sums, writes the
//! six info keys (and `shaped_episode` where an episode ended) and returns R_meta as
//! float32. It reads and writes the wrapper's own attributes (`_obs`, `_acc`, `_taken`,
//! `_ended`, `_env_steps`, `_values`), so the wrapper's general path (Python) can take
//! over on any step and finds them as it left them. What a shaped step records is one
//! function, [`record`], which the general path calls too (`_native.record_step`).
//!
//! Whatever it does not handle it declines before changing anything (it returns `None`):
//! an action, observation or reward that is not the canonical numpy array, a `value_fn`
//! that is not a model's native critic, an episode end with a `score_key`, a closed
//! session. The general path then does the step (and raises what there is to raise).
//!
//! The critic is evaluated once per observation: V(s') of one step is V(s) of the next
//! while the observation object is the wrapper's `_obs` and no parameter of the critic
//! changed (their storage pointers and in-place version counters, which every optimizer
//! step bumps); otherwise V(s) and V(s') are evaluated in one batch. A row's value depends
//! only on that row and the weights, so either way the values are the general path's, bit
//! for bit (`tests/test_sb3_fast_path.py` compares whole training runs).

use std::sync::{Mutex, MutexGuard};

use numpy::{PyArray1, PyArray2, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::intern;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple, PyType};

use super::arrays::{float_rows, info_dicts, is_ndarray};
use super::mlp::Mlp;
use super::record::{record, Shaped};
use crate::columns::{CriticValues, StepArgs};
use crate::stream::NativeStream;

/// The native critic of one policy object, with what tells whether it is still current.
struct Critic {
    /// The policy it was built for (`model.policy`).
    policy: Py<PyAny>,
    mlp: Py<Mlp>,
    /// Whether it gives Q-values (a DQN's Q-network) rather than V.
    q: bool,
    /// The torch parameters its weights are views of, and their storage pointers then.
    params: Vec<Py<PyAny>>,
    ptrs: Vec<u64>,
}

impl Critic {
    /// The parameters' version counters, or `None` when a parameter's storage was replaced
    /// (the views are stale: the critic must be built again).
    fn versions(&self, py: Python<'_>) -> PyResult<Option<Vec<i64>>> {
        let mut versions = Vec::with_capacity(self.params.len());
        for (p, &ptr) in self.params.iter().zip(&self.ptrs) {
            let p = p.bind(py);
            if p.call_method0(intern!(py, "data_ptr"))?.extract::<u64>()? != ptr {
                return Ok(None);
            }
            versions.push(p.getattr(intern!(py, "_version"))?.extract::<i64>()?);
        }
        Ok(Some(versions))
    }
}

/// A current critic: the network, whether it gives Q-values, its parameters' versions.
type CurrentCritic<'py> = (Bound<'py, Mlp>, bool, Vec<i64>);

/// What carries over from one fast step to the next.
#[derive(Default)]
struct State {
    critic: Option<Critic>,
    /// The critic's input: the rows of s (`n × d`), then those of s'.
    x: Vec<f32>,
    /// The observation object whose rows are `x[..n * d]` (the last fast step's s').
    rows_of: Option<Py<PyAny>>,
    /// The critic's output on `x[..n * d]` and the parameters' versions it was computed at.
    values: Option<(Vec<f32>, Vec<i64>)>,
    /// Steps done here, and the observation rows the critic evaluated in them (the
    /// tests count them).
    steps: u64,
    critic_rows: u64,
}

/// `tamrm._native.VecStep(stream, value_fn_type, action_dim, alpha, beta)`: the fast
/// path of one `ShapedVecEnv` on the session `stream`. `value_fn_type` is
/// `tamrm.sb3.ModelValueFn` (the only value function it evaluates itself), `action_dim` 0
/// for a discrete task, `alpha` and `beta` the task's weights (for `shaped_episode`).
#[pyclass(frozen, module = "tamrm._native")]
pub struct VecStep {
    stream: Py<NativeStream>,
    value_fn_type: Py<PyType>,
    action_dim: usize,
    alpha: f64,
    beta: f64,
    state: Mutex<State>,
}

fn lock(state: &Mutex<State>) -> MutexGuard<'_, State> {
    state.lock().unwrap_or_else(|e| e.into_inner())
}

impl VecStep {
    /// Whether `actions` is the canonical array: int64 `(n,)` for a discrete task,
    /// float32 or float64 `(n, action_dim)` for a continuous one.
    fn canonical_actions(&self, py: Python<'_>, actions: &Bound<'_, PyAny>, n: usize) -> bool {
        if !is_ndarray(py, actions) {
            return false;
        }
        if self.action_dim == 0 {
            return actions.cast::<PyArray1<i64>>().is_ok_and(|a| a.len() == n);
        }
        let shape = [n, self.action_dim];
        actions
            .cast::<PyArray2<f32>>()
            .is_ok_and(|a| a.shape() == shape)
            || actions
                .cast::<PyArray2<f64>>()
                .is_ok_and(|a| a.shape() == shape)
    }

    /// The current native critic of `value_fn` (a `ModelValueFn`) for `policy`, and its
    /// parameters' versions; `None`: the policy has no native critic (or gives no
    /// values). A critic whose
    /// parameters' storage changed is built again (by `value_fn._critic_of`, which keeps
    /// the Python side's cache in step).
    fn critic_for<'py>(
        py: Python<'py>,
        state: &mut State,
        value_fn: &Bound<'py, PyAny>,
        policy: &Bound<'py, PyAny>,
    ) -> PyResult<Option<CurrentCritic<'py>>> {
        let mut versions = None;
        if let Some(c) = &state.critic {
            if c.policy.bind(py).is(policy) {
                versions = c.versions(py)?;
            }
        }
        if versions.is_none() {
            state.critic = None;
            state.values = None;
            let found = value_fn.call_method1(intern!(py, "_critic_of"), (policy,))?;
            let (native, q): (Bound<'_, PyAny>, bool) = found.extract()?;
            if native.is_none() {
                return Ok(None);
            }
            let mlp = native.getattr(intern!(py, "_mlp"))?.cast_into::<Mlp>()?;
            let params: Vec<Py<PyAny>> = native.getattr(intern!(py, "_params"))?.extract()?;
            let ptrs: Vec<u64> = native.getattr(intern!(py, "_ptrs"))?.extract()?;
            let critic = Critic {
                policy: policy.clone().unbind(),
                mlp: mlp.unbind(),
                q,
                params,
                ptrs,
            };
            versions = critic.versions(py)?;
            state.critic = Some(critic);
        }
        Ok(match (&state.critic, versions) {
            (Some(c), Some(v)) => Some((c.mlp.bind(py).clone(), c.q, v)),
            _ => None,
        })
    }
}

/// What the critic's values of one step are computed from.
#[derive(Clone, Copy)]
struct Inputs<'a, 'py> {
    /// The wrapper (its `_obs` is s).
    env: &'a Bound<'py, PyAny>,
    /// Its `value_fn` (a `ModelValueFn`) and the model's current policy.
    value_fn: &'a Bound<'py, PyAny>,
    policy: &'a Bound<'py, PyAny>,
    /// s'.
    obs: &'a Bound<'py, PyAny>,
    infos: &'a [Bound<'py, PyDict>],
    truncated: &'a [bool],
}

/// The per-step critic outputs: V/Q of s and of s' (`n × outputs` each).
struct Values {
    before: Vec<f32>,
    after: Vec<f32>,
    q: bool,
    outputs: usize,
    /// The parameters' versions they were computed at.
    versions: Vec<i64>,
    /// Rows of s' replaced by a truncated env's `terminal_observation`: (row, its rows
    /// as observed), put back for the next step's s.
    replaced: Vec<(usize, Vec<f32>)>,
}

#[pymethods]
impl VecStep {
    #[new]
    fn new(
        stream: Py<NativeStream>,
        value_fn_type: Py<PyType>,
        action_dim: usize,
        alpha: f64,
        beta: f64,
    ) -> VecStep {
        VecStep {
            stream,
            value_fn_type,
            action_dim,
            alpha,
            beta,
            state: Mutex::new(State::default()),
        }
    }

    /// Steps done by this fast path.
    #[getter]
    fn steps(&self) -> u64 {
        lock(&self.state).steps
    }

    /// Observation rows the critic evaluated in those steps.
    #[getter]
    fn critic_rows(&self) -> u64 {
        lock(&self.state).critic_rows
    }

    /// Shapes the vector step `(obs, rewards, dones, infos)` of the wrapper `env` whose
    /// actions were `actions`: R_meta as float32, or `None` (nothing changed) when the
    /// step is one for the general path. Errors are the session's step errors.
    #[pyo3(signature = (env, actions, obs, rewards, dones, infos))]
    #[allow(clippy::too_many_arguments)]
    fn step<'py>(
        &self,
        py: Python<'py>,
        env: &Bound<'py, PyAny>,
        actions: &Bound<'py, PyAny>,
        obs: &Bound<'py, PyAny>,
        rewards: &Bound<'py, PyAny>,
        dones: &Bound<'py, PyAny>,
        infos: &Bound<'py, PyAny>,
    ) -> PyResult<Option<Bound<'py, PyArray1<f32>>>> {
        let stream = self.stream.get();
        let mut guard = stream.lock();
        if guard.closed() {
            return Ok(None);
        }
        let n = guard.num_envs();
        let mut state = lock(&self.state);

        // The step's arrays, as SB3's VecEnvs give them.
        let Ok(done_array) = dones.cast::<PyArray1<bool>>() else {
            return Ok(None);
        };
        let Ok(done_ro) = done_array.try_readonly() else {
            return Ok(None);
        };
        let Ok(done) = done_ro.as_slice() else {
            return Ok(None);
        };
        let rewards_ok = is_ndarray(py, rewards)
            && (rewards.cast::<PyArray1<f32>>().is_ok() || rewards.cast::<PyArray1<f64>>().is_ok());
        if done.len() != n
            || !rewards_ok
            || !self.canonical_actions(py, actions, n)
            || obs.is_instance_of::<PyTuple>()
        {
            return Ok(None);
        }
        let any_done = done.iter().any(|&d| d);
        if any_done && !env.getattr(intern!(py, "score_key"))?.is_none() {
            return Ok(None);
        }
        // A list of dicts (DummyVecEnv), or a tuple of them (SubprocVecEnv).
        let Some(info_dicts) = info_dicts(infos, n) else {
            return Ok(None);
        };
        // SB3's dones split by TimeLimit.truncated (as `_end_flags`).
        let (mut terminated, mut truncated) = (Vec::new(), Vec::new());
        if any_done {
            for (i, &d) in done.iter().enumerate() {
                let cut = d
                    && match info_dicts[i].get_item(intern!(py, "TimeLimit.truncated"))? {
                        Some(v) => v.is_truthy()?,
                        None => false,
                    };
                truncated.push(cut);
                terminated.push(d && !cut);
            }
        }

        let value_fn = env.getattr(intern!(py, "value_fn"))?;
        let values = if value_fn.is_none() {
            state.rows_of = None;
            state.values = None;
            None
        } else {
            if !value_fn.get_type().is(self.value_fn_type.bind(py))
                || !value_fn.getattr(intern!(py, "fast"))?.is_truthy()?
                || !is_ndarray(py, obs)
            {
                return Ok(None);
            }
            let policy = value_fn
                .getattr(intern!(py, "model"))?
                .getattr(intern!(py, "policy"))?;
            let inputs = Inputs {
                env,
                value_fn: &value_fn,
                policy: &policy,
                obs,
                infos: &info_dicts,
                truncated: &truncated,
            };
            match Self::critic_values(py, &mut state, &inputs, n)? {
                Some(v) => Some(v),
                None => return Ok(None),
            }
        };

        let args = StepArgs {
            env_ids: None,
            actions,
            rewards,
            terminated: None,
            truncated: None,
            values: None,
            q_values: None,
            scores: None,
            ends: any_done.then_some((&terminated[..], &truncated[..])),
            critic: values.as_ref().map(|v| CriticValues {
                before: &v.before,
                after: &v.after,
                q: v.q,
                outputs: v.outputs,
            }),
        };
        let answer = guard.run(py, &args)?;

        // The wrapper's per-episode sums and the info keys (`record` checks that every
        // column of the answer has `n` rows before it changes anything).
        let shaped = Shaped {
            r_meta: &answer.rewards,
            knn_rewards: &answer.knn_rewards,
            potentials: &answer.potentials,
            knn_active: &answer.knn_active,
            steps: &answer.steps,
            env_rewards: guard.sent_rewards(),
            pool_version: answer.pool_version,
        };
        record(py, env, &info_dicts, done, &shaped, (self.alpha, self.beta))?;

        // What the next step starts from.
        match values {
            Some(v) => {
                let d = state.x.len() / (2 * n);
                let (before, after) = state.x.split_at_mut(n * d);
                for (row, raw) in &v.replaced {
                    after[row * d..(row + 1) * d].copy_from_slice(raw);
                }
                before.copy_from_slice(after);
                state.rows_of = Some(obs.clone().unbind());
                state.values = v.replaced.is_empty().then_some((v.after, v.versions));
            }
            None => state.rows_of = None,
        }
        state.steps += 1;
        env.setattr(intern!(py, "_obs"), obs)?;
        env.setattr(intern!(py, "_values"), py.None())?;
        Ok(Some(PyArray1::from_iter(
            py,
            answer.rewards.iter().map(|&r| r as f32),
        )))
    }
}

impl VecStep {
    /// The critic's values of s (the wrapper's `_obs`) and s' (`obs`, with a truncated
    /// env's row taken from its `terminal_observation`); `None`: the general path's step.
    fn critic_values(
        py: Python<'_>,
        state: &mut State,
        inputs: &Inputs<'_, '_>,
        n: usize,
    ) -> PyResult<Option<Values>> {
        let Inputs {
            env,
            value_fn,
            policy,
            obs,
            infos,
            truncated,
        } = *inputs;
        let Some((mlp, q, versions)) = Self::critic_for(py, state, value_fn, policy)? else {
            return Ok(None);
        };
        let mlp = mlp.get();
        let (d, outputs) = (mlp.inputs(), mlp.outputs());
        if !q && outputs != 1 {
            return Ok(None);
        }
        let prev = env.getattr(intern!(py, "_obs"))?;
        let mut x = std::mem::take(&mut state.x);
        // (An error below leaves `state.x` empty: then the rows are read again.)
        let same =
            x.len() == 2 * n * d && state.rows_of.as_ref().is_some_and(|o| o.bind(py).is(&prev));
        x.resize(2 * n * d, 0.0);
        let (before, after) = x.split_at_mut(n * d);
        let mut ok = same || float_rows(&prev, Some(n), before).is_some();
        ok = ok && float_rows(obs, Some(n), after).is_some();
        let mut replaced = Vec::new();
        for (row, &cut) in truncated.iter().enumerate() {
            if !ok || !cut {
                continue;
            }
            let Some(last) = infos[row].get_item(intern!(py, "terminal_observation"))? else {
                continue;
            };
            if last.is_none() {
                continue;
            }
            let slot = &mut after[row * d..(row + 1) * d];
            replaced.push((row, slot.to_vec()));
            ok = is_ndarray(py, &last) && float_rows(&last, None, slot).is_some();
        }
        if !same {
            state.rows_of = None;
            state.values = None;
        }
        let reuse = state.values.take().filter(|(_, v)| same && *v == versions);
        let result = if !ok {
            None
        } else if let Some((before_values, _)) = reuse {
            let after_values = mlp.eval(py, after, n)?;
            state.critic_rows += n as u64;
            Some((before_values, after_values))
        } else {
            let mut out = mlp.eval(py, &x, 2 * n)?;
            state.critic_rows += 2 * n as u64;
            let after_values = out.split_off(n * outputs);
            Some((out, after_values))
        };
        state.x = x;
        Ok(result.map(|(before, after)| Values {
            before,
            after,
            q,
            outputs,
            versions,
            replaced,
        }))
    }
}
