"""Connection settings shared by every client: address, TLS, API key, timeouts."""

from __future__ import annotations

import os
from dataclasses import dataclass

DEFAULT_TIMEOUT = 10.0
"""Seconds any single request (a unary call, one push's ack, connecting) may take by default."""

DEFAULT_RECONNECT_TIMEOUT = 30.0
"""Seconds a subscription keeps trying to resubscribe after the connection was lost."""

SSE_SILENCE_TIMEOUT = 45.0
"""The server sends an SSE keep-alive comment every 15 s: this much silence means a dead
connection."""


def read_pem(value: "str | bytes | os.PathLike[str] | None") -> bytes | None:
    """PEM bytes from bytes, a PEM string or a file path."""
    if value is None:
        return None
    if isinstance(value, bytes):
        return value
    s = os.fspath(value)
    if s.lstrip().startswith("-----BEGIN"):
        return s.encode()
    with open(s, "rb") as f:
        return f.read()


@dataclass(frozen=True)
class Settings:
    """How to reach the server.

    ``address`` is ``host:port`` (an ``http://``/``https://`` prefix is accepted and an
    ``https://`` one turns TLS on). With ``tls`` the server's certificate is checked against
    ``ca_cert`` (PEM bytes, string or file) or the system's roots; ``tls_server_name`` checks
    it for another name than the address's host. ``api_key`` is sent as ``Bearer`` token.
    """

    host: str
    port: int
    tls: bool = False
    ca_cert: bytes | None = None
    tls_server_name: str | None = None
    api_key: str | None = None
    timeout: float = DEFAULT_TIMEOUT

    @property
    def target(self) -> str:
        """``host:port`` (IPv6 hosts bracketed)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"

    @property
    def base_url(self) -> str:
        """The HTTP base URL."""
        return f"{'https' if self.tls else 'http'}://{self.target}"


def make_settings(
    address: str,
    *,
    api_key: str | None = None,
    tls: bool | None = None,
    ca_cert: "str | bytes | os.PathLike[str] | None" = None,
    tls_server_name: str | None = None,
    timeout: float = DEFAULT_TIMEOUT,
) -> Settings:
    """Parses ``address`` and checks the settings (see :class:`Settings`)."""
    if timeout <= 0:
        raise ValueError("timeout must be positive")
    rest = address
    scheme_tls = None
    for scheme, is_tls in (("https://", True), ("http://", False)):
        if rest.startswith(scheme):
            rest, scheme_tls = rest[len(scheme):], is_tls
    rest = rest.rstrip("/")
    if rest.startswith("["):
        host, _, port_s = rest[1:].partition("]:")
    else:
        host, _, port_s = rest.rpartition(":")
    if not host or not port_s.isdigit():
        raise ValueError(f"address must be host:port, got {address!r}")
    use_tls = tls if tls is not None else bool(scheme_tls) or ca_cert is not None
    if api_key is not None and not api_key.strip():
        raise ValueError("api_key is blank")
    return Settings(
        host=host,
        port=int(port_s),
        tls=use_tls,
        ca_cert=read_pem(ca_cert),
        tls_server_name=tls_server_name,
        api_key=api_key,
        timeout=timeout,
    )
