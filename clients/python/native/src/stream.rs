//! One shaping session as Python sees it (`tamrm.Session` wraps it): the columns in, the
//! client's [`Session`] round trip with the GIL released, the answer out as numpy arrays.

use std::sync::Mutex;

use numpy::{IntoPyArray, PyArray1, PyArray2};
use prost::Message;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use tamrm_client::tonic::Code;
use tamrm_client::{Answer, Session};

use crate::columns::{Prepared, Shape, StepArgs};
use crate::{client_error, status};

pub(crate) struct Inner {
    session: Session,
    shape: Shape,
    prepared: Prepared,
}

impl Inner {
    /// The environments of the stream.
    pub(crate) fn num_envs(&self) -> usize {
        self.shape.num_envs
    }

    /// Whether the session is closed.
    pub(crate) fn closed(&self) -> bool {
        self.session.closed()
    }

    /// The environment rewards of the last batch, as sent.
    pub(crate) fn sent_rewards(&self) -> &[f64] {
        &self.prepared.rewards
    }

    /// Checks `args`, shapes them through the session and records the answer (the one
    /// step path of `step` and `step_vec`). A closed session, a bad argument or a failed
    /// round trip is an error; after one that is not a rejected batch the session is
    /// closed.
    pub(crate) fn run(&mut self, py: Python<'_>, args: &StepArgs<'_, '_>) -> PyResult<Answer> {
        if self.session.closed() {
            return Err(closed_error());
        }
        self.prepared.fill(py, self.shape, args)?;
        let Inner {
            session, prepared, ..
        } = &mut *self;
        py.detach(|| session.step(&prepared.batch()))
            .map_err(client_error)
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
    /// A stream over `session` (opened on a server, a local session, or the engine: the
    /// task it opened on tells the action space).
    pub(crate) fn new(session: Session) -> NativeStream {
        let config = session.opened().config.unwrap_or_default();
        let opened = session.opened().encode_to_vec();
        NativeStream {
            inner: Mutex::new(Inner {
                shape: Shape {
                    num_envs: session.num_envs(),
                    num_actions: config.num_actions,
                },
                session,
                prepared: Prepared::default(),
            }),
            opened,
        }
    }

    /// Opens a session with the GIL released (`open` runs it) as a stream, or the
    /// error as Python sees it.
    pub(crate) fn open<E: Send>(
        py: Python<'_>,
        open: impl FnOnce() -> Result<Session, E> + Send,
        error: impl FnOnce(E) -> PyErr,
    ) -> PyResult<NativeStream> {
        py.detach(open).map(NativeStream::new).map_err(error)
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
        let pool_version = guard.session.pool_version();
        Ok(answer_arrays(py, answer, pool_version))
    }

    /// The task's pool version after the last answered batch (or at open).
    #[getter]
    fn pool_version(&self) -> u64 {
        self.lock().session.pool_version()
    }

    /// Drops the current episodes of `envs` (sent with the next batch that has entries).
    fn abandon(&self, envs: Vec<i64>) -> PyResult<()> {
        let mut inner = self.lock();
        if inner.session.closed() {
            return Err(closed_error());
        }
        let n = inner.session.num_envs();
        let ids = envs
            .iter()
            .map(|&e| {
                u32::try_from(e).map_err(|_| {
                    PyValueError::new_err(format!(
                        "abandon: env id {e} is not in 0..{} (num_envs={n})",
                        n - 1
                    ))
                })
            })
            .collect::<PyResult<Vec<u32>>>()?;
        inner.session.abandon(&ids).map_err(client_error)
    }

    /// Per env: the steps sent in its current episode.
    fn episode_steps<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<i64>> {
        let inner = self.lock();
        let steps: Vec<i64> = inner
            .session
            .episode_steps()
            .iter()
            .map(|&s| s as i64)
            .collect();
        steps.into_pyarray(py)
    }

    /// Whether the session is closed (by `close` or a failure).
    #[getter]
    fn closed(&self) -> bool {
        self.lock().session.closed()
    }

    /// Ends the stream (idempotent); episodes in progress are discarded.
    fn close(&self, py: Python<'_>) {
        let mut guard = self.lock();
        let session = &mut guard.session;
        py.detach(|| session.close());
    }

    /// Re-opens a closed session on the same task (new episodes everywhere).
    fn reopen(&self, py: Python<'_>) -> PyResult<()> {
        let mut guard = self.lock();
        let session = &mut guard.session;
        py.detach(|| session.reopen()).map_err(client_error)
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
