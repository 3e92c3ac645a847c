//! A task's snapshot: `pool.json` and one file per trajectory, the format-1 layout, and
//! `ends.json` (SPEC §9's record of ended episodes). The commit log's changes are folded
//! into it at compaction, at graceful shutdown and after recovery; `pool.json` is the
//! pool's commit point.

use std::collections::HashSet;
use std::fs;
use std::path::Path;

use super::codec::{check_format, encode_trajectory, ClientEnds, EndsFile, PoolFile, FILE_FORMAT};
use super::files::{err, fsync_dir, read_json, traj_path, write_atomic, write_new, Syncs};
use crate::core::Pool;
use crate::store::{Counters, EndedEpisodes, StoreError};

/// Writes `pool.json` atomically.
pub(super) fn write_pool_file(
    dir: &Path,
    pool: &Pool,
    counters: Counters,
    syncs: &Syncs,
) -> Result<(), StoreError> {
    let path = dir.join("pool.json");
    let bytes =
        serde_json::to_vec_pretty(&PoolFile::new(pool, counters)).map_err(|e| err(&path, e))?;
    write_atomic(&path, &bytes, syncs)
}

/// Makes `pool` (with `counters`) the task's snapshot, given the seqs the current
/// `pool.json` lists: writes the trajectories it lacks (not referenced yet, so written in
/// place: a crash leaves only unlisted files, removed at the next start), fsyncs `traj/`,
/// replaces `pool.json` (the commit point), then removes the files of trajectories that
/// left (best effort). Returns the seqs the snapshot now lists.
pub(super) fn write_snapshot(
    dir: &Path,
    pool: &Pool,
    counters: Counters,
    listed: &[u64],
    syncs: &Syncs,
) -> Result<Vec<u64>, StoreError> {
    let old: HashSet<u64> = listed.iter().copied().collect();
    let new: HashSet<u64> = pool.seqs().iter().copied().collect();
    let mut wrote = false;
    for t in pool.trajectories().iter().filter(|t| !old.contains(&t.seq)) {
        write_new(&traj_path(dir, t.seq), &encode_trajectory(t), syncs)?;
        wrote = true;
    }
    if wrote {
        fsync_dir(&dir.join("traj"), syncs)?;
    }
    write_pool_file(dir, pool, counters, syncs)?;
    for seq in old.difference(&new) {
        let path = traj_path(dir, *seq);
        if let Err(e) = fs::remove_file(&path) {
            tracing::warn!(file = %path.display(), error = %e, "could not remove a superseded trajectory file; it is removed at the next start");
        }
    }
    Ok(pool.seqs().to_vec())
}

const ENDS_FILE: &str = "ends.json";

/// Writes `ends.json` atomically.
pub(super) fn write_ends_file(
    dir: &Path,
    ends: &EndedEpisodes,
    syncs: &Syncs,
) -> Result<(), StoreError> {
    let path = dir.join(ENDS_FILE);
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
    let bytes = serde_json::to_vec(&file).map_err(|e| err(&path, e))?;
    write_atomic(&path, &bytes, syncs)
}

/// Reads `ends.json`; none recorded if it does not exist.
pub(super) fn read_ends_file(dir: &Path) -> Result<EndedEpisodes, StoreError> {
    let path = dir.join(ENDS_FILE);
    let mut ends = EndedEpisodes::default();
    if !path.exists() {
        return Ok(ends);
    }
    let file: EndsFile = read_json(&path)?;
    check_format(file.format).map_err(|m| err(&path, m))?;
    for c in file.clients {
        ends.merge(&c.client, c.episodes_ended);
    }
    Ok(ends)
}
