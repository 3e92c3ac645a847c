//! The client's one error type.

use tonic::Status;

/// Any error, boxed (what an [`crate::Interrupt`] check fails with).
pub type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// Why a client call failed.
#[derive(Debug)]
pub enum Error {
    /// A bad argument: nothing was sent. The message names the argument.
    Invalid(String),
    /// The client's runtime or one of its threads could not start.
    Runtime(String),
    /// A failed call: the server's status, or the transport's failure as one
    /// (`UNAVAILABLE`: the server could not be reached).
    Status(Status),
    /// The [`crate::Interrupt`] check failed while a call waited (a Ctrl-C): the session
    /// is closed.
    Interrupted(BoxError),
}

impl Error {
    /// The status, if the error is one.
    pub fn status(&self) -> Option<&Status> {
        match self {
            Error::Status(s) => Some(s),
            _ => None,
        }
    }
}

impl From<Status> for Error {
    fn from(s: Status) -> Error {
        Error::Status(s)
    }
}

impl std::fmt::Display for Error {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Error::Invalid(m) | Error::Runtime(m) => f.write_str(m),
            Error::Status(s) => write!(f, "{:?}: {}", s.code(), s.message()),
            Error::Interrupted(e) => write!(f, "interrupted: {e}"),
        }
    }
}

impl std::error::Error for Error {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Error::Status(s) => Some(s),
            Error::Interrupted(e) => Some(e.as_ref()),
            _ => None,
        }
    }
}
