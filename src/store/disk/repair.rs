//! How a data dir stops and how it is repaired: a graceful stop records in the commit
//! log's header that the server stopped cleanly and where the log ends
//! ([`Shared::record_clean_stop`]); `tamrm repair` ([`DiskStore::repair`]) says what a
//! start would lose of a damaged data dir and, when the operator accepts the loss, cuts
//! the log to what is valid, so that it starts. Nothing is dropped without it.

use std::path::Path;

use super::damage::{judge, versions_after};
use super::dir::{has_tasks, lock_data_dir, read_marker, write_marker};
use super::files::err;
use super::header::{self, Found as Header, STOPPED_CLEANLY};
use super::load::{cut, inspect, migrate_v1};
use super::sealed::{dir_id_text, new_dir_id, read_sealed};
use super::writer::Stats;
use super::{DiskStore, Shared, LOG_FILE};
use crate::store::StoreError;

impl Shared {
    /// Records that the server stopped cleanly: the writer takes nothing more, and the
    /// log's header says where the log ends and that it stopped cleanly, synced. Not
    /// recorded (the next start treats the stop as a crash) when the log failed.
    pub(super) fn record_clean_stop(&self) -> Result<(), StoreError> {
        self.stop();
        let mut log = self.io.lock();
        if !log.loaded || log.stopped {
            return Ok(());
        }
        if let Some(f) = &log.failed {
            return Err(err(
                &log.path,
                format!(
                    "not recorded as stopped cleanly: the log failed ({})",
                    f.message
                ),
            ));
        }
        self.stats.syncs.add();
        log.write_header(log.len, STOPPED_CLEANLY, true)
            .map_err(|e| err(&log.path, format!("record the clean stop: {e}")))?;
        log.stopped = true;
        tracing::info!(log = %log.path.display(), end = log.len, "recorded the clean stop in the commit log's header");
        Ok(())
    }
}

/// What `tamrm repair` found and did.
#[derive(Debug, Clone, Default)]
pub struct RepairReport {
    /// What it found and did, a line each, for the operator.
    pub lines: Vec<String>,
    /// A start would refuse (acknowledged changes would be lost), and nothing was cut.
    pub would_lose: bool,
    /// It cut the log (or rewrote the marker): the data dir now starts.
    pub repaired: bool,
}

impl DiskStore {
    /// Inspects the stopped data dir `root` as a start would. With `accept_loss`, cuts
    /// its commit log to what is valid (and writes a damaged or missing `tamrm.json`
    /// again), logging per task the versions lost, so that it starts. Damage it cannot
    /// cut away (a task's files) is returned as an error naming the file.
    pub fn repair(root: &Path, accept_loss: bool) -> Result<RepairReport, StoreError> {
        let mut report = RepairReport::default();
        repair_marker(root, accept_loss, &mut report)?;
        if report.would_lose {
            return Ok(report);
        }
        let store = DiskStore::open(root)?;
        let shared = &store.inner.shared;
        let mut log = shared.io.lock();
        let bytes = std::fs::read(&log.path).map_err(|e| err(&log.path, format!("read: {e}")))?;
        let foreign = judge(&bytes, &log.dir_id);
        if let (true, true, Some(why)) = (foreign.foreign, accept_loss, &foreign.refusal) {
            // Nothing in it is this data dir's: an empty log, every task from its snapshot.
            cut(shared, &mut log, 0)?;
            report.lines.push(format!(
                "{}: {why}; replaced by an empty log: every task starts from its snapshot, the changes since lost",
                log.path.display()
            ));
            report.repaired = true;
        }
        let found = match inspect(shared, &log) {
            Err(e) if !accept_loss && foreign.foreign => {
                report.lines.push(e.to_string());
                report.lines.push("nothing changed; with --accept-loss the log is replaced by an empty one, every task starting from its snapshot".into());
                report.would_lose = true;
                return Ok(report);
            }
            r => r?,
        };
        let j = &found.judged;
        let restorable = found.versions();
        let Some(problem) = &j.refusal else {
            match &j.torn {
                Some((offset, len, why)) => report.lines.push(format!(
                    "a start cuts {len} bytes at offset {offset} of {LOG_FILE}: {why}; nothing acknowledged is lost"
                )),
                None if !report.repaired => report
                    .lines
                    .push("the data dir starts as it is: nothing to repair".into()),
                None => {}
            }
            return Ok(report);
        };
        report
            .lines
            .push(format!("{}: {problem}", log.path.display()));
        let later = versions_after(j);
        for (id, v) in &restorable {
            let lost = match later.get(id) {
                Some(l) if l > v => format!("versions {} to {l} (at least) are lost", v + 1),
                _ => "any change after it that the log held past the damage is lost".into(),
            };
            report
                .lines
                .push(format!("task {id:?}: restorable at version {v}; {lost}"));
        }
        if !accept_loss {
            report.would_lose = true;
            report.lines.push(format!(
                "nothing changed; `tamrm repair --data-dir {} --accept-loss` cuts {} at offset {} so that the data dir starts",
                root.display(),
                LOG_FILE,
                j.valid_end
            ));
            return Ok(report);
        }
        let end = j.valid_end;
        match j.v1 {
            true => migrate_v1(shared, &mut log, &bytes[..end as usize])?,
            false => cut(shared, &mut log, end)?,
        }
        for (id, v) in &restorable {
            tracing::warn!(task = %id, restored_version = v, lost_up_to = later.get(id).copied(), "repair: the commit log was cut; changes of this task after its restored version are lost");
        }
        report.lines.push(format!(
            "cut {LOG_FILE} at offset {end}: the data dir starts, with the versions above"
        ));
        report.repaired = true;
        Ok(report)
    }
}

/// When `tamrm.json` names another data dir (`id`) than the log's header and the tasks'
/// files, which agree: the marker is the stranger, and that problem.
fn stranger_marker(root: &Path, id: Option<&str>) -> Option<String> {
    let log = std::fs::read(root.join(LOG_FILE)).ok()?;
    let Ok(Header::V2(h)) = header::decode(&log) else {
        return None;
    };
    let log_id = dir_id_text(&h.dir_id);
    if id == Some(log_id.as_str()) {
        return None;
    }
    let task = std::fs::read_dir(root.join("tasks"))
        .ok()?
        .next()?
        .ok()?
        .path();
    let tasks_id = read_sealed::<serde_json::Value>(&task.join("task.json"))
        .ok()?
        .dir_id?;
    (tasks_id == log_id).then(|| {
        format!(
            "{}: names data dir {}, but the commit log and the tasks name {log_id}: copied from another data dir",
            root.join("tamrm.json").display(),
            id.unwrap_or("none")
        )
    })
}

/// A damaged or missing `tamrm.json` of a data dir that holds a log or tasks: reported,
/// and with `accept_loss` written again naming the data dir its log's header names (a new
/// id if the header is unreadable).
fn repair_marker(
    root: &Path,
    accept_loss: bool,
    report: &mut RepairReport,
) -> Result<(), StoreError> {
    let marker = root.join("tamrm.json");
    let problem = match read_marker(root) {
        Ok(m) if m.format.is_some() => match stranger_marker(root, m.dir_id.as_deref()) {
            Some(problem) => problem,
            None => return Ok(()),
        },
        Ok(_) if !root.join(LOG_FILE).exists() && !has_tasks(root) => return Ok(()),
        Ok(_) => format!("{}: missing", marker.display()),
        Err(e) => e.to_string(),
    };
    let log = std::fs::read(root.join(LOG_FILE)).unwrap_or_default();
    let id = match header::decode(&log) {
        Ok(Header::V2(h)) => dir_id_text(&h.dir_id),
        _ => new_dir_id().map_err(|e| err(root, format!("a new data dir id: {e}")))?,
    };
    report.lines.push(problem);
    if !accept_loss {
        report.would_lose = true;
        report.lines.push(format!(
            "nothing changed; `tamrm repair --data-dir {} --accept-loss` writes tamrm.json again (data dir id {id})",
            root.display()
        ));
        return Ok(());
    }
    let lock = lock_data_dir(root)?;
    write_marker(root, &id, &Stats::default())?;
    drop(lock);
    report.lines.push(format!(
        "wrote {} again (data dir id {id})",
        marker.display()
    ));
    report.repaired = true;
    Ok(())
}
