//! What the store holds of each task in memory: its latest committed pool and counters,
//! what its snapshot on disk holds, and so what the snapshot lacks ([`DirtyParts`]).

use std::path::PathBuf;
use std::sync::Arc;

use super::snapshot::{write_snapshots, SnapshotJob};
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
    /// The latest counters durable in the snapshot or the log (a graceful stop logs
    /// `counters` when they are newer).
    pub(super) durable_counters: Counters,
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
            durable_counters: counters,
            pool,
            counters,
            snap_seqs,
            ends,
            ends_gen: 0,
            ends_saved: 0,
        }
    }

    /// A task restored at start: its snapshot (`snap`, the seqs `pool.json` lists), then
    /// the log replayed over it (`pool`, `counters`, and `ends` with `ends_logged` when
    /// the log added to what `ends.json` holds). What the snapshot lacks stays in the
    /// log until the next compaction.
    pub(super) fn restored(
        dir: PathBuf,
        snap: (u64, Counters, Vec<u64>),
        pool: Arc<Pool>,
        counters: Counters,
        ends: EndedEpisodes,
        ends_logged: bool,
    ) -> Entry {
        let (snap_version, snap_counters, snap_seqs) = snap;
        Entry {
            dir,
            pool,
            counters,
            snap_version,
            snap_counters,
            durable_counters: counters,
            snap_seqs,
            ends,
            ends_gen: u64::from(ends_logged),
            ends_saved: 0,
        }
    }

    /// Its snapshot lacks changes: of the pool or counters, or of the ended episodes.
    pub(super) fn is_dirty(&self) -> bool {
        self.pool.version() != self.snap_version
            || self.counters != self.snap_counters
            || self.ends_gen != self.ends_saved
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
            // The counters are written when they changed, even if the pool did not.
            pool: (self.pool.version() != self.snap_version || self.counters != self.snap_counters)
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

/// Writes the parts every task of `dirty` lacks, in one batch of syncs
/// ([`write_snapshots`]), and notes in their entries what their snapshots now hold.
pub(super) fn write_dirty(
    shared: &Shared,
    dirty: &[(String, DirtyParts)],
) -> Result<(), StoreError> {
    if dirty.is_empty() {
        return Ok(());
    }
    let jobs: Vec<SnapshotJob<'_>> = dirty
        .iter()
        .map(|(_, p)| SnapshotJob {
            dir: &p.dir,
            pool: p
                .pool
                .as_ref()
                .map(|(pool, counters, listed)| (&**pool, *counters, listed.as_slice())),
            ends: p.ends.as_ref().map(|(ends, _)| ends),
        })
        .collect();
    let seqs = write_snapshots(&jobs, &shared.dir_id, &shared.stats.syncs, &shared.stopping)?;
    let mut tasks = shared.tasks.lock();
    for ((id, parts), seqs) in dirty.iter().zip(seqs) {
        let Some(e) = tasks.get_mut(id) else { continue };
        if let (Some((pool, counters, _)), Some(seqs)) = (&parts.pool, seqs) {
            e.snapshot_written(pool.version(), seqs, *counters);
        }
        if let Some((_, generation)) = parts.ends {
            e.ends_saved = generation;
        }
    }
    Ok(())
}
