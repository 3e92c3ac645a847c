//! The on-disk store: one directory per task holding its snapshot, and one commit log for
//! the whole data dir into which every pool change is appended and fdatasynced, shared by
//! all the changes that arrive together (group commit), before it is acknowledged. Format
//! (data dir version [`FORMAT_VERSION`]) documented in `docs/storage.md`:
//!
//! ```text
//! DATA_DIR/tamrm.json                      {"format": 4, "dir_id": …, "checksum": …}
//! DATA_DIR/commits.log                     a header (header.rs), then the pool changes
//!                                          since the snapshots (log.rs)
//! DATA_DIR/tasks/<name>/task.json          {"format": 1, "task_id": …, "config": …}
//! DATA_DIR/tasks/<name>/pool.json          {"format": 1, "pool_version": …, "next_seq": …,
//!                                           "seqs": […], "episodes_completed": …, "steps_shaped": …}
//! DATA_DIR/tasks/<name>/traj/<seq>.traj    one trajectory, binary, CRC-32 protected
//! ```
//!
//! A pool change is durable once its group is synced in the log; the snapshots catch up
//! only at compaction (the log past its size limit). A graceful stop logs each task's
//! counters counted since its last change (one group, one sync for all tasks), and a
//! start replays the log over the snapshots and keeps it: neither writes snapshots, so
//! both take a time bounded by the log's size limit, not by the trajectories added.
//!
//! Split by job: [`codec`] (the files' bytes), [`sealed`] (the JSON files' checksum and
//! data dir id), [`log`] (the log's bytes), [`header`] (the log's header: where its
//! acknowledged part ends, how the server stopped), [`damage`] (a torn write or a loss),
//! [`files`] (atomic writes and fsyncs), [`snapshot`] (a task's files), [`writer`] (the
//! group commit thread and compaction), [`load`] (start-up and replay), [`repair`] (the
//! clean stop and `tamrm repair`), [`dir`] (the data dir's lock, format marker and log
//! file at open), [`entry`] (a task's state in memory and what its snapshot lacks), this
//! module (the [`Store`]). Blocking file work other than the log's runs on tokio's blocking pool.

mod codec;
mod damage;
mod dir;
mod entry;
mod files;
mod header;
mod load;
mod log;
mod repair;
mod sealed;
mod snapshot;
mod writer;

use std::collections::HashMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::thread::JoinHandle;

use parking_lot::{Condvar, Mutex};

use super::memory::check_version;
use super::{apply_ops, Committed, Counters, EndedEpisodes, PoolOp, Store, StoreError, StoredTask};
use crate::core::{Pool, TaskConfig};
pub use codec::FORMAT_VERSION;
pub(super) use codec::{decode_trajectory_bytes, encode_trajectory};
use codec::{TaskFile, FILE_FORMAT};
use dir::{open_dir, OpenedDir};
use entry::Entry;
use files::{dir_name, err, fsync_dir, write_atomic};
pub use repair::RepairReport;
use sealed::seal;
use snapshot::write_pool_file;
use writer::{end_counts, Change, ClientEnds, Log, PoolChange, Queue, Stats};

const CREATING: &str = ".creating-";
const DELETING: &str = ".deleting-";
const LOG_FILE: &str = "commits.log";

/// State shared by the store's handles and its writer thread.
struct Shared {
    root: PathBuf,
    /// The data dir's id (`tamrm.json`), sealed into the files it writes.
    dir_id: String,
    log_path: PathBuf,
    /// task id → its directory, pool and snapshot state, for the tasks that exist.
    tasks: Mutex<HashMap<String, Entry>>,
    /// The log; held by whatever writes files (see [`Log`]).
    io: Mutex<Log>,
    queue: Mutex<Queue>,
    wake: Condvar,
    stats: Stats,
    /// Log size that triggers a compaction.
    log_limit: u64,
    /// The server is stopping: a compaction in progress is abandoned ([`Store::stopping`]).
    stopping: std::sync::atomic::AtomicBool,
}

struct Inner {
    shared: Arc<Shared>,
    writer: Option<JoinHandle<()>>,
    /// `DATA_DIR/LOCK`, locked exclusively while the store is open: a second process (or
    /// a second store in this one) cannot open the same data dir. Released after the
    /// writer thread has exited (fields drop after `Drop::drop`).
    _lock: fs::File,
}

impl Drop for Inner {
    /// Stops the writer without writing what still waits (nobody was told it is
    /// durable): closing a store is indistinguishable from a crash, and recovery is the
    /// same.
    fn drop(&mut self) {
        self.shared.stop();
        if let Some(h) = self.writer.take() {
            let _ = h.join();
        }
    }
}

/// Stores tasks under a data directory.
#[derive(Clone)]
pub struct DiskStore {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for DiskStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DiskStore")
            .field("root", &self.inner.shared.root)
            .finish_non_exhaustive()
    }
}

/// Counts of a [`DiskStore`]'s durable work since it was opened.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CommitStats {
    /// Every fsync and fdatasync issued (log groups, log truncations, snapshots, task
    /// creation and deletion, the data dir marker).
    pub syncs: u64,
    /// Groups written to the log, one fdatasync each (but a group of discarded episode
    /// ends only, written without one: storage.md).
    pub groups: u64,
    /// Pool changes written to the log (inserts, replaces, resets: one version each; one
    /// record holds all the changes of a commit, or of a task's group commit).
    pub changes: u64,
    /// Compactions of the log (snapshots written, log emptied) triggered by its size.
    pub compactions: u64,
}

fn checked<T>(path: &Path, r: Result<T, String>) -> Result<T, StoreError> {
    r.map_err(|m| err(path, m))
}

impl DiskStore {
    /// The log size past which the writer compacts, by default: 64 MiB.
    pub const DEFAULT_LOG_LIMIT: u64 = 64 << 20;

    /// Opens (creating if needed, migrating a format-1 dir) a data directory.
    pub fn open(root: impl Into<PathBuf>) -> Result<DiskStore, StoreError> {
        DiskStore::open_with_log_limit(root, DiskStore::DEFAULT_LOG_LIMIT)
    }

    /// [`DiskStore::open`], compacting the commit log whenever it has grown past
    /// `log_limit` bytes (small limits are for tests of compaction).
    pub fn open_with_log_limit(
        root: impl Into<PathBuf>,
        log_limit: u64,
    ) -> Result<DiskStore, StoreError> {
        let root = root.into();
        let stats = Stats::default();
        let OpenedDir {
            lock,
            log_file: file,
            log_path,
            log_len: len,
            dir_id,
        } = open_dir(&root, &stats)?;
        let shared = Arc::new(Shared {
            root,
            dir_id: sealed::dir_id_text(&dir_id),
            log_path: log_path.clone(),
            tasks: Mutex::new(HashMap::new()),
            io: Mutex::new(Log {
                file,
                path: log_path,
                len,
                failed: None,
                in_log: Default::default(),
                compact_at: log_limit,
                loaded: false,
                dir_id,
                stopped: false,
            }),
            queue: Mutex::new(Queue::default()),
            wake: Condvar::new(),
            stats,
            log_limit,
            stopping: Default::default(),
        });
        let writer = writer::spawn(shared.clone())?;
        Ok(DiskStore {
            inner: Arc::new(Inner {
                shared,
                writer: Some(writer),
                _lock: lock,
            }),
        })
    }

    /// Every fsync and fdatasync this store has issued since it was opened.
    pub fn sync_count(&self) -> u64 {
        self.inner.shared.stats.syncs.get()
    }

    /// Counts of the store's durable work since it was opened.
    pub fn commit_stats(&self) -> CommitStats {
        let s = &self.inner.shared.stats;
        CommitStats {
            syncs: s.syncs.get(),
            groups: s.groups.load(Ordering::Relaxed),
            changes: s.changes.load(Ordering::Relaxed),
            compactions: s.compactions.load(Ordering::Relaxed),
        }
    }

    /// Folds the commit log into the snapshots now (as a compaction does when the log
    /// passes its limit): every task whose snapshot lags gets a new one, in one batch of
    /// syncs, then the log is emptied. For `tamrm compact` (a stopped server's data dir,
    /// e.g. before going back to an older build) and tests; after [`Store::load`].
    pub async fn compact(&self) -> Result<(), StoreError> {
        self.run(|s| {
            let mut log = s.io.lock();
            if !log.loaded {
                return Err(err(&s.root, "the store's tasks are not loaded yet"));
            }
            if let Some(f) = &log.failed {
                return Err(err(
                    &log.path,
                    format!("the commit log failed: {}", f.message),
                ));
            }
            writer::checkpoint(s, &mut log)
        })
        .await
    }

    /// Runs blocking file work on tokio's blocking pool (inline outside a runtime).
    async fn run<T: Send + 'static>(
        &self,
        f: impl FnOnce(&Shared) -> Result<T, StoreError> + Send + 'static,
    ) -> Result<T, StoreError> {
        let inner = self.inner.clone();
        match tokio::runtime::Handle::try_current() {
            Ok(h) => h
                .spawn_blocking(move || f(&inner.shared))
                .await
                .map_err(|e| err(&self.inner.shared.root, format!("store task failed: {e}")))?,
            Err(_) => f(&inner.shared),
        }
    }
}

impl Shared {
    fn tasks_dir(&self) -> PathBuf {
        self.root.join("tasks")
    }

    fn entry(&self, id: &str) -> Result<Entry, StoreError> {
        self.tasks
            .lock()
            .get(id)
            .cloned()
            .ok_or_else(|| err(&self.tasks_dir(), format!("task {id:?} has no directory")))
    }

    fn create_task(&self, id: &str, config: &TaskConfig) -> Result<(), StoreError> {
        let mut log = self.io.lock();
        if !log.loaded {
            return Err(err(&self.root, "the store's tasks are not loaded yet"));
        }
        if log.in_log.contains(id) {
            // Records of a deleted task with this id: fold the log away first, so that
            // they can never be replayed over the new task.
            writer::checkpoint(self, &mut log)?;
        }
        let syncs = &self.stats.syncs;
        let tasks = self.tasks_dir();
        let name = dir_name(id);
        let final_dir = tasks.join(&name);
        if final_dir.exists() {
            return Err(err(&final_dir, "directory already exists"));
        }
        let staging = tasks.join(format!("{CREATING}{name}"));
        let _ = fs::remove_dir_all(&staging);
        fs::create_dir_all(staging.join("traj"))
            .map_err(|e| err(&staging, format!("create: {e}")))?;
        let task = TaskFile {
            format: FILE_FORMAT,
            task_id: id.to_string(),
            config: *config,
        };
        let task_path = staging.join("task.json");
        let bytes = seal(&task_path, &task, Some(&self.dir_id))?;
        write_atomic(&task_path, &bytes, syncs)?;
        let pool = Pool::new(config.pool_capacity as usize);
        write_pool_file(&staging, &pool, Counters::default(), &self.dir_id, syncs)?;
        fsync_dir(&staging.join("traj"), syncs)?;
        fs::rename(&staging, &final_dir).map_err(|e| err(&final_dir, format!("rename: {e}")))?;
        fsync_dir(&tasks, syncs)?;
        self.tasks.lock().insert(
            id.to_string(),
            Entry::new(
                final_dir,
                Arc::new(pool),
                Counters::default(),
                Vec::new(),
                EndedEpisodes::default(),
            ),
        );
        Ok(())
    }

    fn delete_task(&self, id: &str) -> Result<(), StoreError> {
        let _log = self.io.lock();
        let dir = self.entry(id)?.dir;
        let name = dir.file_name().and_then(|n| n.to_str()).unwrap_or("task");
        let doomed = self.tasks_dir().join(format!("{DELETING}{name}"));
        fs::rename(&dir, &doomed).map_err(|e| err(&dir, format!("rename: {e}")))?;
        fsync_dir(&self.tasks_dir(), &self.stats.syncs)?;
        self.tasks.lock().remove(id);
        if let Err(e) = fs::remove_dir_all(&doomed) {
            // Already invisible; the next start removes it.
            tracing::warn!(dir = %doomed.display(), error = %e, "could not remove a deleted task's directory");
        }
        Ok(())
    }

    /// What the snapshot of each task lacks, for the tasks whose snapshot lacks changes.
    fn dirty(&self) -> Vec<(String, entry::DirtyParts)> {
        self.tasks
            .lock()
            .iter()
            .filter(|(_, e)| e.is_dirty())
            .map(|(id, e)| (id.clone(), e.dirty_parts()))
            .collect()
    }
}

#[async_trait::async_trait]
impl Store for DiskStore {
    fn describe(&self) -> String {
        format!(
            "data dir {} (format {FORMAT_VERSION}): every pool change is appended to {LOG_FILE} and fdatasynced (one sync per group of concurrent commits) before it is acknowledged",
            self.inner.shared.root.display()
        )
    }

    async fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        self.run(|s| load::load(s, &mut s.io.lock())).await
    }

    async fn create_task(
        &self,
        id: &str,
        config: &TaskConfig,
    ) -> Result<Option<TaskConfig>, StoreError> {
        let (id, config) = (id.to_string(), *config);
        self.run(move |s| s.create_task(&id, &config)).await?;
        Ok(None)
    }

    async fn delete_task(&self, id: &str) -> Result<(), StoreError> {
        let id = id.to_string();
        self.run(move |s| s.delete_task(&id)).await
    }

    async fn commit(
        &self,
        id: &str,
        base: Arc<Pool>,
        ops: Vec<PoolOp>,
        counters: Counters,
    ) -> Result<Committed, StoreError> {
        let shared = &self.inner.shared;
        let known = shared.tasks.lock().get(id).map(|e| e.pool.version());
        if known.is_none() {
            return Err(err(
                &shared.tasks_dir(),
                format!("task {id:?} has no directory"),
            ));
        }
        check_version(id, known, &base)?;
        let ends = end_counts(&ops);
        let (pool, changed) = apply_ops(&base, ops);
        let pool = Arc::new(pool);
        let end_records = ends
            .iter()
            .map(|(c, counts)| log::encode_ends(id, c, counts));
        if pool.version() != base.version() {
            let mut records = vec![log::encode_commit(id, &base, &pool, counters)];
            records.extend(end_records);
            let done = shared.submit(Change {
                task: id.to_string(),
                pool: Some(PoolChange {
                    base_version: base.version(),
                    pool: pool.clone(),
                    counters,
                }),
                ends,
                counters: None,
                records,
            })?;
            done.await.map_err(|_| {
                err(
                    &shared.log_path,
                    "the commit log writer stopped before the commit was written",
                )
            })??;
        } else if !ends.is_empty() {
            // Ends that changed no pool (discarded offers): remembered at once (a graceful
            // shutdown writes them into `ends.json`), and logged in a group without a sync
            // of its own (storage.md): their answer costs no fsync, and a re-sent one of
            // them, offered again after an OS crash before the next sync, is at worst
            // committed once.
            if let Some(e) = shared.tasks.lock().get_mut(id) {
                e.merge_ends(&ends);
            }
            let records = end_records.collect();
            // Not awaited (the writer logs it all the same), and best effort: a store
            // that is closing answers the discarded ends regardless.
            let queued = shared.submit(Change {
                task: id.to_string(),
                pool: None,
                ends,
                counters: None,
                records,
            });
            if let Err(e) = queued {
                tracing::debug!(task = id, error = %e, "episode ends not logged");
            }
        }
        Ok(Committed::new(pool, changed))
    }

    fn syncs(&self) -> Option<u64> {
        Some(self.inner.shared.stats.syncs.get())
    }

    async fn ended_episodes(&self, id: &str, client: &str) -> Result<Vec<(u32, u64)>, StoreError> {
        let tasks = self.inner.shared.tasks.lock();
        Ok(tasks
            .get(id)
            .map(|e| e.ends.counts(client))
            .unwrap_or_default())
    }

    fn stopping(&self) {
        self.inner.shared.stopping.store(true, Ordering::Release);
    }

    async fn stopped(&self) -> Result<(), StoreError> {
        self.run(|s| s.record_clean_stop()).await
    }

    async fn save_counters(
        &self,
        id: &str,
        _pool: Arc<Pool>,
        counters: Counters,
    ) -> Result<(), StoreError> {
        // One kind-3 record, synced with every other task's: a shutdown saves the
        // counters of all tasks at once (`Registry::flush_counters`), so their records
        // form one group. No snapshot is written: what the snapshots lack stays in the
        // log, which the next start replays.
        let shared = &self.inner.shared;
        let record = {
            let mut tasks = shared.tasks.lock();
            let e = tasks
                .get_mut(id)
                .ok_or_else(|| err(&shared.tasks_dir(), format!("task {id:?} has no directory")))?;
            e.counters = counters;
            if e.durable_counters == counters {
                // Nothing counted since the last change: no record, no sync.
                return Ok(());
            }
            log::encode_counters(id, e.pool.version(), counters)
        };
        let done = shared.submit(Change {
            task: id.to_string(),
            pool: None,
            ends: ClientEnds::new(),
            counters: Some(counters),
            records: vec![record],
        })?;
        done.await.map_err(|_| {
            err(
                &shared.log_path,
                "the commit log writer stopped before the counters were written",
            )
        })?
    }
}

#[cfg(test)]
mod tests;
