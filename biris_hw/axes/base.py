"""The axis interface: what the server asks of one servo axis and of the board that signals ends.

Written from what the server calls today on the Model 7600's HCTL-1000s
(:class:`~biris_hw.devices.AxisDriver`, :class:`~biris_hw.devices.MotionBoard`), so that a
second kind of axis (a CiA 402 drive over CANopen, :mod:`biris_hw.axes.cia402`) can stand in for
them without the server knowing which it drives. Both are structural :class:`typing.Protocol`\\ s:
the HCTL classes satisfy them without inheriting anything.

The settling rules (:func:`wait_settled`, :func:`wait_still`) are here too, as functions of a
position reader, because they are the server's rules about a head coming to rest, not a chip's:
every axis kind must answer "settled" on the same evidence, or the administrator would judge
one kind of head by a looser test than the other.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

from biris_hw.errors import HardwareFault
from biris_hw.irq.base import InterruptLine
from biris_hw.pan_reference import PanReference
from biris_hw.records import MotorParams
from biris_hw.timebase import StopEvent, timebase_of
from regs.tech80 import Axis

__all__ = [
    "SETTLE_HOLD_S",
    "SETTLE_LIMIT_S",
    "SETTLE_POLL_S",
    "AxisSet",
    "MotionAxis",
    "MotionController",
    "wait_settled",
    "wait_still",
]

SETTLE_LIMIT_S = 1.0
"""Hardware seconds :meth:`MotionAxis.wait_settled` watches the head by default before calling
it unsettled (watched: polls made on time, :func:`wait_settled`)."""

SETTLE_HOLD_S = 0.015
"""How long the head must stand still at its command position to count as settled (hardware
seconds, about ten HCTL-1000 samples at the record's sample timer). Counted on the hardware
clock, not in polls: a head ringing under a filter it cannot follow passes its destination
slowly at a turning point, and three polls close together on a busy host saw it "settled"
there."""

SETTLE_POLL_S = 0.003
"""How often a settling poll reads the head (hardware seconds): five or more looks inside
:data:`SETTLE_HOLD_S`, two HCTL-1000 samples apart at the record's sample timer. Polling
twice as often finds the same settled position at most one poll sooner, for twice the bus
traffic (and, on the simulator, 15 % more CPU per initialisation)."""

WATCH_GAP_POLLS = 10
"""How many polling periods one gap between two settling polls may count towards the settling
limit (:func:`wait_settled`): a longer gap is a host that was not looking, not a head that
was."""

LATE_VERDICT_POLLS = 2
LATE_VERDICT_LIMITS = 2.0
"""However late each look: a head seen away from its command position at a look made at least
this many settling limits of hardware time after the first (and at least
:data:`LATE_VERDICT_POLLS` looks in all) has not come to rest -- seconds after its profile
ended, that is the shaft's doing, not the host's. A head that arrived during a stall is seen at
its command position at the look after it, and is then watched for its hold. Bounds what a
device whose every read is slow costs: a simulator that cannot keep up with its clock catches
its chips up at each read and falls further behind with each, so waiting for many slow looks
would never end."""


@runtime_checkable
class MotionAxis(Protocol):
    """One servo axis as the server drives it: positions, parameters, hold, move, settle.

    Positions are encoder counts (4096 per head revolution). ``start_trapezoid`` clamps its
    destination to +-0x1000 whatever it is given, and an axis with a pan reference records the
    move there before it starts it.
    """

    def actual_position(self) -> int:
        """Where the encoder says the head is now (counts)."""
        ...

    def command_position(self) -> int:
        """Where the axis's position loop is taking the head now (counts)."""
        ...

    def configure(self, params: MotorParams) -> None:
        """Load BIRIS_MOTOR_PARAMS' six values (sample, filter, profile limits)."""
        ...

    def read_params(self) -> dict[str, int]:
        """The six values as the axis holds them now, raw, in :meth:`MotorParams.to_dict`'s
        keys: they must round-trip exactly (the pan reference compares them)."""
        ...

    def idle(self) -> None:
        """No torque: the head coasts and stays where friction leaves it."""
        ...

    def hold_here(self, zero_counter: bool = False) -> None:
        """Enter position control holding the present position (zeroed first if asked): no
        jump. Called with the axis idle."""
        ...

    def prepare_trapezoid(self, destination: int) -> None:
        """Do ahead what :meth:`start_trapezoid` of ``destination`` does before the motor
        moves (record the move in the pan reference's journal, durably: a file written and
        synced), so that a start at a scheduled time is only the device's own commands."""
        ...

    def start_trapezoid(self, destination: int) -> int:
        """Start a trapezoidal move; returns the destination actually commanded."""
        ...

    def profile_active(self) -> bool:
        """A move started here has not yet been reported ended."""
        ...

    def wait_settled(
        self,
        stop: StopEvent,
        limit_s: float = SETTLE_LIMIT_S,
        sample_s: float = SETTLE_POLL_S,
    ) -> bool:
        """Poll until the head stands at its command position (see :func:`wait_settled`)."""
        ...

    def wait_still(self, stop: StopEvent, limit_s: float = 2.0, sample_s: float = 0.002) -> None:
        """Poll until the encoder stops changing (see :func:`wait_still`)."""
        ...


@runtime_checkable
class MotionController(Protocol):
    """The board beside the axes: end-of-motion interrupt, resets, index latches.

    ``ended_axes`` is what the level-3 routine reads to tell which axes' profiles ended (the
    IRQ_STATUS bits of the Model 7600, :class:`regs.tech80.AxisBit`); ``acknowledge`` clears one.
    """

    def reset_chip(self, axis: Axis) -> None:
        """Stop the axis (no torque) and restart its count at 0 where the head stands."""
        ...

    def enable_end_of_scan(self, axis: Axis, vector: int, enabled: bool = True) -> None:
        """Let (or stop) the end of ``axis``'s profile raise the level-3 interrupt."""
        ...

    def disable_all(self) -> None:
        """No axis raises the level-3 interrupt."""
        ...

    def index_seen(self, axis: Axis) -> bool:
        """The index latch of ``axis`` is set: the head crossed its zero index since cleared."""
        ...

    def clear_index(self, axis: Axis) -> None:
        """Clear (re-arm) the index latch of ``axis``."""
        ...

    def acknowledge(self, axis: Axis) -> None:
        """Clear ``axis``'s bit in :meth:`ended_axes`."""
        ...

    def ended_axes(self) -> int:
        """Bitmask (:class:`regs.tech80.AxisBit`) of axes whose profile ended, unacknowledged."""
        ...

    def take_fault(self) -> HardwareFault | None:
        """A fault the controller saw on its own since last asked, once, as the exception to
        raise with its kind: a drive's heartbeat lost or a communication EMCY (``bus``), any
        other EMCY (``motor_stall``), whether or not an axis was moving; None when there is
        none. A controller that comes to hold one raises its end-of-motion line, so the
        level-3 routine asks at that wake (and every other) and raises it, and the server's
        supervisor reports it to every caller with that kind. The Model 7600 has no such
        faults (a register it cannot read raises as it happens): always None."""
        ...


@runtime_checkable
class AxisSet(Protocol):
    """Axes that are not on the Model 7600: the pan, the tilt and their controller, with the
    line the controller raises at the end of a move (the bundle's ``level3``).

    A :class:`~biris_hw.hardware.BirisHardware` given one drives its axes through it instead of
    the HCTL-1000s; it hands the set its pan reference (the pan's true zero) as it is built, and
    closes it with itself.
    """

    @property
    def azimuth(self) -> MotionAxis:
        """The pan axis."""
        ...

    @property
    def elevation(self) -> MotionAxis:
        """The tilt axis."""
        ...

    @property
    def controller(self) -> MotionController:
        """End-of-motion bits, resets, index latches of both axes."""
        ...

    @property
    def end_of_motion(self) -> InterruptLine:
        """The line raised when an enabled axis's move ends: the bundle's level 3."""
        ...

    def use_pan_reference(self, reference: PanReference) -> None:
        """Record every pan move there first and cut its destination, as the HCTL driver does."""
        ...

    def relink(self) -> None:
        """Bring back every axis whose link was lost (a drive whose heartbeat stopped), as at
        the first use, before a reset initialises; nothing for axes that are there. Raises
        :class:`~biris_hw.errors.HardwareFault` (``bus``) naming what is still missing."""
        ...

    def close(self) -> None:
        """Stop listening, close the line and whatever connection the set owns; idempotent."""
        ...


def wait_settled(
    positions: Callable[[], tuple[int, int]],
    clock: Callable[[], float],
    time_scale: float,
    stop: StopEvent,
    limit_s: float = SETTLE_LIMIT_S,
    sample_s: float = SETTLE_POLL_S,
    holding: Callable[[], bool] | None = None,
) -> int | None:
    """The settling rule of every axis: polling, as the HCTL-1000 datasheet says to tell that
    the motor has stopped (the end of a profile comes before it does). ``positions`` reads
    (actual, command) together, in one bus transaction where the axis can.

    Held means the same reading, within a count of the command position, for at least 3 polls
    and :data:`SETTLE_HOLD_S` of hardware time (``clock``), polled every ``sample_s`` (hardware
    seconds, waited on ``stop`` through the clock's time base: :func:`~biris_hw.timebase.
    timebase_of`). ``holding``, when
    given, says whether the axis's loop holds the head at all (a faulted drive's demand
    follows the head, so it would "settle" anywhere). Returns the settled position, or None
    (not settled, or ``stop`` set).

    The verdict is the motor's, not the host's: ``limit_s`` is hardware time *watched*, the
    sum of the gaps between successive polls, each counted up to :data:`WATCH_GAP_POLLS`
    polling periods. A host that ran a poll late has not watched the head meanwhile, so a
    stall of the polling thread (a loaded machine, a simulator clock far faster than the host)
    costs polls, never a false "had not come to rest": the head is called unsettled only after
    it was seen moving, or away from its command position, across ``limit_s`` of polls made on
    time -- or away from it at a look :data:`LATE_VERDICT_LIMITS` limits of hardware time after
    the first, however late each came. The watchdog above this
    (:mod:`biris_hw.server.motion`) asks the controller before it calls a move stalled.
    """
    watched = 0.0
    gap_limit = WATCH_GAP_POLLS * sample_s
    first: float | None = None
    previous: float | None = None
    last: int | None = None
    polls = 0
    steady = 0
    since = 0.0
    timebase = timebase_of(clock, time_scale)
    while True:
        now = clock()
        pos, target = positions()
        polls += 1
        if previous is not None:
            watched += min(max(now - previous, 0.0), gap_limit)
        else:
            first = now
        previous = now
        at_target = abs(pos - target) <= 1 and (holding is None or holding())
        if at_target and pos == last:
            steady += 1
            if steady >= 3 and now - since >= SETTLE_HOLD_S:
                return pos
        else:
            steady = 0
            since = now
        # seen long enough on time (a head at its command position then gets a hold's worth
        # more), or seen often over a long time however late each look (a few more polls)
        if watched >= limit_s and (not at_target or watched >= limit_s + 2 * SETTLE_HOLD_S):
            return None
        assert first is not None
        late = polls >= LATE_VERDICT_POLLS and now - first >= LATE_VERDICT_LIMITS * limit_s
        if late and (not at_target or (steady == 0 and polls >= LATE_VERDICT_POLLS + 10)):
            return None
        last = pos
        if timebase.wait_event(stop, sample_s, what="settling poll"):
            return None


def wait_still(
    position: Callable[[], int],
    clock: Callable[[], float],
    time_scale: float,
    stop: StopEvent,
    limit_s: float = 2.0,
    sample_s: float = 0.002,
) -> None:
    """Poll until the encoder stops changing (5 equal samples), bounded by ``limit_s`` of
    hardware time: a head let go coasts, and nothing is commanded to compare it with."""
    timebase = timebase_of(clock, time_scale)
    deadline = clock() + limit_s
    last = position()
    steady = 0
    while clock() < deadline and steady < 5:
        if timebase.wait_event(stop, sample_s, what="stillness poll"):
            return
        pos = position()
        steady = steady + 1 if pos == last else 0
        last = pos
