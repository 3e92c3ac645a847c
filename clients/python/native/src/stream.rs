//! One shaping session as Python sees it (`tamrm.Session` wraps it): the columns in, the
//! transport's round trip with the GIL released, the answer out as numpy arrays.

use std::sync::Mutex;

use numpy::{IntoPyArray, PyArray1, PyArray2};
use prost::Message;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use tamrm::proto;
use tonic::Code;

use crate::columns::{Answer, Prepared, Shape, StepArgs};
use crate::tracker::Tracker;
use crate::{engine, remote, status};

/// Why a step failed.
pub(crate) enum StepError {
    /// The server's (or the engine's) answer.
    Status(tonic::Status),
    /// A signal handler raised (Ctrl-C) while waiting: the stream is gone.
    Interrupted(PyErr),
}

impl From<tonic::Status> for StepError {
    fn from(s: tonic::Status) -> StepError {
        StepError::Status(s)
    }
}

/// Where a stream's batches go.
pub(crate) enum Transport {
    /// The embedded engine: the session layer in-process.
    Engine(engine::EngineStream),
    /// A `Shape` stream to a server.
    Remote(remote::RemoteStream),
}

impl Transport {
    /// Shapes one batch. A rejected batch (INVALID_ARGUMENT) changed nothing: a remote
    /// stream is re-opened with every episode resumed before the error is returned.
    fn step(&mut self, batch: &Prepared, tracker: &Tracker) -> Result<Answer, StepError> {
        match self {
            Transport::Engine(e) => e.step(batch).map_err(StepError::Status),
            Transport::Remote(r) => r.step(batch, tracker),
        }
    }

    fn close(&mut self) {
        match self {
            Transport::Engine(e) => e.close(),
            Transport::Remote(r) => r.close(),
        }
    }
}

pub(crate) struct Inner {
    transport: Transport,
    tracker: Tracker,
    shape: Shape,
    prepared: Prepared,
    closed: bool,
    /// The pool version after the last answered batch (or at open).
    pool_version: u64,
}

impl Inner {
    /// The environments of the stream.
    pub(crate) fn num_envs(&self) -> usize {
        self.shape.num_envs
    }

    /// Whether the session is closed.
    pub(crate) fn closed(&self) -> bool {
        self.closed
    }

    /// The environment rewards of the last batch, as sent.
    pub(crate) fn sent_rewards(&self) -> &[f64] {
        &self.prepared.rewards
    }

    /// Checks `args`, shapes them on the transport and records the answer (the one step
    /// path of `step` and `step_vec`). A closed session, a bad argument or a failed
    /// round trip is an error; after one that is not a rejected batch the session is
    /// closed.
    pub(crate) fn run(&mut self, py: Python<'_>, args: &StepArgs<'_, '_>) -> PyResult<Answer> {
        if self.closed {
            return Err(closed_error());
        }
        self.prepared.fill(py, self.shape, args)?;
        let b = self.prepared.len();
        if b == 0 {
            // Nothing is sent; pending abandons wait for a batch with entries.
            return Ok(Answer::default());
        }
        self.tracker.take_abandons(&mut self.prepared.abandon);
        let result = {
            let Inner {
                transport,
                tracker,
                prepared,
                ..
            } = &mut *self;
            py.detach(|| transport.step(prepared, tracker))
        };
        let answer = match result {
            Ok(answer) => answer,
            Err(StepError::Interrupted(interrupt)) => {
                self.closed = true;
                self.tracker.discard_episodes();
                return Err(interrupt);
            }
            Err(StepError::Status(err)) => {
                if err.code() == Code::InvalidArgument {
                    // Rejected, nothing applied: the stream goes on (re-opened if remote);
                    // the abandons travel with the next batch.
                    let sent = std::mem::take(&mut self.prepared.abandon);
                    self.tracker.restore_abandons(&sent);
                    if let Transport::Remote(r) = &self.transport {
                        if r.broken() {
                            self.closed = true;
                            self.tracker.discard_episodes();
                        }
                    }
                } else {
                    self.closed = true;
                    self.transport.close();
                    self.tracker.discard_episodes();
                }
                return Err(crate::status_error(&err));
            }
        };
        if answer.consistent_len() != Some(b) {
            self.closed = true;
            self.transport.close();
            return Err(status(
                Code::Internal,
                format!(
                    "the server answered {} entries for a batch of {b}",
                    answer.rewards.len()
                ),
            ));
        }
        if let Some((env, step)) = self.tracker.ignored_abandon(&self.prepared, &answer) {
            self.closed = true;
            self.transport.close();
            return Err(status(
                Code::Unimplemented,
                format!(
                    "the server ignored StepBatch.abandon (SPEC v1.1 §12): env {env} went on \
                     with its abandoned episode at step {step}; upgrade the server"
                ),
            ));
        }
        self.tracker.record(&self.prepared, &answer);
        self.pool_version = answer.pool_version;
        Ok(answer)
    }
}

/// An open session: `tamrm._session.Session` holds one.
#[pyclass(frozen, module = "tamrm._native")]
pub struct NativeStream {
    inner: Mutex<Inner>,
    /// The `Task` message answering `Open`, encoded.
    opened: Vec<u8>,
}

/// What a step returns to Python: the float columns as the rows of one `(3, B)` array
/// (R_meta, r(t), F: one allocation instead of three), the step indices, knn_active,
/// and the pool version.
type StepAnswer<'py> = (
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray1<bool>>,
    u64,
);

impl NativeStream {
    /// A stream over `transport`, opened on `task` (the answer to `Open`, whichever
    /// transport gave it: its config tells the action space, its stats the pool version).
    pub(crate) fn new(transport: Transport, task: &proto::Task, num_envs: usize) -> NativeStream {
        let config = task.config.unwrap_or_default();
        let (num_actions, action_dim) = if config.num_actions > 0 {
            (config.num_actions, 0)
        } else {
            (0, config.action_dim as usize)
        };
        let keep = matches!(transport, Transport::Remote(_));
        NativeStream {
            inner: Mutex::new(Inner {
                transport,
                tracker: Tracker::new(num_envs, action_dim, keep),
                shape: Shape {
                    num_envs,
                    num_actions,
                },
                prepared: Prepared::default(),
                closed: false,
                pool_version: task.stats.map_or(0, |s| s.pool_version),
            }),
            opened: task.encode_to_vec(),
        }
    }

    pub(crate) fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }
}

fn closed_error() -> PyErr {
    status(Code::Cancelled, "the session is closed")
}

#[pymethods]
impl NativeStream {
    /// The `Task` message the server answered `Open` with (serialized).
    #[getter]
    fn opened<'py>(&self, py: Python<'py>) -> Bound<'py, PyBytes> {
        PyBytes::new(py, &self.opened)
    }

    /// Shapes one step. Arrays as documented in `tamrm._session`; returns
    /// `(parts, steps, knn_active, pool_version)`, `parts` the `(3, B)` float64 rows
    /// rewards, knn_rewards, potentials.
    #[pyo3(signature = (env_ids, actions, rewards, terminated, truncated, values, next_values, q_values, next_q_values, score_rows, score_values))]
    #[allow(clippy::too_many_arguments)]
    fn step<'py>(
        &self,
        py: Python<'py>,
        env_ids: Option<Bound<'py, PyAny>>,
        actions: Bound<'py, PyAny>,
        rewards: Bound<'py, PyAny>,
        terminated: Option<Bound<'py, PyAny>>,
        truncated: Option<Bound<'py, PyAny>>,
        values: Option<Bound<'py, PyAny>>,
        next_values: Option<Bound<'py, PyAny>>,
        q_values: Option<Bound<'py, PyAny>>,
        next_q_values: Option<Bound<'py, PyAny>>,
        score_rows: Option<Bound<'py, PyAny>>,
        score_values: Option<Bound<'py, PyAny>>,
    ) -> PyResult<StepAnswer<'py>> {
        let mut guard = self.lock();
        let args = StepArgs {
            env_ids: env_ids.as_ref(),
            actions: &actions,
            rewards: &rewards,
            terminated: terminated.as_ref(),
            truncated: truncated.as_ref(),
            values: values.as_ref().zip(next_values.as_ref()),
            q_values: q_values.as_ref().zip(next_q_values.as_ref()),
            scores: score_rows.as_ref().zip(score_values.as_ref()),
            ends: None,
            critic: None,
        };
        let answer = guard.run(py, &args)?;
        let pool_version = guard.pool_version;
        Ok(answer_arrays(py, answer, pool_version))
    }

    /// The task's pool version after the last answered batch (or at open).
    #[getter]
    fn pool_version(&self) -> u64 {
        self.lock().pool_version
    }

    /// Drops the current episodes of `envs` (sent with the next batch that has entries).
    fn abandon(&self, envs: Vec<i64>) -> PyResult<()> {
        let mut inner = self.lock();
        if inner.closed {
            return Err(closed_error());
        }
        let n = inner.tracker.num_envs();
        let mut ids = Vec::with_capacity(envs.len());
        for e in envs {
            let id = usize::try_from(e).ok().filter(|&i| i < n).ok_or_else(|| {
                PyValueError::new_err(format!(
                    "abandon: env id {e} is not in 0..{} (num_envs={n})",
                    n - 1
                ))
            })?;
            if ids.contains(&(id as u32)) {
                return Err(PyValueError::new_err(format!(
                    "abandon: env {e} is listed twice"
                )));
            }
            ids.push(id as u32);
        }
        inner.tracker.abandon(&ids);
        Ok(())
    }

    /// Per env: the steps sent in its current episode.
    fn episode_steps<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        let inner = self.lock();
        let steps: Vec<i64> = inner.tracker.steps().iter().map(|&s| s as i64).collect();
        steps.into_pyarray(py)
    }

    /// Whether the session is closed (by `close` or a failure).
    #[getter]
    fn closed(&self) -> bool {
        self.lock().closed
    }

    /// Ends the stream (idempotent); episodes in progress are discarded.
    fn close(&self, py: Python<'_>) {
        let mut guard = self.lock();
        let inner = &mut *guard;
        if inner.closed {
            return;
        }
        inner.closed = true;
        inner.tracker.discard_episodes();
        let transport = &mut inner.transport;
        py.detach(|| transport.close());
    }

    /// Re-opens a closed session on the same task (new episodes everywhere).
    fn reopen(&self, py: Python<'_>) -> PyResult<()> {
        let mut guard = self.lock();
        let inner = &mut *guard;
        inner.tracker.discard_episodes();
        let Inner {
            transport, tracker, ..
        } = inner;
        py.detach(|| match transport {
            Transport::Engine(e) => e.reopen(),
            Transport::Remote(r) => r.reopen(tracker),
        })
        .map_err(|s| crate::status_error(&s))?;
        inner.tracker.reopened();
        inner.closed = false;
        Ok(())
    }
}

fn answer_arrays(py: Python<'_>, a: Answer, pool_version: u64) -> StepAnswer<'_> {
    let n = a.rewards.len();
    let mut parts = a.rewards;
    parts.reserve_exact(2 * n);
    parts.extend_from_slice(&a.knn_rewards);
    parts.extend_from_slice(&a.potentials);
    let parts = numpy::ndarray::Array2::from_shape_vec((3, n), parts)
        .unwrap_or_else(|_| unreachable!("3 columns of n entries"));
    (
        PyArray2::from_owned_array(py, parts),
        a.steps.into_pyarray(py),
        a.knn_active.into_pyarray(py),
        pool_version,
    )
}
