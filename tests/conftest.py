"""Shared fixtures: a simulated target, a server on it, and leak and audit checks."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator

import pytest

from biris_hw import BirisInitRecord
from biris_hw.server import BirisServer
from sim.rig import SimulatedBiris
from sim.scene import Scene


def affinity_allowed() -> bool:
    """Whether a thread may choose its CPUs here (Linux, and not forbidden by a sandbox): setting
    the affinity it already has is the harmless probe."""
    from biris_hw.affinity import pin_current_thread
    from biris_hw.errors import RequestError

    if not hasattr(os, "sched_getaffinity"):
        return False
    try:
        pin_current_thread(os.sched_getaffinity(0))
    except RequestError:
        return False
    return True


def _fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


def _threads() -> set[threading.Thread]:
    return set(threading.enumerate())


@pytest.fixture
def no_leaks() -> Iterator[None]:
    """Fail the test if it leaves a thread or a file descriptor behind."""
    threads, fds = _threads(), _fds()
    yield
    left = [t for t in _threads() - threads if t.is_alive()]
    assert not left, f"threads left running: {left}"
    assert _fds() - fds == set(), "file descriptors left open"


RigFactory = Callable[..., SimulatedBiris]


@pytest.fixture(params=[10.0, 30.0], ids=["x10", "x30"])
def time_scale(request: pytest.FixtureRequest) -> float:
    """End-to-end tests run at two time scales: timing bugs show at one or the other."""
    return float(request.param)


@pytest.fixture
def make_rig(no_leaks: None, time_scale: float) -> Iterator[RigFactory]:
    """Build rigs that are closed after the test, with the audit checked to be clean."""
    rigs: list[SimulatedBiris] = []

    def make(**options: object) -> SimulatedBiris:
        options.setdefault("scene", Scene.circle(2.0))
        options.setdefault("time_scale", time_scale)
        options.setdefault("seed", 7)
        rig = SimulatedBiris(**options)  # type: ignore[arg-type]
        rigs.append(rig)
        return rig.start()

    yield make
    for rig in rigs:
        rig.close()
    for rig in rigs:
        assert rig.audit.violations == [], "\n".join(map(str, rig.audit.violations))


@pytest.fixture
def rig(make_rig: RigFactory) -> SimulatedBiris:
    return make_rig()


@pytest.fixture
def server(rig: SimulatedBiris) -> Iterator[BirisServer]:
    with BirisServer(rig.hardware, BirisInitRecord()) as srv:
        yield srv
