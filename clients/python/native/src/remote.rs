//! `tamrm.Client`'s transport: a tonic channel to a server, unary calls on serialized
//! messages, and `Shape` streams whose round trips run with the GIL released.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use prost::Message;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::{self, shape_request, shape_response};
use tokio::runtime::Runtime;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::MetadataMap;
use tonic::transport::{Channel as TonicChannel, Endpoint};
use tonic::{Code, Request, Status, Streaming};

use crate::columns::{Answer, Prepared};
use crate::options::ChannelOptions;
use crate::stream::{NativeStream, StepError, Transport};
use crate::tracker::Tracker;
use crate::{runtime, status, status_error};

/// Largest message sent (requests) and received (answers), as the grpcio client had.
const MAX_SEND: usize = 64 * 1024 * 1024;
const MAX_RECEIVE: usize = 256 * 1024 * 1024;

/// How often a step waiting for its answer lets Python handle a signal (Ctrl-C).
const SIGNAL_CHECK: Duration = Duration::from_millis(100);

/// One server address of a channel, connected lazily.
pub(crate) struct Target {
    /// The address as given (for messages).
    name: String,
    pub(crate) endpoint: Endpoint,
    /// For `unix:PATH`: the socket (the endpoint's URI is a placeholder then).
    unix: Option<std::path::PathBuf>,
    channel: TonicChannel,
    /// A client on the channel shared by the unary calls (its connection runs on the
    /// module's runtime).
    pub(crate) client: ShapingClient<TonicChannel>,
}

impl Target {
    /// A new lazily connecting channel to this address, whose connection runs on `rt`.
    fn channel_on(&self, rt: &Runtime) -> TonicChannel {
        lazy_channel(rt, &self.endpoint, self.unix.as_deref())
    }
}

/// The addresses of a channel and the one in use: calls and streams go to the current
/// address and move on to the next when it cannot be reached (SPEC §9, §10: any replica
/// serves any task).
pub(crate) struct Targets {
    list: Vec<Target>,
    current: AtomicUsize,
}

impl Targets {
    pub(crate) fn current(&self) -> usize {
        self.current.load(Ordering::Relaxed) % self.list.len()
    }

    /// Makes address `i` the one to use first.
    pub(crate) fn set_current(&self, i: usize) {
        self.current.store(i, Ordering::Relaxed);
    }

    /// How many addresses.
    pub(crate) fn len(&self) -> usize {
        self.list.len()
    }

    pub(crate) fn get(&self, i: usize) -> &Target {
        &self.list[i % self.list.len()]
    }

    /// The order to try the addresses in after address `failed` failed: every other one,
    /// then `failed` itself last.
    pub(crate) fn after(&self, failed: usize) -> impl Iterator<Item = usize> {
        let n = self.list.len();
        (1..=n).map(move |k| (failed + k) % n)
    }

    /// All addresses, for messages.
    pub(crate) fn names(&self) -> String {
        let names: Vec<&str> = self.list.iter().map(|t| t.name.as_str()).collect();
        names.join(", ")
    }
}

/// A connection to one or several servers (`tamrm._native.Channel`).
#[pyclass(frozen, module = "tamrm._native")]
pub struct Channel {
    targets: Arc<Targets>,
    metadata: MetadataMap,
    /// Whether the channel speaks TLS (for the hints of connection errors).
    tls: bool,
    /// How long a session's step resumes a broken stream.
    resume_timeout: Option<Duration>,
    /// How long a session's step polls for its answer before it sleeps.
    busy_poll: Duration,
    rt: &'static Runtime,
    /// The stores of this channel's local sessions: every call waits for the acks of
    /// their ends first, so that it sees them at the server.
    locals: parking_lot::Mutex<Vec<std::sync::Weak<crate::follow::FollowStore>>>,
}

fn client(channel: TonicChannel) -> ShapingClient<TonicChannel> {
    ShapingClient::new(channel)
        .max_decoding_message_size(MAX_RECEIVE)
        .max_encoding_message_size(MAX_SEND)
}

pub(crate) fn request<T>(msg: T, metadata: &MetadataMap, timeout: Option<Duration>) -> Request<T> {
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

/// Words of the errors rustls and hyper give when a TLS handshake fails, or when
/// plaintext HTTP/2 meets a TLS server.
const TLS_WORDS: [&str; 6] = [
    "certificate",
    "tls",
    "handshake",
    "alert",
    "corrupt message",
    "invalidcontenttype",
];
const CLOSED_WORDS: [&str; 4] = ["connection closed", "reset", "broken pipe", "eof"];
const PLAINTEXT_TO_TLS_WORDS: [&str; 6] = [
    "frame",
    "protocol",
    "connection closed",
    "reset",
    "broken pipe",
    "eof",
];

/// Whether the status's source chain holds tonic's `TimeoutExpired`.
fn expired(s: &Status) -> bool {
    let mut source = std::error::Error::source(s);
    while let Some(e) = source {
        if e.is::<tonic::TimeoutExpired>() {
            return true;
        }
        source = e.source();
    }
    false
}

/// A status made by the transport (not the server's answer) with the cause that tonic
/// keeps in its source chain spelled out, saying when it is TLS that failed (or was
/// expected): a wrong CA or a plaintext/TLS mismatch reads as such, not as a bare
/// "transport error".
fn transport_error(target: &str, tls: bool, s: Status) -> Status {
    if std::error::Error::source(&s).is_none() || s.code() == Code::DeadlineExceeded {
        // The server's own answer, or our deadline: as it is.
        return s;
    }
    let detail = tamrm::net::status_chain(&s);
    if expired(&s) {
        // The call's deadline passed in tonic's timeout layer (it says CANCELLED).
        return Status::deadline_exceeded(format!(
            "no answer from {target} within the deadline: {detail}"
        ));
    }
    let lower = detail.to_lowercase();
    let message = if tls && TLS_WORDS.iter().any(|w| lower.contains(w)) {
        format!(
            "TLS handshake with {target} failed: {detail} (check root_certificates, \
             tls_server_name and the client certificate, and that the server has TLS on)"
        )
    } else if tls && CLOSED_WORDS.iter().any(|w| lower.contains(w)) {
        // TLS 1.3: a refused client certificate reaches the client after its handshake
        // finished, often as a plain close.
        format!(
            "connection to {target} closed: {detail} (over TLS: a server with mutual TLS \
             closes connections without a client certificate it accepts; check \
             certificate_chain and private_key)"
        )
    } else if !tls
        && !lower.contains("refused")
        && PLAINTEXT_TO_TLS_WORDS.iter().any(|w| lower.contains(w))
    {
        format!(
            "connection to {target} failed: {detail} (if the server has TLS on, connect \
             with tls=True or root_certificates=)"
        )
    } else {
        format!("could not reach {target}: {detail}")
    };
    // The transport's own codes for a failed connection (UNKNOWN, CANCELLED, INTERNAL
    // for an HTTP/2 protocol error) say less
    // than UNAVAILABLE, which a caller retries on.
    let code = match s.code() {
        Code::Unknown | Code::Cancelled | Code::Internal => Code::Unavailable,
        other => other,
    };
    Status::new(code, message)
}

/// Methods that change nothing, or whose repetition changes nothing more (a `CreateTask`
/// with the same config is the same task): after a connection broke under them they can be
/// sent to the next address.
const IDEMPOTENT: [&str; 4] = ["GetTask", "ListTasks", "GetPool", "CreateTask"];

/// Whether a failed unary call may be sent to the next address: the server refused it
/// without applying anything (its own UNAVAILABLE: shutting down, its store down), the
/// connection could not be made (nothing was sent), or the call is idempotent and the
/// connection broke.
fn may_fail_over(method: &str, s: &Status) -> bool {
    if s.code() != Code::Unavailable && !resumable(s) {
        return false;
    }
    std::error::Error::source(s).is_none()
        || IDEMPOTENT.contains(&method)
        || tamrm::net::status_chain(s)
            .to_lowercase()
            .contains("connect error")
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

/// A lazily connecting channel to one address.
fn connect_lazy(rt: &Runtime, target: &str, options: &ChannelOptions) -> PyResult<Target> {
    let (authority, unix) = split_target(target)?;
    let endpoint = options.endpoint(target, &authority)?;
    let channel = lazy_channel(rt, &endpoint, unix.as_deref());
    Ok(Target {
        name: target.to_string(),
        endpoint,
        unix,
        client: client(channel.clone()),
        channel,
    })
}

/// A channel to `endpoint` (or the Unix socket `unix`) that connects at its first call;
/// its connection is a task of `rt`.
fn lazy_channel(rt: &Runtime, endpoint: &Endpoint, unix: Option<&std::path::Path>) -> TonicChannel {
    // The lazy channels spawn on the current runtime.
    let _enter = rt.enter();
    match unix {
        None => endpoint.connect_lazy(),
        Some(path) => {
            let path = path.to_path_buf();
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
    }
}

impl Channel {
    /// Waits for the acks of the episode ends this channel's local sessions sent without
    /// waiting (SPEC §13), so that the next call sees them at the server.
    fn settle_locals(&self, py: Python<'_>) {
        let stores: Vec<_> = self
            .locals
            .lock()
            .iter()
            .filter_map(|s| s.upgrade())
            .collect();
        if stores.is_empty() {
            return;
        }
        py.detach(|| {
            self.rt.block_on(async {
                for s in &stores {
                    s.wait_acks().await;
                }
            })
        });
    }
}

#[pymethods]
impl Channel {
    /// A lazily connecting channel to `targets` (each `host:port` or `unix:PATH`; the
    /// first is used first) with `options` (TLS, keepalive, metadata sent on every call).
    #[new]
    #[pyo3(signature = (targets, options=None))]
    fn new(targets: Vec<String>, options: Option<ChannelOptions>) -> PyResult<Channel> {
        let rt = runtime()?;
        let options = options.unwrap_or_default();
        if targets.is_empty() {
            return Err(PyValueError::new_err(
                "at least one server address is needed",
            ));
        }
        let list = targets
            .iter()
            .map(|t| connect_lazy(rt, t, &options))
            .collect::<PyResult<Vec<_>>>()?;
        Ok(Channel {
            targets: Arc::new(Targets {
                list,
                current: AtomicUsize::new(0),
            }),
            metadata: options.metadata_map()?,
            tls: options.uses_tls(),
            resume_timeout: options.resume_timeout(),
            busy_poll: options.busy_poll(),
            rt,
            locals: parking_lot::Mutex::new(Vec::new()),
        })
    }

    /// Whether the channel speaks TLS.
    #[getter]
    fn tls(&self) -> bool {
        self.tls
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
        self.settle_locals(py);
        let (md, rt, tls, targets) = (&self.metadata, self.rt, self.tls, &*self.targets);
        let one = |i: usize| {
            let t = targets.get(i);
            let target = t.endpoint.uri().to_string();
            rt.block_on(async {
                let fut = unary(t.client.clone(), method, request, md, timeout);
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
        let out = py
            .detach(|| {
                let first = targets.current();
                let mut failure = match one(first) {
                    Ok(out) => return Ok(out),
                    Err((true, s)) if targets.list.len() > 1 => s,
                    Err((_, s)) => return Err(s),
                };
                for i in targets.after(first).take(targets.list.len() - 1) {
                    match one(i) {
                        Ok(out) => {
                            targets.current.store(i, Ordering::Relaxed);
                            return Ok(out);
                        }
                        Err((true, s)) => failure = s,
                        Err((false, s)) => return Err(s),
                    }
                }
                Err(Status::new(
                    failure.code(),
                    format!(
                        "no server answered ({}): {}",
                        targets.names(),
                        failure.message()
                    ),
                ))
            })
            .map_err(|s| status_error(&s))?;
        Ok(PyBytes::new(py, &out))
    }

    /// Blocks until a connection to the server is established, up to `timeout` seconds.
    /// A failed TLS handshake ends the wait at once: the server is there, and retrying
    /// with the same certificates cannot succeed.
    /// With several addresses: until one of them connects (tried in turn from the
    /// current one), which becomes the current one.
    fn wait_ready(&self, py: Python<'_>, timeout: f64) -> PyResult<()> {
        let (rt, tls, targets) = (self.rt, self.tls, &*self.targets);
        let target = targets.names();
        py.detach(|| {
            rt.block_on(async {
                let wait = Duration::try_from_secs_f64(timeout).unwrap_or(Duration::ZERO);
                let deadline = tokio::time::Instant::now() + wait;
                let mut last = None;
                let mut i = targets.current();
                loop {
                    let left = deadline.saturating_duration_since(tokio::time::Instant::now());
                    let endpoint = &targets.get(i).endpoint;
                    match tokio::time::timeout(left, endpoint.connect()).await {
                        Ok(Ok(_)) => {
                            targets
                                .current
                                .store(i % targets.list.len(), Ordering::Relaxed);
                            return Ok(());
                        }
                        Ok(Err(e)) => {
                            let status =
                                transport_error(&target, tls, Status::from_error(e.into()));
                            if status.message().starts_with("TLS handshake") {
                                return Err(status);
                            }
                            last = Some(status);
                            if left.is_zero() {
                                break;
                            }
                            i += 1;
                            if i % targets.list.len() == targets.current() {
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
                    "could not connect to {target} in {timeout}s{why}"
                )))
            })
        })
        .map_err(|s| status_error(&s))
    }

    /// Whether `grpc.health.v1.Health/Check` answers SERVING for `service` within
    /// `timeout` seconds (retrying while the server cannot be reached yet).
    fn health(&self, py: Python<'_>, service: &str, timeout: f64) -> bool {
        let channel = self.targets.get(self.targets.current()).channel.clone();
        let (md, rt) = (&self.metadata, self.rt);
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

    /// Opens a local session (SPEC §13): a `Follow` stream on `task_id`, and the steps
    /// of `num_envs` environments shaped in-process against the followed pool.
    fn follow(
        &self,
        py: Python<'_>,
        task_id: &str,
        num_envs: u32,
        client_id: &str,
    ) -> PyResult<NativeStream> {
        let conn = crate::follow::Connection {
            targets: self.targets.clone(),
            metadata: self.metadata.clone(),
            tls: self.tls,
            resume_timeout: self.resume_timeout,
            task_id: task_id.to_string(),
            num_envs,
            client_id: client_id.to_string(),
        };
        self.settle_locals(py);
        let (stream, store) = crate::engine::local_session(py, self.rt, conn)?;
        let mut locals = self.locals.lock();
        locals.retain(|s| s.strong_count() > 0);
        locals.push(Arc::downgrade(&store));
        Ok(stream)
    }

    /// Opens a `Shape` stream on `task_id` for `num_envs` environments.
    fn open(
        &self,
        py: Python<'_>,
        task_id: &str,
        num_envs: u32,
        client_id: &str,
    ) -> PyResult<NativeStream> {
        self.settle_locals(py);
        let mut stream = RemoteStream {
            targets: self.targets.clone(),
            at: self.targets.current(),
            metadata: self.metadata.clone(),
            tls: self.tls,
            task_id: task_id.to_string(),
            num_envs,
            client_id: client_id.to_string(),
            resume_timeout: self.resume_timeout,
            busy_poll: self.busy_poll,
            driver: Driver::new()?,
            tx: None,
            inbound: None,
        };
        let tracker = Tracker::new(num_envs as usize, 0, false);
        let task = py
            .detach(|| stream.open_anywhere(&tracker))
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
    /// The channel's addresses; `at` is the one this stream uses.
    targets: Arc<Targets>,
    at: usize,
    metadata: MetadataMap,
    tls: bool,
    task_id: String,
    num_envs: u32,
    client_id: String,
    resume_timeout: Option<Duration>,
    /// How long a step polls for its answer before it sleeps (`busy_poll_us`).
    busy_poll: Duration,
    /// The stream's own connection and the runtime it runs on.
    driver: Driver,
    tx: Option<mpsc::Sender<proto::ShapeRequest>>,
    inbound: Option<Streaming<proto::ShapeResponse>>,
}

impl RemoteStream {
    /// The address this stream uses.
    fn target(&self) -> String {
        self.targets.get(self.at).endpoint.uri().to_string()
    }

    /// Opens the stream on the current address, or with several addresses, on the first
    /// one after it that answers (an `Open` changes nothing, so it can go anywhere).
    fn open_anywhere(&mut self, tracker: &Tracker) -> Result<proto::Task, Status> {
        let first = self.at;
        let mut failure = match self.open(tracker) {
            Ok(task) => return Ok(task),
            Err(s) if resumable(&s) && self.targets.list.len() > 1 => s,
            Err(s) => return Err(s),
        };
        for i in self.targets.after(first).take(self.targets.list.len() - 1) {
            self.at = i;
            match self.open(tracker) {
                Ok(task) => {
                    self.targets.current.store(i, Ordering::Relaxed);
                    return Ok(task);
                }
                Err(s) if resumable(&s) => failure = s,
                Err(s) => return Err(s),
            }
        }
        self.at = first;
        Err(Status::new(
            failure.code(),
            format!(
                "no server answered ({}): {}",
                self.targets.names(),
                failure.message()
            ),
        ))
    }

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
        let mut client = self.driver.client(&self.targets, self.at);
        let req = request(ReceiverStream::new(rx), &self.metadata, None);
        let (target, tls) = (self.target(), self.tls);
        let (inbound, first) = self.driver.rt.block_on(async move {
            tx.send(open)
                .await
                .map_err(|_| Status::internal("the stream's sender closed"))?;
            let mut inbound = client
                .shape(req)
                .await
                .map_err(|s| connect_error(&target, tls, s))?
                .into_inner();
            let first = inbound
                .message()
                .await
                .map_err(|s| connect_error(&target, tls, s))?;
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
    ///
    /// When the stream breaks (the server went away, restarted, or answers UNAVAILABLE)
    /// the step resumes (SPEC §9): it re-opens the stream with every episode of `tracker`
    /// (the state before this batch) and the session's `client_id`, with exponential
    /// backoff for up to `resume_timeout`, re-sends the batch and returns its answer as
    /// if nothing had happened. The server commits no episode end twice for one
    /// `client_id`, so a batch that was applied before its answer was lost is safe to
    /// re-send.
    pub fn step(&mut self, batch: &Prepared, tracker: &Tracker) -> Result<Answer, StepError> {
        let first = self.step_once(batch, tracker);
        let Some(limit) = self.resume_timeout else {
            return first.map_err(|e| match e {
                StepError::Status(s) if resumable(&s) && s.code() != Code::Unavailable => {
                    Status::unavailable(format!(
                        "the connection to {} broke under the session: {}",
                        self.target(),
                        s.message()
                    ))
                    .into()
                }
                other => other,
            });
        };
        let mut failure = match first {
            Err(StepError::Status(s)) if resumable(&s) => s,
            other => return other,
        };
        let deadline = Instant::now() + limit;
        let mut pause = FIRST_PAUSE;
        let mut attempt = 0usize;
        loop {
            let now = Instant::now();
            if now >= deadline {
                self.close_now();
                return Err(Status::unavailable(format!(
                    "the session could not be resumed within resume_timeout_secs = {} ({}): {}",
                    limit.as_secs_f64(),
                    self.targets.names(),
                    failure.message()
                ))
                .into());
            }
            let n = self.targets.list.len();
            attempt += 1;
            // Each address in turn, starting with the one after the failed one (another
            // replica), and a pause (doubling) before each round over all of them.
            self.at = (self.at + 1) % n;
            if attempt % n == 1 || n == 1 {
                self.pause(pause.min(deadline - now))?;
                pause = (pause * 2).min(MAX_PAUSE);
            }
            match self.open(tracker) {
                Ok(_) => {}
                Err(s) if resumable(&s) => {
                    failure = s;
                    continue;
                }
                Err(s) => return Err(s.into()),
            }
            self.targets.current.store(self.at, Ordering::Relaxed);
            match self.step_once(batch, tracker) {
                Err(StepError::Status(s)) if resumable(&s) => failure = s,
                other => return other,
            }
        }
    }

    /// Waits `d` (letting Python handle a Ctrl-C meanwhile).
    fn pause(&mut self, d: Duration) -> Result<(), StepError> {
        let waited = self.driver.rt.block_on(async {
            let end = tokio::time::Instant::now() + d;
            while tokio::time::Instant::now() < end {
                tokio::time::sleep_until(end.min(tokio::time::Instant::now() + SIGNAL_CHECK)).await;
                Python::attach(|py| py.check_signals())?;
            }
            Ok::<(), PyErr>(())
        });
        waited.map_err(|interrupt| {
            self.close_now();
            StepError::Interrupted(interrupt)
        })
    }

    /// Drops the stream without waiting for the server.
    fn close_now(&mut self) {
        self.tx = None;
        self.inbound = None;
    }

    /// One round trip on the current stream (see [`RemoteStream::step`]).
    fn step_once(&mut self, batch: &Prepared, tracker: &Tracker) -> Result<Answer, StepError> {
        let (Some(tx), Some(inbound)) = (self.tx.as_ref(), self.inbound.as_mut()) else {
            return Err(Status::cancelled("the session is closed").into());
        };
        let req = proto::ShapeRequest {
            kind: Some(shape_request::Kind::Steps(batch.to_proto())),
        };
        self.driver.touch();
        let busy_poll = self.busy_poll;
        let result = self.driver.rt.block_on(async {
            if tx.send(req).await.is_err() {
                // The request stream ended: the answer (the status) says why.
            }
            let answer = inbound.message();
            tokio::pin!(answer);
            // Busy polling: the stream's runtime is this thread's, so yielding lets it
            // poll the socket without sleeping, and the vCPU stays awake for the
            // answer instead of being woken for it.
            if !busy_poll.is_zero() {
                let until = Instant::now() + busy_poll;
                while Instant::now() < until {
                    tokio::select! {
                        biased;
                        r = &mut answer => return Ok(r),
                        () = tokio::task::yield_now() => {}
                    }
                }
            }
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
            let _ = self.driver.rt.block_on(async {
                tokio::time::timeout(Duration::from_secs(2), async {
                    while let Ok(Some(_)) = inbound.message().await {}
                })
                .await
            });
        }
    }
}

/// A stream's own connection, on a single-threaded runtime that the thread calling
/// `step` drives itself: the request is written and the answer read on that thread, with
/// no hand-off to a worker thread and back (two thread wake-ups per round trip on the
/// shared runtime: measured, about half of a loopback round trip on the loaded 2-core
/// machine). Between steps a keeper thread drives the runtime for 2 ms whenever no step
/// has for 200 ms, so that the connection answers the server's keepalive pings (and
/// sends its own) while the caller is busy elsewhere: training, evaluating, saving.
struct Driver {
    rt: Arc<Runtime>,
    /// Per address of the channel, this stream's channel to it (made at first use).
    channels: Vec<Option<ShapingClient<TonicChannel>>>,
    /// When a step last drove the runtime (ms since `epoch`).
    last_step: Arc<AtomicU64>,
    epoch: Instant,
    /// Dropped with the driver: ends the keeper thread.
    _stop: std::sync::mpsc::Sender<()>,
}

/// How often the keeper looks whether the connection needs driving.
const KEEPER_TICK: Duration = Duration::from_millis(200);

impl Driver {
    fn new() -> PyResult<Driver> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| {
                pyo3::exceptions::PyRuntimeError::new_err(format!(
                    "tamrm: cannot start a stream's runtime: {e}"
                ))
            })?;
        let rt = Arc::new(rt);
        let (stop, stopped) = std::sync::mpsc::channel::<()>();
        let last_step = Arc::new(AtomicU64::new(0));
        let epoch = Instant::now();
        let (keeper_rt, keeper_last) = (Arc::downgrade(&rt), last_step.clone());
        std::thread::Builder::new()
            .name("tamrm-keepalive".into())
            .spawn(move || loop {
                match stopped.recv_timeout(KEEPER_TICK) {
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                    _ => return,
                }
                let now = epoch.elapsed().as_millis() as u64;
                let idle = now.saturating_sub(keeper_last.load(Ordering::Relaxed));
                if idle < KEEPER_TICK.as_millis() as u64 {
                    continue; // a step drove the connection meanwhile
                }
                let Some(rt) = keeper_rt.upgrade() else {
                    return;
                };
                // Long enough for the connection task to read a ping and write its ack.
                // (The sleep is made inside: it needs the runtime's timer.)
                rt.block_on(async { tokio::time::sleep(Duration::from_millis(2)).await });
            })
            .map_err(|e| {
                pyo3::exceptions::PyRuntimeError::new_err(format!(
                    "tamrm: cannot start a stream's keepalive thread: {e}"
                ))
            })?;
        Ok(Driver {
            rt,
            channels: Vec::new(),
            last_step,
            epoch,
            _stop: stop,
        })
    }

    /// This stream's client for address `i` of `targets` (its own connection).
    fn client(&mut self, targets: &Targets, i: usize) -> ShapingClient<TonicChannel> {
        let i = i % targets.list.len();
        if self.channels.len() < targets.list.len() {
            self.channels.resize(targets.list.len(), None);
        }
        let rt = &self.rt;
        self.channels[i]
            .get_or_insert_with(|| client(targets.get(i).channel_on(rt)))
            .clone()
    }

    /// Notes that a step is driving the runtime now.
    fn touch(&self) {
        self.last_step
            .store(self.epoch.elapsed().as_millis() as u64, Ordering::Relaxed);
    }
}

/// The first wait before resuming a broken session; it doubles up to [`MAX_PAUSE`].
pub(crate) const FIRST_PAUSE: Duration = Duration::from_millis(50);
/// The longest wait between two attempts to resume.
pub(crate) const MAX_PAUSE: Duration = Duration::from_secs(2);

/// Whether a failed step is worth resuming: the server is unreachable or going away
/// (UNAVAILABLE), or the connection broke under the stream (a transport error). Every
/// answer of the server itself (a rejected batch, a deleted task, a quota) is final.
pub(crate) fn resumable(s: &Status) -> bool {
    match s.code() {
        Code::Unavailable => true,
        Code::Unknown | Code::Internal | Code::Cancelled => {
            std::error::Error::source(s).is_some() || s.message().contains("h2 protocol error")
        }
        _ => false,
    }
}

pub(crate) fn connect_error(target: &str, tls: bool, s: Status) -> Status {
    if std::error::Error::source(&s).is_some() {
        transport_error(target, tls, s)
    } else if s.code() == Code::Unavailable || s.code() == Code::Unknown {
        unreachable(target, s.message())
    } else {
        s
    }
}
