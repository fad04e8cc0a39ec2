"""The committed gRPC stubs are exactly what grpcio-tools (the pinned version) generates from
proto/crossview/v1/crossview.proto today."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from conftest import REPO

PKG = REPO / "clients" / "python"


def test_committed_stubs_match_the_proto(tmp_path: Path) -> None:
    spec = importlib.util.spec_from_file_location("generate_stubs", PKG / "tools" / "generate_stubs.py")
    assert spec is not None and spec.loader is not None
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    for fresh in gen.generate(tmp_path):
        committed = PKG / "src" / "crossview_client" / "_pb" / fresh.name
        assert committed.read_bytes() == fresh.read_bytes(), (
            f"{committed} is stale: run `python clients/python/tools/generate_stubs.py`"
        )
