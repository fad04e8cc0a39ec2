"""crossview_client — a Python client for the crossview association service.

Synchronous and asyncio clients over gRPC (``GrpcClient``, ``AsyncGrpcClient``) and HTTP/JSON
with Server-Sent Events (``HttpClient``, ``AsyncHttpClient``), all with the same methods:
``push``, ``push_frame``, ``push_many``, ``subscribe``, ``associate``, ``scenes``, ``scene``,
``reload``, ``stream_recording``, ``wait_ready``. Errors are one hierarchy whatever the
transport (``crossview_client.errors``).

    from crossview_client import GrpcClient
    with GrpcClient("127.0.0.1:8080") as client:
        sub = client.subscribe("demo")
        client.push("demo", "cam0", 0, [{"bbox": [10, 20, 40, 200], "score": 0.9}])
        ...
        for result in sub:
            print(result.frame_id, [i.track_id for i in result.identities])
"""

from __future__ import annotations

from typing import Any, Literal

from . import errors
from ._base import AsyncClient, SyncClient
from ._grpc import AsyncGrpcClient, GrpcClient
from ._http import AsyncHttpClient, HttpClient
from ._subscription import AsyncSubscription, Subscription
from .errors import (
    Conflict,
    CrossviewError,
    DuplicateBatch,
    Forbidden,
    InvalidArgument,
    LateBatch,
    NoModel,
    NotFound,
    OutOfRange,
    PayloadTooLarge,
    Overloaded,
    ResourceExhausted,
    ServerError,
    SubscriberLagged,
    Timeout,
    Unauthenticated,
    Unavailable,
    UnsupportedMediaType,
)
from .recording import Recording, ReplaySummary, open_recording
from .types import (
    Batch,
    Boxes,
    Camera,
    Detection,
    FrameResult,
    Identity,
    Member,
    PushAck,
    ReloadOutcome,
    ResultStatus,
    Scene,
)

__version__ = "0.1.0"

__all__ = [
    "connect",
    "connect_async",
    "SyncClient",
    "AsyncClient",
    "GrpcClient",
    "HttpClient",
    "AsyncGrpcClient",
    "AsyncHttpClient",
    "Subscription",
    "AsyncSubscription",
    "Batch",
    "Boxes",
    "Camera",
    "Detection",
    "FrameResult",
    "Identity",
    "Member",
    "PushAck",
    "ReloadOutcome",
    "ResultStatus",
    "Scene",
    "Recording",
    "ReplaySummary",
    "open_recording",
    "errors",
    "CrossviewError",
    "InvalidArgument",
    "OutOfRange",
    "PayloadTooLarge",
    "NotFound",
    "Conflict",
    "DuplicateBatch",
    "LateBatch",
    "NoModel",
    "Overloaded",
    "ResourceExhausted",
    "SubscriberLagged",
    "Unauthenticated",
    "Forbidden",
    "UnsupportedMediaType",
    "Unavailable",
    "Timeout",
    "ServerError",
]


def connect(address: str, transport: Literal["grpc", "http"] = "grpc", **kwargs: Any) -> SyncClient:
    """A synchronous client for ``address`` (``host:port``) over ``transport``; keyword
    arguments as for ``GrpcClient`` / ``HttpClient`` (``api_key``, ``tls``, ``ca_cert``,
    ``timeout``, ...)."""
    if transport == "grpc":
        return GrpcClient(address, **kwargs)
    if transport == "http":
        return HttpClient(address, **kwargs)
    raise ValueError(f"transport must be 'grpc' or 'http', not {transport!r}")


def connect_async(
    address: str, transport: Literal["grpc", "http"] = "grpc", **kwargs: Any
) -> AsyncGrpcClient | AsyncHttpClient:
    """An asyncio client for ``address`` over ``transport`` (see :func:`connect`); create it
    inside the event loop that will use it."""
    if transport == "grpc":
        return AsyncGrpcClient(address, **kwargs)
    if transport == "http":
        return AsyncHttpClient(address, **kwargs)
    raise ValueError(f"transport must be 'grpc' or 'http', not {transport!r}")
