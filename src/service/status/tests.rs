use super::*;

#[test]
fn trailers_only_responses_are_rewritten_in_their_headers() {
    let res =
        Status::internal("failed to decode Protobuf message: invalid wire type").into_http::<()>();
    let res = remap_response_headers(res);
    let s = Status::from_header_map(res.headers()).unwrap();
    assert_eq!(s.code(), Code::InvalidArgument);
    assert!(s.message().contains("invalid wire type"));
    let ok = remap_response_headers(http::Response::new(()));
    assert!(Status::from_header_map(ok.headers()).is_none());
}

#[test]
fn codes() {
    let s: Status = Error::invalid("steps.rewards[2]", "must be finite, got NaN").into();
    assert_eq!(s.code(), Code::InvalidArgument);
    assert_eq!(s.message(), "steps.rewards[2]: must be finite, got NaN");
    let s: Status = Error::not_found("x").into();
    assert_eq!(s.code(), Code::NotFound);
    let s = remap_decode_status(Status::out_of_range(
        "Error, decoded message length too large: found 10 bytes, the limit is: 5 bytes",
    ));
    assert_eq!(s.code(), Code::ResourceExhausted);
    assert_eq!(
        remap_decode_status(Status::out_of_range("other")).code(),
        Code::OutOfRange
    );
    let s = remap_decode_status(Status::internal(
        "failed to decode Protobuf message: buffer underflow",
    ));
    assert_eq!(s.code(), Code::InvalidArgument);
    assert!(s.message().contains("buffer underflow"), "{}", s.message());
    assert_eq!(
        remap_decode_status(Status::internal("storage error, change not applied: x")).code(),
        Code::Internal
    );
}
