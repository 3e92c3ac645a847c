"""Exceptions raised by the tamrm client.

Every error the server returns is raised as a subclass of :class:`TamrmError` chosen by
its gRPC status code; the server's message (which names the offending field) is the
exception's message and is kept in :attr:`TamrmError.details`.
"""

from __future__ import annotations

import enum

__all__ = [
    "AlreadyExists",
    "DeadlineExceeded",
    "FailedPrecondition",
    "InvalidArgument",
    "ResourceExhausted",
    "SessionClosed",
    "StatusCode",
    "TamrmError",
    "TaskNotFound",
    "Unavailable",
    "from_native",
    "from_status",
]


class StatusCode(enum.Enum):
    """The gRPC status codes (their numbers are the wire values)."""

    OK = 0
    CANCELLED = 1
    UNKNOWN = 2
    INVALID_ARGUMENT = 3
    DEADLINE_EXCEEDED = 4
    NOT_FOUND = 5
    ALREADY_EXISTS = 6
    PERMISSION_DENIED = 7
    RESOURCE_EXHAUSTED = 8
    FAILED_PRECONDITION = 9
    ABORTED = 10
    OUT_OF_RANGE = 11
    UNIMPLEMENTED = 12
    INTERNAL = 13
    UNAVAILABLE = 14
    DATA_LOSS = 15
    UNAUTHENTICATED = 16


class TamrmError(Exception):
    """Base class of every error raised for a failed server call.

    Attributes:
        code: The gRPC status code of the failure (``None`` for client-side errors such
            as :class:`SessionClosed`).
        details: The server's message, which names the offending field or task.
    """

    code: StatusCode | None = None

    def __init__(self, details: str, code: StatusCode | None = None) -> None:
        super().__init__(details)
        self.details = details
        if code is not None:
            self.code = code

    def __str__(self) -> str:
        name = self.code.name if self.code is not None else "ERROR"
        return f"{name}: {self.details}"


class InvalidArgument(TamrmError):
    """The server rejected a request as malformed (``INVALID_ARGUMENT``).

    Raised for out-of-range configuration values, bad task ids, out-of-range actions,
    non-finite numbers, wrong column lengths and similar; the message names the field.
    """

    code = StatusCode.INVALID_ARGUMENT


class TaskNotFound(TamrmError):
    """The task does not exist, or was deleted while a session was open (``NOT_FOUND``)."""

    code = StatusCode.NOT_FOUND


class AlreadyExists(TamrmError):
    """A task with this id exists with a different configuration (``ALREADY_EXISTS``)."""

    code = StatusCode.ALREADY_EXISTS


class ResourceExhausted(TamrmError):
    """A configured server limit was reached (``RESOURCE_EXHAUSTED``)."""

    code = StatusCode.RESOURCE_EXHAUSTED


class FailedPrecondition(TamrmError):
    """The request is valid but the server's state does not allow it (``FAILED_PRECONDITION``)."""

    code = StatusCode.FAILED_PRECONDITION


class Unavailable(TamrmError):
    """The server could not be reached or is shutting down (``UNAVAILABLE``)."""

    code = StatusCode.UNAVAILABLE


class DeadlineExceeded(TamrmError):
    """The call's timeout expired before the server answered (``DEADLINE_EXCEEDED``)."""

    code = StatusCode.DEADLINE_EXCEEDED


class Unauthenticated(TamrmError):
    """The server needs an API key and got none, or an unknown one (``UNAUTHENTICATED``).

    Pass ``api_key=`` or set ``TAMRM_API_KEY``.
    """

    code = StatusCode.UNAUTHENTICATED


class PermissionDenied(TamrmError):
    """The API key's role does not allow this call (``PERMISSION_DENIED``).

    Readers may only read; writers may not delete tasks or reset pools.
    """

    code = StatusCode.PERMISSION_DENIED


class SessionClosed(TamrmError):
    """A session was used after it was closed or after its stream failed.

    ``__cause__`` holds the error that ended the stream, if any.
    """


_BY_CODE: dict[StatusCode, type[TamrmError]] = {
    cls.code: cls
    for cls in (
        InvalidArgument,
        TaskNotFound,
        AlreadyExists,
        ResourceExhausted,
        FailedPrecondition,
        Unavailable,
        DeadlineExceeded,
        Unauthenticated,
        PermissionDenied,
    )
    if cls.code is not None
}


def from_native(err: BaseException) -> TamrmError:
    """Translate the native extension's ``StatusError(code, message)`` to a :class:`TamrmError`."""
    number, message = err.args if len(err.args) == 2 else (2, str(err))
    try:
        code = StatusCode(int(number))
    except ValueError:
        code = StatusCode.UNKNOWN
    return from_status(code, str(message))


def from_status(code: StatusCode, details: str | None) -> TamrmError:
    """Build the :class:`TamrmError` subclass for a status code and message."""
    cls = _BY_CODE.get(code, TamrmError)
    return cls(details or code.name, code)
