//! The service's error type. Every failure a client can cause or observe is one of these;
//! `service::status` is the one place that maps them to gRPC status codes.
//!
//! Nearly every module uses this one, so it uses leaf modules only (modules that use
//! nothing of the crate; `tests/layers.rs` checks it): no import circle runs through it.

use crate::store::error::StoreError;
use crate::task_key::split_key;

/// An error answered to a client.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A malformed request; `field` names the offending field (proto path).
    #[error("{field}: {message}")]
    InvalidArgument {
        /// The offending field, e.g. `steps.actions[3]` or `config.k`.
        field: String,
        /// What is wrong with it.
        message: String,
    },
    /// No task with this id; the message suggests the closest existing id, if one is close.
    #[error("task {id:?} not found{}", hint.as_ref().map(|h| format!(" (did you mean {h:?}?)")).unwrap_or_default())]
    TaskNotFound {
        /// The id asked for.
        id: String,
        /// An existing id a typo away, if any.
        hint: Option<String>,
    },
    /// CreateTask for an existing id with a different resolved config.
    #[error("task {id:?} already exists with a different config ({detail})")]
    AlreadyExists {
        /// The task id.
        id: String,
        /// Which fields differ.
        detail: String,
    },
    /// A configured server limit was reached.
    #[error("{0}")]
    ResourceExhausted(String),
    /// No credential, a malformed one, or a key the server does not know (SPEC §11).
    #[error("{0}")]
    Unauthenticated(String),
    /// A known key calling beyond its role (SPEC §11).
    #[error("{0}")]
    PermissionDenied(String),
    /// The server is shutting down; reconnect to another (or the restarted) server.
    #[error("server is shutting down")]
    ShuttingDown,
    /// The store cannot be reached now (a shared store, e.g. Redis, is down); the change
    /// was not applied and the call may succeed later.
    #[error("{0}")]
    StoreUnavailable(String),
    /// The stream's state no longer matches the store: the client must resume it on a new
    /// stream and re-send its last batch (SPEC §9); what was committed stays committed.
    #[error("{0}")]
    ResumeNeeded(String),
    /// Persisting a change failed; the change was not applied.
    #[error("storage error, change not applied: {0}")]
    Storage(StoreError),
}

impl From<StoreError> for Error {
    fn from(e: StoreError) -> Error {
        match e {
            StoreError::Unavailable { .. } => {
                Error::StoreUnavailable(format!("change not applied: {e}"))
            }
            // Another server deleted the task.
            StoreError::Gone { task } => Error::not_found(split_key(&task).1),
            e => Error::Storage(e),
        }
    }
}

impl Error {
    /// An [`Error::TaskNotFound`] without a suggestion.
    pub fn not_found(id: impl Into<String>) -> Error {
        Error::TaskNotFound {
            id: id.into(),
            hint: None,
        }
    }

    /// An [`Error::InvalidArgument`] for `field`.
    pub fn invalid(field: impl Into<String>, message: impl Into<String>) -> Error {
        Error::InvalidArgument {
            field: field.into(),
            message: message.into(),
        }
    }
}
