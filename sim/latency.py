"""``SlowReads``: the driver's bus reads take longer, as over a transport under load.

A host whose bus is busy (a VM-USB shared with other traffic, a VMEbus with a DMA running, an
interrupt storm on the CPU) sees every read come back late, while the hardware keeps its own
time. The fault panel plays that by making each read the *driver* makes through its windows
sleep for a while in the caller's thread before the access, so what it reads is the state at the
moment the read completes. The simulator's own accesses go through other window objects (the
supervisor's, the device models' backdoors, the far side of the VM-USB) and stay on time.

The windows' classes are untouched: the read methods are wrapped on the window *instances* while
the fault is on (an instance attribute shadows the class's method) and the wrappers removed when
it is cleared, so a window without the fault costs exactly what it cost before. One read the
driver asks for costs one delay, however the window does it inside (``read_many`` may call
``read``; the nested call is not delayed again). The delay is a sleep through the clock's time
base, in hardware seconds: a real sleep in scaled time, time the rig lets pass in virtual time.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable
from typing import Any

from biris_hw.bus.base import BusWindow
from sim.clock import SimClock

__all__ = ["READ_METHODS", "SlowReads"]

READ_METHODS = ("read", "read8", "read16", "read32", "read_many", "read_regs")
"""The public read paths a window may have (``read_regs``: VM-USB windows only). Each call is
one bus transaction, so one delay."""

_ABSENT = object()


class SlowReads:
    """Makes every read through ``windows()`` (evaluated when the fault is switched on) take
    ``delay_s`` hardware seconds longer; thread-safe."""

    def __init__(self, clock: SimClock, windows: Callable[[], Iterable[BusWindow]]) -> None:
        self._clock = clock
        self._windows = windows
        self._lock = threading.Lock()
        self._delay_s = 0.0
        self._made = 0
        self._installed: list[tuple[BusWindow, str, object]] = []
        """(window, method name, what the instance held under that name before: ``_ABSENT``
        or an earlier instance attribute), to put back exactly on clear."""
        self._nested = threading.local()

    @property
    def delay_s(self) -> float:
        """The delay added to each read, hardware seconds (0.0 while the fault is off)."""
        return self._delay_s

    @property
    def made(self) -> int:
        """Reads that were slowed since the rig was built."""
        with self._lock:
            return self._made

    def set(self, delay_s: float) -> None:
        """Slow every driver read by ``delay_s`` hardware seconds from now (0 clears)."""
        if not (math.isfinite(delay_s) and delay_s >= 0.0):
            raise ValueError(f"delay_s must be finite and not negative, not {delay_s}")
        if delay_s == 0.0:
            self.clear()
            return
        with self._lock:
            self._delay_s = delay_s
            if self._installed:
                return
            for window in self._windows():
                for name in READ_METHODS:
                    if not callable(getattr(type(window), name, None)):
                        continue
                    before = window.__dict__.get(name, _ABSENT)
                    setattr(window, name, self._slowed(getattr(window, name)))
                    self._installed.append((window, name, before))

    def clear(self) -> None:
        """Reads are as fast as the window makes them again; a read already asleep finishes."""
        with self._lock:
            self._delay_s = 0.0
            installed, self._installed = self._installed, []
        for window, name, before in reversed(installed):
            if before is _ABSENT:
                delattr(window, name)
            else:
                setattr(window, name, before)

    def _slowed(self, read: Callable[..., Any]) -> Callable[..., Any]:
        """``read`` behind the delay: the sleep comes first (the request waits in the loaded
        transport), then the access, so the value is the one of the moment it completes."""

        def slowed(*args: Any, **kwargs: Any) -> Any:
            nested = self._nested
            if getattr(nested, "active", False):  # inside a slowed read of this thread
                return read(*args, **kwargs)
            delay = self._delay_s
            nested.active = True
            try:
                if delay > 0.0:
                    with self._lock:
                        self._made += 1
                    self._clock.timebase.sleep(delay, what="slowed bus read")
                return read(*args, **kwargs)
            finally:
                nested.active = False

        return slowed
