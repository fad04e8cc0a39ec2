# crossview — the two commands a newcomer needs are `make demo` and `make test`.
SHELL := /bin/bash
ORT_DYLIB_PATH ?= $(CURDIR)/.cache/onnxruntime/libonnxruntime.so.1.31.1
export ORT_DYLIB_PATH

.PHONY: setup build test bench lint fmt demo

## setup: fetch the ONNX Runtime library from PyPI into .cache/ (once)
setup:
	@bash scripts/setup.sh

build: setup
	cargo build --release

## test: the whole test suite (unit, property, integration, end-to-end)
test: setup
	cargo test --all-targets

## bench: criterion benchmarks (encoder, association; see BENCHMARKS.md)
bench: setup
	cargo bench

lint:
	cargo fmt --check
	cargo clippy --all-targets -- -D warnings

fmt:
	cargo fmt

.PHONY: loadtest loadtest-check smoke

## loadtest: build the load generator (target/release/crossview-loadtest; see loadtest/README.md)
loadtest:
	cargo build --release -p crossview-loadtest

## loadtest-check: format, lint and unit-test the load generator (a separate workspace package)
loadtest-check:
	cargo fmt -p crossview-loadtest --check
	cargo clippy -p crossview-loadtest --all-targets -- -D warnings
	cargo test -p crossview-loadtest

## smoke: build the container images and run the compose stack end to end under podman
## (slow, needs root; not part of CI; see deploy/README.md)
smoke: setup
	bash deploy/smoke.sh

## demo: the newcomer's tour — the real server in-process with models/demo.onnx, a simulated
## 4-camera scene streamed into it over gRPC, identities and running accuracy per frame.
## Options pass through DEMO_ARGS, e.g. `make demo DEMO_ARGS="--frames 300 --noisy"`.
demo: setup
	cargo build --release
	./target/release/crossview demo $(DEMO_ARGS)
