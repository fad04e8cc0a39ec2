# crossview — the two commands a newcomer needs are `make demo` and `make test`.
SHELL := /bin/bash
ORT_DYLIB_PATH ?= $(CURDIR)/.cache/onnxruntime/libonnxruntime.so.1.31.1
export ORT_DYLIB_PATH

.PHONY: setup build test bench lint fmt demo

## setup: everything the build and the tests need beyond Rust, from PyPI into .cache/ (once):
## the ONNX Runtime library and the Python venv (the client package clients/python with its test
## extra, and schemathesis for the HTTP API's OpenAPI fuzz test; tests never install anything)
setup:
	@bash scripts/setup.sh

build: setup
	cargo build --release

## test: the whole test suite (unit, property, integration, end-to-end)
test: setup
	cargo test --all-targets

## bench: criterion benchmarks (association, encoder, frame); every driver: bench/README.md
bench: setup
	cargo bench -p crossview-bench

## lint: format check and clippy on every crate of the workspace, benchmark drivers included,
## and the layout rules (no import circle between a crate's modules; in serve, core and train
## no file over 600 lines and no function over 100: scripts/check_layout.py --strict-sizes)
lint:
	cargo fmt --all --check
	cargo clippy --workspace --all-targets -- -D warnings
	python3 scripts/check_layout.py --strict-sizes

fmt:
	cargo fmt --all

.PHONY: loadtest loadtest-check smoke deploy-check

## loadtest: build the load generator (target/release/crossview-loadtest; see loadtest/README.md)
loadtest:
	cargo build --release -p crossview-loadtest

## loadtest-check: format, lint and unit-test the load generator alone
loadtest-check:
	cargo fmt -p crossview-loadtest --check
	cargo clippy -p crossview-loadtest --all-targets -- -D warnings
	cargo test -p crossview-loadtest

## deploy-check: validate deploy/k8s/*.yaml (Kubernetes 1.37 schemas, strict) and
## deploy/docker-compose.yml (compose-spec) without a cluster or an engine; installs its pinned
## validators into .cache/deploy-venv from PyPI the first time (scripts/check-deploy.sh)
deploy-check:
	bash scripts/check-deploy.sh

## smoke: build the container images and run the compose stack end to end under podman
## (slow, needs root; not part of CI; see deploy/README.md)
smoke: setup
	bash deploy/smoke.sh

## demo: the newcomer's tour — the real server in-process with models/demo.onnx, a simulated
## 4-camera scene streamed into it over gRPC, identities and running accuracy per frame; halfway
## a camera is bumped and fenced; the viewer stays up until Ctrl-C.
## Options pass through DEMO_ARGS, e.g. `make demo DEMO_ARGS="--frames 300 --noisy --exit"`.
demo: setup
	cargo build --release
	./target/release/crossview demo $(DEMO_ARGS)
