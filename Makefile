# The two commands of the quick start: `make run` (the simulated car) and `make test`.
# Both create .venv on first use and install what they need into it.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip -q --disable-pip-version-check

.PHONY: run test lint format bench clean

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
	$(PIP) install -e '.[test,donkeycar,mcap,tflite,quantize,zenoh]'
	$(PIP) install --no-deps $(DONKEYCAR)
	touch $@

run: $(VENV)/.base
	$(VENV)/bin/asyncdonkey run examples/car.py $(ARGS)

test: $(VENV)/.test
	$(VENV)/bin/ruff check .
	$(PY) -m pytest $(PYTEST_ARGS)

lint: $(VENV)/.test
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(VENV)/.test
	$(VENV)/bin/ruff format .

bench: $(VENV)/.test
	$(PY) benchmarks/run_all.py --write-docs

clean:
	rm -rf $(VENV) .venv3[0-9]* .pytest_cache .ruff_cache build *.egg-info src/*.egg-info
