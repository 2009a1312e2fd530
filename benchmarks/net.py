"""The network service (Zenoh on loopback TCP): latency, throughput ceiling and fan-out, measured
in one run beside the local path.

* **latency**: every acquisition, from the simulator raising the data interrupt that announces it
  to a subscriber *in another process* receiving the service's Point publication, beside a
  local EVERY_ACQUISITION DATA connection in this process during the same sweeps. Both clocks
  are ``perf_counter_ns`` (CLOCK_MONOTONIC, shared by the processes of one host). Targets: the
  remote p99 within one acquisition period; the remote/local p50 ratio is reported.
* **throughput**: the ceiling of the service's publication path at 128 samples with zero loss:
  the service fed Points as fast as asked by a stand-in sensor (so encoding, Zenoh and the
  remote decoding are all in the figure, the sensor's own rate is not), rates stepped up until a
  subscriber in another process misses one. Target: at least 10 x the sensor's rate.
* **fanout**: the latency measurement with 10 subscriber processes at once.
* **flood_fairness**: a client's ``status()`` round trip while another peer floods the service,
  against the same client's while nobody floods, in one run: what one flooding peer costs the
  others (issue 25: the other clients' p50 within 2 x of quiet).

Run: ``.venv/bin/python -m benchmarks --only net``.
"""

from __future__ import annotations

import bisect
import contextlib
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from benchmarks.common import IrqRecorder, acquisition_period_s, running_server
from benchmarks.harness import BenchContext, Figure, Target, benchmark, summarise
from biris_hw import ConnectionKind
from biris_hw.data import DeliveryPolicy, Point
from biris_hw.errors import ConnectionClosed

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor

__all__ = ["net"]

ROOT = Path(__file__).resolve().parent.parent
TIME_SCALE = 1.0
MATCH_WINDOW_NS = 2_000_000_000
SUBSCRIBERS = 10
RATES = (200, 500, 1000, 2000, 4000, 8000, 12000, 16000)
"""Points per second offered in the throughput steps (the sensor makes 20/s at 128 samples). The
top rungs are more than the service makes on two cores (about 10,000-12,000/s: its publication
path is the limit, the stand-in then hands out as fast as it is asked), so the ceiling is
measured, not the ladder's top."""


def _port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class _Subscriber:
    """A subscriber process: ``python -m benchmarks.net sub ENDPOINT NAME [status]``; prints
    ``ready`` once subscribed (with ``status``: once the service's first status publication has
    reached it), then, when its stdin closes, one JSON line of (receive ns, acq), its drops and
    the CPU seconds it used while measured."""

    def __init__(self, where: str, name: str, wait_status: bool) -> None:
        self.started_ns = time.perf_counter_ns()
        self.ready_ns = 0
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "benchmarks.net", "sub", where, name]
            + (["status"] if wait_status else []),
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def wait_ready(self) -> None:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if line.strip() != "ready":
            raise RuntimeError(f"subscriber did not start: {line!r}")
        self.ready_ns = time.perf_counter_ns()

    def finish(self) -> dict[str, Any]:
        out, _ = self.proc.communicate(timeout=60)
        result: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
        return result


@contextlib.contextmanager
def _subscribers(
    where: str, name: str, n: int, *, wait_status: bool = True
) -> Iterator[list[_Subscriber]]:
    """``n`` subscriber processes, all started at once and all ready when the block begins.

    Ready means what a measurement needs, not that the process printed something: with
    ``wait_status`` each has received one of the service's status publications, so its
    subscriptions have reached the service (declarations travel in order on its link) and its
    decoder is warm. Start-up is kept out of every figure: an early version timed from the
    moment each process had *declared* its subscription, and its first Points then waited
    behind the codec's first use in ten processes at once (up to 0.8 s: docs/benchmarks.md).
    """
    subs: list[_Subscriber] = []
    try:
        subs.extend(_Subscriber(where, name, wait_status) for _ in range(n))
        for sub in subs:
            sub.wait_ready()
        yield subs
    finally:
        for sub in subs:
            if sub.proc.poll() is None:
                sub.proc.kill()
                sub.proc.wait()


def _match(
    raised: dict[int, list[int]], received: list[tuple[int, int]]
) -> tuple[list[float], int]:
    """Latencies (us) of (receive ns, acq) against the latest raise announcing acq before it."""
    samples: list[float] = []
    unmatched = 0
    for t_ret, acq in received:
        times = raised.get(acq, [])
        i = bisect.bisect_right(times, t_ret) - 1
        if i < 0 or t_ret - times[i] > MATCH_WINDOW_NS:
            unmatched += 1
            continue
        samples.append((t_ret - times[i]) / 1000.0)
    return samples, unmatched


def _latency_phase(
    ctx: BenchContext, n_subs: int, seconds: float, samples: int = 64
) -> tuple[list[list[float]], list[float], dict[str, float]]:
    from biris_hw.io.net import serve

    period_us = acquisition_period_s(samples) * 1e6
    where = f"tcp/127.0.0.1:{_port()}"
    with (
        running_server(samples=samples, time_scale=TIME_SCALE) as bench,
        IrqRecorder(bench.rig) as irq,
        serve(bench.server, name="bench", listen=[where], controllers={}, multicast=False),
        _subscribers(where, "bench", n_subs) as subs,
    ):
        ready_s = (max(sub.ready_ns for sub in subs) - min(sub.started_ns for sub in subs)) / 1e9
        local: list[tuple[int, int]] = []
        stop = threading.Event()
        data = bench.server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)

        def read_local() -> None:
            while not stop.is_set():
                try:
                    point = data.ready_for_data(timeout=0.5)
                except TimeoutError:
                    continue
                except ConnectionClosed:
                    return
                local.append((time.perf_counter_ns(), point.acq))

        reader = threading.Thread(target=read_local)
        reader.start()
        conn = bench.server.open()
        irq.clear()
        started = time.perf_counter_ns()
        conn.continuous_scan(-45.0, 45.0)
        stop.wait(seconds)
        conn.stop_scan()
        conn.wait_idle(timeout=60)
        stop.set()
        reader.join()
        data.close()
        conn.close()
        raised = irq.announcing()
        results = [sub.finish() for sub in subs]
    remote = []
    dropped = unmatched = 0
    for result in results:
        got, missing = _match(raised, [(t, acq) for t, acq in result["received"]])
        remote.append(got)
        unmatched += missing
        dropped += int(result["dropped"])
    local_us, _ = _match(raised, local)
    sub_cpu = sum(float(result["cpu_s"]) for result in results)
    extra = {
        "dropped": float(dropped),
        "unmatched": float(unmatched),
        "period_us": period_us,
        "subscribers_ready_s": ready_s,
        "subscribers_cpu_percent": 100.0 * sub_cpu / ((time.perf_counter_ns() - started) / 1e9),
    }
    slow = sum(1 for got in remote for v in got if v > period_us)
    ctx.log(
        f"bench: net latency with {n_subs} subscriber(s): {sum(map(len, remote))} samples, "
        f"{slow} over one period; subscribers ready {ready_s:.1f} s after their start"
    )
    return remote, local_us, extra


@benchmark("net")
def net(ctx: BenchContext) -> list[Figure]:
    """Zenoh service: interrupt -> remote subscriber latency, throughput ceiling, fan-out."""
    seconds = float(ctx.pick(full=20, quick=5))
    figures: list[Figure] = []
    remote, local_us, extra = _latency_phase(ctx, 1, seconds)
    period_us = extra["period_us"]
    r, loc = summarise(remote[0]), summarise(local_us)
    values = {**r, "local_p50": loc["p50"], "local_p99": loc["p99"], **extra}
    values["p50_ratio"] = r["p50"] / loc["p50"] if loc["p50"] else float("nan")
    values["p99_over_period"] = r["p99"] / period_us
    figures.append(
        Figure(
            "net.every_acquisition_remote",
            values,
            "us",
            f"time_scale {TIME_SCALE:g}, 64 samples, continuous +-45 deg sweeps for {seconds:g} s. "
            "Latency = perf_counter_ns when a subscriber in another process (Zenoh peer on "
            "loopback TCP) receives the service's Point publication, minus perf_counter_ns taken "
            "by the simulator as it raised the data interrupt announcing that acquisition; "
            "local_* = the same for an EVERY_ACQUISITION DATA connection in the server's "
            "process during the same sweeps. p50_ratio = remote p50 / local p50.",
            Target("<=", 1.0, on="p99_over_period"),
        )
    )
    figures.append(_throughput(ctx))
    remote, local_us, extra = _latency_phase(ctx, SUBSCRIBERS, seconds)
    every = [v for subscriber in remote for v in subscriber]
    worst_p99 = max(summarise(s)["p99"] for s in remote if s)
    loc = summarise(local_us)
    values = {**summarise(every), "worst_subscriber_p99": worst_p99, **extra}
    values.update(local_p50=loc["p50"], local_p99=loc["p99"])
    values["p99_over_period"] = values["p99"] / extra["period_us"]
    figures.append(
        Figure(
            "net.fanout_10_remote",
            values,
            "us",
            f"As every_acquisition_remote, with {SUBSCRIBERS} subscriber processes at once; "
            "p50/p99 over all their receptions, worst_subscriber_p99 the slowest one's; local_* "
            "the in-process EVERY_ACQUISITION connection during the same sweeps.",
            Target("<=", 1.0, on="p99_over_period"),
        )
    )
    figures.append(_flood_fairness(ctx))
    return figures


class _NoScans:
    """The stand-in's scan connection: nothing ever comes."""

    dropped = 0

    def __init__(self) -> None:
        self._closed = threading.Event()

    def ready_for_data(self, timeout: float | None = None) -> Point:
        if self._closed.wait(timeout if timeout is not None else 3600.0):
            raise ConnectionClosed("closed")
        raise TimeoutError

    def close(self) -> None:
        self._closed.set()


class _Firehose:
    """A stand-in sensor whose every-acquisition feed hands out ``rate`` Points per second."""

    def __init__(self, samples: int) -> None:
        profile = np.arange(samples, dtype=np.int16)
        self.profile = profile
        self.rate = 0.0
        self.acq = 0
        self.next_t = time.perf_counter()
        self.lock = threading.Lock()

    def open(self, kind: ConnectionKind = ConnectionKind.NORMAL, **options: Any) -> Any:
        if kind is ConnectionKind.DATA and options.get("policy") is DeliveryPolicy.EVERY_BUFFER:
            return _NoScans()  # the service's feed reads scans too: none come
        if options.get("policy") is not DeliveryPolicy.EVERY_ACQUISITION:
            raise ConnectionClosed("only the point feed")
        return self

    playback = False
    paced = True
    record = None
    dropped = 0  # as a DATA connection: the stand-in hands out every point it makes

    def clock(self) -> float:
        return float(self.acq)

    def status(self, *, newer_than: int | None = None, timeout: float | None = None) -> Any:
        raise ConnectionClosed("no status")

    def close(self) -> None:
        pass

    def ready_for_data(self, timeout: float | None = None) -> Point:
        with self.lock:
            rate = self.rate
            if rate <= 0:
                threading.Event().wait(min(timeout or 0.01, 0.01))  # as a real feed would wait
                raise TimeoutError
            now = time.perf_counter()
            if timeout is not None and self.next_t - now > timeout:
                # not due within the wait asked for (a reader's poll): as a real feed says
                threading.Event().wait(timeout)
                raise TimeoutError
            if now < self.next_t:
                time.sleep(self.next_t - now)  # pacing the offered rate, not synchronising
            self.next_t = max(self.next_t, now - 0.01) + 1.0 / rate
            self.acq += 1
            return Point(0, 1000, self.profile, self.profile, float(self.acq), self.acq, 0)


def _throughput(ctx: BenchContext) -> Figure:
    from biris_hw.io.net import serve

    samples = 128
    sensor_rate = 1.0 / acquisition_period_s(samples)
    hose = _Firehose(samples)
    where = f"tcp/127.0.0.1:{_port()}"
    step_s = ctx.pick(full=2, quick=1)
    steps: dict[str, float] = {}
    ceiling = 0.0
    # the stand-in has the point feed only: not a whole Sensor, and the service needs no more
    with serve(cast("Sensor", hose), name="hose", listen=[where], multicast=False):
        for rate in RATES:
            # the stand-in publishes no status: ready = subscribed, and the points before the
            # first one received are left out below
            with _subscribers(where, "hose", 1, wait_status=False) as (sub,):
                first = hose.acq
                hose.rate = float(rate)
                started = time.perf_counter()
                threading.Event().wait(step_s)
                hose.rate = 0.0
                with hose.lock:
                    last = hose.acq
                elapsed = time.perf_counter() - started
                # the subscriber has everything once the last point reached it (or never will)
                threading.Event().wait(0.5)
                result = sub.finish()
            # from the first point the subscriber got: its subscription takes a moment to reach
            # the service, and what was published before that was not lost, just not for it
            start = min((acq for _, acq in result["received"] if acq > first), default=last + 1)
            got = {acq for _, acq in result["received"] if start <= acq <= last}
            offered = max(0, last - start + 1)
            lost = offered - len(got)
            achieved = (last - first) / elapsed
            steps[f"lost_at_{rate}"] = float(lost)
            ctx.log(f"bench: net throughput {rate}/s offered, {achieved:.0f}/s made, {lost} lost")
            if lost == 0:
                ceiling = max(ceiling, achieved)
            else:
                break
    values = {
        "ceiling_per_s": ceiling,
        "sensor_per_s": sensor_rate,
        "ratio": ceiling / sensor_rate,
        **steps,
    }
    return Figure(
        "net.throughput_128",
        values,
        "points/s",
        f"Points of 128 samples published by the service as fast as a stand-in sensor hands "
        f"them out (offered rates {', '.join(map(str, RATES))}/s for {step_s} s each), received "
        "by a subscriber in another process over loopback TCP; ceiling = the highest achieved rate "
        "with zero points lost; ratio = ceiling / the sensor's rate at 128 samples.",
        Target(">=", 10.0, on="ratio"),
    )


FLOOD_NAME = "flood"
FLOOD_SWEEP_DEG = 45.0
PROBE_PERIOD_S = 0.02
"""How often the measuring client asks for the status (50 round trips a second)."""
FLOOD_WINDOW = 1000
"""Requests the flooder keeps outstanding: as fast as its Zenoh session sends them."""


class _Helper:
    """A helper process of this module (``python -m benchmarks.net ROLE ...``): its first line
    says it is ready, its last one (after its stdin closes, or when it is done) is JSON."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "benchmarks.net", *args],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def line(self) -> str:
        assert self.proc.stdout is not None
        return self.proc.stdout.readline().strip()

    def finish(self, timeout: float = 120.0) -> dict[str, Any]:
        out, _ = self.proc.communicate(timeout=timeout)
        result: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
        return result

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def _flood_fairness(ctx: BenchContext) -> Figure:
    """A prober process asks for the status every :data:`PROBE_PERIOD_S`; for ``seconds``
    nobody else asks anything (quiet), then a flooder process floods ``status`` under one
    client id for ``seconds`` (flood). Both windows are cut from the prober's one series by the
    flooder's own start and end stamps (``perf_counter_ns``: one clock for the host)."""
    from biris_hw.io.net import serve

    seconds = float(ctx.pick(full=10, quick=3))
    where = f"tcp/127.0.0.1:{_port()}"
    prober = flooder = None
    with (
        running_server(samples=64, time_scale=TIME_SCALE) as bench,
        serve(bench.server, name=FLOOD_NAME, listen=[where], multicast=False) as service,
    ):
        conn = bench.server.open()
        conn.continuous_scan(-FLOOD_SWEEP_DEG, FLOOD_SWEEP_DEG)
        try:
            prober = _Helper("probe", where, FLOOD_NAME)
            if prober.line() != "ready":
                raise RuntimeError("the prober did not start")
            threading.Event().wait(seconds)  # the quiet window
            busy_before = service.refused_busy
            flooder = _Helper("flood", where, FLOOD_NAME, str(seconds))
            started = flooder.line()
            if not started.startswith("flooding"):
                raise RuntimeError(f"the flooder did not start: {started!r}")
            flood = flooder.finish(timeout=seconds + 120.0)
            refused = service.refused_busy - busy_before
            threading.Event().wait(1.0)  # the prober's last round trips after the flood
            probe = prober.finish()  # closes its stdin: it stops and reports
        finally:
            for helper in (prober, flooder):
                if helper is not None:
                    helper.kill()
            conn.stop_scan()
            conn.close()
    t0, t1 = int(flood["started_ns"]), int(flood["ended_ns"])
    quiet = [ms for t, ms in probe["rtt"] if t < t0]
    flooded = [ms for t, ms in probe["rtt"] if t0 <= t < t1]
    q, f = summarise(quiet), summarise(flooded)
    values: dict[str, float] = {
        **f,
        "quiet_p50": q["p50"],
        "quiet_p99": q["p99"],
        "ratio_p50": f["p50"] / q["p50"] if q["p50"] else float("nan"),
        "ratio_p99": f["p99"] / q["p99"] if q["p99"] else float("nan"),
        "quiet_n": float(len(quiet)),
        "flood_n": float(len(flooded)),
        "probe_errors": float(probe["errors"]),
        "flood_sent_per_s": flood["sent"] / max(1e-9, (t1 - t0) / 1e9),
        "flood_ok": float(flood["replies"].get("ok", 0)),
        "flood_busy": float(flood["replies"].get("Busy", 0)),
        "flood_unanswered": float(flood["unanswered"]),
        "service_refused_busy": float(refused),
    }
    ctx.log(
        f"bench: net flood fairness: status p50 {q['p50']:.2f} ms quiet, {f['p50']:.2f} ms "
        f"flooded ({values['flood_sent_per_s']:.0f} requests/s, {refused} Busy)"
    )
    return Figure(
        "net.flood_fairness",
        values,
        "ms",
        f"The service on the simulator (time_scale {TIME_SCALE:g}, 64 samples, continuous "
        f"+-{FLOOD_SWEEP_DEG:g} deg sweeps) in this process; a client in another process asks "
        f"for the status every {PROBE_PERIOD_S * 1000:g} ms (RemoteSensor.status(), round trip "
        f"in ms) for {seconds:g} s alone (quiet_*), then for {seconds:g} s while a third "
        f"process floods status queries under one client id, {FLOOD_WINDOW} outstanding at once "
        "(raw Zenoh, as fast as its session sends: flood_sent_per_s); p50/p99 are the "
        "client's round trips during the flood, ratio_* flooded / quiet. All on loopback TCP "
        "and one host, so the flooder's own CPU is part of the cost.",
        Target("<=", 2.0, on="ratio_p50"),
    )


def _probe(where: str, name: str) -> None:
    """The measuring client: a status round trip every :data:`PROBE_PERIOD_S` until stdin
    closes; prints ``ready``, then one JSON line of (start ns, round trip ms) and errors."""
    from biris_hw.io.net import connect

    rtt: list[tuple[int, float]] = []
    errors = 0
    stop = threading.Event()

    def watch_stdin() -> None:
        sys.stdin.read()
        stop.set()

    with connect(name, [where], multicast=False) as remote:
        remote.status()
        print("ready", flush=True)
        threading.Thread(target=watch_stdin, daemon=True).start()
        while not stop.is_set():
            start = time.perf_counter_ns()
            try:
                remote.status()
            except Exception:  # a refusal or a timeout is what the figure counts
                errors += 1
            else:
                rtt.append((start, (time.perf_counter_ns() - start) / 1e6))
            stop.wait(PROBE_PERIOD_S)
    print(json.dumps({"rtt": rtt, "errors": errors}), flush=True)


def _flood(where: str, name: str, seconds: float) -> None:
    """The flooding peer: raw Zenoh status queries under one client id, :data:`FLOOD_WINDOW`
    outstanding, for ``seconds``; prints ``flooding`` once its session sees the service, then
    one JSON line: sent, replies by kind, unanswered, and its start and end stamps."""
    import uuid

    import zenoh

    from biris_hw.io.net.keys import Keys
    from biris_hw.io.net.zconfig import make_config

    keys = Keys(name)
    session = zenoh.open(make_config(connect=[where]))
    try:
        deadline = time.monotonic() + 30.0
        while not list(session.liveliness().get(keys.service_token, timeout=1.0)):
            if time.monotonic() > deadline:
                raise SystemExit("no service")
        payload = json.dumps({"client": uuid.uuid4().hex}).encode()
        replies: dict[str, int] = {}
        unanswered = 0
        pending: list[Any] = []

        def drain(handlers: list[Any]) -> None:
            nonlocal unanswered
            for handler in handlers:
                got = list(handler)
                if not got:
                    unanswered += 1
                for reply in got:
                    if reply.ok is not None:
                        kind = "ok"
                    else:
                        try:
                            kind = str(json.loads(reply.err.payload.to_bytes())["error"])
                        except (ValueError, KeyError, TypeError):
                            kind = "zenoh"  # Zenoh's own reply (its timeout), not the service's

                    replies[kind] = replies.get(kind, 0) + 1

        print("flooding", flush=True)
        started = time.perf_counter_ns()
        end = started + int(seconds * 1e9)
        sent = 0
        while time.perf_counter_ns() < end:
            pending.append(session.get(keys.rpc("status"), payload=payload, timeout=10.0))
            sent += 1
            if len(pending) >= 2 * FLOOD_WINDOW:
                drain(pending[:FLOOD_WINDOW])
                del pending[:FLOOD_WINDOW]
        ended = time.perf_counter_ns()
        drain(pending)
    finally:
        session.close()  # type: ignore[no-untyped-call]
    print(
        json.dumps(
            {
                "sent": sent,
                "replies": replies,
                "unanswered": unanswered,
                "started_ns": started,
                "ended_ns": ended,
            }
        ),
        flush=True,
    )


# -- the subscriber process ----------------------------------------------------------------------


def _sub(where: str, name: str, wait_status: bool) -> None:
    from biris_hw.io.net import connect

    received: list[tuple[int, int]] = []
    status = threading.Event()
    with connect(name, [where], multicast=False) as remote:
        sub = remote.subscribe("point", lambda p: received.append((time.perf_counter_ns(), p.acq)))
        if wait_status:
            with remote.subscribe("status", lambda _s: status.set()):
                if not status.wait(30):
                    raise SystemExit("no status publication within 30 s")
        print("ready", flush=True)
        cpu0 = time.process_time()
        sys.stdin.read()
        cpu = time.process_time() - cpu0
        sub.close()
        print(json.dumps({"received": received, "dropped": sub.dropped, "cpu_s": cpu}), flush=True)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    if sys.argv[1:2] == ["sub"]:
        _sub(sys.argv[2], sys.argv[3], sys.argv[4:5] == ["status"])
    elif sys.argv[1:2] == ["probe"]:
        _probe(sys.argv[2], sys.argv[3])
    elif sys.argv[1:2] == ["flood"]:
        _flood(sys.argv[2], sys.argv[3], float(sys.argv[4]))
