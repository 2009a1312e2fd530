"""Idle: what a sensor that does nothing costs while it is served and recorded.

A sensor served on Zenoh (:func:`biris_hw.io.net.serve`) and recorded (:class:`Recorder`) while
nobody moves it should cost next to nothing: the status reaches them when it changes (a parked
STATUS request answered on change, the way READY_FOR_DATA is parked until there are data), and
the encoders are read only as fast as the status needs them. Before issue 23 the service polled
the status 20 times a second (each ``status()`` read both encoders in the caller's thread) and
the recorder polled its two DATA connections every 50 ms: about 68 round trips to the
administrator and 41 encoder reads a second, for a sensor at rest.

Counted from outside the code under test, so the same module runs on an older checkout for a
before/after figure: every message posted to the administrator's inbox (``Mailbox._post``, the
one door every ``send``, ``post`` and ``post_oneway`` goes through) by its type, and every read
of the hardware bundle's bus windows (``read``, ``read8``, ``read16``, ``read32``,
``read_many``; a call made inside another one, ``read_many`` reading span by span, counts once)
by window. The server runs on the simulator at time scale 1 (real time: Zenoh's threads cannot
run on virtual time), 64 samples, the service with no controllers, the recorder with its
defaults; counting starts :data:`SETTLE_S` after both have started and lasts the measured
interval.
"""

from __future__ import annotations

import collections
import contextlib
import importlib
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from benchmarks.common import running_server
from benchmarks.harness import BenchContext, BenchSkipped, Figure, Target, benchmark

__all__ = ["SETTLE_S", "Tally", "count_posts", "count_reads", "idle"]

SETTLE_S = 1.0
"""Real seconds between starting the service and the recorder and starting to count: their
connections opened, their first statuses and feeds' first polls made."""

WINDOWS = ("biris", "motion", "coupler")
"""The hardware bundle's bus windows: BIRIS memory, the Model 7600 (the encoders), the coupler."""

_READS = ("read", "read8", "read16", "read32", "read_many")


class Tally:
    """Calls counted by name, from any thread; a call made inside a counted call of the same
    tally (in the same thread) is not counted again."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: collections.Counter[str] = collections.Counter()
        self._inside = threading.local()

    def wrap(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn``, counting each outermost call under ``name``."""

        def counted(*args: Any, **kwargs: Any) -> Any:
            inside = getattr(self._inside, "depth", 0)
            if inside == 0:
                with self._lock:
                    self._counts[name] += 1
            self._inside.depth = inside + 1
            try:
                return fn(*args, **kwargs)
            finally:
                self._inside.depth = inside

        return counted

    def add(self, name: str) -> None:
        with self._lock:
            self._counts[name] += 1

    def snapshot(self) -> collections.Counter[str]:
        with self._lock:
            return collections.Counter(self._counts)


def count_posts(inbox: Any, tally: Tally) -> None:
    """Count every message posted to ``inbox`` (a :class:`biris_hw.ipc.Mailbox`) by its type:
    ``send``, ``post`` and ``post_oneway`` all go through ``_post``."""
    original = inbox._post

    def post(message: object, *args: Any, **kwargs: Any) -> Any:
        tally.add(type(message).__name__)
        return original(message, *args, **kwargs)

    inbox._post = post


def count_reads(hardware: Any, tally: Tally) -> None:
    """Count every read of ``hardware``'s bus windows, by window (see the module)."""
    for name in WINDOWS:
        window = getattr(hardware, name, None)
        if window is None:
            continue
        for method in _READS:
            fn = getattr(window, method, None)
            if fn is not None:
                setattr(window, method, tally.wrap(name, fn))


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _found(name: str, *modules: str) -> Any:
    """``name`` from the first of ``modules`` this checkout has (the outside world moved to
    biris_hw.io in issue 23; an older checkout has it at biris_hw.net and biris_hw.record)."""
    for module in modules:
        try:
            return getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError):
            continue
    raise BenchSkipped(f"{name} cannot run here (none of {', '.join(modules)} has it)")


@contextlib.contextmanager
def _served_and_recorded(ctx: BenchContext) -> Iterator[tuple[Tally, Tally]]:
    serve = _found("serve", "biris_hw.io.net", "biris_hw.net")
    recorder = _found("Recorder", "biris_hw.io.record", "biris_hw.record")
    with running_server(samples=64, time_scale=1.0) as bench:
        posts, reads = Tally(), Tally()
        count_posts(bench.server.inbox, posts)
        count_reads(bench.rig.hardware, reads)
        where = f"tcp/127.0.0.1:{_free_port()}"
        with (
            serve(bench.server, name="idle", listen=[where], multicast=False),
            recorder(bench.server, ctx.work_dir / "idle.mcap"),
        ):
            yield posts, reads


@benchmark("idle")
def idle(ctx: BenchContext) -> list[Figure]:
    """Round trips to the administrator and bus reads a second, served and recorded, at rest."""
    seconds = float(ctx.pick(full=10, quick=3))
    with _served_and_recorded(ctx) as (posts, reads):
        threading.Event().wait(SETTLE_S)  # the measured interval starts after start-up
        posts0, reads0 = posts.snapshot(), reads.snapshot()
        begun = time.monotonic()
        threading.Event().wait(seconds)  # the interval measured: the sensor left alone
        elapsed = time.monotonic() - begun
        posted = posts.snapshot() - posts0
        read = reads.snapshot() - reads0
    method = (
        f"SimulatedBiris at time scale 1, 64 samples, BirisServer served on Zenoh (loopback, no "
        f"controllers) and recorded (Recorder, defaults) in one process, nobody moving it; "
        f"counted over {elapsed:.1f} real s starting {SETTLE_S:g} s after both started, from "
        "outside the code under test (module notes): "
    )
    n_posts = sum(posted.values())
    n_reads = sum(read.values())
    return [
        Figure(
            key="idle.admin_round_trips_per_s",
            values={
                "per_s": n_posts / elapsed,
                "posts": float(n_posts),
                **{f"by_{name}": float(count) for name, count in sorted(posted.items())},
            },
            unit="1/s",
            target=Target("<=", 5.0, on="per_s"),
            method=method
            + "messages posted to the administrator's inbox per second (by_<type>: how many "
            "of each). The issue's figure before: about 68 a second.",
        ),
        Figure(
            key="idle.bus_reads_per_s",
            values={
                "per_s": n_reads / elapsed,
                "reads": float(n_reads),
                **{f"by_{name}": float(read.get(name, 0)) for name in WINDOWS},
            },
            unit="1/s",
            target=Target("<=", 3.2, on="per_s"),
            method=method
            + "reads of the bus windows per second (by_<window>; an encoder read is one "
            "read_many on the motion window). Target: one reading of both encoders a second, "
            "what a status published and recorded once a second at rest needs, and the "
            "coupler's LOCAL_STATUS once a COUPLER_WATCH_S (0.9 s: a BIRIS crate that loses "
            "power is heard within 1 s, issue 26). The issue's figure before: about 41 encoder "
            "reads a second.",
        ),
    ]
