#!/usr/bin/env bash
# Project setup, idempotent, needs python3 + pip (PyPI) and, for one browser test, Chromium:
#  - .cache/venv: the Python client package clients/python (editable) and its test extra, and
#    schemathesis (pinned) for the test that fuzzes the HTTP API against docs/openapi.json;
#  - chromium (Debian package, when missing and running as root with apt-get) for the live
#    viewer's browser test;
#  - .cache/kafka/<version>/libs: Apache Kafka's broker and tools (Maven Central, pinned in
#    scripts/kafka/pom.xml) for the Kafka-mode tests, benchmarks and load tests;
#  - .cache/onnxruntime/: the ONNX Runtime shared library from the PyPI wheel onnxruntime==1.31.1.
set -euo pipefail
cd "$(dirname "$0")/.."

# ---- serve: the Python client package and its tests (clients/python) ------------------------
# .cache/venv holds crossview_client, installed editable with its test extra (pytest,
# cryptography, grpcio-tools, mypy; lower bounds in clients/python/pyproject.toml), for
# tests/cli/python_package.rs. Idempotent and fast when installed: it reinstalls only when
# pyproject.toml changed (its hash is kept in the venv). It runs before the ONNX Runtime step
# because that step exits early once the library is present.
VENV=.cache/venv
PYPROJECT=clients/python/pyproject.toml
STAMP="$VENV/.crossview-client.sha256"
WANT=$(sha256sum "$PYPROJECT" | cut -d' ' -f1)
if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$STAMP" 2>/dev/null)" != "$WANT" ] \
   || ! "$VENV/bin/python" -c 'import crossview_client, pytest, grpc_tools' 2>/dev/null; then
  echo "setup: installing clients/python (editable, with its test extra) into $VENV" >&2
  [ -x "$VENV/bin/python" ] || python3 -m venv "$VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -e "./clients/python[test]"
  echo "$WANT" > "$STAMP"
fi
# schemathesis, pinned, into the same venv: tests/serve/openapi_fuzz.rs runs it against the real
# server and its own description (docs/openapi.json). Fast when present: one version check.
SCHEMATHESIS_VERSION=4.32.5
if [ "$("$VENV/bin/schemathesis" --version 2>/dev/null | awk '{print $NF}')" != "$SCHEMATHESIS_VERSION" ]; then
  echo "setup: installing schemathesis==$SCHEMATHESIS_VERSION into $VENV" >&2
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check \
    "schemathesis==$SCHEMATHESIS_VERSION"
fi

# Headless Chromium for the live viewer's browser test (tests/serve/viewer.rs; without it that
# test skips locally and fails under CI=true). Installed from Debian's archive when missing and
# we may (root + apt-get); otherwise a note. Fast when present: one `command -v`.
if [ -z "${CROSSVIEW_CHROMIUM:-}" ] && ! command -v chromium >/dev/null 2>&1 \
   && ! command -v chromium-browser >/dev/null 2>&1 && ! command -v google-chrome >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing chromium (apt-get) for the viewer's browser test" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq chromium >/dev/null
  else
    echo "setup: no Chromium found; install it (Debian: apt-get install chromium) or set" \
      "CROSSVIEW_CHROMIUM for tests/serve/viewer.rs" >&2
  fi
fi
# ---- end serve -------------------------------------------------------------------------------

# ---- kafka: the broker of the Kafka-mode tests, benchmarks and load tests -------------------
# Apache Kafka (the version pinned in scripts/kafka/pom.xml), resolved by name from Maven Central
# with the broker's runtime classpath into .cache/kafka/<version>/libs (scripts/kafka/broker.sh
# runs it). Needs Java 17 and Maven; fast when present (the pom's hash is kept beside the jars),
# offline from then on.
KAFKA_POM=scripts/kafka/pom.xml
KAFKA_VERSION=$(sed -n 's:.*<kafka.version>\(.*\)</kafka.version>.*:\1:p' "$KAFKA_POM")
KAFKA_HOME=.cache/kafka/$KAFKA_VERSION
KAFKA_WANT=$(sha256sum "$KAFKA_POM" | cut -d' ' -f1)
if [ "$(cat "$KAFKA_HOME/.pom.sha256" 2>/dev/null)" != "$KAFKA_WANT" ]; then
  if ! command -v mvn >/dev/null 2>&1 || ! command -v java >/dev/null 2>&1; then
    echo "setup: Java 17 and Maven are needed for the Kafka broker (Debian: apt-get install" \
      "openjdk-17-jdk-headless maven)" >&2
    exit 1
  fi
  echo "setup: resolving Apache Kafka $KAFKA_VERSION from Maven Central into $KAFKA_HOME" >&2
  rm -rf "$KAFKA_HOME.tmp"
  mvn -q -B -Dstyle.color=never -f "$KAFKA_POM" dependency:copy-dependencies -DincludeScope=runtime \
    -DoutputDirectory="$PWD/$KAFKA_HOME.tmp/libs" >&2
  rm -rf "$KAFKA_HOME"
  mv "$KAFKA_HOME.tmp" "$KAFKA_HOME"
  echo "$KAFKA_WANT" > "$KAFKA_HOME/.pom.sha256"
  echo "setup: Apache Kafka $KAFKA_VERSION at $KAFKA_HOME ($(ls "$KAFKA_HOME/libs" | wc -l) jars)" >&2
fi
# ---- end kafka -------------------------------------------------------------------------------

ORT_VERSION=1.31.1
DEST=.cache/onnxruntime
LIB="$DEST/libonnxruntime.so.$ORT_VERSION"
if [ -f "$LIB" ]; then
  exit 0
fi
mkdir -p "$DEST/wheel"
echo "setup: fetching onnxruntime==$ORT_VERSION from PyPI" >&2
python3 -m pip download --quiet --no-deps --only-binary=:all: \
  --python-version 3.11 --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_17_x86_64 --implementation cp \
  -d "$DEST/wheel" "onnxruntime==$ORT_VERSION"
WHEEL=$(ls "$DEST"/wheel/onnxruntime-"$ORT_VERSION"-*.whl | head -n1)
python3 - "$WHEEL" "$DEST" "$ORT_VERSION" <<'PY'
import sys, zipfile, os
wheel, dest, ver = sys.argv[1:]
name = f"onnxruntime/capi/libonnxruntime.so.{ver}"
with zipfile.ZipFile(wheel) as z:
    data = z.read(name)
tmp = os.path.join(dest, f"libonnxruntime.so.{ver}.tmp")
with open(tmp, "wb") as f:
    f.write(data)
os.replace(tmp, os.path.join(dest, f"libonnxruntime.so.{ver}"))
PY
rm -rf "$DEST/wheel"
echo "setup: ONNX Runtime at $LIB" >&2
