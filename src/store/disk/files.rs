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

/// Writes `bytes` to `path` atomically: a temporary file in the same directory, fsynced,
/// renamed over `path`, then the directory fsynced.
pub(super) fn write_atomic(path: &Path, bytes: &[u8], syncs: &Syncs) -> Result<(), StoreError> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    write_new(&tmp, bytes, syncs)?;
    fs::rename(&tmp, path).map_err(|e| err(path, format!("write: {e}")))?;
    fsync_dir(path.parent().unwrap_or(Path::new(".")), syncs)
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
