//! Assembles and runs the gRPC server: Shaping, grpc.health.v1 and server reflection,
//! with graceful shutdown.

mod linger;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tonic::transport::Server;

use crate::auth::{Access, AuthLayer};
use crate::net::{self, tls};
use crate::proto::shaping_server::ShapingServer;
use crate::quota::QuotaLedger;
use crate::registry::Registry;
use crate::service::status::remap_response_headers;
use crate::service::{ShapingRoutes, ShapingService};
use crate::settings::Settings;
use crate::store::{DiskStore, MemoryStore, RedisOptions, RedisStore, Store};
use crate::telemetry::{self, GrpcMetricsLayer, Metrics};

/// Why the server could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The data directory could not be opened or holds corrupt state.
    #[error("cannot restore state: {0}")]
    Store(#[from] crate::store::StoreError),
    /// The listen address could not be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The cause.
        source: std::io::Error,
    },
    /// The port file could not be written.
    #[error("cannot write port file: {0}")]
    PortFile(std::io::Error),
    /// The API key file could not be read or is invalid.
    #[error("{0}")]
    ApiKeys(#[from] crate::auth::KeyFileError),
    /// The reflection service could not be built from the embedded descriptors.
    #[error("cannot build the reflection service: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// A TLS file is missing, unreadable or not usable PEM (a settings error).
    #[error("{0}")]
    Tls(#[from] tls::TlsError),
}

impl StartError {
    /// Whether a setting is at fault (a TLS or API key file it names): the binary exits
    /// with 2 for these, as for every other settings error (docs/configuration.md).
    pub fn is_settings_error(&self) -> bool {
        matches!(self, Self::Tls(_) | Self::ApiKeys(_))
    }
}

/// A running server.
pub struct RunningServer {
    addr: SocketAddr,
    shutdown: CancellationToken,
    grace: Duration,
    registry: Arc<Registry>,
    /// Told when the server has stopped (a data dir records a clean stop).
    store: Arc<dyn Store>,
    serve: JoinHandle<Result<(), tonic::transport::Error>>,
    closing: TaskTracker,
    metrics_addr: Option<SocketAddr>,
}

impl RunningServer {
    /// The bound address (with the real port when listening on port 0).
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The bound address of the metrics endpoint, if metrics are on.
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.metrics_addr
    }

    /// Stops accepting, lets open streams finish the batch they are processing (they then
    /// end with UNAVAILABLE), waits up to the grace period, and persists counters.
    pub async fn shutdown(self) {
        self.shutdown.cancel();
        // A compaction in progress would hold up the last batches' commits.
        self.registry.stopping();
        match tokio::time::timeout(self.grace, self.serve).await {
            Ok(Ok(Ok(()))) => {}
            Ok(Ok(Err(e))) => tracing::error!(error = %e, "server error during shutdown"),
            Ok(Err(e)) => tracing::error!(error = %e, "server task failed"),
            Err(_) => {
                tracing::warn!(grace = ?self.grace, "connections still open after the grace period; exiting anyway")
            }
        }
        // Closed connections drain what their clients still send, so the last answers
        // are not destroyed by a TCP reset (see `linger`).
        self.closing.close();
        let _ = tokio::time::timeout(linger::LINGER, self.closing.wait()).await;
        self.registry.flush_counters().await;
        if let Err(e) = self.store.stopped().await {
            tracing::warn!(error = %e, "the clean stop is not recorded; the next start treats it as a crash");
        }
    }
}

/// HTTP/2 receive window of one connection, shared by its streams: 16 streams' worth, so
/// that one stalled stream cannot stop the others of its connection (with hyper's default
/// the two windows are equal, and it does). The bound on what one connection can make the
/// server hold of unread requests.
const CONNECTION_WINDOW: u32 = 16 << 20;

/// Opens the store, restores every task, binds and starts serving.
pub async fn start(settings: &Settings) -> Result<RunningServer, StartError> {
    tracing::info!("tamrm {}", crate::build_info::describe());
    // Before anything else: a bad certificate must not leave a half-started server.
    let tls = tls::server_config(&settings.tls)?;
    // Tenant quotas are kept for every replica in a shared store (when there are keys,
    // hence tenants); otherwise in this process.
    let mut ledger: Option<Arc<dyn QuotaLedger>> = None;
    let store: Arc<dyn Store> = match (&settings.store, &settings.data_dir) {
        (Some(url), _) => {
            let mut options = RedisOptions::new(url.as_str());
            options.poll_interval = Duration::from_millis(settings.store_poll_ms);
            options.tls = settings.store_tls.clone();
            let store = RedisStore::open(&options).await?;
            if settings.api_keys.is_some() {
                let lease = Duration::from_millis(settings.store_lease_ms);
                ledger = Some(Arc::new(store.ledger(lease)));
            }
            Arc::new(store)
        }
        (None, Some(dir)) => Arc::new(DiskStore::open(dir)?),
        (None, None) => Arc::new(MemoryStore::new()),
    };
    tracing::info!("{}", store.describe());
    let metrics = settings.metrics_listen.map(|_| Arc::new(Metrics::new()));
    let store = telemetry::metered(store, metrics.as_ref());
    let (registry, restored) = Registry::open(store.clone(), settings.limits).await?;
    if restored.tasks > 0 {
        tracing::info!(
            tasks = restored.tasks,
            trajectories = restored.trajectories,
            read_only = restored.read_only,
            "restored tasks and pools"
        );
    }
    let registry = Arc::new(registry);
    // Only a store shared with other servers announces changes.
    let _watcher = registry.watch_changes();
    // And shares its counters, at the same staleness bound.
    let _counters = registry.sync_counters_every(Duration::from_millis(settings.store_poll_ms));

    let listener = TcpListener::bind(settings.listen)
        .await
        .map_err(|source| StartError::Bind {
            addr: settings.listen,
            source,
        })?;
    let addr = listener.local_addr().map_err(|source| StartError::Bind {
        addr: settings.listen,
        source,
    })?;

    let access = open_access(settings, addr, ledger)?;
    let shutdown = CancellationToken::new();
    let limit = settings.limits.max_message_bytes;
    let mut service = ShapingService::new(registry.clone(), shutdown.clone());
    if access.is_some() {
        service = service.with_credentials_required();
    }
    let shaping = ShapingRoutes::new(service.with_metrics(metrics.clone()), limit);
    let (health_reporter, health) = tonic_health::server::health_reporter();
    health_reporter
        .set_serving::<ShapingServer<ShapingService>>()
        .await;
    let reflection = |b: tonic_reflection::server::Builder<'static>| {
        b.register_encoded_file_descriptor_set(crate::proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection_v1 = reflection(tonic_reflection::server::Builder::configure()).build_v1()?;
    let reflection_v1alpha =
        reflection(tonic_reflection::server::Builder::configure()).build_v1alpha()?;
    let metrics_addr = match (settings.metrics_listen, &metrics) {
        (Some(at), Some(m)) => Some(
            telemetry::listen(
                at,
                m.clone(),
                registry.clone(),
                settings.dashboard.then(|| telemetry::Dashboard {
                    tasks: registry.clone(),
                    access: access.clone(),
                }),
                shutdown.clone(),
            )
            .await
            .map_err(|source| StartError::Bind { addr: at, source })?,
        ),
        _ => None,
    };

    let stop = shutdown.clone();
    let reporter = health_reporter.clone();
    let closing = TaskTracker::new();
    let tracker = closing.clone();
    let keepalive = settings.limits.keepalive_secs;
    let builder = match tls {
        Some(config) => Server::builder()
            .tls_config(config)
            .map_err(|e| tls::TlsError {
                what: "TLS configuration",
                file: settings.tls.cert.clone().unwrap_or_default(),
                problem: net::chain(&e),
            })?,
        None => Server::builder(),
    };
    let router = builder
        .initial_stream_window_size(crate::service::STREAM_WINDOW)
        .initial_connection_window_size(CONNECTION_WINDOW)
        .http2_keepalive_interval((keepalive > 0).then(|| Duration::from_secs(keepalive)))
        .http2_keepalive_timeout(Some(Duration::from_secs(
            settings.limits.keepalive_timeout_secs.max(1),
        )))
        .layer(GrpcMetricsLayer::new(metrics)) // outside the remap: sees the final codes
        .layer(tower::util::MapResponseLayer::new(remap_response_headers))
        .layer(tower::util::option_layer(access.map(AuthLayer::new)))
        .add_service(health)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(shaping);
    let serve = tokio::spawn(async move {
        let signal = async move {
            stop.cancelled().await;
            reporter
                .set_not_serving::<ShapingServer<ShapingService>>()
                .await;
        };
        router
            .serve_with_incoming_shutdown(linger::incoming(listener, tracker), signal)
            .await
    });
    tracing::info!("{}", settings.tls.describe());
    tracing::info!("listening on {addr}");
    tracing::info!(
        "runtime threads: {}",
        tokio::runtime::Handle::current().metrics().num_workers()
    );
    if let Some(path) = &settings.port_file {
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, format!("{addr}\n"))
            .and_then(|_| std::fs::rename(&tmp, path))
            .map_err(StartError::PortFile)?;
    }
    Ok(RunningServer {
        addr,
        shutdown,
        grace: Duration::from_secs(settings.shutdown_grace_secs),
        registry,
        store,
        serve,
        closing,
        metrics_addr,
    })
}

/// Reads the API key file, if the settings name one, and reloads it on SIGHUP for as long
/// as the server runs; without one, says that the server is open (a warning when it
/// listens beyond loopback).
fn open_access(
    settings: &Settings,
    addr: SocketAddr,
    ledger: Option<Arc<dyn QuotaLedger>>,
) -> Result<Option<Arc<Access>>, StartError> {
    let Some(path) = &settings.api_keys else {
        if addr.ip().is_loopback() {
            tracing::info!("no --api-keys: the server is open to every local caller (one default tenant, every right)");
        } else {
            tracing::warn!("no --api-keys: the server is OPEN: anyone who reaches {addr} can read, change and delete every task; give it an --api-keys file");
        }
        return Ok(None);
    };
    if let Some(ledger) = &ledger {
        tracing::info!("{}", ledger.describe());
    }
    let access = Arc::new(Access::open_with(path, ledger)?);
    tracing::info!(file = %path.display(), "API keys required (authorization: Bearer <key>); SIGHUP reads the file again");
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::hangup()) {
            Ok(mut hup) => {
                let weak = Arc::downgrade(&access);
                tokio::spawn(async move {
                    while hup.recv().await.is_some() {
                        let Some(access) = weak.upgrade() else { return };
                        match access.reload() {
                            Ok((keys, tenants)) => {
                                tracing::info!(keys, tenants, "API key file read again")
                            }
                            Err(e) => tracing::error!("{e}; the keys in force stay"),
                        }
                    }
                });
            }
            Err(e) => {
                tracing::warn!(error = %e, "cannot watch SIGHUP: the API key file is read only at start")
            }
        }
    }
    Ok(Some(access))
}

/// Asks the server at `addr` whether it serves `tamrm.v1.Shaping` (grpc.health.v1),
/// within `timeout`, over TLS when `tls` is given. `Ok` when it answers SERVING;
/// otherwise why not.
pub async fn healthcheck(
    addr: SocketAddr,
    tls: Option<tonic::transport::ClientTlsConfig>,
    timeout: Duration,
) -> Result<(), String> {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{health_client::HealthClient, HealthCheckRequest};
    let check = async {
        let plaintext = tls.is_none();
        let scheme = if plaintext { "http" } else { "https" };
        let mut endpoint = tonic::transport::Endpoint::from_shared(format!("{scheme}://{addr}"))
            .map_err(|e| e.to_string())?;
        if let Some(config) = tls {
            endpoint = endpoint.tls_config(config).map_err(|e| net::chain(&e))?;
        }
        let channel = endpoint
            .connect()
            .await
            .map_err(|e| format!("cannot connect to {addr}: {}", net::chain(&e)))?;
        let service = <ShapingServer<ShapingService> as tonic::server::NamedService>::NAME;
        let answer = HealthClient::new(channel)
            .check(HealthCheckRequest {
                service: service.to_string(),
            })
            .await
            .map_err(|s| {
                let why = net::status_chain(&s);
                let hint = if plaintext && why.contains("h2 protocol error") {
                    " (does the server have TLS on? then give --tls-ca or TAMRM_TLS_CA)"
                } else {
                    ""
                };
                format!("{addr}: {why}{hint}")
            })?;
        match answer.into_inner().status() {
            ServingStatus::Serving => Ok(()),
            other => Err(format!("{addr}: {service} is {}", other.as_str_name())),
        }
    };
    tokio::time::timeout(timeout, check)
        .await
        .unwrap_or_else(|_| Err(format!("{addr}: no answer within {timeout:?}")))
}
