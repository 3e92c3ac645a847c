//! What a start makes of the commit log it finds (docs/storage.md, "What start-up does
//! with what it finds"): the valid groups it can replay, and whether what is past them is
//! the torn last write of a crash (never acknowledged: cut off) or the loss of
//! acknowledged changes (the start refuses, and only `tamrm repair --accept-loss` cuts
//! it). The header ([`super::header`]) tells the two apart: it names the data dir, the
//! end of the acknowledged part, and whether the server stopped cleanly. Pure: no I/O.

use std::collections::BTreeMap;

use super::header::{self, Found, Header, HEADER_LEN, LOG_FORMAT_V2};
use super::log::{scan, Record, Scan};
use super::sealed::dir_id_text;

/// A commit log judged.
#[derive(Debug)]
pub(super) struct Judged {
    /// The log's header names another data dir: nothing in it is this data dir's.
    pub foreign: bool,
    /// The log has the format-1 layout (data dir format 3): rewritten with a header at
    /// this start.
    pub v1: bool,
    /// Its valid groups (none if the log belongs to another data dir) and its damage.
    pub scan: Scan,
    /// Where its valid groups end: the log is cut there (a torn tail, or by repair).
    pub valid_end: u64,
    /// Why a start must refuse, naming the offset.
    pub refusal: Option<String>,
    /// A torn last write to cut off at a start: offset, bytes, and what is known of it.
    pub torn: Option<(u64, u64, String)>,
}

/// Judges the log `b` of the data dir `dir_id`.
pub(super) fn judge(b: &[u8], dir_id: &[u8; 16]) -> Judged {
    let len = b.len() as u64;
    let (start, acked, clean, v1, mut refusal) = match header::decode(b) {
        Ok(Found::V1) => (header::HEADER_V1_LEN, None, false, true, None),
        Ok(Found::V2(h)) if &h.dir_id != dir_id => {
            let why = format!(
                "at offset 0: the log belongs to another data dir (its header names data dir {}, tamrm.json names {}): copied from elsewhere?",
                dir_id_text(&h.dir_id),
                dir_id_text(dir_id)
            );
            return Judged {
                foreign: true,
                v1: false,
                scan: Scan {
                    groups: Vec::new(),
                    damage: None,
                },
                valid_end: 0,
                refusal: Some(why),
                torn: None,
            };
        }
        Ok(Found::V2(h)) => (HEADER_LEN, Some(h.acked_end), h.clean(), false, None),
        Err(why) => {
            // The groups of a header that fails only its checksum are still read, for
            // what a repair can keep.
            let framed = b.len() >= HEADER_LEN as usize
                && b[8..12] == LOG_FORMAT_V2.to_le_bytes()
                && b.starts_with(b"TAMRMLOG");
            let start = if framed { HEADER_LEN } else { len };
            (
                start,
                None,
                false,
                false,
                Some(format!("at offset 0: {why}")),
            )
        }
    };
    let scan = scan(b, start as usize);
    let valid_end = match (&scan.damage, refusal.is_some() && start == len) {
        (_, true) => 0,
        (Some(d), _) => d.offset,
        (None, _) => len,
    };
    let mut torn = None;
    if refusal.is_none() {
        refusal = match (&scan.damage, acked) {
            (Some(d), _) if d.undecodable => Some(format!(
                "the group at offset {} has a valid checksum but does not decode ({})",
                d.offset, d.why
            )),
            (Some(d), _) if !d.later.is_empty() => Some(format!(
                "the group at offset {} is damaged ({}), and valid groups follow it from offset {}: damage in the middle of the log",
                d.offset, d.why, d.later[0].offset
            )),
            (Some(d), Some(a)) if a > d.offset => Some(format!(
                "{}the group at offset {} is damaged or cut short ({}), inside the acknowledged part of the log, which ends at offset {a}",
                stopped(clean),
                d.offset,
                d.why
            )),
            (None, Some(a)) if a > len => Some(format!(
                "{}the log ends at offset {len}, but its acknowledged part ends at offset {a}: it was cut short",
                stopped(clean)
            )),
            (_, Some(a)) if clean && len > a => Some(format!(
                "after a clean stop the log ends at offset {a}, but it is {len} bytes long: {} bytes appeared after the stop, from offset {a}",
                len - a
            )),
            (Some(d), _) => {
                let known = match acked {
                    Some(a) => format!("past the acknowledged part, which ends at offset {a}: a write interrupted by a crash, never acknowledged"),
                    None => "a format-3 log, which records no acknowledged end: taken for a write interrupted by a crash, never acknowledged".into(),
                };
                torn = Some((d.offset, len - d.offset, format!("{} ({known})", d.why)));
                None
            }
            _ => None,
        };
    }
    Judged {
        foreign: false,
        v1,
        scan,
        valid_end,
        refusal,
        torn,
    }
}

fn stopped(clean: bool) -> &'static str {
    match clean {
        true => "after a clean stop ",
        false => "after a crash ",
    }
}

/// Per task, the highest pool version named by the valid groups past the damage: what a
/// cut at the damage loses at least (`None` if none follow).
pub(super) fn versions_after(judged: &Judged) -> BTreeMap<String, u64> {
    let mut out = BTreeMap::new();
    let later = judged.scan.damage.iter().flat_map(|d| &d.later);
    for r in later.flat_map(|g| &g.records) {
        if let Record::Commit(c) = r {
            let v = out.entry(c.task.clone()).or_insert(0);
            *v = c.version.max(*v);
        }
    }
    out
}

/// The header of a log cut at `end`, open.
pub(super) fn open_header(dir_id: [u8; 16], end: u64) -> Header {
    Header {
        dir_id,
        acked_end: end.max(HEADER_LEN),
        state: header::OPEN,
    }
}

#[cfg(test)]
mod tests;
