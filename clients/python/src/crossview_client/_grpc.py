"""The gRPC transport (``crossview.v1.Association``): a synchronous client on ``grpc`` and an
asyncio client on ``grpc.aio``, both over the stubs generated from the .proto (``_pb/``).

Pushes go through one long-lived bidirectional ``Push`` call per client: each batch is one
message, each ack comes back in order, so many batches can be in flight at once. When that
call breaks (the server restarted), the batches in flight fail with ``Unavailable`` and the
next push opens a new call, waiting up to its timeout for the server to be reachable.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import queue
import threading
from collections.abc import AsyncIterator, Iterable, Iterator, Mapping
from typing import Any, cast

import grpc
import grpc.aio

from ._base import AsyncClient, SyncClient, Timestamp, frame_batches, to_seconds
from ._config import DEFAULT_RECONNECT_TIMEOUT, DEFAULT_TIMEOUT, Settings, make_settings
from ._convert import (
    ack_from_pb,
    batch_to_pb,
    detection_to_pb,
    reload_from_pb,
    result_from_pb,
    scene_from_pb,
    timestamp_to_pb,
)
from ._pb import crossview_pb2 as pb
from ._pb import crossview_pb2_grpc as rpc
from ._subscription import LOST_HINT, AsyncSubscription, Subscription
from .errors import CrossviewError, Timeout, Unavailable, error_from_grpc
from .types import Batch, Boxes, FrameResult, PushAck, ReloadOutcome, Scene

__all__ = ["GrpcClient", "AsyncGrpcClient"]

DEFAULT_MAX_IN_FLIGHT = 512
_CHANNEL_OPTIONS: list[tuple[str, Any]] = [
    # Notice a dead peer on long-lived calls (Subscribe, Push) within ~30 s.
    ("grpc.keepalive_time_ms", 20_000),
    ("grpc.keepalive_timeout_ms", 10_000),
    # Come back quickly after a server restart (the default backoff grows to 120 s).
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.min_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 1_000),
    ("grpc.max_receive_message_length", 64 * 1024 * 1024),
    ("grpc.enable_http_proxy", 0),
]


def _options(s: Settings, extra: Iterable[tuple[str, Any]] = ()) -> list[tuple[str, Any]]:
    opts = list(_CHANNEL_OPTIONS) + list(extra)
    if s.tls_server_name:
        opts.append(("grpc.ssl_target_name_override", s.tls_server_name))
    return opts


def _credentials(s: Settings) -> grpc.ChannelCredentials:
    return grpc.ssl_channel_credentials(root_certificates=s.ca_cert)


def _open_channel(module: Any, s: Settings, extra: Iterable[tuple[str, Any]]) -> Any:
    """A channel of ``module`` (``grpc`` or ``grpc.aio``) to ``s.target``: TLS when ``s.tls``."""
    if s.tls:
        return module.secure_channel(s.target, _credentials(s), options=_options(s, extra))
    return module.insecure_channel(s.target, options=_options(s, extra))


def map_rpc_error(e: grpc.RpcError, *, where: str = "") -> CrossviewError:
    """A failed gRPC call as the package's exception (connection failures as Unavailable)."""
    call = cast(grpc.Call, e)
    code = call.code()
    details = call.details() or ""
    name = code.name if code is not None else "UNKNOWN"
    if name == "UNAVAILABLE":
        return Unavailable(f"{where}{details or 'server unavailable'}", status=name)
    if name == "DEADLINE_EXCEEDED" and "Deadline Exceeded" in details:
        return Timeout(f"{where}no answer within the timeout", status=name)
    kind, field = _error_metadata(call.trailing_metadata())
    return error_from_grpc(name, details, kind, field)


def _error_metadata(meta: Any) -> tuple[str, str | None]:
    """The server's error kind and field from a status's trailing metadata (empty when absent:
    a server from before they were sent, or an error made by the gRPC library itself)."""
    kind, field = "", None
    for key, value in meta or ():
        if key == "crossview-error-kind":
            kind = str(value)
        elif key == "crossview-error-field":
            field = str(value)
    return kind, field


def _metadata(s: Settings) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {s.api_key}"),) if s.api_key else ()


def _associate_request(
    scene: str, frame_id: int, views: Mapping[str, Boxes], timestamp: Timestamp | None
) -> pb.AssociateRequest:
    batches = frame_batches(scene, frame_id, views)
    req = pb.AssociateRequest(
        scene=scene,
        frame_id=frame_id,
        views=[
            pb.CameraView(camera=b.camera, detections=[detection_to_pb(d) for d in b.detections])
            for b in batches
        ],
    )
    if timestamp is not None:
        req.time.CopyFrom(timestamp_to_pb(to_seconds(timestamp)))
    return req


class _PushCall:
    """One open ``Push`` call: batches queued in, acks resolved in order by a reader thread."""

    def __init__(self, stub: rpc.AssociationStub, metadata: tuple[tuple[str, str], ...]) -> None:
        self._requests: queue.SimpleQueue[pb.Batch | None] = queue.SimpleQueue()
        self._pending: collections.deque[concurrent.futures.Future[PushAck]] = collections.deque()
        self._lock = threading.Lock()
        self.broken: CrossviewError | None = None
        self._call = stub.Push(self._messages(), metadata=metadata)
        self._reader = threading.Thread(target=self._read, name="crossview-push-acks", daemon=True)
        self._reader.start()

    def _messages(self) -> Iterator[pb.Batch]:
        while True:
            m = self._requests.get()
            if m is None:
                return
            yield m

    def submit(self, batch: pb.Batch) -> concurrent.futures.Future[PushAck]:
        fut: concurrent.futures.Future[PushAck] = concurrent.futures.Future()
        with self._lock:
            if self.broken is not None:
                raise self.broken
            self._pending.append(fut)
            self._requests.put(batch)
        return fut

    def _read(self) -> None:
        err: CrossviewError
        try:
            for ack in cast(Iterator[pb.BatchAck], self._call):
                with self._lock:
                    fut = self._pending.popleft() if self._pending else None
                if fut is not None and not fut.done():
                    fut.set_result(ack_from_pb(ack))
            err = Unavailable("the server ended the push stream (shutting down?)")
        except grpc.RpcError as e:
            err = map_rpc_error(e, where="push: ")
        except Exception as e:  # a bug here must not leave pushes waiting forever
            err = CrossviewError(f"push stream reader failed: {e!r}")
        self.fail(err)

    def fail(self, err: CrossviewError) -> None:
        """Marks the call broken and fails every batch still waiting for its ack."""
        with self._lock:
            if self.broken is None:
                self.broken = err
            pending = list(self._pending)
            self._pending.clear()
        for fut in pending:
            if not fut.done():
                fut.set_exception(err)

    def close(self) -> None:
        self._requests.put(None)
        self._call.cancel()
        self.fail(Unavailable("client closed"))


class GrpcClient(SyncClient):
    """A synchronous crossview client over gRPC.

    ``address``: ``host:port``. ``api_key``: the server's ``--api-key``. ``tls`` / ``ca_cert``
    (PEM bytes, string or path) / ``tls_server_name``: TLS to a server with ``--tls-cert``.
    ``timeout``: the default bound, in seconds, of every call (connecting included); each
    method also takes its own. ``max_in_flight``: batches ``push_many`` keeps unacknowledged.
    ``channel_options``: further ``grpc`` channel arguments (after this client's defaults).
    Thread-safe.
    """

    def __init__(
        self,
        address: str,
        *,
        api_key: str | None = None,
        tls: bool | None = None,
        ca_cert: Any = None,
        tls_server_name: str | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        max_in_flight: int = DEFAULT_MAX_IN_FLIGHT,
        channel_options: Iterable[tuple[str, Any]] = (),
    ) -> None:
        self.settings = make_settings(
            address, api_key=api_key, tls=tls, ca_cert=ca_cert,
            tls_server_name=tls_server_name, timeout=timeout,
        )
        s = self.settings
        self._channel: grpc.Channel = _open_channel(grpc, s, channel_options)
        self._stub = rpc.AssociationStub(self._channel)  # type: ignore[no-untyped-call]
        self._health = self._channel.unary_unary(
            "/grpc.health.v1.Health/Check",
            request_serializer=lambda b: b,
            response_deserializer=lambda b: b,
        )
        self._md = _metadata(s)
        self._max_in_flight = max(1, max_in_flight)
        self._push_lock = threading.Lock()
        self._push_call: _PushCall | None = None

    def _t(self, timeout: float | None) -> float:
        return self.settings.timeout if timeout is None else timeout

    def _ready(self, timeout: float) -> None:
        """Waits (at most ``timeout``) until the server answers a health check.

        A gRPC call rather than ``grpc.channel_ready_future``, whose polling thread outlives
        it and fails noisily when the channel is closed."""
        try:
            self._health(b"", timeout=timeout, wait_for_ready=True)
        except grpc.RpcError as e:
            if cast(grpc.Call, e).code() in (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.UNAVAILABLE):
                raise Unavailable(
                    f"cannot connect to {self.settings.target} within {timeout:g} s", status="UNAVAILABLE"
                ) from None
            # Any other answer (e.g. UNIMPLEMENTED) still means the server is there.

    def wait_ready(self, timeout: float = 30.0) -> None:
        self._ready(timeout)

    def _unary(self, method: Any, request: Any, timeout: float | None) -> Any:
        t = self._t(timeout)
        try:
            return method(request, timeout=t, metadata=self._md, wait_for_ready=True)
        except grpc.RpcError as e:
            err = map_rpc_error(e)
            if isinstance(err, Timeout):
                self._ready(0.2)  # raises Unavailable when the server is not reachable at all
            raise err from None

    def scenes(self, *, timeout: float | None = None) -> list[Scene]:
        resp = self._unary(self._stub.ListScenes, pb.ListScenesRequest(), timeout)
        return [scene_from_pb(s) for s in resp.scenes]

    def scene(self, name: str, *, timeout: float | None = None) -> Scene:
        return scene_from_pb(self._unary(self._stub.GetScene, pb.GetSceneRequest(scene=name), timeout))

    def reload(self, *, timeout: float | None = None) -> list[ReloadOutcome]:
        return reload_from_pb(self._unary(self._stub.Reload, pb.ReloadRequest(), timeout))

    def associate(
        self,
        scene: str,
        frame_id: int,
        views: Mapping[str, Boxes],
        *,
        timestamp: Timestamp | None = None,
        timeout: float | None = None,
    ) -> FrameResult:
        req = _associate_request(scene, frame_id, views, timestamp)
        return result_from_pb(self._unary(self._stub.Associate, req, timeout))

    def _call_for_push(self, timeout: float) -> _PushCall:
        with self._push_lock:
            call = self._push_call
            if call is None or call.broken is not None:
                self._ready(timeout)
                call = self._push_call = _PushCall(self._stub, self._md)
            return call

    def push_many(self, batches: Iterable[Batch], *, timeout: float | None = None) -> list[PushAck]:
        t = self._t(timeout)
        acks: list[PushAck] = []
        window: collections.deque[concurrent.futures.Future[PushAck]] = collections.deque()
        call: _PushCall | None = None

        def settle_oldest() -> None:
            fut = window.popleft()
            try:
                acks.append(fut.result(timeout=t))
            except concurrent.futures.TimeoutError:
                # A call that does not ack in time is abandoned: the next push opens another.
                assert call is not None
                call.fail(Timeout(f"push: no ack within {t:g} s"))
                call.close()
                raise Timeout(f"push: no ack within {t:g} s") from None

        for b in batches:
            if call is None or call.broken is not None:
                call = self._call_for_push(t)
            window.append(call.submit(batch_to_pb(b)))
            if len(window) >= self._max_in_flight:
                settle_oldest()
        while window:
            settle_oldest()
        return acks

    def subscribe(
        self,
        scene: str,
        *,
        reconnect: bool = True,
        reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT,
        timeout: float | None = None,
    ) -> Subscription:
        """The scene's frame results as an iterator; see ``crossview_client.Subscription`` for
        what happens when the connection is lost or the subscriber falls behind."""

        def connect(t: float) -> _GrpcSource:
            self._ready(t)
            call = self._stub.Subscribe(pb.SubscribeRequest(scene=scene), metadata=self._md)
            return _GrpcSource(call, t)

        return Subscription(
            scene, connect, timeout=self._t(timeout), reconnect=reconnect,
            reconnect_timeout=reconnect_timeout,
        )

    def close(self) -> None:
        with self._push_lock:
            if self._push_call is not None:
                self._push_call.close()
                self._push_call = None
        self._channel.close()


class _GrpcSource:
    """One ``Subscribe`` call; the constructor waits (at most ``timeout``) for the server to
    accept it: its response headers come once the subscription is registered."""

    def __init__(self, call: Any, timeout: float) -> None:
        self._call = call
        done = threading.Event()
        call.add_done_callback(lambda *_: done.set())
        headers: list[object] = []
        waiter = threading.Thread(target=lambda: headers.append(call.initial_metadata()), daemon=True)
        waiter.start()
        waiter.join(timeout)
        if waiter.is_alive():
            call.cancel()
            raise Timeout(f"subscribe: the server did not accept the subscription within {timeout:g} s")
        if done.is_set() and call.code() is not None and call.code() != grpc.StatusCode.OK:
            raise map_rpc_error(call, where="subscribe: ")

    def __next__(self) -> FrameResult:
        try:
            return result_from_pb(next(self._call))
        except grpc.RpcError as e:
            err = map_rpc_error(e)
            if isinstance(err, Unavailable):
                raise Unavailable(f"{LOST_HINT}: {err.message}", status=err.status) from None
            raise err from None

    def close(self) -> None:
        self._call.cancel()


class _AsyncGrpcSource:
    def __init__(self, call: Any) -> None:
        self._call = call
        self._it: AsyncIterator[pb.FrameResult] = call.__aiter__()

    @classmethod
    async def open(cls, call: Any, timeout: float) -> _AsyncGrpcSource:
        try:
            await asyncio.wait_for(call.initial_metadata(), timeout)
        except asyncio.TimeoutError:
            call.cancel()
            raise Timeout(f"subscribe: the server did not accept the subscription within {timeout:g} s") from None
        except grpc.RpcError as e:
            raise map_rpc_error(e, where="subscribe: ") from None
        if call.done():
            code = await call.code()
            if code != grpc.StatusCode.OK:
                kind, field = _error_metadata(await call.trailing_metadata())
                raise error_from_grpc(code.name, await call.details() or "", kind, field)
        return cls(call)

    async def __anext__(self) -> FrameResult:
        try:
            return result_from_pb(await self._it.__anext__())
        except grpc.RpcError as e:
            err = map_rpc_error(e)
            if isinstance(err, Unavailable):
                raise Unavailable(f"{LOST_HINT}: {err.message}", status=err.status) from None
            raise err from None

    async def aclose(self) -> None:
        self._call.cancel()


class _AsyncPushCall:
    """One open ``Push`` call for the asyncio client: writes under a lock, acks resolved in
    order by a reader task."""

    def __init__(self, stub: rpc.AssociationStub, metadata: tuple[tuple[str, str], ...]) -> None:
        self._call: Any = stub.Push(metadata=metadata)
        self._pending: collections.deque[asyncio.Future[PushAck]] = collections.deque()
        self._write_lock = asyncio.Lock()
        self.broken: CrossviewError | None = None
        self._reader = asyncio.get_running_loop().create_task(self._read())

    async def submit(self, batch: pb.Batch) -> asyncio.Future[PushAck]:
        fut: asyncio.Future[PushAck] = asyncio.get_running_loop().create_future()
        async with self._write_lock:
            if self.broken is not None:
                raise self.broken
            self._pending.append(fut)
            try:
                await self._call.write(batch)
            except (grpc.RpcError, asyncio.InvalidStateError) as e:
                err = (
                    map_rpc_error(e, where="push: ")
                    if isinstance(e, grpc.RpcError)
                    else Unavailable(f"push: the push stream is closed: {e}")
                )
                self.fail(err)
                raise err from None
        return fut

    async def _read(self) -> None:
        err: CrossviewError
        try:
            while True:
                ack = await self._call.read()
                if ack is grpc.aio.EOF:  # type: ignore[attr-defined]
                    err = Unavailable("the server ended the push stream (shutting down?)")
                    break
                fut = self._pending.popleft() if self._pending else None
                if fut is not None and not fut.done():
                    fut.set_result(ack_from_pb(ack))
        except grpc.RpcError as e:
            err = map_rpc_error(e, where="push: ")
        except asyncio.CancelledError:
            err = Unavailable("client closed")
        self.fail(err)

    def fail(self, err: CrossviewError) -> None:
        if self.broken is None:
            self.broken = err
        while self._pending:
            fut = self._pending.popleft()
            if not fut.done():
                fut.set_exception(err)

    async def close(self) -> None:
        self._call.cancel()
        self._reader.cancel()
        self.fail(Unavailable("client closed"))


class AsyncGrpcClient(AsyncClient):
    """An asyncio crossview client over gRPC (``grpc.aio``); same arguments and methods as
    :class:`GrpcClient`, as coroutines. Use it from one event loop."""

    def __init__(
        self,
        address: str,
        *,
        api_key: str | None = None,
        tls: bool | None = None,
        ca_cert: Any = None,
        tls_server_name: str | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        max_in_flight: int = DEFAULT_MAX_IN_FLIGHT,
        channel_options: Iterable[tuple[str, Any]] = (),
    ) -> None:
        self.settings = make_settings(
            address, api_key=api_key, tls=tls, ca_cert=ca_cert,
            tls_server_name=tls_server_name, timeout=timeout,
        )
        s = self.settings
        self._channel: grpc.aio.Channel = _open_channel(grpc.aio, s, channel_options)
        self._stub = rpc.AssociationStub(self._channel)  # type: ignore[no-untyped-call]
        self._md = _metadata(s)
        self._max_in_flight = max(1, max_in_flight)
        self._push_call: _AsyncPushCall | None = None
        self._push_lock = asyncio.Lock()

    def _t(self, timeout: float | None) -> float:
        return self.settings.timeout if timeout is None else timeout

    async def wait_ready(self, timeout: float = 30.0) -> None:
        """Waits until the server is reachable, at most ``timeout`` s (else ``Unavailable``)."""
        try:
            await asyncio.wait_for(self._channel.channel_ready(), timeout)
        except asyncio.TimeoutError:
            raise Unavailable(f"cannot connect to {self.settings.target} within {timeout:g} s") from None

    async def _unary(self, method: Any, request: Any, timeout: float | None) -> Any:
        t = self._t(timeout)
        try:
            return await method(request, timeout=t, metadata=self._md, wait_for_ready=True)
        except grpc.RpcError as e:
            err = map_rpc_error(e)
            if isinstance(err, Timeout) and self._channel.get_state() != grpc.ChannelConnectivity.READY:
                raise Unavailable(
                    f"cannot reach {self.settings.target} within {t:g} s", status="UNAVAILABLE"
                ) from None
            raise err from None

    async def scenes(self, *, timeout: float | None = None) -> list[Scene]:
        """Every served scene."""
        resp = await self._unary(self._stub.ListScenes, pb.ListScenesRequest(), timeout)
        return [scene_from_pb(s) for s in resp.scenes]

    async def scene(self, name: str, *, timeout: float | None = None) -> Scene:
        """One scene; ``NotFound`` when unknown."""
        return scene_from_pb(
            await self._unary(self._stub.GetScene, pb.GetSceneRequest(scene=name), timeout)
        )

    async def reload(self, *, timeout: float | None = None) -> list[ReloadOutcome]:
        """Re-reads every model file on the server."""
        return reload_from_pb(await self._unary(self._stub.Reload, pb.ReloadRequest(), timeout))

    async def associate(
        self,
        scene: str,
        frame_id: int,
        views: Mapping[str, Boxes],
        *,
        timestamp: Timestamp | None = None,
        timeout: float | None = None,
    ) -> FrameResult:
        """Associates one already synchronized frame (``views``: camera → boxes)."""
        req = _associate_request(scene, frame_id, views, timestamp)
        return result_from_pb(await self._unary(self._stub.Associate, req, timeout))

    async def _call_for_push(self, timeout: float) -> _AsyncPushCall:
        async with self._push_lock:
            call = self._push_call
            if call is None or call.broken is not None:
                await self.wait_ready(timeout)
                call = self._push_call = _AsyncPushCall(self._stub, self._md)
            return call

    async def push_many(self, batches: Iterable[Batch], *, timeout: float | None = None) -> list[PushAck]:
        """Pushes many batches, pipelined, in order; one ack each (refusals in ``ack.error``)."""
        t = self._t(timeout)
        acks: list[PushAck] = []
        window: collections.deque[asyncio.Future[PushAck]] = collections.deque()
        call: _AsyncPushCall | None = None

        async def settle_oldest() -> None:
            fut = window.popleft()
            try:
                acks.append(await asyncio.wait_for(asyncio.shield(fut), t))
            except asyncio.TimeoutError:
                assert call is not None
                call.fail(Timeout(f"push: no ack within {t:g} s"))
                await call.close()
                raise Timeout(f"push: no ack within {t:g} s") from None

        for b in batches:
            if call is None or call.broken is not None:
                call = await self._call_for_push(t)
            window.append(await asyncio.wait_for(call.submit(batch_to_pb(b)), t))
            if len(window) >= self._max_in_flight:
                await settle_oldest()
        while window:
            await settle_oldest()
        return acks

    async def subscribe(
        self,
        scene: str,
        *,
        reconnect: bool = True,
        reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT,
        timeout: float | None = None,
    ) -> AsyncSubscription:
        """The scene's frame results as an async iterator (``async for r in await
        client.subscribe(scene)``); returns once the server registered the subscription."""

        async def connect(t: float) -> _AsyncGrpcSource:
            await self.wait_ready(t)
            call = self._stub.Subscribe(pb.SubscribeRequest(scene=scene), metadata=self._md)
            return await _AsyncGrpcSource.open(call, t)

        sub = AsyncSubscription(scene, connect, reconnect=reconnect, reconnect_timeout=reconnect_timeout)
        return await sub._start(self._t(timeout))

    async def close(self) -> None:
        """Closes the channel."""
        if self._push_call is not None:
            await self._push_call.close()
            self._push_call = None
        await self._channel.close(None)
