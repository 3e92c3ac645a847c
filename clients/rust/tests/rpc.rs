//! The one table of unary RPCs (`tamrm_client::rpc`) names every unary RPC of the
//! service, on both backends, and answers the server's statuses.

mod common;

use common::{create_request, Server};
use prost::Message;
use tamrm_client::tonic::Code;
use tamrm_client::{proto, rpc, Channel, ChannelOptions};

#[test]
fn every_unary_rpc_is_in_the_table_of_both_backends() {
    let rt = tamrm_client::runtime().unwrap();
    let (_, service) = common::engine();
    let server = Server::start(&[]);
    let channel = Channel::connect(&[&server.addr], ChannelOptions::new()).unwrap();
    let methods: Vec<&str> = tamrm::auth::unary_rpcs().collect();
    assert!(methods.len() >= 7, "{methods:?}");
    for method in methods {
        // An empty request: a valid message with no task id, which the service refuses
        // or answers, but never as an unknown method.
        let local = rt.block_on(rpc::serve(&service, method, &[]));
        let remote = channel.call(method, &[], None);
        for (backend, answer) in [("in-process", local), ("remote", remote)] {
            if let Err(s) = answer {
                assert_ne!(s.code(), Code::Unimplemented, "{backend} {method}: {s:?}");
            }
        }
    }
    let unknown = rt.block_on(rpc::serve(&service, "Nope", &[])).unwrap_err();
    assert_eq!(unknown.code(), Code::Unimplemented);
    assert_eq!(
        channel.call("Nope", &[], None).unwrap_err().code(),
        Code::Unimplemented
    );
}

#[test]
fn both_backends_answer_alike() {
    let rt = tamrm_client::runtime().unwrap();
    let (_, service) = common::engine();
    let server = Server::start(&[]);
    let channel = Channel::connect(&[&server.addr], ChannelOptions::new()).unwrap();
    let create = create_request("t").encode_to_vec();
    let local = rt
        .block_on(rpc::serve(&service, "CreateTask", &create))
        .unwrap();
    let remote = channel.call("CreateTask", &create, None).unwrap();
    assert_eq!(
        proto::Task::decode(local.as_slice()).unwrap().config,
        proto::Task::decode(remote.as_slice()).unwrap().config
    );
    // A malformed request and a missing task: the same status on both.
    for (method, bytes) in [
        ("GetTask", vec![0xff, 0xff]),
        ("GetTask", b"\x0a\x01x".to_vec()),
    ] {
        let local = rt
            .block_on(rpc::serve(&service, method, &bytes))
            .unwrap_err();
        let remote = channel.call(method, &bytes, None).unwrap_err();
        assert_eq!(local.code(), remote.code(), "{local:?} {remote:?}");
        assert!(
            matches!(local.code(), Code::InvalidArgument | Code::NotFound),
            "{local:?}"
        );
    }
}
