"""The HTTP/JSON transport: a synchronous and an asyncio client on ``httpx``, results over
Server-Sent Events.

``httpx`` because one library gives both a blocking and an asyncio client with the same
request model, per-phase timeouts (connect, read, write, pool), TLS with a custom CA, and
streamed responses for SSE. Many batches go as one ``application/x-ndjson`` body (one
request, one answer with a result per line), a single batch as a JSON body.
"""

from __future__ import annotations

import json
import ssl
from collections.abc import AsyncIterator, Iterable, Iterator, Mapping
from typing import Any

import httpx

from ._base import AsyncClient, SyncClient, Timestamp, frame_batches, to_seconds
from ._config import (
    DEFAULT_RECONNECT_TIMEOUT,
    DEFAULT_TIMEOUT,
    SSE_SILENCE_TIMEOUT,
    Settings,
    make_settings,
)
from ._convert import reload_from_json, result_from_json, scene_from_json
from ._subscription import LOST_HINT, AsyncSubscription, Subscription
from .errors import (
    CrossviewError,
    ServerError,
    SubscriberLagged,
    Timeout,
    Unavailable,
    error_for_kind,
    error_from_http,
)
from .types import Batch, Boxes, FrameResult, PushAck, ReloadOutcome, Scene

__all__ = ["HttpClient", "AsyncHttpClient"]

NDJSON_MAX_LINES = 1024
"""Batches sent in one JSON Lines body (well under the server's 4 MiB default body limit for
usual detector output)."""

NDJSON_MAX_BYTES = 2 * 1024 * 1024


def _verify(s: Settings) -> ssl.SSLContext | bool:
    if not s.tls:
        return True
    ctx = ssl.create_default_context()
    if s.ca_cert is not None:
        ctx.load_verify_locations(cadata=s.ca_cert.decode())
    return ctx


def _check_settings(s: Settings) -> Settings:
    if s.tls_server_name:
        raise ValueError("tls_server_name is for gRPC only: over HTTP connect by the certificate's name")
    return s


def _client_options(s: Settings) -> dict[str, Any]:
    """The ``httpx.Client`` / ``httpx.AsyncClient`` arguments of a client with settings ``s``
    (checked for HTTP), apart from its transport."""
    _check_settings(s)
    return {
        "base_url": s.base_url, "headers": _headers(s), "verify": _verify(s),
        "timeout": httpx.Timeout(s.timeout), "trust_env": False,
    }


def _headers(s: Settings) -> dict[str, str]:
    h = {"accept": "application/json"}
    if s.api_key:
        h["authorization"] = f"Bearer {s.api_key}"
    return h


def _transport_error(e: httpx.HTTPError, what: str) -> CrossviewError:
    """A failure to talk to the server as the package's exception."""
    if isinstance(e, httpx.TimeoutException):
        if isinstance(e, (httpx.ConnectTimeout, httpx.PoolTimeout)):
            return Unavailable(f"{what}: cannot connect within the timeout ({e!r})", kind="connection")
        return Timeout(f"{what}: no answer within the timeout ({e!r})")
    if isinstance(e, (httpx.ConnectError, httpx.RemoteProtocolError, httpx.ReadError, httpx.WriteError, httpx.CloseError)):
        return Unavailable(f"{what}: {e!r}", kind="connection")
    return ServerError(f"{what}: {e!r}")


def _check(resp: httpx.Response) -> Any:
    """The decoded JSON of a successful answer; the mapped exception otherwise."""
    try:
        body = resp.json() if resp.content else None
    except ValueError:
        body = None
    if resp.status_code >= 400:
        raise error_from_http(resp.status_code, body, resp.text, resp.headers.get("retry-after"))
    if body is None:
        raise ServerError(f"HTTP {resp.status_code}: expected a JSON answer", status=resp.status_code)
    return body


def _chunks(batches: Iterable[Batch]) -> Iterator[list[Batch]]:
    """Consecutive batches of one scene, at most NDJSON_MAX_LINES / ~NDJSON_MAX_BYTES a chunk."""
    chunk: list[Batch] = []
    size = 0
    for b in batches:
        if chunk and (b.scene != chunk[0].scene or len(chunk) >= NDJSON_MAX_LINES or size >= NDJSON_MAX_BYTES):
            yield chunk
            chunk, size = [], 0
        chunk.append(b)
        size += 64 + 40 * len(b.detections)
    if chunk:
        yield chunk


def _ndjson(chunk: list[Batch]) -> bytes:
    return ("\n".join(json.dumps(b.to_json(), separators=(",", ":")) for b in chunk) + "\n").encode()


def _acks_from_ndjson(chunk: list[Batch], body: Any) -> list[PushAck]:
    results = body.get("results") if isinstance(body, dict) else None
    if not isinstance(results, list):
        raise ServerError("unexpected answer to a JSON Lines push: no 'results'")
    by_line: dict[int, Any] = {}
    for r in results:
        if isinstance(r, dict) and isinstance(r.get("line"), int):
            by_line[r["line"]] = r
    acks = []
    for i, b in enumerate(chunk):
        r = by_line.get(i + 1)
        error: CrossviewError | None = None
        if r is None:
            error = ServerError(
                f"the server stopped reading the body at line {body.get('stopped_at_line')} "
                "(too many refused lines) before this batch", kind="not_processed"
            )
        elif not r.get("accepted"):
            err = r.get("error") or {}
            error = error_for_kind(str(err.get("kind") or ""), str(err.get("message") or "refused"))
        placed = r.get("frame_id") if r is not None else None
        frame_id = int(placed) if isinstance(placed, int) else b.frame_id
        acks.append(PushAck(b.scene, b.camera, frame_id, error))
    return acks


def _single_ack(b: Batch, resp: httpx.Response) -> PushAck:
    try:
        _check(resp)
    except CrossviewError as e:
        if e.kind in ("connection", "unauthenticated", "unsupported_media_type", "forbidden", "unavailable"):
            raise
        return PushAck(b.scene, b.camera, b.frame_id, e)
    try:
        placed = resp.json().get("frame_id")
    except ValueError:
        placed = None
    frame_id = int(placed) if isinstance(placed, int) else b.frame_id
    return PushAck(b.scene, b.camera, frame_id, None)


def _associate_body(
    scene: str, frame_id: int, views: Mapping[str, Boxes], timestamp: Timestamp | None = None
) -> dict[str, Any]:
    body: dict[str, Any] = {} if timestamp is None else {"time": to_seconds(timestamp)}
    return body | {
        "frame_id": frame_id,
        "views": [
            {"camera": b.camera, "detections": [d.to_json() for d in b.detections]}
            for b in frame_batches(scene, frame_id, views)
        ],
    }


def _sse_error(data: str) -> CrossviewError:
    """The exception of an SSE ``error`` event: its data is the server's error body
    ``{"error": {"kind", "message", "field"}}`` (plain text from servers before it)."""
    kind, message = "", data
    try:
        err = json.loads(data)["error"]
        kind, message = str(err.get("kind") or ""), str(err.get("message") or data)
    except (ValueError, TypeError, KeyError, AttributeError):
        pass
    lower = message.lower()
    if "fell" in lower and "behind" in lower:
        return SubscriberLagged(message, status=200)
    if not kind:
        kind = "resource_exhausted" if "exhausted" in lower else "internal"
    return error_for_kind(kind, message)


class _SseParser:
    """Server-Sent Events, line by line: ``feed`` returns a frame result for each ``frame``
    event, raises for an ``error`` event (the server dropped this subscriber)."""

    def __init__(self, scene: str) -> None:
        self.scene = scene
        self._event = ""
        self._data: list[str] = []

    def feed(self, line: str) -> FrameResult | None:
        if line == "":
            event, data = self._event or "message", "\n".join(self._data)
            self._event, self._data = "", []
            if event == "frame" and data:
                return result_from_json(json.loads(data))
            if event == "error":
                raise _sse_error(data)
            return None
        if line.startswith(":"):
            return None  # keep-alive comment
        name, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if name == "event":
            self._event = value
        elif name == "data":
            self._data.append(value)
        return None


def _quote(segment: str) -> str:
    from urllib.parse import quote

    return quote(segment, safe="")


class HttpClient(SyncClient):
    """A synchronous crossview client over HTTP/JSON (results over SSE).

    Same arguments as ``GrpcClient``, plus ``http_transport``: an ``httpx`` transport of your own
    (socket options, proxies; it then also carries the TLS settings); ``timeout`` bounds connecting and every read and write of
    a request. A subscription reads with a ``SSE_SILENCE_TIMEOUT`` bound (the server sends a
    keep-alive every 15 s), so a dead connection is noticed. Thread-safe (httpx's pool).
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
        http_transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.settings = make_settings(
            address, api_key=api_key, tls=tls, ca_cert=ca_cert,
            tls_server_name=tls_server_name, timeout=timeout,
        )
        self._http = httpx.Client(**_client_options(self.settings), transport=http_transport)

    def _t(self, timeout: float | None) -> httpx.Timeout:
        return httpx.Timeout(self.settings.timeout if timeout is None else timeout)

    def _request(self, method: str, path: str, what: str, timeout: float | None, **kw: Any) -> Any:
        try:
            resp = self._http.request(method, path, timeout=self._t(timeout), **kw)
        except httpx.HTTPError as e:
            raise _transport_error(e, what) from None
        return _check(resp)

    def wait_ready(self, timeout: float = 30.0) -> None:
        import time

        deadline = time.monotonic() + timeout
        last: Exception | None = None
        while time.monotonic() < deadline:
            try:
                r = self._http.get("/readyz", timeout=httpx.Timeout(min(2.0, timeout)))
                if r.status_code == 200:
                    return
                last = ServerError(f"/readyz answered {r.status_code}")
            except httpx.HTTPError as e:
                last = e
            time.sleep(0.05)
        raise Unavailable(f"server at {self.settings.base_url} not ready within {timeout:g} s ({last!r})")

    def scenes(self, *, timeout: float | None = None) -> list[Scene]:
        body = self._request("GET", "/v1/scenes", "scenes", timeout)
        return [scene_from_json(s) for s in body.get("scenes") or ()]

    def scene(self, name: str, *, timeout: float | None = None) -> Scene:
        return scene_from_json(self._request("GET", f"/v1/scenes/{_quote(name)}", "scene", timeout))

    def reload(self, *, timeout: float | None = None) -> list[ReloadOutcome]:
        return reload_from_json(self._request("POST", "/v1/admin/reload", "reload", timeout, json={}))

    def associate(
        self,
        scene: str,
        frame_id: int,
        views: Mapping[str, Boxes],
        *,
        timestamp: Timestamp | None = None,
        timeout: float | None = None,
    ) -> FrameResult:
        body = _associate_body(scene, frame_id, views, timestamp)
        return result_from_json(
            self._request("POST", f"/v1/scenes/{_quote(scene)}/associate", "associate", timeout, json=body)
        )

    def push_many(self, batches: Iterable[Batch], *, timeout: float | None = None) -> list[PushAck]:
        acks: list[PushAck] = []
        for chunk in _chunks(batches):
            path = f"/v1/scenes/{_quote(chunk[0].scene)}/batches"
            try:
                if len(chunk) == 1:
                    resp = self._http.post(path, json=chunk[0].to_json(), timeout=self._t(timeout))
                    acks.append(_single_ack(chunk[0], resp))
                    continue
                resp = self._http.post(
                    path, content=_ndjson(chunk), timeout=self._t(timeout),
                    headers={"content-type": "application/x-ndjson"},
                )
            except httpx.HTTPError as e:
                raise _transport_error(e, "push") from None
            acks.extend(_acks_from_ndjson(chunk, _check(resp)))
        return acks

    def subscribe(
        self,
        scene: str,
        *,
        reconnect: bool = True,
        reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT,
        timeout: float | None = None,
    ) -> Subscription:
        """The scene's frame results (SSE) as an iterator; see ``Subscription``."""

        def connect(t: float) -> _HttpSource:
            return _HttpSource(self._http, scene, t)

        return Subscription(
            scene, connect, timeout=self.settings.timeout if timeout is None else timeout,
            reconnect=reconnect, reconnect_timeout=reconnect_timeout,
        )

    def close(self) -> None:
        self._http.close()


class _HttpSource:
    """One SSE response; the constructor returns once the server answered (subscribed)."""

    def __init__(self, http: httpx.Client, scene: str, timeout: float) -> None:
        self._parser = _SseParser(scene)
        t = httpx.Timeout(timeout, read=SSE_SILENCE_TIMEOUT)
        req = http.build_request("GET", f"/v1/scenes/{_quote(scene)}/events", timeout=t,
                                 headers={"accept": "text/event-stream"})
        try:
            self._resp = http.send(req, stream=True)
        except httpx.HTTPError as e:
            raise _transport_error(e, "subscribe") from None
        if self._resp.status_code != 200:
            self._resp.read()
            self._resp.close()
            _check(self._resp)
        self._lines = self._resp.iter_lines()

    def __next__(self) -> FrameResult:
        try:
            for line in self._lines:
                r = self._parser.feed(line)
                if r is not None:
                    return r
        except httpx.HTTPError as e:
            raise Unavailable(f"{LOST_HINT}: {e!r}", kind="connection") from None
        except CrossviewError:
            self.close()
            raise
        raise StopIteration

    def close(self) -> None:
        self._resp.close()


class _AsyncHttpSource:
    def __init__(self, resp: httpx.Response, scene: str) -> None:
        self._resp = resp
        self._parser = _SseParser(scene)
        self._lines: AsyncIterator[str] = resp.aiter_lines()

    @classmethod
    async def open(cls, http: httpx.AsyncClient, scene: str, timeout: float) -> _AsyncHttpSource:
        t = httpx.Timeout(timeout, read=SSE_SILENCE_TIMEOUT)
        req = http.build_request("GET", f"/v1/scenes/{_quote(scene)}/events", timeout=t,
                                 headers={"accept": "text/event-stream"})
        try:
            resp = await http.send(req, stream=True)
        except httpx.HTTPError as e:
            raise _transport_error(e, "subscribe") from None
        if resp.status_code != 200:
            await resp.aread()
            await resp.aclose()
            _check(resp)
        return cls(resp, scene)

    async def __anext__(self) -> FrameResult:
        try:
            async for line in self._lines:
                r = self._parser.feed(line)
                if r is not None:
                    return r
        except httpx.HTTPError as e:
            raise Unavailable(f"{LOST_HINT}: {e!r}", kind="connection") from None
        except CrossviewError:
            await self.aclose()
            raise
        raise StopAsyncIteration

    async def aclose(self) -> None:
        await self._resp.aclose()


class AsyncHttpClient(AsyncClient):
    """An asyncio crossview client over HTTP/JSON (``httpx.AsyncClient``); same arguments and
    methods as :class:`HttpClient`, as coroutines."""

    def __init__(
        self,
        address: str,
        *,
        api_key: str | None = None,
        tls: bool | None = None,
        ca_cert: Any = None,
        tls_server_name: str | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        http_transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        self.settings = make_settings(
            address, api_key=api_key, tls=tls, ca_cert=ca_cert,
            tls_server_name=tls_server_name, timeout=timeout,
        )
        self._http = httpx.AsyncClient(**_client_options(self.settings), transport=http_transport)

    def _t(self, timeout: float | None) -> httpx.Timeout:
        return httpx.Timeout(self.settings.timeout if timeout is None else timeout)

    async def _request(self, method: str, path: str, what: str, timeout: float | None, **kw: Any) -> Any:
        try:
            resp = await self._http.request(method, path, timeout=self._t(timeout), **kw)
        except httpx.HTTPError as e:
            raise _transport_error(e, what) from None
        return _check(resp)

    async def wait_ready(self, timeout: float = 30.0) -> None:
        """Waits until ``/readyz`` answers 200, at most ``timeout`` s (else ``Unavailable``)."""
        import asyncio
        import time

        deadline = time.monotonic() + timeout
        last: Exception | None = None
        while time.monotonic() < deadline:
            try:
                r = await self._http.get("/readyz", timeout=httpx.Timeout(min(2.0, timeout)))
                if r.status_code == 200:
                    return
                last = ServerError(f"/readyz answered {r.status_code}")
            except httpx.HTTPError as e:
                last = e
            await asyncio.sleep(0.05)
        raise Unavailable(f"server at {self.settings.base_url} not ready within {timeout:g} s ({last!r})")

    async def scenes(self, *, timeout: float | None = None) -> list[Scene]:
        """Every served scene."""
        body = await self._request("GET", "/v1/scenes", "scenes", timeout)
        return [scene_from_json(s) for s in body.get("scenes") or ()]

    async def scene(self, name: str, *, timeout: float | None = None) -> Scene:
        """One scene; ``NotFound`` when unknown."""
        return scene_from_json(await self._request("GET", f"/v1/scenes/{_quote(name)}", "scene", timeout))

    async def reload(self, *, timeout: float | None = None) -> list[ReloadOutcome]:
        """Re-reads every model file on the server."""
        return reload_from_json(await self._request("POST", "/v1/admin/reload", "reload", timeout, json={}))

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
        body = _associate_body(scene, frame_id, views, timestamp)
        return result_from_json(
            await self._request("POST", f"/v1/scenes/{_quote(scene)}/associate", "associate", timeout, json=body)
        )

    async def push_many(self, batches: Iterable[Batch], *, timeout: float | None = None) -> list[PushAck]:
        """Pushes many batches (JSON Lines bodies), in order; refusals in ``ack.error``."""
        acks: list[PushAck] = []
        for chunk in _chunks(batches):
            path = f"/v1/scenes/{_quote(chunk[0].scene)}/batches"
            try:
                if len(chunk) == 1:
                    resp = await self._http.post(path, json=chunk[0].to_json(), timeout=self._t(timeout))
                    acks.append(_single_ack(chunk[0], resp))
                    continue
                resp = await self._http.post(
                    path, content=_ndjson(chunk), timeout=self._t(timeout),
                    headers={"content-type": "application/x-ndjson"},
                )
            except httpx.HTTPError as e:
                raise _transport_error(e, "push") from None
            acks.extend(_acks_from_ndjson(chunk, _check(resp)))
        return acks

    async def subscribe(
        self,
        scene: str,
        *,
        reconnect: bool = True,
        reconnect_timeout: float = DEFAULT_RECONNECT_TIMEOUT,
        timeout: float | None = None,
    ) -> AsyncSubscription:
        """The scene's frame results (SSE) as an async iterator; returns once subscribed."""

        async def connect(t: float) -> _AsyncHttpSource:
            return await _AsyncHttpSource.open(self._http, scene, t)

        sub = AsyncSubscription(scene, connect, reconnect=reconnect, reconnect_timeout=reconnect_timeout)
        return await sub._start(self.settings.timeout if timeout is None else timeout)

    async def close(self) -> None:
        """Closes the connection pool."""
        await self._http.aclose()
