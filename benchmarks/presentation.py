"""Presentation delay: how old is the newest acquisition a client can have during a scan?

The report's server hands out *complete scans*: during a sweep a client can only have the
previous one, whose newest acquisition ages by the whole sweep (and the 240 ms start-up of the
next) before anything newer appears. Streaming every acquisition (DeliveryPolicy.
EVERY_ACQUISITION) should cut that to about one acquisition period. Both are measured in one
continuous 90 degree scan at time_scale 1, by three clients at once:

* **report_mode** - a client sampling at random moments (every 2-20 ms) asks REQUEST_SCAN_DATA for
  both directions, takes the newer scan, and records now minus the time of its newest
  acquisition. ``at_delivery_*`` is the same age for a DATA connection at the moment it receives
  each buffer (the best a report-mode client can do);
* **streaming** - a DATA connection with EVERY_ACQUISITION: now minus the acquisition's time at
  each delivery.

Then the same three clients again, on the same server, with two CPU-bound processes beside it
(:func:`benchmarks.common.contended`): **streaming_contended**, whose target is what a client
streaming on a busy robot's computer needs (p99 within two acquisition periods), and
**streaming_contended_lost**, what the streaming client missed meanwhile (target: nothing). Both
carry the quiet figure's p50 / p99 and the ratios contended / quiet.

Ages are hardware seconds, shown in ms (time_scale 1, so hardware and wall time agree). The
acquisition's time is its true mid-exposure from the simulator (the server's estimate is snapped
to the nearest one): the server's estimate is made when it reads the frame, so any delay in
reading would otherwise shift the estimate and hide itself.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable

from benchmarks.common import (
    Bench,
    Contention,
    acquisition_period_s,
    against_quiet,
    contended,
    load_average,
    running_server,
    snap_to,
)
from benchmarks.harness import BenchContext, Figure, Target, benchmark, percentile, summarise
from biris_hw import ConnectionKind, DeliveryPolicy, Direction, Scan
from biris_hw.client import Connection

__all__ = ["presentation"]

SAMPLES = 64
SWEEP_DEG = 45.0
TIME_SCALE = 1.0


@benchmark("presentation_ms")
def presentation(ctx: BenchContext) -> list[Figure]:
    """Age of the newest acquisition a client can have: latest complete scan vs streaming."""
    seconds = float(ctx.pick(full=20, quick=3))
    period = acquisition_period_s(SAMPLES)
    streaming_target = Target("<=", round(period * 1e3, 1), on="p99")
    with running_server(samples=SAMPLES, time_scale=TIME_SCALE) as bench:
        run = _Run(bench, seconds)
        run.measure()
        ctx.log("bench: presentation_ms.streaming_contended")
        with contended() as load:
            busy = _Run(bench, seconds)
            busy.measure()
    times = bench.rig.supervisor.acquisition_times
    tolerance = period / 2.0
    report_ages, report_unsnapped = _ages(run.sampled, times, tolerance)
    delivery_ages, delivery_unsnapped = _ages(run.scan_deliveries, times, tolerance)
    if not report_ages:
        raise RuntimeError("no complete scan was available to sample")
    setting = (
        f"time_scale {TIME_SCALE:g}, {SAMPLES} samples (period {period * 1e3:.1f} ms), continuous "
        f"scanning between -{SWEEP_DEG:g} and +{SWEEP_DEG:g} degrees (90 degree sweeps) for "
        f"{seconds:g} s; hardware ms. Acquisition times are the simulator's true mid-exposure "
        "times (the server's estimates snapped to them)."
    )
    report_values = summarise(report_ages)
    if delivery_ages:
        report_values["at_delivery_p50"] = percentile(delivery_ages, 50)
        report_values["at_delivery_p99"] = percentile(delivery_ages, 99)
        report_values["at_delivery_n"] = float(len(delivery_ages))
    report_values["unsnapped"] = float(report_unsnapped + delivery_unsnapped)
    figures = [
        Figure(
            key="presentation_ms.report_mode",
            values=report_values,
            unit="ms",
            method=(
                f"{setting} Sampled at random moments (2-20 ms apart): REQUEST_SCAN_DATA for "
                "CW and CCW, the newer scan's newest acquisition, age = now - its time. "
                "at_delivery_* = the same age when a DATA connection receives each buffer. No "
                "target: the baseline the streaming figure is compared with."
            ),
        )
    ]
    streaming_method = (
        f"{setting} A client thread blocked in ready_for_data on an EVERY_ACQUISITION DATA "
        "connection; age = hardware time when it returns - the Point's acquisition time. The "
        "acquisition exists half a period after its mid-exposure, so about period/2 is the "
        "floor. lost = points the connection missed (its dropped count: pushed out of its "
        "queue or lost by the server)."
    )
    quiet = _streaming(run, times, tolerance)
    figures.append(
        Figure(
            key="presentation_ms.streaming",
            values=quiet,
            unit="ms",
            target=streaming_target,
            method=f"{streaming_method} 1-minute load average {run.loadavg:.2f} at the start.",
        )
    )
    figures += _streaming_contended(busy, times, tolerance, quiet, load, streaming_method)
    return figures


def _streaming(run: _Run, times: list[float], tolerance: float) -> dict[str, float]:
    """The streaming client's ages, summarised, with what it missed and the machine's load."""
    ages, unsnapped = _ages(run.stream_deliveries, times, tolerance)
    if not ages:
        raise RuntimeError("the EVERY_ACQUISITION connection delivered nothing")
    values = summarise(ages)
    values["unsnapped"] = float(unsnapped)
    values["lost"] = float(run.stream_lost)
    values["loadavg_1min"] = run.loadavg
    return values


def _streaming_contended(
    busy: _Run,
    times: list[float],
    tolerance: float,
    quiet: dict[str, float],
    load: Contention,
    streaming_method: str,
) -> list[Figure]:
    """presentation_ms.streaming measured with load beside the server: the age (target: p99
    within two periods) and what was lost (target: nothing), each beside the quiet figure."""
    period_ms = acquisition_period_s(SAMPLES) * 1e3
    values = _streaming(busy, times, tolerance)
    del values["loadavg_1min"]  # the load's own figures say how busy the machine was
    values |= load.values
    values |= against_quiet(values, quiet)
    method = (
        f"{streaming_method} {load.describe()} The same three clients as the quiet figures, "
        "on the same server, right after them. Target: p99 within two acquisition periods "
        f"({2 * period_ms:.1f} ms)."
    )
    lost_values = {
        key: values[key]
        for key in ("lost", "n", "p50", "p99", "max", "load_processes", "load_cpu_percent")
    }
    lost_values["quiet_lost"] = quiet["lost"]
    note = (
        f"Contended ({load.processes} CPU-bound processes beside the server): streaming p50 "
        f"{values['p50']:.1f} ms, p99 {values['p99']:.1f} ms ({values['ratio_p50']:.2f}x / "
        f"{values['ratio_p99']:.2f}x the quiet p50 / p99), {int(values['lost'])} lost "
        "(presentation_ms.streaming_contended)."
    )
    return [
        Figure(
            key="presentation_ms.streaming_contended",
            values=values,
            unit="ms",
            target=Target("<=", round(2 * period_ms, 1), on="p99"),
            method=method,
            note=note,
        ),
        Figure(
            key="presentation_ms.streaming_contended_lost",
            values=lost_values,
            unit="ms",
            target=Target("==", 0.0, on="lost"),
            method=(
                "What the streaming client of presentation_ms.streaming_contended missed while "
                "the load ran (lost: its connection's dropped count, which includes points the "
                "server lost), beside its ages (ms) and the quiet run's lost. Target: nothing "
                "lost."
            ),
        ),
    ]


class _Run:
    """The three clients of one measurement run, each in its own thread (or the caller's)."""

    def __init__(self, bench: Bench, seconds: float) -> None:
        self.bench = bench
        self.seconds = seconds
        self.clock = bench.rig.clock.now
        self.stop = threading.Event()
        self.sampled: list[tuple[float, float]] = []
        """(now, estimated time of the newest acquisition in the latest complete scan)."""
        self.scan_deliveries: list[tuple[float, float]] = []
        self.stream_deliveries: list[tuple[float, float]] = []
        self.stream_lost = 0
        """Points the streaming connection missed (its ``dropped``), at its last delivery."""
        self.loadavg = load_average()
        self.errors: list[BaseException] = []

    def measure(self) -> None:
        server = self.bench.server
        conn = server.open()
        threads = [
            threading.Thread(target=self._guard, args=(self._scans,), name="bench-scans"),
            threading.Thread(target=self._guard, args=(self._stream,), name="bench-stream"),
        ]
        for thread in threads:
            thread.start()
        try:
            conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG)
            self._sample(conn)
        finally:
            self.stop.set()
            for thread in threads:
                thread.join()
            conn.stop_scan()
            conn.wait_idle(timeout=30.0)
            conn.close()
        if self.errors:
            raise self.errors[0]

    def _guard(self, body: Callable[[], None]) -> None:
        """Run a client; what it raises goes to the caller."""
        try:
            body()
        except BaseException as exc:
            self.errors.append(exc)

    def _sample(self, conn: Connection) -> None:
        rng = random.Random(3)
        end = time.perf_counter() + self.seconds
        while time.perf_counter() < end:
            time.sleep(rng.uniform(0.002, 0.020))
            newest: float | None = None
            for direction in (Direction.CW, Direction.CCW):
                scan = conn.request_scan_data(direction)
                if scan is not None and scan.n_acq and (newest is None or scan.t[-1] > newest):
                    newest = float(scan.t[-1])
            now = self.clock()
            if newest is not None:
                self.sampled.append((now, newest))

    def _scans(self) -> None:
        data = self.bench.server.open(ConnectionKind.DATA)
        try:
            while not self.stop.is_set():
                try:
                    scan: Scan = data.ready_for_data(timeout=0.5)
                except TimeoutError:
                    continue
                now = self.clock()
                if scan.n_acq:
                    self.scan_deliveries.append((now, float(scan.t[-1])))
        finally:
            data.close()

    def _stream(self) -> None:
        data = self.bench.server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
        try:
            while not self.stop.is_set():
                try:
                    point = data.ready_for_data(timeout=0.5)
                except TimeoutError:
                    continue
                self.stream_deliveries.append((self.clock(), point.t))
                self.stream_lost = data.dropped
        finally:
            data.close()


def _ages(
    pairs: list[tuple[float, float]], times: list[float], tolerance: float
) -> tuple[list[float], int]:
    """Ages in ms, with the acquisition time snapped to the simulator's; and how many could not
    be snapped (their estimate is used as is)."""
    ages: list[float] = []
    unsnapped = 0
    for now, estimate in pairs:
        exact = snap_to(times, estimate, tolerance)
        if exact is None:
            unsnapped += 1
            exact = estimate
        ages.append((now - exact) * 1e3)
    return ages, unsnapped
