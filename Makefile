# One task runner: CI (.ci/run) calls the same targets. `make help` lists them.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
PY     := $(BIN)/python

.PHONY: help demo test lint rust-test bench venv install clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

$(BIN)/activate:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

venv: $(BIN)/activate  ## create .venv (Python virtual environment)

install: venv  ## build the Rust extension (release) and install m360 with test/lint extras
	$(PY) -m pip install --quiet ".[test,lint,bench]"

demo: install  ## the main job: m360.estimate on a synthetic panorama (simulated network), write out/
	$(BIN)/m360 demo -o out/

test: install  ## the test suite (pytest)
	$(PY) -m pytest

rust-test:  ## Rust unit tests of the core
	cargo test --workspace

lint: install  ## formatting, clippy, ruff, mypy and the stub check of m360._core
	cargo fmt --all --check
	cargo clippy --workspace --all-targets -- -D warnings
	$(BIN)/ruff check python tests benches
	$(BIN)/ruff format --check python tests benches
	$(BIN)/mypy
	cd /tmp && $(abspath $(PY)) -m mypy.stubtest m360._core

bench: install  ## benchmark tables (see benches/)
	$(PY) benches/bench_resample.py
	$(PY) benches/bench_align.py
	$(PY) benches/bench_blend.py
	$(PY) benches/bench_estimate.py
	$(PY) benches/bench_batch.py

clean:  ## remove build products and the virtual environment
	rm -rf target $(VENV) out
