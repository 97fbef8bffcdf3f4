# knotlab: `make run` sets up and runs the main job; `make test` sets up and passes the tests
# (all of them: CI); `make check` is the fast loop (lint + the tests not marked slow or browser).
# Each creates .venv idempotently (re-installing only when pyproject.toml changes).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
# One BLAS thread per process: we parallelise over processes, never inside BLAS.
export OMP_NUM_THREADS ?= 1
export OPENBLAS_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1

.PHONY: run test check lint format system-deps clean

$(BIN)/activate:
	$(PYTHON) -m venv $(VENV)

$(VENV)/.installed-run: pyproject.toml | $(BIN)/activate
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml | $(BIN)/activate
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test]"
	touch $@ $(VENV)/.installed-run

run: $(VENV)/.installed-run
	$(BIN)/knotlab app

system-deps:
	bash scripts/install_system_deps.sh

lint: $(VENV)/.installed-test
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

format: $(VENV)/.installed-test
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

test: $(VENV)/.installed-test system-deps lint
	$(BIN)/python -m pytest -n 2 --dist loadgroup -q --durations=15

# No root needed: tests that need a missing PostgreSQL skip; Chromium's are `browser`, deselected.
check: lint
	$(BIN)/python -m pytest -m "not slow and not browser" -n 2 --dist loadgroup -q

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
