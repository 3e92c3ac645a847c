//! Server settings, layered: built-in defaults < config file (TOML) < environment
//! variables < command-line flags.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use clap::{Args, Parser, Subcommand};
use serde::Deserialize;

use crate::limits::{Limits, LimitsLayer};
pub use crate::net::parse_addr;
use crate::net::tls::{HealthcheckTls, TlsFiles};
use crate::store::RedisTls;

/// Default listen address.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:50051";

/// `tamrm`: the TAMRM reward-shaping server.
#[derive(Debug, Parser)]
#[command(name = "tamrm", version = crate::build_info::describe(), about, long_about = None)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
#[allow(clippy::large_enum_variant)] // parsed once per process; boxing buys nothing
pub enum Command {
    /// Serve the tamrm.v1.Shaping gRPC API (plus grpc.health.v1 and server reflection).
    Serve(ServeArgs),
    /// Ask a server's grpc.health.v1 service whether it serves; exit 0 if it does, 1 if
    /// not (for container health checks: no shell needed).
    Healthcheck(HealthcheckArgs),
    /// Make a new random API key, or hash a given one: prints the key (once) and the
    /// `[[keys]]` entry for the `--api-keys` file, which holds only its SHA-256.
    Key(KeyArgs),
    /// Fold a stopped server's commit log into its snapshots (storage.md, "Versioning"):
    /// needed before opening the data dir with a build of format 2, and otherwise
    /// never (a running server compacts when its log passes 64 MiB).
    Compact(CompactArgs),
    /// A server's tasks: `tasks list`, `tasks get ID` (`--json` for scripts).
    Tasks(crate::cli::TasksArgs),
    /// A task's pool as a file: `pool export ID [-o FILE]`, `pool import FILE [--task
    /// NEW_ID] [--replace]` (the format of docs/storage.md, "Pool export format").
    Pool(crate::cli::PoolArgs),
    /// The shell completion script of `tamrm` (bash, zsh, fish, elvish, powershell).
    Completions(crate::cli::CompletionsArgs),
    /// Say what a start of a stopped server's damaged data dir would lose and, with
    /// --accept-loss, cut its commit log to what is valid so that it starts
    /// (docs/backups.md).
    Repair(RepairArgs),
}

/// Flags of `tamrm repair`.
#[derive(Debug, Clone, Args)]
pub struct RepairArgs {
    /// The data dir (the server using it must be stopped: it holds the dir's lock).
    #[arg(long, env = "TAMRM_DATA_DIR")]
    pub data_dir: std::path::PathBuf,
    /// Cut the log to what is valid, losing the acknowledged changes after it.
    #[arg(long)]
    pub accept_loss: bool,
}

/// Flags of `tamrm compact`.
#[derive(Debug, Clone, Args)]
pub struct CompactArgs {
    /// The data dir (the server using it must be stopped: it holds the dir's lock).
    #[arg(long, env = "TAMRM_DATA_DIR")]
    pub data_dir: std::path::PathBuf,
}

/// Flags of `tamrm key`.
#[derive(Debug, Clone, Args)]
pub struct KeyArgs {
    /// The tenant the key acts for.
    #[arg(long, default_value = "default")]
    pub tenant: String,
    /// What the key may do: reader, writer or admin.
    #[arg(long, default_value = "writer", value_parser = ["reader", "writer", "admin"])]
    pub role: String,
    /// Hash the key read from standard input instead of making a new one.
    #[arg(long)]
    pub stdin: bool,
}

/// Flags of `tamrm healthcheck`. It reads the server's own settings as `tamrm serve`
/// does (the config file, then `TAMRM_*` variables) to find the server's address and
/// TLS; its flags win over both.
#[derive(Debug, Clone, Args)]
pub struct HealthcheckArgs {
    /// The server's TOML config file, as given to `tamrm serve` (its `listen`, `[tls]`
    /// and `[healthcheck]` are used).
    #[arg(long, env = "TAMRM_CONFIG", value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// The server, `host:port` [default: the port the server's settings listen on, on
    /// loopback: 127.0.0.1:50051 unless --config or TAMRM_LISTEN say otherwise].
    #[arg(long, value_name = "ADDR", value_parser = parse_addr)]
    pub addr: Option<SocketAddr>,
    /// Seconds to wait for the answer.
    #[arg(long, default_value_t = 3)]
    pub timeout_secs: u64,
    /// TLS towards the server (see `docs/deployment.md`).
    #[command(flatten)]
    pub tls: HealthcheckTls,
}

/// What `tamrm healthcheck` checks: the address and the TLS towards it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HealthcheckTarget {
    /// The server's address.
    pub addr: SocketAddr,
    /// The healthcheck's own TLS settings (file < environment < flags).
    pub tls: HealthcheckTls,
    /// The server's TLS files, as its settings resolve them (the default CA).
    pub server_tls: TlsFiles,
}

impl HealthcheckArgs {
    /// Resolves the server's settings as `tamrm serve` would with this config file (or
    /// `TAMRM_CONFIG`) and the `TAMRM_*` variables, and overlays this command's flags:
    /// the address to check (`--addr`, else where the server listens, an unspecified
    /// address such as 0.0.0.0 becoming loopback) and the TLS to speak.
    pub fn resolve(&self) -> Result<HealthcheckTarget, SettingsError> {
        use clap::FromArgMatches;
        let matches = ServeArgs::augment_args(clap::Command::new("serve"))
            .try_get_matches_from(["serve"])
            .map_err(|e| SettingsError(format!("the server's environment: {e}")))?;
        let mut serve = ServeArgs::from_arg_matches(&matches)
            .map_err(|e| SettingsError(format!("the server's environment: {e}")))?;
        if self.config.is_some() {
            serve.config.clone_from(&self.config);
        }
        let mut tls = match &serve.config {
            Some(path) => read_file(path)?.healthcheck.unwrap_or_default(),
            None => HealthcheckTls::default(),
        };
        tls.apply(&self.tls);
        let settings = Settings::layered(&serve)?;
        Ok(HealthcheckTarget {
            addr: self.addr.unwrap_or_else(|| loopback(settings.listen)),
            tls,
            server_tls: settings.tls,
        })
    }
}

/// `listen` as a client reaches it on this machine: an unspecified address (0.0.0.0, ::)
/// becomes loopback.
fn loopback(listen: SocketAddr) -> SocketAddr {
    if !listen.ip().is_unspecified() {
        return listen;
    }
    let ip = if listen.is_ipv4() {
        std::net::Ipv4Addr::LOCALHOST.into()
    } else {
        std::net::Ipv6Addr::LOCALHOST.into()
    };
    SocketAddr::new(ip, listen.port())
}

/// Flags of `tamrm serve`. Each can also be set by the environment variable shown, or by
/// the config file; flags win over the environment, which wins over the file.
#[derive(Debug, Clone, Default, Args)]
pub struct ServeArgs {
    /// TOML config file (keys as in `docs/configuration.md`).
    #[arg(long, env = "TAMRM_CONFIG", value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Address to listen on, `host:port` (a host name is resolved); port 0 picks a free
    /// port [default: 127.0.0.1:50051].
    #[arg(long, env = "TAMRM_LISTEN", value_name = "ADDR", value_parser = parse_addr)]
    pub listen: Option<SocketAddr>,
    /// Directory for durable tasks and pools; without it, state is in memory only.
    #[arg(long, env = "TAMRM_DATA_DIR", value_name = "DIR")]
    pub data_dir: Option<PathBuf>,
    /// Write the bound address (`host:port`) to this file once listening.
    #[arg(long, env = "TAMRM_PORT_FILE", value_name = "FILE")]
    pub port_file: Option<PathBuf>,
    /// Keep tasks and pools in Redis, shared with every server given the same URL:
    /// `redis://[[USER]:PASSWORD@]HOST:PORT[/DB]`, or a Redis Cluster by its seed nodes:
    /// `redis-cluster://[[USER]:PASSWORD@]HOST:PORT[,HOST:PORT...]` (see docs/scaling.md);
    /// `rediss://` and `rediss-cluster://` over TLS (see --store-tls-ca). Excludes
    /// --data-dir.
    #[arg(long, env = "TAMRM_STORE", value_name = "URL")]
    pub store: Option<String>,
    /// With --store: how often every task's pool version is polled, in milliseconds, as
    /// a backstop for lost notifications (the staleness bound) [default: 1000].
    #[arg(long, env = "TAMRM_STORE_POLL_MS", value_name = "MS")]
    pub store_poll_ms: Option<u64>,
    /// With --store and --api-keys: how long a stream's lease on its tenant's
    /// max_open_streams lasts without renewal, in milliseconds: the bound on how long the
    /// streams of a replica that died keep counting [default: 10000].
    #[arg(long, env = "TAMRM_STORE_LEASE_MS", value_name = "MS")]
    pub store_lease_ms: Option<u64>,
    /// With a `rediss://` or `rediss-cluster://` store: PEM CA certificate(s) to verify
    /// Redis with [default: the system's roots].
    #[arg(long, env = "TAMRM_STORE_TLS_CA", value_name = "FILE")]
    pub store_tls_ca: Option<PathBuf>,
    /// With a `rediss://` store: PEM client certificate to present to Redis (needs
    /// --store-tls-key) [default: none].
    #[arg(long, env = "TAMRM_STORE_TLS_CERT", value_name = "FILE")]
    pub store_tls_cert: Option<PathBuf>,
    /// The private key of --store-tls-cert.
    #[arg(long, env = "TAMRM_STORE_TLS_KEY", value_name = "FILE")]
    pub store_tls_key: Option<PathBuf>,
    /// Server limits (each also `TAMRM_<NAME>` and `[limits] <name>` in the file).
    #[command(flatten)]
    pub limits: LimitsLayer,
    /// Seconds to wait for open streams at shutdown before exiting anyway [default: 30].
    #[arg(long, env = "TAMRM_SHUTDOWN_GRACE_SECS")]
    pub shutdown_grace_secs: Option<u64>,
    /// API key file (TOML: SHA-256 of each key, its tenant and role, tenant quotas; see
    /// docs/deployment.md). With it every RPC but health checks needs
    /// `authorization: Bearer <key>`; read again on SIGHUP. Without it the server is open.
    #[arg(long, env = "TAMRM_API_KEYS", value_name = "FILE")]
    pub api_keys: Option<PathBuf>,
    /// TLS certificate, key and client CA (each also `TAMRM_TLS_<NAME>` and `[tls]
    /// <name>` in the file).
    #[command(flatten)]
    pub tls: TlsFiles,
    /// Serve Prometheus metrics at `http://ADDR/metrics` (`host:port`; port 0 picks a free
    /// port) [default: off].
    #[arg(long, env = "TAMRM_METRICS_LISTEN", value_name = "ADDR", value_parser = parse_addr)]
    pub metrics_listen: Option<SocketAddr>,
    /// Serve a read-only page of the tasks and their pools at `http://ADDR/` on the
    /// metrics listener (needs --metrics-listen; with --api-keys, a reader key).
    #[arg(long, env = "TAMRM_DASHBOARD")]
    pub dashboard: bool,
    /// Threads of the async runtime that serves every connection [default: one per
    /// CPU]. 1 suits a server that shares a small machine with the learner it serves
    /// (see docs/configuration.md).
    #[arg(long, env = "TAMRM_WORKER_THREADS", value_name = "N")]
    pub worker_threads: Option<usize>,
}

/// The config file: every key optional.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FileSettings {
    /// Listen address (`host:port`; a host name is resolved).
    #[serde(default, deserialize_with = "deserialize_addr")]
    pub listen: Option<SocketAddr>,
    /// Data directory.
    pub data_dir: Option<PathBuf>,
    /// Port file.
    pub port_file: Option<PathBuf>,
    /// Shared store URL (`redis://`, `rediss://`, `redis-cluster://` or
    /// `rediss-cluster://`).
    pub store: Option<String>,
    /// Version poll interval of the shared store, milliseconds.
    pub store_poll_ms: Option<u64>,
    /// Stream lease time of the shared store's tenant quotas, milliseconds.
    pub store_lease_ms: Option<u64>,
    /// CA file to verify a `rediss://` store with.
    pub store_tls_ca: Option<PathBuf>,
    /// Client certificate for a `rediss://` store.
    pub store_tls_cert: Option<PathBuf>,
    /// Its private key.
    pub store_tls_key: Option<PathBuf>,
    /// Shutdown grace period, seconds.
    pub shutdown_grace_secs: Option<u64>,
    /// Limits (any subset).
    pub limits: Option<LimitsLayer>,
    /// API key file.
    pub api_keys: Option<PathBuf>,
    /// TLS files (any subset).
    pub tls: Option<TlsFiles>,
    /// `tamrm healthcheck`'s TLS settings (any subset); `tamrm serve` ignores them.
    pub healthcheck: Option<HealthcheckTls>,
    /// Metrics address (`host:port`).
    #[serde(default, deserialize_with = "deserialize_addr")]
    pub metrics_listen: Option<SocketAddr>,
    /// The dashboard on the metrics listener.
    pub dashboard: Option<bool>,
    /// Threads of the async runtime.
    pub worker_threads: Option<usize>,
}

/// Resolved server settings.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Listen address.
    pub listen: SocketAddr,
    /// Data directory (durable) or `None` (in memory).
    pub data_dir: Option<PathBuf>,
    /// Where to write the bound address.
    pub port_file: Option<PathBuf>,
    /// A store shared with other servers (`redis://...` or `redis-cluster://...`), or `None`.
    pub store: Option<String>,
    /// Version poll interval of the shared store, milliseconds.
    pub store_poll_ms: u64,
    /// Stream lease time of the shared store's tenant quotas, milliseconds.
    pub store_lease_ms: u64,
    /// TLS files for a `rediss://` store.
    pub store_tls: RedisTls,
    /// Server limits.
    pub limits: Limits,
    /// Shutdown grace period, seconds.
    pub shutdown_grace_secs: u64,
    /// API key file, or `None` for an open server.
    pub api_keys: Option<PathBuf>,
    /// TLS files (TLS off when none).
    pub tls: TlsFiles,
    /// Where to serve Prometheus metrics; `None`: no metrics.
    pub metrics_listen: Option<SocketAddr>,
    /// Whether the metrics listener also serves the dashboard.
    pub dashboard: bool,
    /// Threads of the async runtime; `None`: one per CPU.
    pub worker_threads: Option<usize>,
}

/// The default of `store_lease_ms`.
pub const DEFAULT_STORE_LEASE_MS: u64 = 10_000;
/// The least `store_lease_ms` may be.
pub const MIN_STORE_LEASE_MS: u64 = 300;

/// The most runtime threads `worker_threads` may ask for.
pub const MAX_WORKER_THREADS: usize = 1024;

impl Default for Settings {
    fn default() -> Settings {
        Settings {
            listen: DEFAULT_LISTEN.parse().expect("valid default address"),
            data_dir: None,
            port_file: None,
            store: None,
            store_poll_ms: 1000,
            store_lease_ms: DEFAULT_STORE_LEASE_MS,
            store_tls: RedisTls::default(),
            limits: Limits::default(),
            shutdown_grace_secs: 30,
            api_keys: None,
            tls: TlsFiles::default(),
            metrics_listen: None,
            dashboard: false,
            worker_threads: None,
        }
    }
}

/// A settings problem, naming its source.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct SettingsError(String);

impl Settings {
    /// Defaults, overlaid by the config file (if `args.config` names one), overlaid by the
    /// flags/environment in `args` (clap already gives flags precedence over environment).
    pub fn resolve(args: &ServeArgs) -> Result<Settings, SettingsError> {
        let s = Settings::layered(args)?;
        s.tls.check().map_err(SettingsError)?;
        if s.dashboard && s.metrics_listen.is_none() {
            return Err(SettingsError(
                "dashboard is served on the metrics listener: give --metrics-listen (TAMRM_METRICS_LISTEN) too".into(),
            ));
        }
        if let Some(url) = &s.store {
            if s.data_dir.is_some() {
                return Err(SettingsError(
                    "store and data_dir exclude each other: tasks live either in Redis (--store) or in a data dir (--data-dir)".into(),
                ));
            }
            let target = crate::store::RedisTarget::parse(url)
                .map_err(|e| SettingsError(format!("store: {e}")))?;
            s.store_tls.check(target.tls()).map_err(SettingsError)?;
        } else if !s.store_tls.is_empty() {
            return Err(SettingsError(
                "store_tls_ca, store_tls_cert and store_tls_key need a rediss:// or rediss-cluster:// store (--store)".into(),
            ));
        }
        if let Some(n) = s.worker_threads {
            if !(1..=MAX_WORKER_THREADS).contains(&n) {
                return Err(SettingsError(format!(
                    "worker_threads must be from 1 to {MAX_WORKER_THREADS}, got {n}"
                )));
            }
        }
        if s.store_poll_ms == 0 {
            return Err(SettingsError("store_poll_ms must be at least 1".into()));
        }
        if s.store_lease_ms < MIN_STORE_LEASE_MS {
            return Err(SettingsError(format!(
                "store_lease_ms must be at least {MIN_STORE_LEASE_MS} (leases are renewed every third of it), got {}",
                s.store_lease_ms
            )));
        }
        if s.limits.max_message_bytes < 1024 {
            return Err(SettingsError(format!(
                "max_message_bytes must be at least 1024, got {}",
                s.limits.max_message_bytes
            )));
        }
        Ok(s)
    }

    /// The layers without the checks of [`Settings::resolve`]: what `tamrm healthcheck`
    /// reads (it needs the address and the certificate, and must not fail on a setting
    /// that only the server uses).
    fn layered(args: &ServeArgs) -> Result<Settings, SettingsError> {
        let mut s = Settings::default();
        if let Some(path) = &args.config {
            s.apply_file(&read_file(path)?);
        }
        s.apply_args(args);
        Ok(s)
    }

    fn apply_file(&mut self, f: &FileSettings) {
        set(&mut self.listen, f.listen);
        if f.data_dir.is_some() {
            self.data_dir.clone_from(&f.data_dir);
        }
        if f.port_file.is_some() {
            self.port_file.clone_from(&f.port_file);
        }
        if f.store.is_some() {
            self.store.clone_from(&f.store);
        }
        set(&mut self.store_poll_ms, f.store_poll_ms);
        set(&mut self.store_lease_ms, f.store_lease_ms);
        self.store_tls.apply(&RedisTls {
            ca: f.store_tls_ca.clone(),
            cert: f.store_tls_cert.clone(),
            key: f.store_tls_key.clone(),
        });
        set(&mut self.shutdown_grace_secs, f.shutdown_grace_secs);
        if f.api_keys.is_some() {
            self.api_keys.clone_from(&f.api_keys);
        }
        self.metrics_listen = f.metrics_listen.or(self.metrics_listen);
        self.dashboard = f.dashboard.unwrap_or(self.dashboard);
        self.worker_threads = f.worker_threads.or(self.worker_threads);
        if let Some(l) = &f.limits {
            self.limits.apply(l);
        }
        if let Some(t) = &f.tls {
            self.tls.apply(t);
        }
    }

    fn apply_args(&mut self, a: &ServeArgs) {
        set(&mut self.listen, a.listen);
        if a.data_dir.is_some() {
            self.data_dir.clone_from(&a.data_dir);
        }
        if a.port_file.is_some() {
            self.port_file.clone_from(&a.port_file);
        }
        if a.store.is_some() {
            self.store.clone_from(&a.store);
        }
        set(&mut self.store_poll_ms, a.store_poll_ms);
        set(&mut self.store_lease_ms, a.store_lease_ms);
        self.store_tls.apply(&RedisTls {
            ca: a.store_tls_ca.clone(),
            cert: a.store_tls_cert.clone(),
            key: a.store_tls_key.clone(),
        });
        set(&mut self.shutdown_grace_secs, a.shutdown_grace_secs);
        if a.api_keys.is_some() {
            self.api_keys.clone_from(&a.api_keys);
        }
        self.metrics_listen = a.metrics_listen.or(self.metrics_listen);
        self.dashboard |= a.dashboard;
        self.worker_threads = a.worker_threads.or(self.worker_threads);
        self.limits.apply(&a.limits);
        self.tls.apply(&a.tls);
    }
}

fn deserialize_addr<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<Option<SocketAddr>, D::Error> {
    let s = String::deserialize(d)?;
    parse_addr(&s).map(Some).map_err(serde::de::Error::custom)
}

fn set<T>(slot: &mut T, value: Option<T>) {
    if let Some(v) = value {
        *slot = v;
    }
}

fn read_file(path: &Path) -> Result<FileSettings, SettingsError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| SettingsError(format!("config file {}: {e}", path.display())))?;
    toml::from_str(&text).map_err(|e| SettingsError(format!("config file {}: {e}", path.display())))
}

#[cfg(test)]
mod tests;
