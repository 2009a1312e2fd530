# Every target creates .venv on first use and installs the project from pyproject.toml.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
LINT_DIRS := biris_hw regs sim benchmarks tests $(wildcard tools)
# pytest keeps its rewritten test modules in __pycache__ (git-ignored); an environment that sets
# PYTHONDONTWRITEBYTECODE makes every run rewrite all of them again (about 10 s on 2 cores)
PYTEST := env -u PYTHONDONTWRITEBYTECODE $(PY) -m pytest

.PHONY: test test-slow test-under-load demo lint bench clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev,demo,toml,bench,can,net,record]'
	@touch $(STAMP)

test: $(STAMP)
	$(PYTEST) -m "not slow" -q -n auto

test-slow: $(STAMP)
	$(PYTEST) -m slow -q

# The fast tier with three CPU-bound processes beside it (sim.hostload), as on a shared machine.
test-under-load: $(STAMP)
	$(PY) tools/under_load.py --processes 3 -- $(PYTEST) -m "not slow" -q -n auto

demo: $(STAMP)
	$(VENV)/bin/biris demo

lint: $(STAMP)
	$(VENV)/bin/ruff check $(LINT_DIRS)
	$(VENV)/bin/ruff format --check $(LINT_DIRS)
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports --no-cache

bench: $(STAMP)
	$(PY) -m benchmarks

clean:
	rm -rf $(VENV) build .pytest_cache .mypy_cache .ruff_cache
