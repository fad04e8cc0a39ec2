"""Fixtures: the real ``crossview serve`` binary (``$CROSSVIEW_BIN``) on a free loopback port.

The server's bound address comes from its "serving" log line (``RUST_LOG=info``), as the Rust
tests read it. Without ``$CROSSVIEW_BIN`` the tests skip, except under ``CI=true``, where a
test that cannot run its real dependency must fail.
"""

from __future__ import annotations

import itertools
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[3]
MODELS = REPO / "models"
DEMO_MODEL = MODELS / "demo.onnx"
DEMO_CAMERAS = ("cam0", "cam1", "cam2", "cam3")
#: The demo scene declared at 10 frames/s (capture times need the scene's rate).
DEMO_TIMED_SCENE = "demo=" + ",".join(f"{c}:1280x720" for c in DEMO_CAMERAS) + "@10fps"
START_TIMEOUT = 60.0
_ADDR = re.compile(r"(\d+\.\d+\.\d+\.\d+:\d+)")
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def crossview_bin() -> str:
    """The server binary; skips (fails under CI=true) when ``$CROSSVIEW_BIN`` is not set."""
    path = os.environ.get("CROSSVIEW_BIN")
    if not path or not Path(path).is_file():
        reason = "set CROSSVIEW_BIN to the crossview binary (cargo test --test cli python does)"
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true, so this test may not skip: {reason}")
        pytest.skip(reason)
    return path


def server_env() -> dict[str, str]:
    env = dict(os.environ)
    env["RUST_LOG"] = "info"
    # Tests push whole recordings at once on a busy machine: no frame is shed under them.
    env.setdefault("CROSSVIEW_MAX_QUEUE_DELAY", "60s")
    env.pop("CROSSVIEW_API_KEYS", None)
    if "ORT_DYLIB_PATH" not in env:
        ort = REPO / ".cache" / "onnxruntime" / "libonnxruntime.so.1.31.1"
        if ort.exists():
            env["ORT_DYLIB_PATH"] = str(ort)
    return env


class Server:
    """One ``crossview serve`` process; ``restart()`` starts it again on the same port."""

    def __init__(self, args: list[str], port: int = 0) -> None:
        self.args = args
        self.port = port
        self.addr = ""
        self.log: list[str] = []
        self.proc: subprocess.Popen[str] | None = None
        self.start()

    def start(self) -> None:
        cmd = [crossview_bin(), "serve", "--listen", f"127.0.0.1:{self.port}", *self.args]
        proc = subprocess.Popen(
            cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            text=True, env=server_env(), cwd=REPO,
        )
        self.proc = proc
        ready = threading.Event()
        found: list[str] = []

        def read() -> None:
            assert proc.stderr is not None
            for line in proc.stderr:
                line = _ANSI.sub("", line.rstrip("\n"))
                self.log.append(line)
                if "serving" in line and not found:
                    m = _ADDR.search(line)
                    if m:
                        found.append(m.group(1))
                        ready.set()
            ready.set()

        threading.Thread(target=read, daemon=True).start()
        if not ready.wait(START_TIMEOUT) or not found:
            self.kill()
            raise RuntimeError("crossview serve did not start:\n" + "\n".join(self.log[-30:]))
        self.addr = found[0]
        self.port = int(self.addr.rsplit(":", 1)[1])

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 30.0) -> None:
        """Stops the server (SIGTERM: graceful) and waits for it, at most ``timeout`` s."""
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(sig)
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def restart(self) -> None:
        self.stop()
        deadline = time.monotonic() + 30
        while True:  # the port may linger a moment
            try:
                self.start()
                return
            except RuntimeError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    def metric(self, name: str, timeout: float = 10.0) -> float:
        """The value of one Prometheus sample line starting with ``name`` (0 when absent)."""
        import httpx

        text = httpx.get(f"http://{self.addr}/metrics", timeout=timeout).text
        for line in text.splitlines():
            if line.split(" ")[0] == name:
                return float(line.split()[-1])
        return 0.0


def start_server(*args: str, port: int = 0) -> Server:
    """A demo-model server with ``args`` (the scene "demo", 4 cameras of 1280×720)."""
    return Server(["--model", str(DEMO_MODEL), *args], port=port)


@pytest.fixture(scope="session")
def server() -> Iterator[Server]:
    """One server shared by the API tests. Its sync timeout is long, so a frame waits for all
    its cameras however loaded the machine; every test pushes complete frames with fresh ids."""
    s = start_server("--sync-timeout", "60s")
    yield s
    s.stop()


_frame_ids = itertools.count(1000, 10)


@pytest.fixture
def frame_id() -> int:
    """A fresh frame id, above every id used before on the shared server (the test may use
    the next 9 too)."""
    return next(_frame_ids)


def person_boxes(n: int = 3, shift: float = 0.0) -> list[list[float]]:
    """``n`` plausible person boxes (x1, y1, x2, y2, score) in a 1280×720 image."""
    return [[100.0 + 200 * i + shift, 200.0, 160.0 + 200 * i + shift, 400.0, 0.9] for i in range(n)]


def run_python(args: list[str], timeout: float = 90.0, **kw: Any) -> subprocess.CompletedProcess[str]:
    """Runs a Python script with this interpreter, bounded by ``timeout``."""
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, timeout=timeout, **kw
    )


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
