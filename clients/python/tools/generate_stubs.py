"""Regenerates the committed gRPC stubs (src/crossview_client/_pb/) from
proto/crossview/v1/crossview.proto with grpcio-tools (the version pinned in pyproject's test
extra). tests/test_stubs.py runs it into a temporary directory and checks the committed files
are what it writes.

Usage: python tools/generate_stubs.py [OUT_SRC_DIR]   (default: the package's src/)
"""

from __future__ import annotations

import sys
from pathlib import Path

from grpc_tools import protoc

HERE = Path(__file__).resolve().parent
PROTO_DIR = HERE.parents[2] / "proto" / "crossview" / "v1"
PROTO = PROTO_DIR / "crossview.proto"
# The proto is mapped into the package (-Icrossview_client/_pb=...), so the generated modules
# import each other as crossview_client._pb.* and need no rewriting.
VIRTUAL = "crossview_client/_pb"
FILES = ("crossview_pb2.py", "crossview_pb2.pyi", "crossview_pb2_grpc.py")


def generate(out_src: Path) -> list[Path]:
    """Writes the stubs under ``out_src/crossview_client/_pb/`` and returns their paths."""
    (out_src / VIRTUAL).mkdir(parents=True, exist_ok=True)
    # The well-known types (google/protobuf/timestamp.proto) ship with grpcio-tools.
    well_known = Path(protoc.__file__).resolve().parent / "_proto"
    rc = protoc.main([
        "grpc_tools.protoc",
        f"-I{VIRTUAL}={PROTO_DIR}",
        f"-I{well_known}",
        f"--python_out={out_src}",
        f"--pyi_out={out_src}",
        f"--grpc_python_out={out_src}",
        str(PROTO),
    ])
    if rc != 0:
        raise RuntimeError(f"protoc failed with exit code {rc}")
    return [out_src / VIRTUAL / f for f in FILES]


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parent / "src"
    for p in generate(out):
        print(p)
