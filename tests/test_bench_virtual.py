"""The virtual-time benchmark: registered, loss-checked, and in the report in quick mode.

Benchmarks never fail the build, so nothing here judges a target: the quick run must go
through the harness into report.json with both figures, measured and self-consistent, and the
loss check must name each way a window can fail to be loss-free.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from benchmarks.harness import SECTIONS, main, registry
from benchmarks.virtual_time import LOSSES, _ceiling, _unaccounted


def test_virtual_time_is_a_registered_section() -> None:
    assert "virtual_time" in SECTIONS and "virtual_time" in registry.benchmarks()


def test_a_loss_free_window_has_no_problems() -> None:
    before = {"acquisitions_in_scans": 10, "constant_azimuth": 1, **dict.fromkeys(LOSSES, 0)}
    after = {**before, "acquisitions_in_scans": 110, "constant_azimuth": 5}
    assert _unaccounted(104, before, after, 0, []) == (104, [])


@pytest.mark.parametrize("counter", LOSSES)
def test_every_loss_counter_is_named(counter: str) -> None:
    after = {"acquisitions_in_scans": 100, counter: 2}
    received, problems = _unaccounted(100, {}, after, 0, [])
    assert received == 100 and problems == [f"{counter} 2"]


def test_made_against_received_client_drops_and_the_audit_are_named() -> None:
    after = {"acquisitions_in_scans": 90, "constant_azimuth": 5}
    received, problems = _unaccounted(100, {}, after, 3, ["COMMAND written while busy"])
    assert received == 95
    assert problems == [
        "the simulator made 100 acquisitions, the server received 95",
        "the DATA connection dropped 3 scans",
        "audit: COMMAND written while busy",
    ]


@pytest.mark.slow
def test_quick_run_writes_both_figures_to_the_report(tmp_path: Path) -> None:
    assert main(["--out", str(tmp_path), "--only", "virtual_time", "--quick"]) == 0
    doc: dict[str, Any] = json.loads((tmp_path / "report.json").read_text())
    section = doc["virtual_time"]
    assert section["status"] == "ok", section.get("error")
    figures = section["figures"]
    assert set(figures) == {"scan360"}
    for fig in figures.values():
        assert fig["met"] in (True, False) and len(fig["method"]) > 200
        assert all(v is not None and math.isfinite(v) for v in fig["values"].values())

    scan360 = figures["scan360"]
    v = scan360["values"]
    assert scan360["unit"] == "s" and scan360["target"]["text"] == "p50 <= 0.5"
    assert v["n"] == 4 and 0 < v["min"] <= v["p50"] <= v["max"]
    assert v["acquisitions"] > 40 and v["hw_s"] > 2.0  # a whole revolution, at 64 samples


@pytest.mark.slow
def test_the_virtual_ceiling_is_a_loss_free_cpu_figure() -> None:
    """``throughput.virtual_ceiling``, which the throughput section reports beside its own."""
    ceiling = _ceiling(15.0)
    assert ceiling.key == "throughput.virtual_ceiling"
    assert ceiling.unit == "acq/cpu-s"
    assert ceiling.target is not None and ceiling.target.on == "acq_per_cpu_s"
    v = ceiling.values
    assert all(math.isfinite(value) for value in v.values())
    assert v["hw_s"] >= 15.0 and v["acquisitions"] > 10 * v["hw_s"]  # ~15/s with turn-arounds
    assert v["acq_per_cpu_s"] == pytest.approx(v["acquisitions"] / v["cpu_s"])
    assert v["hw_s_per_wall_s"] == pytest.approx(v["hw_s"] / v["wall_s"])
    assert v["scans_read"] >= 5
