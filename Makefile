# crossview — the two commands a newcomer needs are `make demo` and `make test`.
SHELL := /bin/bash
ORT_DYLIB_PATH ?= $(CURDIR)/.cache/onnxruntime/libonnxruntime.so.1.31.1
export ORT_DYLIB_PATH

.PHONY: setup build test lint fmt demo

## setup: fetch the ONNX Runtime library from PyPI into .cache/ (once)
setup:
	@bash scripts/setup.sh

build: setup
	cargo build --release

## test: the whole test suite (unit, property, integration, end-to-end)
test: setup
	cargo test --all-targets

lint:
	cargo fmt --check
	cargo clippy --all-targets -- -D warnings

fmt:
	cargo fmt

## demo: the newcomer's tour — the real server in-process with models/demo.onnx, a simulated
## 4-camera scene streamed into it over gRPC, identities and running accuracy per frame.
## Options pass through DEMO_ARGS, e.g. `make demo DEMO_ARGS="--frames 300 --noisy"`.
demo: setup
	cargo build --release
	./target/release/crossview demo $(DEMO_ARGS)
