//! The Shape stream's codec: the bytes on the wire are protobuf, exactly as prost reads
//! and writes them; only the two messages of every batch take a shorter path.
//!
//! - A `ShapeRequest` that carries a `StepBatch` of packed columns is read straight from
//!   the received bytes (slices, one allocation of the exact size per column) instead of
//!   one buffer call and a growing `Vec` per element. Anything else (`Open`, the
//!   `episode_scores` map, unknown fields, unpacked encodings, long varints, malformed
//!   bytes) is left to prost, so the decoded value, and every decoding error, is prost's.
//! - A `ShapedBatch` is written by the stream's task straight from the session's outputs
//!   into one buffer per stream (no answer columns), byte for byte what prost writes for
//!   the `ShapeResponse` that [`super::convert::shaped_proto`] builds; the encoder copies it.
//!
//! [`ShapeCodec`] is what [`super::ShapingRoutes`] mounts for `/tamrm.v1.Shaping/Shape`.

use bytes::{Buf, BufMut, Bytes, BytesMut};
use prost::Message;
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::Status;

use crate::proto::{self, shape_request, ShapeRequest, ShapeResponse};
use crate::session::Shaped;

/// One message of a Shape stream's answer.
#[derive(Debug)]
pub enum Answer {
    /// Encoded by prost (`opened`).
    Message(ShapeResponse),
    /// A `ShapeResponse` already encoded (a `ShapedBatch`, by [`encode_shaped`]).
    Encoded(Bytes),
}

/// The codec of the Shape stream: decodes `ShapeRequest`s, encodes [`Answer`]s.
#[derive(Debug, Clone, Copy, Default)]
pub struct ShapeCodec;

impl Codec for ShapeCodec {
    type Encode = Answer;
    type Decode = ShapeRequest;
    type Encoder = ShapeCodec;
    type Decoder = ShapeCodec;

    fn encoder(&mut self) -> ShapeCodec {
        ShapeCodec
    }

    fn decoder(&mut self) -> ShapeCodec {
        ShapeCodec
    }
}

impl Encoder for ShapeCodec {
    type Item = Answer;
    type Error = Status;

    fn encode(&mut self, item: Answer, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
        match item {
            Answer::Message(m) => m
                .encode(dst)
                .map_err(|e| Status::internal(format!("encoding an answer: {e}"))),
            Answer::Encoded(bytes) => {
                dst.put_slice(&bytes);
                Ok(())
            }
        }
    }
}

impl Decoder for ShapeCodec {
    type Item = ShapeRequest;
    type Error = Status;

    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<ShapeRequest>, Status> {
        let len = src.remaining();
        let chunk = src.chunk();
        if chunk.len() == len {
            if let Some(batch) = step_batch_request(chunk) {
                src.advance(len);
                return Ok(Some(ShapeRequest {
                    kind: Some(shape_request::Kind::Steps(batch)),
                }));
            }
        }
        // What tonic's prost codec does, error message included.
        ShapeRequest::decode(src)
            .map(Some)
            .map_err(|e| Status::internal(e.to_string()))
    }
}

/// Decodes a `ShapeRequest` from `bytes` as prost does (the same value, the same errors):
/// a batch of packed columns by the short path, anything else by prost.
pub fn decode_request(bytes: &[u8]) -> Result<ShapeRequest, prost::DecodeError> {
    match step_batch_request(bytes) {
        Some(batch) => Ok(ShapeRequest {
            kind: Some(shape_request::Kind::Steps(batch)),
        }),
        None => ShapeRequest::decode(bytes),
    }
}

/// A varint of at most 5 bytes at the start of `bytes`: its value and length (`None` if
/// it is longer, or not terminated within `bytes`: prost decides those).
#[inline]
fn varint(bytes: &[u8]) -> Option<(u64, usize)> {
    let mut value = 0u64;
    for (i, &b) in bytes.iter().take(5).enumerate() {
        value |= u64::from(b & 0x7f) << (7 * i);
        if b < 0x80 {
            return Some((value, i + 1));
        }
    }
    None
}

/// Appends the packed varints of `payload`, each converted by `of`, if every one is at most
/// 5 bytes long and the last one ends the payload.
#[inline]
fn packed_varints<T>(payload: &[u8], out: &mut Vec<T>, of: impl Fn(u64) -> T) -> Option<()> {
    if payload.last().is_some_and(|&b| b >= 0x80) {
        return None;
    }
    out.reserve(payload.iter().filter(|&&b| b < 0x80).count());
    let mut rest = payload;
    while let Some((&b, tail)) = rest.split_first() {
        if b < 0x80 {
            out.push(of(u64::from(b)));
            rest = tail;
        } else {
            let (v, n) = varint(rest)?;
            out.push(of(v));
            rest = &rest[n..];
        }
    }
    Some(())
}

/// Appends the packed little-endian values of `payload` (`N` bytes each), if it holds a
/// whole number of them.
#[inline]
fn packed_fixed<T, const N: usize>(
    payload: &[u8],
    out: &mut Vec<T>,
    of: impl Fn([u8; N]) -> T,
) -> Option<()> {
    let chunks = payload.chunks_exact(N);
    if !chunks.remainder().is_empty() {
        return None;
    }
    out.reserve(payload.len() / N);
    out.extend(chunks.map(|c| {
        let mut b = [0u8; N];
        b.copy_from_slice(c);
        of(b)
    }));
    Some(())
}

/// The `StepBatch` of a `ShapeRequest` whose only field is `steps` and whose batch holds
/// only packed columns (fields 1–10 and 12), each field's key and length well-formed:
/// the value prost decodes from the same bytes. `None` for anything else.
fn step_batch_request(bytes: &[u8]) -> Option<proto::StepBatch> {
    // Field 2 (`steps`), length-delimited, spanning the rest of the message.
    let (&key, rest) = bytes.split_first()?;
    let (len, n) = varint(rest)?;
    let body = &rest[n..];
    if key != (2 << 3 | 2) || usize::try_from(len).ok()? != body.len() {
        return None;
    }
    let mut b = proto::StepBatch::default();
    let mut rest = body;
    while let Some((&key, tail)) = rest.split_first() {
        // One-byte keys of length-delimited (packed) fields only.
        if key & 0x87 != 2 {
            return None;
        }
        let (len, n) = varint(tail)?;
        let len = usize::try_from(len).ok()?;
        let payload = tail.get(n..n.checked_add(len)?)?;
        rest = &tail[n + len..];
        let f32_le = f32::from_le_bytes;
        match key >> 3 {
            1 => packed_varints(payload, &mut b.env_ids, |v| v as u32)?,
            2 => packed_varints(payload, &mut b.actions, |v| v as u32)?,
            3 => packed_fixed(payload, &mut b.action_vectors, f32_le)?,
            4 => packed_fixed(payload, &mut b.rewards, f64::from_le_bytes)?,
            5 => packed_varints(payload, &mut b.terminated, |v| v != 0)?,
            6 => packed_varints(payload, &mut b.truncated, |v| v != 0)?,
            7 => packed_fixed(payload, &mut b.values, f32_le)?,
            8 => packed_fixed(payload, &mut b.next_values, f32_le)?,
            9 => packed_fixed(payload, &mut b.q_values, f32_le)?,
            10 => packed_fixed(payload, &mut b.next_q_values, f32_le)?,
            12 => packed_varints(payload, &mut b.abandon, |v| v as u32)?,
            // The scores map (11), unknown fields.
            _ => return None,
        }
    }
    Some(b)
}

fn put_varint(out: &mut BytesMut, mut v: u64) {
    while v >= 0x80 {
        out.put_u8((v as u8) | 0x80);
        v >>= 7;
    }
    out.put_u8(v as u8);
}

fn varint_len(v: u64) -> usize {
    prost::encoding::encoded_len_varint(v)
}

/// The step index as the answer carries it (as [`super::convert::shaped_proto`]).
fn step_u32(step: u64) -> u32 {
    u32::try_from(step).unwrap_or(u32::MAX)
}

/// Writes the `ShapeResponse` that answers a batch (its `ShapedBatch`) to `out`: the bytes
/// prost writes for `ShapeResponse { shaped: shaped_proto(s) }`.
pub fn encode_shaped(s: &Shaped<'_>, out: &mut BytesMut) {
    let o = s.outputs;
    let n = o.len();
    let steps_len: usize = o.iter().map(|o| varint_len(step_u32(o.step).into())).sum();
    // Packed fields: key, length, values; empty ones are left out, as is a zero version.
    let packed = |len: usize| {
        if n == 0 {
            0
        } else {
            1 + varint_len(len as u64) + len
        }
    };
    let body = 3 * packed(8 * n)
        + packed(steps_len)
        + packed(n)
        + if s.pool_version == 0 {
            0
        } else {
            1 + varint_len(s.pool_version)
        };
    out.reserve(1 + varint_len(body as u64) + body);
    out.put_u8(2 << 3 | 2);
    put_varint(out, body as u64);
    if n > 0 {
        let doubles = |out: &mut BytesMut, key: u8, f: fn(&crate::core::StepOutput) -> f64| {
            out.put_u8(key);
            put_varint(out, 8 * n as u64);
            let at = out.len();
            out.resize(at + 8 * n, 0);
            for (dst, o) in out[at..].chunks_exact_mut(8).zip(o) {
                dst.copy_from_slice(&f(o).to_le_bytes());
            }
        };
        doubles(out, 1 << 3 | 2, |o| o.reward);
        doubles(out, 2 << 3 | 2, |o| o.knn_reward);
        doubles(out, 3 << 3 | 2, |o| o.potential);
        out.put_u8(4 << 3 | 2);
        put_varint(out, steps_len as u64);
        for o in o {
            put_varint(out, step_u32(o.step).into());
        }
        out.put_u8(5 << 3 | 2);
        put_varint(out, n as u64);
        out.extend(o.iter().map(|o| u8::from(o.knn_active)));
    }
    if s.pool_version != 0 {
        out.put_u8(6 << 3);
        put_varint(out, s.pool_version);
    }
}

#[cfg(test)]
mod tests;
