"""Exceptions raised by the tamrm client.

Every error the server returns is raised as a subclass of :class:`TamrmError` chosen by
its gRPC status code; the server's message (which names the offending field) is the
exception's message and is kept in :attr:`TamrmError.details`.
"""

from __future__ import annotations

import grpc

__all__ = [
    "AlreadyExists",
    "DeadlineExceeded",
    "FailedPrecondition",
    "InvalidArgument",
    "ResourceExhausted",
    "SessionClosed",
    "TamrmError",
    "TaskNotFound",
    "Unavailable",
    "from_native",
    "from_rpc_error",
    "from_status",
]


class TamrmError(Exception):
    """Base class of every error raised for a failed server call.

    Attributes:
        code: The gRPC status code of the failure (``None`` for client-side errors such
            as :class:`SessionClosed`).
        details: The server's message, which names the offending field or task.
    """

    code: grpc.StatusCode | None = None

    def __init__(self, details: str, code: grpc.StatusCode | None = None) -> None:
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

    code = grpc.StatusCode.INVALID_ARGUMENT


class TaskNotFound(TamrmError):
    """The task does not exist, or was deleted while a session was open (``NOT_FOUND``)."""

    code = grpc.StatusCode.NOT_FOUND


class AlreadyExists(TamrmError):
    """A task with this id exists with a different configuration (``ALREADY_EXISTS``)."""

    code = grpc.StatusCode.ALREADY_EXISTS


class ResourceExhausted(TamrmError):
    """A configured server limit was reached (``RESOURCE_EXHAUSTED``)."""

    code = grpc.StatusCode.RESOURCE_EXHAUSTED


class FailedPrecondition(TamrmError):
    """The request is valid but the server's state does not allow it (``FAILED_PRECONDITION``)."""

    code = grpc.StatusCode.FAILED_PRECONDITION


class Unavailable(TamrmError):
    """The server could not be reached or is shutting down (``UNAVAILABLE``)."""

    code = grpc.StatusCode.UNAVAILABLE


class DeadlineExceeded(TamrmError):
    """The call's timeout expired before the server answered (``DEADLINE_EXCEEDED``)."""

    code = grpc.StatusCode.DEADLINE_EXCEEDED


class SessionClosed(TamrmError):
    """A session was used after it was closed or after its stream failed.

    ``__cause__`` holds the error that ended the stream, if any.
    """


_BY_CODE: dict[grpc.StatusCode, type[TamrmError]] = {
    cls.code: cls
    for cls in (
        InvalidArgument,
        TaskNotFound,
        AlreadyExists,
        ResourceExhausted,
        FailedPrecondition,
        Unavailable,
        DeadlineExceeded,
    )
    if cls.code is not None
}


def from_rpc_error(err: grpc.RpcError) -> TamrmError:
    """Translate a ``grpc.RpcError`` (sync or asyncio) into the matching :class:`TamrmError`."""
    code_fn = getattr(err, "code", None)
    details_fn = getattr(err, "details", None)
    code = code_fn() if callable(code_fn) else grpc.StatusCode.UNKNOWN
    details = details_fn() if callable(details_fn) else None
    if not details:
        details = str(err)
    return from_status(code, details)


_BY_NUMBER: dict[int, grpc.StatusCode] = {code.value[0]: code for code in grpc.StatusCode}


def from_native(err: BaseException) -> TamrmError:
    """Translate the native extension's ``StatusError(code, message)`` to a :class:`TamrmError`."""
    number, message = err.args if len(err.args) == 2 else (2, str(err))
    return from_status(_BY_NUMBER.get(int(number), grpc.StatusCode.UNKNOWN), str(message))


def from_status(code: grpc.StatusCode, details: str | None) -> TamrmError:
    """Build the :class:`TamrmError` subclass for a status code and message."""
    cls = _BY_CODE.get(code, TamrmError)
    return cls(details or code.name, code)
