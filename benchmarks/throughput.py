"""Throughput ceiling: the highest acquisition rate the server takes without losing one.

The simulator's clock runs ``time_scale`` times faster than real, so BIRIS makes acquisitions
``time_scale`` times as often while the server's work per acquisition stays what it is. Each
trial is a fresh rig at 128 samples (3 fields: 19.98 acquisitions per hardware second inside a
sequence) scanning continuously between -45 and +45 degrees for a few wall seconds, then
stopping at the end of a sweep. A trial **passes** when

* it is loss-free: every acquisition BIRIS made reached the administrator (supervisor count ==
  server count), no scan reported ``dropped``, no fault, a clean audit; and
* it kept time: no data interrupt was raised later than 10 % of the window (wall time) after
  its due time, *and* inside acquisition sequences the data interrupts came at no less than
  90 % of the nominal rate. The due time is exact (the simulator's schedule), so this says the
  rig really produced acquisitions at time_scale x the sensor's rate; server and simulator
  share one process and one GIL, and past some time_scale the simulator itself falls behind.
  The rate test is needed because the lag alone cannot see that: a saturated simulator catches
  up in the start-up between sequences, so its lag never exceeds one sequence (a few ms of wall
  time at high time_scale) while it makes acquisitions at a fraction of the nominal rate.

The figure is the rate of the fastest passing trial: time_scale x 19.98/s, verified as above;
``measured_acq_per_s`` is the rate the data interrupts actually came at inside sequences. The
search doubles time_scale from a start value, then bisects (geometrically) between the fastest
pass and the slowest failure, within a wall-clock budget.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

from benchmarks.common import IrqRecorder, acquisition_period_s, running_server
from benchmarks.harness import BenchContext, Figure, Target, benchmark
from benchmarks.virtual_time import virtual_ceiling

__all__ = ["throughput"]

SAMPLES = 128
SWEEP_DEG = 45.0
KEEP_UP = 0.1
"""A trial kept time when the simulator was never later than this share of the window (wall
time) in raising a data interrupt, and made its acquisitions inside sequences at the nominal
rate within this share. A lag that grows, or a rate that falls short, means the process cannot
produce (or take) that rate."""
MAX_SCALE = 4096.0
RESOLUTION = 1.15
"""Bisecting stops when the bad time_scale is within this factor of the good one."""
TARGET = Target(">=", 3000.0, on="acq_per_s")
"""100 times the sensor's rate."""


@dataclass
class Trial:
    """One rig at one time_scale: what it measured and, if it failed, why."""

    time_scale: float
    window: float
    acq_per_s: float = 0.0
    """Measured rate inside acquisition sequences, per wall second (pooled over sequences)."""
    nominal_per_s: float = 0.0
    max_lag_s: float = math.inf
    """Worst lateness of the simulator's data interrupts, wall seconds."""
    mean_acq_per_s: float = 0.0
    """Acquisitions over the whole scanning window, sweep gaps included."""
    made: int = 0
    received: int = 0
    lost: int = 0
    cpu: dict[str, float] = field(default_factory=dict)
    server_us_per_acq: float = 0.0
    failure: str = ""

    @property
    def loss_free(self) -> bool:
        return not self.failure and self.lost == 0 and self.made > 0

    @property
    def kept_up(self) -> bool:
        return self.lag_ok and self.rate_ok

    @property
    def lag_ok(self) -> bool:
        return self.max_lag_s <= KEEP_UP * self.window

    @property
    def rate_ok(self) -> bool:
        """Inside sequences the rig made acquisitions at (at least) nominal rate, within KEEP_UP."""
        return self.acq_per_s >= (1.0 - KEEP_UP) * self.nominal_per_s

    @property
    def passed(self) -> bool:
        return self.loss_free and self.kept_up


@benchmark("throughput")
def throughput(ctx: BenchContext) -> list[Figure]:
    """Highest loss-free acquisition rate at 128 samples (time_scale search) and its CPU."""
    budget = float(ctx.pick(full=80, quick=8))
    window = float(ctx.pick(full=3, quick=1))
    scale = float(ctx.pick(full=16, quick=64))
    started = time.perf_counter()
    trials: list[Trial] = []
    good: float | None = None
    bad: float | None = None
    ended = "budget"
    while True:
        ctx.log(f"bench: throughput trial at time_scale {scale:g}")
        trial = _trial(scale, window)
        trials.append(trial)
        if trial.passed:
            good = scale if good is None else max(good, scale)
        else:
            bad = scale if bad is None else min(bad, scale)
        if good is None:
            scale /= 2  # even the start was too fast: come down until a trial passes
            if scale < 1.0:
                ended = "no time_scale passed"
                break
        elif bad is None:
            scale *= 2
            if scale > MAX_SCALE:
                ended = f"time_scale limit {MAX_SCALE:g}"
                break
        elif bad / good <= RESOLUTION:
            ended = "bisected"
            break
        else:
            scale = math.sqrt(good * bad)
        spent = time.perf_counter() - started
        if spent + (spent / len(trials)) * 1.2 > budget:
            break
    # the CPU-cost figure beside the load-bound one: a run on virtual time (benchmarks.virtual_time)
    return [_figure(trials, budget, window, ended), virtual_ceiling(ctx)]


def _figure(trials: list[Trial], budget: float, window: float, ended: str) -> Figure:
    passed = [t for t in trials if t.passed]
    best = max(passed, key=lambda t: t.time_scale, default=None)
    failed = [t for t in trials if not t.passed]
    first_bad = min(failed, key=lambda t: t.time_scale, default=None)
    if first_bad is None:
        limit = "none (no trial lost an acquisition or fell behind)"
    elif not first_bad.loss_free:
        why = first_bad.failure or f"{first_bad.lost} acquisitions lost"
        limit = f"time_scale {first_bad.time_scale:g}: {why}"
    elif not first_bad.lag_ok:
        limit = (
            f"time_scale {first_bad.time_scale:g}: nothing lost, but the simulator raised an "
            f"interrupt {first_bad.max_lag_s * 1e3:.0f} ms late (saturated)"
        )
    else:
        limit = (
            f"time_scale {first_bad.time_scale:g}: nothing lost, but acquisitions came at "
            f"{first_bad.acq_per_s:.0f}/s inside sequences, "
            f"{first_bad.acq_per_s / first_bad.nominal_per_s:.0%} of the nominal "
            f"{first_bad.nominal_per_s:.0f}/s (saturated)"
        )
    tried = ", ".join(f"{t.time_scale:g}{'' if t.passed else '*'}" for t in trials)
    method = (
        f"Fresh rig per trial, {SAMPLES} samples, continuous scanning +-{SWEEP_DEG:g} degrees "
        f"for {window:g} wall s; time_scale doubled from {trials[0].time_scale:g}, then "
        f"bisected, within {budget:g} s (tried: {tried}; * = failed; stopped: {ended}). A "
        "trial passes when it is loss-free (every acquisition the simulator made reached the "
        "administrator, no scan dropped any, no fault, clean audit) and kept time (no data "
        f"interrupt more than {KEEP_UP:.0%} of the window late against the simulator's "
        f"schedule, and measured_acq_per_s at least {1.0 - KEEP_UP:.0%} of nominal). "
        "acq_per_s = time_scale x 19.98/s of the fastest passing trial; measured_acq_per_s = "
        "the rate the data interrupts came at inside sequences (start-up excluded; pooled over "
        "the window's sequences, each of which lasts about 1.25 s / time_scale of wall time, "
        "so a sequence's first and last interrupt each add their scheduling delay); "
        "mean_acq_per_s includes the start-up between sweeps; max_lag_ms = the "
        f"worst lateness (wall). First failure: {limit}. cpu_percent = process CPU / wall "
        "while scanning (100 = one core, simulator included); server_ and sim_ = their "
        "threads' share. server_cpu_us_per_acq = the server threads' CPU time per acquisition; "
        "server_bound_acq_per_s = 1e6 / that: a projection (one core, no simulator), not a "
        "measurement, not judged."
    )
    if best is None:
        return Figure(
            key="throughput.ceiling",
            values={"acq_per_s": 0.0, "samples": float(SAMPLES), "trials": float(len(trials))},
            unit="acq/s",
            target=TARGET,
            method="No trial passed. " + method,
        )
    values = {
        "acq_per_s": best.nominal_per_s,
        "samples": float(SAMPLES),
        "time_scale": best.time_scale,
        "measured_acq_per_s": best.acq_per_s,
        "mean_acq_per_s": best.mean_acq_per_s,
        "max_lag_ms": best.max_lag_s * 1e3,
        "acquisitions": float(best.received),
        **best.cpu,
        "server_cpu_us_per_acq": best.server_us_per_acq,
        "server_bound_acq_per_s": 1e6 / best.server_us_per_acq if best.server_us_per_acq else 0.0,
        "trials": float(len(trials)),
    }
    return Figure(
        key="throughput.ceiling", values=values, unit="acq/s", target=TARGET, method=method
    )


def _trial(time_scale: float, window: float) -> Trial:
    period = acquisition_period_s(SAMPLES)
    trial = Trial(time_scale, window, nominal_per_s=time_scale / period)
    try:
        with (
            running_server(samples=SAMPLES, time_scale=time_scale) as bench,
            IrqRecorder(bench.rig) as irq,
        ):
            conn = bench.server.open()
            made0 = bench.rig.supervisor.acquisitions_made
            with bench.cpu() as cpu:
                t0 = time.perf_counter_ns()
                conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG)
                time.sleep(window)
                t1 = time.perf_counter_ns()
            conn.stop_scan()
            conn.wait_idle(timeout=max(10.0, 30.0 / time_scale))
            counters = bench.server.status()["counters"]
            trial.made = bench.rig.supervisor.acquisitions_made - made0
            # kept in scans, or made with the head standing at a scan's end (dropped, counted)
            trial.received = int(counters["acquisitions"]) + int(counters["constant_azimuth"])
            trial.lost = (
                int(counters["dropped_acquisitions"])
                + int(counters["stale_acquisitions"])
                + max(0, trial.made - trial.received)
            )
            if counters["faults"]:
                trial.failure = f"{counters['faults']} hardware fault(s)"
            spans = irq.sequence_spans()
            wall_ns = sum(ns for _, ns in spans)
            trial.acq_per_s = sum(n for n, _ in spans) * 1e9 / wall_ns if wall_ns else 0.0
            announced = sum(1 for e in irq.data if e.announces >= 0 and t0 <= e.t_ns <= t1)
            trial.mean_acq_per_s = announced * 1e9 / (t1 - t0)
            trial.cpu = {k: v for k, v in cpu.values.items() if k.endswith("_percent")}
            server_s = cpu.values.get("server_cpu_percent", 0.0) / 100.0 * cpu.values["wall_s"]
            trial.server_us_per_acq = 1e6 * server_s / announced if announced else 0.0
            made_times = bench.rig.supervisor.acquisition_times_since(made0)
            lags = irq.lags_hw(made_times, period)
            trial.max_lag_s = max(lags) / time_scale if lags else math.inf
            if not spans:
                trial.failure = trial.failure or "no complete acquisition sequence"
            violations = bench.rig.audit.violations
            if violations:
                trial.failure = trial.failure or f"audit: {violations[0]}"
    except Exception as exc:  # a fault or a timeout at this rate is this trial's result
        trial.failure = f"{type(exc).__name__}: {exc}"
    return trial
