//! The data dir itself, as a store opens it: its lock (one store at a time), its format
//! marker (a format-1 dir is migrated), and its commit log file (created when missing).

use std::fs;
use std::path::{Path, PathBuf};

use super::codec::{check_root_format, RootFile, FORMAT_V1, FORMAT_V2, FORMAT_VERSION};
use super::files::{err, read_json, remove_tmp_files, write_atomic};
use super::writer::Stats;
use super::{checked, log, LOG_FILE};
use crate::store::StoreError;

/// A data dir, opened: locked, of the current format, with its commit log.
pub(super) struct OpenedDir {
    /// `DATA_DIR/LOCK`, locked exclusively until dropped.
    pub lock: fs::File,
    /// The commit log, open for reading and writing.
    pub log_file: fs::File,
    /// Its path.
    pub log_path: PathBuf,
    /// Its length now.
    pub log_len: u64,
}

/// Opens the data dir `root` (creating it if needed): takes its lock, removes the
/// temporary files of an interrupted write, checks or writes its format marker
/// (migrating format 1) and opens its commit log. File syncs are counted in `stats`.
pub(super) fn open_dir(root: &Path, stats: &Stats) -> Result<OpenedDir, StoreError> {
    let tasks = root.join("tasks");
    fs::create_dir_all(&tasks).map_err(|e| err(&tasks, format!("create: {e}")))?;
    let lock = lock_data_dir(root)?;
    remove_tmp_files(root)?;
    let marker = root.join("tamrm.json");
    let found = if marker.exists() {
        let f: RootFile = read_json(&marker)?;
        checked(&marker, check_root_format(f.format))?;
        Some(f.format)
    } else {
        None
    };
    let log_path = root.join(LOG_FILE);
    if !log_path.exists() {
        if found.is_some_and(|f| f >= FORMAT_V2) {
            return Err(err(
                &log_path,
                "missing: a data dir of format 2 or later keeps the pool changes since the last snapshots in it; restore it, or move the data dir aside",
            ));
        }
        // Created before the marker names a format with a log, so such a dir always has one.
        write_atomic(&log_path, &log::header(), &stats.syncs)?;
    }
    if found != Some(FORMAT_VERSION) {
        let bytes = serde_json::to_vec(&RootFile {
            format: FORMAT_VERSION,
        })
        .map_err(|e| err(&marker, e))?;
        write_atomic(&marker, &bytes, &stats.syncs)?;
        match found {
            Some(FORMAT_V1) => {
                tracing::info!(dir = %root.display(), "migrated the data dir from format 1 to format {FORMAT_VERSION} (an empty commit log added)");
            }
            Some(FORMAT_V2) => {
                tracing::info!(dir = %root.display(), "migrated the data dir from format 2 to format {FORMAT_VERSION} (graceful stops now leave the commit log to the next start; an older build cannot open it)");
            }
            _ => {}
        }
    }
    let file = fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&log_path)
        .map_err(|e| err(&log_path, format!("open: {e}")))?;
    let len = file
        .metadata()
        .map_err(|e| err(&log_path, format!("stat: {e}")))?
        .len();
    Ok(OpenedDir {
        lock,
        log_file: file,
        log_path,
        log_len: len,
    })
}

/// Takes the data dir's lock, or explains who holds it.
fn lock_data_dir(root: &Path) -> Result<fs::File, StoreError> {
    let path = root.join("LOCK");
    let file = fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(|e| err(&path, format!("open: {e}")))?;
    // A lock belongs to the open file description, which a process forked by another
    // thread of this one shares until it execs: a lock just released can look held for
    // a moment. Only a lock still held after `LOCK_PATIENCE` is another user's.
    let deadline = std::time::Instant::now() + LOCK_PATIENCE;
    loop {
        match file.try_lock() {
            Ok(()) => return Ok(file),
            Err(fs::TryLockError::WouldBlock) if std::time::Instant::now() < deadline => {
                std::thread::sleep(std::time::Duration::from_millis(5))
            }
            Err(fs::TryLockError::WouldBlock) => return Err(err(
                root,
                "the data dir is in use by another tamrm process (its LOCK file is held); stop that process or use another data dir",
            )),
            Err(fs::TryLockError::Error(e)) => return Err(err(&path, format!("lock: {e}"))),
        }
    }
}

/// How long [`lock_data_dir`] waits for a held lock before it reports the data dir as in
/// use.
const LOCK_PATIENCE: std::time::Duration = std::time::Duration::from_millis(500);
