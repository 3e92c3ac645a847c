//! The data dir itself, as a store opens it: its lock (one store at a time), its format
//! marker and id (formats 1 to 3 are migrated), and its commit log file (created when
//! missing).

use std::fs;
use std::path::{Path, PathBuf};

use super::codec::{check_root_format, RootFile, FORMAT_V1, FORMAT_V2, FORMAT_VERSION};
use super::files::{err, remove_tmp_files, write_atomic};
use super::header::{Header, HEADER_LEN, OPEN};
use super::sealed::{dir_id_bytes, new_dir_id, read_sealed, seal, Unsealed};
use super::writer::Stats;
use super::{checked, LOG_FILE};

const MARKER: &str = "tamrm.json";
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
    /// The data dir's id.
    pub dir_id: [u8; 16],
}

/// The data dir's format marker and id, as `tamrm.json` has them.
pub(super) struct Marker {
    /// `None`: no marker (a new data dir).
    pub format: Option<u32>,
    /// The data dir's id (`None` before format 4).
    pub dir_id: Option<String>,
}

/// Reads `tamrm.json`: its format (one this build opens) and, from format 4, the data
/// dir's id, checked against its checksum.
pub(super) fn read_marker(root: &Path) -> Result<Marker, StoreError> {
    let marker = root.join(MARKER);
    if !marker.exists() {
        return Ok(Marker {
            format: None,
            dir_id: None,
        });
    }
    let f: Unsealed<RootFile> = read_sealed(&marker)?;
    let format = f.value.format;
    checked(&marker, check_root_format(format))?;
    if format >= FORMAT_VERSION && (!f.sealed || f.dir_id.is_none()) {
        return Err(err(
            &marker,
            "damaged: a format-4 marker carries the data dir's id and a checksum",
        ));
    }
    Ok(Marker {
        format: Some(format),
        dir_id: f.dir_id,
    })
}

/// Writes `tamrm.json` of the current format naming the data dir `dir_id`.
pub(super) fn write_marker(root: &Path, dir_id: &str, stats: &Stats) -> Result<(), StoreError> {
    let marker = root.join(MARKER);
    let bytes = seal(
        &marker,
        &RootFile {
            format: FORMAT_VERSION,
        },
        Some(dir_id),
    )?;
    write_atomic(&marker, &bytes, &stats.syncs)
}

/// Whether `tasks/` holds anything.
pub(super) fn has_tasks(root: &Path) -> bool {
    fs::read_dir(root.join("tasks")).is_ok_and(|mut d| d.next().is_some())
}

/// Opens the data dir `root` (creating it if needed): takes its lock, removes the
/// temporary files of an interrupted write, checks or writes its format marker
/// (migrating formats 1 to 3) and opens its commit log. File syncs are counted in `stats`.
pub(super) fn open_dir(root: &Path, stats: &Stats) -> Result<OpenedDir, StoreError> {
    let tasks = root.join("tasks");
    fs::create_dir_all(&tasks).map_err(|e| err(&tasks, format!("create: {e}")))?;
    let lock = lock_data_dir(root)?;
    remove_tmp_files(root)?;
    let found = read_marker(root)?;
    let log_path = root.join(LOG_FILE);
    if found.format.is_none() && (log_path.exists() || has_tasks(root)) {
        return Err(err(
            &root.join(MARKER),
            "missing, but the data dir holds a commit log or tasks; `tamrm repair --data-dir DIR` writes it again",
        ));
    }
    let dir_id = match &found.dir_id {
        Some(id) => id.clone(),
        None => new_dir_id().map_err(|e| err(root, format!("a new data dir id: {e}")))?,
    };
    let id_bytes = dir_id_bytes(&dir_id).ok_or_else(|| {
        err(
            &root.join(MARKER),
            format!("damaged: dir_id {dir_id:?} is not 32 hex digits"),
        )
    })?;
    if !log_path.exists() {
        if found.format.is_some_and(|f| f >= FORMAT_V2) {
            return Err(err(
                &log_path,
                "missing: a data dir of format 2 or later keeps the pool changes since the last snapshots in it; restore it, or move the data dir aside",
            ));
        }
        // Created before the marker names a format with a log, so such a dir always has one.
        let h = Header {
            dir_id: id_bytes,
            acked_end: HEADER_LEN,
            state: OPEN,
        };
        write_atomic(&log_path, &h.encode(), &stats.syncs)?;
    }
    if found.format != Some(FORMAT_VERSION) {
        write_marker(root, &dir_id, stats)?;
        match found.format {
            Some(FORMAT_V1) => {
                tracing::info!(dir = %root.display(), "migrated the data dir from format 1 to format {FORMAT_VERSION} (an empty commit log added)");
            }
            Some(f) => {
                tracing::info!(dir = %root.display(), "migrated the data dir from format {f} to format {FORMAT_VERSION} (the commit log records where it ends and how the server stopped; files are sealed with a checksum as they are rewritten; an older build cannot open it)");
            }
            None => {}
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
        dir_id: id_bytes,
    })
}

/// Takes the data dir's lock, or explains who holds it.
pub(super) fn lock_data_dir(root: &Path) -> Result<fs::File, StoreError> {
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
