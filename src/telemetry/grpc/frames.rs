//! Where the gRPC messages of a body end: the length-prefixed framing read off the body's
//! data frames, however they split it.

/// The length of a gRPC message's prefix: a compression flag and a big-endian `u32`
/// length.
pub(super) const PREFIX: u8 = 5;

/// Counts the whole gRPC messages in the data of a body: each is a [`PREFIX`] of 5 bytes
/// and as many bytes as its length says, and either may be split anywhere across data
/// frames. [`MessageFrames::feed`] reads only the prefixes (a payload is skipped in one
/// step) and allocates nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) struct MessageFrames {
    /// Bytes of the current message's prefix seen: 0 to 4 while it is read, [`PREFIX`]
    /// once the message's payload is being skipped.
    pub(super) prefix: u8,
    /// While the prefix is read, the length bytes seen so far; then the payload bytes
    /// still to come (never 0 in the payload: an empty message ends with its prefix).
    pub(super) len: u32,
}

impl MessageFrames {
    /// Reads the next `data` of the body; returns how many messages ended in it.
    pub(super) fn feed(&mut self, mut data: &[u8]) -> u64 {
        let mut ended = 0;
        while !data.is_empty() {
            if self.prefix == PREFIX {
                // Skip the payload, or as much of it as this data holds.
                let n = data.len().min(self.len as usize);
                data = &data[n..];
                self.len -= n as u32;
                if self.len == 0 {
                    ended += 1;
                    self.prefix = 0;
                }
            } else if self.prefix == 0 && data.len() >= usize::from(PREFIX) {
                // A whole prefix in this data (the usual case).
                let len = u32::from_be_bytes([data[1], data[2], data[3], data[4]]);
                data = &data[usize::from(PREFIX)..];
                if len == 0 {
                    ended += 1;
                } else {
                    self.len = len;
                    self.prefix = PREFIX;
                }
            } else {
                // A prefix split across data frames, one byte at a time (the first byte
                // is the compression flag).
                if self.prefix > 0 {
                    self.len = self.len << 8 | u32::from(data[0]);
                }
                data = &data[1..];
                self.prefix += 1;
                if self.prefix == PREFIX && self.len == 0 {
                    ended += 1;
                    self.prefix = 0;
                }
            }
        }
        ended
    }
}
