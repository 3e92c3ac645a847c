//! `tamrm.Client`'s transport: a tonic channel to a server, unary calls on serialized
//! messages, and `Shape` streams whose round trips run with the GIL released.

use std::str::FromStr;
use std::time::Duration;

use prost::Message;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::{self, shape_request, shape_response};
use tokio::runtime::Runtime;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::{AsciiMetadataKey, AsciiMetadataValue, MetadataMap};
use tonic::transport::{Channel as TonicChannel, Endpoint};
use tonic::{Code, Request, Status, Streaming};

use crate::columns::{Answer, Prepared};
use crate::stream::{NativeStream, StepError, Transport};
use crate::tracker::Tracker;
use crate::{runtime, status, status_error};

/// Largest message sent (requests) and received (answers), as the grpcio client had.
const MAX_SEND: usize = 64 * 1024 * 1024;
const MAX_RECEIVE: usize = 256 * 1024 * 1024;

/// How often a step waiting for its answer lets Python handle a signal (Ctrl-C).
const SIGNAL_CHECK: Duration = Duration::from_millis(100);

/// A connection to a server (`tamrm._native.Channel`).
#[pyclass(frozen, module = "tamrm._native")]
pub struct Channel {
    endpoint: Endpoint,
    channel: TonicChannel,
    client: ShapingClient<TonicChannel>,
    metadata: MetadataMap,
    rt: &'static Runtime,
}

fn client(channel: TonicChannel) -> ShapingClient<TonicChannel> {
    ShapingClient::new(channel)
        .max_decoding_message_size(MAX_RECEIVE)
        .max_encoding_message_size(MAX_SEND)
}

fn request<T>(msg: T, metadata: &MetadataMap, timeout: Option<Duration>) -> Request<T> {
    let mut req = Request::new(msg);
    *req.metadata_mut() = metadata.clone();
    if let Some(t) = timeout {
        req.set_timeout(t);
    }
    req
}

fn decode<M: Message + Default>(bytes: &[u8]) -> Result<M, Status> {
    M::decode(bytes).map_err(|e| {
        Status::invalid_argument(format!("request: not a valid protobuf message ({e})"))
    })
}

/// The HTTP authority of `target` and, for `unix:PATH` (or `unix:///PATH`), the socket
/// path. gRPC's `dns:`, `ipv4:` and `ipv6:` schemes name a `host:port`.
fn split_target(target: &str) -> PyResult<(String, Option<std::path::PathBuf>)> {
    if let Some(path) = target.strip_prefix("unix:") {
        let path = path.strip_prefix("//").unwrap_or(path);
        return Ok(("localhost".to_string(), Some(path.into())));
    }
    for scheme in ["dns:", "ipv4:", "ipv6:"] {
        if let Some(rest) = target.strip_prefix(scheme) {
            let rest = rest.trim_start_matches('/');
            return Ok((rest.to_string(), None));
        }
    }
    if let Some((scheme, _)) = target
        .split_once(':')
        .filter(|(s, _)| s.starts_with("unix-abstract") || *s == "vsock")
    {
        return Err(PyValueError::new_err(format!(
            "target {target:?}: the {scheme}: scheme is not supported by tamrm.Client; use host:port or unix:PATH"
        )));
    }
    Ok((target.to_string(), None))
}

/// A transport failure as a status (`UNAVAILABLE`: could not reach the server).
fn unreachable(target: &str, e: impl std::fmt::Display) -> Status {
    Status::unavailable(format!("could not reach {target}: {e}"))
}

async fn unary(
    mut c: ShapingClient<TonicChannel>,
    method: &str,
    bytes: &[u8],
    md: &MetadataMap,
    timeout: Option<Duration>,
) -> Result<Vec<u8>, Status> {
    macro_rules! call {
        ($rpc:ident) => {
            c.$rpc(request(decode(bytes)?, md, timeout))
                .await?
                .get_ref()
                .encode_to_vec()
        };
    }
    Ok(match method {
        "CreateTask" => call!(create_task),
        "GetTask" => call!(get_task),
        "ListTasks" => call!(list_tasks),
        "DeleteTask" => call!(delete_task),
        "ResetPool" => call!(reset_pool),
        "GetPool" => call!(get_pool),
        "AddTrajectory" => call!(add_trajectory),
        other => return Err(Status::unimplemented(format!("no method {other:?}"))),
    })
}

#[pymethods]
impl Channel {
    /// A lazily connecting channel to `target` (`host:port`), with `metadata` sent on
    /// every call.
    #[new]
    #[pyo3(signature = (target, metadata=Vec::new()))]
    fn new(target: &str, metadata: Vec<(String, String)>) -> PyResult<Channel> {
        let rt = runtime()?;
        let (authority, unix) = split_target(target)?;
        let endpoint = Endpoint::from_shared(format!("http://{authority}"))
            .map_err(|e| PyValueError::new_err(format!("target {target:?}: {e}")))?
            .tcp_nodelay(true)
            .connect_timeout(Duration::from_secs(10))
            .http2_keep_alive_interval(Duration::from_secs(30))
            .keep_alive_while_idle(false);
        let mut md = MetadataMap::new();
        for (k, v) in metadata {
            let key = AsciiMetadataKey::from_str(&k)
                .map_err(|e| PyValueError::new_err(format!("metadata key {k:?}: {e}")))?;
            let value = AsciiMetadataValue::from_str(&v)
                .map_err(|e| PyValueError::new_err(format!("metadata value of {k:?}: {e}")))?;
            md.append(key, value);
        }
        // The lazy channels spawn on the current runtime.
        let _enter = rt.enter();
        let channel = match &unix {
            None => endpoint.connect_lazy(),
            Some(path) => {
                let path = path.clone();
                endpoint.connect_with_connector_lazy(tower::service_fn(
                    move |_: tonic::transport::Uri| {
                        let path = path.clone();
                        async move {
                            let stream = tokio::net::UnixStream::connect(path).await?;
                            Ok::<_, std::io::Error>(hyper_util::rt::TokioIo::new(stream))
                        }
                    },
                ))
            }
        };
        Ok(Channel {
            endpoint,
            client: client(channel.clone()),
            channel,
            metadata: md,
            rt,
        })
    }

    /// One unary call on serialized messages; `timeout` in seconds (`None`: none).
    #[pyo3(signature = (method, request, timeout=None))]
    fn call<'py>(
        &self,
        py: Python<'py>,
        method: &str,
        request: &[u8],
        timeout: Option<f64>,
    ) -> PyResult<Bound<'py, PyBytes>> {
        let timeout = match timeout {
            None => None,
            Some(t) if t.is_nan() => {
                return Err(PyValueError::new_err(
                    "timeout must be a number of seconds, got nan",
                ))
            }
            // A deadline already past (or beyond any clock): fail now, as gRPC does.
            Some(t) => Some(Duration::try_from_secs_f64(t).map_err(|_| {
                status(
                    Code::DeadlineExceeded,
                    format!("deadline of {t}s exceeded before the call"),
                )
            })?),
        };
        let (c, md, rt) = (self.client.clone(), &self.metadata, self.rt);
        let target = self.endpoint.uri().to_string();
        let out = py
            .detach(|| {
                rt.block_on(async {
                    let fut = unary(c, method, request, md, timeout);
                    match timeout {
                        // The header deadline bounds the server; this one the connection.
                        Some(t) => tokio::time::timeout(t + Duration::from_millis(500), fut)
                            .await
                            .unwrap_or_else(|_| {
                                Err(Status::deadline_exceeded(format!(
                                    "no answer from {target} in {}s",
                                    t.as_secs_f64()
                                )))
                            }),
                        None => fut.await,
                    }
                })
            })
            .map_err(|s| status_error(&s))?;
        Ok(PyBytes::new(py, &out))
    }

    /// Blocks until a connection to the server is established, up to `timeout` seconds.
    fn wait_ready(&self, py: Python<'_>, timeout: f64) -> PyResult<()> {
        let (endpoint, rt) = (self.endpoint.clone(), self.rt);
        py.detach(|| {
            rt.block_on(async {
                let wait = Duration::try_from_secs_f64(timeout).unwrap_or(Duration::ZERO);
                let deadline = tokio::time::Instant::now() + wait;
                loop {
                    let left = deadline.saturating_duration_since(tokio::time::Instant::now());
                    match tokio::time::timeout(left, endpoint.connect()).await {
                        Ok(Ok(_)) => return Ok(()),
                        Ok(Err(_)) if !left.is_zero() => {
                            tokio::time::sleep(Duration::from_millis(50).min(left)).await;
                        }
                        _ => return Err(()),
                    }
                    if tokio::time::Instant::now() >= deadline {
                        return Err(());
                    }
                }
            })
        })
        .map_err(|()| {
            status(
                Code::Unavailable,
                format!("could not connect to {} in {timeout}s", self.endpoint.uri()),
            )
        })
    }

    /// Whether `grpc.health.v1.Health/Check` answers SERVING for `service` within
    /// `timeout` seconds (retrying while the server cannot be reached yet).
    fn health(&self, py: Python<'_>, service: &str, timeout: f64) -> bool {
        let (channel, md, rt) = (self.channel.clone(), &self.metadata, self.rt);
        let wait = Duration::try_from_secs_f64(timeout).unwrap_or(Duration::ZERO);
        py.detach(|| {
            rt.block_on(async {
                let deadline = tokio::time::Instant::now() + wait;
                let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
                loop {
                    let left = deadline.saturating_duration_since(tokio::time::Instant::now());
                    let req = tonic_health::pb::HealthCheckRequest {
                        service: service.to_string(),
                    };
                    let answer =
                        tokio::time::timeout(left, health.check(request(req, md, Some(left))))
                            .await;
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
        })
    }

    /// Opens a `Shape` stream on `task_id` for `num_envs` environments.
    fn open(
        &self,
        py: Python<'_>,
        task_id: &str,
        num_envs: u32,
        client_id: &str,
    ) -> PyResult<NativeStream> {
        let mut stream = RemoteStream {
            client: self.client.clone(),
            metadata: self.metadata.clone(),
            target: self.endpoint.uri().to_string(),
            task_id: task_id.to_string(),
            num_envs,
            client_id: client_id.to_string(),
            rt: self.rt,
            tx: None,
            inbound: None,
        };
        let tracker = Tracker::new(num_envs as usize, 0, false);
        let task = py
            .detach(|| stream.open(&tracker))
            .map_err(|s| status_error(&s))?;
        Ok(NativeStream::new(
            Transport::Remote(stream),
            &task,
            num_envs as usize,
        ))
    }
}

/// One `Shape` stream to a server.
pub(crate) struct RemoteStream {
    client: ShapingClient<TonicChannel>,
    metadata: MetadataMap,
    target: String,
    task_id: String,
    num_envs: u32,
    client_id: String,
    rt: &'static Runtime,
    tx: Option<mpsc::Sender<proto::ShapeRequest>>,
    inbound: Option<Streaming<proto::ShapeResponse>>,
}

impl RemoteStream {
    /// Opens the stream, resuming `tracker`'s episodes; returns the `opened` task.
    fn open(&mut self, tracker: &Tracker) -> Result<proto::Task, Status> {
        self.close();
        let open = proto::ShapeRequest {
            kind: Some(shape_request::Kind::Open(proto::Open {
                task_id: self.task_id.clone(),
                num_envs: self.num_envs,
                resume: tracker.resume(),
                client_id: self.client_id.clone(),
            })),
        };
        let (tx, rx) = mpsc::channel(4);
        let mut client = self.client.clone();
        let req = request(ReceiverStream::new(rx), &self.metadata, None);
        let target = self.target.clone();
        let (inbound, first) = self.rt.block_on(async move {
            tx.send(open)
                .await
                .map_err(|_| Status::internal("the stream's sender closed"))?;
            let mut inbound = client
                .shape(req)
                .await
                .map_err(|s| connect_error(&target, s))?
                .into_inner();
            let first = inbound
                .message()
                .await
                .map_err(|s| connect_error(&target, s))?;
            Ok::<_, Status>(((tx, inbound), first))
        })?;
        match first.and_then(|r| r.kind) {
            Some(shape_response::Kind::Opened(task)) => {
                self.tx = Some(inbound.0);
                self.inbound = Some(inbound.1);
                Ok(task)
            }
            Some(shape_response::Kind::Shaped(_)) => Err(Status::internal(
                "expected 'opened' as the first Shape response, got 'shaped'",
            )),
            None => Err(Status::unavailable(
                "the server ended the Shape stream before answering Open",
            )),
        }
    }

    /// Whether the stream is gone (a failed re-open after a rejected batch).
    pub fn broken(&self) -> bool {
        self.tx.is_none()
    }

    /// Sends one batch and waits for its answer. After a rejected batch
    /// (INVALID_ARGUMENT, nothing applied) the stream is re-opened with every episode of
    /// `tracker` resumed, so that the session goes on as if it had never been sent.
    pub fn step(&mut self, batch: &Prepared, tracker: &Tracker) -> Result<Answer, StepError> {
        let (Some(tx), Some(inbound)) = (self.tx.as_ref(), self.inbound.as_mut()) else {
            return Err(Status::cancelled("the session is closed").into());
        };
        let req = proto::ShapeRequest {
            kind: Some(shape_request::Kind::Steps(batch.to_proto())),
        };
        let result = self.rt.block_on(async {
            if tx.send(req).await.is_err() {
                // The request stream ended: the answer (the status) says why.
            }
            let answer = inbound.message();
            tokio::pin!(answer);
            loop {
                tokio::select! {
                    r = &mut answer => return Ok(r),
                    () = tokio::time::sleep(SIGNAL_CHECK) => {
                        // A Ctrl-C while the server takes its time: Python handles
                        // signals only once it runs again.
                        Python::attach(|py| py.check_signals())?;
                    }
                }
            }
        });
        let result = match result {
            Ok(r) => r,
            Err(interrupt) => {
                self.tx = None;
                self.inbound = None;
                return Err(StepError::Interrupted(interrupt));
            }
        };
        match result {
            Ok(Some(proto::ShapeResponse {
                kind: Some(shape_response::Kind::Shaped(msg)),
            })) => Ok(Answer::from_proto(msg)),
            Ok(Some(_)) => Err(Status::internal("expected a 'shaped' Shape response").into()),
            Ok(None) => {
                Err(Status::unavailable("the server ended the Shape stream unexpectedly").into())
            }
            Err(s) if s.code() == Code::InvalidArgument => {
                if self.open(tracker).is_err() {
                    self.close();
                }
                Err(s.into())
            }
            Err(s) => Err(s.into()),
        }
    }

    /// Re-opens with new episodes everywhere (`tracker` discarded them).
    pub fn reopen(&mut self, tracker: &Tracker) -> Result<(), Status> {
        self.open(tracker).map(|_| ())
    }

    /// Half-closes the stream and lets the server end it.
    pub fn close(&mut self) {
        self.tx = None;
        if let Some(mut inbound) = self.inbound.take() {
            // Drain briefly so the server sees a clean end; never wait long.
            let _ = self.rt.block_on(async {
                tokio::time::timeout(Duration::from_secs(2), async {
                    while let Ok(Some(_)) = inbound.message().await {}
                })
                .await
            });
        }
    }
}

fn connect_error(target: &str, s: Status) -> Status {
    if s.code() == Code::Unavailable || s.code() == Code::Unknown {
        unreachable(target, s.message())
    } else {
        s
    }
}
