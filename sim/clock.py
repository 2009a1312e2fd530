"""``SimClock``: hardware time for the simulator, running ``time_scale`` times faster than real.

Every delay in the simulator is expressed in hardware seconds and converted here, so one knob
speeds a whole run up (tests use 5-50) without changing what the driver sees, except speed.

That holds only while the host keeps up. Every millisecond the host is late is ``time_scale``
milliseconds of hardware time: at x300 a thread scheduled 10 ms late sees its video field three
hardware seconds late, and the driver's hardware-time deadlines (a 1 s settling limit, a 4 s BIRIS
timeout) stop meaning what they mean on the robot. So the clock also measures how late the work
it schedules runs (:meth:`SimClock.lateness`), for a person to be told (:data:`LAG_WARNING_S`).
"""

from __future__ import annotations

import math
import threading
import time

__all__ = ["FIELD_PERIOD", "LAG_WARNING_S", "SimClock"]

FIELD_PERIOD = 1.0 / 59.94
"""One RS-170 video field, in hardware seconds."""

LAG_WARNING_S = 2.0 * FIELD_PERIOD
"""How late (hardware seconds, on average: :meth:`SimClock.lateness`) the simulator may run
before a person is told that the host cannot keep up with the time scale: one acquisition of
64 samples (two video fields). A host that keeps up is a few milliseconds late at x30 and well
under one at x4; at x100 a busy 2-core host is already about 40 ms late, with single wakes
seconds late, and the driver starts to see heads that "had not come to rest" in time."""

_LATENESS_WINDOW_REAL_S = 0.5
"""Real seconds over which :meth:`SimClock.lateness` averages: long enough that one thread
descheduled once is not "behind", short enough that a run that falls behind is seen within a
second."""


class SimClock:
    """Hardware seconds since the clock was made: ``(monotonic - t0) * time_scale``."""

    def __init__(self, time_scale: float = 1.0) -> None:
        if not time_scale > 0.0:
            raise ValueError(f"time_scale must be positive, not {time_scale}")
        self._scale = float(time_scale)
        self._t0 = time.monotonic()
        self._lateness = 0.0
        self._lateness_at = self._t0

    @property
    def time_scale(self) -> float:
        return self._scale

    @property
    def t0(self) -> float:
        """``time.monotonic()`` when hardware time was 0.

        CLOCK_MONOTONIC is system-wide on Linux, so a driver in another process that knows
        ``t0`` and the scale computes the very same hardware time (``sim.process`` sends both).
        """
        return self._t0

    def now(self) -> float:
        """Hardware time in seconds."""
        return (time.monotonic() - self._t0) * self._scale

    __call__ = now

    def to_real(self, hw_seconds: float) -> float:
        """Real seconds that ``hw_seconds`` of hardware time take."""
        return hw_seconds / self._scale

    def wait_until(self, t_hw: float, stop: threading.Event) -> bool:
        """Block until hardware time ``t_hw``; False at once if ``stop`` is set meanwhile."""
        while True:
            remaining = t_hw - self.now()
            if remaining <= 0.0:
                self._note_lateness(-remaining)
                return not stop.is_set()
            if stop.wait(remaining / self._scale):
                return False

    def _note_lateness(self, late_hw: float) -> None:
        """Fold one wake's lateness into the running average, weighted by the real time since
        the previous wake (so a wake after a long stall counts for the stall's length).

        Written by the one thread that waits (the BIRIS supervisor's), read by any: two float
        stores, each atomic, and a reader that sees the older of the pair is off by one wake.
        """
        at = time.monotonic()
        weight = 1.0 - math.exp(-(at - self._lateness_at) / _LATENESS_WINDOW_REAL_S)
        self._lateness += weight * (late_hw - self._lateness)
        self._lateness_at = at

    def lateness(self) -> float:
        """How late, in hardware seconds, the work waiting on this clock has been running:
        an average of each :meth:`wait_until`'s overshoot over about half a second of real time.

        Near 0 while the host keeps up (a wake is late by the host's scheduling latency times
        the scale); it grows when the host cannot do a hardware second's work in
        ``1 / time_scale`` real seconds. Read-only: measuring changes nothing in the simulation.
        """
        return self._lateness
