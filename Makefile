# The two commands of the quick start: `make run` (the simulated car) and `make test`; `make` alone lists every
# target (each target's `## ` comment is its line in `make help`).
# Both create a venv on first use and install what they need into it. See docs/testing.md for the other test targets.
.DEFAULT_GOAL := help

# One venv per Python version, so that PYTHON picks the interpreter the tests run on: .venv for the default python3,
# .venv<major><minor> for another (make test PYTHON=python3.13 uses .venv313, as .ci/run does). A VENV made by
# another version than PYTHON's is refused with the command that fixes it, never used silently.
PYTHON ?= python3
VERSION_OF = $(shell $(1) -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)
PYVER  := $(call VERSION_OF,$(PYTHON))
VENV   ?= $(if $(filter $(PYVER),$(call VERSION_OF,python3)),.venv,.venv$(subst .,,$(PYVER)))
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip -q --disable-pip-version-check

# checked for every goal but help (bare make) and clean, which must work whatever the venv
ifneq ($(filter-out help clean,$(or $(MAKECMDGOALS),help)),)
ifeq ($(PYVER),)
$(error PYTHON=$(PYTHON) does not run: name a Python 3.11, 3.12 or 3.13 interpreter, e.g. make test PYTHON=python3.13)
endif
VENV_PYVER := $(if $(wildcard $(PY)),$(call VERSION_OF,$(PY)))
ifneq ($(VENV_PYVER),)
ifneq ($(VENV_PYVER),$(PYVER))
$(error $(VENV) was made by Python $(VENV_PYVER), but PYTHON=$(PYTHON) is Python $(PYVER): $(if $(filter file,$(origin VENV)),remove it with make clean and run make again,leave VENV unset (Python $(PYVER) gets .venv$(subst .,,$(PYVER))) or remove it first: make clean VENV=$(VENV)))
endif
endif
endif

.PHONY: help run test test-fast test-loaded test-aarch64 lint format bench dist clean

help:  ## list the targets (what bare `make` does)
	@echo "make <target> [PYTHON=python3.13] [ARGS=...] [PYTEST_ARGS=...]; venv for PYTHON=$(PYTHON): $(VENV)"
	@grep -hE '^[a-zA-Z0-9_-]+:.*## ' $(MAKEFILE_LIST) | sed -E 's/^([a-zA-Z0-9_-]+):.*## (.*)$$/\1\t\2/' | \
		awk -F '\t' '{ printf "  %-13s %s\n", $$1, $$2 }'

$(VENV)/.base: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PIP) install --upgrade pip
	$(PIP) install -e .
	touch $@

# Donkeycar's own pins would pull numpy < 2 (5.3) and dozens of packages its car code does not import: install
# it without its dependencies, beside the ones its code we run needs (the `donkeycar` extra), so the interop
# tests (its parts, its test suite and a car made by `donkey createcar` on our loop, its reader on our tubs)
# and the benchmark comparisons always run. Donkeycar 5.3 installs only on Python 3.11, 5.4 on 3.12 and 3.13.
DONKEYCAR := "donkeycar==5.3.0; python_version < '3.12'" "donkeycar~=5.4.0; python_version >= '3.12'"

$(VENV)/.test: $(VENV)/.base
	$(PIP) install -e '.[test,donkeycar-cli,mcap,tflite,quantize,zenoh]'
	$(PIP) install --no-deps $(DONKEYCAR)
	touch $@

# The web controller's browser tests drive Debian's chromium through Playwright: Playwright's own browser download
# cannot work on the car's machines (no internet beyond package registries). Installed here, once, before the tests
# (nothing to do when it is there); apt-get needs root, so elsewhere this stops with the command to run.
CHROMIUM ?= $(or $(ASYNCDONKEY_CHROMIUM),/usr/bin/chromium)

$(CHROMIUM):
	@if [ "$$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then \
		echo "the browser tests need Chromium at $@: run 'sudo apt-get install -y chromium' (or set" \
			"ASYNCDONKEY_CHROMIUM to a Chromium binary), or leave them out: make test-fast" >&2; \
		exit 1; \
	fi
	DEBIAN_FRONTEND=noninteractive apt-get update -q
	DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium
	@test -x $@ || { echo "apt-get installed chromium, but not at $@" >&2; exit 1; }

# What is deterministic and fast: the tests on the virtual clock and the plain unit tests, none of the kinds that
# need real time, a browser, Donkeycar, sockets or processes (the markers, docs/testing.md).
FAST := not realtime and not browser and not donkeycar and not network and not subprocess

# ARGS go to `asyncdonkey run`: its own options first, then the car's after a lone --, e.g.
# make run ARGS="-- --seconds 120" or make run ARGS="--hz 50 -- --laps 3" (docs/simulator.md lists them).
# Afterwards the commands are in the venv: .venv/bin/asyncdonkey, .venv/bin/python (docs/cli.md).
run: $(VENV)/.base  ## drive the simulated car for 25 s (ARGS go to asyncdonkey run; docs/simulator.md)
	$(VENV)/bin/asyncdonkey run examples/car.py $(ARGS)

# The type check: mypy, strict on the safety, time and drive-core modules, elsewhere capped by .ci/mypy-ceiling.txt
TYPECHECK := $(PY) .ci/mypy-ceiling

test: $(VENV)/.test $(CHROMIUM)  ## ruff, mypy and the whole suite (needs Chromium; about 9 min on 2 cores)
	$(VENV)/bin/ruff check .
	$(TYPECHECK)
	$(PY) -m pytest $(PYTEST_ARGS)

# The edit-and-test loop keeps pytest's rewritten test modules in __pycache__ (ignored by git) even where the
# environment sets PYTHONDONTWRITEBYTECODE: without them each worker rewrites and compiles some 350 modules on every
# run, and collecting takes 11 s instead of 3-4 s (docs/testing.md).
test-fast: $(VENV)/.test  ## the deterministic tests on every core, no browser, sockets or processes (about 50 s)
	$(VENV)/bin/ruff check .
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -n auto -m "$(FAST)" $(PYTEST_ARGS)

# The whole suite beside one busy process per core: a loaded machine, as a shared CI runner is. Each busy process
# spins until the shell that started it is gone, so none outlives the run, however it ends; the shell also kills
# them as soon as pytest returns (or is interrupted), and exits with pytest's status.
BUSY := import os, itertools; parent = os.getppid(); any(os.getppid() != parent for _ in itertools.count())

test-loaded: $(VENV)/.test $(CHROMIUM)  ## the whole suite beside one busy process per core
	$(VENV)/bin/ruff check .
	@busy=""; \
	for _ in $$(seq "$$(nproc)"); do $(PY) -c '$(BUSY)' >/dev/null 2>&1 & busy="$$busy $$!"; done; \
	trap 'kill $$busy 2>/dev/null' EXIT; \
	trap 'exit 130' INT TERM; \
	echo "test-loaded: $$(nproc) busy processes ($$busy ) beside the suite"; \
	$(PY) -m pytest $(PYTEST_ARGS)

# The fast suite on the Raspberry Pi's architecture and Python: an arm64 Debian 12 root (Raspberry Pi OS Bookworm's
# base), made once with debootstrap, runs make test-fast under qemu-user. Needs root; not in CI: it is slow (on 2
# cores: the root 7 min and its venv 6.5 min once, then the suite ~10 min). What it proves: docs/raspberry-pi.md.
test-aarch64:  ## the fast suite in an arm64 Debian 12 root under qemu-user (as root; slow; not in CI)
	.ci/test-aarch64 $(PYTEST_ARGS)

lint: $(VENV)/.test  ## ruff check, ruff format --check and the type check
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(TYPECHECK)

format: $(VENV)/.test  ## ruff format the sources
	$(VENV)/bin/ruff format .

bench: $(VENV)/.test  ## the benchmarks beside Donkeycar; rewrites docs/benchmarks.md
	$(PY) benchmarks/run_all.py --write-docs

# The wheel and the sdist, built by the standard frontend (python -m build, in an isolated environment with the
# setuptools pyproject.toml asks for); the version is asyncdonkey.__version__. Install the wheel anywhere with
# pip install 'dist/asyncdonkey-<version>-py3-none-any.whl[mcap]' (docs/install.md).
dist: $(VENV)/.base  ## build the wheel and the sdist into dist/
	$(PIP) install 'build>=1.2'
	rm -rf dist
	$(PY) -m build --outdir dist .

clean:  ## remove the venvs, the caches and the build output
	rm -rf $(VENV) .venv3[0-9]* .pytest_cache .ruff_cache .mypy_cache build dist *.egg-info src/*.egg-info
