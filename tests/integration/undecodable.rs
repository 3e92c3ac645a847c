//! Bytes that are not a valid protobuf message of the request's type are the client's
//! fault: every RPC answers them with INVALID_ARGUMENT (SPEC §8), never INTERNAL, and
//! nothing changes. The requests are raw bytes sent through a codec that does not encode,
//! to a real server on 127.0.0.1:0.

use crate::common::*;

use std::time::Duration;

use bytes::{Buf, BufMut, Bytes};
use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
use tonic::{Code, Status};

/// Sends the bytes it is given as the message, and returns the answer's bytes.
#[derive(Debug, Clone, Copy, Default)]
struct RawCodec;

impl Codec for RawCodec {
    type Encode = Bytes;
    type Decode = Bytes;
    type Encoder = RawCodec;
    type Decoder = RawCodec;
    fn encoder(&mut self) -> RawCodec {
        RawCodec
    }
    fn decoder(&mut self) -> RawCodec {
        RawCodec
    }
}

impl Encoder for RawCodec {
    type Item = Bytes;
    type Error = Status;
    fn encode(&mut self, item: Bytes, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
        dst.put(item);
        Ok(())
    }
}

impl Decoder for RawCodec {
    type Item = Bytes;
    type Error = Status;
    fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<Bytes>, Status> {
        Ok(Some(src.copy_to_bytes(src.remaining())))
    }
}

/// Not a valid message of any of our request types, each for its own reason.
const UNDECODABLE: [(&str, &[u8]); 4] = [
    ("a length-delimited field without its length", &[0x0a]),
    ("a truncated length-delimited field", &[0x0a, 0x05, b'a']),
    (
        "a varint longer than 10 bytes",
        &[
            0x10, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01,
        ],
    ),
    (
        "field 1 (a string) with the varint wire type",
        &[0x08, 0x01],
    ),
];

async fn raw_channel(addr: std::net::SocketAddr) -> tonic::client::Grpc<tonic::transport::Channel> {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    tonic::client::Grpc::new(channel)
}

#[track_caller]
fn assert_invalid(what: &str, s: &Status) {
    assert_eq!(
        s.code(),
        Code::InvalidArgument,
        "{what}: wrong code, message {:?}",
        s.message()
    );
    assert!(
        s.message().contains("not a valid protobuf message"),
        "{what}: {:?}",
        s.message()
    );
}

#[tokio::test]
async fn every_unary_rpc_answers_undecodable_bytes_with_invalid_argument() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(2, 2, 2, 0, 1)).await;
    let before = get_task(&mut c, "t").await;
    let mut raw = raw_channel(server.addr()).await;
    for rpc in tamrm::auth::unary_rpcs() {
        // ListTasksRequest has no fields: only bytes that cannot be parsed at all count.
        for (what, bytes) in UNDECODABLE {
            if rpc == "ListTasks" && what.starts_with("field 1") {
                continue;
            }
            raw.ready().await.unwrap();
            let path =
                http::uri::PathAndQuery::from_maybe_shared(format!("/tamrm.v1.Shaping/{rpc}"))
                    .unwrap();
            let r = tokio::time::timeout(
                Duration::from_secs(10),
                raw.unary(
                    tonic::Request::new(Bytes::from_static(bytes)),
                    path,
                    RawCodec,
                ),
            )
            .await
            .expect("an answer");
            match r {
                Ok(_) => panic!("{rpc}, {what}: accepted"),
                Err(s) => assert_invalid(&format!("{rpc}, {what}"), &s),
            }
        }
    }
    assert_eq!(get_task(&mut c, "t").await, before, "nothing changed");
}

#[tokio::test]
async fn an_undecodable_stream_message_ends_the_stream_with_invalid_argument() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "t", discrete(2, 2, 2, 0, 1)).await;
    let mut raw = raw_channel(server.addr()).await;
    for (what, bytes) in UNDECODABLE {
        raw.ready().await.unwrap();
        let path = http::uri::PathAndQuery::from_static("/tamrm.v1.Shaping/Shape");
        let out = tokio_stream::iter(vec![Bytes::from_static(bytes)]);
        let r = tokio::time::timeout(
            Duration::from_secs(10),
            raw.streaming(tonic::Request::new(out), path, RawCodec),
        )
        .await
        .expect("an answer");
        let status = match r {
            Err(s) => s,
            Ok(resp) => {
                let mut inbound = resp.into_inner();
                match tokio::time::timeout(Duration::from_secs(10), inbound.message())
                    .await
                    .expect("an answer")
                {
                    Err(s) => s,
                    Ok(m) => panic!("{what}: expected a status, got {m:?}"),
                }
            }
        };
        assert_invalid(what, &status);
    }
    let t = get_task(&mut c, "t").await;
    assert_eq!(t.stats.unwrap().open_streams, 0);
}
