//! The unary RPCs of `tamrm.v1.Shaping` by name, on serialized messages: one table for
//! both backends, a remote server ([`remote`]) and an in-process `Shaping` service
//! ([`serve`], the Python client's embedded engine).

use std::time::Duration;

use prost::Message;
use tamrm::proto::shaping_client::ShapingClient;
use tamrm::proto::shaping_server::Shaping;
use tonic::metadata::MetadataMap;
use tonic::transport::Channel as TonicChannel;
use tonic::{Request, Status};

/// The one table: runs `$call!(method_name)` for the RPC named `$method` (each of
/// `tamrm::auth::unary_rpcs()`: a test checks it), or answers UNIMPLEMENTED for a name it
/// does not know.
macro_rules! dispatch {
    ($method:expr, $call:ident) => {
        match $method {
            "CreateTask" => $call!(create_task),
            "GetTask" => $call!(get_task),
            "ListTasks" => $call!(list_tasks),
            "DeleteTask" => $call!(delete_task),
            "ResetPool" => $call!(reset_pool),
            "GetPool" => $call!(get_pool),
            "AddTrajectory" => $call!(add_trajectory),
            other => return Err(Status::unimplemented(format!("no method {other:?}"))),
        }
    };
}

/// A request message from its bytes; a malformed one is INVALID_ARGUMENT.
pub fn decode<M: Message + Default>(bytes: &[u8]) -> Result<M, Status> {
    M::decode(bytes).map_err(|e| {
        Status::invalid_argument(format!("request: not a valid protobuf message ({e})"))
    })
}

/// A request with `metadata` and, if any, a `timeout` (the `grpc-timeout` header).
pub(crate) fn request<T>(msg: T, metadata: &MetadataMap, timeout: Option<Duration>) -> Request<T> {
    let mut req = Request::new(msg);
    *req.metadata_mut() = metadata.clone();
    if let Some(t) = timeout {
        req.set_timeout(t);
    }
    req
}

/// One unary call to a server on request bytes, answering response bytes.
pub(crate) async fn remote(
    mut c: ShapingClient<TonicChannel>,
    method: &str,
    bytes: &[u8],
    md: &MetadataMap,
    timeout: Option<Duration>,
) -> Result<Vec<u8>, Status> {
    macro_rules! call {
        ($rpc:ident) => {
            c.$rpc(request(decode(bytes)?, md, timeout))
                .await?
                .get_ref()
                .encode_to_vec()
        };
    }
    Ok(dispatch!(method, call))
}

/// One unary call of an in-process `Shaping` service on request bytes, answering
/// response bytes (same checks, same statuses as over the network).
pub async fn serve<S: Shaping>(service: &S, method: &str, bytes: &[u8]) -> Result<Vec<u8>, Status> {
    macro_rules! call {
        ($rpc:ident) => {
            service
                .$rpc(Request::new(decode(bytes)?))
                .await?
                .get_ref()
                .encode_to_vec()
        };
    }
    Ok(dispatch!(method, call))
}
