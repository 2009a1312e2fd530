"""One motor axis as the administrator keeps it: its worker, its queue of orders, its watchdog.

The report drives the pan motor through two tasks -- _az_scan_start, a worker that reports
AZ_READY and is *replied* the next destination, and _Biris_az_notifier, which reports AZ_SCAN_DONE
-- and foresees the same pair for a tilt motor (_el_scan_start, _el_scan_notifier). Both axes
are therefore the same bookkeeping: orders wait in a queue until the worker is free, one runs at
a time, and a watchdog (beyond the report) turns a motion that never ends into a fault instead
of a hang. Only the administrator thread touches these objects; they never block.

An order carries its *purpose* (a scan's move, a tilt's, homing, a parameter load, the
initialiser's move) and what it serves; the administrator maps the purpose to the named method
that handles its end.
"""

from __future__ import annotations

import dataclasses
import enum
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

from biris_hw.angles import clamp_counts
from biris_hw.devices import SETTLE_LIMIT_S
from biris_hw.ipc import Envelope
from biris_hw.records import MotorParams
from biris_hw.server.cmd_transfer import Timer
from biris_hw.server.messages import MoveOrder, ParamsOrder
from regs.tech80 import Axis, AxisBit

if TYPE_CHECKING:
    from biris_hw.server.elevation import Tilt
    from biris_hw.server.scan_assembly import ActiveScan

__all__ = ["ARRIVAL_TOLERANCE_COUNTS", "AxisState", "Motion", "MotionPurpose", "expected_move_s"]


ARRIVAL_TOLERANCE_COUNTS = 8
"""How far from its destination an axis may stand once its move has ended (counts, 0.7 degree).

The HCTL-1000 ends its profile whatever the shaft does, so the end of a move proves nothing: the
notifier reads the encoder once the head has settled, and a miss beyond this is a motor_stall
fault, never a completed scan. Appendix B's filter settles to 0 counts with at most 2 of
overshoot; 8 leaves room for a softer user filter while any real failure (a locked shaft, a dead
amplifier, a gain of 0) misses by the whole move."""

RECHECK_GRACE_S = SETTLE_LIMIT_S + 0.5
"""Hardware seconds after which a watchdog that ran out and asked the controller whether the
move had ended asks again, while no answer has come (a host too busy to run the level-3
routine). The answer decides, not this bound: a move the controller had not ended is a
motor_stall; one it had ended is verified by its notifier."""

WATCHDOG_REAL_SLACK_S = 0.5
"""Real seconds a motor watchdog allows on top, for notifier threads that a busy machine runs
late: on a simulator clock 20 times fast, 50 ms of starvation is a whole hardware second."""


class MotionPurpose(enum.Enum):
    """Why an axis order was given: names the administrator's case for its end."""

    SCAN = "scan"  # a scan's or sweep's move
    TILT = "tilt"  # a tilt's move
    HOME = "home"  # BIRIS_HOME
    PARAMS = "params"  # BIRIS_MOTOR_PARAMS (a ParamsOrder)
    INIT = "init"  # the initialiser's move (replied to its envelope)


@dataclass(eq=False)
class Motion:
    """One order for an axis worker, and what it serves."""

    order: MoveOrder | ParamsOrder
    purpose: MotionPurpose
    scan: ActiveScan | None = None
    tilt: Tilt | None = None
    requester: Envelope | None = None
    """The initialiser's INIT_MOVE, replied when the move ends."""
    origin: int | None = None
    """Where a move starts on the axis's count when that is not where the axis's last move ended
    (the initialiser's moves: a chip reset or a re-zeroing moved the count); the watchdog's bound
    is that of the distance really driven."""


def expected_move_s(distance: int, params: MotorParams) -> float:
    """How long a trapezoid of ``distance`` counts should take (hardware seconds)."""
    period = params.sample_period_s
    vmax = max(params.max_vel, 1)
    accel = max(params.max_accel / 256.0, 1.0 / 256.0)
    samples = abs(distance) / vmax + 2.0 * vmax / accel + 2.0
    return samples * period


class AxisState:
    """The administrator's record of one axis; ``position`` is where its last move ends."""

    def __init__(self, axis: Axis, watchdog: Timer, motor: MotorParams) -> None:
        self.axis = axis
        self.watchdog = watchdog
        self.motor = motor
        """The parameters the chip runs with (what the latest ParamsOrder loaded)."""
        self.env: Envelope | None = None
        """The worker, parked on its last READY report."""
        self.queue: deque[Motion] = deque()
        self.current: Motion | None = None
        self.position = 0
        self.watchdog_gen = -1
        self.rechecked = False
        """The running move's watchdog ran out once and the controller was asked."""
        self._allowed_s = 0.0
        """Hardware seconds the running move has, from its start, before it is a stall."""
        self._tokens = 0

    @property
    def name(self) -> str:
        return "azimuth" if self.axis is Axis.AZIMUTH else "elevation"

    @property
    def end_bit(self) -> int:
        """This axis's bit in the controller's ended-axes mask (:class:`regs.tech80.AxisBit`)."""
        return int(AxisBit.AZIMUTH if self.axis is Axis.AZIMUTH else AxisBit.ELEVATION)

    def busy(self) -> bool:
        """An order runs or waits."""
        return self.current is not None or bool(self.queue)

    def moving(self) -> bool:
        """A move (not a parameter load) runs or waits."""
        jobs = [*self.queue, *([self.current] if self.current else [])]
        return any(isinstance(job.order, MoveOrder) for job in jobs)

    def motor_for_next_move(self) -> MotorParams:
        """The parameters the next queued move will run with: a load ahead of it counts."""
        motor = self.motor
        for job in [*([self.current] if self.current else []), *self.queue]:
            if isinstance(job.order, ParamsOrder):
                motor = job.order.params
        return motor

    def submit(self, job: Motion) -> None:
        self.queue.append(job)

    def dispatch(self) -> bool:
        """Reply the next order to the parked worker, if both exist; True if one was sent.

        Every destination goes through _Scan_limit here, whoever asked for it.
        """
        if self.current is not None or self.env is None or not self.queue:
            return False
        job = self.queue.popleft()
        self.current = job
        env, self.env = self.env, None
        order = job.order
        if isinstance(order, MoveOrder):
            dest = clamp_counts(order.destination)
            self._tokens += 1
            order = dataclasses.replace(order, destination=dest, token=self._tokens)
            job.order = order  # what the worker got: the clamped destination and the token
            start = self.position if job.origin is None else job.origin
            duration = expected_move_s(dest - start, self.motor)
            if order.schedule is not None:  # a scan's move starts BIRIS's start-up later
                duration += order.schedule.lead_s
            # the notifier's settling may take up to SETTLE_LIMIT_S more, then threads run late
            self._allowed_s = duration * 1.5 + SETTLE_LIMIT_S + 1.0
            self.watchdog_gen = self.watchdog.arm(
                self._allowed_s, real_slack_s=WATCHDOG_REAL_SLACK_S
            )
            self.rechecked = False
            self.position = dest
        env.reply(order)
        return True

    def grace(self) -> None:
        """The watchdog ran out: the controller is asked whether the move had ended, and the
        watchdog asks again every :data:`RECHECK_GRACE_S` until the answer comes."""
        self.rechecked = True
        self.watchdog_gen = self.watchdog.arm(RECHECK_GRACE_S, real_slack_s=WATCHDOG_REAL_SLACK_S)

    def remaining_s(self, started: tuple[int, float] | None, now: float) -> float:
        """How much longer (hardware seconds) the running move may take before its not having
        ended is a stall, judged from when its worker started it (``started``: the worker's
        (token, time) record). A move its worker has not started yet has all of its time."""
        job = self.current
        if job is None or not isinstance(job.order, MoveOrder):
            return 0.0
        allowed = self._allowed_s
        if started is None or started[0] != job.order.token:
            return allowed
        return allowed - (now - started[1])

    def rearm(self, hw_seconds: float) -> None:
        """Arm the watchdog again for ``hw_seconds`` (a move judged not yet due)."""
        self.rechecked = False
        self.watchdog_gen = self.watchdog.arm(hw_seconds, real_slack_s=WATCHDOG_REAL_SLACK_S)

    def finish_current(self) -> Motion | None:
        """The running order is over (its end was reported); returns it."""
        job, self.current = self.current, None
        if job is not None and isinstance(job.order, MoveOrder):
            self.watchdog.disarm()
        return job

    def ends_current(self, token: int | None) -> bool:
        """Whether an end-of-move report with ``token`` is the end of the move now running
        (not of one a reset or fault abandoned)."""
        job = self.current
        if job is None or not isinstance(job.order, MoveOrder):
            return False
        return token is None or token == job.order.token

    def abandon(self) -> list[Motion]:
        """A fault or reset: every order, running or waiting, is given up; returns them."""
        self.watchdog.disarm()
        jobs = [*([self.current] if self.current else []), *self.queue]
        self.queue.clear()
        self.current = None
        return jobs
