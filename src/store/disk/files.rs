//! File-system steps of the disk store: atomic writes, directory fsyncs, JSON files,
//! leftovers of interrupted writes, and the names of task directories and trajectory
//! files.

use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use serde::Deserialize;

use crate::store::StoreError;

pub(super) fn err(path: &Path, e: impl std::fmt::Display) -> StoreError {
    StoreError::new(path, e)
}

/// Counts the fsyncs and fdatasyncs a store issues (every call, whatever it syncs).
#[derive(Debug, Default)]
pub(super) struct Syncs(AtomicU64);

impl Syncs {
    /// Records one sync.
    pub fn add(&self) {
        self.0.fetch_add(1, Ordering::Relaxed);
    }
    /// Syncs so far.
    pub fn get(&self) -> u64 {
        self.0.load(Ordering::Relaxed)
    }
}

/// fsyncs a directory, so that the entries created, renamed or removed in it are durable.
pub(super) fn fsync_dir(dir: &Path, syncs: &Syncs) -> Result<(), StoreError> {
    syncs.add();
    File::open(dir)
        .and_then(|f| f.sync_all())
        .map_err(|e| err(dir, format!("fsync directory: {e}")))
}

/// Writes `bytes` to a new file at `path` (no rename: for files nothing refers to yet)
/// and fsyncs it.
pub(super) fn write_new(path: &Path, bytes: &[u8], syncs: &Syncs) -> Result<(), StoreError> {
    let write = || -> std::io::Result<()> {
        let mut f = File::create(path)?;
        f.write_all(bytes)?;
        syncs.add();
        f.sync_all()
    };
    write().map_err(|e| err(path, format!("write: {e}")))
}

/// Writes `bytes` to a new file at `path` without syncing it: one of a batch whose files
/// are then synced together ([`fsync_many`]).
pub(super) fn write_unsynced(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let write = || -> std::io::Result<()> { File::create(path)?.write_all(bytes) };
    write().map_err(|e| err(path, format!("write: {e}")))
}

/// Threads that sync one batch: the file system's journal commits one transaction at a
/// time, and every fsync waiting meanwhile joins the next one, so syncs issued together
/// share commits (one by one, each file cost a commit of its own: about 2 ms here).
const SYNC_THREADS: usize = 64;

/// fsyncs every file or directory of `paths`, many at a time ([`SYNC_THREADS`]); returns
/// once all are durable, or the first failure.
pub(super) fn fsync_many(paths: &[PathBuf], syncs: &Syncs) -> Result<(), StoreError> {
    let sync = |path: &PathBuf| {
        syncs.add();
        File::open(path)
            .and_then(|f| f.sync_all())
            .map_err(|e| err(path, format!("fsync: {e}")))
    };
    if paths.len() <= 1 {
        return paths.iter().try_for_each(sync);
    }
    let per = paths.len().div_ceil(SYNC_THREADS);
    std::thread::scope(|s| {
        let workers: Vec<_> = paths
            .chunks(per)
            .map(|chunk| s.spawn(move || chunk.iter().try_for_each(sync)))
            .collect();
        workers.into_iter().try_for_each(|w| {
            w.join()
                .unwrap_or_else(|_| Err(err(&paths[0], "an fsync thread panicked")))
        })
    })
}

/// Writes `bytes` to `path` atomically: a temporary file in the same directory, fsynced,
/// renamed over `path`, then the directory fsynced.
pub(super) fn write_atomic(path: &Path, bytes: &[u8], syncs: &Syncs) -> Result<(), StoreError> {
    let tmp = tmp_path(path);
    write_new(&tmp, bytes, syncs)?;
    fs::rename(&tmp, path).map_err(|e| err(path, format!("write: {e}")))?;
    fsync_dir(path.parent().unwrap_or(Path::new(".")), syncs)
}

/// The temporary file of an atomic write of `path`: `path` + `.tmp`.
pub(super) fn tmp_path(path: &Path) -> PathBuf {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    PathBuf::from(tmp)
}

/// Reads and parses a JSON file; a parse failure is reported as corruption.
pub(super) fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, StoreError> {
    let bytes = fs::read(path).map_err(|e| err(path, format!("read: {e}")))?;
    serde_json::from_slice(&bytes).map_err(|e| err(path, format!("corrupt or truncated JSON: {e}")))
}

/// Removes `*.tmp` files directly in `dir`: the halves of atomic writes that never
/// reached their rename, so never acknowledged.
pub(super) fn remove_tmp_files(dir: &Path) -> Result<(), StoreError> {
    let entries = fs::read_dir(dir).map_err(|e| err(dir, format!("read: {e}")))?;
    for entry in entries {
        let path = entry.map_err(|e| err(dir, e))?.path();
        if path.is_file() && path.extension().is_some_and(|x| x == "tmp") {
            tracing::info!(file = %path.display(), "removing an interrupted write's temporary file");
            fs::remove_file(&path).map_err(|e| err(&path, format!("remove: {e}")))?;
        }
    }
    Ok(())
}

/// FNV-1a, 64 bit: a stable hash for directory names (std's hasher is not stable).
fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// A readable, filesystem-safe, collision-resistant directory name for a task id.
pub(super) fn dir_name(id: &str) -> String {
    let readable: String = id
        .chars()
        .take(64)
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect();
    format!("{readable}-{:016x}", fnv1a(id))
}

/// The file of trajectory `seq` in a task directory.
pub(super) fn traj_path(task_dir: &Path, seq: u64) -> PathBuf {
    task_dir.join("traj").join(format!("{seq:020}.traj"))
}

#[cfg(test)]
mod tests;
