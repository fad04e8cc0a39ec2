"""Subscriptions: an iterator (or async iterator) of frame results that survives a lost
connection by resubscribing, for every transport.

Semantics, the same over gRPC and HTTP (SSE):

- ``subscribe()`` returns once the server has registered the subscription, so every result
  published after it returns is delivered (in frame-id order).
- The connection is lost or the server shuts down (it ends every subscription then): with
  ``reconnect=True`` (the default) the iterator resubscribes, waiting up to
  ``reconnect_timeout`` seconds for the server to come back, and goes on. Results published
  while it was disconnected are not replayed (the server keeps none): look at ``frame_id``, and
  at ``reconnects``. If the server is not back in time, ``Unavailable`` is raised. With
  ``reconnect=False`` the loss raises ``Unavailable`` at once.
- The server drops a subscriber that falls more than its ``--subscriber-buffer`` results behind:
  the iterator raises ``SubscriberLagged`` (never resubscribes silently: results were lost
  because *this consumer* is too slow). A subscriber that takes no result for the server's
  ``--subscriber-stall-timeout`` has its connection closed: that arrives as a lost connection.
- Any other error (unknown scene, wrong API key) raises its exception.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from typing import Protocol

from .errors import CrossviewError, Timeout, Unavailable
from .types import FrameResult

log = logging.getLogger("crossview_client")

LOST_HINT = (
    "connection to the server lost (the server restarted or shut down, the network failed, or "
    "this subscriber stalled: it took no result for the server's --subscriber-stall-timeout)"
)


class Source(Protocol):
    """One server-side subscription: its results, then StopIteration when the server ends it."""

    def __next__(self) -> FrameResult: ...

    def close(self) -> None: ...


class AsyncSource(Protocol):
    """The async counterpart of :class:`Source` (``StopAsyncIteration`` at the end)."""

    def __anext__(self) -> Awaitable[FrameResult]: ...

    async def aclose(self) -> None: ...


def _backoff(attempt: int) -> float:
    return float(min(0.05 * 2**attempt, 1.0))


class Subscription(Iterator[FrameResult]):
    """The results of one scene as an iterator (see the module's notes on reconnection)."""

    def __init__(
        self,
        scene: str,
        connect: Callable[[float], Source],
        *,
        timeout: float,
        reconnect: bool,
        reconnect_timeout: float,
    ) -> None:
        self.scene = scene
        self.reconnects = 0
        """How often the subscription was re-established after a lost connection."""
        self._connect = connect
        self._reconnect = reconnect
        self._reconnect_timeout = reconnect_timeout
        self._closed = False
        self._source: Source | None = connect(timeout)

    def __iter__(self) -> Subscription:
        return self

    def __next__(self) -> FrameResult:
        while True:
            source = self._source
            if self._closed or source is None:
                raise StopIteration
            try:
                return next(source)
            except StopIteration:
                cause: CrossviewError = Unavailable(
                    f"the server ended the subscription to {self.scene!r} (shutting down?)"
                )
            except Unavailable as e:
                cause = e
            if self._closed:
                raise StopIteration
            source.close()
            self._source = None
            if not self._reconnect:
                raise cause
            self._resubscribe(cause)

    def _resubscribe(self, cause: CrossviewError) -> None:
        log.warning("subscription to %r lost (%s); resubscribing", self.scene, cause)
        deadline = time.monotonic() + self._reconnect_timeout
        attempt = 0
        while not self._closed:
            left = deadline - time.monotonic()
            if left <= 0:
                raise Unavailable(
                    f"could not resubscribe to {self.scene!r} within {self._reconnect_timeout:g} s "
                    f"after: {cause.message}"
                ) from cause
            try:
                self._source = self._connect(max(left, 0.05))
                self.reconnects += 1
                return
            except (Unavailable, Timeout) as e:
                log.debug("resubscribe attempt failed: %s", e)
                time.sleep(min(_backoff(attempt), max(deadline - time.monotonic(), 0)))
                attempt += 1

    def close(self) -> None:
        """Ends the subscription (from any thread; a blocked ``next`` then stops)."""
        self._closed = True
        if self._source is not None:
            self._source.close()

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncSubscription(AsyncIterator[FrameResult]):
    """The results of one scene as an async iterator (same semantics as :class:`Subscription`).

    Create it with ``await client.subscribe(scene)``.
    """

    def __init__(
        self,
        scene: str,
        connect: Callable[[float], Awaitable[AsyncSource]],
        *,
        reconnect: bool,
        reconnect_timeout: float,
    ) -> None:
        self.scene = scene
        self.reconnects = 0
        self._connect = connect
        self._reconnect = reconnect
        self._reconnect_timeout = reconnect_timeout
        self._closed = False
        self._source: AsyncSource | None = None

    async def _start(self, timeout: float) -> AsyncSubscription:
        self._source = await self._connect(timeout)
        return self

    def __aiter__(self) -> AsyncSubscription:
        return self

    async def __anext__(self) -> FrameResult:
        while True:
            source = self._source
            if self._closed or source is None:
                raise StopAsyncIteration
            try:
                return await source.__anext__()
            except StopAsyncIteration:
                cause: CrossviewError = Unavailable(
                    f"the server ended the subscription to {self.scene!r} (shutting down?)"
                )
            except Unavailable as e:
                cause = e
            if self._closed:
                raise StopAsyncIteration
            await source.aclose()
            self._source = None
            if not self._reconnect:
                raise cause
            await self._resubscribe(cause)

    async def _resubscribe(self, cause: CrossviewError) -> None:
        log.warning("subscription to %r lost (%s); resubscribing", self.scene, cause)
        deadline = time.monotonic() + self._reconnect_timeout
        attempt = 0
        while not self._closed:
            left = deadline - time.monotonic()
            if left <= 0:
                raise Unavailable(
                    f"could not resubscribe to {self.scene!r} within {self._reconnect_timeout:g} s "
                    f"after: {cause.message}"
                ) from cause
            try:
                self._source = await self._connect(max(left, 0.05))
                self.reconnects += 1
                return
            except (Unavailable, Timeout) as e:
                log.debug("resubscribe attempt failed: %s", e)
                await asyncio.sleep(min(_backoff(attempt), max(deadline - time.monotonic(), 0)))
                attempt += 1

    async def aclose(self) -> None:
        """Ends the subscription."""
        self._closed = True
        if self._source is not None:
            await self._source.aclose()
            self._source = None

    async def __aenter__(self) -> AsyncSubscription:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
