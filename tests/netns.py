"""Network faults for the remote-client tests: a partition between two network namespaces, a
Zenoh router that can be killed, and the processes that run on either side.

:class:`Partition` makes two namespaces joined by a veth pair (``ip netns``, ``ip link``: root
on Linux), runs a process in either (:meth:`Partition.start`), and cuts and mends the link
(:meth:`Partition.cut`, :meth:`Partition.mend`); leaving the block deletes both namespaces, and
the veth pair with them, whatever happened. :func:`unavailable` says why the platform cannot
(the tests skip with that reason).

:class:`TickingSensor` is a sensor in memory that completes a scan every ``period_s`` seconds,
CW and CCW in turn, numbered per direction as a server numbers them, and offers each to every
DATA connection of scans (a full queue drops its oldest and counts it, as a server's does). So
what a remote reader got, missed and dropped can be checked against what was made, exactly.
:class:`Reader` reads such a sensor through a remote DATA connection on a thread of its own,
asking again after each ConnectionLost, as an application would.

Run as a program (``python -m tests.netns ROLE ...``), the roles a test starts in a namespace or
beside itself; each prints ``ready`` once it is, then runs until stdin closes (or SIGTERM):

* ``router ENDPOINT`` -- a Zenoh router listening on ENDPOINT;
* ``serve --name N (--listen E | --connect E) [--mode M] [--period S] [--lease-ms L]`` -- a
  service on a :class:`TickingSensor`; prints ``released`` each time it has released a vanished
  client's connections, and ``made {...}`` (scans made per direction) on a ``made`` line;
* ``read --name N --endpoint E [--mode M] [--lease-ms L]`` -- a :class:`Reader`; prints ``lost
  {...}`` at each ConnectionLost, ``again {...}`` at the first scan after one, ``wrong {...}``
  for any other error, and ``summary {...}`` (what it got, missed, dropped) on a ``quit`` line;
* ``linger --name N --endpoint E`` -- a client that never closes: ``ready``, then it returns at
  the first line it reads, leaving its remote sensor to the interpreter's exit.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Scan
from biris_hw.errors import ConnectionClosed, ConnectionLost
from biris_hw.status import ServerState, ServerStatus
from tests.net_helpers import ROOT, START_S, Helper

PORT = 17447
"""The service's port inside a namespace (nothing else listens there)."""


def zenoh_options(lease_ms: int | None = None, mode: str | None = None) -> dict[str, Any]:
    """Zenoh settings for a test's sessions: a short lease (a cut link is noticed in about
    ``lease_ms``, not Zenoh's 10 s), quick reconnection, and the mode."""
    options: dict[str, Any] = {
        "connect/retry": {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}
    }
    if lease_ms is not None:
        options["transport/link/tx/lease"] = lease_ms
        options["transport/link/tx/keep_alive"] = 4
    if mode is not None:
        options["mode"] = mode
    return options


# -- a sensor that scans by itself --------------------------------------------------------------


def make_scan(direction: Direction, seq: int, t: float) -> Scan:
    """A tiny scan (2 acquisitions of 4 samples): enough for the codec, cheap to send."""
    ranges = np.full((2, 4), 1500, dtype=np.int16)
    return Scan(
        direction=direction,
        seq=seq,
        azimuth=np.array([0, 8], dtype=np.int32) * direction.sign,
        range_mm=ranges,
        closest_mm=ranges[:, 0].copy(),
        intensity=np.zeros((2, 4), dtype=np.int16),
        t=np.array([t, t + 0.001]),
    )


class TickingSensor:
    """A sensor in memory that scans on its own (see the module). Thread-safe; every wait is on
    one condition, woken by whatever ends it."""

    playback = False
    paced = True
    record = None

    def __init__(self, period_s: float = 0.02) -> None:
        self.period_s = period_s
        self.cond = threading.Condition()
        self.made = {Direction.CW: 0, Direction.CCW: 0}
        self._conns: list[TickConnection] = []
        self._next = 1
        self._closed = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t0 = time.monotonic()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._tick, name="ticking-sensor", daemon=True)
        self._thread.start()

    def _tick(self) -> None:
        direction = Direction.CW
        while not self._stop.wait(self.period_s):
            with self.cond:
                self.made[direction] += 1
                scan = make_scan(direction, self.made[direction], self.clock())
                for conn in self._conns:
                    conn.offer(scan)
                self.cond.notify_all()
            direction = Direction.CCW if direction is Direction.CW else Direction.CW

    def stop(self) -> None:
        """No more scans (the count stays what it is)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def clock(self) -> float:
        return time.monotonic() - self._t0

    def open(
        self,
        kind: ConnectionKind = ConnectionKind.NORMAL,
        *,
        policy: DeliveryPolicy = DeliveryPolicy.LATEST,
        depth: int | None = None,
    ) -> TickConnection:
        with self.cond:
            if self._closed:
                raise ConnectionClosed("the ticking sensor is closed")
            conn = TickConnection(self, self._next, kind, policy, depth or 8)
            self._next += 1
            self._conns.append(conn)
        return conn

    def status(self, *, newer_than: int | None = None, timeout: float | None = None) -> Any:
        if newer_than is not None:  # its status says nothing new: waits out its timeout
            with self.cond:
                self.cond.wait_for(lambda: self._closed, timeout)
            raise TimeoutError("the ticking sensor's status does not change")
        with self.cond:
            scans = sum(self.made.values())
        return ServerStatus(
            state=ServerState.SCANNING,
            fault=None,
            azimuth=0,
            elevation=0,
            calibration=None,
            continuous=True,
            acquisition="single",
            ring="off",
            counters={"scans": scans},
            connections={},
        )

    def forget(self, conn: TickConnection) -> None:
        with self.cond:
            if conn in self._conns:
                self._conns.remove(conn)
            self.cond.notify_all()

    def close(self) -> None:
        self._stop.set()
        with self.cond:
            self._closed = True
            self.cond.notify_all()


class TickConnection:
    """One connection of a :class:`TickingSensor`: a DATA connection of scans queues them."""

    def __init__(
        self, sensor: TickingSensor, ident: int, kind: Any, policy: Any, depth: int
    ) -> None:
        self.sensor = sensor
        self.ident = ident
        self.kind = ConnectionKind(kind)
        self.policy = DeliveryPolicy(policy)
        self.depth = depth
        self.dropped = 0
        self.closed = False
        self._queue: list[Scan] = []

    def offer(self, scan: Scan) -> None:
        """A scan completed (under the sensor's condition)."""
        if self.kind is not ConnectionKind.DATA or self.policy is DeliveryPolicy.EVERY_ACQUISITION:
            return
        if self.policy is DeliveryPolicy.LATEST:
            self.dropped += len(self._queue)
            self._queue = [scan]
            return
        self._queue.append(scan)
        if len(self._queue) > self.depth:
            del self._queue[0]
            self.dropped += 1

    def ready_for_data(self, timeout: float | None = None) -> Scan:
        with self.sensor.cond:
            self.sensor.cond.wait_for(lambda: self.closed or bool(self._queue), timeout)
            if self.closed:
                raise ConnectionClosed(f"connection {self.ident} is closed")
            if not self._queue:
                raise TimeoutError("no scan")
            return self._queue.pop(0)

    def status(self, *, newer_than: int | None = None, timeout: float | None = None) -> Any:
        if newer_than is not None:
            with self.sensor.cond:
                self.sensor.cond.wait_for(lambda: self.closed, timeout)
            if self.closed:
                raise ConnectionClosed(f"connection {self.ident} is closed")
            raise TimeoutError("the ticking sensor's status does not change")
        return self.sensor.status()

    def wait_idle(self, timeout: float | None = None) -> None:
        return None

    def request_point(self) -> None:
        return None

    def request_scan_data(self, direction: Any) -> None:
        return None

    def stop_scan(self) -> None:
        return None

    def close(self) -> None:
        with self.sensor.cond:
            self.closed = True
        self.sensor.forget(self)

    def __enter__(self) -> TickConnection:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- a remote reader that rides out the network -------------------------------------------------


class Reader:
    """Reads scans through ``remote``'s DATA connection (EVERY_BUFFER) on a thread, asking again
    after every ConnectionLost; notes what it got and every error by its class."""

    def __init__(self, remote: Any, depth: int = 1024, report: Any = None) -> None:
        self.remote = remote
        self.data = remote.open(
            ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=depth
        )
        self.cond = threading.Condition()
        self.got: dict[Direction, list[int]] = {Direction.CW: [], Direction.CCW: []}
        self.lost: list[tuple[float, str]] = []
        """(time.monotonic(), message) of each ConnectionLost."""
        self.again: list[float] = []
        """time.monotonic() of the first scan after each ConnectionLost."""
        self.wrong: list[BaseException] = []
        """Any other error (a RequestError above all: a partition must never be one)."""
        self._report = report
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="reader", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        waiting_again = False
        while not self._stop.is_set():
            try:
                scan = self.data.ready_for_data(timeout=1.0)
            except TimeoutError:
                continue
            except ConnectionLost as exc:
                with self.cond:
                    self.lost.append((time.monotonic(), str(exc)))
                    self.cond.notify_all()
                waiting_again = True
                self._say("lost", {"message": str(exc)})
                continue
            except BaseException as exc:  # noted, and the reader ends: the test fails on it
                with self.cond:
                    self.wrong.append(exc)
                    self.cond.notify_all()
                self._say("wrong", {"error": type(exc).__name__, "message": str(exc)})
                return
            with self.cond:
                self.got[scan.direction].append(scan.seq)
                if waiting_again:
                    self.again.append(time.monotonic())
                self.cond.notify_all()
            if waiting_again:
                waiting_again = False
                self._say("again", {"seq": scan.seq, "direction": scan.direction.name})

    def _say(self, what: str, body: dict[str, Any]) -> None:
        if self._report is not None:
            self._report(what, body)

    def count(self) -> int:
        with self.cond:
            return sum(len(seqs) for seqs in self.got.values())

    def wait(self, predicate: Any, timeout: float, what: str) -> None:
        """Wait until ``predicate()`` (read under the reader's condition), or fail."""
        with self.cond:
            if not self.cond.wait_for(lambda: predicate() or bool(self.wrong), timeout):
                raise AssertionError(f"the reader never saw {what} in {timeout:g} s")
            if self.wrong:
                raise AssertionError(f"the reader failed: {self.wrong[0]!r}")

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(START_S)

    def summary(self) -> dict[str, Any]:
        """What it got per direction (first, last, how many), and what the connection counted."""
        with self.cond:
            got = {
                d.name: {"first": seqs[0], "last": seqs[-1], "count": len(seqs)}
                for d, seqs in self.got.items()
                if seqs
            }
            ordered = all(a < b for seqs in self.got.values() for a, b in itertools.pairwise(seqs))
        return {
            "got": got,
            "ordered": ordered,
            "missed": self.data.missed,
            "dropped": self.data.dropped,
            "reopened": self.data.reopened,
            "lost": len(self.lost),
            "wrong": [f"{type(e).__name__}: {e}" for e in self.wrong],
            "outages": len(self.remote.outages),
        }


def accounted(summary: dict[str, Any]) -> tuple[int, int]:
    """(scans the sensor made between each direction's first and last scan read, scans read +
    missed + dropped): equal when every scan is accounted for."""
    made = sum(g["last"] - g["first"] + 1 for g in summary["got"].values())
    seen = sum(g["count"] for g in summary["got"].values())
    return made, seen + summary["missed"] + summary["dropped"]


# -- processes, and the namespaces they run in --------------------------------------------------


class Proc(Helper):
    """A role of this module in another process, in namespace ``ns`` if given; its stdout lines
    on a queue (:meth:`expect`), ended by :meth:`close` or :meth:`kill` (those of Helper)."""

    def __init__(self, args: Sequence[str], ns: str | None = None) -> None:
        where = ["ip", "netns", "exec", ns] if ns is not None else []
        self.proc = subprocess.Popen(
            [*where, sys.executable, "-m", "tests.netns", *args],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def send(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def expect_json(self, prefix: str, timeout: float = START_S) -> dict[str, Any]:
        line = self.expect(prefix + " ", timeout)
        body: dict[str, Any] = json.loads(line[len(prefix) + 1 :])
        return body


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=30)


def unavailable() -> str | None:
    """Why this platform cannot make network namespaces (None when it can)."""
    if not sys.platform.startswith("linux"):
        return "network namespaces are a Linux feature"
    if shutil.which("ip") is None:
        return "needs the ip command (iproute2)"
    if os.geteuid() != 0:
        return "making network namespaces needs root"
    probe = f"biris-probe-{os.getpid()}"
    made = _ip("netns", "add", probe, check=False)
    if made.returncode != 0:
        return f"ip netns add failed: {made.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return None


class Partition:
    """Two network namespaces, A and B, joined by a veth pair (see the module)."""

    def __init__(self) -> None:
        tag = os.getpid() % 100000
        self.ns = (f"biris-{tag}-a", f"biris-{tag}-b")
        self._dev = (f"bv{tag}a", f"bv{tag}b")  # an interface name has 15 characters at most
        subnet = f"10.199.{tag % 250 + 1}"
        self.addr = (f"{subnet}.1", f"{subnet}.2")
        self._procs: list[Proc] = []

    def __enter__(self) -> Partition:
        try:
            for ns in self.ns:
                _ip("netns", "add", ns)
                _ip("-n", ns, "link", "set", "lo", "up")
            a, b = self.ns
            dev_a, dev_b = self._dev
            _ip("link", "add", dev_a, "netns", a, "type", "veth", "peer", "name", dev_b, "netns", b)
            for ns, dev, addr in zip(self.ns, self._dev, self.addr, strict=True):
                _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
                _ip("-n", ns, "link", "set", dev, "up")
        except BaseException:
            self._delete()
            raise
        return self

    def endpoint(self, side: int, port: int = PORT) -> str:
        return f"tcp/{self.addr[side]}:{port}"

    def start(self, side: int, args: Sequence[str]) -> Proc:
        """A role of this module in namespace A (0) or B (1); ended when the block ends."""
        proc = Proc(args, self.ns[side])
        self._procs.append(proc)
        return proc

    def cut(self) -> None:
        """Take the link down: packets between A and B go nowhere, no socket is told."""
        _ip("-n", self.ns[0], "link", "set", self._dev[0], "down")

    def mend(self) -> None:
        _ip("-n", self.ns[0], "link", "set", self._dev[0], "up")

    def __exit__(self, *exc: object) -> None:
        try:
            for proc in self._procs:
                proc.close()
        finally:
            self._delete()

    def _delete(self) -> None:
        for ns in self.ns:  # deleting a namespace deletes its end of the pair, and so the pair
            _ip("netns", "del", ns, check=False)

    def leftovers(self) -> list[str]:
        """Namespaces or links of ours that still exist (none after the block)."""
        names = _ip("netns", "list").stdout
        links = _ip("-o", "link", "show").stdout
        return [n for n in (*self.ns, *self._dev) if n in names or f" {n}@" in links]


# -- the roles, when run as a program -----------------------------------------------------------


def _router(argv: Sequence[str]) -> None:
    import zenoh

    from biris_hw.io.net.zconfig import make_config

    config = make_config(listen=[argv[0]], options={"mode": "router"})
    session = zenoh.open(config)
    try:
        print("ready", flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            sys.stdin.read()
    finally:
        session.close()  # type: ignore[no-untyped-call]


class _Released(logging.Handler):
    """Prints ``released`` when the service has released a vanished client's connections: its
    count (:attr:`Service.released_clients`) looked at whenever it logs, as it does then."""

    def __init__(self) -> None:
        super().__init__()
        self.service: Any = None
        self._seen = 0

    def emit(self, record: logging.LogRecord) -> None:
        if self.service is None:
            return
        released = self.service.released_clients
        if released > self._seen:
            self._seen = released
            print("released", flush=True)


def _serve(argv: Sequence[str]) -> None:
    from biris_hw.io.net import serve

    parser = argparse.ArgumentParser()
    parser.add_argument("--name", default="biris0")
    parser.add_argument("--listen", action="append", default=[])
    parser.add_argument("--connect", action="append", default=[])
    parser.add_argument("--mode")
    parser.add_argument("--period", type=float, default=0.02)
    parser.add_argument("--lease-ms", type=int)
    args = parser.parse_args(argv)
    released = _Released()
    service_log = logging.getLogger("biris_hw.io.net.service")
    service_log.setLevel(logging.INFO)
    service_log.addHandler(released)
    sensor = TickingSensor(args.period)
    with serve(
        sensor,  # type: ignore[arg-type]
        name=args.name,
        listen=args.listen,
        connect=args.connect,
        multicast=False,
        options=zenoh_options(args.lease_ms, args.mode),
    ) as service:
        released.service = service
        sensor.start()
        print("ready", flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            for line in sys.stdin:
                if line.strip() == "made":
                    with sensor.cond:
                        made = {d.name: n for d, n in sensor.made.items()}
                    print("made " + json.dumps(made), flush=True)
        _STOPPING.set()
        sensor.close()


def _read(argv: Sequence[str]) -> None:
    from biris_hw.io.net import connect

    parser = argparse.ArgumentParser()
    parser.add_argument("--name", default="biris0")
    parser.add_argument("--endpoint", required=True)
    parser.add_argument("--mode")
    parser.add_argument("--lease-ms", type=int)
    args = parser.parse_args(argv)

    def report(what: str, body: dict[str, Any]) -> None:
        print(f"{what} {json.dumps(body)}", flush=True)

    options = zenoh_options(args.lease_ms, args.mode)
    with connect(args.name, [args.endpoint], multicast=False, options=options) as remote:
        reader = Reader(remote, report=report)
        reader.wait(lambda: reader.count() >= 4, START_S, "its first scans")
        print("ready", flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            for line in sys.stdin:
                if line.strip() == "quit":
                    break
        _STOPPING.set()
        reader.stop()
        print("summary " + json.dumps(reader.summary()), flush=True)


def _linger(argv: Sequence[str]) -> None:
    """A client that never closes: connects, opens a DATA connection, says ``ready``, and
    returns when it reads a line (its interpreter must then end by itself)."""
    from biris_hw.io.net import connect

    parser = argparse.ArgumentParser()
    parser.add_argument("--name", default="biris0")
    parser.add_argument("--endpoint", required=True)
    args = parser.parse_args(argv)
    remote = connect(args.name, [args.endpoint], multicast=False, options=zenoh_options())
    remote.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
    print("ready", flush=True)
    sys.stdin.readline()


_STOPPING = threading.Event()


def _on_term(signum: int, frame: object) -> None:
    """SIGTERM: a KeyboardInterrupt the first time, while the role waits; ignored once it is
    leaving (Helper.close closes stdin, then terminates)."""
    if not _STOPPING.is_set():
        _STOPPING.set()
        raise KeyboardInterrupt


def main(argv: Sequence[str]) -> None:
    signal.signal(signal.SIGTERM, _on_term)
    roles = {"router": _router, "serve": _serve, "read": _read, "linger": _linger}
    roles[argv[0]](argv[1:])


@contextlib.contextmanager
def router_process(endpoint: str) -> Iterator[Proc]:
    """A Zenoh router in another process (on the host's network), ready when the block
    begins; killed or ended when it ends."""
    router = Proc(["router", endpoint])
    try:
        router.expect("ready")
        yield router
    finally:
        router.close()


if __name__ == "__main__":
    main(sys.argv[1:])
