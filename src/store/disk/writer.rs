//! Group commit: one thread owns the commit log. It takes every commit waiting at that
//! moment (from all streams and all tasks), checks each against the task's current
//! version, appends their records as one group with one `write`, calls `fdatasync` once,
//! publishes the new pools in the store's table and only then acknowledges them all.
//! While it syncs, the next commits queue up and form the next group.
//!
//! Compaction (also here, between groups, when the log has grown past the limit): every
//! task whose pool is newer than its snapshot gets a new snapshot, then the log is
//! truncated to its header and fsynced. A crash anywhere in between leaves records that
//! the snapshots already contain, which replay skips by version.

use std::collections::{HashMap, HashSet, VecDeque};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;

use tokio::sync::oneshot;

use super::entry::write_dirty;
use super::files::{err, Syncs};
use super::header::{Header, HEADER_LEN, OPEN};
use super::log::encode_group;
use super::Shared;
use crate::core::Pool;
use crate::store::{Counters, PoolOp, StoreError};

/// At most this many bytes of records go into one group (a larger single record still
/// forms a group of its own).
const MAX_GROUP_BYTES: usize = 16 << 20;

/// A change for the writer: a task's pool change, the episode ends it records (SPEC §9),
/// or both; or the task's counters at a graceful stop; with their encoded log records.
pub(super) struct Change {
    pub task: String,
    /// The pool change; `None` for a record of discarded episode ends only, or of
    /// counters (checked against no version: neither changes the pool).
    pub pool: Option<PoolChange>,
    pub ends: ClientEnds,
    /// The counters a kind-3 record holds (synced, and then durable).
    pub counters: Option<Counters>,
    pub records: Vec<Vec<u8>>,
}

/// Episode ends per client: (client, [(env, episodes ended)]).
pub(super) type ClientEnds = Vec<(Arc<str>, Vec<(u32, u64)>)>;

/// A pool change: the version it was planned against, the resulting pool and counters.
pub(super) struct PoolChange {
    pub base_version: u64,
    pub pool: Arc<Pool>,
    pub counters: Counters,
}

impl Change {
    fn bytes(&self) -> usize {
        self.records.iter().map(Vec::len).sum()
    }
}

/// A change waiting for the writer, with where to send the outcome.
struct CommitReq {
    change: Change,
    ack: oneshot::Sender<Result<(), StoreError>>,
}

/// Commits waiting for the writer.
#[derive(Default)]
pub(super) struct Queue {
    jobs: VecDeque<CommitReq>,
    /// The store is closing: the writer exits without writing what waits.
    stop: bool,
    /// The writer has exited: nothing is accepted any more.
    dead: bool,
}

/// The commit log file and what the writer knows about it. Held (in `Shared::io`) by the
/// writer for a group or a compaction, and by whatever else writes task files (load,
/// create, delete, graceful-shutdown snapshots), so these never interleave.
pub(super) struct Log {
    pub file: File,
    pub path: PathBuf,
    /// End of the last complete group.
    pub len: u64,
    /// Set when a write or sync failed: nothing more is appended until it is cleared
    /// ([`Failed`] says how).
    pub failed: Option<Failed>,
    /// Tasks with records in the log (including deleted ones).
    pub in_log: HashSet<String>,
    /// The log size at which the writer compacts next.
    pub compact_at: u64,
    /// `load` has run: the tasks are known and the log is replayed and truncated.
    pub loaded: bool,
    /// The data dir's id, which the log's header names.
    pub dir_id: [u8; 16],
    /// A graceful stop recorded itself in the header: nothing more is appended.
    pub stopped: bool,
}

impl Log {
    /// Writes the log's header saying that it ends at `acked_end` and is in `state`
    /// (`sync`: and makes the whole file durable).
    pub fn write_header(&self, acked_end: u64, state: u32, sync: bool) -> std::io::Result<()> {
        let h = Header {
            dir_id: self.dir_id,
            acked_end,
            state,
        };
        self.file.write_all_at(&h.encode(), 0)?;
        match sync {
            true => self.file.sync_data(),
            false => Ok(()),
        }
    }
}

/// A failed append to the log.
#[derive(Debug, Clone)]
pub(super) struct Failed {
    pub message: String,
    /// The sync failed: what the file holds is unknown (a failed fsync may have dropped
    /// dirty pages and a later one would not say so), so only a restart, recovering from
    /// what reached the disk, clears it. Otherwise the write itself failed (a full disk):
    /// the next group first cuts the file back to its last complete group and syncs it,
    /// and if that works the log takes changes again.
    pub in_sync: bool,
}

/// Counters of durable work, kept by the store.
#[derive(Debug, Default)]
pub(super) struct Stats {
    pub syncs: Syncs,
    pub groups: AtomicU64,
    pub changes: AtomicU64,
    pub compactions: AtomicU64,
}

impl Shared {
    /// Queues a commit for the writer; the receiver resolves once it is durable (or
    /// failed). Errors if the writer is gone.
    pub(super) fn submit(
        &self,
        change: Change,
    ) -> Result<oneshot::Receiver<Result<(), StoreError>>, StoreError> {
        let mut q = self.queue.lock();
        if q.dead || q.stop {
            return Err(err(&self.log_path, "the commit log writer has stopped"));
        }
        let (ack, rx) = oneshot::channel();
        q.jobs.push_back(CommitReq { change, ack });
        self.wake.notify_one();
        Ok(rx)
    }

    /// Tells the writer to exit (it finishes the group it is writing, if any).
    pub(super) fn stop(&self) {
        self.queue.lock().stop = true;
        self.wake.notify_all();
    }
}

/// Starts the writer thread.
pub(super) fn spawn(shared: Arc<Shared>) -> Result<JoinHandle<()>, StoreError> {
    std::thread::Builder::new()
        .name("tamrm-commit-log".into())
        .spawn(move || run(&shared))
        .map_err(|e| err(&PathBuf::from("commit log writer"), format!("spawn: {e}")))
}

/// Marks the writer dead when it exits, however it exits, dropping what still waits (its
/// callers get an error instead of waiting forever).
struct MarkDead<'a>(&'a Shared);

impl Drop for MarkDead<'_> {
    fn drop(&mut self) {
        let mut q = self.0.queue.lock();
        q.dead = true;
        q.jobs.clear();
    }
}

fn run(shared: &Shared) {
    let _dead = MarkDead(shared);
    loop {
        let batch = {
            let mut q = shared.queue.lock();
            while q.jobs.is_empty() && !q.stop {
                shared.wake.wait(&mut q);
            }
            if q.stop {
                return;
            }
            take_group(&mut q.jobs)
        };
        let mut log = shared.io.lock();
        write_group(shared, &mut log, batch);
        if log.len >= log.compact_at && log.failed.is_none() {
            match checkpoint(shared, &mut log) {
                Ok(()) => {
                    shared.stats.compactions.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) if shared.stopping.load(Ordering::Acquire) => {
                    tracing::info!(error = %e, "commit log compaction cut short by the stop");
                }
                Err(e) => {
                    log.compact_at = log.len.saturating_add(shared.log_limit);
                    tracing::warn!(error = %e, "commit log compaction failed; retried when the log has grown by its limit again");
                }
            }
        }
    }
}

/// Everything waiting, up to [`MAX_GROUP_BYTES`] of records (at least one commit).
fn take_group(jobs: &mut VecDeque<CommitReq>) -> Vec<CommitReq> {
    let mut bytes = 0;
    let mut out = Vec::with_capacity(jobs.len());
    while let Some(j) = jobs.front() {
        let n = j.change.bytes();
        if !out.is_empty() && bytes + n > MAX_GROUP_BYTES {
            break;
        }
        bytes += n;
        out.extend(jobs.pop_front());
    }
    out
}

fn reply(req: CommitReq, r: Result<(), StoreError>) {
    // The caller may have gone (a cancelled request); the outcome stands regardless.
    let _ = req.ack.send(r);
}

/// Checks, writes, syncs and acknowledges one group.
fn write_group(shared: &Shared, log: &mut Log, batch: Vec<CommitReq>) {
    recover(log);
    let mut accepted = Vec::with_capacity(batch.len());
    {
        let tasks = shared.tasks.lock();
        // Versions after the commits already accepted into this group.
        let mut pending: HashMap<String, u64> = HashMap::new();
        for req in batch {
            if log.stopped {
                let m = "the server has stopped: the commit log takes no more changes";
                reply(req, Err(err(&log.path, m)));
                continue;
            }
            if let Some(f) = &log.failed {
                let m = match f.in_sync {
                    true => format!(
                        "a sync of the commit log failed earlier ({}); restart the server to recover",
                        f.message
                    ),
                    false => f.message.clone(),
                };
                reply(req, Err(err(&log.path, m)));
                continue;
            }
            let c = &req.change;
            let found = pending
                .get(&c.task)
                .copied()
                .or_else(|| tasks.get(&c.task).map(|e| e.pool.version()));
            match (found, &c.pool) {
                (None, _) => {
                    let m = format!("task {:?} has no directory", c.task);
                    reply(req, Err(err(&shared.root.join("tasks"), m)));
                }
                (Some(v), Some(p)) if v != p.base_version => {
                    let e = StoreError::Conflict {
                        task: c.task.clone(),
                        expected: p.base_version,
                        found: v,
                    };
                    reply(req, Err(e));
                }
                (Some(_), Some(p)) => {
                    pending.insert(c.task.clone(), p.pool.version());
                    accepted.push(req);
                }
                (Some(_), None) => accepted.push(req),
            }
        }
    }
    if accepted.is_empty() {
        return;
    }
    let records: Vec<&[u8]> = accepted
        .iter()
        .flat_map(|r| r.change.records.iter().map(Vec::as_slice))
        .collect();
    let bytes = encode_group(&records);
    // A group of discarded episode ends only is written without a sync of its own: it
    // survives the process (kill -9 included) in the page cache and is made durable by
    // the next group's fdatasync, so it never delays the pool changes behind it.
    let sync = accepted
        .iter()
        .any(|r| r.change.pool.is_some() || r.change.counters.is_some());
    let written = match log.file.write_all_at(&bytes, log.len) {
        Err(e) => Err((e, false)),
        Ok(()) if !sync => Ok(()),
        Ok(()) => {
            shared.stats.syncs.add();
            log.file.sync_data().map_err(|e| (e, true))
        }
    };
    if let Err((e, in_sync)) = written {
        let m = format!("append and fdatasync: {e}");
        match in_sync {
            true => {
                tracing::error!(file = %log.path.display(), error = %e, "a commit log sync failed; no more pool changes are accepted until a restart")
            }
            false => {
                tracing::error!(file = %log.path.display(), error = %e, "a commit log write failed; pool changes are refused until a write succeeds again")
            }
        }
        // Best effort: cut the partial group off (recovery drops it anyway, as the tail).
        let _ = log.file.set_len(log.len);
        log.failed = Some(Failed {
            message: m.clone(),
            in_sync,
        });
        for req in accepted {
            reply(req, Err(err(&log.path, &m)));
        }
        return;
    }
    log.len += bytes.len() as u64;
    if sync {
        // Before the acknowledgements: the header never says more than is durable, and
        // the next group's fdatasync makes it durable in turn (header.rs).
        if let Err(e) = log.write_header(log.len, OPEN, false) {
            tracing::warn!(file = %log.path.display(), error = %e, "could not record the acknowledged end in the commit log's header");
        }
    }
    shared.stats.groups.fetch_add(1, Ordering::Relaxed);
    // Pool changes, not records: a record of one task's group holds several.
    let n: u64 = accepted
        .iter()
        .filter_map(|r| r.change.pool.as_ref())
        .map(|p| p.pool.version().saturating_sub(p.base_version))
        .sum();
    shared.stats.changes.fetch_add(n, Ordering::Relaxed);
    let mut tasks = shared.tasks.lock();
    for req in accepted {
        let c = &req.change;
        if let Some(e) = tasks.get_mut(&c.task) {
            // Ends that changed no pool were merged when they were queued (commit).
            if let Some(p) = &c.pool {
                e.pool = p.pool.clone();
                e.counters = p.counters;
                e.durable_counters = p.counters;
                e.merge_ends(&c.ends);
            }
            if let Some(counters) = c.counters {
                e.durable_counters = counters;
            }
        }
        log.in_log.insert(c.task.clone());
        reply(req, Ok(()));
    }
}

/// After a failed write (not a failed sync): cuts the log back to its last complete
/// group and syncs it (the groups written without a sync of their own too); once that
/// works, the log takes changes again.
fn recover(log: &mut Log) {
    if !matches!(&log.failed, Some(f) if !f.in_sync) {
        return;
    }
    if log
        .file
        .set_len(log.len)
        .and_then(|()| log.file.sync_all())
        .is_ok()
    {
        tracing::info!(file = %log.path.display(), "the commit log takes changes again");
        log.failed = None;
    }
}

/// Snapshots every task whose pool, counters or ended episodes are newer than its
/// snapshot (one batch of syncs), then empties the log.
pub(super) fn checkpoint(shared: &Shared, log: &mut Log) -> Result<(), StoreError> {
    write_dirty(shared, &shared.dirty())?;
    truncate(shared, log)
}

/// Empties the log (keeping its header) and makes that durable before anything more is
/// appended, so that no stale group can reappear behind new ones. Only called when every
/// record in it is in a snapshot.
pub(super) fn truncate(shared: &Shared, log: &mut Log) -> Result<(), StoreError> {
    if log.len > HEADER_LEN {
        shared.stats.syncs.add();
        // The header first: a crash before the cut leaves groups past the acknowledged
        // end, which replay skips (they are in the snapshots).
        log.write_header(HEADER_LEN, OPEN, false)
            .and_then(|()| log.file.set_len(HEADER_LEN))
            .and_then(|()| log.file.sync_all())
            .map_err(|e| err(&log.path, format!("truncate: {e}")))?;
    }
    log.len = HEADER_LEN;
    log.in_log.clear();
    log.compact_at = shared.log_limit.max(HEADER_LEN + 1);
    Ok(())
}

/// The episode ends the offers of `ops` name, per client: (env, episodes ended).
pub(super) fn end_counts(ops: &[PoolOp]) -> ClientEnds {
    let mut out = ClientEnds::new();
    for op in ops {
        if let PoolOp::Offer { end: Some(m), .. } = op {
            let count = (m.env, m.episode.saturating_add(1));
            match out.iter_mut().find(|(c, _)| *c == m.client) {
                Some((_, counts)) => counts.push(count),
                None => out.push((m.client.clone(), vec![count])),
            }
        }
    }
    out
}
