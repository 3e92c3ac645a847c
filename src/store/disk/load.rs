//! Start-up: read every task's snapshot (cleaning up unfinished changes), replay the
//! commit log over the snapshots, cut a torn last group off the log and keep the rest:
//! no snapshot is written, so a start costs reading the snapshots and at most the log's
//! size limit of records, however many changes the log holds. The next compaction folds
//! the log into snapshots.
//!
//! Replay rules per record (docs/storage.md): a record of a task without a directory is
//! ignored (the task was deleted, or moved out of `tasks/` by an operator); a pool change
//! whose version the snapshot already has is skipped; one that continues the task's
//! version is applied; one that leaves a gap is corruption. Records of ended episodes
//! are merged with the task's `ends.json` (counts only grow, so any order is right), and
//! so are records of counters (each counter the larger of the two), whose version must
//! not be past the task's. What the log holds past its valid groups is judged by
//! [`super::damage`]: a torn write past the acknowledged end is cut, anything else is
//! refused naming the log file, the offset and what each task can be restored at.

use std::collections::{HashMap, HashSet};
use std::fs;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::codec::{check_format, decode_trajectory, decode_trajectory_bytes, PoolFile, TaskFile};
use super::damage::{judge, open_header, Judged};
use super::files::{err, fsync_dir, remove_tmp_files, traj_path, write_atomic};
use super::header::{HEADER_LEN, HEADER_V1_LEN};
use super::log::{Record, Scan};
use super::sealed::read_own;
use super::snapshot::read_ends_file;
use super::writer::Log;
use super::{checked, Entry, Shared, CREATING, DELETING};
use crate::core::{Pool, Trajectory};
use crate::store::{Counters, EndedEpisodes, StoreError, StoredTask};

/// A task as its snapshot has it.
struct Loaded {
    task: StoredTask,
    dir: PathBuf,
    /// The seqs `pool.json` lists.
    listed: Vec<u64>,
    /// The pool version and counters `pool.json` holds.
    snap: (u64, Counters),
    /// `ends.json`, then the log's records of ended episodes merged in.
    ends: EndedEpisodes,
    /// The log added to `ends`.
    ends_changed: bool,
}

fn load_task(dir: &Path, dir_id: &str) -> Result<StoredTask, StoreError> {
    remove_tmp_files(dir)?;
    let task_path = dir.join("task.json");
    let task: TaskFile = read_own(&task_path, dir_id)?;
    checked(&task_path, check_format(task.format))?;
    task.config
        .check()
        .map_err(|e| err(&task_path, format!("config.{}: {}", e.field, e.message)))?;
    let pool_path = dir.join("pool.json");
    let pf: PoolFile = read_own(&pool_path, dir_id)?;
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
    // Files not listed in pool.json are unfinished or superseded changes (the commit
    // log holds its trajectories itself).
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

fn load_snapshots(shared: &Shared) -> Result<Vec<Loaded>, StoreError> {
    let tasks_dir = shared.root.join("tasks");
    let mut names: Vec<PathBuf> = fs::read_dir(&tasks_dir)
        .map_err(|e| err(&tasks_dir, format!("read: {e}")))?
        .map(|e| e.map(|e| e.path()).map_err(|e| err(&tasks_dir, e)))
        .collect::<Result<_, _>>()?;
    names.sort();
    let mut out: Vec<Loaded> = Vec::new();
    let mut seen: HashMap<String, PathBuf> = HashMap::new();
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
        let task = load_task(&path, &shared.dir_id)?;
        if let Some(other) = seen.insert(task.id.clone(), path.clone()) {
            return Err(err(
                &path,
                format!("task {:?} is also stored in {}", task.id, other.display()),
            ));
        }
        let listed = task.pool.seqs().to_vec();
        let snap = (task.pool.version(), task.counters);
        let ends = read_ends_file(&path, &shared.dir_id)?;
        out.push(Loaded {
            task,
            dir: path,
            listed,
            snap,
            ends,
            ends_changed: false,
        });
    }
    fsync_dir(&tasks_dir, &shared.stats.syncs)?;
    Ok(out)
}

/// A task's pool while records are replayed over it.
struct Replaying {
    version: u64,
    next_seq: u64,
    seqs: Vec<u64>,
    trajectories: HashMap<u64, Arc<Trajectory>>,
    counters: Counters,
}

impl Replaying {
    fn new(pool: &Pool, counters: Counters) -> Replaying {
        Replaying {
            version: pool.version(),
            next_seq: pool.next_seq(),
            seqs: pool.seqs().to_vec(),
            trajectories: pool
                .trajectories()
                .iter()
                .map(|t| (t.seq, t.clone()))
                .collect(),
            counters,
        }
    }
}

/// Replays the log's records over the snapshots. Returns the indices of the tasks it
/// changed (their pool and counters replaced).
fn replay(path: &Path, scan: &Scan, tasks: &mut [Loaded]) -> Result<Vec<usize>, StoreError> {
    let index: HashMap<String, usize> = tasks
        .iter()
        .enumerate()
        .map(|(i, t)| (t.task.id.clone(), i))
        .collect();
    let mut states: HashMap<usize, Replaying> = HashMap::new();
    let mut orphans: HashSet<&str> = HashSet::new();
    for g in &scan.groups {
        for (ri, rec) in g.records.iter().enumerate() {
            let at = |m: String| {
                err(
                    path,
                    format!(
                        "group at offset {}, record {ri}, task {:?}: {m}",
                        g.offset,
                        rec.task()
                    ),
                )
            };
            let Some(&i) = index.get(rec.task()) else {
                if orphans.insert(rec.task()) {
                    tracing::warn!(task = %rec.task(), log = %path.display(), "ignoring commit log records of a task that has no directory (deleted, or moved out of tasks/)");
                }
                continue;
            };
            let rec = match rec {
                Record::Commit(c) => c,
                Record::Ends(e) => {
                    let t = &mut tasks[i];
                    t.ends.merge(&e.client, e.counts.iter().copied());
                    t.ends_changed = true;
                    continue;
                }
                Record::Counters(c) => {
                    let task = &tasks[i].task;
                    let st = states
                        .entry(i)
                        .or_insert_with(|| Replaying::new(&task.pool, task.counters));
                    if c.version > st.version {
                        return Err(at(format!(
                            "counters at version {}, but the task is at version {}: a change is missing",
                            c.version, st.version
                        )));
                    }
                    st.counters = Counters {
                        episodes_completed: st
                            .counters
                            .episodes_completed
                            .max(c.counters.episodes_completed),
                        steps_shaped: st.counters.steps_shaped.max(c.counters.steps_shaped),
                    };
                    continue;
                }
            };
            let task = &tasks[i].task;
            let st = states
                .entry(i)
                .or_insert_with(|| Replaying::new(&task.pool, task.counters));
            if rec.version <= st.version {
                continue; // already in the snapshot
            }
            if rec.base_version != st.version {
                return Err(at(format!(
                    "a change from version {} to {}, but the task is at version {}: a change is missing",
                    rec.base_version, rec.version, st.version
                )));
            }
            let mut added = HashMap::with_capacity(rec.added.len());
            for b in &rec.added {
                let t = decode_trajectory_bytes(b, &task.config)
                    .map_err(|m| at(format!("a trajectory: {m}")))?;
                added.insert(t.seq, Arc::new(t));
            }
            let mut trajectories = HashMap::with_capacity(rec.seqs.len());
            for &s in &rec.seqs {
                let t = added
                    .remove(&s)
                    .or_else(|| st.trajectories.get(&s).cloned())
                    .ok_or_else(|| at(format!("seq {s} is neither added nor in the pool")))?;
                trajectories.insert(s, t);
            }
            if let Some(s) = added.keys().next() {
                return Err(at(format!("added trajectory seq {s} is not in the pool")));
            }
            *st = Replaying {
                version: rec.version,
                next_seq: rec.next_seq,
                seqs: rec.seqs.clone(),
                trajectories,
                counters: rec.counters,
            };
        }
    }
    let mut changed = Vec::new();
    for (i, st) in states {
        let t = &mut tasks[i].task;
        if st.counters != t.counters {
            t.counters = st.counters;
            changed.push(i);
        }
        if st.version == t.pool.version() {
            continue;
        }
        let mut list = Vec::with_capacity(st.seqs.len());
        for s in &st.seqs {
            if let Some(tr) = st.trajectories.get(s) {
                list.push(Trajectory::clone(tr));
            }
        }
        t.pool = Pool::restore(
            t.config.pool_capacity as usize,
            list,
            st.version,
            st.next_seq,
        )
        .map_err(|m| err(path, format!("task {:?} after replay: {m}", t.id)))?;
        changed.push(i);
    }
    changed.sort_unstable();
    changed.dedup();
    Ok(changed)
}

/// The data dir as a start finds it: every task's snapshot with the log's valid groups
/// replayed over it, and the log judged ([`judge`]).
pub(super) struct Found {
    tasks: Vec<Loaded>,
    changed: usize,
    pub judged: Judged,
    bytes: Vec<u8>,
}

impl Found {
    /// Per task, the pool version it would be restored at.
    pub fn versions(&self) -> Vec<(String, u64)> {
        let mut v: Vec<_> = self
            .tasks
            .iter()
            .map(|t| (t.task.id.clone(), t.task.pool.version()))
            .collect();
        v.sort();
        v
    }
}

/// Reads every snapshot and the log, judges the log and replays its valid groups.
pub(super) fn inspect(shared: &Shared, log: &Log) -> Result<Found, StoreError> {
    let bytes = fs::read(&log.path).map_err(|e| err(&log.path, format!("read: {e}")))?;
    let judged = judge(&bytes, &log.dir_id);
    if let (true, Some(why)) = (judged.foreign, &judged.refusal) {
        // Before the tasks' files, which name the data dir too: the two files that
        // disagree are named, whichever of them is the stranger.
        return Err(err(&log.path, why));
    }
    let mut tasks = load_snapshots(shared)?;
    let changed = replay(&log.path, &judged.scan, &mut tasks)?.len();
    Ok(Found {
        tasks,
        changed,
        judged,
        bytes,
    })
}

/// The error of a start that would lose acknowledged changes: the problem (with its
/// offset), per task the version that can be restored, and the way forward.
fn refusal(shared: &Shared, log: &Log, problem: &str, found: &Found) -> StoreError {
    let versions = found.versions();
    let mut list: Vec<String> = versions
        .iter()
        .take(20)
        .map(|(id, v)| format!("{id:?} at version {v}"))
        .collect();
    if versions.len() > 20 {
        list.push(format!("and {} more", versions.len() - 20));
    }
    let list = match list.is_empty() {
        true => "no tasks".to_string(),
        false => list.join(", "),
    };
    err(
        &log.path,
        format!(
            "{problem}. Starting would lose acknowledged changes, so the server does not start. What can be restored: {list}. `tamrm repair --data-dir {}` shows what would be lost; with --accept-loss it cuts the log to what is valid",
            shared.root.display()
        ),
    )
}

/// Loads every task: snapshots, then the log replayed over them. The log is kept (its
/// torn last group, if any, cut off and the cut synced), and appended to from its end;
/// its header is rewritten as open (and synced) before anything is appended. A log that
/// lost acknowledged changes, or is damaged in the middle, is refused ([`judge`]).
pub(super) fn load(shared: &Shared, log: &mut Log) -> Result<Vec<StoredTask>, StoreError> {
    let found = inspect(shared, log)?;
    if let Some(problem) = &found.judged.refusal {
        return Err(refusal(shared, log, problem, &found));
    }
    let scan = &found.judged.scan;
    let records: usize = scan.groups.iter().map(|g| g.records.len()).sum();
    if records > 0 {
        tracing::info!(log = %log.path.display(), groups = scan.groups.len(), records, tasks_changed = found.changed, "replayed the commit log");
    }
    let end = found.judged.valid_end;
    if let Some((offset, len, why)) = &found.judged.torn {
        tracing::warn!(log = %log.path.display(), offset, bytes = len, problem = %why, "dropping the incomplete last group of the commit log");
    }
    if found.judged.v1 {
        migrate_v1(shared, log, &found.bytes[..end as usize])?;
    } else {
        cut(shared, log, end)?;
    }
    let Found { tasks, judged, .. } = found;
    {
        let mut entries = shared.tasks.lock();
        entries.clear();
        for t in &tasks {
            entries.insert(
                t.task.id.clone(),
                Entry::restored(
                    t.dir.clone(),
                    (t.snap.0, t.snap.1, t.listed.clone()),
                    Arc::new(t.task.pool.clone()),
                    t.task.counters,
                    t.ends.clone(),
                    t.ends_changed,
                ),
            );
        }
    }
    log.in_log = judged
        .scan
        .groups
        .iter()
        .flat_map(|g| g.records.iter().map(|r| r.task().to_string()))
        .collect();
    log.compact_at = shared.log_limit.max(HEADER_LEN + 1);
    log.failed = None;
    log.stopped = false;
    log.loaded = true;
    Ok(tasks.into_iter().map(|t| t.task).collect())
}

/// Cuts the log at `end` (at least its header) and marks it open, synced, unless it is
/// that already: what follows is appended after `end`, and every group before it is
/// durable (groups written without a sync of their own included).
pub(super) fn cut(shared: &Shared, log: &mut Log, end: u64) -> Result<(), StoreError> {
    let end = end.max(HEADER_LEN);
    let want = open_header(log.dir_id, end).encode();
    let mut head = vec![0u8; want.len()];
    let same = log.len == end && log.file.read_exact_at(&mut head, 0).is_ok() && head == want;
    if !same {
        shared.stats.syncs.add();
        log.file
            .set_len(end)
            .and_then(|()| log.file.write_all_at(&want, 0))
            .and_then(|()| log.file.sync_all())
            .map_err(|e| err(&log.path, format!("cut at offset {end} and mark open: {e}")))?;
    }
    log.len = end;
    Ok(())
}

/// Rewrites a format-1 log (data dir format 3) with the format-2 header: the header,
/// then its valid groups, written atomically.
pub(super) fn migrate_v1(shared: &Shared, log: &mut Log, valid: &[u8]) -> Result<(), StoreError> {
    let groups = valid.get(HEADER_V1_LEN as usize..).unwrap_or(&[]);
    let mut bytes = open_header(log.dir_id, HEADER_LEN + groups.len() as u64).encode();
    bytes.extend_from_slice(groups);
    write_atomic(&log.path, &bytes, &shared.stats.syncs)?;
    log.file = fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&log.path)
        .map_err(|e| err(&log.path, format!("open: {e}")))?;
    log.len = bytes.len() as u64;
    tracing::info!(log = %log.path.display(), "rewrote the commit log with a header recording the data dir, its acknowledged end and how the server stopped (log format 2)");
    Ok(())
}
