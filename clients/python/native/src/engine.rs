//! `tamrm.Engine`: the server's registry, stores and session layer in-process. The unary
//! calls go through the server's own `Shaping` implementation (same checks, same
//! statuses, the client's one RPC table: [`tamrm_client::rpc::serve`]); streams are the
//! client's [`tamrm_client::EngineStream`]s fed straight from numpy columns.

use std::sync::Arc;

use pyo3::prelude::*;
use pyo3::types::PyBytes;
use tamrm::limits::Limits;
use tamrm::registry::Registry;
use tamrm::service::ShapingService;
use tamrm::store::{DiskStore, MemoryStore, Store};
use tamrm_client::tonic::Code;
use tamrm_client::{rpc, EngineStream};
use tokio::runtime::Runtime;
use tokio_util::sync::CancellationToken;

use crate::stream::NativeStream;
use crate::{runtime, status, status_error};

/// The embedded engine (`tamrm._native.Engine`).
#[pyclass(frozen, module = "tamrm._native")]
pub struct Engine {
    registry: Arc<Registry>,
    service: ShapingService,
    rt: &'static Runtime,
    description: String,
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
            .detach(|| rt.block_on(rpc::serve(service, method, request)))
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
        let (registry, rt) = (self.registry.clone(), self.rt);
        NativeStream::open(
            py,
            || EngineStream::open(registry, rt, task_id, num_envs, client_id),
            |s| status_error(&s),
        )
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
        self.registry.stopping();
        self.rt.block_on(self.registry.flush_counters());
    }
}
