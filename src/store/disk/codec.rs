//! The bytes of the on-disk format (version [`FORMAT_VERSION`], `docs/storage.md`): the
//! JSON files' shapes and the binary, CRC-32 protected trajectory file. Pure: no I/O.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::files::traj_path;
use crate::core::{ActionCount, ActionSeq, Pool, TaskConfig, Trajectory};
use crate::store::Counters;

/// Version of the data dir's layout, in `DATA_DIR/tamrm.json`: 2 since pool changes go
/// to the commit log (`commits.log`), 3 since a graceful stop logs counters (kind-3
/// records) and leaves the log to the next start instead of writing snapshots. Older
/// dirs are migrated at open: a format-1 dir is a format-3 dir with an empty log, a
/// format-2 dir one whose log has no kind-3 records. 4 since the log's header records
/// the data dir's id, where the log's acknowledged part ends and whether the server
/// stopped cleanly, and the JSON files are sealed with a checksum (`sealed.rs`); a
/// format-3 dir's log is rewritten with that header at its first start.
pub const FORMAT_VERSION: u32 = 4;
/// The first data dir format, still opened (and migrated).
pub(super) const FORMAT_V1: u32 = 1;
/// The second data dir format, still opened (and migrated).
pub(super) const FORMAT_V2: u32 = 2;
/// The third data dir format, still opened (and migrated).
pub(super) const FORMAT_V3: u32 = 3;
/// Version of `task.json`, `pool.json` and the trajectory files (unchanged by format 2).
pub(super) const FILE_FORMAT: u32 = 1;

const TRAJ_MAGIC: &[u8; 8] = b"TAMRMTRJ";
/// magic, format, kind, dim, seq, score, length.
const HEADER: usize = 8 + 4 + 4 + 4 + 8 + 8 + 8;

/// `DATA_DIR/tamrm.json`.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RootFile {
    pub format: u32,
}

/// `tasks/<name>/task.json`.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct TaskFile {
    pub format: u32,
    pub task_id: String,
    pub config: TaskConfig,
}

/// `tasks/<name>/pool.json`, the commit point of a task's pool.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct PoolFile {
    pub format: u32,
    pub pool_version: u64,
    pub next_seq: u64,
    pub seqs: Vec<u64>,
    pub episodes_completed: u64,
    pub steps_shaped: u64,
}

impl PoolFile {
    pub fn new(pool: &Pool, counters: Counters) -> PoolFile {
        PoolFile {
            format: FILE_FORMAT,
            pool_version: pool.version(),
            next_seq: pool.next_seq(),
            seqs: pool.seqs().to_vec(),
            episodes_completed: counters.episodes_completed,
            steps_shaped: counters.steps_shaped,
        }
    }

    pub fn counters(&self) -> Counters {
        Counters {
            episodes_completed: self.episodes_completed,
            steps_shaped: self.steps_shaped,
        }
    }
}

/// `tasks/<name>/ends.json`: the episode ends committed per client (SPEC §9), as of the
/// last snapshot (the log's kind-2 records add to it). Absent: none (older data dirs).
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct EndsFile {
    pub format: u32,
    pub clients: Vec<ClientEnds>,
}

/// One client's ended episodes in `ends.json`.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct ClientEnds {
    pub client: String,
    /// (env, episodes ended).
    pub episodes_ended: Vec<(u32, u64)>,
}

/// The format a task, pool or trajectory file declares is the one this build reads.
pub(super) fn check_format(format: u32) -> Result<(), String> {
    if format != FILE_FORMAT {
        return Err(format!(
            "on-disk format {format} is not supported by this build (format {FILE_FORMAT})"
        ));
    }
    Ok(())
}

/// The data dir format in `tamrm.json` is one this build opens (the current one, or an
/// older one, which it migrates).
pub(super) fn check_root_format(format: u32) -> Result<(), String> {
    if ![FORMAT_V1, FORMAT_V2, FORMAT_V3, FORMAT_VERSION].contains(&format) {
        return Err(format!(
            "on-disk format {format} is not supported by this build (format {FORMAT_VERSION}, and {FORMAT_V1} to {FORMAT_V3} which it migrates)"
        ));
    }
    Ok(())
}

/// Binary trajectory file: magic, format, kind, dim, seq, score, length, payload, CRC-32
/// of everything before it; all little-endian.
pub(in crate::store) fn encode_trajectory(t: &Trajectory) -> Vec<u8> {
    let (kind, dim, len) = match &t.actions {
        ActionSeq::Discrete(v) => (0u32, 0u32, v.len()),
        ActionSeq::Continuous { dim, data } => (1, *dim as u32, data.len() / dim),
    };
    let mut b = Vec::with_capacity(HEADER + 4 + len * 4 * (dim.max(1) as usize));
    b.extend_from_slice(TRAJ_MAGIC);
    b.extend_from_slice(&FILE_FORMAT.to_le_bytes());
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

fn u32s(payload: &[u8]) -> Vec<u32> {
    payload
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Decodes and checks a trajectory file read from `path` for a task with `config`: the
/// checks of [`decode_trajectory_bytes`] and the seq against the file name.
pub(super) fn decode_trajectory(
    path: &Path,
    b: &[u8],
    config: &TaskConfig,
) -> Result<Trajectory, String> {
    let t = decode_trajectory_bytes(b, config)?;
    if path.file_name() != traj_path(Path::new(""), t.seq).file_name() {
        return Err(format!(
            "holds seq {}, which does not match its file name",
            t.seq
        ));
    }
    Ok(t)
}

/// Decodes and checks a trajectory file's bytes (from a file or the commit log) for a
/// task with `config`: length, magic, checksum, format, the payload size, and the actions
/// against the action space (the validator every request uses).
pub(in crate::store) fn decode_trajectory_bytes(
    b: &[u8],
    config: &TaskConfig,
) -> Result<Trajectory, String> {
    if b.len() < HEADER + 4 {
        return Err(format!(
            "truncated: {} bytes, a trajectory file has at least {}",
            b.len(),
            HEADER + 4
        ));
    }
    let (body, crc) = b.split_at(b.len() - 4);
    let stored_crc = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
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
    check_format(u32_at(8))?;
    let (kind, dim) = (u32_at(12), u32_at(16) as usize);
    let seq = u64_at(20);
    let score = f64::from_bits(u64_at(28));
    let len = usize::try_from(u64_at(36)).map_err(|_| "length overflows")?;
    let payload = &body[HEADER..];
    let space = config.action_space;
    let expected_dim = space.action_dim();
    if kind != u32::from(expected_dim > 0) || dim != expected_dim {
        return Err(format!(
            "action kind {kind}/dim {dim} does not match the task config"
        ));
    }
    if Some(payload.len()) != len.checked_mul(dim.max(1)).and_then(|x| x.checked_mul(4)) {
        return Err(format!(
            "payload is {} bytes for {len} actions of dim {}",
            payload.len(),
            dim.max(1)
        ));
    }
    if len == 0 || len > config.max_trajectory_len as usize {
        return Err(format!(
            "length {len} outside 1..={}",
            config.max_trajectory_len
        ));
    }
    let (actions, vectors) = if kind == 0 {
        (u32s(payload), Vec::new())
    } else {
        (
            Vec::new(),
            u32s(payload).into_iter().map(f32::from_bits).collect(),
        )
    };
    let actions = space
        .to_seq(actions, vectors, ActionCount::AtLeastOne)
        .map_err(|e| e.to_string())?;
    Ok(Trajectory {
        actions,
        score,
        seq,
    })
}

#[cfg(test)]
mod tests;
