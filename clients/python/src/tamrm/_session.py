"""The synchronous shaping session: one ``Shape`` stream driving a vector of environments."""

from __future__ import annotations

import contextlib
import queue
import sys
import threading
from collections.abc import Iterator
from typing import Any

import grpc

from tamrm._batch import StepInput
from tamrm._closing import Closing
from tamrm._errors import SessionClosed, TamrmError, from_rpc_error
from tamrm._proto.tamrm.v1 import shaping_pb2 as pb
from tamrm._stream import SessionCore
from tamrm._types import StepResult

__all__ = ["Session"]

_CLOSE_TIMEOUT = 10.0


class Session(SessionCore[StepResult], Closing):
    """One open ``Shape`` stream shaping ``num_envs`` environments of one task.

    Create it with :meth:`tamrm.Client.session` and use it as a context manager; each
    :meth:`step` is one round trip (one ``StepBatch`` out, one ``ShapedBatch`` back) on
    the stream, which stays open until :meth:`close`. A session is not thread-safe: use
    one per thread (several sessions may shape on the same task at once). A session
    pickles as a new session of the same task on (the unpickled copy of) its client,
    e.g. in a ``SubprocVecEnv`` worker.

    Attributes:
        task_id: The task shaped.
        num_envs: Number of environments (rows of a full step).
        task: The task as the server returned it when the stream opened (its ``config``
            tells whether actions are discrete).
    """

    def _start(self) -> None:
        # Open the stream now, blocking until the server answers ``Open``.
        self._requests: queue.SimpleQueue[pb.ShapeRequest | None] = queue.SimpleQueue()
        self._responses: Any = None
        self._open()

    # -- stream plumbing -------------------------------------------------------------

    def _open(self) -> None:
        requests: queue.SimpleQueue[pb.ShapeRequest | None] = queue.SimpleQueue()

        def request_iter() -> Iterator[pb.ShapeRequest]:
            while True:
                item = requests.get()
                if item is None:
                    return
                yield item

        requests.put(self._open_request())
        self._requests = requests
        self._responses = self._stub.Shape(request_iter(), metadata=self._metadata)
        self._opened(self._receive())

    def _receive(self) -> pb.ShapeResponse:
        try:
            resp: pb.ShapeResponse = next(self._responses)
            return resp
        except grpc.RpcError as exc:
            err: TamrmError = from_rpc_error(exc)
        except StopIteration:
            err = TamrmError("the server ended the Shape stream unexpectedly")
        except KeyboardInterrupt:
            # Ctrl-C while waiting for the server: the stream's state is unknown, end it
            # now (so that close() has nothing to wait for) and let the interrupt go on.
            self._abort(SessionClosed(f"the session on task {self.task_id!r} was interrupted"))
            raise
        self._abort(err)
        raise err from None

    def _abort(self, err: BaseException) -> None:
        self._failed(err)
        self._requests.put(None)
        if self._responses is not None:
            self._responses.cancel()

    def _exchange(self, step: StepInput) -> StepResult:
        prepared = self._prepare(step)
        if isinstance(prepared, StepResult):
            return prepared
        self._requests.put(prepared.request)
        try:
            resp = self._receive()
        except TamrmError as err:
            if self._rejected(err):
                # The batch changed nothing: go on on a new stream with every episode resumed.
                with contextlib.suppress(TamrmError):
                    self._open()
            raise
        try:
            return self._shaped(resp, prepared)
        except TamrmError as err:
            self._abort(err)
            raise

    # -- public API ------------------------------------------------------------------

    def restart(self) -> None:
        """Close the stream and open a new one on the same task.

        Episodes in progress are discarded by the server (SPEC §6: an episode whose
        stream ends before its final step is not stored); every environment starts a
        new episode at its next step. To drop only some environments' episodes, use
        :meth:`abandon`.
        """
        self.close()
        self._open()

    def close(self) -> None:
        """Half-close the stream and wait (briefly) for the server to end it.

        Idempotent. Episodes still in progress are discarded by the server. While a
        ``KeyboardInterrupt`` unwinds (``close`` in a ``finally`` or ``with`` exit after
        Ctrl-C) the stream is cancelled at once instead; a Ctrl-C during the wait cancels
        it too.
        """
        if not self._closing():
            return
        self._requests.put(None)
        responses = self._responses
        if responses is None:
            return
        if isinstance(sys.exc_info()[1], KeyboardInterrupt):
            responses.cancel()
            return
        done = threading.Event()
        responses.add_done_callback(lambda _call: done.set())
        try:
            finished = done.wait(_CLOSE_TIMEOUT)
        except KeyboardInterrupt:
            responses.cancel()
            raise
        if not finished:
            responses.cancel()

    def __del__(self) -> None:
        # An unclosed session: end the request iterator so that the stream half-closes
        # and gRPC's request thread exits (no blocking here; close() is the clean way).
        requests = getattr(self, "_requests", None)
        if requests is not None:
            requests.put(None)

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<tamrm.Session task_id={self.task_id!r} num_envs={self.num_envs} {state}>"
