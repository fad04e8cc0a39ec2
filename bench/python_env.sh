# shellcheck shell=bash
# Sourced by the bench scripts: the ONNX Runtime library (scripts/setup.sh) and a virtual
# environment with numpy, scipy and onnxruntime==1.31.1 from PyPI in .cache/bench-venv ($VENV).
bash scripts/setup.sh
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}

VENV=.cache/bench-venv
if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import numpy, scipy, onnxruntime' 2>/dev/null; then
  echo "bench: creating $VENV with numpy, scipy, onnxruntime==1.31.1 (PyPI)" >&2
  "${PYTHON:-python3}" -m venv "$VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check \
    numpy scipy "onnxruntime==1.31.1"
fi
