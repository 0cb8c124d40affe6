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

# Donkeycar's own pins would pull numpy < 2: install it without its dependencies, beside ours, so the
# interop tests (its parts on our loop, its reader on our tubs) and the benchmark comparisons always run.
$(VENV)/.test: $(VENV)/.base
	$(PIP) install -e '.[test]'
	$(PIP) install --no-deps donkeycar==5.3.0 pyfiglet pillow
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
	$(PY) benchmarks/run_all.py --write-readme

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache build *.egg-info src/*.egg-info
