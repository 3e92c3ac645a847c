//! A task's snapshot: `pool.json` and one file per trajectory, the format-1 layout, and
//! `ends.json` (SPEC §9's record of ended episodes). The commit log's changes are folded
//! into it at compaction, at graceful shutdown and after recovery, for every task that
//! lacks them in one batch of syncs; `pool.json` is the pool's commit point.

use std::collections::HashSet;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use super::codec::{check_format, encode_trajectory, ClientEnds, EndsFile, PoolFile, FILE_FORMAT};
use super::files::{err, fsync_many, tmp_path, traj_path, write_atomic, write_unsynced, Syncs};
use super::sealed::{read_own, seal};
use crate::core::Pool;
use crate::store::{Counters, EndedEpisodes, StoreError};

/// Writes `pool.json` atomically.
pub(super) fn write_pool_file(
    dir: &Path,
    pool: &Pool,
    counters: Counters,
    dir_id: &str,
    syncs: &Syncs,
) -> Result<(), StoreError> {
    let path = dir.join("pool.json");
    let bytes = seal(&path, &PoolFile::new(pool, counters), Some(dir_id))?;
    write_atomic(&path, &bytes, syncs)
}

/// One task's part of a batch of snapshots ([`write_snapshots`]): its directory, the pool
/// to snapshot (with its counters and the seqs the current `pool.json` lists), and the
/// ended episodes to write to `ends.json`.
pub(super) struct SnapshotJob<'a> {
    pub dir: &'a Path,
    pub pool: Option<(&'a Pool, Counters, &'a [u64])>,
    pub ends: Option<&'a EndedEpisodes>,
}

/// Makes each job's pool (with its counters) and ended episodes its task's snapshot, with
/// the syncs of all of them batched: writes every trajectory file a `pool.json` lacks
/// (not referenced yet, so written in place: a crash leaves only unlisted files, removed
/// at the next start), fsyncs them and their `traj/` directories together, writes every
/// `pool.json.tmp` and `ends.json.tmp`, fsyncs them together, renames them over
/// `pool.json` and `ends.json` (each rename a task's commit point) and fsyncs the task
/// directories together; then removes the files of trajectories that left (best effort).
/// Returns, per job, the seqs its `pool.json` now lists (`None` for a job without pool).
///
/// Abandoned, with an error, once `stop` is set, at any point before the renames: what
/// it wrote by then is unlisted, so the next start removes it.
pub(super) fn write_snapshots(
    jobs: &[SnapshotJob<'_>],
    dir_id: &str,
    syncs: &Syncs,
    stop: &AtomicBool,
) -> Result<Vec<Option<Vec<u64>>>, StoreError> {
    let check = |dir: &Path| match stop.load(Ordering::Acquire) {
        true => Err(err(dir, ABANDONED)),
        false => Ok(()),
    };
    let mut files = Vec::new();
    let mut traj_dirs = Vec::new();
    for (dir, pool, listed) in jobs
        .iter()
        .filter_map(|j| j.pool.map(|(p, _, l)| (j.dir, p, l)))
    {
        let old: HashSet<u64> = listed.iter().copied().collect();
        let before = files.len();
        for t in pool.trajectories().iter().filter(|t| !old.contains(&t.seq)) {
            check(dir)?;
            let path = traj_path(dir, t.seq);
            write_unsynced(&path, &encode_trajectory(t))?;
            files.push(path);
        }
        if files.len() > before {
            traj_dirs.push(dir.join("traj"));
        }
    }
    fsync_many(&files, syncs)?;
    fsync_many(&traj_dirs, syncs)?;
    if let Some(j) = jobs.first() {
        check(j.dir)?;
    }
    let mut renames = Vec::new();
    for j in jobs {
        if let Some((pool, counters, _)) = j.pool {
            let path = j.dir.join("pool.json");
            let bytes = seal(&path, &PoolFile::new(pool, counters), Some(dir_id))?;
            renames.push((path, bytes));
        }
        if let Some(ends) = j.ends {
            let path = j.dir.join(ENDS_FILE);
            let bytes = ends_bytes(&path, ends, dir_id)?;
            renames.push((path, bytes));
        }
    }
    let tmps: Vec<PathBuf> = renames
        .iter()
        .map(|(path, bytes)| {
            let tmp = tmp_path(path);
            write_unsynced(&tmp, bytes).map(|()| tmp)
        })
        .collect::<Result<_, _>>()?;
    fsync_many(&tmps, syncs)?;
    for (tmp, (path, _)) in tmps.iter().zip(&renames) {
        fs::rename(tmp, path).map_err(|e| err(path, format!("write: {e}")))?;
    }
    let task_dirs: Vec<PathBuf> = jobs
        .iter()
        .filter(|j| j.pool.is_some() || j.ends.is_some())
        .map(|j| j.dir.to_path_buf())
        .collect();
    fsync_many(&task_dirs, syncs)?;
    let mut out = Vec::with_capacity(jobs.len());
    for j in jobs {
        let Some((pool, _, listed)) = j.pool else {
            out.push(None);
            continue;
        };
        let new: HashSet<u64> = pool.seqs().iter().copied().collect();
        for seq in listed.iter().filter(|s| !new.contains(s)) {
            let path = traj_path(j.dir, *seq);
            if let Err(e) = fs::remove_file(&path) {
                tracing::warn!(file = %path.display(), error = %e, "could not remove a superseded trajectory file; it is removed at the next start");
            }
        }
        out.push(Some(pool.seqs().to_vec()));
    }
    Ok(out)
}

const ENDS_FILE: &str = "ends.json";

/// The error of a batch of snapshots abandoned because the server is stopping.
pub(super) const ABANDONED: &str =
    "snapshots abandoned: the server is stopping (the commit log keeps every change)";

/// The bytes of `ends.json` (at `path`) holding `ends`.
fn ends_bytes(path: &Path, ends: &EndedEpisodes, dir_id: &str) -> Result<Vec<u8>, StoreError> {
    let file = EndsFile {
        format: FILE_FORMAT,
        clients: ends
            .all()
            .map(|(client, episodes_ended)| ClientEnds {
                client: client.to_string(),
                episodes_ended,
            })
            .collect(),
    };
    seal(path, &file, Some(dir_id))
}

/// Reads `ends.json`; none recorded if it does not exist.
pub(super) fn read_ends_file(dir: &Path, dir_id: &str) -> Result<EndedEpisodes, StoreError> {
    let path = dir.join(ENDS_FILE);
    let mut ends = EndedEpisodes::default();
    if !path.exists() {
        return Ok(ends);
    }
    let file: EndsFile = read_own(&path, dir_id)?;
    check_format(file.format).map_err(|m| err(&path, m))?;
    for c in file.clients {
        ends.merge(&c.client, c.episodes_ended);
    }
    Ok(ends)
}
