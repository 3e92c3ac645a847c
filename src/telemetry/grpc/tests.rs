use super::frames::PREFIX;
use super::*;

#[test]
fn every_served_method_is_known_and_typed() {
    let m = methods();
    let shape = m.get("/tamrm.v1.Shaping/Shape").copied();
    assert_eq!(
        shape.map(|s| (s.grpc_type, s.grpc_service)),
        Some(("bidi_stream", "tamrm.v1.Shaping"))
    );
    let get = m.get("/tamrm.v1.Shaping/GetTask").copied();
    assert_eq!(get.map(|s| s.grpc_type), Some("unary"));
    let follow = m.get("/tamrm.v1.Shaping/Follow").copied();
    assert_eq!(follow.map(|s| s.grpc_type), Some("bidi_stream"));
    let watch = m.get("/grpc.health.v1.Health/Watch").copied();
    assert_eq!(watch.map(|s| s.grpc_type), Some("server_stream"));
    assert!(m.contains_key("/grpc.reflection.v1.ServerReflection/ServerReflectionInfo"));
    assert!(m.contains_key("/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo"));
    assert!(!m.contains_key("/tamrm.v1.Shaping/Nope"));
}

#[test]
fn status_codes_are_named_as_in_go() {
    let mut h = http::HeaderMap::new();
    assert_eq!(status_of(&h), None);
    h.insert("grpc-status", http::HeaderValue::from_static("5"));
    assert_eq!(status_of(&h), Some("NotFound"));
    h.insert("grpc-status", http::HeaderValue::from_static("99"));
    assert_eq!(status_of(&h), Some("Unknown"));
}

/// `lens` as gRPC messages (flags alternating), and the offset just past each.
fn encode(lens: &[u32]) -> (Vec<u8>, Vec<usize>) {
    let mut bytes = Vec::new();
    let mut ends = Vec::new();
    for (i, &len) in lens.iter().enumerate() {
        bytes.push(u8::from(i % 2 == 1));
        bytes.extend_from_slice(&len.to_be_bytes());
        bytes.extend((0..len).map(|j| (j % 251) as u8));
        ends.push(bytes.len());
    }
    (bytes, ends)
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig { cases: 500, ..Default::default() })]

    /// Cut anywhere (empty chunks too, and many cuts inside the prefixes), the
    /// counter has counted, after each chunk, exactly the messages whose last byte it
    /// has seen.
    #[test]
    fn message_frames_count_whole_messages_across_any_chunks(
        lens in proptest::collection::vec(
            proptest::prop_oneof![0u32..4, 0u32..300, 250u32..70_000],
            0..12,
        ),
        cuts in proptest::collection::vec(
            (
                proptest::prelude::any::<proptest::sample::Index>(),
                0usize..=usize::from(PREFIX),
                proptest::prelude::any::<bool>(),
            ),
            0..24,
        ),
    ) {
        let (bytes, ends) = encode(&lens);
        let starts: Vec<usize> = std::iter::once(0).chain(ends.iter().copied()).collect();
        let mut cuts: Vec<usize> = cuts
            .iter()
            .map(|(at, into_prefix, anywhere)| {
                if *anywhere {
                    at.index(bytes.len() + 1)
                } else {
                    // Into the prefix of a message (or at the end).
                    (at.get(&starts) + into_prefix).min(bytes.len())
                }
            })
            .collect();
        cuts.push(bytes.len());
        cuts.sort_unstable();
        let mut frames = MessageFrames::default();
        let (mut from, mut counted) = (0, 0u64);
        for to in cuts {
            counted += frames.feed(&bytes[from..to]);
            from = to;
            let whole = ends.iter().filter(|&&e| e <= to).count() as u64;
            proptest::prop_assert_eq!(counted, whole, "after {} of {} bytes", to, bytes.len());
        }
        proptest::prop_assert_eq!(frames, MessageFrames::default(), "ends between messages");
    }
}

#[test]
fn message_frames_read_prefixes_byte_by_byte_and_wait_for_the_payload() {
    let (bytes, _) = encode(&[0, 3]);
    let mut frames = MessageFrames::default();
    let byte_by_byte: u64 = bytes.iter().map(|b| frames.feed(&[*b])).sum();
    assert_eq!(byte_by_byte, 2, "an empty message and one of 3 bytes");
    assert_eq!(
        frames.feed(&[1, 1, 2, 3, 4]),
        0,
        "a prefix with no payload yet"
    );
    assert_eq!(frames.len, 0x0102_0304);
    assert_eq!(frames.feed(&vec![0; 0x0102_0303]), 0, "one byte short");
    assert_eq!(
        frames.feed(&[0, 0, 0, 0, 0, 0]),
        2,
        "its last byte and an empty message"
    );
    assert_eq!(frames, MessageFrames::default());
}

/// Through the layer: a streaming call whose messages are split across request
/// frames, answered with two messages in one frame; then a failed unary call
/// (trailers only) on a path no service serves.
#[test]
fn the_layer_counts_request_and_response_messages() {
    use http_body_util::BodyExt;
    type Frames = http_body_util::StreamBody<
        futures::stream::Iter<
            std::vec::IntoIter<Result<http_body::Frame<bytes::Bytes>, std::convert::Infallible>>,
        >,
    >;
    fn body(frames: Vec<http_body::Frame<bytes::Bytes>>) -> Frames {
        http_body_util::StreamBody::new(futures::stream::iter(
            frames.into_iter().map(Ok).collect::<Vec<_>>(),
        ))
    }
    fn trailers(code: &'static str) -> http_body::Frame<bytes::Bytes> {
        let mut t = http::HeaderMap::new();
        t.insert("grpc-status", http::HeaderValue::from_static(code));
        http_body::Frame::trailers(t)
    }
    // Reads the whole request, then answers two messages for a known method and
    // UNIMPLEMENTED (trailers only) for any other.
    async fn answer(
        req: http::Request<MeteredRequestBody<Frames>>,
    ) -> Result<http::Response<Frames>, std::convert::Infallible> {
        let known = methods().contains_key(req.uri().path());
        req.into_body().collect().await.unwrap();
        Ok(if known {
            let (two, _) = encode(&[2, 0]);
            http::Response::new(body(vec![
                http_body::Frame::data(two.into()),
                trailers("0"),
            ]))
        } else {
            let mut res = http::Response::new(body(vec![]));
            res.headers_mut()
                .insert("grpc-status", http::HeaderValue::from_static("12"));
            res
        })
    }
    let metrics = Arc::new(Metrics::new());
    let mut svc = tower::Layer::layer(
        &GrpcMetricsLayer::new(Some(metrics.clone())),
        tower::service_fn(answer),
    );
    let mut call = |path: &'static str, request: Vec<u8>, cut: usize| {
        let req = http::Request::builder()
            .uri(path)
            .body(body(vec![
                http_body::Frame::data(bytes::Bytes::copy_from_slice(&request[..cut])),
                http_body::Frame::data(bytes::Bytes::copy_from_slice(&request[cut..])),
            ]))
            .unwrap();
        let res = futures::executor::block_on(tower::Service::call(&mut svc, req)).unwrap();
        futures::executor::block_on(res.into_body().collect()).unwrap();
    };
    let (three, _) = encode(&[7, 0, 40]);
    call("/tamrm.v1.Shaping/Shape", three, 9);
    let (one, _) = encode(&[5]);
    call("/tamrm.v1.Shaping/Nope", one, 3);

    let count = |family: &Family<Method, Counter>, path: &str| {
        let method = methods().get(path).copied().unwrap_or(UNKNOWN);
        family.get_or_create(&method).get()
    };
    let g = &metrics.grpc;
    assert_eq!(count(&g.received, "/tamrm.v1.Shaping/Shape"), 3);
    assert_eq!(count(&g.sent, "/tamrm.v1.Shaping/Shape"), 2);
    assert_eq!(count(&g.received, "/tamrm.v1.Shaping/Nope"), 1);
    assert_eq!(count(&g.sent, "/tamrm.v1.Shaping/Nope"), 0, "trailers only");
    assert_eq!(count(&g.started, "/tamrm.v1.Shaping/Shape"), 1);
}
