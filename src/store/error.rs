//! [`StoreError`], the one error of every store. A leaf module: it uses nothing of the
//! crate, so that the service's error type (`crate::error`) can hold it without
//! importing the store.

use std::path::PathBuf;

/// A storage failure. `Clone`: a failed group commit fails every request in it with the
/// same error.
#[derive(Debug, Clone, thiserror::Error)]
pub enum StoreError {
    /// Reading or writing failed; `path` names the file, directory or key concerned.
    #[error("{}: {message}", path.display())]
    Io {
        /// The file, directory or key concerned.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// The store cannot be reached now (e.g. Redis is down); the call may succeed later.
    #[error("{what}: the store is unavailable: {message}")]
    Unavailable {
        /// The store and what was being done.
        what: String,
        /// What went wrong.
        message: String,
    },
    /// The task no longer exists in the store (deleted, perhaps by another server).
    #[error("task {task:?} no longer exists in the store")]
    Gone {
        /// The task id.
        task: String,
    },
    /// The pool changed since the version a conditional commit was planned against.
    #[error("task {task:?}: the pool is at version {found}, the commit expected {expected}")]
    Conflict {
        /// The task id.
        task: String,
        /// The version the commit was planned against.
        expected: u64,
        /// The store's version.
        found: u64,
    },
}

impl StoreError {
    pub(crate) fn new(path: impl Into<PathBuf>, message: impl std::fmt::Display) -> StoreError {
        StoreError::Io {
            path: path.into(),
            message: message.to_string(),
        }
    }
}
