"""Soak: a long run of continuous scanning at a high time scale, and whether anything drifts.

Continuous +-90 degree scanning at time_scale 50 with two DATA clients, one taking every
acquisition as a Point (EVERY_ACQUISITION) and one the latest complete scan (LATEST), for about
60 s of wall time (5 s quick), once in the report's mode (one BI_ACQUIRE per sweep) and once
with Appendix D's continuous acquisition (``BirisInitRecord(continuous_acquisition=True)``).

Each run gives four figures, each measured within that one run:

* **accounts**: acquisitions BIRIS made (the simulator's count) against those the server
  accounted for (``ServerStatus.accounts().accounted``), compared where the accounts are
  complete: after stop_scan + wait_idle in report mode; in continuous acquisition when the ring
  has stopped (a reset stops it; the acquisitions made before the reset restarted it are told
  apart by the simulator's sequence start time). Target: unaccounted == 0.
* **memory**: RSS growth of the whole process (server, simulator and clients) per 10^5
  acquisitions, from a point after warm-up to the end of scanning.
* **threads** and **descriptors** before the rig was built and after server and rig were closed.
  Target: none left.
* **faults**: faults the server reported and hardware rules the simulator's audit caught while
  nothing was wrong. Target: 0.
"""

from __future__ import annotations

import gc
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from benchmarks.common import running_server
from benchmarks.harness import BenchContext, Figure, Target, benchmark
from benchmarks.soak_service import service_with_resets
from biris_hw import BirisInitRecord, ConnectionKind, DeliveryPolicy
from biris_hw.client import Connection
from biris_hw.errors import BirisError
from sim import SimulatedBiris

__all__ = ["soak"]

TIME_SCALE = 50.0
SWEEP_DEG = 90.0
WARM_UP = 0.2
"""Fraction of the run before the memory baseline is taken (imports, caches, first buffers)."""
CLIENT_TIMEOUT = 0.5
"""Wall seconds a client waits for data before it looks whether the run is over."""
DRAIN_TIMEOUT = 30.0
"""Wall seconds for stop_scan + wait_idle (a sweep takes about 30 ms at x50)."""
POINTS_DEPTH = 8192
"""The EVERY_ACQUISITION queue: a second of a slow client at x50, so nothing need be dropped."""
MAX_RSS_PER_1E5 = 2_000_000.0
"""Bytes of RSS growth per 10^5 acquisitions the memory figure allows (20 bytes each): half of
what keeping one float per acquisition costs (a float and its list slot, about 40 bytes; the
review measured 42 for the simulator's old unbounded history). A run of a minute also fills
the bounded buffers, which is included: the simulator keeps the newest 65,536 acquisition times
(about 0.5 MB once full)."""


def _rss_bytes() -> int:
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@dataclass
class _Client:
    """A DATA client in a thread of its own (it opens its connection there: it owns it)."""

    name: str
    policy: DeliveryPolicy
    received: int = 0
    dropped: int = 0
    errors: list[str] = field(default_factory=list)
    opened: threading.Event = field(default_factory=threading.Event)

    def run(self, open_conn: Callable[[], Connection[Any]], stop: threading.Event) -> None:
        conn = open_conn()
        self.opened.set()
        try:
            while not stop.is_set():
                try:
                    conn.ready_for_data(timeout=CLIENT_TIMEOUT)
                except TimeoutError:
                    continue
                except BirisError as exc:
                    self.errors.append(f"{type(exc).__name__}: {exc}")
                    break
                self.received += 1
            while True:  # what is queued was delivered to this client: take it
                try:
                    conn.ready_for_data(timeout=0)
                except (TimeoutError, BirisError):
                    break
                self.received += 1
            self.dropped = conn.dropped
        finally:
            conn.close()


@dataclass
class _Run:
    seconds: float
    made: int = 0
    accounted: int = 0
    read: int = 0
    in_scans: int = 0
    dropped_reasons: int = 0
    idle: int = 0
    lost: int = 0
    adds_up: bool = False
    rss_warm: int = 0
    rss_end: int = 0
    made_warm: int = 0
    made_end: int = 0
    threads_before: int = 0
    threads_during: int = 0
    threads_after: int = 0
    fds_before: int = 0
    fds_during: int = 0
    fds_after: int = 0
    faults: int = 0
    violations: int = 0
    client_errors: int = 0
    kept: int = 0
    points: int = 0
    points_dropped: int = 0
    scans: int = 0
    scans_dropped: int = 0
    hw_s: float = 0.0


def _made_before_restart(rig: SimulatedBiris, made_before: int, starts_before: int) -> int:
    """Acquisitions BIRIS made before the ring was started again after a reset: those after
    the restart's sequence start are the new ring's (not yet accounted for, by design)."""
    sup = rig.supervisor
    made_now = sup.acquisitions_made
    if sup.sequences_started <= starts_before:
        return made_now  # not restarted (yet): everything made is the stopped ring's
    restart = sup.sequence_starts[-1]
    times = sup.acquisition_times_since(made_before)
    return made_before + sum(1 for t in times if t < restart)


def _soak(record: BirisInitRecord, seconds: float, log: Callable[[str], None]) -> _Run:
    run = _Run(seconds)
    gc.collect()
    run.threads_before, run.fds_before = threading.active_count(), _fds()
    with running_server(time_scale=TIME_SCALE, record=record, seed=9) as bench:
        rig, server = bench.rig, bench.server
        conn = server.open()
        conn.wait_idle(timeout=DRAIN_TIMEOUT)
        stop = threading.Event()
        clients = [
            _Client("points", DeliveryPolicy.EVERY_ACQUISITION),
            _Client("latest", DeliveryPolicy.LATEST),
        ]
        depth = {DeliveryPolicy.EVERY_ACQUISITION: POINTS_DEPTH, DeliveryPolicy.LATEST: 1}
        threads = [
            threading.Thread(
                target=c.run,
                args=(
                    lambda c=c: server.open(
                        ConnectionKind.DATA, policy=c.policy, depth=depth[c.policy]
                    ),
                    stop,
                ),
                name=f"soak-{c.name}",
            )
            for c in clients
        ]
        for t in threads:
            t.start()
        for c in clients:
            if not c.opened.wait(DRAIN_TIMEOUT):
                raise RuntimeError(f"the {c.name} client could not open its connection")
        hw0 = rig.clock.now()
        conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG)
        started = time.monotonic()
        warm_at = started + WARM_UP * seconds
        end_at = started + seconds
        while time.monotonic() < warm_at:
            stop.wait(min(0.5, max(0.0, warm_at - time.monotonic())))  # paced, not a handshake
        gc.collect()
        run.rss_warm, run.made_warm = _rss_bytes(), rig.supervisor.acquisitions_made
        while time.monotonic() < end_at:
            stop.wait(min(1.0, max(0.0, end_at - time.monotonic())))
        gc.collect()
        run.rss_end, run.made_end = _rss_bytes(), rig.supervisor.acquisitions_made
        run.threads_during, run.fds_during = threading.active_count(), _fds()
        conn.stop_scan()
        conn.wait_idle(timeout=DRAIN_TIMEOUT)
        run.hw_s = rig.clock.now() - hw0
        stop.set()  # the clients take what is queued for them and close
        for t in threads:
            t.join(DRAIN_TIMEOUT)
        points, latest = clients
        run.points, run.points_dropped = points.received, points.dropped
        run.scans, run.scans_dropped = latest.received, latest.dropped
        run.client_errors = len(points.errors) + len(latest.errors)
        for c in clients:
            for error in c.errors[:3]:
                log(f"bench: soak {c.name} client: {error}")
        if record.continuous_acquisition:
            made_before, starts_before = (
                rig.supervisor.acquisitions_made,
                rig.supervisor.sequences_started,
            )
            conn.reset()  # stops the ring: the frames it made idle are counted then
            status = server.status()
            run.made = _made_before_restart(rig, made_before, starts_before)
        else:
            status = server.status()
            run.made = rig.supervisor.acquisitions_made
        accounts = status.accounts()
        run.accounted, run.read, run.in_scans = accounts.accounted, accounts.read, accounts.in_scans
        run.dropped_reasons = accounts.constant_azimuth + accounts.stale + accounts.aborted
        run.idle, run.lost, run.adds_up = accounts.idle, accounts.lost, accounts.adds_up
        run.kept = int(status.counters["acquisitions"])
        run.faults = int(status.counters["faults"])
        run.violations = len(rig.audit.violations)
        conn.close()
    gc.collect()
    run.threads_after, run.fds_after = threading.active_count(), _fds()
    return run


def _figures(mode: str, record_text: str, run: _Run) -> list[Figure]:
    base = (
        f"{record_text}; continuous +-{SWEEP_DEG:g} degree scanning at time_scale "
        f"{TIME_SCALE:g} for {run.seconds:g} s of wall time ({run.hw_s:.0f} s of hardware time), "
        "an EVERY_ACQUISITION and a LATEST DATA client, one run."
    )
    unaccounted = run.made - run.accounted
    grown = run.rss_end - run.rss_warm
    acquisitions = max(run.made_end - run.made_warm, 1)
    return [
        Figure(
            key=f"soak.{mode}_accounts",
            values={
                "made": float(run.made),
                "accounted": float(run.accounted),
                "unaccounted": float(unaccounted),
                "read": float(run.read),
                "in_scans": float(run.in_scans),
                "dropped_for_a_reason": float(run.dropped_reasons),
                "idle_ring_frames": float(run.idle),
                "lost": float(run.lost),
                "adds_up": float(run.adds_up),
                "points_received": float(run.points),
                "points_dropped": float(run.points_dropped),
                "points_missing": float(run.kept - run.points - run.points_dropped),
                "scans_received": float(run.scans),
                "scans_replaced": float(run.scans_dropped),
            },
            unit="acquisitions",
            target=Target("==", 0.0, on="unaccounted"),
            method=base
            + " made = the simulator's acquisitions_made; accounted = status().accounts()"
            ".accounted (read + idle ring frames + lost), compared after stop_scan + wait_idle"
            " (report mode) or once a reset has stopped the ring (continuous acquisition);"
            " adds_up is the administrator's identity (1 = holds); points_missing = acquisitions"
            " kept minus those the EVERY_ACQUISITION client received or was told it lost.",
        ),
        Figure(
            key=f"soak.{mode}_memory",
            values={
                "rss_growth_per_1e5_acquisitions": grown / acquisitions * 1e5,
                "rss_warm_mb": run.rss_warm / 1e6,
                "rss_end_mb": run.rss_end / 1e6,
                "acquisitions": float(acquisitions),
            },
            unit="bytes",
            target=Target("<=", MAX_RSS_PER_1E5, on="rss_growth_per_1e5_acquisitions"),
            method=base
            + f" Process RSS (VmRSS, after gc) {WARM_UP:.0%} into the run and at its end,"
            " divided by the acquisitions made in between; includes the simulator, and bounded"
            " buffers still filling (the simulator's 65,536 acquisition times). Quick runs make"
            " few acquisitions, so the figure is noisy there.",
        ),
        _left_behind(
            f"soak.{mode}_threads",
            "threads",
            (run.threads_before, run.threads_during, run.threads_after),
            base + " threading.active_count() before the rig was built, at the end of"
            " scanning, and after the server and the rig were closed.",
        ),
        _left_behind(
            f"soak.{mode}_descriptors",
            "descriptors",
            (run.fds_before, run.fds_during, run.fds_after),
            base + " Entries of /proc/self/fd at the same three moments.",
        ),
        Figure(
            key=f"soak.{mode}_faults",
            values={
                "faults": float(run.faults),
                "audit_violations": float(run.violations),
                "client_errors": float(run.client_errors),
                "problems": float(run.faults + run.violations + run.client_errors),
            },
            unit="count",
            target=Target("==", 0.0, on="problems"),
            method=base + " faults = the server's fault counter; audit_violations = the"
            " simulator's audit; client_errors = errors the DATA clients got. Nothing was"
            " injected.",
        ),
    ]


def _left_behind(key: str, unit: str, counts: tuple[int, int, int], method: str) -> Figure:
    """A resource counted before the run, during it and after close; ``left`` must be 0."""
    before, during, after = counts
    return Figure(
        key=key,
        values={
            "before": float(before),
            "during": float(during),
            "after_close": float(after),
            "left": float(after - before),
        },
        unit=unit,
        target=Target("==", 0.0, on="left"),
        method=method,
    )


@benchmark("soak")
def soak(ctx: BenchContext) -> list[Figure]:
    """Continuous scanning at x50: accounts, memory, threads, descriptors, faults; then the
    service through resets and router restarts (:mod:`benchmarks.soak_service`)."""
    seconds = float(ctx.pick(full=60, quick=5))
    figures: list[Figure] = []
    for mode, record, text in (
        ("report_mode", BirisInitRecord(), "The default BirisInitRecord (report mode)"),
        (
            "continuous_acquisition",
            BirisInitRecord(continuous_acquisition=True),
            "BirisInitRecord(continuous_acquisition=True)",
        ),
    ):
        ctx.log(f"bench: soak.{mode} ({seconds:g} s)")
        figures += _figures(mode, text, _soak(record, seconds, ctx.log))
    return figures + service_with_resets(ctx)
