"""TLS and API keys: a server with a self-signed certificate (made here with ``cryptography``)
and ``--api-key``, reached over both transports, sync and async."""

from __future__ import annotations

import asyncio
import datetime
import ipaddress
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import DEMO_CAMERAS, Server, person_boxes, start_server
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

import crossview_client as cv

KEY = "s3cret-key"


def self_signed(dir: Path) -> tuple[Path, Path]:
    """A certificate for localhost and 127.0.0.1 and its key, as PEM files."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = dir / "cert.pem", dir / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    return cert_path, key_path


@pytest.fixture(scope="module")
def tls_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Server, Path]]:
    cert, key = self_signed(tmp_path_factory.mktemp("tls"))
    s = start_server("--tls-cert", str(cert), "--tls-key", str(key), "--api-key", KEY,
                     "--sync-timeout", "60s")
    yield s, cert
    s.stop()


@pytest.mark.parametrize("transport", ["grpc", "http"])
def test_tls_with_api_key(transport: str, tls_server: tuple[Server, Path]) -> None:
    server, cert = tls_server
    with cv.connect(server.addr, transport, api_key=KEY, ca_cert=cert, timeout=20.0) as client:  # type: ignore[arg-type]
        client.wait_ready(30)
        assert client.settings.tls  # type: ignore[attr-defined]
        assert [s.name for s in client.scenes()] == ["demo"]
        fid = 10 if transport == "grpc" else 20
        with client.subscribe("demo") as sub:
            acks = client.push_frame("demo", fid, {c: person_boxes(2) for c in DEMO_CAMERAS})
            assert all(a.accepted for a in acks)
            r = next(r for r in sub if r.frame_id == fid)
        assert r.complete and r.identities
        assert client.reload()[0].outcome == "unchanged"


@pytest.mark.parametrize("transport", ["grpc", "http"])
def test_wrong_or_missing_key_is_unauthenticated(transport: str, tls_server: tuple[Server, Path]) -> None:
    server, cert = tls_server
    for key in ("wrong-key", None):
        with cv.connect(server.addr, transport, api_key=key, ca_cert=cert, timeout=20.0) as client:  # type: ignore[arg-type]
            with pytest.raises(cv.Unauthenticated) as e:
                client.scenes()
            assert e.value.kind == "unauthenticated"
            with pytest.raises(cv.Unauthenticated):
                client.push("demo", "cam0", 5, [])
            with pytest.raises(cv.Unauthenticated):
                client.subscribe("demo", reconnect=False)


@pytest.mark.parametrize("transport", ["grpc", "http"])
def test_async_tls_with_api_key(transport: str, tls_server: tuple[Server, Path]) -> None:
    server, cert = tls_server

    async def main() -> None:
        async with cv.connect_async(server.addr, transport, api_key=KEY, ca_cert=cert) as c:  # type: ignore[arg-type]
            assert [s.name for s in await c.scenes()] == ["demo"]
        async with cv.connect_async(server.addr, transport, api_key="nope", ca_cert=cert) as c:  # type: ignore[arg-type]
            with pytest.raises(cv.Unauthenticated):
                await c.scenes()

    asyncio.run(asyncio.wait_for(main(), 60))


@pytest.mark.parametrize("transport", ["grpc", "http"])
def test_untrusted_certificate_is_refused(transport: str, tls_server: tuple[Server, Path]) -> None:
    server, _ = tls_server
    # TLS on, but the self-signed certificate is not among the system's roots.
    with cv.connect(server.addr, transport, api_key=KEY, tls=True, timeout=3.0) as client:  # type: ignore[arg-type]
        with pytest.raises(cv.Unavailable):
            client.scenes()
