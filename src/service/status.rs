//! The one place where service errors become gRPC statuses.

use tonic::{Code, Status};

use crate::error::Error;

impl From<Error> for Status {
    fn from(e: Error) -> Status {
        let code = match &e {
            Error::InvalidArgument { .. } => Code::InvalidArgument,
            Error::TaskNotFound { .. } => Code::NotFound,
            Error::AlreadyExists { .. } => Code::AlreadyExists,
            Error::ResourceExhausted(_) => Code::ResourceExhausted,
            Error::Unauthenticated(_) => Code::Unauthenticated,
            Error::PermissionDenied(_) => Code::PermissionDenied,
            Error::ShuttingDown | Error::StoreUnavailable(_) | Error::ResumeNeeded(_) => {
                Code::Unavailable
            }
            Error::Storage(_) => Code::Internal,
        };
        if code == Code::Internal {
            tracing::error!(error = %e, "request failed");
        }
        Status::new(code, e.to_string())
    }
}

/// Rewrites the statuses tonic produces *before* a handler sees a request, so that a
/// client's fault is never reported as ours (SPEC §8):
/// - a message over `max_message_bytes` (tonic: OUT_OF_RANGE) becomes RESOURCE_EXHAUSTED,
///   gRPC's code for a configured limit;
/// - bytes that are not a valid protobuf message of the request's type (tonic: INTERNAL
///   "failed to decode Protobuf message: ...") become INVALID_ARGUMENT. INTERNAL stays what
///   operators alert on: a bug of ours or a storage failure.
///
/// Used on the statuses of stream messages (`service::stream`) and, through
/// [`remap_response_headers`], on unary responses.
pub fn remap_decode_status(status: Status) -> Status {
    if is_size_limit(status.code(), status.message()) {
        Status::resource_exhausted(format!(
            "message too large for this server's max_message_bytes limit ({})",
            status.message()
        ))
    } else if is_decode_failure(status.code(), status.message()) {
        Status::invalid_argument(format!(
            "request: not a valid protobuf message of its type ({})",
            status.message()
        ))
    } else {
        status
    }
}

fn is_size_limit(code: Code, message: &str) -> bool {
    code == Code::OutOfRange && message.contains("message length too large")
}

fn is_decode_failure(code: Code, message: &str) -> bool {
    code == Code::Internal && message.starts_with("failed to decode Protobuf message")
}

/// Applies [`remap_decode_status`] to a response whose status travels in its headers
/// (tonic answers a unary request it cannot decode with a trailers-only response, before
/// any handler runs).
pub fn remap_response_headers<B>(mut res: http::Response<B>) -> http::Response<B> {
    let Some(status) = Status::from_header_map(res.headers()) else {
        return res;
    };
    if status.code() == Code::Ok {
        return res;
    }
    let remapped = remap_decode_status(status.clone());
    if remapped.code() != status.code() {
        if let Err(e) = remapped.add_header(res.headers_mut()) {
            tracing::warn!(error = %e, "could not rewrite a response status");
        }
    }
    res
}

#[cfg(test)]
mod tests;
