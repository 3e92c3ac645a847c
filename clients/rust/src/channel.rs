//! [`Channel`]: a connection to one or several servers, its unary calls, and the
//! sessions opened on it: remote ([`crate::remote`]) or local ([`crate::local`]).

use std::sync::{Arc, Weak};
use std::time::Duration;

use prost::Message;
use tamrm::proto;
use tokio::runtime::Runtime;
use tonic::metadata::MetadataMap;
use tonic::{Code, Status};

use crate::error::Error;
use crate::local::{self, FollowStore};
use crate::options::{ChannelOptions, Interrupt};
use crate::remote::failure::{may_fail_over, none_answered, transport_error};
use crate::remote::targets::{Target, Targets};
use crate::remote::{RemoteStream, StreamConfig};
use crate::rpc::{self, request};
use crate::session::Session;
use crate::tracker::Tracker;

/// A connection to one or several servers: calls and streams go to the current address
/// and move on to the next when it cannot be reached.
pub struct Channel {
    targets: Arc<Targets>,
    metadata: MetadataMap,
    /// Whether the channel speaks TLS (for the hints of connection errors).
    tls: bool,
    /// How long a session's step resumes a broken stream.
    resume_timeout: Option<Duration>,
    /// How long a session's step polls for its answer before it sleeps.
    busy_poll: Duration,
    interrupt: Option<Interrupt>,
    rt: &'static Runtime,
    /// The stores of this channel's local sessions: every call waits for the acks of
    /// their ends first, so that it sees them at the server.
    locals: parking_lot::Mutex<Vec<Weak<FollowStore>>>,
}

impl std::fmt::Debug for Channel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Channel")
            .field("targets", &self.targets.names())
            .field("tls", &self.tls)
            .finish_non_exhaustive()
    }
}

impl Channel {
    /// A lazily connecting channel to `targets` (each `host:port` or `unix:PATH`; the
    /// first is used first) with `options`. Nothing is sent yet: see
    /// [`Channel::wait_ready`].
    pub fn connect<S: AsRef<str>>(
        targets: &[S],
        options: ChannelOptions,
    ) -> Result<Channel, Error> {
        let rt = crate::runtime::runtime()
            .map_err(|e| Error::Runtime(format!("tamrm: cannot start the tokio runtime: {e}")))?;
        if targets.is_empty() {
            return Err(Error::Invalid(
                "at least one server address is needed".into(),
            ));
        }
        options.check()?;
        let list = targets
            .iter()
            .map(|t| Target::connect_lazy(rt, t.as_ref(), &options))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Channel {
            targets: Arc::new(Targets::new(list)),
            metadata: options.metadata_map()?,
            tls: options.uses_tls(),
            resume_timeout: options.resume_timeout_value(),
            busy_poll: options.busy_poll_value(),
            interrupt: options.interrupt_check(),
            rt,
            locals: parking_lot::Mutex::new(Vec::new()),
        })
    }

    /// Whether the channel speaks TLS.
    pub fn tls(&self) -> bool {
        self.tls
    }

    /// Waits for the acks of the episode ends this channel's local sessions sent without
    /// waiting (SPEC §13), so that the next call sees them at the server.
    fn settle_locals(&self) {
        let stores: Vec<_> = self
            .locals
            .lock()
            .iter()
            .filter_map(|s| s.upgrade())
            .collect();
        if stores.is_empty() {
            return;
        }
        self.rt.block_on(async {
            for s in &stores {
                s.wait_acks().await;
            }
        });
    }

    /// One unary call on serialized messages: `method` is the `Shaping` RPC's name
    /// (one of `tamrm::auth::unary_rpcs()`), `request` its serialized request; answers the serialized
    /// response. A call the server did not apply, or an idempotent one whose connection
    /// broke, goes to the next address.
    pub fn call(
        &self,
        method: &str,
        request: &[u8],
        timeout: Option<Duration>,
    ) -> Result<Vec<u8>, Status> {
        self.settle_locals();
        let (md, rt, tls, targets) = (&self.metadata, self.rt, self.tls, &*self.targets);
        let one = |i: usize| {
            let t = targets.get(i);
            let target = t.uri();
            rt.block_on(async {
                let fut = rpc::remote(t.client.clone(), method, request, md, timeout);
                match timeout {
                    // The header deadline bounds the server; this one the connection.
                    Some(d) => tokio::time::timeout(d + Duration::from_millis(500), fut)
                        .await
                        .unwrap_or_else(|_| {
                            Err(Status::deadline_exceeded(format!(
                                "no answer from {target} in {}s",
                                d.as_secs_f64()
                            )))
                        }),
                    None => fut.await,
                }
            })
            .map_err(|s| (may_fail_over(method, &s), transport_error(&target, tls, s)))
        };
        let first = targets.current();
        let mut failure = match one(first) {
            Ok(out) => return Ok(out),
            Err((true, s)) if targets.len() > 1 => s,
            Err((_, s)) => return Err(s),
        };
        for i in targets.after(first).take(targets.len() - 1) {
            match one(i) {
                Ok(out) => {
                    targets.set_current(i);
                    return Ok(out);
                }
                Err((true, s)) => failure = s,
                Err((false, s)) => return Err(s),
            }
        }
        Err(none_answered(&targets.names(), &failure))
    }

    /// One typed unary call (see [`Channel::call`]).
    fn unary<Q: Message, A: Message + Default>(&self, method: &str, req: &Q) -> Result<A, Status> {
        let bytes = self.call(method, &req.encode_to_vec(), None)?;
        A::decode(bytes.as_slice()).map_err(|e| {
            Status::internal(format!("{method}: the server's answer is malformed: {e}"))
        })
    }

    /// `CreateTask`: creates a task (the same config again is the same task).
    pub fn create_task(&self, req: &proto::CreateTaskRequest) -> Result<proto::Task, Status> {
        self.unary("CreateTask", req)
    }

    /// `GetTask`: the task's config and stats.
    pub fn get_task(&self, task_id: &str) -> Result<proto::Task, Status> {
        let req = proto::GetTaskRequest {
            task_id: task_id.into(),
        };
        self.unary("GetTask", &req)
    }

    /// `ListTasks`.
    pub fn list_tasks(&self) -> Result<proto::ListTasksResponse, Status> {
        self.unary("ListTasks", &proto::ListTasksRequest {})
    }

    /// `DeleteTask`.
    pub fn delete_task(&self, task_id: &str) -> Result<proto::DeleteTaskResponse, Status> {
        let req = proto::DeleteTaskRequest {
            task_id: task_id.into(),
        };
        self.unary("DeleteTask", &req)
    }

    /// `ResetPool`: empties the task's pool.
    pub fn reset_pool(&self, task_id: &str) -> Result<proto::Task, Status> {
        let req = proto::ResetPoolRequest {
            task_id: task_id.into(),
        };
        self.unary("ResetPool", &req)
    }

    /// `GetPool`: the task's pool of trajectories.
    pub fn get_pool(&self, task_id: &str) -> Result<proto::Pool, Status> {
        let req = proto::GetPoolRequest {
            task_id: task_id.into(),
        };
        self.unary("GetPool", &req)
    }

    /// `AddTrajectory`: offers a trajectory to the task's pool.
    pub fn add_trajectory(
        &self,
        req: &proto::AddTrajectoryRequest,
    ) -> Result<proto::AddTrajectoryResponse, Status> {
        self.unary("AddTrajectory", req)
    }

    /// Blocks until a connection to the server is established, up to `timeout`. A
    /// failed TLS handshake ends the wait at once: the server is there, and retrying with
    /// the same certificates cannot succeed. With several addresses: until one of them
    /// connects (tried in turn from the current one), which becomes the current one.
    pub fn wait_ready(&self, timeout: Duration) -> Result<(), Status> {
        let (tls, targets) = (self.tls, &*self.targets);
        let target = targets.names();
        self.rt.block_on(async {
            let deadline = tokio::time::Instant::now() + timeout;
            let mut last = None;
            let mut i = targets.current();
            loop {
                let left = deadline.saturating_duration_since(tokio::time::Instant::now());
                let endpoint = &targets.get(i).endpoint;
                match tokio::time::timeout(left, endpoint.connect()).await {
                    Ok(Ok(_)) => {
                        targets.set_current(i);
                        return Ok(());
                    }
                    Ok(Err(e)) => {
                        let status = transport_error(&target, tls, Status::from_error(e.into()));
                        if status.message().starts_with("TLS handshake") {
                            return Err(status);
                        }
                        last = Some(status);
                        if left.is_zero() {
                            break;
                        }
                        i += 1;
                        if i % targets.len() == targets.current() {
                            // Every address tried once: wait before the next round.
                            tokio::time::sleep(Duration::from_millis(50).min(left)).await;
                        }
                    }
                    Err(_) => break,
                }
                if tokio::time::Instant::now() >= deadline {
                    break;
                }
            }
            let why = last
                .map(|s| format!(" ({})", s.message()))
                .unwrap_or_default();
            Err(Status::unavailable(format!(
                "could not connect to {target} in {}s{why}",
                timeout.as_secs_f64()
            )))
        })
    }

    /// Whether `grpc.health.v1.Health/Check` answers SERVING for `service` within
    /// `timeout` (retrying while the server cannot be reached yet).
    pub fn health(&self, service: &str, timeout: Duration) -> bool {
        let channel = self.targets.get(self.targets.current()).channel.clone();
        let md = &self.metadata;
        self.rt.block_on(async {
            let deadline = tokio::time::Instant::now() + timeout;
            let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
            loop {
                let left = deadline.saturating_duration_since(tokio::time::Instant::now());
                let req = tonic_health::pb::HealthCheckRequest {
                    service: service.to_string(),
                };
                let answer =
                    tokio::time::timeout(left, health.check(request(req, md, Some(left)))).await;
                match answer {
                    Ok(Ok(r)) => {
                        return r.get_ref().status
                            == tonic_health::pb::health_check_response::ServingStatus::Serving
                                as i32
                    }
                    Ok(Err(s)) if s.code() == Code::Unavailable && !left.is_zero() => {
                        tokio::time::sleep(Duration::from_millis(50).min(left)).await;
                    }
                    _ => return false,
                }
            }
        })
    }

    /// Opens a session (a `Shape` stream) on `task_id` for `num_envs` environments;
    /// `client_id` names the learner, so that a resumed stream commits no episode end
    /// twice (SPEC §9; empty: none).
    pub fn open(&self, task_id: &str, num_envs: u32, client_id: &str) -> Result<Session, Error> {
        self.settle_locals();
        let config = StreamConfig {
            targets: self.targets.clone(),
            metadata: self.metadata.clone(),
            tls: self.tls,
            resume_timeout: self.resume_timeout,
            busy_poll: self.busy_poll,
            interrupt: self.interrupt.clone(),
        };
        let mut stream = RemoteStream::new(config, task_id, num_envs, client_id)?;
        let tracker = Tracker::new(num_envs as usize, 0, false);
        let task = stream.open_anywhere(&tracker)?;
        Ok(Session::new(Box::new(stream), task, num_envs as usize))
    }

    /// Opens a local session (SPEC §13): a `Follow` stream on `task_id`, and the steps of
    /// `num_envs` environments shaped in-process against the followed pool; only the
    /// episode ends cross the network.
    pub fn follow(&self, task_id: &str, num_envs: u32, client_id: &str) -> Result<Session, Error> {
        let conn = local::Connection {
            targets: self.targets.clone(),
            metadata: self.metadata.clone(),
            tls: self.tls,
            resume_timeout: self.resume_timeout,
            task_id: task_id.to_string(),
            num_envs,
            client_id: client_id.to_string(),
        };
        self.settle_locals();
        let (session, store) = local::local_session(self.rt, conn)?;
        let mut locals = self.locals.lock();
        locals.retain(|s| s.strong_count() > 0);
        locals.push(Arc::downgrade(&store));
        Ok(session)
    }
}
