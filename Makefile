# DHG — the two commands that matter: `make demo` and `make test`. Each creates .venv, installs
# the pinned dependencies, builds the Rust extension, then runs.
SHELL := /bin/bash
.DEFAULT_GOAL := help

PYTHON ?= python3
LOCK := requirements.lock
LOCK_HASH := $(shell sha256sum $(LOCK) | cut -c1-16)
# Third-party packages live in a virtualenv cached outside the clone, keyed by the lock file's
# hash (torch alone is several GB). .venv is the clone's own small virtualenv: it sees the cached
# packages through a .pth file and holds only dhg, so two clones never import each other's code.
DHG_CACHE ?= $(HOME)/.cache/dhg
DEPS := $(DHG_CACHE)/venv-$(LOCK_HASH)
VENV := .venv
VPY := $(VENV)/bin/python
# One cargo target dir shared by clones (a cache: a machine without it just builds from scratch).
export CARGO_TARGET_DIR ?= $(DHG_CACHE)/target
export VIRTUAL_ENV := $(abspath $(VENV))
PURELIB := import sysconfig; print(sysconfig.get_paths()["purelib"])

.PHONY: help venv build browser demo test test-all test-rust test-python lint bench device-kit clean fuzz

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-12s %s\n", $$1, $$2}'

$(VENV)/.clone-ready-$(LOCK_HASH): $(LOCK)
	@if [ ! -f $(DEPS)/.complete ]; then \
	  echo ">> creating virtualenv $(DEPS) from $(LOCK)"; \
	  rm -rf $(DEPS) && mkdir -p $(DHG_CACHE) && \
	  $(PYTHON) -m venv $(DEPS) && \
	  $(DEPS)/bin/python -m pip install -q --upgrade pip && \
	  $(DEPS)/bin/python -m pip install -q -r $(LOCK) && \
	  touch $(DEPS)/.complete; \
	fi
	@# Earlier checkouts installed dhg into the shared virtualenv; only a clone's .venv holds it now.
	@if ls -d $(DEPS)/lib/python*/site-packages/dhg-*.dist-info >/dev/null 2>&1; then \
	  $(DEPS)/bin/python -m pip uninstall -q -y dhg; fi
	@rm -rf $(VENV) && $(DEPS)/bin/python -m venv --without-pip $(VENV)
	@$(DEPS)/bin/python -c '$(PURELIB)' > "$$($(VPY) -c '$(PURELIB)')/zz_dhg_deps.pth"
	@# The tools, so an activated .venv has them: the standalone binaries linked, and the Python
	@# ones as wrappers that run .venv's python (theirs in the cache could not import dhg).
	@for tool in maturin ruff; do ln -sf $(abspath $(DEPS))/bin/$$tool $(VENV)/bin/$$tool; done
	@for pair in "pytest pytest" "torchrun torch.distributed.run"; do set -- $$pair; \
	  printf '#!/bin/sh\nexec "$$(dirname "$$0")/python" -m %s "$$@"\n' $$2 > $(VENV)/bin/$$1; \
	  chmod +x $(VENV)/bin/$$1; done
	@touch $@

venv: $(VENV)/.clone-ready-$(LOCK_HASH) ## create .venv with the pinned dependencies

build: venv ## build the Rust extension into .venv (maturin develop --release)
	PIP_QUIET=1 $(VENV)/bin/maturin develop --release -q

demo: build browser ## dhg-serve on the phantom + bundled model, a guided and an unguided virtual novice
	$(VENV)/bin/dhg live-demo --out out/demo

BROWSER_PKGS := chromium chromium-driver
browser: ## Debian's Chromium and its driver, for the viewer's browser tests and demo screenshot (apt-get, once)
	@if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then \
	  echo ">> installing $(BROWSER_PKGS) (the viewer's tests drive a real headless Chromium)"; \
	  SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	  $$SUDO apt-get install -y -q --no-install-recommends $(BROWSER_PKGS) >/dev/null 2>&1 || \
	  { $$SUDO apt-get update -q >/dev/null && \
	    $$SUDO apt-get install -y -q --no-install-recommends $(BROWSER_PKGS) >/dev/null; } || \
	  { echo "cannot install $(BROWSER_PKGS): install them by hand (Debian/Ubuntu packages)"; exit 1; }; \
	fi

test: build browser ## cargo test + pytest (without the tests marked slow or gpu)
	cargo test --workspace -q
	$(VPY) -m pytest -q

test-all: test ## make test, then the tests marked slow (and gpu, which skip without CUDA); CI runs this
	$(VPY) -m pytest -q -m "slow or gpu"

FUZZ_SECONDS ?= 20
fuzz: ## build the libFuzzer targets on stable Rust and run each FUZZ_SECONDS (20) from its seed corpus
	FUZZ_TARGET_DIR=$(DHG_CACHE)/fuzz-target fuzz/run.sh $(FUZZ_SECONDS)

lint: build ## clippy, rustfmt, ruff, mypy (the package), stubtest, and both lock files up to date
	cargo metadata --locked --format-version 1 > /dev/null
	cd fuzz && cargo metadata --locked --format-version 1 > /dev/null
	cargo clippy --workspace --all-targets -q -- -D warnings
	cargo clippy -p bone_sim --features python -q -- -D warnings
	cargo fmt --all --check
	$(VENV)/bin/ruff check python tests
	$(VENV)/bin/ruff format --check python tests
	$(VPY) -m mypy python/dhg
	$(VPY) -m mypy.stubtest dhg._bone_sim

bench: build ## criterion benches and the Python benchmarks (figures go in docs/benchmarks.md)
	$(VPY) tests/benchmarks/export_phantom_raw.py target/bench-data
	DHG_BENCH_DATA=$(abspath target/bench-data) cargo bench -p bone_sim
	$(VPY) tests/benchmarks/bench_volume.py
	$(VPY) tests/benchmarks/bench_session.py

device-kit: venv ## pack .devkit for the runs on a lent 16-core machine (tests/benchmarks/device/run.sh there)
	tests/benchmarks/device/pack.sh

clean: ## remove build outputs in the clone (keeps the caches)
	rm -rf $(VENV) out .devkit python/dhg/*.so
