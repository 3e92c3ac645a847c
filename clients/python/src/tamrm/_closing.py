"""``with`` / ``async with`` support for the clients and sessions: both end in ``close()``."""

from __future__ import annotations

from types import TracebackType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing_extensions import Self

__all__ = ["AsyncClosing", "Closing"]


class Closing:
    """A context manager whose exit calls the blocking ``close()``."""

    #: Whether the object is open in a ``with`` block (which then owns it: the wrappers
    #: leave such a session open on their ``close()``).
    _in_with: bool = False

    def close(self) -> None:
        """Release the object's resources (idempotent)."""
        raise NotImplementedError

    def _close_on_exit(self, exc: BaseException | None) -> None:
        """What leaving the ``with`` block does (``exc``: the exception unwinding it)."""
        self.close()

    def __enter__(self) -> Self:
        self._in_with = True
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._in_with = False
        self._close_on_exit(exc)


class AsyncClosing:
    """An async context manager whose exit awaits ``close()``."""

    async def close(self) -> None:
        """Release the object's resources (idempotent)."""
        raise NotImplementedError

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()
