"""Soak of the service through resets and router restarts (``soak.service_with_resets``).

A served simulator (x10, Scene.room(), continuous +-45 degree sweeps) behind a Zenoh router that
runs in a process of its own, as on a robot where the router bridges the sensor's computer and
the others. Every participant is a Zenoh client of that router: the service, a controller, a
recorder (``Recorder`` on a remote sensor) and three remote readers -- a subscriber of every
acquisition (``subscribe("point")``), a subscriber of every scan (``subscribe("scan")``) and a
DATA connection read scan by scan (EVERY_BUFFER). Every period the controller resets the sensor
(and sweeps again), and half a period later the router is killed and started again on the same
endpoint a few seconds later. Nobody restarts a consumer: each must carry on by itself.

What is measured, in that one run:

* **accounts**: acquisitions BIRIS made (the simulator's count) against those the server
  accounted for, after the last stop_scan + wait_idle. Target: unaccounted == 0.
* **consumers**: for each consumer, what it got and what it was told it missed, against what
  there was to get. The subscribers are exact: the service numbers its publications (the
  ``point`` and ``scan`` counters), so received + dropped must equal what was published. The
  DATA reader is exact for scans: received + missed (``Scan.seq`` gaps across an outage) +
  dropped (its queue) against the scans the service's sensor completed while it was connected.
  The recorder: scans written + dropped + unwritten + missed; its acquisitions lost in an
  outage are not counted one by one (a remote EVERY_ACQUISITION connection does not number
  them) but as lost spans (seconds), which the figure reports beside. Target: uncounted == 0
  over the exact counts, and no consumer failed.
* **events**: resets and router restarts done, faults seen, consumer errors.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from benchmarks.harness import BenchContext, Figure, Target
from biris_hw import BirisInitRecord, BirisServer, ConnectionKind
from biris_hw.data import DeliveryPolicy, Scan
from biris_hw.errors import BirisError, ConnectionLost, HardwareFault, Initialising
from sim import Scene, SimulatedBiris

__all__ = ["service_with_resets"]

TIME_SCALE = 10.0
SWEEP_DEG = 45.0
ROUTER_DOWN_S = 3.0
"""How long the router stays down at each restart (the review's blip)."""
LEASE_MS = 2000
"""Zenoh's lease for every session here: a dead router is noticed in about 2 s, not 10."""
RETRY_S = 30.0
"""How long the controller retries a request through an outage (the project's ride-out bound)."""
SETTLE_S = 20.0
"""How long the end waits for every consumer to have taken what it was sent."""

_ROUTER = """
import json, sys, threading, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
conf.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(conf)
print("ready", flush=True)
sys.stdin.read()
session.close()
"""

_T = TypeVar("_T")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class _Router:
    """A Zenoh router in a process of its own, killed and started again on the same endpoint."""

    def __init__(self, where: str) -> None:
        self.where = where
        self.proc: subprocess.Popen[str] | None = None
        self.restarts = 0

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _ROUTER, self.where],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # blocks until it listens (or dies: "")
        if line.strip() != "ready":
            raise RuntimeError(f"the Zenoh router did not start on {self.where}")

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(timeout=10)
            self.proc = None

    def restart(self, down_s: float, stop: threading.Event) -> None:
        self.kill()
        stop.wait(down_s)  # the blip: how long the network is away, not a synchronisation
        self.start()
        self.restarts += 1


def _options(mode: str = "client") -> dict[str, Any]:
    return {
        "mode": mode,
        "transport/link/tx/lease": LEASE_MS,
        "transport/link/tx/keep_alive": 4,
        "connect/retry": {
            "period_init_ms": 200,
            "period_max_ms": 1000,
            "period_increase_factor": 2,
        },
    }


def _retrying(call: Callable[[], _T], what: str) -> _T:
    """``call()``, again while the network is lost, for up to :data:`RETRY_S`."""
    deadline = time.monotonic() + RETRY_S
    while True:
        try:
            return call()
        except ConnectionLost:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{what}: the service stayed out of reach {RETRY_S} s") from None


@dataclass
class _Counter:
    """What a subscriber received, under a lock (Zenoh calls it from its own thread)."""

    received: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def see(self, _item: Any) -> None:
        with self.lock:
            self.received += 1


@dataclass
class _ScanReader:
    """A DATA connection read scan by scan in a thread of its own, through every outage."""

    received: int = 0
    outages: int = 0
    errors: list[str] = field(default_factory=list)
    last_seq: dict[str, int] = field(default_factory=dict)
    first_seq: dict[str, int] = field(default_factory=dict)
    missed: int = 0
    dropped: int = 0

    def run(self, conn: Any, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                scan: Scan = conn.ready_for_data(timeout=0.5)
            except TimeoutError:
                continue
            except ConnectionLost:
                self.outages += 1
                continue
            except Initialising:  # a reset under way: the data come back on this connection
                continue
            except BirisError as exc:
                self.errors.append(f"{type(exc).__name__}: {exc}")
                if isinstance(exc, HardwareFault):
                    continue  # a fault reaches the reader; the reset brings the data back
                break
            self.received += 1
            key = scan.direction.name
            self.first_seq.setdefault(key, scan.seq)
            self.last_seq[key] = scan.seq
        self.missed = int(getattr(conn, "missed", 0))
        self.dropped = int(conn.dropped)


@dataclass
class _Run:
    seconds: float
    made: int = 0
    accounted: int = 0
    resets: int = 0
    router_restarts: int = 0
    faults: int = 0
    published_points: int = 0
    published_scans: int = 0
    unpublished: int = 0
    point_sub: tuple[int, int] = (0, 0)
    scan_sub: tuple[int, int] = (0, 0)
    reader: _ScanReader = field(default_factory=_ScanReader)
    recorder: dict[str, Any] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)


@contextmanager
def _stack(seconds: float, log: Callable[[str], None]) -> Iterator[Any]:
    """Router, rig, server and service, all closed on exit."""
    from biris_hw.io.net import serve

    where = f"tcp/127.0.0.1:{_free_port()}"
    router = _Router(where)
    router.start()
    try:
        with (
            SimulatedBiris(scene=Scene.room(), samples=64, time_scale=TIME_SCALE, seed=1) as rig,
            BirisServer(rig.hardware, BirisInitRecord()) as server,
            serve(
                server,
                name="soak",
                connect=[where],
                controllers={"op": "soak"},
                multicast=False,
                options=_options(),
            ) as service,
        ):
            log(f"bench: soak.service_with_resets: serving through a router at {where}")
            yield router, rig, server, service
    finally:
        router.kill()


def _soak(seconds: float, period: float, log: Callable[[str], None]) -> _Run:
    from biris_hw.io.net import connect
    from biris_hw.io.record import Recorder

    run = _Run(seconds)
    stop = threading.Event()
    with (
        _stack(seconds, log) as (router, rig, server, service),
        tempfile.TemporaryDirectory() as tmp,
    ):
        where = router.where
        kw: dict[str, Any] = {"multicast": False, "options": _options()}
        with (
            connect("soak", [where], user="op", password="soak", **kw) as controller,
            connect("soak", [where], **kw) as points_remote,
            connect("soak", [where], **kw) as scans_remote,
            connect("soak", [where], **kw) as data_remote,
            connect("soak", [where], **kw) as record_remote,
        ):
            points, scans = _Counter(), _Counter()
            point_sub = points_remote.subscribe("point", points.see)
            scan_sub = scans_remote.subscribe("scan", scans.see)
            data = data_remote.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
            reader = threading.Thread(target=run.reader.run, args=(data, stop), daemon=True)
            reader.start()
            recorder = Recorder(record_remote, Path(tmp) / "soak.mcap", profiles=False)
            recorder.start()
            conn = controller.open()
            _retrying(lambda: conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG), "sweep")
            started = time.monotonic()
            next_reset, next_blip = started + period, started + period / 2
            while (now := time.monotonic()) < started + seconds:
                if now >= next_blip:
                    log("bench: soak.service_with_resets: router restart")
                    router.restart(ROUTER_DOWN_S, stop)
                    next_blip += period
                elif now >= next_reset:
                    log("bench: soak.service_with_resets: reset")
                    _retrying(conn.reset, "reset")
                    run.resets += 1
                    _retrying(lambda: conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG), "sweep")
                    next_reset += period
                stop.wait(max(0.0, min(next_blip, next_reset, started + seconds) - now))
            _retrying(conn.stop_scan, "stop")
            _retrying(lambda: conn.wait_idle(timeout=30.0), "wait_idle")
            status = server.status()
            run.made = rig.supervisor.acquisitions_made
            run.accounted = status.accounts().accounted
            run.faults = status.counters.get("faults", 0)
            completed = server.status().counters.get("scans", 0)
            deadline = time.monotonic() + SETTLE_S
            while True:  # the feed publishes within a batch or two, Zenoh on its own threads
                run.published_points = service.published["point"]
                run.published_scans = service.published["scan/cw"] + service.published["scan/ccw"]
                settled = (
                    run.published_scans + service.dropped_scans >= completed
                    and points.received + point_sub.dropped >= run.published_points
                    and scans.received + scan_sub.dropped >= run.published_scans
                )
                if settled or time.monotonic() > deadline:
                    break
                stop.wait(0.1)  # a look: what is compared is read again after it
            run.unpublished = service.dropped_points + service.dropped_scans
            stop.set()
            reader.join(timeout=10)
            run.point_sub = (points.received, point_sub.dropped)
            run.scan_sub = (scans.received, scan_sub.dropped)
            point_sub.close()
            scan_sub.close()
            summary = recorder.close()
            run.recorder = {
                "scans": recorder.scans,
                "points": recorder.points,
                "dropped_points": recorder.dropped_points,
                "dropped_scans": recorder.dropped_scans,
                "unwritten_scans": getattr(summary, "unwritten_scans", 0),
                "unwritten_points": getattr(summary, "unwritten_points", 0),
                "lost_seconds": getattr(summary, "lost_seconds", 0.0),
                "missed_scans": int(getattr(record_remote, "missed", 0)),
                "error": None if recorder.error is None else str(recorder.error),
            }
            run.router_restarts = router.restarts
            with suppress(BirisError):
                data.close()
    run.errors = list(run.reader.errors)
    if run.recorder["error"]:
        run.errors.append(f"recorder: {run.recorder['error']}")
    return run


def service_with_resets(ctx: BenchContext) -> list[Figure]:
    """The figures of ``soak.service_with_resets`` (called by the ``soak`` section)."""
    seconds = float(ctx.pick(full=180, quick=24))
    period = float(ctx.pick(full=60, quick=12))
    ctx.log(
        f"bench: soak.service_with_resets ({seconds:g} s, a reset and a blip every {period:g} s)"
    )
    run = _soak(seconds, period, ctx.log)
    base = (
        f"{seconds:g} s of wall time at x{TIME_SCALE:g}, continuous +-{SWEEP_DEG:g} degree sweeps"
        f" of Scene.room(); every {period:g} s a controller's reset, and half a period later the"
        f" router killed and started again {ROUTER_DOWN_S:g} s later; service, controller,"
        " recorder and three readers are Zenoh clients of that router (lease"
        f" {LEASE_MS} ms); pid {os.getpid()}."
    )
    points_uncounted = run.published_points - sum(run.point_sub)
    scans_uncounted = run.published_scans - sum(run.scan_sub)
    rec = run.recorder
    recorder_scans = rec["scans"] + rec["dropped_scans"] + rec["unwritten_scans"]
    recorder_scans += rec["missed_scans"]
    reader_scans = run.reader.received + run.reader.missed + run.reader.dropped
    reader_span = sum(
        run.reader.last_seq[d] - run.reader.first_seq[d] + 1 for d in run.reader.last_seq
    )
    return [
        Figure(
            key="soak.service_with_resets_accounts",
            values={
                "made": float(run.made),
                "accounted": float(run.accounted),
                "unaccounted": float(run.made - run.accounted),
                "resets": float(run.resets),
                "router_restarts": float(run.router_restarts),
                "faults": float(run.faults),
            },
            unit="acquisitions",
            target=Target("==", 0.0, on="unaccounted"),
            method=base + " made = the simulator's acquisitions_made; accounted ="
            " status().accounts().accounted after the last stop_scan + wait_idle.",
        ),
        Figure(
            key="soak.service_with_resets_consumers",
            values={
                "points_published": float(run.published_points),
                "points_received": float(run.point_sub[0]),
                "points_dropped": float(run.point_sub[1]),
                "points_uncounted": float(points_uncounted),
                "scans_published": float(run.published_scans),
                "scans_received": float(run.scan_sub[0]),
                "scans_dropped": float(run.scan_sub[1]),
                "scans_uncounted": float(scans_uncounted),
                "reader_scans_read": float(run.reader.received),
                "reader_scans_missed": float(run.reader.missed),
                "reader_scans_dropped": float(run.reader.dropped),
                "reader_scans_uncounted": float(reader_span - reader_scans),
                "reader_outages_seen": float(run.reader.outages),
                "recorder_scans": float(rec["scans"]),
                "recorder_scans_counted": float(recorder_scans - rec["scans"]),
                "recorder_points": float(rec["points"]),
                "recorder_points_dropped": float(rec["dropped_points"] + rec["unwritten_points"]),
                "recorder_lost_seconds": float(rec["lost_seconds"]),
                "consumer_errors": float(len(run.errors)),
                "uncounted": float(points_uncounted + scans_uncounted + reader_span - reader_scans),
            },
            unit="count",
            target=Target("==", 0.0, on="uncounted"),
            method=base
            + " Subscribers: received + dropped (gaps in the service's publication counters)"
            " against the service's own count of publications. DATA reader: scans read +"
            " missed (Scan.seq gaps across outages, RemoteConnection.missed) + dropped against"
            " the seq span it saw. Recorder: scans written, and those counted as dropped,"
            " unwritten or missed; its acquisitions lost in an outage are counted as time"
            " (recorder_lost_seconds), not one by one. consumer_errors lists errors other than"
            " ConnectionLost, Initialising and a fault's HardwareFault: "
            + json.dumps(run.errors[:5]),
        ),
    ]
