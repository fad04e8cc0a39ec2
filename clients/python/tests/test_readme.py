"""The README's "From Python" steps, as written, and the example scripts, against the real
server. The README block runs in a scratch directory that links the repository's
``clients`` and ``models``; only the install line is left out (tests never install: the
package is already installed here by scripts/setup.sh), and the binary, the interpreter and
the port are this test's."""

from __future__ import annotations

import re
import subprocess
import sys
import threading
from pathlib import Path

from conftest import (
    DEMO_TIMED_SCENE,
    REPO,
    crossview_bin,
    free_port,
    run_python,
    server_env,
    start_server,
)

EXAMPLES = REPO / "clients" / "python" / "examples"


def readme_block() -> list[str]:
    text = (REPO / "README.md").read_text()
    m = re.search(r"<!-- from-python -->\s*```sh\n(.*?)```\s*<!-- /from-python -->", text, re.S)
    assert m, "README.md lost its From Python block"
    return [line for line in m.group(1).splitlines() if line.strip()]


def test_readme_from_python_steps_work_as_written(tmp_path: Path) -> None:
    lines = readme_block()
    assert lines[0] == "python3 -m venv .venv && .venv/bin/pip install ./clients/python"
    port = str(free_port())
    script = "\n".join(
        line.replace("target/release/crossview", crossview_bin())
        .replace(".venv/bin/python", sys.executable)
        .replace("8080", port)
        for line in lines[1:]
    )
    (tmp_path / "clients").symlink_to(REPO / "clients")
    (tmp_path / "models").symlink_to(REPO / "models")
    out = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", f"trap 'kill %1 2>/dev/null || true' EXIT\n{script}"],
        cwd=tmp_path, env=server_env(), capture_output=True, text=True, timeout=120,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    frames = [l for l in out.stdout.splitlines() if l.startswith("frame ")]
    assert len(frames) == 20, out.stdout
    assert all(re.match(r"frame \d+ at \S+: \d+ identities ", l) for l in frames)
    assert "20 frames" in out.stdout


def test_examples_push_and_follow(tmp_path: Path) -> None:
    # The detector example stamps its batches with capture times: the scene declares its rate.
    server = start_server("--sync-timeout", "60s", "--scene", DEMO_TIMED_SCENE)
    try:
        rec = tmp_path / "demo.jsonl"
        subprocess.run(
            [crossview_bin(), "simulate", "--preset", "square4", "--seed", "4", "--frames", "5",
             "--out", str(rec)], check=True, env=server_env(), capture_output=True, timeout=60,
        )
        follower = subprocess.Popen(
            [sys.executable, str(EXAMPLES / "follow_tracks.py"), "--server", server.addr,
             "--transport", "http", "--frames", "5"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        assert follower.stdout is not None
        lines: list[str] = []
        subscribed = threading.Event()

        def read() -> None:
            assert follower.stdout is not None
            for line in follower.stdout:
                lines.append(line)
                if line.startswith("subscribed"):
                    subscribed.set()
            subscribed.set()

        threading.Thread(target=read, daemon=True).start()
        assert subscribed.wait(60), "".join(lines)
        pushed = run_python(
            [str(EXAMPLES / "push_from_detector.py"), "--server", server.addr, "--scene", "demo", str(rec)]
        )
        assert pushed.returncode == 0, pushed.stdout + pushed.stderr
        assert pushed.stdout.count("identities") == 5
        follower.wait(60)
        out = "".join(lines)
        assert follower.returncode == 0, out
        assert out.count(" complete, associated, model 0.1.0@") == 5, out
        assert "seen by cam" in out and "track 0 appears" in out
    finally:
        server.stop()


def simulated_recording(tmp_path: Path, seed: int) -> Path:
    """A 6-frame recording of the simulator's square4 scene (the demo model's 4 cameras)."""
    rec = tmp_path / "demo.jsonl"
    subprocess.run(
        [crossview_bin(), "simulate", "--preset", "square4", "--seed", str(seed), "--frames", "6",
         "--out", str(rec)], check=True, env=server_env(), capture_output=True, timeout=60,
    )
    return rec


def test_stream_recording_replays_camera_by_camera(tmp_path: Path) -> None:
    import crossview_client as cv

    server = start_server("--sync-timeout", "60s")
    try:
        rec = simulated_recording(tmp_path, seed=5)
        with rec.open("a") as f:
            f.write('{"camera": "cam0", "frame_id": 99, "detec')  # a torn last line
        for transport, offset in (("grpc", 0), ("http", 1)):
            with cv.connect(server.addr, transport) as client:  # type: ignore[arg-type]
                with client.subscribe("demo") as sub:
                    summary = client.stream_recording(rec, scene="demo")
                    if offset:  # the same frames again: every batch is now late
                        assert summary.accepted == 0 and summary.rejected == {"late": 24}
                        continue
                    assert (summary.accepted, summary.rejected_total, summary.frames) == (24, 0, 6)
                    assert summary.torn_lines == 1
                    got = [next(sub).frame_id for _ in range(6)]
                assert got == list(range(6))
    finally:
        server.stop()


def test_async_stream_recording_replays_frame_by_frame(tmp_path: Path) -> None:
    """The asyncio clients replay the same way (one frame's batches at a time, paced here)."""
    import asyncio

    import crossview_client as cv

    server = start_server("--sync-timeout", "60s")
    try:
        rec = simulated_recording(tmp_path, seed=6)

        async def main() -> None:
            for transport, late in (("grpc", False), ("http", True)):
                async with cv.connect_async(server.addr, transport) as client:  # type: ignore[arg-type]
                    sub = await client.subscribe("demo")
                    summary = await client.stream_recording(rec, scene="demo", fps=50)
                    if late:  # the same frames again: every batch is now late
                        assert summary.accepted == 0 and summary.rejected == {"late": 24}
                        continue
                    assert (summary.accepted, summary.rejected_total, summary.frames) == (24, 0, 6)
                    async with sub:
                        got = [(await sub.__anext__()).frame_id for _ in range(6)]
                    assert got == list(range(6))

        asyncio.run(asyncio.wait_for(main(), 90))
    finally:
        server.stop()
