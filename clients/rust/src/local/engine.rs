//! [`EngineStream`]: a session's [`Transport`] through the session layer in-process, and
//! the local sessions of a channel built on it (SPEC §13).

use std::sync::Arc;
use std::time::Duration;

use tamrm::limits::Limits;
use tamrm::proto;
use tamrm::registry::{Registry, DEFAULT_TENANT};
use tamrm::service::convert;
use tamrm::session::{Batch, OpenRequest, StreamSession};
use tamrm::store::Store;
use tokio::runtime::Runtime;
use tonic::Status;

use super::connection::Connection;
use super::follow::FollowStore;
use crate::answer::Answer;
use crate::error::Error;
use crate::session::{Session, Transport};
use crate::tracker::Tracker;

/// One session of an in-process registry (the embedded engine's, or a local session's).
pub struct EngineStream {
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
struct Local {
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
    rt: &'static Runtime,
    conn: Connection,
) -> Result<(Session, Arc<FollowStore>), Error> {
    let (task_id, num_envs, client_id) =
        (conn.task_id.clone(), conn.num_envs, conn.client_id.clone());
    let store = Arc::new(FollowStore::open(rt, conn)?);
    let opened = store.opened().clone();
    let shared: Arc<dyn Store> = store.clone();
    let (registry, _) = rt
        .block_on(Registry::open(shared, Limits::default()))
        .map_err(|e| Status::internal(e.to_string()))?;
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
    stream.reopen_session()?;
    let session = Session::new(Box::new(stream), opened, num_envs as usize);
    Ok((session, store))
}

impl EngineStream {
    /// Opens a session of `registry` (whose tasks run on `rt`) on `task_id` for
    /// `num_envs` environments: the stream and the task as `Open` answers it.
    pub fn open(
        registry: Arc<Registry>,
        rt: &'static Runtime,
        task_id: &str,
        num_envs: u32,
        client_id: &str,
    ) -> Result<Session, Status> {
        let mut stream = EngineStream {
            session: None,
            registry,
            task_id: task_id.to_string(),
            num_envs,
            client_id: client_id.to_string(),
            rt,
            local: None,
        };
        stream.reopen_session()?;
        let Some(session) = &stream.session else {
            return Err(Status::internal("the session did not open"));
        };
        let opened: proto::Task = convert::task_proto(session.task());
        Ok(Session::new(Box::new(stream), opened, num_envs as usize))
    }

    /// (Re-)opens the session with new episodes everywhere.
    fn reopen_session(&mut self) -> Result<(), Status> {
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

impl Transport for EngineStream {
    /// Shapes one batch in-process.
    fn step(&mut self, batch: &Batch<'_>, _: &Tracker) -> Result<Answer, Error> {
        let Some(session) = self.session.as_mut() else {
            return Err(Status::cancelled("the session is closed").into());
        };
        let rt = self.rt;
        if let Some(local) = &self.local {
            // The acks of the ends in flight: a refused one is this step's error, and a
            // copy that went its own way takes the server's pool (see `FollowStore::commit`).
            if let Some(pool) = local.store.poll()? {
                session.task().refresh((*pool).clone());
            }
        }
        match rt.block_on(session.step(batch)) {
            Ok(shaped) => Ok(Answer::from_outputs(shaped.outputs, shaped.pool_version)),
            // A local session's commit that the server refused: the server's status.
            Err(e) => Err(self
                .local
                .as_ref()
                .and_then(|l| l.store.take_failure())
                .unwrap_or_else(|| e.into())
                .into()),
        }
    }

    /// Ends the session: its episodes in progress are discarded. A local session reports
    /// the steps it shaped since its last message first, then ends its Follow stream.
    fn close(&mut self) {
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

    fn reopen(&mut self, _: &Tracker) -> Result<(), Status> {
        self.reopen_session()
    }
}
