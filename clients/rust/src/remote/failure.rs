//! Failure classification: which failures a call may retry elsewhere or a session may
//! resume, and the transport's failures spelled out (a wrong CA or a plaintext/TLS
//! mismatch reads as such, not as a bare "transport error").

use tonic::{Code, Status};

/// Words of the errors rustls and hyper give when a TLS handshake fails, or when
/// plaintext HTTP/2 meets a TLS server.
const TLS_WORDS: [&str; 6] = [
    "certificate",
    "tls",
    "handshake",
    "alert",
    "corrupt message",
    "invalidcontenttype",
];
const CLOSED_WORDS: [&str; 4] = ["connection closed", "reset", "broken pipe", "eof"];
const PLAINTEXT_TO_TLS_WORDS: [&str; 6] = [
    "frame",
    "protocol",
    "connection closed",
    "reset",
    "broken pipe",
    "eof",
];

/// A transport failure as a status (`UNAVAILABLE`: could not reach the server).
fn unreachable(target: &str, e: impl std::fmt::Display) -> Status {
    Status::unavailable(format!("could not reach {target}: {e}"))
}

/// Whether the status's source chain holds tonic's `TimeoutExpired`.
fn expired(s: &Status) -> bool {
    let mut source = std::error::Error::source(s);
    while let Some(e) = source {
        if e.is::<tonic::TimeoutExpired>() {
            return true;
        }
        source = e.source();
    }
    false
}

/// A status made by the transport (not the server's answer) with the cause that tonic
/// keeps in its source chain spelled out, saying when it is TLS that failed (or was
/// expected).
pub(crate) fn transport_error(target: &str, tls: bool, s: Status) -> Status {
    if std::error::Error::source(&s).is_none() || s.code() == Code::DeadlineExceeded {
        // The server's own answer, or our deadline: as it is.
        return s;
    }
    let detail = tamrm::net::status_chain(&s);
    if expired(&s) {
        // The call's deadline passed in tonic's timeout layer (it says CANCELLED).
        return Status::deadline_exceeded(format!(
            "no answer from {target} within the deadline: {detail}"
        ));
    }
    let lower = detail.to_lowercase();
    let message = if tls && TLS_WORDS.iter().any(|w| lower.contains(w)) {
        format!(
            "TLS handshake with {target} failed: {detail} (check root_certificates, \
             tls_server_name and the client certificate, and that the server has TLS on)"
        )
    } else if tls && CLOSED_WORDS.iter().any(|w| lower.contains(w)) {
        // TLS 1.3: a refused client certificate reaches the client after its handshake
        // finished, often as a plain close.
        format!(
            "connection to {target} closed: {detail} (over TLS: a server with mutual TLS \
             closes connections without a client certificate it accepts; check \
             certificate_chain and private_key)"
        )
    } else if !tls
        && !lower.contains("refused")
        && PLAINTEXT_TO_TLS_WORDS.iter().any(|w| lower.contains(w))
    {
        format!(
            "connection to {target} failed: {detail} (if the server has TLS on, connect \
             with tls=True or root_certificates=)"
        )
    } else {
        format!("could not reach {target}: {detail}")
    };
    // The transport's own codes for a failed connection (UNKNOWN, CANCELLED, INTERNAL
    // for an HTTP/2 protocol error) say less than UNAVAILABLE, which a caller retries on.
    let code = match s.code() {
        Code::Unknown | Code::Cancelled | Code::Internal => Code::Unavailable,
        other => other,
    };
    Status::new(code, message)
}

/// Methods that change nothing, or whose repetition changes nothing more (a `CreateTask`
/// with the same config is the same task): after a connection broke under them they can be
/// sent to the next address.
const IDEMPOTENT: [&str; 4] = ["GetTask", "ListTasks", "GetPool", "CreateTask"];

/// Whether a failed unary call may be sent to the next address: the server refused it
/// without applying anything (its own UNAVAILABLE: shutting down, its store down), the
/// connection could not be made (nothing was sent), or the call is idempotent and the
/// connection broke.
pub(crate) fn may_fail_over(method: &str, s: &Status) -> bool {
    if s.code() != Code::Unavailable && !resumable(s) {
        return false;
    }
    std::error::Error::source(s).is_none()
        || IDEMPOTENT.contains(&method)
        || tamrm::net::status_chain(s)
            .to_lowercase()
            .contains("connect error")
}

/// Whether a failed step is worth resuming: the server is unreachable or going away
/// (UNAVAILABLE), or the connection broke under the stream (a transport error). Every
/// answer of the server itself (a rejected batch, a deleted task, a quota) is final.
pub(crate) fn resumable(s: &Status) -> bool {
    match s.code() {
        Code::Unavailable => true,
        Code::Unknown | Code::Internal | Code::Cancelled => {
            std::error::Error::source(s).is_some() || s.message().contains("h2 protocol error")
        }
        _ => false,
    }
}

/// A failure to open a stream as a status that says what failed.
pub(crate) fn connect_error(target: &str, tls: bool, s: Status) -> Status {
    if std::error::Error::source(&s).is_some() {
        transport_error(target, tls, s)
    } else if s.code() == Code::Unavailable || s.code() == Code::Unknown {
        unreachable(target, s.message())
    } else {
        s
    }
}

/// "no server answered (a, b): why", with `failure`'s code.
pub(crate) fn none_answered(names: &str, failure: &Status) -> Status {
    Status::new(
        failure.code(),
        format!("no server answered ({names}): {}", failure.message()),
    )
}
