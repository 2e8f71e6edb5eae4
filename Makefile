# One task runner: CI (.ci/run) calls the same targets. `make help` lists them.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
PY     := $(BIN)/python
# Release tooling (make wheel): maturin 1.x cross-links with zig against an old glibc, so the
# Linux wheel carries a manylinux tag from any build machine; auditwheel checks that tag.
MATURIN    := maturin>=1.16,<2
ZIGLANG    := ziglang==0.17.1
AUDITWHEEL := auditwheel>=6.1
MANYLINUX ?= manylinux_2_28

# What the installed m360 is built from. The release install copies python/ into site-packages,
# so the Python sources count too; the editable dev build reads them in place.
RUST_SRC := Cargo.toml Cargo.lock $(shell find rust -name '*.rs' -o -name Cargo.toml 2>/dev/null)
PY_SRC   := $(shell find python -name '*.py' -o -name '*.pyi' -o -name py.typed 2>/dev/null)
RELEASE_STAMP := $(VENV)/.m360-release
DEV_STAMP     := $(VENV)/.m360-dev
# `make test` uses the build the developer chose last: the dev build once `make build-dev` ran,
# the release build otherwise (a fresh machine, CI). Either is rebuilt only when out of date.
BUILT := $(if $(wildcard $(DEV_STAMP)),$(DEV_STAMP),$(RELEASE_STAMP))
EXTRAS := test,lint,bench,ray,3d
PYTEST_ARGS ?=

# The release install runs `pip install -v` so that the Rust build shows as it runs, but pip -v
# prints thousands of lines. PIP_PROGRESS (POSIX sh) reads that output, followed by a last line
# "m360-exit STATUS", and keeps pip's phases, cargo's Compiling/Finished lines, warnings and
# errors, with one dot per dependency collected; it exits with STATUS, after the last 40 lines of
# the whole log ($(VENV)/install.log) when STATUS is not 0.
PIP_PROGRESS = { dots=0; rc=1; \
  while IFS= read -r line; do case $$line in \
    "m360-exit "*) rc=$${line\#m360-exit };; \
    "Collecting "*) [ $$dots -gt 0 ] || printf '   collecting the dependencies '; \
      dots=$$((dots + 1)); printf .;; \
    *" Compiling "*|*" Finished "*|*"Downloaded "*" crates"*|*"Found pyo3"*|*"Built wheel"*|\
    "Processing "*|*"Building wheel for "*"started"|"Successfully built"*|*"warning: "*|*"error: "*|\
    *"error["*|"ERROR: "*|"WARNING: "*|"Successfully installed"*) \
      [ $$dots -eq 0 ] || { echo " $$dots"; dots=0; }; \
      case $$line in "Successfully installed"*) set -f; set -- $$line; \
        line="Successfully installed m360 and $$(($$\# - 3)) other packages";; esac; \
      printf '%s\n' "$$line";; \
  esac; done; [ $$dots -eq 0 ] || echo " $$dots"; \
  [ "$$rc" = 0 ] || { echo "pip failed (exit $$rc); the end of $(VENV)/install.log:"; \
    tail -n 40 $(VENV)/install.log; }; exit $$rc; }

.PHONY: help demo test lint format rust-test bench venv install build-dev wheel clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

$(BIN)/activate:
	@echo "==> m360: creating the virtual environment $(VENV)"
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

venv: $(BIN)/activate  ## create .venv (Python virtual environment)

$(RELEASE_STAMP): $(BIN)/activate pyproject.toml $(RUST_SRC) $(PY_SRC)
	rm -f $(DEV_STAMP) python/m360/_core*.so python/m360/_core*.pyd
	@echo "==> m360: installing m360[$(EXTRAS)] into $(VENV): the dependencies (about 1 min),"
	@echo "    then the Rust core m360._core, release build (3-5 min on 2 cores, 1-2 min on 8)"
	@echo '$(PY) -m pip install -v ".[$(EXTRAS)]"  (filtered; whole log: $(VENV)/install.log)'
	@{ $(PY) -m pip install -v ".[$(EXTRAS)]" 2>&1; echo "m360-exit $$?"; } \
	  | tee $(VENV)/install.log | $(PIP_PROGRESS)
	touch $@

$(DEV_STAMP): $(BIN)/activate pyproject.toml $(RUST_SRC)
	$(PY) -m pip install --quiet "$(MATURIN)"
	@echo "==> m360: maturin develop: the dependencies, then the Rust core, debug build"
	@echo "    (about 2 min on 2 cores the first time, seconds after a small change)"
	VIRTUAL_ENV=$(abspath $(VENV)) $(BIN)/maturin develop --extras $(EXTRAS)
	rm -f $(RELEASE_STAMP)
	touch $@

install: $(RELEASE_STAMP)  ## build the Rust extension (release) and install m360 with test/lint extras

build-dev: $(DEV_STAMP)  ## editable debug build into .venv (make test then rebuilds only what changed)

demo: $(BUILT)  ## the main job: m360.estimate on a synthetic panorama (simulated network), write out/
	$(BIN)/m360 demo -o out/

test: $(BUILT)  ## the test suite (pytest); make test PYTEST_ARGS='-m "not wheel"' skips the wheel test
	$(PY) -m pytest $(PYTEST_ARGS)

# The release profile, so that the extension's release build (make install) is reused: a debug
# build of the dependencies (faer above all) takes 5-8 min on 2 cores. Overflow checks and debug
# assertions stay on in the core itself, as in a debug build. The criterion benchmarks have their
# own crate (rust/m360-bench), whose dependencies would change shared crates' features. The
# bindings crate (m360-py) has no Rust tests: the Python suite tests it.
RUST_TEST_CONFIG := --config profile.release.package.m360-core.overflow-checks=true \
  --config profile.release.package.m360-core.debug-assertions=true

rust-test:  ## Rust unit tests of the core (release build, with overflow checks in the core)
	cargo test --release -p m360-core $(RUST_TEST_CONFIG)

$(VENV)/.wheel-tools: $(BIN)/activate Makefile
	@echo "==> m360: installing the release tools (maturin, zig: about 50 MB, auditwheel)"
	$(PY) -m pip install --quiet "$(MATURIN)" "$(ZIGLANG)" "$(AUDITWHEEL)"
	touch $@

# maturin runs `python -m ziglang` from PATH: the venv's bin comes first.
dist/.stamp: $(VENV)/.wheel-tools pyproject.toml README.md $(RUST_SRC) $(PY_SRC)
	rm -rf dist
	@echo "==> m360: the release wheel (maturin + zig: 3-5 min on 2 cores) and the sdist"
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/maturin build --release --zig \
	  --compatibility $(MANYLINUX) --out dist
	$(BIN)/maturin sdist --out dist
	$(BIN)/auditwheel show dist/*.whl
	touch $@

wheel: dist/.stamp  ## release wheel (abi3, manylinux_2_28 via zig) and sdist into dist/
	@ls -l dist/*.whl dist/*.tar.gz

lint: $(BUILT)  ## formatting, clippy, ruff, mypy, stub check of m360._core, actionlint
	cargo fmt --all --check
	cargo clippy --workspace --all-targets -- -D warnings
	$(BIN)/ruff check python tests benches
	$(BIN)/ruff format --check python tests benches
	$(BIN)/mypy
	cd /tmp && $(abspath $(PY)) -m mypy.stubtest m360._core
	$(BIN)/actionlint .github/workflows/*.yml

format: venv  ## rewrite: cargo fmt, ruff format, ruff check --fix
	$(PY) -m pip install --quiet "ruff>=0.6"
	cargo fmt --all
	$(BIN)/ruff format python tests benches
	$(BIN)/ruff check --fix python tests benches

bench: $(RELEASE_STAMP)  ## benchmark tables (see benches/), always on the release build
	$(PY) benches/bench_resample.py
	$(PY) benches/bench_align.py
	$(PY) benches/bench_blend.py
	$(PY) benches/bench_estimate.py
	$(PY) benches/bench_batch.py
	$(PY) benches/bench_threads.py
	$(PY) benches/bench_3d.py

clean:  ## remove build products and the virtual environment
	rm -rf target $(VENV) out dist python/m360/_core*.so
