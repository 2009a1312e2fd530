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

from benchmarks.common import Bench, acquisition_period_s, running_server, snap_to
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
    stream_ages, stream_unsnapped = _ages(run.stream_deliveries, times, tolerance)
    if not stream_ages:
        raise RuntimeError("the EVERY_ACQUISITION connection delivered nothing")
    values = summarise(stream_ages)
    values["unsnapped"] = float(stream_unsnapped)
    figures.append(
        Figure(
            key="presentation_ms.streaming",
            values=values,
            unit="ms",
            target=streaming_target,
            method=(
                f"{setting} A client thread blocked in ready_for_data on an "
                "EVERY_ACQUISITION DATA connection; age = hardware time when it returns - "
                "the Point's acquisition time. The acquisition exists half a period after "
                "its mid-exposure, so about period/2 is the floor."
            ),
        )
    )
    return figures


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
