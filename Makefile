# Every target creates .venv on first use and installs the project from pyproject.toml.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
LINT_DIRS := biris_hw regs sim benchmarks tests $(wildcard tools)
# pytest keeps its rewritten test modules in __pycache__ (git-ignored); an environment that sets
# PYTHONDONTWRITEBYTECODE makes every run rewrite all of them again (about 10 s on 2 cores)
PYTEST := env -u PYTHONDONTWRITEBYTECODE $(PY) -m pytest
# pytest-xdist workers: one per core and one more. The scaled-real-time tests spend part of their
# time waiting on the wall clock; the extra worker computes meanwhile. Measured on 2 cores (the
# VM's own speed varied up to 2x from minute to minute): quiet, in five alternated pairs, 4
# workers took 49.9-64.8 s (the machine 7-10 % idle) against 56.6-68.9 s for 3 (16-20 % idle),
# faster in four pairs; 5 were slower (69-94 s: a quarter more CPU). Beside three CPU-bound
# processes 4 were faster in four runs of five (86-154 s against 126-156 s, before 3 came down
# to 121-128 s) by taking more of the machine from them, and left each worker's threads less of
# it: a scaled-time VM-USB test's simulator once fell 48 ms behind its clock and its move was
# called stalled. A suite that passes under load is worth more than 5 s quiet. On a slower day
# (three alternated pairs) 4 workers were no faster quietly: 75.9-79.5 s against 77.8-79.1 s,
# with 10 s more CPU (one more collection, more contention) for the idle time they filled; under
# load they passed seven runs of seven in the tree in 116.2-141.7 s (3: 142.4-156.2 s), then in
# a clean clone tests/test_net.py's first scan came back partial with no acquisition (marked so)
# and the test, waiting for one, failed: 4 stay out until such tests scan again after a cut scan.
# A test file's tests go to one worker (--dist loadfile), so a module's shared fixture (a served
# sensor, the demo run) is built once, not once per worker that gets one of its tests; the
# longest modules go first (tests/module_order.py, from tests/module_costs.json: make test-costs)
WORKERS ?= $(shell $(PYTHON) -c 'import os; n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(); print((n or 1) + 1)')

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
