"""The server benchmarks run end to end in quick mode and produce figures worth reading.

Benchmarks never fail the build, so these tests do not judge targets: they check that every
section runs through the harness, that each figure has samples and a plausible unit and value,
and that a figure this machine cannot measure (the pinned latencies without CPU affinity) says
what it needs instead. Each section is run once per module and its outcome shared.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from benchmarks.floor import hand_over_floor
from benchmarks.harness import BenchContext, Figure, Outcome, registry, run_one
from benchmarks.report import collect_meta, write_reports
from sim.clock import SimClock
from sim.irqgate import InterruptGate

UNITS = {
    "latency_us": "us",
    "presentation_ms": "ms",
    "throughput": "acq/s",
    "fanout": "ms",
    "sweep_gap_ms": "ms",
}
"""Unit of each section's figures..."""
KEY_UNITS = {"latency_us.server_over_floor": "x", "throughput.virtual_ceiling": "acq/cpu-s"}
"""... but for these: a ratio in a section of times, a CPU cost beside a rate."""


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Outcome]:
    """Each section run once in quick mode, however many tests look at it."""
    outcomes: dict[str, Outcome] = {}

    def run(section: str) -> Outcome:
        if section not in outcomes:
            bench = registry.benchmarks()[section]
            work = tmp_path_factory.mktemp(section)
            outcomes[section] = run_one(bench, BenchContext(quick=True, work_dir=work))
        outcome = outcomes[section]
        assert outcome.status in ("ok", "skipped"), outcome.traceback or outcome.error
        if outcome.status == "skipped":
            assert outcome.reason
        return outcome

    return run


def _measured(fig: Figure) -> bool:
    """A figure either carries samples or says, with n = 0, what it needs to be measured."""
    if fig.method.startswith("NOT MEASURED"):
        assert "needs" in fig.method
        assert fig.values == {"n": 0.0}
        return False
    assert fig.method and len(fig.method) > 40
    assert all(math.isfinite(v) for v in fig.values.values()), fig.values
    return True


@pytest.mark.slow
@pytest.mark.parametrize("section", sorted(UNITS))
def test_section_runs_in_quick_mode(section: str, quick_run: Callable[[str], Outcome]) -> None:
    outcome = quick_run(section)
    if outcome.status == "skipped":
        return
    assert outcome.figures
    measured = [fig for fig in outcome.figures if _measured(fig)]
    assert measured, "no figure of the section was measured"
    for fig in outcome.figures:
        assert fig.unit == KEY_UNITS.get(fig.key, UNITS[section])
        assert fig.target is not None or "No target" in fig.method or section == "fanout"
    for fig in measured:
        if fig.key == "latency_us.server_over_floor":
            assert fig.values["ratio"] > 0
        elif fig.key == "throughput.virtual_ceiling":
            assert fig.values["acq_per_cpu_s"] > 0 and fig.values["acquisitions"] > 0
        elif section == "throughput":
            assert fig.values["acq_per_s"] > 0
            assert fig.values["samples"] == 128
            assert 0 < fig.values["cpu_percent"] < 400
        else:
            assert fig.values["n"] > 0
            assert 0 < fig.values["p99"] <= fig.values["max"]
            assert fig.values.get("p50", 0.0) <= fig.values["p99"]
    if section == "latency_us":
        keys = {fig.name for fig in outcome.figures}
        assert {"request_point", "request_point_p99", "every_acquisition"} <= keys
        assert {"every_acquisition_p99", "floor", "server_over_floor"} <= keys
        # and again with the server's and the client's threads on one CPU (biris_hw.affinity)
        assert {"every_acquisition_pinned", "request_point_pinned_p99"} <= keys
        pinned = next(f for f in outcome.figures if f.name == "every_acquisition_pinned")
        assert "BirisInitRecord(cpus=(" in pinned.method or pinned.values == {"n": 0.0}
        point = next(f for f in outcome.figures if f.name == "request_point")
        assert point.values["p50"] < 100_000  # microseconds: well under 0.1 s
        assert point.values["polls_p50"] >= 1
    if section == "fanout":
        assert [fig.values["clients"] for fig in outcome.figures] == [1, 10, 100]
    if section == "sweep_gap_ms":
        report = next(f for f in outcome.figures if f.name == "report_mode")
        # each report-mode sweep pays BIRIS's 240 ms start-up again
        assert report.values["p50"] > 240


# -- the hand-over floor -------------------------------------------------------------------------


def test_floor_chain_delivers_every_item_it_was_waiting_for() -> None:
    run = hand_over_floor(5, period_s=0.005)
    assert len(run.latencies_us) == 5
    assert run.timeouts == 0
    assert run.written >= 5
    assert all(0 < us < 1_000_000 for us in run.latencies_us)


def test_floor_refuses_zero_samples() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        hand_over_floor(0, period_s=0.005)


@pytest.mark.slow
def test_floor_and_ratio_appear_in_a_quick_report(
    quick_run: Callable[[str], Outcome], tmp_path: Path
) -> None:
    outcome = quick_run("latency_us")
    assert outcome.status == "ok"
    meta = collect_meta(seconds=outcome.seconds, quick=True, only=["latency_us"], load_errors={})
    write_reports(tmp_path, meta, [outcome])
    figures = json.loads((tmp_path / "report.json").read_text())["latency_us"]["figures"]
    floor, ratio = figures["floor"], figures["server_over_floor"]
    every = figures["every_acquisition"]["values"]
    assert floor["unit"] == "us" and floor["key"] == "latency_us.floor"
    assert floor["values"]["n"] == every["n"]  # as many samples as every_acquisition
    assert 0 < floor["values"]["p50"] <= floor["values"]["p99"]
    assert ratio["values"]["ratio"] == pytest.approx(every["p50"] / floor["values"]["p50"])
    assert ratio["values"]["floor_p50"] == floor["values"]["p50"]
    md = (tmp_path / "report.md").read_text()
    assert "- Server's own cost: every_acquisition p50" in md
    assert f"is {ratio['values']['ratio']:.1f}x the bare hand-over floor" in md
    assert "| floor (us) |" in md and "| server_over_floor (x) |" in md


# -- the simulator's measurement hook ------------------------------------------------------------


def test_irq_gate_hook_sees_every_raise_with_a_timestamp() -> None:
    pulled: list[int] = []
    gate = InterruptGate(pulled.append, SimClock(1.0))
    seen: list[tuple[str, int]] = []
    gate.raise_irq("data")  # no hook: nothing recorded, nothing breaks
    gate.on_raise = lambda source, t_ns: seen.append((source, t_ns))
    before = time.perf_counter_ns()
    gate.raise_irq("data")
    gate.drop_next("cmd")
    gate.raise_irq("cmd")
    after = time.perf_counter_ns()
    gate.on_raise = None
    gate.raise_irq("data")
    assert [s for s, _ in seen] == ["data", "cmd"]  # a dropped raise is still a raise
    assert all(before <= t <= after for _, t in seen)
    assert seen[0][1] <= seen[1][1]
    assert pulled == [1, 1, 1]
    assert gate.raised == 4 and gate.dropped == 1
    gate.close()
