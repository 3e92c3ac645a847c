//! The bytes of the commit log `DATA_DIR/commits.log` (`docs/storage.md`): a header, then
//! groups, each one `write` + one `fdatasync` of the group-commit writer, holding the
//! records of the pool changes it acknowledged together. Pure: no I/O.
//!
//! ```text
//! header  "TAMRMLOG" | format u32 | … (header.rs)
//! group   "TGRP" | payload length n u32 | record count u32 | n bytes of records | CRC-32 u32
//! record  kind u8 (1) | id length u32 | id | base version u64 | version u64 | next_seq u64
//!         | episodes_completed u64 | steps_shaped u64 | k u32 | k seqs u64 (the pool after)
//!         | m u32 | m × (length u32 | a trajectory file's bytes)   (the trajectories added)
//! record  kind u8 (2) | id length u32 | id | client length u32 | client
//!         | n u32 | n × (env u32 | episodes ended u64)   (SPEC §9's record of ended episodes)
//! record  kind u8 (3) | id length u32 | id | version u64 | episodes_completed u64
//!         | steps_shaped u64   (a task's counters at a graceful stop, at pool version)
//! ```
//!
//! A kind-2 record goes with the kind-1 record of the change that ended those episodes,
//! in the same group (logs written before it existed hold only kind 1). Kind 3 exists
//! since data dir format 3: a graceful stop logs the counters counted since the last
//! change instead of writing snapshots.
//!
//! The CRC of a group covers its magic, lengths and records. A group is the unit of
//! atomicity: the writer writes the next group only after the previous one is synced, so
//! after a crash only the last group can be incomplete.

use super::codec::encode_trajectory;
use crate::core::Pool;
use crate::store::Counters;

const GROUP_MAGIC: &[u8; 4] = b"TGRP";
/// magic, payload length, record count.
const GROUP_HEAD: usize = 12;
const KIND_COMMIT: u8 = 1;
const KIND_ENDS: u8 = 2;
const KIND_COUNTERS: u8 = 3;

/// One record of the log.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Record {
    /// A pool change.
    Commit(Commit),
    /// Episode ends committed by a client.
    Ends(Ends),
    /// A task's counters, logged at a graceful stop.
    Counters(CountersAt),
}

impl Record {
    /// The task the record is about.
    pub fn task(&self) -> &str {
        match self {
            Record::Commit(c) => &c.task,
            Record::Ends(e) => &e.task,
            Record::Counters(c) => &c.task,
        }
    }
}

/// The episode ends of one client that a change committed (or discarded), as counts per
/// env: the no-double-commit record of SPEC §9, so that it survives a restart.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Ends {
    pub task: String,
    pub client: String,
    /// (env, episodes ended).
    pub counts: Vec<(u32, u64)>,
}

/// Encodes a record of `client`'s ended episodes on `task`.
pub(super) fn encode_ends(task: &str, client: &str, counts: &[(u32, u64)]) -> Vec<u8> {
    let mut b = Vec::with_capacity(16 + task.len() + client.len() + 12 * counts.len());
    b.push(KIND_ENDS);
    put_bytes(&mut b, task.as_bytes());
    put_bytes(&mut b, client.as_bytes());
    put_len(&mut b, counts.len());
    for &(env, count) in counts {
        b.extend_from_slice(&env.to_le_bytes());
        b.extend_from_slice(&count.to_le_bytes());
    }
    b
}

/// A task's counters (which only grow) when its pool was at `version`.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct CountersAt {
    pub task: String,
    pub version: u64,
    pub counters: Counters,
}

/// Encodes a record of `task`'s counters at pool version `version`.
pub(super) fn encode_counters(task: &str, version: u64, counters: Counters) -> Vec<u8> {
    let mut b = Vec::with_capacity(29 + task.len());
    b.push(KIND_COUNTERS);
    put_bytes(&mut b, task.as_bytes());
    for v in [version, counters.episodes_completed, counters.steps_shaped] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b
}

/// One pool change as it is logged: the pool after the change, given as the seqs it
/// holds, the trajectories new since `base_version`, and the counters.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Commit {
    pub task: String,
    pub base_version: u64,
    pub version: u64,
    pub next_seq: u64,
    pub counters: Counters,
    pub seqs: Vec<u64>,
    /// Encoded trajectory files (checked against the task config at replay).
    pub added: Vec<Vec<u8>>,
}

/// Encodes the record of the change from `base` to `after`.
pub(super) fn encode_commit(task: &str, base: &Pool, after: &Pool, counters: Counters) -> Vec<u8> {
    // Both pools hold their trajectories by seq: one merge finds the new ones.
    let old = base.seqs();
    let mut j = 0;
    let added: Vec<Vec<u8>> = after
        .trajectories()
        .iter()
        .filter(|t| {
            j += old[j..].partition_point(|&s| s < t.seq);
            old.get(j) != Some(&t.seq)
        })
        .map(|t| encode_trajectory(t))
        .collect();
    let mut b = Vec::with_capacity(64 + task.len() + 8 * after.len());
    b.push(KIND_COMMIT);
    put_bytes(&mut b, task.as_bytes());
    for v in [
        base.version(),
        after.version(),
        after.next_seq(),
        counters.episodes_completed,
        counters.steps_shaped,
    ] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    put_len(&mut b, after.len());
    after
        .seqs()
        .iter()
        .for_each(|s| b.extend_from_slice(&s.to_le_bytes()));
    put_len(&mut b, added.len());
    added.iter().for_each(|t| put_bytes(&mut b, t));
    b
}

fn put_len(b: &mut Vec<u8>, n: usize) {
    // Lengths are bounded by the server's limits (message size, pool capacity), far
    // below 4 GiB; saturate rather than wrap, which would fail the decode loudly.
    b.extend_from_slice(&u32::try_from(n).unwrap_or(u32::MAX).to_le_bytes());
}

fn put_bytes(b: &mut Vec<u8>, bytes: &[u8]) {
    put_len(b, bytes.len());
    b.extend_from_slice(bytes);
}

/// One group's bytes: its records (already encoded) framed and checksummed.
pub(super) fn encode_group(records: &[&[u8]]) -> Vec<u8> {
    let n: usize = records.iter().map(|r| r.len()).sum();
    let mut b = Vec::with_capacity(GROUP_HEAD + n + 4);
    b.extend_from_slice(GROUP_MAGIC);
    put_len(&mut b, n);
    put_len(&mut b, records.len());
    records.iter().for_each(|r| b.extend_from_slice(r));
    let crc = crc32fast::hash(&b);
    b.extend_from_slice(&crc.to_le_bytes());
    b
}

/// A checked reader over bytes read from disk: every read is bounds-checked.
struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.b.len())
            .ok_or_else(|| format!("a record ends early (needs {n} bytes at {})", self.pos))?;
        let s = &self.b[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, String> {
        Ok(self.take(1)?[0])
    }
    fn u32(&mut self) -> Result<u32, String> {
        let mut a = [0u8; 4];
        a.copy_from_slice(self.take(4)?);
        Ok(u32::from_le_bytes(a))
    }
    fn u64(&mut self) -> Result<u64, String> {
        let mut a = [0u8; 8];
        a.copy_from_slice(self.take(8)?);
        Ok(u64::from_le_bytes(a))
    }
    fn len(&mut self) -> Result<usize, String> {
        usize::try_from(self.u32()?).map_err(|_| "a length overflows".to_string())
    }
    fn bytes(&mut self) -> Result<&'a [u8], String> {
        let n = self.len()?;
        self.take(n)
    }
}

fn decode_record(r: &mut Reader) -> Result<Record, String> {
    match r.u8()? {
        KIND_COMMIT => decode_commit(r).map(Record::Commit),
        KIND_ENDS => decode_ends(r).map(Record::Ends),
        KIND_COUNTERS => decode_counters(r).map(Record::Counters),
        kind => Err(format!(
            "unknown record kind {kind} (written by a newer tamrm?)"
        )),
    }
}

fn decode_counters(r: &mut Reader) -> Result<CountersAt, String> {
    let task = String::from_utf8(r.bytes()?.to_vec()).map_err(|_| "a task id is not UTF-8")?;
    Ok(CountersAt {
        task,
        version: r.u64()?,
        counters: Counters {
            episodes_completed: r.u64()?,
            steps_shaped: r.u64()?,
        },
    })
}

fn decode_ends(r: &mut Reader) -> Result<Ends, String> {
    let task = String::from_utf8(r.bytes()?.to_vec()).map_err(|_| "a task id is not UTF-8")?;
    let client = String::from_utf8(r.bytes()?.to_vec()).map_err(|_| "a client id is not UTF-8")?;
    let n = r.len()?;
    let mut counts = Vec::with_capacity(n.min(r.b.len() / 12));
    for _ in 0..n {
        counts.push((r.u32()?, r.u64()?));
    }
    Ok(Ends {
        task,
        client,
        counts,
    })
}

fn decode_commit(r: &mut Reader) -> Result<Commit, String> {
    let task = String::from_utf8(r.bytes()?.to_vec()).map_err(|_| "a task id is not UTF-8")?;
    let (base_version, version, next_seq) = (r.u64()?, r.u64()?, r.u64()?);
    let counters = Counters {
        episodes_completed: r.u64()?,
        steps_shaped: r.u64()?,
    };
    let k = r.len()?;
    // Bounded by the bytes present, so a bad count cannot allocate much.
    let mut seqs = Vec::with_capacity(k.min(r.b.len() / 8));
    for _ in 0..k {
        seqs.push(r.u64()?);
    }
    let m = r.len()?;
    let mut added = Vec::with_capacity(m.min(r.b.len() / 4));
    for _ in 0..m {
        added.push(r.bytes()?.to_vec());
    }
    if version <= base_version {
        return Err(format!(
            "task {task:?}: version {version} does not follow base version {base_version}"
        ));
    }
    Ok(Commit {
        task,
        base_version,
        version,
        next_seq,
        counters,
        seqs,
        added,
    })
}

/// The group starting at `off`, if a complete one with a valid checksum is there:
/// its records' bytes and record count, and the offset after it.
fn group_at(b: &[u8], off: usize) -> Result<(&[u8], usize, usize), String> {
    let rest = b.get(off..).unwrap_or(&[]);
    if rest.len() < GROUP_HEAD + 4 {
        return Err(format!(
            "{} bytes, a group has at least {}",
            rest.len(),
            GROUP_HEAD + 4
        ));
    }
    if &rest[..4] != GROUP_MAGIC {
        return Err("no group magic".into());
    }
    let mut r = Reader { b: rest, pos: 4 };
    let (n, count) = (r.len()?, r.len()?);
    let end = n
        .checked_add(GROUP_HEAD)
        .filter(|&e| e.checked_add(4).is_some_and(|t| t <= rest.len()))
        .ok_or_else(|| format!("incomplete: the group needs {n} bytes of records"))?;
    let mut crc = [0u8; 4];
    crc.copy_from_slice(&rest[end..end + 4]);
    if crc32fast::hash(&rest[..end]) != u32::from_le_bytes(crc) {
        return Err("checksum mismatch".into());
    }
    Ok((&rest[GROUP_HEAD..end], count, off + end + 4))
}

/// A group read back: where it starts and its records.
#[derive(Debug)]
pub(super) struct Group {
    pub offset: u64,
    pub records: Vec<Record>,
}

/// Where a log stops being valid: the offset of the first group that fails its checks,
/// why, and the valid groups found after it (none: the damage is the log's tail).
#[derive(Debug)]
pub(super) struct Damage {
    pub offset: u64,
    pub why: String,
    /// The group has a valid checksum but its records do not decode: never a torn write.
    pub undecodable: bool,
    /// The valid groups after the damage, up to the next damage (their changes are lost
    /// if the log is cut at `offset`).
    pub later: Vec<Group>,
}

/// What a log holds: its valid groups from the header on and, if it has one, where that
/// stops ([`Damage`]). Whether the damage is a torn last write (never acknowledged) or
/// the loss of acknowledged changes is decided by the caller, from the header.
#[derive(Debug)]
pub(super) struct Scan {
    pub groups: Vec<Group>,
    pub damage: Option<Damage>,
}

/// The group at `off` decoded, and the offset after it; or why not, and whether its
/// checksum was valid (then its records are what fails).
fn read_group(b: &[u8], off: usize) -> Result<(Group, usize), (String, bool)> {
    let (payload, count, next) = group_at(b, off).map_err(|why| (why, false))?;
    let mut r = Reader { b: payload, pos: 0 };
    let mut records = Vec::with_capacity(count.min(payload.len()));
    for i in 0..count {
        records.push(decode_record(&mut r).map_err(|m| (format!("record {i}: {m}"), true))?);
    }
    if r.pos != payload.len() {
        let m = format!("{} bytes after its {count} records", payload.len() - r.pos);
        return Err((m, true));
    }
    let group = Group {
        offset: off as u64,
        records,
    };
    Ok((group, next))
}

/// Reads a whole log whose groups start at `start` (after its header).
pub(super) fn scan(b: &[u8], start: usize) -> Scan {
    let mut off = start;
    let mut groups = Vec::new();
    while off < b.len() {
        match read_group(b, off) {
            Ok((g, next)) => {
                groups.push(g);
                off = next;
            }
            Err((why, undecodable)) => {
                let mut later = Vec::new();
                if let Some(mut p) = (off + 1..b.len()).find(|&p| group_at(b, p).is_ok()) {
                    while let Ok((g, next)) = read_group(b, p) {
                        later.push(g);
                        p = next;
                    }
                }
                let damage = Damage {
                    offset: off as u64,
                    why,
                    undecodable,
                    later,
                };
                return Scan {
                    groups,
                    damage: Some(damage),
                };
            }
        }
    }
    Scan {
        groups,
        damage: None,
    }
}

#[cfg(test)]
mod tests;
