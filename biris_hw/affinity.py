"""Keeping threads on chosen CPUs (Linux), for the lowest and steadiest latency.

Every acquisition crosses threads: the level-2 demultiplexer (which drains it, as
biris_data_notifier), the administrator, then the client's own thread. Each hand-over is a
wake-up; when the two threads sit on different CPUs it costs an inter-processor interrupt and a
cold cache, about 30 us on a small virtual machine against under 2 us on one CPU, and that is
most of what the server adds to an acquisition's latency there. So a user who wants the latency
down can keep the server's threads on one CPU (``BirisInitRecord(cpus=(n,))``) and call
:func:`pin_current_thread` with the same set in the thread that reads the data. On a real target
the interrupt should be steered to that CPU too, and other work kept off it. With the in-process
simulator, create it inside :func:`pinned` as well: its raise is the interrupt, and the
interpreter lock serialises its work with the server's whatever the CPUs, so one CPU costs no
parallelism there (measured: ``make bench``'s ``latency_us.*_pinned`` figures).

Affinity is per thread on Linux and inherited at creation: the server pins the thread that
creates its tasks while it creates them, so every task starts where it should and nothing else in
the caller's process is touched.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager

from biris_hw.errors import RequestError

__all__ = ["available_cpus", "check_cpus", "pin_current_thread", "pinned"]


def _calls() -> tuple[Callable[[int], set[int]], Callable[[int, Collection[int]], None]]:
    get = getattr(os, "sched_getaffinity", None)
    put = getattr(os, "sched_setaffinity", None)
    if get is None or put is None:
        raise RequestError("cpus: CPU affinity is not supported on this platform")
    return get, put


def available_cpus() -> frozenset[int]:
    """The CPUs this thread may run on (what the process was started with, or narrowed to)."""
    get, _ = _calls()
    return frozenset(get(0))


def check_cpus(cpus: Collection[int]) -> frozenset[int]:
    """``cpus`` as a set, if every one is available here; a RequestError naming the rest if not."""
    wanted = frozenset(cpus)
    if not wanted:
        raise RequestError("cpus: names no CPU")
    missing = wanted - available_cpus()
    if missing:
        raise RequestError(
            f"cpus: {sorted(missing)} not available to this process "
            f"(it may use {sorted(available_cpus())})"
        )
    return wanted


def pin_current_thread(cpus: Collection[int]) -> frozenset[int]:
    """Keep the calling thread on ``cpus`` from now on; returns where it could run before."""
    wanted = check_cpus(cpus)
    get, put = _calls()
    before = frozenset(get(0))
    try:
        put(0, wanted)
    except OSError as exc:  # a sandbox may forbid it even where the CPUs exist
        raise RequestError(f"cpus: cannot keep this thread on {sorted(wanted)}: {exc}") from None
    return before


@contextmanager
def pinned(cpus: Collection[int]) -> Iterator[None]:
    """The calling thread on ``cpus`` for the block (threads it starts inherit it), then back."""
    before = pin_current_thread(cpus)
    try:
        yield
    finally:
        _, put = _calls()
        put(0, before)
