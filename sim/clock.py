"""``SimClock``: hardware time for the simulator, running ``time_scale`` times faster than real.

Every delay in the simulator is expressed in hardware seconds and converted here, so one knob
speeds a whole run up (tests use 5-50) without changing what the driver sees, except speed.
"""

from __future__ import annotations

import threading
import time

__all__ = ["FIELD_PERIOD", "SimClock"]

FIELD_PERIOD = 1.0 / 59.94
"""One RS-170 video field, in hardware seconds."""


class SimClock:
    """Hardware seconds since the clock was made: ``(monotonic - t0) * time_scale``."""

    def __init__(self, time_scale: float = 1.0) -> None:
        if not time_scale > 0.0:
            raise ValueError(f"time_scale must be positive, not {time_scale}")
        self._scale = float(time_scale)
        self._t0 = time.monotonic()

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
                return not stop.is_set()
            if stop.wait(remaining / self._scale):
                return False
