"""How many acquisitions a report-mode scan asks BIRIS for, and when its motor starts.

The report: "the number of BIRIS acquisitions for each scan is adjusted automatically to match
the given scan length". Its own formula (scan length / ``_Get_acq_rate()``, with BIRIS_DATA_RATE
as the acquisition period) ignores two things the hardware does, and the scan it gives misses
its start and stands at its end:

* each BI_ACQUIRE sequence first spends BIRIS's start-up (240 ms, ACQ_LINE = -1) acquiring
  nothing, so a motor started with it has covered a third of a 90 degree scan by the first
  acquisition;
* the real acquisition period is whole video fields (2 fields, 33.4 ms, at 64 samples; 3 at
  128), not BIRIS_DATA_RATE's 30 ms.

So the server writes BI_ACQUIRE first and starts the trapezoid one start-up later, at a
hardware time fixed by the write (:mod:`~biris_hw.server.start_schedule`): whenever the host
sees BIRIS's interrupts, the motion begins as BIRIS's first acquisition does. The start-up is
learned (:meth:`ScanTiming.note_startup`: from BI_ACQUIRE's write to the first acquisition,
the smallest of the recent ones, since the reader's bound on a start is never early), and the
motor is started a quarter of a video field before it (:data:`START_AFTER_S`): BIRIS sees a
command at the next vertical sync, so its start-up ends up to a field later, and the first
acquisition is then exposed with the head just under way.

The count is as many acquisitions as the trapezoid lasts in real acquisition periods -- ramps
included -- from that start, plus how late the host has started motors on recent scans (the
one thing left to its timing: one timed wake of the azimuth worker), plus one to stand at the
destination and one spare. An acquisition taken with the head still standing at either end is
discarded and counted (``constant_azimuth``), as in continuous acquisition, so a scan's data
span its length. A start later than the count allowed for leaves the scan short of its
destination: the scan says so (``partial`` with its reason), never silently.
"""

from __future__ import annotations

import math
from collections import deque

from biris_hw.records import MotorParams
from regs.layout import SAMPLES_CHOICES, acquisition_period_s

__all__ = [
    "DATA_RATE_TOLERANCE",
    "FIELD_S",
    "HOST_LATENCY_S",
    "STARTUP_FIELDS_S",
    "STARTUP_S",
    "ScanTiming",
    "data_rate_mismatch",
    "trapezoid_s",
]

DATA_RATE_TOLERANCE = 0.05
"""BIRIS_DATA_RATE may differ from the real acquisition period by this fraction before the
server says so (it always counts with the real period)."""

RECENT_KEPT = 8
"""How many recent start-ups and start latenesses the estimates look at."""

MAX_LATENESS_S = 0.5
"""A motor-start lateness beyond this (hardware seconds) is taken as this: a server that slow
has other problems, and a scan must not ask for seconds of acquisitions standing at its end."""

HOST_LATENCY_S = 0.010
"""Host seconds a loaded host may take to wake the azimuth worker at its scheduled start and
hand the start to the motor, always allowed for (more once more has been measured). On the real
head it is a third of a period, at most one more acquisition standing at the destination (dropped,
counted); a simulator run at ``time_scale`` 30 turns it into 300 ms of hardware time, nine
periods, which a host sharing its interpreter with the simulator (a 5 ms GIL hand-over is
150 ms there) needs."""

STARTUP_S = 0.240
"""The report's start-up of an acquisition sequence (hardware seconds), until one is measured."""

FIELD_S = 1.0 / 59.94
"""One RS-170 video field: BIRIS sees a command at the vertical sync after its write."""

START_AFTER_S = -FIELD_S / 4.0
"""When the motor starts relative to the shortest start-up measured (hardware seconds; negative:
before it). BIRIS sees a command up to a field after its write, so its first acquisition begins
0 to 1 field after the shortest start-up and is exposed half a period later; the head follows
its command about 11 ms late at Appendix B's gains (measured on the simulated plant: 0.9 counts
8.6 ms after F0, 4.3 counts at 15 ms). Started a quarter field early, the head has left its
start by the first exposure when BIRIS saw the command at once (or that acquisition is standing
and the next is under one acquisition's travel from the start), and has not gone one
acquisition's travel by it when BIRIS saw the command a field late."""

STARTUP_FIELDS_S = math.ceil(STARTUP_S / FIELD_S - 1e-9) * FIELD_S
"""The report's start-up in whole video fields (15, 250.25 ms): the shortest BIRIS takes from a
command it sees at once, and the estimate until one is measured (interpretation)."""

STARTUP_MAX_S = STARTUP_FIELDS_S + FIELD_S
"""The longest start-up the report's BIRIS can take from BI_ACQUIRE's write (hardware seconds):
its 240 ms in whole fields, after up to a field before it sees the command (interpretation:
the start-up counts from that vertical sync, as the simulator does). A measured start-up above
it is a bound made loose by a host that looked late, and is taken as this."""

SETTLE_PERIODS = 0.25
"""Periods allowed after the trapezoid's last setpoint for the head to be within a count or
two of the destination (the filter's lag at the default gains is a few samples)."""


def trapezoid_s(distance: int, params: MotorParams) -> float:
    """How long the HCTL-1000's trapezoid of ``distance`` counts lasts (hardware seconds).

    Accelerate at ``max_accel`` / 256 counts per sample squared to ``max_vel`` counts per sample,
    cruise, decelerate; a move too short to reach ``max_vel`` is a triangle. Unlike the
    watchdog's bound (:func:`~biris_hw.server.motion.expected_move_s`) this is the time itself.
    """
    d = abs(distance)
    if d == 0:
        return 0.0
    vmax = float(max(params.max_vel, 1))
    accel = max(params.max_accel, 1) / 256.0
    if d < vmax * vmax / accel:  # never reaches full speed: a triangle
        return 2.0 * math.sqrt(d / accel) * params.sample_period_s
    return (d / vmax + vmax / accel) * params.sample_period_s  # ramp up, cruise, ramp down


def data_rate_mismatch(data_rate_ms: int, period_s: float) -> str | None:
    """What to tell the operator when BIRIS_DATA_RATE is not the real acquisition period."""
    if period_s <= 0.0:
        return None
    given = data_rate_ms / 1000.0
    if abs(given - period_s) <= DATA_RATE_TOLERANCE * period_s:
        return None
    return (
        f"BIRIS_DATA_RATE is {data_rate_ms} ms but BIRIS acquires every {period_s * 1000.0:.2f} "
        f"ms (whole video fields); scans are counted with {period_s * 1000.0:.2f} ms"
    )


class ScanTiming:
    """The acquisition period, BIRIS's start-up and the motor-start lateness a report-mode scan
    is counted and scheduled with.

    ``period_s`` is learned at initialisation (the frame size BIRIS reports gives the samples
    per acquisition, hence the fields per acquisition). The start-up is learned from every
    scan (:meth:`note_startup`), and so is how late the azimuth worker started the motor after
    its scheduled time (:meth:`note_lateness`): the largest of the recent ones counts, so a
    server that was slow once asks for a spare acquisition rather than ends a scan short.

    ``time_scale`` is the hardware's (hardware seconds per host second): before any lateness is
    measured the count allows :data:`HOST_LATENCY_S` of host time in hardware seconds.
    """

    def __init__(self, period_s: float = 0.0, time_scale: float = 1.0) -> None:
        self.period_s = period_s
        self.host_latency_s = HOST_LATENCY_S * max(time_scale, 0.0)
        """:data:`HOST_LATENCY_S` in hardware seconds."""
        self._startups: deque[float] = deque(maxlen=RECENT_KEPT)
        self._lateness: deque[float] = deque(maxlen=RECENT_KEPT)

    @property
    def startup_s(self) -> float:
        """BIRIS's shortest start-up from BI_ACQUIRE's write to its first acquisition (hardware
        seconds): the smallest recently measured, else the report's 240 ms in whole fields."""
        if not self._startups:
            return STARTUP_FIELDS_S
        return min(min(self._startups), STARTUP_MAX_S)

    @property
    def startup_lead_s(self) -> float:
        """From BI_ACQUIRE's write to the trapezoid's start (hardware seconds): the shortest
        start-up less a quarter of a field (:data:`START_AFTER_S`)."""
        return self.startup_s + START_AFTER_S

    @property
    def lateness_allowance_s(self) -> float:
        """How late after its schedule the next scan's motor may start without the scan ending
        short (hardware seconds): the largest recent lateness, at least the host's latency."""
        seen = max(self._lateness) if self._lateness else 0.0
        return min(max(seen, self.host_latency_s), MAX_LATENESS_S)

    def note_startup(self, startup_s: float) -> None:
        """A sequence's first acquisition began ``startup_s`` after BI_ACQUIRE's write (the
        reader's bound, never early). Implausible values (negative, or beyond a second) are
        ignored: a bound from a host that looked very late says nothing about BIRIS."""
        if math.isfinite(startup_s) and 0.0 < startup_s < 1.0:
            self._startups.append(startup_s)

    def note_lateness(self, late_s: float) -> None:
        """A scan's trapezoid started ``late_s`` after its schedule."""
        if math.isfinite(late_s):
            self._lateness.append(min(max(late_s, 0.0), MAX_LATENESS_S))

    def acquisitions(self, distance: int, params: MotorParams) -> int:
        """BI_ACQUIRE's count for a scan of ``distance`` counts at ``params``.

        Acquisition k is exposed around (k + 1/2) periods after the first began; the motor
        starts about then (:data:`START_AFTER_S`), plus the lateness allowed for, and the
        head arrives a trapezoid and a settling later. The count reaches the first acquisition
        made at or after the arrival (it is kept: the scan's last point, at the destination),
        plus one spare (discarded, counted, as standing). At least 2 for any scan that moves.
        """
        if distance == 0:
            return 0
        period = self.period_s
        if period <= 0.0:  # not initialised: nothing can acquire; keep the arithmetic sane
            period = acquisition_period_s(SAMPLES_CHOICES[0])
        start = max(START_AFTER_S, 0.0) + self.lateness_allowance_s
        arrival = start + trapezoid_s(distance, params) + SETTLE_PERIODS * period
        last = max(0, math.ceil(arrival / period - 0.5))  # the first exposed at the arrival
        return last + 2
