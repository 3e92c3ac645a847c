//! `tamrm.Engine`: the server's registry, stores and session layer in-process. The unary
//! calls go through the server's own `Shaping` implementation (same checks, same
//! statuses); streams are `session::StreamSession`s fed straight from numpy columns.

use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use tamrm::limits::Limits;
use tamrm::proto::shaping_server::Shaping;
use tamrm::registry::{Registry, DEFAULT_TENANT};
use tamrm::service::{convert, ShapingService};
use tamrm::session::{OpenRequest, StreamSession};
use tamrm::store::{DiskStore, MemoryStore, Store};
use tokio::runtime::Runtime;
use tokio_util::sync::CancellationToken;
use tonic::{Code, Request, Status};

use crate::columns::{Answer, Prepared};
use crate::follow::{Connection, FollowStore};
use crate::stream::{NativeStream, Transport};
use crate::{runtime, status, status_error};

/// The embedded engine (`tamrm._native.Engine`).
#[pyclass(frozen, module = "tamrm._native")]
pub struct Engine {
    registry: Arc<Registry>,
    service: ShapingService,
    rt: &'static Runtime,
    description: String,
}

/// One stream of the embedded engine.
pub(crate) struct EngineStream {
    session: Option<StreamSession>,
    registry: Arc<Registry>,
    task_id: String,
    num_envs: u32,
    client_id: String,
    rt: &'static Runtime,
    /// For a local session (SPEC §13): the store following the server, and the tasks
    /// that take its updates in and report the steps.
    local: Option<Local>,
}

/// What a local session holds besides the engine's stream.
pub(crate) struct Local {
    store: Arc<FollowStore>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Drop for Local {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

/// How often a local session reports the steps it shaped when no episode end does.
const STEPS_REPORT: Duration = Duration::from_secs(1);

/// How long closing a local session waits to report its last steps.
const CLOSE_REPORT: Duration = Duration::from_secs(5);

/// A local session (SPEC §13): the engine's session layer over a registry whose one task
/// follows the server's through `conn`.
pub(crate) fn local_session(
    py: Python<'_>,
    rt: &'static Runtime,
    conn: Connection,
) -> PyResult<(NativeStream, Arc<FollowStore>)> {
    let (task_id, num_envs, client_id) =
        (conn.task_id.clone(), conn.num_envs, conn.client_id.clone());
    let store = Arc::new(
        py.detach(|| FollowStore::open(rt, conn))
            .map_err(|s| status_error(&s))?,
    );
    let opened = store.opened().clone();
    let shared: Arc<dyn Store> = store.clone();
    let (registry, _) = py
        .detach(|| rt.block_on(Registry::open(shared, Limits::default())))
        .map_err(|e| status(Code::Internal, e.to_string()))?;
    let registry = Arc::new(registry);
    let tasks = {
        let _in_rt = rt.enter();
        [
            registry.watch_changes(),
            registry.sync_counters_every(STEPS_REPORT),
        ]
        .into_iter()
        .flatten()
        .collect()
    };
    let mut stream = EngineStream {
        session: None,
        registry,
        task_id,
        num_envs,
        client_id,
        rt,
        local: Some(Local {
            store: store.clone(),
            tasks,
        }),
    };
    py.detach(|| stream.reopen())
        .map_err(|s| status_error(&s))?;
    let stream = NativeStream::new(Transport::Engine(stream), &opened, num_envs as usize);
    Ok((stream, store))
}

fn encode(msg: &impl Message) -> Vec<u8> {
    msg.encode_to_vec()
}

fn decode<M: Message + Default>(bytes: &[u8]) -> Result<M, Status> {
    M::decode(bytes).map_err(|e| {
        Status::invalid_argument(format!("request: not a valid protobuf message ({e})"))
    })
}

/// Runs one unary call of `service` on request bytes, answering response bytes.
pub(crate) async fn call_service(
    service: &ShapingService,
    method: &str,
    bytes: &[u8],
) -> Result<Vec<u8>, Status> {
    Ok(match method {
        "CreateTask" => encode(
            service
                .create_task(Request::new(decode(bytes)?))
                .await?
                .get_ref(),
        ),
        "GetTask" => encode(
            service
                .get_task(Request::new(decode(bytes)?))
                .await?
                .get_ref(),
        ),
        "ListTasks" => encode(
            service
                .list_tasks(Request::new(decode(bytes)?))
                .await?
                .get_ref(),
        ),
        "DeleteTask" => encode(
            service
                .delete_task(Request::new(decode(bytes)?))
                .await?
                .get_ref(),
        ),
        "ResetPool" => encode(
            service
                .reset_pool(Request::new(decode(bytes)?))
                .await?
                .get_ref(),
        ),
        "GetPool" => encode(
            service
                .get_pool(Request::new(decode(bytes)?))
                .await?
                .get_ref(),
        ),
        "AddTrajectory" => encode(
            service
                .add_trajectory(Request::new(decode(bytes)?))
                .await?
                .get_ref(),
        ),
        other => return Err(Status::unimplemented(format!("no method {other:?}"))),
    })
}

#[pymethods]
impl Engine {
    /// An engine over `data_dir` (a `tamrm serve --data-dir` directory, created if
    /// missing; locked while the engine is open) or, with `None`, in memory.
    #[new]
    #[pyo3(signature = (data_dir=None))]
    fn new(py: Python<'_>, data_dir: Option<std::path::PathBuf>) -> PyResult<Engine> {
        let rt = runtime()?;
        let store: Arc<dyn Store> = match &data_dir {
            Some(dir) => Arc::new(
                DiskStore::open(dir)
                    .map_err(|e| status(Code::FailedPrecondition, e.to_string()))?,
            ),
            None => Arc::new(MemoryStore::new()),
        };
        let description = store.describe();
        let (registry, _restored) = py
            .detach(|| rt.block_on(Registry::open(store, Limits::default())))
            .map_err(|e| status(Code::FailedPrecondition, e.to_string()))?;
        let registry = Arc::new(registry);
        let service = ShapingService::new(registry.clone(), CancellationToken::new());
        Ok(Engine {
            registry,
            service,
            rt,
            description,
        })
    }

    /// One unary call: `method` is the `Shaping` RPC's name, `request` its serialized
    /// request; returns the serialized response.
    fn call<'py>(
        &self,
        py: Python<'py>,
        method: &str,
        request: &[u8],
    ) -> PyResult<Bound<'py, PyBytes>> {
        let service = &self.service;
        let rt = self.rt;
        let out = py
            .detach(|| rt.block_on(call_service(service, method, request)))
            .map_err(|s| status_error(&s))?;
        Ok(PyBytes::new(py, &out))
    }

    /// Opens a session on `task_id` for `num_envs` environments.
    fn open(
        &self,
        py: Python<'_>,
        task_id: &str,
        num_envs: u32,
        client_id: &str,
    ) -> PyResult<NativeStream> {
        let mut stream = EngineStream {
            session: None,
            registry: self.registry.clone(),
            task_id: task_id.to_string(),
            num_envs,
            client_id: client_id.to_string(),
            rt: self.rt,
            local: None,
        };
        py.detach(|| stream.reopen())
            .map_err(|s| status_error(&s))?;
        let Some(session) = &stream.session else {
            return Err(status(Code::Internal, "the session did not open"));
        };
        let opened = convert::task_proto(session.task());
        Ok(NativeStream::new(
            Transport::Engine(stream),
            &opened,
            num_envs as usize,
        ))
    }

    /// Persists the task counters (pools are durable at every change already).
    fn flush(&self, py: Python<'_>) {
        let registry = &self.registry;
        let rt = self.rt;
        py.detach(|| rt.block_on(registry.flush_counters()));
    }

    /// The store, in one line.
    #[getter]
    fn description(&self) -> &str {
        &self.description
    }
}

impl Drop for Engine {
    /// The task counters since the last commit are persisted when the engine goes (its
    /// pools are durable at every change already).
    fn drop(&mut self) {
        self.rt.block_on(self.registry.flush_counters());
    }
}

impl EngineStream {
    /// Shapes one batch in-process.
    pub fn step(&mut self, batch: &Prepared) -> Result<Answer, Status> {
        let Some(session) = self.session.as_mut() else {
            return Err(Status::cancelled("the session is closed"));
        };
        let rt = self.rt;
        if let Some(local) = &self.local {
            // The acks of the ends in flight: a refused one is this step's error, and a
            // copy that went its own way takes the server's pool (see `FollowStore::commit`).
            if let Some(pool) = local.store.poll()? {
                session.task().refresh((*pool).clone());
            }
        }
        match rt.block_on(session.step(&batch.batch())) {
            Ok(shaped) => Ok(Answer::from_outputs(shaped.outputs, shaped.pool_version)),
            // A local session's commit that the server refused: the server's status.
            Err(e) => Err(self
                .local
                .as_ref()
                .and_then(|l| l.store.take_failure())
                .unwrap_or_else(|| e.into())),
        }
    }

    /// Ends the session: its episodes in progress are discarded. A local session reports
    /// the steps it shaped since its last message first, then ends its Follow stream.
    pub fn close(&mut self) {
        self.session = None;
        if let Some(local) = &self.local {
            let registry = &self.registry;
            // The timer is made inside the runtime (it needs its time driver). The last
            // ends' acks first: a closed session has nothing in flight.
            let _ = self.rt.block_on(async {
                tokio::time::timeout(CLOSE_REPORT, async {
                    local.store.wait_acks().await;
                    registry.flush_counters().await
                })
                .await
            });
        }
        if let Some(local) = &self.local {
            local.store.stop();
        }
    }

    /// (Re-)opens the session with new episodes everywhere.
    pub fn reopen(&mut self) -> Result<(), Status> {
        self.session = None;
        if let Some(local) = &self.local {
            // A closed local session follows the task again, from a fresh snapshot.
            if let Some(pool) = local.store.restart(self.rt)? {
                let registry = &self.registry;
                let task = self
                    .rt
                    .block_on(registry.lookup(DEFAULT_TENANT, &self.task_id))?;
                task.refresh(pool);
            }
        }
        let req = OpenRequest {
            tenant: DEFAULT_TENANT,
            task_id: &self.task_id,
            num_envs: self.num_envs,
            resume: &[],
            client_id: &self.client_id,
            transport_bytes: 0,
        };
        self.session = Some(
            self.rt
                .block_on(StreamSession::open(&self.registry, &req))?,
        );
        Ok(())
    }
}
