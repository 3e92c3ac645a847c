//! The commit log's header (log format 2, data dir format 4): which data dir the log
//! belongs to, where its last acknowledged group ends, and whether the server stopped
//! cleanly, with a CRC-32 making it trustworthy. Pure: no I/O.
//!
//! ```text
//! "TAMRMLOG" | format u32 (2) | dir id 16 bytes | acknowledged end u64 | state u32
//!            | CRC-32 u32 of the 40 bytes before it
//! ```
//!
//! The writer rewrites the header (no sync of its own) after each group's fdatasync and
//! before acknowledging it, so the header never says more than what is durable, and the
//! next group's fdatasync makes it durable: after kill -9 or a power loss, a log found
//! shorter than its acknowledged end lost acknowledged changes, where a group past it
//! was never acknowledged. A graceful stop writes state [`STOPPED_CLEANLY`] and syncs;
//! the next start writes [`OPEN`] and syncs before any change is acknowledged.

/// Version of the log layout with this header.
pub(super) const LOG_FORMAT_V2: u32 = 2;
/// The format-1 layout (data dir format 3 and older): a 12-byte header, no more.
pub(super) const LOG_FORMAT_V1: u32 = 1;
/// Bytes of a format-2 header.
pub(super) const HEADER_LEN: u64 = 44;
/// Bytes of a format-1 header.
pub(super) const HEADER_V1_LEN: u64 = 12;
const MAGIC: &[u8; 8] = b"TAMRMLOG";
/// The log is in use, or its server crashed.
pub(super) const OPEN: u32 = 0;
/// Its server stopped gracefully, every change written.
pub(super) const STOPPED_CLEANLY: u32 = 1;

/// A log header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Header {
    pub dir_id: [u8; 16],
    /// The end of the last acknowledged group (a header alone: [`HEADER_LEN`]).
    pub acked_end: u64,
    /// [`OPEN`] or [`STOPPED_CLEANLY`].
    pub state: u32,
}

impl Header {
    /// The header's bytes.
    pub fn encode(&self) -> Vec<u8> {
        let mut b = Vec::with_capacity(HEADER_LEN as usize);
        b.extend_from_slice(MAGIC);
        b.extend_from_slice(&LOG_FORMAT_V2.to_le_bytes());
        b.extend_from_slice(&self.dir_id);
        b.extend_from_slice(&self.acked_end.to_le_bytes());
        b.extend_from_slice(&self.state.to_le_bytes());
        let crc = crc32fast::hash(&b);
        b.extend_from_slice(&crc.to_le_bytes());
        b
    }

    /// Whether the server stopped cleanly.
    pub fn clean(&self) -> bool {
        self.state == STOPPED_CLEANLY
    }
}

/// What a log's first bytes say.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Found {
    /// A format-1 log (no id, no acknowledged end): read as before format 4, then
    /// migrated.
    V1,
    /// A format-2 log.
    V2(Header),
}

/// Reads a log's header; the error says what is wrong with it.
pub(super) fn decode(b: &[u8]) -> Result<Found, String> {
    if b.len() < HEADER_V1_LEN as usize || &b[..8] != MAGIC {
        return Err(format!(
            "not a tamrm commit log (bad or truncated header: {} bytes)",
            b.len()
        ));
    }
    let format = u32::from_le_bytes([b[8], b[9], b[10], b[11]]);
    match format {
        LOG_FORMAT_V1 => return Ok(Found::V1),
        LOG_FORMAT_V2 => {}
        f => {
            return Err(format!(
                "commit log format {f} is not supported by this build (format {LOG_FORMAT_V2}, and {LOG_FORMAT_V1} which it migrates)"
            ))
        }
    }
    let n = HEADER_LEN as usize;
    if b.len() < n {
        return Err(format!(
            "the header is truncated: {} bytes, it has {n}",
            b.len()
        ));
    }
    let crc = u32::from_le_bytes([b[n - 4], b[n - 3], b[n - 2], b[n - 1]]);
    if crc32fast::hash(&b[..n - 4]) != crc {
        return Err("the header fails its checksum (damaged)".into());
    }
    let mut dir_id = [0u8; 16];
    dir_id.copy_from_slice(&b[12..28]);
    let mut end = [0u8; 8];
    end.copy_from_slice(&b[28..36]);
    let state = u32::from_le_bytes([b[36], b[37], b[38], b[39]]);
    if state > STOPPED_CLEANLY {
        return Err(format!("the header's state {state} is unknown"));
    }
    Ok(Found::V2(Header {
        dir_id,
        acked_end: u64::from_le_bytes(end),
        state,
    }))
}

#[cfg(test)]
mod tests;
