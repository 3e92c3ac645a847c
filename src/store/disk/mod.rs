//! The on-disk store: one directory per task, every change written atomically and
//! fsynced before it is acknowledged. Format (version [`FORMAT_VERSION`]) documented in
//! `docs/storage.md`:
//!
//! ```text
//! DATA_DIR/tamrm.json                      {"format": 1}
//! DATA_DIR/tasks/<name>/task.json          {"format": 1, "task_id": …, "config": …}
//! DATA_DIR/tasks/<name>/pool.json          {"format": 1, "pool_version": …, "next_seq": …,
//!                                           "seqs": […], "episodes_completed": …, "steps_shaped": …}
//! DATA_DIR/tasks/<name>/traj/<seq>.traj    one trajectory, binary, CRC-32 protected
//! ```
//!
//! `pool.json` is the commit point: a trajectory file not listed in it is an unfinished
//! change (removed at start); a listed file that is missing or fails its checks makes the
//! server refuse to start, naming the file.
//!
//! Split by job: [`codec`] (the bytes), [`files`] (atomic writes and fsyncs), this module
//! (the [`Store`]: which files a change writes, in which order). The blocking file work
//! runs on tokio's blocking pool.

mod codec;
mod files;

use std::collections::{HashMap, HashSet};
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use parking_lot::Mutex;

use super::memory::check_version;
use super::{apply_ops, Committed, Counters, PoolOp, Store, StoreError, StoredTask};
use crate::core::{Pool, TaskConfig};
pub use codec::FORMAT_VERSION;
use codec::{check_format, decode_trajectory, encode_trajectory, PoolFile, RootFile, TaskFile};
use files::{
    dir_name, err, fsync_dir, read_json, remove_tmp_files, traj_path, write_atomic, write_new,
};

const CREATING: &str = ".creating-";
const DELETING: &str = ".deleting-";

/// A task the store holds: its directory and the pool version last committed.
#[derive(Debug, Clone)]
struct Entry {
    dir: PathBuf,
    version: u64,
}

#[derive(Debug)]
struct Inner {
    root: PathBuf,
    /// `DATA_DIR/LOCK`, locked exclusively while the store is open: a second process (or
    /// a second store in this one) cannot open the same data dir.
    _lock: fs::File,
    /// task id → its directory and version, for the tasks that exist.
    tasks: Mutex<HashMap<String, Entry>>,
}

/// Stores tasks under a data directory.
#[derive(Debug, Clone)]
pub struct DiskStore {
    inner: Arc<Inner>,
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
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(fs::TryLockError::WouldBlock) => Err(err(
            root,
            "the data dir is in use by another tamrm process (its LOCK file is held); stop that process or use another data dir",
        )),
        Err(fs::TryLockError::Error(e)) => Err(err(&path, format!("lock: {e}"))),
    }
}

fn checked<T>(path: &Path, r: Result<T, String>) -> Result<T, StoreError> {
    r.map_err(|m| err(path, m))
}

impl DiskStore {
    /// Opens (creating if needed) a data directory.
    pub fn open(root: impl Into<PathBuf>) -> Result<DiskStore, StoreError> {
        let root = root.into();
        let tasks = root.join("tasks");
        fs::create_dir_all(&tasks).map_err(|e| err(&tasks, format!("create: {e}")))?;
        let lock = lock_data_dir(&root)?;
        remove_tmp_files(&root)?;
        let marker = root.join("tamrm.json");
        if marker.exists() {
            let f: RootFile = read_json(&marker)?;
            checked(&marker, check_format(f.format))?;
        } else {
            let bytes = serde_json::to_vec(&RootFile {
                format: FORMAT_VERSION,
            })
            .map_err(|e| err(&marker, e))?;
            write_atomic(&marker, &bytes)?;
        }
        Ok(DiskStore {
            inner: Arc::new(Inner {
                root,
                _lock: lock,
                tasks: Mutex::new(HashMap::new()),
            }),
        })
    }

    /// Runs blocking file work on tokio's blocking pool (inline outside a runtime).
    async fn run<T: Send + 'static>(
        &self,
        f: impl FnOnce(&Inner) -> Result<T, StoreError> + Send + 'static,
    ) -> Result<T, StoreError> {
        let inner = self.inner.clone();
        match tokio::runtime::Handle::try_current() {
            Ok(h) => h
                .spawn_blocking(move || f(&inner))
                .await
                .map_err(|e| err(&self.inner.root, format!("store task failed: {e}")))?,
            Err(_) => f(&inner),
        }
    }
}

impl Inner {
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

    fn write_pool_file(dir: &Path, pool: &Pool, counters: Counters) -> Result<(), StoreError> {
        let path = dir.join("pool.json");
        let bytes =
            serde_json::to_vec_pretty(&PoolFile::new(pool, counters)).map_err(|e| err(&path, e))?;
        write_atomic(&path, &bytes)
    }

    fn load_task(&self, dir: &Path) -> Result<StoredTask, StoreError> {
        remove_tmp_files(dir)?;
        let task_path = dir.join("task.json");
        let task: TaskFile = read_json(&task_path)?;
        checked(&task_path, check_format(task.format))?;
        let pool_path = dir.join("pool.json");
        let pf: PoolFile = read_json(&pool_path)?;
        checked(&pool_path, check_format(pf.format))?;
        let mut trajectories = Vec::with_capacity(pf.seqs.len());
        for &seq in &pf.seqs {
            let path = traj_path(dir, seq);
            let bytes = fs::read(&path).map_err(|e| {
                err(
                    &path,
                    format!("listed in pool.json but cannot be read: {e}"),
                )
            })?;
            trajectories.push(checked(
                &path,
                decode_trajectory(&path, &bytes, &task.config),
            )?);
        }
        // Files not listed in pool.json are unfinished or superseded changes.
        let traj_dir = dir.join("traj");
        let listed: HashSet<PathBuf> = pf.seqs.iter().map(|&s| traj_path(dir, s)).collect();
        let entries = fs::read_dir(&traj_dir).map_err(|e| err(&traj_dir, format!("read: {e}")))?;
        for entry in entries {
            let path = entry.map_err(|e| err(&traj_dir, e))?.path();
            if !listed.contains(&path) {
                tracing::info!(file = %path.display(), "removing trajectory file not committed to pool.json (an unfinished or superseded change)");
                fs::remove_file(&path).map_err(|e| err(&path, format!("remove: {e}")))?;
            }
        }
        let pool = Pool::restore(
            task.config.pool_capacity as usize,
            trajectories,
            pf.pool_version,
            pf.next_seq,
        )
        .map_err(|m| err(&pool_path, m))?;
        Ok(StoredTask {
            id: task.task_id,
            config: task.config,
            pool,
            counters: pf.counters(),
        })
    }

    fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        let tasks_dir = self.tasks_dir();
        let mut names: Vec<PathBuf> = fs::read_dir(&tasks_dir)
            .map_err(|e| err(&tasks_dir, format!("read: {e}")))?
            .map(|e| e.map(|e| e.path()).map_err(|e| err(&tasks_dir, e)))
            .collect::<Result<_, _>>()?;
        names.sort();
        let mut out = Vec::new();
        let mut tasks = self.tasks.lock();
        for path in names {
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if name.starts_with(CREATING) || name.starts_with(DELETING) {
                tracing::warn!(dir = %path.display(), "removing an unfinished task creation or deletion");
                fs::remove_dir_all(&path).map_err(|e| err(&path, format!("remove: {e}")))?;
                continue;
            }
            if !path.is_dir() {
                return Err(err(&path, "unexpected file in the tasks directory"));
            }
            let task = self.load_task(&path)?;
            let entry = Entry {
                dir: path.clone(),
                version: task.pool.version(),
            };
            if let Some(other) = tasks.insert(task.id.clone(), entry) {
                return Err(err(
                    &path,
                    format!(
                        "task {:?} is also stored in {}",
                        task.id,
                        other.dir.display()
                    ),
                ));
            }
            out.push(task);
        }
        fsync_dir(&tasks_dir)?;
        Ok(out)
    }

    fn create_task(&self, id: &str, config: &TaskConfig) -> Result<(), StoreError> {
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
            format: FORMAT_VERSION,
            task_id: id.to_string(),
            config: *config,
        };
        let task_path = staging.join("task.json");
        let bytes = serde_json::to_vec_pretty(&task).map_err(|e| err(&task_path, e))?;
        write_atomic(&task_path, &bytes)?;
        Self::write_pool_file(
            &staging,
            &Pool::new(config.pool_capacity as usize),
            Counters::default(),
        )?;
        fsync_dir(&staging.join("traj"))?;
        fs::rename(&staging, &final_dir).map_err(|e| err(&final_dir, format!("rename: {e}")))?;
        fsync_dir(&tasks)?;
        self.tasks.lock().insert(
            id.to_string(),
            Entry {
                dir: final_dir,
                version: 0,
            },
        );
        Ok(())
    }

    fn delete_task(&self, id: &str) -> Result<(), StoreError> {
        let dir = self.entry(id)?.dir;
        let name = dir.file_name().and_then(|n| n.to_str()).unwrap_or("task");
        let doomed = self.tasks_dir().join(format!("{DELETING}{name}"));
        fs::rename(&dir, &doomed).map_err(|e| err(&dir, format!("rename: {e}")))?;
        fsync_dir(&self.tasks_dir())?;
        self.tasks.lock().remove(id);
        if let Err(e) = fs::remove_dir_all(&doomed) {
            // Already invisible; the next start removes it.
            tracing::warn!(dir = %doomed.display(), error = %e, "could not remove a deleted task's directory");
        }
        Ok(())
    }

    /// Writes the trajectories `after` has and `before` lacks, then `pool.json` (the
    /// commit point), then removes the files of trajectories `after` dropped.
    fn persist(
        &self,
        dir: &Path,
        before: &Pool,
        after: &Pool,
        counters: Counters,
    ) -> Result<(), StoreError> {
        let old: HashSet<u64> = before.seqs().iter().copied().collect();
        let new: HashSet<u64> = after.seqs().iter().copied().collect();
        let mut wrote = false;
        for t in after
            .trajectories()
            .iter()
            .filter(|t| !old.contains(&t.seq))
        {
            // Not yet referenced by pool.json, so written in place: a crash here leaves
            // only an unlisted file, removed at the next start.
            write_new(&traj_path(dir, t.seq), &encode_trajectory(t))?;
            wrote = true;
        }
        if wrote {
            fsync_dir(&dir.join("traj"))?;
        }
        Self::write_pool_file(dir, after, counters)?;
        for seq in old.difference(&new) {
            let path = traj_path(dir, *seq);
            if let Err(e) = fs::remove_file(&path) {
                tracing::warn!(file = %path.display(), error = %e, "could not remove a superseded trajectory file; it is removed at the next start");
            }
        }
        Ok(())
    }

    fn commit(
        &self,
        id: &str,
        base: &Pool,
        ops: Vec<PoolOp>,
        counters: Counters,
    ) -> Result<Committed, StoreError> {
        let entry = self.entry(id)?;
        check_version(id, Some(entry.version), base)?;
        let (pool, changed) = apply_ops(base, ops);
        if pool.version() != base.version() {
            self.persist(&entry.dir, base, &pool, counters)?;
            if let Some(e) = self.tasks.lock().get_mut(id) {
                e.version = pool.version();
            }
        }
        Ok(Committed {
            pool: Arc::new(pool),
            changed,
        })
    }
}

#[async_trait::async_trait]
impl Store for DiskStore {
    fn describe(&self) -> String {
        format!(
            "data dir {} (format {FORMAT_VERSION}): every task and pool change is fsynced before it is acknowledged",
            self.inner.root.display()
        )
    }

    async fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        self.run(|s| s.load()).await
    }

    async fn create_task(&self, id: &str, config: &TaskConfig) -> Result<(), StoreError> {
        let (id, config) = (id.to_string(), *config);
        self.run(move |s| s.create_task(&id, &config)).await
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
        let id = id.to_string();
        self.run(move |s| s.commit(&id, &base, ops, counters)).await
    }

    async fn save_counters(
        &self,
        id: &str,
        pool: Arc<Pool>,
        counters: Counters,
    ) -> Result<(), StoreError> {
        let id = id.to_string();
        self.run(move |s| Inner::write_pool_file(&s.entry(&id)?.dir, &pool, counters))
            .await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_data_dir_opens_once_at_a_time() {
        let dir = tempfile::tempdir().unwrap();
        let first = DiskStore::open(dir.path()).unwrap();
        let e = DiskStore::open(dir.path()).unwrap_err().to_string();
        assert!(e.contains("in use by another tamrm process"), "{e}");
        drop(first);
        DiskStore::open(dir.path()).expect("the lock is released with the store");
    }
}
