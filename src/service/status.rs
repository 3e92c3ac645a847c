//! The one place where service errors become gRPC statuses.

use tonic::{Code, Status};

use crate::error::Error;

impl From<Error> for Status {
    fn from(e: Error) -> Status {
        let code = match &e {
            Error::InvalidArgument { .. } => Code::InvalidArgument,
            Error::TaskNotFound(_) => Code::NotFound,
            Error::AlreadyExists { .. } => Code::AlreadyExists,
            Error::ResourceExhausted(_) => Code::ResourceExhausted,
            Error::ShuttingDown => Code::Unavailable,
            Error::Storage(_) => Code::Internal,
        };
        if code == Code::Internal {
            tracing::error!(error = %e, "request failed");
        }
        Status::new(code, e.to_string())
    }
}

/// tonic reports a message over the size limit as OUT_OF_RANGE; gRPC's convention (and
/// SPEC §8) is RESOURCE_EXHAUSTED for a configured limit. Used for statuses tonic
/// produces while decoding; see also `server::ResourceExhaustedLayer` for unary calls.
pub fn remap_decode_status(status: Status) -> Status {
    if is_size_limit(status.code(), status.message()) {
        Status::resource_exhausted(format!(
            "message too large for this server's max_message_bytes limit ({})",
            status.message()
        ))
    } else {
        status
    }
}

/// Whether a status is tonic's "message length too large" decode error.
pub fn is_size_limit(code: Code, message: &str) -> bool {
    code == Code::OutOfRange && message.contains("message length too large")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes() {
        let s: Status = Error::invalid("steps.rewards[2]", "must be finite, got NaN").into();
        assert_eq!(s.code(), Code::InvalidArgument);
        assert_eq!(s.message(), "steps.rewards[2]: must be finite, got NaN");
        let s: Status = Error::TaskNotFound("x".into()).into();
        assert_eq!(s.code(), Code::NotFound);
        let s = remap_decode_status(Status::out_of_range(
            "Error, decoded message length too large: found 10 bytes, the limit is: 5 bytes",
        ));
        assert_eq!(s.code(), Code::ResourceExhausted);
        assert_eq!(
            remap_decode_status(Status::out_of_range("other")).code(),
            Code::OutOfRange
        );
    }
}
