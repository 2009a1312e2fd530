"""Sweep gap: the blind time between one sweep's last acquisition and the next sweep's first.

In the report's mode every sweep is its own BI_ACQUIRE, so each turn-around costs BIRIS's 240 ms
start-up (plus the command's trip through the server and a wait for the next video field). The
head waits at the limit for it (issue 12: the trapezoid starts when the first acquisition
begins), so the gap is blind *time* at the turn-around, not a hole in the sweep: before that
change the head swept on and the first ~32 degrees of every sweep were missing (300 ms then,
one period less than now, since the standing acquisition at the limit is now discarded).
Continuous acquisition (Appendix D, ``BirisInitRecord(continuous_acquisition=True)``) keeps
BIRIS acquiring through the turn-around and only partitions the stream into sweeps, so the gap
should be one acquisition period.

Measured from consecutive buffers of one DATA connection during continuous 90 degree sweeps:
gap = next scan's first acquisition time - previous scan's last, in hardware ms. Acquisition
times are the server's Scan.t snapped to the simulator's exact mid-exposure times (the
estimates carry the server's reading delay). time_scale 3: the times are hardware times, and
the only part of a gap that scales is the server's own reaction, which can lengthen a
report-mode gap by at most one video field.
"""

from __future__ import annotations

from contextlib import ExitStack
from itertools import pairwise

from benchmarks.common import acquisition_period_s, running_server, snap_to
from benchmarks.harness import BenchContext, Figure, Target, benchmark, summarise
from biris_hw import BirisInitRecord, ConnectionKind

__all__ = ["sweep_gap"]

SAMPLES = 64
SWEEP_DEG = 45.0
TIME_SCALE = 3.0
EXPLAINING_COUNTERS = ("dropped_acquisitions", "constant_azimuth")
"""Server status counters shown beside the gaps: acquisitions lost, and acquisitions discarded
because the head stood still, e.g. at a turn-around."""
BUFFER_TIMEOUT = 10.0
"""Wall seconds to wait for a buffer; a sweep takes about 0.4 s at TIME_SCALE."""


@benchmark("sweep_gap_ms")
def sweep_gap(ctx: BenchContext) -> list[Figure]:
    """Last acquisition of a sweep to the first of the next: report mode vs continuous."""
    sweeps = ctx.pick(full=24, quick=4)
    period_ms = acquisition_period_s(SAMPLES) * 1e3
    target = Target("<=", round(period_ms, 1), on="p99")
    ctx.log("bench: sweep_gap_ms.report_mode")
    report = _measure(BirisInitRecord(), sweeps)
    figures = [
        Figure(
            key="sweep_gap_ms.report_mode",
            values={**summarise(report.gaps), **report.extra(period_ms)},
            unit="ms",
            method=_method(sweeps, "the default BirisInitRecord (one BI_ACQUIRE per sweep)")
            + " No target: the baseline.",
        )
    ]
    ctx.log("bench: sweep_gap_ms.continuous_acquisition")
    cont = _measure(BirisInitRecord(continuous_acquisition=True), sweeps)
    figures.append(
        Figure(
            key="sweep_gap_ms.continuous_acquisition",
            values={**summarise(cont.gaps), **cont.extra(period_ms)},
            unit="ms",
            target=target,
            method=_method(sweeps, "BirisInitRecord(continuous_acquisition=True)"),
        )
    )
    return figures


def _method(sweeps: int, record: str) -> str:
    return (
        f"{record}; continuous scanning +-{SWEEP_DEG:g} degrees, {SAMPLES} samples, time_scale "
        f"{TIME_SCALE:g}, {sweeps} consecutive buffers of one DATA connection. Gap = next "
        "Scan.t[0] - previous Scan.t[-1] (snapped to the simulator's exact mid-exposure times), "
        "hardware ms; pairs separated by a buffer the client missed are skipped. A gap of k "
        "periods means k-1 acquisitions are in neither buffer. sequences = acquisition "
        "sequences BIRIS started while scanning; dropped_acquisitions and constant_azimuth "
        "(acquisitions discarded while the head stood still) are the server's status counters "
        "at the end."
    )


class _Gaps:
    def __init__(self) -> None:
        self.gaps: list[float] = []
        self.sequences = 0
        self.buffers = 0
        self.skipped = 0
        self.unsnapped = 0
        self.counters: dict[str, float] = {}
        """Server status counters that explain a long gap."""

    def extra(self, period_ms: float) -> dict[str, float]:
        longer = sum(1 for g in self.gaps if g > 1.5 * period_ms)
        return {
            "period_ms": period_ms,
            "gaps_over_one_period": float(longer),
            "sequences": float(self.sequences),
            "buffers": float(self.buffers),
            "skipped": float(self.skipped),
            "unsnapped": float(self.unsnapped),
            **self.counters,
        }


def _measure(record: BirisInitRecord, sweeps: int) -> _Gaps:
    """Scan until ``sweeps`` buffers have arrived."""
    out = _Gaps()
    edges: list[tuple[float, float, int]] = []  # (first t, last t, client dropped so far)
    with ExitStack() as stack:
        bench = stack.enter_context(
            running_server(samples=SAMPLES, time_scale=TIME_SCALE, record=record)
        )
        conn = stack.enter_context(bench.server.open())
        data = stack.enter_context(bench.server.open(ConnectionKind.DATA))
        starts0 = bench.rig.supervisor.sequences_started
        conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG)
        try:
            while len(edges) < sweeps:
                scan = data.ready_for_data(timeout=BUFFER_TIMEOUT)
                if scan.n_acq:
                    edges.append((float(scan.t[0]), float(scan.t[-1]), data.dropped))
        finally:
            conn.stop_scan()
            conn.wait_idle(timeout=30.0)
        out.sequences = bench.rig.supervisor.sequences_started - starts0
        counters = bench.server.status()["counters"]
        out.counters = {name: float(counters[name]) for name in EXPLAINING_COUNTERS}
        times = bench.rig.supervisor.acquisition_times
    period = acquisition_period_s(SAMPLES)
    out.buffers = len(edges)
    for (_, prev_last, prev_dropped), (next_first, _, dropped) in pairwise(edges):
        if dropped != prev_dropped:
            out.skipped += 1
            continue
        a = snap_to(times, prev_last, period / 2.0)
        b = snap_to(times, next_first, period / 2.0)
        if a is None or b is None:
            out.unsnapped += 1
            a, b = prev_last, next_first
        out.gaps.append((b - a) * 1e3)
    if not out.gaps:
        raise RuntimeError("no pair of consecutive buffers to measure")
    return out
