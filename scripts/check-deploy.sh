#!/usr/bin/env bash
# Validates the deployment files without a cluster or a container engine (`make deploy-check`):
#  1. deploy/k8s/*.yaml against the Kubernetes 1.37 OpenAPI schemas, strictly (unknown fields,
#     wrong types and unknown kinds fail), with kubernetes-validate;
#  2. deploy/docker-compose.yml against the compose-spec JSON schema (vendored by
#     check-jsonschema);
#  3. consistency, in Python: kustomization.yaml lists exactly the manifests beside it; every
#     CROSSVIEW_* variable given to `crossview serve` (compose services running `serve`, the k8s
#     ConfigMap and container env) is one src/cli/ declares; the kafka profile's services all
#     carry `profiles: ["kafka"]` and the default ones none; deploy/prometheus.yml parses.
# Idempotent: the pinned tools (scripts/deploy-check-requirements.txt) are installed from PyPI
# into .cache/deploy-venv once (reinstalled when that file changes); afterwards it runs offline
# in a few seconds. Needs python3 with venv.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=.cache/deploy-venv
REQ=scripts/deploy-check-requirements.txt
K8S_VERSION=1.37.0
stamp="$VENV/.requirements.sha256"
want=$(sha256sum "$REQ" | cut -d' ' -f1)
if [[ ! -x $VENV/bin/python || ! -f $stamp || $(cat "$stamp") != "$want" ]]; then
  echo "deploy-check: installing the validators into $VENV (PyPI, once)" >&2
  rm -rf "$VENV"
  mkdir -p "$(dirname "$VENV")"
  python3 -m venv "$VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --no-input -r "$REQ"
  echo "$want" >"$stamp"
fi
bin=$VENV/bin
status=0

# ---- 1. Kubernetes manifests ------------------------------------------------------------------
manifests=()
for f in deploy/k8s/*.yaml; do
  [[ $(basename "$f") == kustomization.yaml ]] || manifests+=("$f")
done
if (( ${#manifests[@]} == 0 )); then
  echo "deploy-check: no manifests in deploy/k8s" >&2
  exit 1
fi
# kubernetes-validate only warns (exit 0) on a kind it has no schema for: a warning fails too.
if ! out=$("$bin/kubernetes-validate" --strict --kubernetes-version "$K8S_VERSION" "${manifests[@]}" 2>&1); then
  status=1
fi
echo "$out"
if grep -q '^WARN' <<<"$out"; then
  echo "deploy-check: kubernetes-validate warned (unknown kind or version?): failing" >&2
  status=1
fi

# ---- 2. compose file --------------------------------------------------------------------------
echo "deploy/docker-compose.yml against compose-spec:"
"$bin/check-jsonschema" --builtin-schema vendor.compose-spec deploy/docker-compose.yml || status=1

# ---- 3. consistency ---------------------------------------------------------------------------
"$bin/python" - <<'PY' || status=1
import glob, os, re, sys
import yaml

errors = []
def err(msg):
    errors.append(msg)

def load_all(path):
    with open(path) as f:
        return [d for d in yaml.safe_load_all(f) if d is not None]

# Variables `crossview serve` reads: its flags' env fallbacks, the global ones, and the
# non-CROSSVIEW ones the image uses.
known = set()
for src in ("src/cli/serve.rs", "src/cli/mod.rs"):
    with open(src) as f:
        known |= set(re.findall(r'env\s*=\s*"(CROSSVIEW_[A-Z0-9_]+)"', f.read()))
if "CROSSVIEW_KAFKA_BROKERS" not in known or "CROSSVIEW_MODELS" not in known:
    err("could not read the serve flags' env names from src/cli/serve.rs")

def check_env(where, names):
    for n in names:
        if n.startswith("CROSSVIEW_") and n not in known:
            err(f"{where}: {n} is not an env fallback of `crossview serve` (src/cli/serve.rs)")

# kustomization.yaml lists exactly the manifests beside it.
kdir = "deploy/k8s"
kust = load_all(os.path.join(kdir, "kustomization.yaml"))[0]
listed = set(kust.get("resources", []))
present = {os.path.basename(p) for p in glob.glob(os.path.join(kdir, "*.yaml"))} - {"kustomization.yaml"}
for name in sorted(listed - present):
    err(f"{kdir}/kustomization.yaml lists {name}, which does not exist")
for name in sorted(present - listed):
    err(f"{kdir}/{name} is not listed in kustomization.yaml")
image_names = {i.get("name") for i in kust.get("images", [])}

for path in sorted(glob.glob(os.path.join(kdir, "*.yaml"))):
    if path.endswith("kustomization.yaml"):
        continue
    for doc in load_all(path):
        kind = doc.get("kind")
        if kind == "ConfigMap":
            check_env(path, doc.get("data", {}).keys())
        if kind == "Deployment":
            for c in doc["spec"]["template"]["spec"].get("containers", []):
                check_env(f"{path} container {c.get('name')}", [e["name"] for e in c.get("env", [])])
                if c.get("image") not in image_names:
                    err(f"{path}: image {c.get('image')!r} is not rewritten by kustomization.yaml images")

# compose: env names of the services running `serve`, and the kafka profile.
compose = load_all("deploy/docker-compose.yml")[0]
services = compose.get("services", {})
kafka_services = {"broker", "kafka-topics", "replica-a", "replica-b", "kafka-replay"}
for name in sorted(kafka_services - services.keys()):
    err(f"deploy/docker-compose.yml: no service {name} (kafka profile)")
for name, svc in services.items():
    profiles = svc.get("profiles")
    if name in kafka_services and profiles != ["kafka"]:
        err(f"deploy/docker-compose.yml: {name} should have profiles: [\"kafka\"], has {profiles}")
    if name not in kafka_services and profiles:
        err(f"deploy/docker-compose.yml: {name} has profiles {profiles}: the default `up` would change")
    if svc.get("command") == ["serve"]:
        env = svc.get("environment", {})
        names = env.keys() if isinstance(env, dict) else [e.split("=", 1)[0] for e in env]
        check_env(f"deploy/docker-compose.yml service {name}", names)
ids = [services[r].get("environment", {}).get("CROSSVIEW_KAFKA_PRODUCER_ID") for r in ("replica-a", "replica-b") if r in services]
if len(set(ids)) != len(ids) or None in ids:
    err(f"deploy/docker-compose.yml: the replicas need distinct CROSSVIEW_KAFKA_PRODUCER_IDs, have {ids}")

prom = load_all("deploy/prometheus.yml")[0]
if not prom.get("scrape_configs"):
    err("deploy/prometheus.yml: no scrape_configs")

for e in errors:
    print(f"ERROR {e}", file=sys.stderr)
if errors:
    sys.exit(1)
print("consistency: ok (kustomization, serve env names, kafka profile, prometheus.yml)")
PY

if (( status != 0 )); then
  echo "deploy-check: FAILED" >&2
  exit 1
fi
echo "deploy-check: ok"
