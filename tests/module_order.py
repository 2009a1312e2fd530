"""The order the test modules are handed out in: the longest first (a pytest plugin).

``make test`` sends each test module whole to one xdist worker (``--dist loadfile``). xdist's own
order is by number of tests, and a module's number of tests says little about its length: one
test of a served sensor under continuous scan runs for seconds, 500 register checks for fewer.
Handed out last, such a module kept one worker busy while the others had finished (3 to 7 s at
the end of a quiet ``make test`` on 2 cores). Longest first, the short ones fill the gaps at the
end (the longest-processing-time rule).

Each module's length comes from ``tests/module_costs.json`` (seconds, from a whole run of the
fast tier); a module it does not know yet is placed as if each of its tests took
:data:`UNKNOWN_TEST_S`. The file only orders the run: a stale one makes no test pass or fail.
``make test-costs`` writes it again (``--record-module-costs PATH``).

The order is the same in every worker (xdist requires that they collect alike): it depends only
on the file and the collection.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import pytest

COSTS_PATH = Path(__file__).with_name("module_costs.json")

UNKNOWN_TEST_S = 0.05
"""The assumed length of each test of a module the costs file does not list (seconds; the fast
tier's tests average 0.064 s in a run of three workers on two cores). Only ``make test-costs``
on the whole fast tier should write the file: a run of some modules would leave out the rest."""

_durations: defaultdict[str, float] = defaultdict(float)
"""Seconds each module's tests took in this run, set-up and teardown included (the controller
writes them; every xdist worker's reports reach it)."""


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--record-module-costs",
        metavar="PATH",
        default=None,
        help="write each test module's seconds in this run to PATH (tests/module_costs.json)",
    )


def _module(nodeid: str) -> str:
    return nodeid.split("::", 1)[0]


def load_costs(path: Path = COSTS_PATH) -> dict[str, float]:
    """The recorded seconds per module, or none (a missing or unreadable file orders nothing)."""
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(raw, dict):
        return {}
    return {str(k): float(v) for k, v in raw.items() if isinstance(v, int | float)}


def longest_first(nodeids: list[str], costs: dict[str, float]) -> list[int]:
    """The indices of ``nodeids`` reordered module by module, the longest module first; the
    tests of a module keep their order and stay together, and equal costs keep the modules'
    collection order."""
    first_at: dict[str, int] = {}
    counts: defaultdict[str, int] = defaultdict(int)
    for i, nodeid in enumerate(nodeids):
        first_at.setdefault(_module(nodeid), i)
        counts[_module(nodeid)] += 1

    def cost(module: str) -> float:
        known = costs.get(module)
        return known if known is not None else counts[module] * UNKNOWN_TEST_S

    def key(i: int) -> tuple[float, int, int]:
        module = _module(nodeids[i])
        return (-cost(module), first_at[module], i)

    return sorted(range(len(nodeids)), key=key)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    costs = load_costs()
    if not costs:
        return
    order = longest_first([item.nodeid for item in items], costs)
    items[:] = [items[i] for i in order]


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    _durations[_module(report.nodeid)] += report.duration


def pytest_sessionfinish(session: pytest.Session) -> None:
    path = session.config.getoption("--record-module-costs")
    if path is None or hasattr(session.config, "workerinput"):
        return
    costs = {module: round(seconds, 2) for module, seconds in sorted(_durations.items())}
    Path(path).write_text(json.dumps(costs, indent=1) + "\n")
