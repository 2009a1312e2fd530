"""The supervisor's time: the video field grid, and events that fall between fields.

Everything BIRIS does is synchronised to vertical sync, except a command's completion, which
comes a seeded jitter after its field; both kinds of moment are kept here, in one order, so the
supervisor thread only ever asks "what is due by now?". A hang moves the whole schedule by whole
fields, so what was on the field grid stays on it.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass

from sim.clock import FIELD_PERIOD

__all__ = ["FieldSchedule"]


@dataclass(order=True)
class _Event:
    time: float
    order: int
    action: Callable[[float], None]


class FieldSchedule:
    """Fields counted from clock time 0, and events at clock times; not thread-safe."""

    def __init__(self) -> None:
        self._events: list[_Event] = []
        self._order = 0
        self.vsync = 0
        """The next field to process."""

    def at(self, time: float, action: Callable[[float], None]) -> None:
        """Run ``action(time)`` once the clock has passed ``time``."""
        self._order += 1
        heapq.heappush(self._events, _Event(time, self._order, action))

    @property
    def pending(self) -> bool:
        """An event (a command's completion) is still to come."""
        return bool(self._events)

    def next_wake(self) -> float:
        """Clock time of the next field or event, whichever comes first."""
        wake = self.vsync * FIELD_PERIOD
        if self._events and self._events[0].time < wake:
            wake = self._events[0].time
        return wake

    def idle_wake(self, fields: int) -> float:
        """Clock time of field ``vsync + fields - 1``: where a thread with nothing to do but
        look at COMMAND next looks, ``fields`` fields on (computed as :meth:`next_wake` computes
        a field's time, so :meth:`run_due` at that time runs that field too)."""
        return (self.vsync + fields - 1) * FIELD_PERIOD

    def resume(self, now: float) -> int:
        """Move everything still to come so that it resumes at the field after ``now``.

        Returns the shift in fields (0 when nothing was behind).
        """
        resume = math.floor(now / FIELD_PERIOD) + 1
        shift = max(0, resume - self.vsync)
        self.vsync += shift
        if shift:
            dt = shift * FIELD_PERIOD
            for event in self._events:
                event.time += dt
        return shift

    def run_due(self, now: float, on_vsync: Callable[[int], None]) -> None:
        """Run every event and field due by ``now``, in time order (events first at a tie)."""
        while True:
            t_vsync = self.vsync * FIELD_PERIOD
            if self._events and self._events[0].time <= t_vsync:
                if self._events[0].time > now:
                    return
                event = heapq.heappop(self._events)
                event.action(event.time)
            else:
                if t_vsync > now:
                    return
                on_vsync(self.vsync)
                self.vsync += 1
