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

use std::collections::HashMap;
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use parking_lot::Mutex;
use serde::{Deserialize, Serialize};

use super::{Counters, Store, StoreError, StoredTask};
use crate::core::{ActionSeq, Pool, TaskConfig, Trajectory};

/// Version of the on-disk format written by this build.
pub const FORMAT_VERSION: u32 = 1;

const TRAJ_MAGIC: &[u8; 8] = b"TAMRMTRJ";
const CREATING: &str = ".creating-";
const DELETING: &str = ".deleting-";

#[derive(Serialize, Deserialize)]
struct RootFile {
    format: u32,
}

#[derive(Serialize, Deserialize)]
struct TaskFile {
    format: u32,
    task_id: String,
    config: TaskConfig,
}

#[derive(Serialize, Deserialize)]
struct PoolFile {
    format: u32,
    pool_version: u64,
    next_seq: u64,
    seqs: Vec<u64>,
    episodes_completed: u64,
    steps_shaped: u64,
}

/// Stores tasks under a data directory.
#[derive(Debug)]
pub struct DiskStore {
    root: PathBuf,
    /// task id → its directory, for the tasks that exist.
    dirs: Mutex<HashMap<String, PathBuf>>,
}

fn err(path: &Path, e: impl std::fmt::Display) -> StoreError {
    StoreError::new(path, e)
}

fn fsync_dir(dir: &Path) -> Result<(), StoreError> {
    File::open(dir)
        .and_then(|f| f.sync_all())
        .map_err(|e| err(dir, format!("fsync directory: {e}")))
}

/// Writes `bytes` to `path` atomically: a temporary file in the same directory, fsynced,
/// renamed over `path`, then the directory fsynced.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    let write = || -> std::io::Result<()> {
        let mut f = File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        fs::rename(&tmp, path)
    };
    write().map_err(|e| err(path, format!("write: {e}")))?;
    fsync_dir(path.parent().unwrap_or(Path::new(".")))
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, StoreError> {
    let bytes = fs::read(path).map_err(|e| err(path, format!("read: {e}")))?;
    serde_json::from_slice(&bytes).map_err(|e| err(path, format!("corrupt or truncated JSON: {e}")))
}

fn check_format(path: &Path, format: u32) -> Result<(), StoreError> {
    if format != FORMAT_VERSION {
        return Err(err(
            path,
            format!(
                "on-disk format {format} is not supported by this build (format {FORMAT_VERSION})"
            ),
        ));
    }
    Ok(())
}

/// Removes `*.tmp` files directly in `dir`: the halves of atomic writes that never
/// reached their rename, so never acknowledged.
fn remove_tmp_files(dir: &Path) -> Result<(), StoreError> {
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
fn dir_name(id: &str) -> String {
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

fn traj_path(task_dir: &Path, seq: u64) -> PathBuf {
    task_dir.join("traj").join(format!("{seq:020}.traj"))
}

/// Binary trajectory file: magic, format, kind, dim, seq, score, length, payload, CRC-32
/// of everything before it; all little-endian.
fn encode_trajectory(t: &Trajectory) -> Vec<u8> {
    let (kind, dim, len) = match &t.actions {
        ActionSeq::Discrete(v) => (0u32, 0u32, v.len()),
        ActionSeq::Continuous { dim, data } => (1, *dim as u32, data.len() / dim),
    };
    let mut b = Vec::with_capacity(48 + len * 4 * (dim.max(1) as usize));
    b.extend_from_slice(TRAJ_MAGIC);
    b.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    b.extend_from_slice(&kind.to_le_bytes());
    b.extend_from_slice(&dim.to_le_bytes());
    b.extend_from_slice(&t.seq.to_le_bytes());
    b.extend_from_slice(&t.score.to_bits().to_le_bytes());
    b.extend_from_slice(&(len as u64).to_le_bytes());
    match &t.actions {
        ActionSeq::Discrete(v) => v.iter().for_each(|a| b.extend_from_slice(&a.to_le_bytes())),
        ActionSeq::Continuous { data, .. } => data
            .iter()
            .for_each(|a| b.extend_from_slice(&a.to_bits().to_le_bytes())),
    }
    let crc = crc32fast::hash(&b);
    b.extend_from_slice(&crc.to_le_bytes());
    b
}

fn decode_trajectory(path: &Path, b: &[u8], config: &TaskConfig) -> Result<Trajectory, String> {
    const HEADER: usize = 8 + 4 + 4 + 4 + 8 + 8 + 8;
    if b.len() < HEADER + 4 {
        return Err(format!(
            "truncated: {} bytes, a trajectory file has at least {}",
            b.len(),
            HEADER + 4
        ));
    }
    let (body, crc) = b.split_at(b.len() - 4);
    let stored_crc = u32::from_le_bytes(crc.try_into().map_err(|_| "crc")?);
    if &b[..8] != TRAJ_MAGIC {
        return Err("not a tamrm trajectory file (bad magic)".into());
    }
    if crc32fast::hash(body) != stored_crc {
        return Err("checksum mismatch: the file is corrupt or truncated".into());
    }
    let u32_at = |o: usize| u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
    let u64_at = |o: usize| {
        let mut a = [0u8; 8];
        a.copy_from_slice(&b[o..o + 8]);
        u64::from_le_bytes(a)
    };
    let format = u32_at(8);
    if format != FORMAT_VERSION {
        return Err(format!(
            "format {format} is not supported (this build: {FORMAT_VERSION})"
        ));
    }
    let (kind, dim) = (u32_at(12), u32_at(16) as usize);
    let seq = u64_at(20);
    let score = f64::from_bits(u64_at(28));
    let len = usize::try_from(u64_at(36)).map_err(|_| "length overflows")?;
    let payload = &body[HEADER..];
    let expect_name = traj_path(Path::new(""), seq);
    if path.file_name() != expect_name.file_name() {
        return Err(format!(
            "holds seq {seq}, which does not match its file name"
        ));
    }
    let actions = match (kind, config.action_space) {
        (0, crate::core::ActionSpace::Discrete { num_actions }) => {
            if Some(payload.len()) != len.checked_mul(4) {
                return Err(format!(
                    "payload is {} bytes for {len} actions",
                    payload.len()
                ));
            }
            let v: Vec<u32> = payload
                .chunks_exact(4)
                .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            if let Some(a) = v.iter().find(|&&a| a >= num_actions) {
                return Err(format!(
                    "action {a} out of range for num_actions {num_actions}"
                ));
            }
            ActionSeq::Discrete(v)
        }
        (1, crate::core::ActionSpace::Continuous { action_dim }) if dim == action_dim as usize => {
            if Some(payload.len()) != len.checked_mul(dim).and_then(|x| x.checked_mul(4)) {
                return Err(format!(
                    "payload is {} bytes for {len} actions of dim {dim}",
                    payload.len()
                ));
            }
            let data: Vec<f32> = payload
                .chunks_exact(4)
                .map(|c| f32::from_bits(u32::from_le_bytes([c[0], c[1], c[2], c[3]])))
                .collect();
            ActionSeq::Continuous { dim, data }
        }
        _ => {
            return Err(format!(
                "action kind {kind}/dim {dim} does not match the task config"
            ))
        }
    };
    if len == 0 || len > config.max_trajectory_len as usize {
        return Err(format!(
            "length {len} outside 1..={}",
            config.max_trajectory_len
        ));
    }
    Ok(Trajectory {
        actions,
        score,
        seq,
    })
}

impl DiskStore {
    /// Opens (creating if needed) a data directory.
    pub fn open(root: impl Into<PathBuf>) -> Result<DiskStore, StoreError> {
        let root = root.into();
        let tasks = root.join("tasks");
        fs::create_dir_all(&tasks).map_err(|e| err(&tasks, format!("create: {e}")))?;
        remove_tmp_files(&root)?;
        let marker = root.join("tamrm.json");
        if marker.exists() {
            let f: RootFile = read_json(&marker)?;
            check_format(&marker, f.format)?;
        } else {
            let bytes = serde_json::to_vec(&RootFile {
                format: FORMAT_VERSION,
            })
            .map_err(|e| err(&marker, e))?;
            write_atomic(&marker, &bytes)?;
        }
        Ok(DiskStore {
            root,
            dirs: Mutex::new(HashMap::new()),
        })
    }

    fn tasks_dir(&self) -> PathBuf {
        self.root.join("tasks")
    }

    fn task_dir(&self, id: &str) -> Result<PathBuf, StoreError> {
        self.dirs
            .lock()
            .get(id)
            .cloned()
            .ok_or_else(|| err(&self.tasks_dir(), format!("task {id:?} has no directory")))
    }

    fn write_pool_file(dir: &Path, pool: &Pool, counters: Counters) -> Result<(), StoreError> {
        let file = PoolFile {
            format: FORMAT_VERSION,
            pool_version: pool.version(),
            next_seq: pool.next_seq(),
            seqs: pool.seqs().to_vec(),
            episodes_completed: counters.episodes_completed,
            steps_shaped: counters.steps_shaped,
        };
        let path = dir.join("pool.json");
        let bytes = serde_json::to_vec_pretty(&file).map_err(|e| err(&path, e))?;
        write_atomic(&path, &bytes)
    }

    fn load_task(&self, dir: &Path) -> Result<StoredTask, StoreError> {
        remove_tmp_files(dir)?;
        let task_path = dir.join("task.json");
        let task: TaskFile = read_json(&task_path)?;
        check_format(&task_path, task.format)?;
        let pool_path = dir.join("pool.json");
        let pf: PoolFile = read_json(&pool_path)?;
        check_format(&pool_path, pf.format)?;
        let mut trajectories = Vec::with_capacity(pf.seqs.len());
        for &seq in &pf.seqs {
            let path = traj_path(dir, seq);
            let bytes = fs::read(&path).map_err(|e| {
                err(
                    &path,
                    format!("listed in pool.json but cannot be read: {e}"),
                )
            })?;
            let t = decode_trajectory(&path, &bytes, &task.config).map_err(|m| err(&path, m))?;
            trajectories.push(t);
        }
        // Files not listed in pool.json are unfinished or superseded changes.
        let traj_dir = dir.join("traj");
        let listed: std::collections::HashSet<PathBuf> =
            pf.seqs.iter().map(|&s| traj_path(dir, s)).collect();
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
            counters: Counters {
                episodes_completed: pf.episodes_completed,
                steps_shaped: pf.steps_shaped,
            },
        })
    }
}

impl Store for DiskStore {
    fn describe(&self) -> String {
        format!(
            "data dir {} (format {FORMAT_VERSION}): every task and pool change is fsynced before it is acknowledged",
            self.root.display()
        )
    }

    fn is_durable(&self) -> bool {
        true
    }

    fn load(&self) -> Result<Vec<StoredTask>, StoreError> {
        let tasks_dir = self.tasks_dir();
        let mut names: Vec<PathBuf> = fs::read_dir(&tasks_dir)
            .map_err(|e| err(&tasks_dir, format!("read: {e}")))?
            .map(|e| e.map(|e| e.path()).map_err(|e| err(&tasks_dir, e)))
            .collect::<Result<_, _>>()?;
        names.sort();
        let mut out = Vec::new();
        let mut dirs = self.dirs.lock();
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
            if let Some(other) = dirs.insert(task.id.clone(), path.clone()) {
                return Err(err(
                    &path,
                    format!("task {:?} is also stored in {}", task.id, other.display()),
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
        self.dirs.lock().insert(id.to_string(), final_dir);
        Ok(())
    }

    fn delete_task(&self, id: &str) -> Result<(), StoreError> {
        let dir = self.task_dir(id)?;
        let name = dir.file_name().and_then(|n| n.to_str()).unwrap_or("task");
        let doomed = self.tasks_dir().join(format!("{DELETING}{name}"));
        fs::rename(&dir, &doomed).map_err(|e| err(&dir, format!("rename: {e}")))?;
        fsync_dir(&self.tasks_dir())?;
        self.dirs.lock().remove(id);
        if let Err(e) = fs::remove_dir_all(&doomed) {
            // Already invisible; the next start removes it.
            tracing::warn!(dir = %doomed.display(), error = %e, "could not remove a deleted task's directory");
        }
        Ok(())
    }

    fn commit(
        &self,
        id: &str,
        before: &Pool,
        after: &Pool,
        counters: Counters,
    ) -> Result<(), StoreError> {
        let dir = self.task_dir(id)?;
        let old: std::collections::HashSet<u64> = before.seqs().iter().copied().collect();
        let new: std::collections::HashSet<u64> = after.seqs().iter().copied().collect();
        let added: Vec<&Trajectory> = after
            .trajectories()
            .iter()
            .filter(|t| !old.contains(&t.seq))
            .map(|t| t.as_ref())
            .collect();
        if !added.is_empty() {
            // Not yet referenced by pool.json, so written in place: a crash here leaves
            // only an unlisted file, removed at the next start.
            for t in &added {
                let path = traj_path(&dir, t.seq);
                let write = || -> std::io::Result<()> {
                    let mut f = File::create(&path)?;
                    f.write_all(&encode_trajectory(t))?;
                    f.sync_all()
                };
                write().map_err(|e| err(&path, format!("write: {e}")))?;
            }
            fsync_dir(&dir.join("traj"))?;
        }
        // The commit point.
        Self::write_pool_file(&dir, after, counters)?;
        for seq in old.difference(&new) {
            let path = traj_path(&dir, *seq);
            if let Err(e) = fs::remove_file(&path) {
                tracing::warn!(file = %path.display(), error = %e, "could not remove a superseded trajectory file; it is removed at the next start");
            }
        }
        Ok(())
    }

    fn save_counters(&self, id: &str, pool: &Pool, counters: Counters) -> Result<(), StoreError> {
        Self::write_pool_file(&self.task_dir(id)?, pool, counters)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::TaskConfigInput;

    fn cfg(n: u32, m: u32) -> TaskConfig {
        TaskConfig::resolve(&TaskConfigInput {
            num_actions: n,
            action_dim: m,
            pool_capacity: Some(3),
            ..Default::default()
        })
        .unwrap()
    }

    #[test]
    fn trajectories_round_trip_bit_for_bit() {
        let t = Trajectory {
            actions: ActionSeq::Continuous {
                dim: 2,
                data: vec![1.5, -0.0, f32::MIN_POSITIVE, 3.25],
            },
            score: -0.1,
            seq: 42,
        };
        let bytes = encode_trajectory(&t);
        let path = traj_path(Path::new("x"), 42);
        assert_eq!(decode_trajectory(&path, &bytes, &cfg(0, 2)).unwrap(), t);
        // Every truncation and every single-byte flip is detected.
        for cut in 0..bytes.len() {
            assert!(
                decode_trajectory(&path, &bytes[..cut], &cfg(0, 2)).is_err(),
                "cut {cut}"
            );
        }
        for i in 0..bytes.len() {
            let mut b = bytes.clone();
            b[i] ^= 0x40;
            assert!(
                decode_trajectory(&path, &b, &cfg(0, 2)).is_err(),
                "flip {i}"
            );
        }
        // Wrong kind for the task.
        assert!(decode_trajectory(&path, &bytes, &cfg(4, 0)).is_err());
    }

    #[test]
    fn directory_names_are_safe_and_distinct() {
        let a = dir_name("maze/v1:seed-0");
        assert!(!a.contains('/') && !a.contains(':'));
        assert_ne!(dir_name("a/b"), dir_name("a:b"));
        assert!(dir_name(&"x".repeat(128)).len() < 100);
    }
}
