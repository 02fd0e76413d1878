# Quick start: `make demo` (the main job) and `make test` (the test suite).
# Both create .venv with the package and what it needs, from this repository's own files.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
DOCS_STAMP := $(VENV)/.docs-installed-stamp
PYTEST_ARGS ?=
# the suite runs in 2 processes (pytest-xdist; one per core of the CI machine), test files kept
# whole per process so that each compiles its JAX programs once
WORKERS ?= 2
LINTED := rbo_jax tests benchmarks notebooks docs/_hooks
# pip installs without compiling every module of every dependency to bytecode (about 17 s of a
# 42 s install, most of it for modules never imported); the first import of a module compiles
# and writes its bytecode instead, so the recipes' processes may write it (a user's
# PYTHONDONTWRITEBYTECODE would otherwise have every process compile jax's modules again, ~4 s)
unexport PYTHONDONTWRITEBYTECODE

.PHONY: demo lint test test-slow test-all bench docs docs-test clean

$(STAMP): pyproject.toml
	$(PYTHON) -c 'import sys; assert sys.version_info >= (3, 10), "rbo_jax needs Python >= 3.10"'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --no-compile -e ".[test,plot,bench]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/rbo-jax reproduce --out out

# the code's lint and format (ruff, pinned in the test extra), then the tests
lint: $(STAMP)
	$(BIN)/ruff check $(LINTED)
	$(BIN)/ruff format --check $(LINTED)

# two tiers, by marker (docs/development.md): `make test` is the quick tier (every module's unit,
# physics and property tests; the README's test command), `make test-slow` the complete tier's
# other tests alone (notebooks, reproduce, real-process fault tests, benchmark smoke runs, large
# sizes, costly tests: marked `slow`), `make test-all` both. Compiled programs are kept in
# ~/.cache/rbo_jax/test-cache between runs (RBO_JAX_TEST_COMPILATION_CACHE=off: a cold run).
test: lint
	$(BIN)/python -m pytest -q -n $(WORKERS) --dist loadfile -m "not slow and not docs" $(PYTEST_ARGS)

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -n $(WORKERS) --dist loadfile -m "slow and not docs" $(PYTEST_ARGS)

test-all: test test-slow

bench: $(STAMP)
	$(BIN)/python benchmarks/run.py

# the documentation site into site/ (mkdocs.yml; the notebooks are executed, a few minutes), built
# strictly: a warning, a broken link or a public name without an API entry fails it
$(DOCS_STAMP): $(STAMP) pyproject.toml
	$(BIN)/python -m pip install --quiet -e ".[docs]"
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/python -m mkdocs build --strict

# the built site in headless Chromium (Debian: apt-get install chromium chromium-driver)
docs-test: docs
	RBO_DOCS_SITE=site $(BIN)/python -m pytest -q -m docs tests/test_docs_browser.py $(PYTEST_ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis out site .cache/docs-notebooks
	@echo "(the tests' compilation cache stays in ~/.cache/rbo_jax/test-cache: remove it by hand)"
