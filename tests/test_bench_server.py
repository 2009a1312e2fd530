"""The server benchmarks run end to end in quick mode and produce figures worth reading.

Benchmarks never fail the build, so these tests do not judge targets: they check that every
section runs through the harness, that each figure has samples and a plausible unit and value,
and that a figure whose server feature is missing says what it needs instead. The streaming
figures are also run once against an *emulated* EVERY_ACQUISITION connection (REQUEST_POINT
polled behind the planned API), so their code is exercised before the real feature exists.
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

import biris_hw
from biris_hw.bench.harness import BenchContext, Figure, Outcome, registry, run_one
from biris_hw.client import Connection
from biris_hw.data import ConnectionKind, Point
from biris_hw.server import BirisServer
from sim.clock import SimClock
from sim.irqgate import InterruptGate

UNITS = {
    "latency_us": "us",
    "presentation_ms": "ms",
    "throughput": "acq/s",
    "fanout": "ms",
    "sweep_gap_ms": "ms",
}


def _run(section: str, tmp_path: Path) -> Outcome:
    bench = registry.benchmarks()[section]
    outcome = run_one(bench, BenchContext(quick=True, work_dir=tmp_path))
    assert outcome.status in ("ok", "skipped"), outcome.traceback or outcome.error
    if outcome.status == "skipped":
        assert outcome.reason
    return outcome


def _measured(fig: Figure) -> bool:
    """A figure either carries samples or says, with n = 0, which feature it needs."""
    if fig.method.startswith("NOT MEASURED"):
        assert "needs" in fig.method
        assert fig.values == {"n": 0.0}
        return False
    assert fig.method and len(fig.method) > 40
    assert all(math.isfinite(v) for v in fig.values.values()), fig.values
    return True


@pytest.mark.parametrize("section", sorted(UNITS))
def test_section_runs_in_quick_mode(section: str, tmp_path: Path) -> None:
    outcome = _run(section, tmp_path)
    if outcome.status == "skipped":
        return
    assert outcome.figures
    measured = [fig for fig in outcome.figures if _measured(fig)]
    assert measured, "every figure of the section is missing its feature"
    for fig in outcome.figures:
        assert fig.unit == UNITS[section]
        assert fig.target is not None or "No target" in fig.method or section == "fanout"
    for fig in measured:
        if section == "throughput":
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


# -- emulated streaming --------------------------------------------------------------------------


class _Policy(enum.Enum):
    LATEST = "latest"
    EVERY_ACQUISITION = "every_acquisition"


class _Streaming:
    """Stands in for an EVERY_ACQUISITION DATA connection: polls REQUEST_POINT for new points."""

    def __init__(self, conn: Connection) -> None:
        self._conn = conn
        self._last_t = -math.inf

    def ready_for_data(self, timeout: float | None = None) -> Point:
        deadline = time.monotonic() + (timeout if timeout is not None else 60.0)
        while time.monotonic() < deadline:
            point = self._conn.request_point()
            if point is not None and point.t > self._last_t:
                self._last_t = point.t
                return point
            time.sleep(0.0002)
        raise TimeoutError("no new point")

    def close(self) -> None:
        self._conn.close()


@pytest.fixture
def emulated_streaming(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    real_open = BirisServer.open

    def open_(
        self: BirisServer, kind: ConnectionKind = ConnectionKind.NORMAL, policy: object = None
    ) -> object:
        if policy is _Policy.EVERY_ACQUISITION:
            return _Streaming(real_open(self))
        return real_open(self, kind)

    monkeypatch.setattr(biris_hw, "DeliveryPolicy", _Policy, raising=False)
    monkeypatch.setattr(BirisServer, "open", open_)
    yield


@pytest.mark.parametrize(
    ("section", "names"),
    [
        ("latency_us", {"every_acquisition", "every_acquisition_p99"}),
        ("presentation_ms", {"streaming"}),
    ],
)
@pytest.mark.usefixtures("emulated_streaming")
def test_streaming_figures_are_measured_once_the_feature_exists(
    section: str, names: set[str], tmp_path: Path
) -> None:
    outcome = _run(section, tmp_path)
    assert outcome.status == "ok"
    figures = {fig.name: fig for fig in outcome.figures if fig.name in names}
    assert set(figures) == names
    for fig in figures.values():
        assert _measured(fig), fig.method
        assert fig.values["n"] > 0
    if section == "presentation_ms":
        # a polled stream is at most a period or so old, far below a report-mode sweep
        assert figures["streaming"].values["p50"] < 200


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
