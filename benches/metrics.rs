//! The cost of recording metrics (docs/benchmarks.md, "Metrics overhead"):
//!
//! - `record_batch`: what a Shape stream adds per `StepBatch` with metrics on: two clock
//!   reads, two histogram observations, two counter additions (`ShapeMetrics::batch`);
//! - `grpc_layer/{none,off,on}`: one unary request to a service that answers at once with
//!   a body of one data frame and `grpc-status: 0` trailers, the body drained: without the
//!   layer, through `GrpcMetricsLayer` without metrics, and with them.
//!
//! `cargo bench --bench metrics`

use std::convert::Infallible;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;
use criterion::{criterion_group, criterion_main, Criterion};
use http_body_util::{BodyExt, StreamBody};
use hyper::body::Frame;
use tamrm::telemetry::{GrpcMetricsLayer, Metrics};
use tower::{Layer, Service, ServiceExt};

fn record_batch(c: &mut Criterion) {
    let metrics = Metrics::new();
    let shape = metrics.shape("bench");
    c.bench_function("metrics/record_batch", |b| {
        b.iter(|| {
            let started = Instant::now();
            shape.batch(
                std::hint::black_box(256),
                std::hint::black_box(1),
                started.elapsed(),
            );
        })
    });
}

type Body = StreamBody<futures::stream::Iter<std::vec::IntoIter<Result<Frame<Bytes>, Infallible>>>>;

/// Answers without reading the request body (of any type: the layer hands the inner
/// service its body wrapped in a message counter).
fn answer<B>(
    _req: http::Request<B>,
) -> std::future::Ready<Result<http::Response<Body>, Infallible>> {
    let mut trailers = http::HeaderMap::new();
    trailers.insert("grpc-status", http::HeaderValue::from_static("0"));
    let frames = vec![
        Ok(Frame::data(Bytes::from_static(b"\0\0\0\0\x02ok"))),
        Ok(Frame::trailers(trailers)),
    ];
    std::future::ready(Ok(http::Response::new(StreamBody::new(
        futures::stream::iter(frames),
    ))))
}

/// One unary request through `svc`, its body drained.
fn one_request<S, B>(svc: &mut S)
where
    S: Service<http::Request<()>, Response = http::Response<B>, Error = Infallible>,
    B: http_body::Body<Data = Bytes>,
    B::Error: std::fmt::Debug,
{
    futures::executor::block_on(async {
        let req = http::Request::builder()
            .uri("/tamrm.v1.Shaping/GetTask")
            .body(())
            .expect("request");
        let svc = svc.ready().await.expect("ready");
        let res = svc.call(req).await.expect("response");
        res.into_body().collect().await.expect("body")
    });
}

fn grpc_layer(c: &mut Criterion) {
    let mut bare = tower::service_fn(answer::<()>);
    c.bench_function("metrics/grpc_layer/none", |b| {
        b.iter(|| one_request(&mut bare))
    });
    for (name, metrics) in [("off", None), ("on", Some(Arc::new(Metrics::new())))] {
        let mut svc = GrpcMetricsLayer::new(metrics).layer(tower::service_fn(answer));
        c.bench_function(&format!("metrics/grpc_layer/{name}"), |b| {
            b.iter(|| one_request(&mut svc))
        });
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().measurement_time(Duration::from_secs(3));
    targets = record_batch, grpc_layer
}
criterion_main!(benches);
