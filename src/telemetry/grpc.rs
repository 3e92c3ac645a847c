//! Per-RPC metrics with the names and labels of go-grpc-prometheus, recorded by one tower
//! layer around the whole router: `grpc_server_started_total` when a request arrives,
//! `grpc_server_handled_total{grpc_code}` and `grpc_server_handling_seconds` when its
//! response ends, with the final `grpc-status`: from the response headers for a
//! trailers-only response (errors before or instead of a message), else from the
//! trailers at the end of the body (so a stream is handled when it ends). A response
//! body dropped before its end (the client went away) counts as `Canceled`.
//!
//! `grpc_server_msg_received_total` and `grpc_server_msg_sent_total` count the messages
//! of each RPC as they pass through the layer: it wraps the request body and the response
//! body and reads the 5-byte prefix of every length-prefixed gRPC message
//! ([`MessageFrames`]), split anywhere across body frames or several in one. A message
//! counts when its last byte passes (a request message when the handler reads it, a
//! response message when the server writes it), so, as in go-grpc-prometheus, a unary
//! call counts one received and, when it succeeds, one sent (a failed call answers with
//! trailers only), and a stream one per message each way. The counters of an RPC are
//! resolved when it starts; per body frame the cost is a few integer operations and, when
//! a message ends in it, one counter addition.

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, OnceLock};
use std::task::{ready, Context, Poll};
use std::time::Instant;

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::histogram::Histogram;
use prost::Message;
use tonic::Code;

use super::Metrics;

mod frames;

use frames::MessageFrames;

/// Upper bounds of `grpc_server_handling_seconds`: 100 µs to 10 s, then 1 min, 10 min and
/// 1 h for Shape streams.
const HANDLING_BUCKETS: [f64; 19] = [
    1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
    60.0, 600.0, 3600.0,
];

/// The labels of one method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, EncodeLabelSet)]
struct Method {
    grpc_type: &'static str,
    grpc_service: &'static str,
    grpc_method: &'static str,
}

/// A path that is not one of the served methods.
const UNKNOWN: Method = Method {
    grpc_type: "unknown",
    grpc_service: "unknown",
    grpc_method: "unknown",
};

/// The labels of one method and a final status.
#[derive(Debug, Clone, PartialEq, Eq, Hash, EncodeLabelSet)]
struct Handled {
    grpc_type: &'static str,
    grpc_service: &'static str,
    grpc_method: &'static str,
    grpc_code: &'static str,
}

/// The methods the server serves, by request path (`/package.Service/Method`), from the
/// descriptor sets of its services: built once per process, so the label values can be
/// `&'static str`.
fn methods() -> &'static HashMap<String, Method> {
    static METHODS: OnceLock<HashMap<String, Method>> = OnceLock::new();
    METHODS.get_or_init(|| {
        let sets = [
            crate::proto::FILE_DESCRIPTOR_SET,
            tonic_health::pb::FILE_DESCRIPTOR_SET,
            tonic_reflection::pb::v1::FILE_DESCRIPTOR_SET,
            tonic_reflection::pb::v1alpha::FILE_DESCRIPTOR_SET,
        ];
        let mut methods = HashMap::new();
        for set in sets {
            let set = match prost_types::FileDescriptorSet::decode(set) {
                Ok(s) => s,
                Err(e) => {
                    tracing::warn!(error = %e, "an embedded descriptor set does not decode; its methods are labelled unknown");
                    continue;
                }
            };
            for file in &set.file {
                for service in &file.service {
                    let full = match file.package() {
                        "" => service.name().to_string(),
                        p => format!("{p}.{}", service.name()),
                    };
                    let grpc_service: &'static str = Box::leak(full.clone().into_boxed_str());
                    for m in &service.method {
                        let grpc_type = match (m.client_streaming(), m.server_streaming()) {
                            (false, false) => "unary",
                            (true, false) => "client_stream",
                            (false, true) => "server_stream",
                            (true, true) => "bidi_stream",
                        };
                        let grpc_method: &'static str =
                            Box::leak(m.name().to_string().into_boxed_str());
                        methods.insert(
                            format!("/{full}/{}", m.name()),
                            Method {
                                grpc_type,
                                grpc_service,
                                grpc_method,
                            },
                        );
                    }
                }
            }
        }
        methods
    })
}

/// The name go-grpc-prometheus gives a code (`codes.Code.String()`).
fn code_name(code: Code) -> &'static str {
    match code {
        Code::Ok => "OK",
        Code::Cancelled => "Canceled",
        Code::Unknown => "Unknown",
        Code::InvalidArgument => "InvalidArgument",
        Code::DeadlineExceeded => "DeadlineExceeded",
        Code::NotFound => "NotFound",
        Code::AlreadyExists => "AlreadyExists",
        Code::PermissionDenied => "PermissionDenied",
        Code::ResourceExhausted => "ResourceExhausted",
        Code::FailedPrecondition => "FailedPrecondition",
        Code::Aborted => "Aborted",
        Code::OutOfRange => "OutOfRange",
        Code::Unimplemented => "Unimplemented",
        Code::Internal => "Internal",
        Code::Unavailable => "Unavailable",
        Code::DataLoss => "DataLoss",
        Code::Unauthenticated => "Unauthenticated",
    }
}

/// The `grpc-status` of a header map (headers of a trailers-only response, or trailers).
fn status_of(headers: &http::HeaderMap) -> Option<&'static str> {
    headers
        .get("grpc-status")
        .map(|v| code_name(Code::from_bytes(v.as_bytes())))
}

/// The gRPC families of a [`Metrics`].
pub(super) struct GrpcMetrics {
    started: Family<Method, Counter>,
    handled: Family<Handled, Counter>,
    seconds: Family<Method, Histogram, fn() -> Histogram>,
    received: Family<Method, Counter>,
    sent: Family<Method, Counter>,
}

impl GrpcMetrics {
    pub(super) fn register(registry: &mut prometheus_client::registry::Registry) -> GrpcMetrics {
        let m = GrpcMetrics {
            started: Family::default(),
            handled: Family::default(),
            seconds: Family::new_with_constructor(|| Histogram::new(HANDLING_BUCKETS)),
            received: Family::default(),
            sent: Family::default(),
        };
        registry.register(
            "grpc_server_started",
            "RPCs started on the server",
            m.started.clone(),
        );
        registry.register(
            "grpc_server_handled",
            "RPCs completed on the server, by final status code",
            m.handled.clone(),
        );
        registry.register(
            "grpc_server_handling_seconds",
            "Time from an RPC's request to the end of its response (a stream's whole life)",
            m.seconds.clone(),
        );
        registry.register(
            "grpc_server_msg_received",
            "gRPC messages received on the server (one per unary call, one per message a client streams)",
            m.received.clone(),
        );
        registry.register(
            "grpc_server_msg_sent",
            "gRPC messages sent by the server (one per successful unary call, one per streamed response)",
            m.sent.clone(),
        );
        m
    }
}

/// One body's message count: its frames and the counter of its RPC's method.
#[derive(Debug)]
struct Messages {
    counter: Counter,
    frames: MessageFrames,
}

impl Messages {
    fn new(family: &Family<Method, Counter>, method: &Method) -> Messages {
        Messages {
            counter: family.get_or_create_owned(method),
            frames: MessageFrames::default(),
        }
    }

    /// Counts the messages that end in a body frame (nothing for trailers).
    fn frame<D: AsRef<[u8]>>(&mut self, frame: &http_body::Frame<D>) {
        if let Some(data) = frame.data_ref() {
            let ended = self.frames.feed(data.as_ref());
            if ended > 0 {
                self.counter.inc_by(ended);
            }
        }
    }
}

/// One RPC in flight; recorded as handled, with `code`, when dropped.
struct Rpc {
    metrics: Arc<Metrics>,
    method: Method,
    start: Instant,
    code: &'static str,
}

impl Rpc {
    fn start(metrics: Arc<Metrics>, method: Method) -> Rpc {
        metrics.grpc.started.get_or_create(&method).inc();
        Rpc {
            metrics,
            method,
            start: Instant::now(),
            code: code_name(Code::Cancelled),
        }
    }

    fn finish(mut self, code: &'static str) {
        self.code = code;
    }
}

impl Drop for Rpc {
    fn drop(&mut self) {
        let g = &self.metrics.grpc;
        g.handled
            .get_or_create(&Handled {
                grpc_type: self.method.grpc_type,
                grpc_service: self.method.grpc_service,
                grpc_method: self.method.grpc_method,
                grpc_code: self.code,
            })
            .inc();
        g.seconds
            .get_or_create(&self.method)
            .observe(self.start.elapsed().as_secs_f64());
    }
}

/// The tower layer that records the gRPC metrics of every request (nothing without
/// metrics).
#[derive(Debug, Clone, Default)]
pub struct GrpcMetricsLayer {
    metrics: Option<Arc<Metrics>>,
}

impl GrpcMetricsLayer {
    /// A layer recording into `metrics`; with `None` it passes requests through.
    pub fn new(metrics: Option<Arc<Metrics>>) -> GrpcMetricsLayer {
        GrpcMetricsLayer { metrics }
    }
}

impl<S> tower::Layer<S> for GrpcMetricsLayer {
    type Service = GrpcMetricsService<S>;

    fn layer(&self, inner: S) -> GrpcMetricsService<S> {
        GrpcMetricsService {
            inner,
            metrics: self.metrics.clone(),
        }
    }
}

/// The service of [`GrpcMetricsLayer`].
#[derive(Debug, Clone)]
pub struct GrpcMetricsService<S> {
    inner: S,
    metrics: Option<Arc<Metrics>>,
}

impl<S, ReqBody, ResBody> tower::Service<http::Request<ReqBody>> for GrpcMetricsService<S>
where
    S: tower::Service<
        http::Request<MeteredRequestBody<ReqBody>>,
        Response = http::Response<ResBody>,
    >,
{
    type Response = http::Response<MeteredBody<ResBody>>;
    type Error = S::Error;
    type Future = ResponseFuture<S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<ReqBody>) -> Self::Future {
        let (rpc, received, sent) = match &self.metrics {
            Some(m) => {
                let method = methods().get(req.uri().path()).copied().unwrap_or(UNKNOWN);
                let received = Messages::new(&m.grpc.received, &method);
                let sent = Messages::new(&m.grpc.sent, &method);
                (
                    Some(Rpc::start(m.clone(), method)),
                    Some(received),
                    Some(sent),
                )
            }
            None => (None, None, None),
        };
        let req = req.map(|inner| MeteredRequestBody {
            inner,
            messages: received,
        });
        ResponseFuture {
            inner: self.inner.call(req),
            rpc,
            sent,
        }
    }
}

pin_project_lite::pin_project! {
    /// The response future of [`GrpcMetricsService`].
    pub struct ResponseFuture<F> {
        #[pin]
        inner: F,
        rpc: Option<Rpc>,
        sent: Option<Messages>,
    }
}

impl<F, B, E> Future for ResponseFuture<F>
where
    F: Future<Output = Result<http::Response<B>, E>>,
{
    type Output = Result<http::Response<MeteredBody<B>>, E>;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let this = self.project();
        let result = ready!(this.inner.poll(cx));
        let rpc = this.rpc.take();
        Poll::Ready(match result {
            Ok(res) => {
                // A trailers-only response carries its final status in the headers.
                let rpc = match (rpc, status_of(res.headers())) {
                    (Some(rpc), Some(code)) => {
                        rpc.finish(code);
                        None
                    }
                    (rpc, _) => rpc,
                };
                let sent = this.sent.take();
                Ok(res.map(|inner| MeteredBody { inner, rpc, sent }))
            }
            Err(e) => {
                if let Some(rpc) = rpc {
                    rpc.finish(code_name(Code::Unknown));
                }
                Err(e)
            }
        })
    }
}

pin_project_lite::pin_project! {
    /// A response body that counts the messages it sends and records its RPC as handled
    /// when its trailers arrive (or when it ends or is dropped without them).
    pub struct MeteredBody<B> {
        #[pin]
        inner: B,
        rpc: Option<Rpc>,
        sent: Option<Messages>,
    }
}

impl<B> http_body::Body for MeteredBody<B>
where
    B: http_body::Body,
    B::Data: AsRef<[u8]>,
{
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<B::Data>, B::Error>>> {
        let this = self.project();
        let frame = ready!(this.inner.poll_frame(cx));
        if let (Some(sent), Some(Ok(f))) = (this.sent.as_mut(), &frame) {
            sent.frame(f);
        }
        if this.rpc.is_some() {
            let code = match &frame {
                Some(Ok(f)) => f
                    .trailers_ref()
                    .map(|t| status_of(t).unwrap_or_else(|| code_name(Code::Unknown))),
                // The body failed, or ended without trailers: no status reached the client.
                Some(Err(_)) | None => Some(code_name(Code::Unknown)),
            };
            if let Some(code) = code {
                if let Some(rpc) = this.rpc.take() {
                    rpc.finish(code);
                }
            }
        }
        Poll::Ready(frame)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

pin_project_lite::pin_project! {
    /// A request body that counts the messages the handler reads from it.
    pub struct MeteredRequestBody<B> {
        #[pin]
        inner: B,
        messages: Option<Messages>,
    }
}

impl<B> http_body::Body for MeteredRequestBody<B>
where
    B: http_body::Body,
    B::Data: AsRef<[u8]>,
{
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<B::Data>, B::Error>>> {
        let this = self.project();
        let frame = ready!(this.inner.poll_frame(cx));
        if let (Some(messages), Some(Ok(f))) = (this.messages.as_mut(), &frame) {
            messages.frame(f);
        }
        Poll::Ready(frame)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests;
