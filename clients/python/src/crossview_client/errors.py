"""One exception hierarchy for every transport.

The server reports an error as an HTTP status plus ``{"error": {"kind", "message", "field"}}``
or as a gRPC status code (and, for a pushed batch, as an ack with ``code``, ``kind`` and
``message``). Both are mapped here onto the same classes, so calling code catches
``DuplicateBatch`` or ``NotFound`` whichever transport it uses.
"""

from __future__ import annotations

import re
from typing import Final

__all__ = [
    "CrossviewError",
    "InvalidArgument",
    "OutOfRange",
    "PayloadTooLarge",
    "NotFound",
    "Conflict",
    "DuplicateBatch",
    "LateBatch",
    "NoModel",
    "ResourceExhausted",
    "Overloaded",
    "SubscriberLagged",
    "Unauthenticated",
    "Forbidden",
    "UnsupportedMediaType",
    "Unavailable",
    "Timeout",
    "ServerError",
    "error_for_kind",
    "error_from_http",
    "error_from_grpc",
]


class CrossviewError(Exception):
    """Any error the crossview server reported, or a failure to reach it.

    ``kind`` is the server's short stable error kind (``duplicate``, ``late``, ``unknown_scene``,
    ``invalid_argument``, ...; ``connection`` or ``timeout`` for client-side failures), ``field``
    the offending request field when the server named one, ``status`` the HTTP status or the
    gRPC status code name it came with.
    """

    default_kind = "internal"

    def __init__(
        self,
        message: str,
        *,
        kind: str | None = None,
        field: str | None = None,
        status: int | str | None = None,
    ) -> None:
        super().__init__(message)
        self.message: str = message
        self.kind: str = kind or self.default_kind
        self.field: str | None = field
        self.status: int | str | None = status

    def __str__(self) -> str:
        where = f" (field {self.field})" if self.field else ""
        return f"[{self.kind}] {self.message}{where}"


class InvalidArgument(CrossviewError):
    """A value the server refused: a bad box, score or appearance vector (422, INVALID_ARGUMENT)."""

    default_kind = "invalid_argument"


class OutOfRange(InvalidArgument):
    """A frame id outside the scene's frame-id window (422 ``out_of_range``, OUT_OF_RANGE)."""

    default_kind = "out_of_range"


class PayloadTooLarge(InvalidArgument):
    """A request body over the server's ``--max-request-bytes`` (413)."""

    default_kind = "payload_too_large"


class NotFound(CrossviewError):
    """An unknown scene or camera (404, NOT_FOUND)."""

    default_kind = "unknown_scene"


class Conflict(CrossviewError):
    """The request contradicts the scene's state (409, ALREADY_EXISTS / FAILED_PRECONDITION)."""

    default_kind = "conflict"


class DuplicateBatch(Conflict):
    """The same camera already reported this frame (409 ``duplicate``, ALREADY_EXISTS)."""

    default_kind = "duplicate"


class LateBatch(Conflict):
    """The batch's frame was already published (409 ``late``, FAILED_PRECONDITION)."""

    default_kind = "late"


class NoModel(Conflict):
    """Unary association on a declared scene that has no model yet (409 ``no_model``)."""

    default_kind = "no_model"


class ResourceExhausted(CrossviewError):
    """A server queue or budget is full; back off and retry (429, RESOURCE_EXHAUSTED)."""

    default_kind = "resource_exhausted"


class Overloaded(ResourceExhausted):
    """The scene is over its queue budget (``serve --max-queue-delay``): the batch's frame was
    shed whole (429 / RESOURCE_EXHAUSTED, kind ``overloaded``). ``retry_after`` is how many
    seconds the server asks to wait before sending more (``None`` when it gave none)."""

    default_kind = "overloaded"

    def __init__(self, message: str, *, retry_after: float | None = None, **kw: object) -> None:
        super().__init__(message, **kw)  # type: ignore[arg-type]
        self.retry_after: float | None = retry_after


class SubscriberLagged(ResourceExhausted):
    """The server dropped this subscription: it fell too far behind the scene's results.

    Results published meanwhile are lost for this subscriber; a new subscription starts at
    the newest result.
    """

    default_kind = "subscriber_lagged"


class Unauthenticated(CrossviewError):
    """Missing or wrong API key (401, UNAUTHENTICATED)."""

    default_kind = "unauthenticated"


class Forbidden(CrossviewError):
    """A cross-origin write the server refuses (403)."""

    default_kind = "forbidden"


class UnsupportedMediaType(CrossviewError):
    """A body of a media type the route does not take (415)."""

    default_kind = "unsupported_media_type"


class Unavailable(CrossviewError):
    """The server cannot be reached, is shutting down (503, UNAVAILABLE) or the connection broke.

    A push that fails with it may or may not have been accepted before the connection broke.
    """

    default_kind = "unavailable"


class Timeout(CrossviewError):
    """The call did not complete within its timeout (client side, 408 or DEADLINE_EXCEEDED)."""

    default_kind = "timeout"


class ServerError(CrossviewError):
    """An internal server error, or an answer this client does not understand (500, INTERNAL)."""

    default_kind = "internal"


_BY_KIND: Final[dict[str, type[CrossviewError]]] = {
    "invalid_argument": InvalidArgument,
    "format": InvalidArgument,
    "out_of_range": OutOfRange,
    "payload_too_large": PayloadTooLarge,
    "unknown_scene": NotFound,
    "unknown_camera": NotFound,
    "not_found": NotFound,
    "duplicate": DuplicateBatch,
    "late": LateBatch,
    "no_model": NoModel,
    "resource_exhausted": ResourceExhausted,
    "overloaded": Overloaded,
    "subscriber_stalled": ResourceExhausted,
    "subscriber_lagged": SubscriberLagged,
    "deadline_exceeded": Timeout,
    "timeout": Timeout,
    "unauthenticated": Unauthenticated,
    "forbidden": Forbidden,
    "unsupported_media_type": UnsupportedMediaType,
    "unavailable": Unavailable,
    "connection": Unavailable,
}

_BY_HTTP_STATUS: Final[dict[int, type[CrossviewError]]] = {
    401: Unauthenticated,
    403: Forbidden,
    404: NotFound,
    408: Timeout,
    409: Conflict,
    413: PayloadTooLarge,
    415: UnsupportedMediaType,
    422: InvalidArgument,
    429: ResourceExhausted,
    503: Unavailable,
}

# gRPC status code names (grpc.StatusCode.X.name) → class; the kind comes from the message.
_BY_GRPC_CODE: Final[dict[str, type[CrossviewError]]] = {
    "INVALID_ARGUMENT": InvalidArgument,
    "OUT_OF_RANGE": OutOfRange,
    "NOT_FOUND": NotFound,
    "ALREADY_EXISTS": DuplicateBatch,
    "FAILED_PRECONDITION": LateBatch,
    "RESOURCE_EXHAUSTED": ResourceExhausted,
    "UNAUTHENTICATED": Unauthenticated,
    "PERMISSION_DENIED": Forbidden,
    "UNAVAILABLE": Unavailable,
    "DEADLINE_EXCEEDED": Timeout,
    "CANCELLED": Unavailable,
}

# Numeric google.rpc.Code values, for BatchAck.code.
GRPC_CODE_NAMES: Final[dict[int, str]] = {
    0: "OK",
    1: "CANCELLED",
    2: "UNKNOWN",
    3: "INVALID_ARGUMENT",
    4: "DEADLINE_EXCEEDED",
    5: "NOT_FOUND",
    6: "ALREADY_EXISTS",
    7: "PERMISSION_DENIED",
    8: "RESOURCE_EXHAUSTED",
    9: "FAILED_PRECONDITION",
    10: "ABORTED",
    11: "OUT_OF_RANGE",
    12: "UNIMPLEMENTED",
    13: "INTERNAL",
    14: "UNAVAILABLE",
    15: "DATA_LOSS",
    16: "UNAUTHENTICATED",
}

_INVALID_FIELD = re.compile(r"^invalid (\S+?): ")


def error_for_kind(
    kind: str,
    message: str,
    *,
    field: str | None = None,
    status: int | str | None = None,
    fallback: type[CrossviewError] = ServerError,
) -> CrossviewError:
    """The exception for a server error ``kind`` (``fallback``'s class when the kind is new)."""
    cls = _BY_KIND.get(kind, fallback)
    return cls(message, kind=kind or None, field=field, status=status)


def error_from_http(
    status: int, body: object, text: str = "", retry_after: str | None = None
) -> CrossviewError:
    """Maps an HTTP error answer (status, decoded JSON body if any, its ``Retry-After``
    header) to an exception."""
    e = _error_from_http(status, body, text)
    if isinstance(e, Overloaded) and retry_after is not None:
        try:
            e.retry_after = float(retry_after)
        except ValueError:
            pass
    return e


def _error_from_http(status: int, body: object, text: str) -> CrossviewError:
    fallback = _BY_HTTP_STATUS.get(status, ServerError)
    if isinstance(body, dict):
        err = body.get("error")
        if isinstance(err, dict):
            kind = str(err.get("kind") or "")
            message = str(err.get("message") or f"HTTP {status}")
            field = err.get("field")
            field_s = str(field) if field is not None else None
            if status == 413 and not kind:
                kind = "payload_too_large"
            if kind in _BY_KIND:
                return error_for_kind(kind, message, field=field_s, status=status)
            return fallback(message, kind=kind or None, field=field_s, status=status)
    message = text.strip() or f"HTTP {status}"
    return fallback(message[:512], status=status)


def kind_from_grpc(code_name: str, message: str) -> str:
    """The server's error kind behind a gRPC status (its code plus its message's wording).

    For statuses without the server's ``crossview-error-kind`` metadata (servers before it,
    errors of the gRPC library itself): the ambiguous codes are told apart by the message: FAILED_PRECONDITION is ``late`` or ``no_model``, RESOURCE_EXHAUSTED is a full
    queue, a lagging or a stalled subscriber, a frame deadline.
    """
    m = message.lower()
    if code_name == "FAILED_PRECONDITION":
        return "no_model" if "has no model" in m else "late"
    if code_name == "RESOURCE_EXHAUSTED":
        if m.startswith("overloaded:"):
            return "overloaded"
        if "subscriber stalled" in m:
            return "subscriber_stalled"
        if "deadline exceeded" in m:
            return "deadline_exceeded"
        if "fell" in m and "behind" in m:
            return "subscriber_lagged"
        return "resource_exhausted"
    if code_name == "NOT_FOUND":
        return "unknown_camera" if m.startswith("unknown camera") else "unknown_scene"
    if code_name == "INVALID_ARGUMENT":
        return "invalid_argument"
    if code_name == "OUT_OF_RANGE":
        return "payload_too_large" if "max-request-bytes" in m or "too large" in m else "out_of_range"
    if code_name == "ALREADY_EXISTS":
        return "duplicate"
    if code_name == "DEADLINE_EXCEEDED":
        return "timeout"
    if code_name in ("UNAVAILABLE", "CANCELLED"):
        return "unavailable"
    return code_name.lower()


def error_from_grpc(
    code_name: str, message: str, kind: str = "", field: str | None = None
) -> CrossviewError:
    """Maps a gRPC status (its code, message and the server's ``crossview-error-kind`` /
    ``crossview-error-field`` metadata) or a rejected BatchAck (code, message, kind) to an
    exception. Without a kind from the server, it is read off the code and the message."""
    if not kind:
        kind = kind_from_grpc(code_name, message)
    elif kind == "resource_exhausted" and kind_from_grpc(code_name, message) == "subscriber_lagged":
        # The server has one kind for every full queue; the wording tells a lagging
        # subscriber apart.
        kind = "subscriber_lagged"
    fallback = _BY_GRPC_CODE.get(code_name, ServerError)
    if field is None:
        match = _INVALID_FIELD.match(message)
        field = match.group(1) if match and code_name == "INVALID_ARGUMENT" else None
    if kind in _BY_KIND:
        return error_for_kind(kind, message, field=field, status=code_name)
    return fallback(message, kind=kind, field=field, status=code_name)
