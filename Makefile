# Every target creates .venv on first use and installs the project from pyproject.toml.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
LINT_DIRS := biris_hw regs sim benchmarks tests $(wildcard tools)
# pytest keeps its rewritten test modules in __pycache__ (git-ignored); an environment that sets
# PYTHONDONTWRITEBYTECODE makes every run rewrite all of them again (about 10 s on 2 cores)
PYTEST := env -u PYTHONDONTWRITEBYTECODE $(PY) -m pytest
# pytest-xdist workers: one per core and two more. The scaled-real-time tests spend part of their
# time waiting on the wall clock; the extra workers compute meanwhile. Measured on 2 cores (a VM
# whose speed varies up to 2x from minute to minute), 4 workers against 3: quiet, faster in four
# of five alternated pairs one day (49.9-64.8 s against 56.6-68.9 s) and even on a slower day
# (75.9-79.5 s against 77.8-79.1 s: 10 s more CPU, one more collection and more contention, for
# the idle time they filled); beside three CPU-bound processes 116.2-141.7 s in seven runs of
# seven, all passed, against 142.4-156.2 s for 3 (the suite's share of the machine 54 % against
# 46 %). More workers leave each one's real-time threads less of the machine, which the realtime
# tests must bear: a scaled-time VM-USB test's move was once called stalled so (its simulator
# 48 ms behind its clock), in an earlier version, not since. 5 workers were slower (69-94 s
# quiet: a quarter more CPU).
# A test file's tests go to one worker (--dist loadfile), so a module's shared fixture (a served
# sensor, the demo run) is built once, not once per worker that gets one of its tests; the
# longest modules go first (tests/module_order.py, from tests/module_costs.json: make test-costs)
WORKERS ?= $(shell $(PYTHON) -c 'import os; n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(); print((n or 1) + 2)')

.PHONY: test test-costs test-slow test-under-load demo lint bench clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev,demo,toml,bench,can,net,record]'
	@touch $(STAMP)

# pytest rewrites the asserts of every test module the first time it imports it (about 11 s of
# CPU for the whole suite) and caches the result in __pycache__; on a fresh clone each xdist
# worker would do it at once, three times over (make test took 124 s cold against 95 s warm).
# Collecting once first, in one process, when nothing is cached yet, leaves them the cache.
REWRITTEN := $(wildcard tests/__pycache__/conftest.*-pytest-*.pyc)

test: $(STAMP)
	@$(if $(REWRITTEN),true,$(PYTEST) -m "not slow" -q --collect-only >/dev/null || true)
	$(PYTEST) -m "not slow" -q -n $(WORKERS) --dist loadfile --no-loadscope-reorder

# The fast tier once, writing each module's seconds to tests/module_costs.json (the order above)
test-costs: $(STAMP)
	$(PYTEST) -m "not slow" -q -n $(WORKERS) --dist loadfile --no-loadscope-reorder --record-module-costs tests/module_costs.json

# One process: with xdist workers the slow tier's scaled-time tests load each other (docs/development.md)
test-slow: $(STAMP)
	$(PYTEST) -m slow -q

# The fast tier with three CPU-bound processes beside it (sim.hostload), as on a shared machine.
test-under-load: $(STAMP)
	$(PY) tools/under_load.py --processes 3 -- $(PYTEST) -m "not slow" -q -n $(WORKERS) --dist loadfile --no-loadscope-reorder

demo: $(STAMP)
	$(VENV)/bin/biris demo

lint: $(STAMP)
	$(VENV)/bin/ruff check --no-cache $(LINT_DIRS)
	$(VENV)/bin/ruff format --no-cache --check $(LINT_DIRS)
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports --no-cache

bench: $(STAMP)
	$(PY) -m benchmarks

clean:
	rm -rf $(VENV) build .pytest_cache .mypy_cache .ruff_cache
