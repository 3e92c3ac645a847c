//! What the store holds of each task in memory: its latest committed pool and counters,
//! what its snapshot on disk holds, and so what the snapshot lacks ([`DirtyParts`]).

use std::path::PathBuf;
use std::sync::Arc;

use super::snapshot::{write_ends_file, write_snapshot};
use super::writer::ClientEnds;
use super::Shared;
use crate::core::Pool;
use crate::store::{Counters, EndedEpisodes, StoreError};

/// A task the store holds: its directory, its latest committed pool and counters, and
/// what its snapshot on disk holds.
#[derive(Debug, Clone)]
pub(super) struct Entry {
    pub(super) dir: PathBuf,
    pub(super) pool: Arc<Pool>,
    pub(super) counters: Counters,
    /// The pool version of the snapshot (`pool.json`).
    pub(super) snap_version: u64,
    /// The counters `pool.json` holds.
    pub(super) snap_counters: Counters,
    /// The seqs `pool.json` lists (their trajectory files exist).
    pub(super) snap_seqs: Vec<u64>,
    /// The episode ends committed per client (SPEC §9): `ends.json` and the log's
    /// kind-2 records, so that a restarted server does not commit a re-sent end again.
    pub(super) ends: EndedEpisodes,
    /// Merges into `ends` so far, and how many of them `ends.json` holds.
    pub(super) ends_gen: u64,
    pub(super) ends_saved: u64,
}

impl Entry {
    /// A task whose snapshot is `pool` and `ends`.
    pub(super) fn new(
        dir: PathBuf,
        pool: Arc<Pool>,
        counters: Counters,
        snap_seqs: Vec<u64>,
        ends: EndedEpisodes,
    ) -> Entry {
        Entry {
            dir,
            snap_version: pool.version(),
            snap_counters: counters,
            pool,
            counters,
            snap_seqs,
            ends,
            ends_gen: 0,
            ends_saved: 0,
        }
    }

    /// The log holds changes its snapshot lacks.
    pub(super) fn is_dirty(&self) -> bool {
        self.pool.version() != self.snap_version || self.ends_gen != self.ends_saved
    }

    /// Records episode ends, per client (env, episodes ended).
    pub(super) fn merge_ends(&mut self, ends: &ClientEnds) {
        for (client, counts) in ends {
            self.ends.merge(client, counts.iter().copied());
        }
        if !ends.is_empty() {
            self.ends_gen += 1;
        }
    }

    /// What its snapshot lacks.
    pub(super) fn dirty_parts(&self) -> DirtyParts {
        DirtyParts {
            dir: self.dir.clone(),
            pool: (self.pool.version() != self.snap_version)
                .then(|| (self.pool.clone(), self.counters, self.snap_seqs.clone())),
            ends: (self.ends_gen != self.ends_saved).then(|| (self.ends.clone(), self.ends_gen)),
        }
    }

    pub(super) fn snapshot_written(&mut self, version: u64, seqs: Vec<u64>, counters: Counters) {
        self.snap_version = version;
        self.snap_counters = counters;
        self.snap_seqs = seqs;
    }
}

/// What one task's snapshot lacks: its pool (newer than `pool.json`: the pool, counters
/// and the seqs `pool.json` lists) and its ended episodes (newer than `ends.json`).
pub(super) struct DirtyParts {
    pub(super) dir: PathBuf,
    pub(super) pool: Option<(Arc<Pool>, Counters, Vec<u64>)>,
    pub(super) ends: Option<(EndedEpisodes, u64)>,
}

impl DirtyParts {
    /// Writes them, and notes in the task's entry what its snapshot now holds.
    pub(super) fn write(self, shared: &Shared, id: &str) -> Result<(), StoreError> {
        let syncs = &shared.stats.syncs;
        if let Some((pool, counters, listed)) = self.pool {
            let seqs = write_snapshot(&self.dir, &pool, counters, &listed, syncs)?;
            if let Some(e) = shared.tasks.lock().get_mut(id) {
                e.snapshot_written(pool.version(), seqs, counters);
            }
        }
        if let Some((ends, generation)) = self.ends {
            write_ends_file(&self.dir, &ends, syncs)?;
            if let Some(e) = shared.tasks.lock().get_mut(id) {
                e.ends_saved = generation;
            }
        }
        Ok(())
    }
}
