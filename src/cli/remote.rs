//! The connection of the client-side commands (`tamrm tasks`, `tamrm pool`): one gRPC
//! channel to `--server`, TLS as `tamrm healthcheck` speaks it, the API key sent as
//! `authorization: Bearer KEY` on every call, and a deadline per call.

use std::net::SocketAddr;
use std::time::Duration;

use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, ClientTlsConfig, Endpoint};

use crate::net;
use crate::proto::shaping_client::ShapingClient;
use crate::proto::{self, Task};

/// The largest message sent or received: a pool of 100 000 trajectories of a few hundred
/// actions (the server's own `max_message_bytes` still applies).
const MAX_MESSAGE_BYTES: usize = 1 << 30;

/// Where and how to reach the server.
#[derive(Debug, Clone)]
pub struct Target {
    /// The server's address.
    pub addr: SocketAddr,
    /// TLS towards it; `None`: plaintext.
    pub tls: Option<ClientTlsConfig>,
    /// The API key, if the server has `--api-keys`.
    pub api_key: Option<String>,
    /// Each call's deadline.
    pub timeout: Duration,
}

/// Adds the API key to every call.
#[derive(Clone)]
pub struct Credentials(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Credentials {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

/// A failed call or connection, worded for the command's user; `code` is the gRPC
/// status when the server answered.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct CallError {
    /// The server's status code, if it answered.
    pub code: Option<tonic::Code>,
    /// What went wrong.
    pub message: String,
}

impl CallError {
    /// An error of the command itself (no call failed).
    pub fn new(code: tonic::Code, message: impl Into<String>) -> CallError {
        CallError {
            code: Some(code),
            message: message.into(),
        }
    }
}

/// One unary call with the deadline, its answer or the failure worded for the user.
macro_rules! call {
    ($self:ident, $method:ident, $name:literal, $msg:expr) => {{
        let req = $self.request($msg);
        match $self.client.$method(req).await {
            Ok(r) => Ok(r.into_inner()),
            Err(s) => Err($self.failed($name, s)),
        }
    }};
}

/// The server's calls the commands make.
pub struct Remote {
    client: ShapingClient<InterceptedService<Channel, Credentials>>,
    addr: SocketAddr,
    timeout: Duration,
}

impl Remote {
    /// Connects to `target` (the API key is checked by the first call).
    pub async fn connect(target: &Target) -> Result<Remote, CallError> {
        let failed = |message: String| CallError {
            code: None,
            message,
        };
        let auth = match &target.api_key {
            Some(key) => Some(format!("Bearer {}", key.trim()).parse().map_err(|_| {
                failed("the API key holds characters a header cannot carry".into())
            })?),
            None => None,
        };
        let addr = target.addr;
        let scheme = if target.tls.is_some() {
            "https"
        } else {
            "http"
        };
        let mut endpoint = Endpoint::from_shared(format!("{scheme}://{addr}"))
            .map_err(|e| failed(e.to_string()))?
            .connect_timeout(target.timeout);
        if let Some(tls) = target.tls.clone() {
            endpoint = endpoint
                .tls_config(tls)
                .map_err(|e| failed(net::chain(&e)))?;
        }
        let channel = endpoint
            .connect()
            .await
            .map_err(|e| failed(format!("cannot connect to {addr}: {}", net::chain(&e))))?;
        let client = ShapingClient::with_interceptor(channel, Credentials(auth))
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        Ok(Remote {
            client,
            addr,
            timeout: target.timeout,
        })
    }

    fn request<T>(&self, msg: T) -> tonic::Request<T> {
        let mut req = tonic::Request::new(msg);
        req.set_timeout(self.timeout);
        req
    }

    fn failed(&self, call: &str, s: tonic::Status) -> CallError {
        let why = net::status_chain(&s);
        let hint = if why.contains("h2 protocol error") {
            " (does the server have TLS on? then give --tls-ca or TAMRM_TLS_CA)"
        } else {
            ""
        };
        CallError {
            code: Some(s.code()),
            message: format!("{call} on {}: {why}{hint}", self.addr),
        }
    }

    /// `ListTasks`: every task the caller's tenant holds, by id.
    pub async fn list_tasks(&mut self) -> Result<Vec<Task>, CallError> {
        Ok(call!(self, list_tasks, "ListTasks", proto::ListTasksRequest {})?.tasks)
    }

    /// `GetTask`.
    pub async fn get_task(&mut self, task_id: &str) -> Result<Task, CallError> {
        let task_id = task_id.into();
        call!(self, get_task, "GetTask", proto::GetTaskRequest { task_id })
    }

    /// `GetPool`: the trajectories in `seq` order.
    pub async fn get_pool(&mut self, task_id: &str) -> Result<proto::Pool, CallError> {
        let task_id = task_id.into();
        call!(self, get_pool, "GetPool", proto::GetPoolRequest { task_id })
    }

    /// `CreateTask` with every config field sent.
    pub async fn create_task(
        &mut self,
        task_id: &str,
        config: proto::TaskConfig,
    ) -> Result<Task, CallError> {
        let msg = proto::CreateTaskRequest {
            task_id: task_id.into(),
            config: Some(config),
        };
        call!(self, create_task, "CreateTask", msg)
    }

    /// `DeleteTask`.
    pub async fn delete_task(&mut self, task_id: &str) -> Result<(), CallError> {
        let task_id = task_id.into();
        call!(
            self,
            delete_task,
            "DeleteTask",
            proto::DeleteTaskRequest { task_id }
        )
        .map(drop)
    }

    /// `ResetPool`.
    pub async fn reset_pool(&mut self, task_id: &str) -> Result<Task, CallError> {
        let task_id = task_id.into();
        call!(
            self,
            reset_pool,
            "ResetPool",
            proto::ResetPoolRequest { task_id }
        )
    }

    /// `AddTrajectory`.
    pub async fn add_trajectory(
        &mut self,
        task_id: &str,
        trajectory: proto::Trajectory,
    ) -> Result<proto::AddTrajectoryResponse, CallError> {
        let msg = proto::AddTrajectoryRequest {
            task_id: task_id.into(),
            trajectory: Some(trajectory),
        };
        call!(self, add_trajectory, "AddTrajectory", msg)
    }
}
