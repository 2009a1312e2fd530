"""``SimClock``: hardware time for the simulator, on scaled real time or on virtual time.

Every delay in the simulator is expressed in hardware seconds, and every thread of the simulator
waits through the clock's :class:`~biris_hw.timebase.TimeBase` (:attr:`SimClock.timebase`), so
the same models run on either kind of time:

* :class:`~biris_hw.timebase.ScaledTime` (the default): hardware time runs ``time_scale`` times
  faster than real time, and one knob speeds a whole run up (tests use 5-50) without changing
  what the driver sees, except speed. That holds only while the host keeps up. Every
  millisecond the host is late is ``time_scale`` milliseconds of hardware time: at x300 a thread
  scheduled 10 ms late sees its video field three hardware seconds late, and the driver's
  hardware-time deadlines (a 1 s settling limit, a 4 s BIRIS timeout) stop meaning what they
  mean on the robot. So the clock also measures how late the work it schedules runs
  (:meth:`SimClock.lateness`), for a person to be told (:data:`LAG_WARNING_S`).
* :class:`~biris_hw.timebase.VirtualTime`: hardware time moves only when every thread of the rig
  waits, straight to the next thing due. Nothing is ever late (:meth:`SimClock.lateness` is
  always 0.0) and a run gives the same result each time, however busy the host.
"""

from __future__ import annotations

import math
import threading
import time

from biris_hw.timebase import HwEvent, ScaledTime, TimeBase

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
    """Hardware seconds, read from (and waited on through) one :class:`TimeBase`.

    ``time_scale`` is the rig's scale: hardware seconds per real second in scaled time, the
    *nominal* scale in virtual time (the scale the run stands for; the time base's
    ``nominal_scale`` reads callers' timeouts at it). ``timebase`` defaults to a new
    :class:`ScaledTime` at ``time_scale``, starting now; a :class:`ScaledTime` passed in must run
    at ``time_scale``, so that the clock and its time base never disagree about real time.
    """

    def __init__(self, time_scale: float = 1.0, *, timebase: TimeBase | None = None) -> None:
        if not time_scale > 0.0:
            raise ValueError(f"time_scale must be positive, not {time_scale}")
        self._scale = float(time_scale)
        if timebase is None:
            timebase = ScaledTime(self._scale)
        elif isinstance(timebase, ScaledTime) and timebase.time_scale != self._scale:
            raise ValueError(
                f"a ScaledTime at x{timebase.time_scale:g} cannot run a clock at x{self._scale:g}"
            )
        self._timebase = timebase
        self._virtual = timebase.virtual
        if type(self).now is SimClock.now:
            self.now = timebase.now  # type: ignore[method-assign]  # see now()
        self._lateness = 0.0
        self._lateness_at = time.monotonic()

    def now(self) -> float:
        """Hardware time in seconds: the time base's.

        Each clock replaces this method by the time base's own bound ``now`` (unless a subclass
        overrides it): cheaper per call, and ``clock.now`` handed to a component as its hardware
        clock is recognised by :func:`~biris_hw.timebase.timebase_of` as this time base, so the
        component's waits go through it too (in virtual time a wait through any other would
        never end).
        """
        return self._timebase.now()

    def __call__(self) -> float:
        """``now()``: the clock is a ``Callable[[], float]`` for whoever wants one."""
        return self.now()

    @property
    def timebase(self) -> TimeBase:
        """The time base every simulator thread and wait goes through (threads made with its
        ``Thread``, events and conditions with its ``Event`` and ``Condition``)."""
        return self._timebase

    @property
    def virtual(self) -> bool:
        """True on virtual time: no real duration means anything, nothing is ever late."""
        return self._virtual

    @property
    def time_scale(self) -> float:
        """The scale the clock was made with (the nominal one in virtual time)."""
        return self._scale

    @property
    def t0(self) -> float:
        """``time.monotonic()`` when hardware time was 0 (scaled time only).

        CLOCK_MONOTONIC is system-wide on Linux, so a driver in another process that knows
        ``t0`` and the scale computes the very same hardware time (``sim.process`` sends both).
        Virtual time lives in this process's memory and no other process can follow it:
        RuntimeError there (as for any time base that is not a :class:`ScaledTime`), rather
        than a number that would put the other process's clock anywhere.
        """
        timebase = self._timebase
        if not isinstance(timebase, ScaledTime):
            raise RuntimeError(f"{timebase!r} has no real-time origin to share with a process")
        return timebase.t0

    def to_real(self, hw_seconds: float) -> float:
        """Real seconds that ``hw_seconds`` of hardware time take (scaled time only).

        RuntimeError in virtual time, where hardware time does not pass with real time: a real
        wait computed from it would decide the simulation by the host's speed. Wait through
        :attr:`timebase` instead, in hardware seconds.
        """
        if self._virtual:
            raise RuntimeError("virtual time has no real duration: wait through clock.timebase")
        return hw_seconds / self._scale

    def timeout_until(self, t_hw: float, now: float | None = None) -> float:
        """The hardware timeout, from ``now`` (default: the present), of a wait through the time
        base that must not end before ``t_hw``; 0.0 once ``t_hw`` has passed.

        ``t_hw - now`` itself may fall short: a wait's deadline is ``now + timeout``, and in
        floating point ``now + (t_hw - now)`` can round to just below ``t_hw`` (``t_hw`` over
        twice ``now``). In virtual time the waiter would wake a hair early, still before
        ``t_hw``, and wait again for a timeout too small to move time: for ever. So the timeout
        is nudged up, an ulp at a time, until the deadline is ``t_hw`` or just after.
        """
        if now is None:
            now = self.now()
        timeout = t_hw - now
        if timeout <= 0.0:
            return 0.0
        while now + timeout < t_hw:
            timeout = math.nextafter(timeout, math.inf)
        return timeout

    def wait_until(
        self, t_hw: float, stop: HwEvent | threading.Event, *, what: str = "next field"
    ) -> bool:
        """Block until hardware time ``t_hw``; False at once if ``stop`` is set meanwhile.

        ``stop`` is an event of :attr:`timebase` (its wait is in hardware seconds, labelled
        ``what``: by default the BIRIS supervisor's, this method's one user in the simulator);
        a plain ``threading.Event`` still works in scaled time. On waking, a scaled
        clock notes how late the wake was (:meth:`lateness`); a virtual one is never late.
        """
        while True:
            now = self.now()
            remaining = t_hw - now
            if remaining <= 0.0:
                if not self._virtual:
                    self._note_lateness(-remaining)
                return not stop.is_set()
            if isinstance(stop, HwEvent):
                if stop.wait(self.timeout_until(t_hw, now), what=what):
                    return False
            elif self._virtual:
                raise TypeError("in virtual time, stop must be an event of clock.timebase")
            elif stop.wait(remaining / self._scale):
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
        ``1 / time_scale`` real seconds. Always 0.0 in virtual time, where every wake happens at
        the very instant it was due. Read-only: measuring changes nothing in the simulation.
        """
        return self._lateness
