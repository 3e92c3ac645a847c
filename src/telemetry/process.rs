//! The standard `process_*` metrics of the server's own process, read from `/proc` at
//! every scrape (Linux; elsewhere they stay 0): CPU seconds, resident memory, open file
//! descriptors and the start time.

use std::sync::atomic::AtomicU64;

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;

/// The `process_*` metrics, registered with names and meanings as Prometheus's own
/// clients give them.
#[derive(Debug, Default)]
pub(super) struct ProcessMetrics {
    cpu_seconds: Counter<f64, AtomicU64>,
    resident_bytes: Gauge,
    open_fds: Gauge,
    start_time: Gauge<f64, AtomicU64>,
}

/// What `/proc` says of this process now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Reading {
    /// User and system CPU time, seconds.
    pub cpu_seconds: f64,
    /// Resident set size, bytes.
    pub resident_bytes: u64,
    /// Open file descriptors.
    pub open_fds: u64,
    /// Start time, seconds since the Unix epoch.
    pub start_time: f64,
}

impl ProcessMetrics {
    pub(super) fn register(registry: &mut Registry) -> ProcessMetrics {
        let m = ProcessMetrics::default();
        registry.register(
            "process_cpu_seconds",
            "Total user and system CPU time spent in seconds",
            m.cpu_seconds.clone(),
        );
        registry.register(
            "process_resident_memory_bytes",
            "Resident memory size in bytes",
            m.resident_bytes.clone(),
        );
        registry.register(
            "process_open_fds",
            "Number of open file descriptors",
            m.open_fds.clone(),
        );
        registry.register(
            "process_start_time_seconds",
            "Start time of the process since unix epoch in seconds",
            m.start_time.clone(),
        );
        m
    }

    /// Brings the metrics to what `/proc` says now; without `/proc` they stay as they are.
    pub(super) fn update(&self) {
        let Some(r) = read() else { return };
        let seen = self.cpu_seconds.get();
        if r.cpu_seconds > seen {
            self.cpu_seconds.inc_by(r.cpu_seconds - seen);
        }
        self.resident_bytes
            .set(i64::try_from(r.resident_bytes).unwrap_or(i64::MAX));
        self.open_fds
            .set(i64::try_from(r.open_fds).unwrap_or(i64::MAX));
        self.start_time.set(r.start_time);
    }
}

/// The fields of `/proc/self/stat` after the command name (which may hold spaces and
/// parentheses, so the line is cut at its last `)`): field 3 (state) first.
fn stat_fields(stat: &str) -> Option<Vec<&str>> {
    let (_, rest) = stat.rsplit_once(')')?;
    Some(rest.split_whitespace().collect())
}

/// Parses the process's readings from the texts of `/proc/self/stat`, `/proc/stat`
/// (`btime`) and `/proc/self/status` (`VmRSS`), with `ticks` clock ticks a second.
pub(super) fn parse(
    stat: &str,
    system: &str,
    status: &str,
    ticks: f64,
    fds: u64,
) -> Option<Reading> {
    let f = stat_fields(stat)?;
    // After the name: state is field 3, utime 14, stime 15, starttime 22 (proc(5)).
    let field = |n: usize| f.get(n - 3).and_then(|v| v.parse::<u64>().ok());
    let (utime, stime, start) = (field(14)?, field(15)?, field(22)?);
    let boot: u64 = system
        .lines()
        .find_map(|l| l.strip_prefix("btime "))
        .and_then(|v| v.trim().parse().ok())?;
    let rss_kib: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    Some(Reading {
        cpu_seconds: (utime + stime) as f64 / ticks,
        resident_bytes: rss_kib * 1024,
        open_fds: fds,
        start_time: boot as f64 + start as f64 / ticks,
    })
}

/// This process's readings, `None` without `/proc`.
pub(super) fn read() -> Option<Reading> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let system = std::fs::read_to_string("/proc/stat").ok()?;
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let fds = std::fs::read_dir("/proc/self/fd").map_or(0, |d| d.count() as u64);
    parse(&stat, &system, &status, clock_ticks(), fds)
}

/// Clock ticks a second, the unit of `/proc/self/stat`'s times: the kernel's USER_HZ,
/// which `sysconf(_SC_CLK_TCK)` would return, 100 on every architecture tamrm builds for
/// (a constant keeps the crate free of `unsafe` and of a libc call).
fn clock_ticks() -> f64 {
    100.0
}
