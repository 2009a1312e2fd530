"""Server-added latency: from BIRIS raising a data interrupt to a client holding the acquisition.

The clock starts in the simulator, at the instant it raises the data interrupt that announces
acquisition k (:class:`~benchmarks.common.IrqRecorder`), so the whole driver path is inside
the figure: level-2 demultiplexer, data notifier, frame read, administrator, reply, and the
client thread waking up. Everything runs at time_scale 1, in one process, on one GIL, with the
simulator's own work competing: that is the honest worst case of an in-process rig.

Two ways of holding an acquisition are timed, one after the other during the same continuous
90 degree scan:

* **every_acquisition** - a DATA connection with DeliveryPolicy.EVERY_ACQUISITION, whose client
  thread is blocked in ready_for_data; latency = its return minus the raise of the interrupt that
  announced that acquisition. No load but the client itself.
* **every_acquisition_contended** - the same, right after it on the same server and scan, with
  two CPU-bound processes beside the process (:func:`benchmarks.common.contended`): what a busy
  neighbour on the robot's computer costs the data path. Reported with the quiet figure's p50
  and p99 and the ratios contended / quiet.
* **request_point** - REQUEST_POINT has nothing to wait on, so the client must ask. On each raise
  (woken by the hook) a client thread calls request_point until it returns the acquisition just
  announced; latency = that return minus the raise, and the number of calls it took is reported.
  The polling is load on the administrator and the return includes one full round trip, so this
  is an upper bound on when the administrator had the acquisition.

Right after, with the rig closed, the same process measures the **floor**
(:mod:`benchmarks.floor`): the bare hand-over chain the data path needs at least (eventfd
written at the same cadence, a thread polling it, the administrator's inbox, the client's
thread), as many samples as every_acquisition has. ``server_over_floor`` = every_acquisition
p50 / floor p50 is the server's own cost as a ratio: 1 would be a server that adds nothing to
moving an item between threads.
"""

from __future__ import annotations

import bisect
import contextlib
import dataclasses
import math
import queue
import time
from collections.abc import Mapping
from dataclasses import dataclass

from benchmarks.common import (
    Bench,
    Contention,
    DataRaise,
    IrqRecorder,
    acquisition_period_s,
    against_quiet,
    contended,
    load_average,
    not_measured,
    running_server,
)
from benchmarks.floor import hand_over_floor
from benchmarks.harness import BenchContext, Figure, Target, benchmark, percentile, summarise
from biris_hw import BirisInitRecord, ConnectionKind, DeliveryPolicy
from biris_hw.affinity import available_cpus, pinned
from biris_hw.errors import RequestError

__all__ = ["latency"]

SAMPLES = 64
SWEEP_DEG = 45.0
"""Continuous scanning between -45 and +45 degrees: 90 degree sweeps, as the report's examples."""

P50_TARGET = Target("<=", 200.0, on="p50")
P99_TARGET = Target("<=", 1000.0, on="p99")
MATCH_WINDOW_NS = 500_000_000
"""A delivery more than this after the raise of its acquisition is not matched to it."""
POLL_GIVE_UP_NS = 100_000_000
"""request_point polling for one acquisition stops after this (counted as missed)."""


@benchmark("latency_us")
def latency(ctx: BenchContext) -> list[Figure]:
    """Interrupt raise to DATA delivery (EVERY_ACQUISITION) and to request_point, time_scale 1.

    The first again with CPU-bound processes beside the server (``_contended``). Then the bare
    hand-over floor and the server's cost over it (``floor``, ``server_over_floor``). Then the
    first two again with the opt-in of
    :mod:`biris_hw.affinity` (``_pinned`` figures): the server's threads, the client's and the
    simulator's (the interrupt's source) on one CPU.
    """
    seconds = float(ctx.pick(full=20, quick=2))
    figures = _measure(ctx, seconds, "", None)
    every = next(f for f in figures if f.key == "latency_us.every_acquisition")
    ctx.log("bench: latency_us.floor")
    floor = _floor(int(every.values["n"]))
    figures += [floor, _server_over_floor(every, floor)]
    try:
        return figures + _measure(ctx, seconds, "_pinned", min(available_cpus()))
    except RequestError as exc:  # not Linux, or affinity refused here
        reason = f"needs CPU affinity: {exc}"
        for key, target in _KEYS:
            figures.append(not_measured(f"latency_us.{key}_pinned", "us", target, reason))
        return figures


_KEYS = (
    ("every_acquisition", P50_TARGET),
    ("every_acquisition_p99", P99_TARGET),
    ("request_point", P50_TARGET),
    ("request_point_p99", P99_TARGET),
)


def _measure(ctx: BenchContext, seconds: float, suffix: str, cpu: int | None) -> list[Figure]:
    """Both figures on a fresh server; with ``cpu``, it and the measuring thread kept there."""
    record = BirisInitRecord() if cpu is None else BirisInitRecord(cpus=(cpu,))
    figures: list[Figure] = []
    with (
        pinned({cpu}) if cpu is not None else contextlib.nullcontext(),
        running_server(samples=SAMPLES, time_scale=1.0, record=record) as bench,
        IrqRecorder(bench.rig) as irq,
    ):
        note = "" if cpu is None else _pinned_note(cpu)
        conn = bench.server.open()
        conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG)
        try:
            ctx.log(f"bench: latency_us.every_acquisition{suffix}")
            quiet = _every_acquisition(bench, irq, seconds, suffix, note)
            figures += quiet
            if cpu is None:
                ctx.log("bench: latency_us.every_acquisition_contended")
                figures += _every_acquisition_contended(bench, irq, seconds, quiet)
            ctx.log(f"bench: latency_us.request_point{suffix}")
            figures += _request_point(bench, irq, seconds, suffix, note)
        finally:
            conn.stop_scan()
            conn.wait_idle(timeout=30.0)
            conn.close()
    return figures


def _pinned_note(cpu: int) -> str:
    return (
        f" Opt-in run: BirisInitRecord(cpus=({cpu},)) keeps every server thread on CPU {cpu}, "
        "and the measuring client thread and the simulator are kept there too "
        "(biris_hw.affinity.pinned), as the interrupt would be steered to that CPU on a target: "
        "the whole process on one CPU, so no hand-over crosses CPUs."
    )


def _every_acquisition(
    bench: Bench, irq: IrqRecorder, seconds: float, suffix: str = "", note: str = ""
) -> list[Figure]:
    run = _deliveries(bench, irq, seconds)
    extra = {**run.values(), "loadavg_1min": run.loadavg}
    return _pair(f"every_acquisition{suffix}", run.samples, run.method(seconds) + note, extra)


def _every_acquisition_contended(
    bench: Bench, irq: IrqRecorder, seconds: float, quiet: list[Figure]
) -> list[Figure]:
    """every_acquisition again with :data:`~benchmarks.common.CONTENDING_PROCESSES` CPU-bound
    processes beside the server; its rows carry the quiet ones' p50 / p99 and the ratios."""
    with contended() as load:
        run = _deliveries(bench, irq, seconds)
    figures = _pair(
        "every_acquisition_contended",
        run.samples,
        f"{run.method(seconds)} {load.describe()} Measured right after "
        "latency_us.every_acquisition on the same server and scan.",
        {**run.values(), **load.values},
    )
    quiet_main = next(fig for fig in quiet if fig.name == "every_acquisition")
    ratios = against_quiet(figures[0].values, quiet_main.values)
    main, tail = (dataclasses.replace(fig, values={**fig.values, **ratios}) for fig in figures)
    return [dataclasses.replace(main, note=_contended_note(main.values, load)), tail]


def _contended_note(values: Mapping[str, float], load: Contention) -> str:
    return (
        f"Contended ({load.processes} CPU-bound processes beside the server): "
        f"every_acquisition p50 {values['p50']:.0f} us, p99 {values['p99']:.0f} us, "
        f"{values['ratio_p50']:.2f}x / {values['ratio_p99']:.2f}x the quiet p50 / p99 "
        "measured just before it (latency_us.every_acquisition_contended)."
    )


class _Raises:
    """The data interrupts that announced an acquisition, looked up by the acquisition's time.

    The interrupt announcing acquisition k is raised as its exposure ends, half a period after
    its mid-exposure time (``Point.t``, the server's estimate, within a millisecond or so of the
    simulator's): the announcing raise nearest that moment in hardware time, within half a
    period, is the one. Matching by time needs no acquisition number, so it holds however the
    server numbers a scan's rows.
    """

    def __init__(self, data: list[DataRaise], period: float) -> None:
        raises = sorted((e.t_hw, e.t_ns) for e in data if e.announces >= 0)
        self._t_hw = [t_hw for t_hw, _ in raises]
        self._t_ns = [t_ns for _, t_ns in raises]
        self._period = period

    def announcing(self, t_mid: float) -> int | None:
        """perf_counter_ns of the raise announcing the acquisition exposed around ``t_mid``."""
        due = t_mid + self._period / 2.0
        i = bisect.bisect_left(self._t_hw, due)
        near = [j for j in (i - 1, i) if 0 <= j < len(self._t_hw)]
        if not near:
            return None
        best = min(near, key=lambda j: abs(self._t_hw[j] - due))
        return self._t_ns[best] if abs(self._t_hw[best] - due) <= self._period / 2.0 else None


@dataclass
class _Deliveries:
    """One every_acquisition measurement: latencies and what was left out, and why."""

    samples: list[float]
    unmatched: int
    not_waiting: int
    lost: int
    """Points the connection missed (its ``dropped``: pushed out of its queue or lost by the
    server), as of the client's last ready_for_data."""
    loadavg: float

    def values(self) -> dict[str, float]:
        return {
            "unmatched": float(self.unmatched),
            "not_waiting": float(self.not_waiting),
            "lost": float(self.lost),
        }

    def method(self, seconds: float) -> str:
        return (
            f"{_setting(seconds)} A client thread blocked in ready_for_data on a DATA connection "
            "opened with DeliveryPolicy.EVERY_ACQUISITION; latency = perf_counter_ns when it "
            "returns minus perf_counter_ns taken by the simulator as it raised the data "
            "interrupt announcing that acquisition (matched by time: the raise whose hardware "
            "time is nearest the end of the Point's exposure, Point.t + period/2, within half a "
            "period, and before the return; not by Point.acq, which numbers the scan's rows and "
            "skips acquisitions made with the head standing; "
            f"{self.unmatched} unmatched; "
            f"{self.not_waiting} raised before the client was back in ready_for_data, left out "
            f"as the client's delay); lost = points the connection missed ({self.lost}). "
            f"1-minute load average {self.loadavg:.2f} at the start."
        )


def _deliveries(bench: Bench, irq: IrqRecorder, seconds: float) -> _Deliveries:
    irq.clear()
    loadavg = load_average()
    data = bench.server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
    returns: list[tuple[int, int, float]] = []  # (entered ready_for_data, returned, Point.t)
    try:
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            called = time.perf_counter_ns()
            try:
                point = data.ready_for_data(timeout=2.0)
            except TimeoutError:
                continue
            returns.append((called, time.perf_counter_ns(), point.t))
        lost = data.dropped
    finally:
        data.close()
    raises = _Raises(irq.data, acquisition_period_s(SAMPLES))
    samples: list[float] = []
    unmatched = not_waiting = 0
    for t_call, t_ret, t_point in returns:
        raised = raises.announcing(t_point)
        if raised is None or raised > t_ret or t_ret - raised > MATCH_WINDOW_NS:
            unmatched += 1
            continue
        if raised < t_call:
            not_waiting += 1  # queued while the client was away: its delay, not the server's
            continue
        samples.append((t_ret - raised) / 1000.0)
    if not samples:
        raise RuntimeError("no EVERY_ACQUISITION delivery could be matched to its interrupt")
    return _Deliveries(samples, unmatched, not_waiting, lost, loadavg)


def _request_point(
    bench: Bench, irq: IrqRecorder, seconds: float, suffix: str = "", note: str = ""
) -> list[Figure]:
    conn = bench.server.open()
    period = acquisition_period_s(SAMPLES)
    samples: list[float] = []
    polls: list[float] = []
    overtaken = missed = behind = 0
    try:
        _drain(irq.events)
        irq.listen = True
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            try:
                event = irq.events.get(timeout=1.0)
            except queue.Empty:
                continue
            if not irq.events.empty():
                behind += 1  # a newer raise is waiting: this one's clock started long ago
                continue
            expected_t = event.t_hw - period / 2.0  # mid-exposure of the acquisition announced
            give_up = event.t_ns + POLL_GIVE_UP_NS
            n = 0
            while True:
                point = conn.request_point()
                now = time.perf_counter_ns()
                n += 1
                if point is not None:
                    if abs(point.t - expected_t) < period / 2.0:  # by time (see _Raises)
                        samples.append((now - event.t_ns) / 1000.0)
                        polls.append(float(n))
                        break
                    if point.t > expected_t + period / 2.0:
                        overtaken += 1  # a newer acquisition arrived first; cannot happen in order
                        break
                if now > give_up:
                    missed += 1
                    break
    finally:
        irq.listen = False
        conn.close()
    if not samples:
        raise RuntimeError("request_point never returned an announced acquisition")
    method = (
        f"{_setting(seconds)} On each data interrupt (the simulator's hook wakes a client "
        "thread), the client calls request_point in a loop until it returns the acquisition "
        "that interrupt announced (Point.t within half a period of its "
        "mid-exposure); latency = the return of that call minus the raise, both "
        "perf_counter_ns. An upper bound on when the administrator had it: it includes one "
        "round trip and the polling loads the administrator. polls = calls per acquisition; "
        f"skipped: {behind} raises while the client was behind, {overtaken} overtaken, "
        f"{missed} not seen within {POLL_GIVE_UP_NS // 1_000_000} ms."
    )
    extra = {
        "polls_p50": percentile(polls, 50),
        "polls_p99": percentile(polls, 99),
        "polls_max": max(polls),
        "missed": float(missed + overtaken),
    }
    return _pair(f"request_point{suffix}", samples, method + note, extra)


def _floor(samples: int) -> Figure:
    """The bare hand-over chain, as many samples as every_acquisition (same process, rig closed)."""
    period = acquisition_period_s(SAMPLES)
    run = hand_over_floor(samples, period)
    if not run.latencies_us:
        raise RuntimeError("the hand-over floor chain delivered nothing")
    values = summarise(run.latencies_us)
    values["p999"] = percentile(run.latencies_us, 99.9)
    values["not_waiting"] = float(run.not_waiting)
    method = (
        "The bare hand-over chain the data path needs at least, no server logic: a 'simulator' "
        f"thread writes an os.eventfd every {period * 1e3:.1f} ms (the acquisition cadence of "
        "every_acquisition), a thread blocked in select.poll on it reads it and posts the item "
        "to a biris_hw.ipc.Mailbox (collecting the previous post's reply first, as the data "
        "notifier does), an 'administrator' thread receives it, replies at once and replies the "
        "item to the client's parked send (READY_FOR_DATA), and the client thread wakes holding "
        "it. Latency = perf_counter_ns in the client thread minus perf_counter_ns just before the "
        f"eventfd write; {int(values['n'])} samples, as many as every_acquisition, measured in "
        "the same process right after it with the rig closed (no simulator load). "
        f"{run.not_waiting} items written before the client was back waiting were left out. No "
        "target: the yardstick for server_over_floor."
    )
    return Figure(key="latency_us.floor", values=values, unit="us", method=method)


def _server_over_floor(every: Figure, floor: Figure) -> Figure:
    """every_acquisition p50 / floor p50: what the server costs over moving an item."""
    server_p50, floor_p50 = every.values["p50"], floor.values["p50"]
    ratio = server_p50 / floor_p50 if floor_p50 > 0 else math.nan
    values = {
        "ratio": ratio,
        "every_acquisition_p50": server_p50,
        "floor_p50": floor_p50,
        "every_acquisition_p99": every.values["p99"],
        "floor_p99": floor.values["p99"],
    }
    return Figure(
        key="latency_us.server_over_floor",
        values=values,
        unit="x",
        method=(
            "latency_us.every_acquisition p50 / latency_us.floor p50, both from this run: the "
            "server's own cost as a multiple of the bare eventfd -> poll -> administrator -> "
            "client hand-over (1 = the server adds nothing). The every_acquisition side also "
            "carries the simulator's work in the same process. No target."
        ),
        note=(
            f"Server's own cost: every_acquisition p50 {server_p50:.0f} us is {ratio:.1f}x the "
            f"bare hand-over floor (p50 {floor_p50:.0f} us) measured in the same run "
            "(latency_us.server_over_floor)."
        ),
    )


def _pair(name: str, samples: list[float], method: str, extra: dict[str, float]) -> list[Figure]:
    """Two rows for one set of samples, because the issue sets two targets (p50 and p99)."""
    values = {**summarise(samples), **extra}
    tail = {"p99": values["p99"], "p999": percentile(samples, 99.9), "max": values["max"]}
    tail["n"] = values["n"]
    return [
        Figure(
            key=f"latency_us.{name}", values=values, unit="us", target=P50_TARGET, method=method
        ),
        Figure(
            key=f"latency_us.{name}_p99",
            values=tail,
            unit="us",
            target=P99_TARGET,
            method=f"The tail of latency_us.{name} (same samples).",
        ),
    ]


def _setting(seconds: float) -> str:
    return (
        f"time_scale 1, {SAMPLES} samples (an acquisition every "
        f"{acquisition_period_s(SAMPLES) * 1e3:.1f} ms), continuous scanning between "
        f"-{SWEEP_DEG:g} and +{SWEEP_DEG:g} degrees for {seconds:g} s; simulator and server "
        "in one process."
    )


def _drain(q: queue.SimpleQueue[DataRaise]) -> None:
    while True:
        try:
            q.get_nowait()
        except queue.Empty:
            return
