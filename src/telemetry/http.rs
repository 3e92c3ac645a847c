//! The metrics endpoint: `GET /metrics` on its own port, HTTP/1.1, Prometheus text
//! format 0.0.4; with `--dashboard` also the dashboard's pages ([`super::page`]).
//! Anything else gets 404 (405 for another method on `/metrics`).

use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use http_body_util::Full;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;

use super::{Dashboard, Metrics};
use crate::registry::Registry;

/// How long a client may take to send a request's headers.
const HEADER_TIMEOUT: Duration = Duration::from_secs(10);

/// Binds `addr` and serves `metrics` (with the gauges read from `tasks`) there, and the
/// `dashboard` if given, until `shutdown` is cancelled. Returns the bound address (the
/// real port for port 0).
pub async fn listen(
    addr: SocketAddr,
    metrics: Arc<Metrics>,
    tasks: Arc<Registry>,
    dashboard: Option<Dashboard>,
    shutdown: CancellationToken,
) -> std::io::Result<SocketAddr> {
    let listener = TcpListener::bind(addr).await?;
    let bound = listener.local_addr()?;
    tokio::spawn(async move {
        loop {
            let stream = tokio::select! {
                _ = shutdown.cancelled() => return,
                accepted = listener.accept() => match accepted {
                    Ok((stream, _)) => stream,
                    Err(e) => {
                        // Out of file descriptors and the like: wait, do not spin.
                        tracing::warn!(error = %e, "metrics endpoint: accept failed");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        continue;
                    }
                },
            };
            let (metrics, tasks, dashboard) = (metrics.clone(), tasks.clone(), dashboard.clone());
            let service = hyper::service::service_fn(move |req: http::Request<_>| {
                let (metrics, tasks) = (metrics.clone(), tasks.clone());
                let page = dashboard.clone().map(|d| PageRequest::of(&req, d));
                async move {
                    if let Some(res) = match page {
                        Some(p) => p.answer().await,
                        None => None,
                    } {
                        return Ok::<_, Infallible>(res);
                    }
                    Ok::<_, Infallible>(answer(&req, &metrics, &tasks))
                }
            });
            let conn = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(HEADER_TIMEOUT)
                .serve_connection(TokioIo::new(stream), service);
            let stop = shutdown.clone();
            tokio::spawn(async move {
                tokio::select! {
                    _ = stop.cancelled() => {}
                    r = conn => {
                        if let Err(e) = r {
                            tracing::debug!(error = %e, "metrics endpoint: connection failed");
                        }
                    }
                }
            });
        }
    });
    tracing::info!("metrics on http://{bound}/metrics");
    Ok(bound)
}

/// A request's parts the dashboard reads, taken before its answer is awaited.
struct PageRequest {
    dashboard: Dashboard,
    get: bool,
    path: String,
    query: String,
    authorization: Option<Vec<u8>>,
}

impl PageRequest {
    fn of<B>(req: &http::Request<B>, dashboard: Dashboard) -> PageRequest {
        PageRequest {
            dashboard,
            get: req.method() == http::Method::GET || req.method() == http::Method::HEAD,
            path: req.uri().path().to_string(),
            query: req.uri().query().unwrap_or("").to_string(),
            authorization: req
                .headers()
                .get(http::header::AUTHORIZATION)
                .map(|v| v.as_bytes().to_vec()),
        }
    }

    /// The dashboard's answer, if the request is for one of its pages.
    async fn answer(self) -> Option<http::Response<Full<Bytes>>> {
        if !self.get {
            return None;
        }
        let (status, content_type, body) = self
            .dashboard
            .answer(&self.path, &self.query, self.authorization.as_deref())
            .await?;
        let mut res = http::Response::new(Full::new(Bytes::from(body)));
        *res.status_mut() = status;
        let headers = res.headers_mut();
        headers.insert(
            http::header::CONTENT_TYPE,
            http::header::HeaderValue::from_static(content_type),
        );
        headers.insert(
            http::header::CACHE_CONTROL,
            http::header::HeaderValue::from_static("no-store"),
        );
        Some(res)
    }
}

fn answer<B>(
    req: &http::Request<B>,
    metrics: &Metrics,
    tasks: &Registry,
) -> http::Response<Full<Bytes>> {
    use http::{header, Method, StatusCode};
    let reply = |status: StatusCode, content_type: &'static str, body: String| {
        let mut res = http::Response::new(Full::new(Bytes::from(body)));
        *res.status_mut() = status;
        res.headers_mut().insert(
            header::CONTENT_TYPE,
            header::HeaderValue::from_static(content_type),
        );
        res
    };
    const TEXT: &str = "text/plain; charset=utf-8";
    if req.uri().path() != "/metrics" {
        return reply(
            StatusCode::NOT_FOUND,
            TEXT,
            "not found: try /metrics\n".into(),
        );
    }
    if req.method() != Method::GET && req.method() != Method::HEAD {
        let mut res = reply(StatusCode::METHOD_NOT_ALLOWED, TEXT, "use GET\n".into());
        res.headers_mut()
            .insert(header::ALLOW, header::HeaderValue::from_static("GET, HEAD"));
        return res;
    }
    match metrics.render(tasks) {
        Ok(text) => reply(
            StatusCode::OK,
            prometheus_client::encoding::prometheus_text::CONTENT_TYPE,
            text,
        ),
        Err(e) => reply(
            StatusCode::INTERNAL_SERVER_ERROR,
            TEXT,
            format!("cannot encode the metrics: {e}\n"),
        ),
    }
}
