# DHG — the two commands that matter: `make demo` and `make test`. Each creates .venv, installs
# the pinned dependencies, builds the Rust extension, then runs.
SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON ?= python3
LOCK := requirements.lock
LOCK_HASH := $(shell sha256sum $(LOCK) | cut -c1-16)
# The virtualenv is cached outside the clone, keyed by the lock file's hash; .venv links to it.
DHG_CACHE ?= $(HOME)/.cache/dhg
VENV_CACHE := $(DHG_CACHE)/venv-$(LOCK_HASH)
VENV := .venv
VPY := $(VENV)/bin/python
# One cargo target dir shared by clones (a cache: a machine without it just builds from scratch).
export CARGO_TARGET_DIR ?= $(DHG_CACHE)/target
export VIRTUAL_ENV := $(abspath $(VENV))

.PHONY: help venv build demo test test-rust test-python lint bench clean

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-12s %s\n", $$1, $$2}'

$(VENV)/.ready-$(LOCK_HASH): $(LOCK)
	@if [ ! -f $(VENV_CACHE)/.complete ]; then \
	  echo ">> creating virtualenv $(VENV_CACHE) from $(LOCK)"; \
	  rm -rf $(VENV_CACHE) && mkdir -p $(DHG_CACHE) && \
	  $(PYTHON) -m venv $(VENV_CACHE) && \
	  $(VENV_CACHE)/bin/python -m pip install -q --upgrade pip && \
	  $(VENV_CACHE)/bin/python -m pip install -q -r $(LOCK) && \
	  touch $(VENV_CACHE)/.complete; \
	fi
	@rm -rf $(VENV) && ln -s $(VENV_CACHE) $(VENV)
	@touch $@

venv: $(VENV)/.ready-$(LOCK_HASH) ## create .venv with the pinned dependencies

build: venv ## build the Rust extension into .venv (maturin develop --release)
	PIP_QUIET=1 $(VENV)/bin/maturin develop --release -q

demo: build ## dhg-serve on the phantom + bundled model, a guided and an unguided virtual novice
	$(VENV)/bin/dhg live-demo --out out/demo

test: build ## cargo test + pytest
	cargo test --workspace -q
	$(VPY) -m pytest -q

lint: build ## clippy, rustfmt, ruff, stubtest
	cargo clippy --workspace --all-targets -q -- -D warnings
	cargo clippy -p bone_sim --features python -q -- -D warnings
	cargo fmt --all --check
	$(VENV)/bin/ruff check python tests
	$(VPY) -m mypy.stubtest dhg._bone_sim

bench: build ## criterion benches and the Python benchmarks (figures go in docs/benchmarks.md)
	$(VPY) tests/benchmarks/export_phantom_raw.py target/bench-data
	DHG_BENCH_DATA=$(abspath target/bench-data) cargo bench -p bone_sim
	$(VPY) tests/benchmarks/bench_volume.py
	$(VPY) tests/benchmarks/bench_session.py

clean: ## remove build outputs in the clone (keeps the caches)
	rm -rf $(VENV) out python/dhg/*.so
