"""The order test modules are handed to the xdist workers (tests/module_order.py)."""

from __future__ import annotations

import json
from pathlib import Path

from tests.module_order import COSTS_PATH, UNKNOWN_TEST_S, load_costs, longest_first

IDS = [
    "tests/test_a.py::one",
    "tests/test_a.py::two",
    "tests/test_b.py::one",
    "tests/test_c.py::one",
    "tests/test_c.py::two",
    "tests/test_c.py::three",
]


def _modules(order: list[int]) -> list[str]:
    return [IDS[i] for i in order]


def test_the_longest_module_goes_first_and_each_keeps_its_tests_together_in_order() -> None:
    order = longest_first(IDS, {"tests/test_a.py": 1.0, "tests/test_b.py": 9.0})
    # test_c is unknown: three tests at UNKNOWN_TEST_S each, shorter than test_a's second
    assert 3 * UNKNOWN_TEST_S < 1.0
    assert _modules(order) == [
        "tests/test_b.py::one",
        "tests/test_a.py::one",
        "tests/test_a.py::two",
        "tests/test_c.py::one",
        "tests/test_c.py::two",
        "tests/test_c.py::three",
    ]


def test_equal_costs_keep_the_collection_order() -> None:
    costs = {"tests/test_a.py": 2.0, "tests/test_b.py": 2.0, "tests/test_c.py": 2.0}
    assert longest_first(IDS, costs) == list(range(len(IDS)))


def test_a_missing_or_broken_costs_file_orders_nothing(tmp_path: Path) -> None:
    assert load_costs(tmp_path / "none.json") == {}
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    assert load_costs(broken) == {}
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2]")
    assert load_costs(listed) == {}
    mixed = tmp_path / "mixed.json"
    mixed.write_text(json.dumps({"tests/test_a.py": 1.5, "tests/test_b.py": "soon"}))
    assert load_costs(mixed) == {"tests/test_a.py": 1.5}


def test_the_checked_in_costs_are_read() -> None:
    """A stale entry only orders the run less well; a file that cannot be read orders nothing."""
    assert load_costs(COSTS_PATH), "tests/module_costs.json is missing or empty: make test-costs"
