# Quick start: `make demo` (the main job) and `make test` (the test suite).
# Both create .venv with the package and what it needs, from this repository's own files.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
PYTEST_ARGS ?=
# the suite runs in 2 processes (pytest-xdist; one per core of the CI machine), test files kept
# whole per process so that each compiles its JAX programs once
WORKERS ?= 2
LINTED := rbo_jax tests benchmarks notebooks

.PHONY: demo lint test test-all bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 10), "rbo_jax needs Python >= 3.10"'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,plot,bench]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/rbo-jax reproduce --out out

# the code's lint and format (ruff, pinned in the test extra), then the tests
lint: $(STAMP)
	$(BIN)/ruff check $(LINTED)
	$(BIN)/ruff format --check $(LINTED)

test: lint
	$(BIN)/python -m pytest -q -n $(WORKERS) --dist loadfile -m "not slow" $(PYTEST_ARGS)

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -n $(WORKERS) --dist loadfile $(PYTEST_ARGS)

bench: $(STAMP)
	$(BIN)/python benchmarks/run.py

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis out
