"""How many acquisitions a report-mode scan asks BIRIS for, and when its motor starts.

The report: "the number of BIRIS acquisitions for each scan is adjusted automatically to match
the given scan length". Its own formula (scan length / ``_Get_acq_rate()``, with BIRIS_DATA_RATE
as the acquisition period) ignores two things the hardware does, and the scan it gives misses
its start and stands at its end (issue 12: ``--to 90`` gave a first acquisition at ~33 degrees
and 11 of 25 taken standing at 90):

* each BI_ACQUIRE sequence first spends BIRIS's start-up (240 ms, ACQ_LINE = -1) acquiring
  nothing, so a motor started with it has covered a third of a 90 degree scan by the first
  acquisition;
* the real acquisition period is whole video fields (2 fields, 33.4 ms, at 64 samples; 3 at
  128), not BIRIS_DATA_RATE's 30 ms.

So the server writes BI_ACQUIRE first and starts the trapezoid when BIRIS signals that the
start-up is over (the first data interrupt of the sequence, ACQ_LINE >= 0: SEQUENCE_STARTED), and
asks for as many acquisitions as the trapezoid lasts in real acquisition periods -- ramps
included -- plus the time it takes the server to start the motor once told (learned, scan after
scan), plus one to stand at the destination and one spare. An acquisition taken with the head
still standing at either end is discarded and counted (``constant_azimuth``), as in continuous
acquisition, so a scan's data span its length: the first kept acquisition within one period of
the motion's start, the last at the destination.
"""

from __future__ import annotations

import math
from collections import deque

from biris_hw.records import MotorParams
from regs.layout import SAMPLES_CHOICES, acquisition_period_s

__all__ = [
    "DATA_RATE_TOLERANCE",
    "HOST_LATENCY_S",
    "ScanTiming",
    "data_rate_mismatch",
    "trapezoid_s",
]

DATA_RATE_TOLERANCE = 0.05
"""BIRIS_DATA_RATE may differ from the real acquisition period by this fraction before the
server says so (it always counts with the real period)."""

START_DELAYS_KEPT = 8
"""How many recent motor-start delays the estimate looks at (the largest counts)."""

MAX_START_DELAY_S = 0.5
"""A start delay beyond this (hardware seconds) is taken as this: a server that slow has other
problems, and a scan must not ask for seconds of acquisitions standing at its end."""

HOST_LATENCY_S = 0.003
"""Host seconds a loaded host may take between BIRIS's first data interrupt and the trapezoid's
hand-over (a notifier's wake-up, the administrator's inbox, the worker's). On the real head it is
a tenth of a period; a simulator run at ``time_scale`` 30 turns it into 90 ms of hardware time,
nearly three periods, which the first scan (before any delay is learned) must allow for or end
short of its destination."""

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
    """The acquisition period and the motor-start delay a report-mode scan is counted with.

    ``period_s`` is learned at initialisation (the frame size BIRIS reports gives the samples
    per acquisition, hence the fields per acquisition). The start delay is learned from every
    scan: from the moment BIRIS began the first acquisition (the reader's bound) to the moment
    the administrator handed the trapezoid to the azimuth worker. The largest of the recent
    ones counts, so a server that was slow once asks for a spare acquisition rather than ends
    a scan short of its destination.

    ``time_scale`` is the hardware's (hardware seconds per host second): before any delay is
    learned the estimate allows :data:`HOST_LATENCY_S` of host time in hardware seconds.
    """

    def __init__(self, period_s: float = 0.0, time_scale: float = 1.0) -> None:
        self.period_s = period_s
        self.host_latency_s = HOST_LATENCY_S * max(time_scale, 0.0)
        """:data:`HOST_LATENCY_S` in hardware seconds."""
        self._delays: deque[float] = deque(maxlen=START_DELAYS_KEPT)

    @property
    def start_delay_s(self) -> float:
        """The motor-start delay the next scan is counted with (hardware seconds): the largest
        of the recent ones; before any has been seen, one acquisition period plus the host's
        latency in hardware time (a driver in another process than its simulator, or a loaded
        host, starts a period or two late, and a scan that ends short of its destination is
        worse than a few more standing at it, which are dropped and counted)."""
        if not self._delays:
            return min(self.period_s + self.host_latency_s, MAX_START_DELAY_S)
        return max(self._delays)

    def note_start_delay(self, delay_s: float) -> None:
        """The trapezoid of a scan was handed over ``delay_s`` after its first acquisition
        began."""
        if math.isfinite(delay_s):
            self._delays.append(min(max(delay_s, 0.0), MAX_START_DELAY_S))

    def acquisitions(self, distance: int, params: MotorParams) -> int:
        """BI_ACQUIRE's count for a scan of ``distance`` counts at ``params``.

        Acquisition k is exposed around (k + 1/2) periods after the first began; the head
        arrives ``start delay + trapezoid + settling`` after that. The count reaches the first
        acquisition made at or after the arrival (it is kept: the scan's last point, at the
        destination), plus one spare against a start later than any seen so far (discarded,
        counted, as standing). At least 2 for any scan that moves.
        """
        if distance == 0:
            return 0
        period = self.period_s
        if period <= 0.0:  # not initialised: nothing can acquire; keep the arithmetic sane
            period = acquisition_period_s(SAMPLES_CHOICES[0])
        arrival = self.start_delay_s + trapezoid_s(distance, params) + SETTLE_PERIODS * period
        last = max(0, math.ceil(arrival / period - 0.5))  # the first exposed at the arrival
        return last + 2
