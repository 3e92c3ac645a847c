//! Prometheus metrics (`tamrm serve --metrics-listen ADDR`, docs/deployment.md lists
//! them): one [`Metrics`] per server, recorded by
//! - [`GrpcMetricsLayer`], a tower layer around the whole gRPC router: every RPC's start,
//!   end (with its final `grpc-status`) and duration, and the messages it received and
//!   sent;
//! - [`ShapeMetrics`], held by each open Shape stream: one batch's latency, entries and
//!   episode ends, a few atomic operations per batch (nothing per entry);
//! - [`MeteredStore`], a [`Store`](crate::store::Store) decorator: store commits' latency
//!   and the pool changes they made;
//! - the gauges read from the registry when scraped: tasks held, and per task its pool's
//!   size, best and worst score;
//! - the `process_*` metrics of the server's process, read from `/proc` when scraped.
//!
//! With `--dashboard`, the same listener serves a read-only page of the tasks and their
//! pools ([`Dashboard`]).
//!
//! With metrics off nothing is recorded: the layer passes requests through, streams hold
//! no [`ShapeMetrics`] and the store is not wrapped.
//!
//! Label cardinality is bounded: gRPC labels come from the served services' descriptors
//! (an unknown path is `unknown`), and the per-task label names the first
//! [`MAX_TASK_LABELS`] tasks seen and [`OTHER_TASKS`] for the rest (for the pool gauges:
//! the pools of the rest together, their sizes summed, the best of their best scores and
//! the worst of their worst).

mod grpc;
mod http;
mod page;
mod process;
mod store;

use std::collections::{HashMap, HashSet};
use std::sync::atomic::AtomicU64;
use std::sync::Arc;
use std::time::Duration;

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::Histogram;

pub use grpc::{
    GrpcMetricsLayer, GrpcMetricsService, MeteredBody, MeteredRequestBody, ResponseFuture,
};
pub use http::listen;
pub use page::{task_page, Dashboard};
pub use store::{metered, MeteredStore};

/// Tasks that get their own `task` label value; later tasks share [`OTHER_TASKS`].
pub const MAX_TASK_LABELS: usize = 100;

/// The `task` label value of every task past the first [`MAX_TASK_LABELS`] (`~` is not
/// allowed in task ids, so it never names a real task).
pub const OTHER_TASKS: &str = "~other";

/// Upper bounds of the latency histograms (batch, store commit), seconds: 5 µs to 1 s.
const LATENCY_BUCKETS: [f64; 17] = [
    5e-6, 1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 0.01, 0.025, 0.05, 0.1, 0.25,
    0.5, 1.0,
];

/// Upper bounds of the batch size histogram, entries: 1, 2, 4, … 65536.
fn size_buckets() -> impl Iterator<Item = f64> {
    (0..=16).map(|i| f64::from(1u32 << i))
}

/// The `task` label.
#[derive(Debug, Clone, PartialEq, Eq, Hash, EncodeLabelSet)]
struct TaskLabel {
    task: Arc<str>,
}

/// Names the first `max` tasks it is asked about by their id, every later one
/// [`OTHER_TASKS`]. A task keeps its label for the life of the server (also when deleted
/// and created again), so a counter's series never changes name.
#[derive(Debug)]
struct TaskLabels {
    max: usize,
    named: parking_lot::Mutex<HashSet<Arc<str>>>,
    other: Arc<str>,
}

impl TaskLabels {
    fn new(max: usize) -> TaskLabels {
        TaskLabels {
            max,
            named: parking_lot::Mutex::new(HashSet::new()),
            other: Arc::from(OTHER_TASKS),
        }
    }

    fn label(&self, task: &str) -> TaskLabel {
        let mut named = self.named.lock();
        let task = match named.get(task) {
            Some(name) => name.clone(),
            None if named.len() < self.max => {
                let name: Arc<str> = Arc::from(task);
                named.insert(name.clone());
                name
            }
            None => self.other.clone(),
        };
        TaskLabel { task }
    }
}

/// Every metric of one server, and the registry that encodes them.
pub struct Metrics {
    registry: prometheus_client::registry::Registry,
    grpc: grpc::GrpcMetrics,
    steps: Family<TaskLabel, Counter>,
    episodes: Family<TaskLabel, Counter>,
    pool_changes: Family<TaskLabel, Counter>,
    batch_seconds: Histogram,
    batch_entries: Histogram,
    commit_seconds: Histogram,
    open_streams: Gauge,
    tasks: Gauge,
    stream_bytes: Gauge,
    /// The data dir's syncs, brought up to the store's count at every scrape.
    store_syncs: Counter,
    pool_size: Family<TaskLabel, Gauge>,
    pool_best: Family<TaskLabel, Gauge<f64, AtomicU64>>,
    pool_worst: Family<TaskLabel, Gauge<f64, AtomicU64>>,
    process: process::ProcessMetrics,
    /// One scrape at a time sets the gauges read at scrape time.
    scraping: parking_lot::Mutex<()>,
    labels: TaskLabels,
}

impl std::fmt::Debug for Metrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Metrics").finish_non_exhaustive()
    }
}

impl Default for Metrics {
    fn default() -> Metrics {
        Metrics::new()
    }
}

impl Metrics {
    /// Every metric at zero, registered.
    pub fn new() -> Metrics {
        Metrics::with_task_labels(MAX_TASK_LABELS)
    }

    fn with_task_labels(max_task_labels: usize) -> Metrics {
        let mut registry = prometheus_client::registry::Registry::default();
        let grpc = grpc::GrpcMetrics::register(&mut registry);
        let m = Metrics {
            grpc,
            steps: Family::default(),
            episodes: Family::default(),
            pool_changes: Family::default(),
            batch_seconds: Histogram::new(LATENCY_BUCKETS),
            batch_entries: Histogram::new(size_buckets()),
            commit_seconds: Histogram::new(LATENCY_BUCKETS),
            open_streams: Gauge::default(),
            tasks: Gauge::default(),
            stream_bytes: Gauge::default(),
            store_syncs: Counter::default(),
            pool_size: Family::default(),
            pool_best: Family::default(),
            pool_worst: Family::default(),
            process: process::ProcessMetrics::register(&mut registry),
            scraping: parking_lot::Mutex::new(()),
            labels: TaskLabels::new(max_task_labels),
            registry: prometheus_client::registry::Registry::default(),
        };
        registry.register(
            "tamrm_steps_shaped",
            "Step entries shaped by Shape streams",
            m.steps.clone(),
        );
        registry.register(
            "tamrm_episodes_completed",
            "Episodes ended by Shape streams (offered to the pool)",
            m.episodes.clone(),
        );
        registry.register(
            "tamrm_pool_changes",
            "Pool operations that changed a pool (trajectories stored, resets)",
            m.pool_changes.clone(),
        );
        registry.register(
            "tamrm_batch_seconds",
            "Time of one StepBatch through the session (validation, shaping, commit)",
            m.batch_seconds.clone(),
        );
        registry.register(
            "tamrm_batch_entries",
            "Entries per StepBatch",
            m.batch_entries.clone(),
        );
        registry.register(
            "tamrm_store_commit_seconds",
            "Time of one store commit (the episode ends of a batch, AddTrajectory, ResetPool, or a group of them on one task committed together)",
            m.commit_seconds.clone(),
        );
        registry.register(
            "tamrm_open_streams",
            "Open Shape streams",
            m.open_streams.clone(),
        );
        registry.register(
            "tamrm_store_syncs",
            "fsyncs and fdatasyncs of the data dir (0 without --data-dir): divided by tamrm_pool_changes_total, the syncs each change cost",
            m.store_syncs.clone(),
        );
        registry.register("tamrm_tasks", "Tasks held", m.tasks.clone());
        // Exposed as tamrm_build_info{...} 1 (an info metric takes the _info suffix).
        registry.register(
            "tamrm_build",
            "The server's version, commit, proto API version and data dir format",
            prometheus_client::metrics::info::Info::new(vec![
                ("version", crate::build_info::VERSION.to_owned()),
                ("commit", crate::build_info::COMMIT.to_owned()),
                ("proto", crate::build_info::PROTO.to_owned()),
                (
                    "data_dir_format",
                    crate::build_info::DATA_DIR_FORMAT.to_string(),
                ),
            ]),
        );
        registry.register(
            "tamrm_stream_bytes_reserved",
            "Bytes the open Shape streams reckon to hold (limit: max_total_stream_bytes)",
            m.stream_bytes.clone(),
        );
        registry.register(
            "tamrm_pool_size",
            "Trajectories in the task's pool (read at scrape time)",
            m.pool_size.clone(),
        );
        registry.register(
            "tamrm_pool_best_score",
            "Highest episode score in the task's pool; no series while the pool is empty",
            m.pool_best.clone(),
        );
        registry.register(
            "tamrm_pool_worst_score",
            "Lowest episode score in the task's pool; no series while the pool is empty",
            m.pool_worst.clone(),
        );
        Metrics { registry, ..m }
    }

    /// Sets the pool gauges from the tasks `tasks` holds now: a series per task label
    /// (the tasks past the label cap together), none for a task deleted since.
    fn pool_gauges(&self, tasks: &crate::registry::Registry) {
        let mut pools: HashMap<TaskLabel, (usize, Option<(f64, f64)>)> = HashMap::new();
        for task in tasks.all() {
            let stats = task.stats();
            let (size, range) = pools.entry(self.labels.label(task.key())).or_default();
            *size += stats.pool_size;
            if stats.pool_size > 0 {
                let (worst, best) = (stats.worst_score, stats.best_score);
                *range = Some(range.map_or((worst, best), |(w, b)| (w.min(worst), b.max(best))));
            }
        }
        self.pool_size.clear();
        self.pool_best.clear();
        self.pool_worst.clear();
        for (label, (size, range)) in pools {
            self.pool_size
                .get_or_create(&label)
                .set(i64::try_from(size).unwrap_or(i64::MAX));
            if let Some((worst, best)) = range {
                self.pool_best.get_or_create(&label).set(best);
                self.pool_worst.get_or_create(&label).set(worst);
            }
        }
    }

    /// The recorder of one open Shape stream on `task`: counts as an open stream until
    /// dropped.
    pub fn shape(&self, task: &str) -> ShapeMetrics {
        let label = self.labels.label(task);
        self.open_streams.inc();
        ShapeMetrics {
            open_streams: self.open_streams.clone(),
            steps: self.steps.get_or_create_owned(&label),
            episodes: self.episodes.get_or_create_owned(&label),
            batch_seconds: self.batch_seconds.clone(),
            batch_entries: self.batch_entries.clone(),
        }
    }

    fn commit(&self, task: &str, elapsed: Duration, changes: usize) {
        self.commit_seconds.observe(elapsed.as_secs_f64());
        if changes > 0 {
            self.pool_changes
                .get_or_create(&self.labels.label(task))
                .inc_by(changes as u64);
        }
    }

    /// The Prometheus text exposition (format 0.0.4) of every metric, with the gauges of
    /// tasks, pools and reserved stream bytes and the store's syncs read from `tasks` now,
    /// and the `process_*` metrics from `/proc`.
    pub fn render(&self, tasks: &crate::registry::Registry) -> Result<String, std::fmt::Error> {
        let _one = self.scraping.lock();
        self.pool_gauges(tasks);
        self.process.update();
        let count = tasks.len();
        self.tasks.set(i64::try_from(count).unwrap_or(i64::MAX));
        if let Some(syncs) = tasks.store_syncs() {
            let seen = self.store_syncs.get();
            self.store_syncs.inc_by(syncs.saturating_sub(seen));
        }
        let bytes = tasks.reserved_stream_bytes();
        self.stream_bytes
            .set(i64::try_from(bytes).unwrap_or(i64::MAX));
        let mut text = String::new();
        prometheus_client::encoding::prometheus_text::encode(&mut text, &self.registry)?;
        Ok(text)
    }
}

/// The metrics one Shape stream records, resolved when it opens: per batch, two
/// histogram observations and one or two counter additions. Not `Clone`: it is the
/// stream's count in `tamrm_open_streams`, given back when dropped.
#[derive(Debug)]
pub struct ShapeMetrics {
    open_streams: Gauge,
    steps: Counter,
    episodes: Counter,
    batch_seconds: Histogram,
    batch_entries: Histogram,
}

impl ShapeMetrics {
    /// Records one shaped batch: its `entries`, the `episodes` it ended and the time it
    /// took.
    pub fn batch(&self, entries: usize, episodes: usize, elapsed: Duration) {
        self.batch_seconds.observe(elapsed.as_secs_f64());
        self.batch_entries.observe(entries as f64);
        self.steps.inc_by(entries as u64);
        if episodes > 0 {
            self.episodes.inc_by(episodes as u64);
        }
    }
}

impl Drop for ShapeMetrics {
    fn drop(&mut self) {
        self.open_streams.dec();
    }
}

#[cfg(test)]
mod tests;
