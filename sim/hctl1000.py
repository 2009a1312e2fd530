"""The HP HCTL-1000 motion-control IC, as a model that closes a loop around :class:`MotorPlant`.

Two ways in, kept apart on purpose (docs/design.md): the *bus* (``bus_read``/``bus_write``), one
byte per access with the chip's side effects (R14H latches, R0EH commits, R13H clears, R00H sets
one flag, R05H changes mode) and the audit; and the *backdoor* (``peek``/``poke`` and typed
properties) for the simulator, register dumps and tests, with no side effects at all.

Time advances one sample period per :meth:`Hctl1000.step` (t = 16(T+1)/f_clk, T = R0FH; a new T
applies from the next period because each step reads R0FH when it starts). At each sample the
chip reads the encoder, runs the mode's profile generator, runs the filter
``MC[n] = (K/4)(X[n] - (A/256) X[n-1]) - (B/256) MC[n-1]`` on the position error X, truncates
towards zero, clamps to -128..127 and stores the result offset-binary in R08H; the plant then runs
one sample period under that command. ``MC[n-1]`` is the stored (clamped) output, as in an 8-bit
part. :meth:`advance_to` steps up to a hardware time and skips sample periods in which nothing
observable can change (head held by friction or stalled, filter in a fixed point or two-cycle;
only the winding current of the held motor is left where it was).

Interpretations where the datasheets found say nothing (docs/design.md):

* A sample timer below 07H (the datasheet's minimum) runs as 07H: the chip could not finish its
  computation, and the model must not drown in 8 us ticks.
* Power-up/reset values are ours: every register 0 except sample timer 40H, filter A = E5H,
  B = 00H, K = 40H (recollection of the HCTL-1100's, unverified), R08H = 80H and status E0H.
  Program counter 00H is a software reset with the same effect; the chip shows
  :attr:`Mode.RESET` until the next sample and then enters init/idle by itself.
* Entering init/idle clears the filter history, sets R08H to 80H and clears F0 (a profile cannot
  run in idle). R08H written in init/idle drives the motor open loop (ELDORA's test does this).
* Align (02H, from init/idle) has nothing to commutate on a DC motor: the chip goes straight to
  position control and clears F0/F3/F5, as it would after the align sequence.
* 02H/03H while already in control are ignored (the datasheet allows them from init/idle only).
* If the host sets several control flags (forbidden) the first of F0, F3, F5 runs. F1 is the
  chip's own (R00H writes to it are ignored); F2 (unipolar) limits R08H to 80H..FFH; F4 is stored.
* Reading R00H returns the flags, bit n = Fn; R05H reads 0. The HCTL-1000 has no position
  preset: R15H..R17H are ignored. Unmapped registers read 0 and ignore writes.
* Any write to R13H clears the actual position counter (an HCTL-1100 fact applied to the 1000)
  and the software reset (R05H = 00H) clears it too. Neither is verified for the HCTL-1000, so
  a chip can be made to differ (:class:`ChipVariant`, ``chip.variant``): a driver that assumes
  a clear without reading the counter back then commits a command far from the head.
* Reading R0CH..R0EH returns the live command position; R0CH/R0DH writes are held until R0EH.
* Proportional velocity: the command position follows the actual position, so leaving the mode
  holds the head where it is; R34H/R35H get the measured counts per sample.
* Integral velocity: on entry the command velocity starts at 0 and the command position at the
  present command position; the velocity ramps towards R3CH at the programmed acceleration.
* Trapezoid: start position, final position, acceleration and maximum velocity are captured when
  the profile starts (the datasheet forbids changing them while F0 is set). The setpoint at
  sample k is the ideal trapezoid (or triangle) sampled at k and rounded; the first sample whose
  setpoint is the final position is the last (F0 clears there), so the steps sum exactly to the
  move and never exceed the maximum velocity. F0 set in init/idle waits for 03H. With no
  acceleration or no maximum velocity programmed the profile never progresses (presumably what
  the chip does).
* The profile generator knows nothing of the shaft. A stalled plant (a locked shaft) or a dead
  amplifier leaves it running: the trapezoid ends on time, F0 clears and the board signals the
  end of scan, while the position stays where the shaft stopped -- the real chip's failure mode,
  which a driver can only catch by comparing the encoder with the destination. (An earlier
  model froze the profile of a stalled plant, so a driver's end-of-scan watchdog caught every
  stall and nothing showed a move "completed" away from its destination.)

Audit rules (recorded with the register values involved; a violation is a driver bug):

* ``MOTOR_BEYOND_LIMIT``: a trapezoid starts (F0 reaches control) with a final position outside
  +-0x1000, or an R0EH write commits a command position outside +-0x1000.
* ``POSITION_MODE_WHILE_MOVING``: (a) an R00H write takes the chip from trapezoid or a velocity
  mode to position control while a trapezoid is still running (always) or the head turns faster
  than 0.5 counts/sample; (b) an R0EH write in position control commits a command more than
  16 counts from the actual position while the head turns faster than 0.5 counts/sample;
  (c) R05H = 02H/03H enters position control while the head turns faster than 0.5 counts/sample;
  (d) R05H = 02H/03H enters position control with the command position more than
  :data:`JUMP_COUNTS` from the actual position: the head jumps to it (a driver that zeroed the
  command but not the counter, the report's HOME warning).
* ``MOTION_WHILE_UNINITIALISED``: a trapezoid or velocity mode starts before both the filter gain
  (R22H) and the sample timer (R0FH) have been written since the last reset.
* ``WRITE_TO_READ_ONLY``: any write to R12H, R14H, R34H or R35H (the write is ignored).
* ``HEAD_BEYOND_LIMIT`` (a chip made with ``head_limit``; the board passes
  :data:`HEAD_LIMIT_COUNTS` for the pan axis): after a sample, the plant's *true* azimuth is
  beyond +-``head_limit`` counts from true zero, whatever the chip's counter reads (a counter
  zeroed a revolution away still reads inside the envelope). Once per excursion: recorded when
  the head leaves, re-armed only when it is back within +-0x1000. One comparison per sample.

The model is not thread-safe; :class:`sim.tech80.Model7600` serialises it under its lock.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass

from regs.hctl1000 import (
    F_CLK_HZ,
    HCTL_SPACE,
    MOTION_LIMIT_COUNTS,
    SAMPLE_TIMER_MIN,
    Reg,
    Status,
    to_signed24,
)
from sim.audit import Audit, Rule
from sim.motor import MotorPlant

__all__ = [
    "HEAD_LIMIT_COUNTS",
    "HEAD_OVERSHOOT_COUNTS",
    "HISTORY",
    "JUMP_COUNTS",
    "MOVING_COUNTS_PER_SAMPLE",
    "POWER_UP",
    "ChipVariant",
    "Hctl1000",
    "Mode",
]

ACCESS_TICKS = 4096
"""Most samples one bus access simulates to catch the chip up (5.8 s of hardware time at
Appendix B's sample timer: never reached while the board's thread keeps the chip on time)."""

HISTORY = 1024
"""Samples of encoder readings kept for :meth:`Hctl1000.position_at`: 1.4 s of hardware time at
the default sample period, far more than a late thread is behind at any time scale tests use."""
_HIST_MASK = HISTORY - 1

MOVING_COUNTS_PER_SAMPLE = 0.5
"""Above this head speed a switch to position control counts as 'while moving'."""

JUMP_COUNTS = 16
"""A committed command further than this from the actual position makes the head jump."""

HEAD_OVERSHOOT_COUNTS = 48
"""How far past +-0x1000 the true pan head may go before ``HEAD_BEYOND_LIMIT``.

A driver that keeps its destinations within +-0x1000 still sees the head pass them by the
filter's overshoot: at most 2 counts with Appendix B's filter, at most 21 counts over 450 random
filters and profiles (a limit cycle of K = 0xFF, A = 0x00; the reliability review's random
runs reached 4114.7, 18.7 past). 48 counts (4.2 degrees) is over twice that, so no legal filter
trips it, yet far short of the stops (256 counts) and of a revolution's wind-up (4096)."""

HEAD_LIMIT_COUNTS = MOTION_LIMIT_COUNTS + HEAD_OVERSHOOT_COUNTS
"""Beyond +-this many counts from true azimuth 0 the true pan head is audited."""

POWER_UP: dict[int, int] = {
    Reg.SAMPLE_TIMER: 0x40,
    Reg.FILTER_ZERO: 0xE5,
    Reg.FILTER_POLE: 0x00,
    Reg.FILTER_GAIN: 0x40,
    Reg.MOTOR_COMMAND: 0x80,
}
"""Non-zero register values after a reset (ours; see the module docstring)."""

_F0, _F1, _F2, _F3, _F4, _F5 = (1 << n for n in range(6))
_CONTROL_FLAGS = _F0 | _F3 | _F5
_READ_ONLY = frozenset({Reg.ACT_POS_MSB, Reg.ACT_POS_LSB, Reg.ACT_VEL_LSB, Reg.ACT_VEL_MSB})
_STORED = frozenset(
    {
        Reg.PWM_COMMAND,
        Reg.SAMPLE_TIMER,
        Reg.COMMUTATOR_RING,
        Reg.COMMUTATOR_VEL_TIMER,
        Reg.COMMUTATOR_X,
        Reg.COMMUTATOR_Y,
        Reg.COMMUTATOR_OFFSET,
        Reg.COMMUTATOR_MAX_ADVANCE,
        Reg.FILTER_ZERO,
        Reg.FILTER_POLE,
        Reg.FILTER_GAIN,
        Reg.CMD_VEL_LSB,
        Reg.CMD_VEL_MSB,
        Reg.ACCEL_LSB,
        Reg.ACCEL_MSB,
        Reg.MAX_VELOCITY,
        Reg.FINAL_POS_LSB,
        Reg.FINAL_POS_MID,
        Reg.FINAL_POS_MSB,
        Reg.INT_VELOCITY,
    }
)
"""Plain read/write registers: the chip only reads them."""
_MASKS: dict[int, int] = {Reg.ACCEL_MSB: 0x7F, Reg.MAX_VELOCITY: 0x7F}
_STATUS_FIXED = int(Status.STOP_CLEAR | Status.LIMIT_CLEAR)
_STATUS_PROFILE = int(Status.PROFILE)
_STATUS_IDLE = int(Status.INIT_IDLE)


class Mode(enum.Enum):
    """What the chip is doing (program counter state plus control flags)."""

    RESET = "reset"
    INIT_IDLE = "init/idle"
    POSITION = "position"
    PROPORTIONAL_VELOCITY = "proportional velocity"
    INTEGRAL_VELOCITY = "integral velocity"
    TRAPEZOID = "trapezoid"


@dataclass(frozen=True)
class ChipVariant:
    """How this chip differs from the model's reading of the datasheet (all True: as read).

    Real HCTL-1000s were never seen by this project (docs/design.md): the variants are what a
    driver must not take for granted, each proved by a test that fails on a driver that does.
    """

    r13h_clears: bool = True
    """A write to R13H clears the actual position counter (False: the write does nothing)."""
    reset_clears: bool = True
    """The software reset (R05H = 00H) zeroes the actual position counter (False: the reset
    restores every other register and leaves the counter counting)."""


_MOVES = frozenset({Mode.TRAPEZOID, Mode.PROPORTIONAL_VELOCITY, Mode.INTEGRAL_VELOCITY})

# Plain names for the per-sample code: one global lookup each instead of an enum attribute and
# an ``__index__`` call per use.
_POSITION = Mode.POSITION
_RESET = Mode.RESET
_INIT_IDLE = Mode.INIT_IDLE
_R_MOTOR_COMMAND = int(Reg.MOTOR_COMMAND)
_R_FILTER_ZERO = int(Reg.FILTER_ZERO)
_R_FILTER_POLE = int(Reg.FILTER_POLE)
_R_FILTER_GAIN = int(Reg.FILTER_GAIN)
_R_ACT_VEL_LSB = int(Reg.ACT_VEL_LSB)
_R_ACT_VEL_MSB = int(Reg.ACT_VEL_MSB)
_R_CMD_VEL_LSB = int(Reg.CMD_VEL_LSB)
_R_CMD_VEL_MSB = int(Reg.CMD_VEL_MSB)


def _wrap24(value: int) -> int:
    return ((value + 0x80_0000) & 0xFF_FFFF) - 0x80_0000


class _Trapezoid:
    """Setpoints of one trapezoidal (or triangular) move, sampled once per sample period."""

    __slots__ = ("accel", "final", "n_samples", "peak", "sign", "start", "t_accel", "t_cruise")

    def __init__(self, start: int, final: int, accel: float, vmax: int) -> None:
        self.start = start
        self.final = final
        distance = abs(final - start)
        self.sign = 1 if final >= start else -1
        self.accel = accel
        self.peak = 0.0
        self.t_accel = 0.0
        self.t_cruise = 0.0
        if distance == 0:
            self.n_samples: int | None = 1
        elif accel <= 0.0 or vmax <= 0:
            self.n_samples = None  # never progresses
        else:
            ramp = vmax * vmax / (2.0 * accel)
            if 2.0 * ramp >= distance:  # triangle: vmax not reached before halfway
                self.peak = math.sqrt(accel * distance)
            else:
                self.peak = float(vmax)
                self.t_cruise = (distance - 2.0 * ramp) / vmax
            self.t_accel = self.peak / accel
            total = 2.0 * self.t_accel + self.t_cruise
            n = max(1, math.ceil(total - 1e-9))
            while n > 1 and self._along(n - 1) >= distance - 0.5:
                n -= 1  # rounding reaches the final position early: that sample is the last
            self.n_samples = n

    def _along(self, k: float) -> float:
        """Distance covered by the ideal profile after k samples."""
        a, ta, tc = self.accel, self.t_accel, self.t_cruise
        if k <= ta:
            return 0.5 * a * k * k
        if k <= ta + tc:
            return 0.5 * a * ta * ta + self.peak * (k - ta)
        left = max(0.0, 2.0 * ta + tc - k)
        return abs(self.final - self.start) - 0.5 * a * left * left

    def setpoint(self, k: int) -> int:
        """Command position issued at sample k (1-based); the last one is the final position."""
        n = self.n_samples
        if n is None:
            return self.start
        if k >= n:
            return self.final
        # _along(k), written out: this runs once per sample of every move
        a, ta = self.accel, self.t_accel
        if k <= ta:
            along = 0.5 * a * k * k
        elif k <= ta + self.t_cruise:
            along = 0.5 * a * ta * ta + self.peak * (k - ta)
        else:
            along = self._along(k)
        return self.start + self.sign * math.floor(along + 0.5)


class Hctl1000:
    """One HCTL-1000 driving one :class:`MotorPlant`.

    ``clock`` (hardware seconds), when given, makes every bus access first catch the chip up to
    the present; the board passes the simulator clock. ``on_profile_end`` is called once each time
    the chip issues the last setpoint of a trapezoid and clears F0 -- which does not mean the head
    has stopped. ``head_limit`` (counts from true zero) turns on the ``HEAD_BEYOND_LIMIT`` audit
    of the plant's true position; it is a property of the axis's cable, not of the chip, so
    only the pan axis has one. ``variant`` (:class:`ChipVariant`; settable at any time, like a
    chip swapped between runs) says where this chip departs from the datasheet reading.
    """

    def __init__(
        self,
        name: str,
        plant: MotorPlant,
        *,
        audit: Audit | None = None,
        clock: Callable[[], float] | None = None,
        f_clk: float = F_CLK_HZ,
        head_limit: float | None = None,
        variant: ChipVariant = ChipVariant(),  # frozen: sharing the default is harmless
    ) -> None:
        self.name = name
        self.plant = plant
        self.variant = variant
        self._audit = audit
        self._clock = clock
        self._f_clk = float(f_clk)
        self.on_profile_end: Callable[[], None] | None = None
        if head_limit is not None and not head_limit > 0.0:
            raise ValueError("head_limit must be positive")
        self._head_limit = math.inf if head_limit is None else float(head_limit)
        self._head_rearm = min(float(MOTION_LIMIT_COUNTS), self._head_limit)
        # the true head outside (low, high) calls _head_crossed: +-limit while it is inside;
        # while it is out, the side of the envelope it must come back to
        self._head_low, self._head_high = -self._head_limit, self._head_limit
        self._head_out = False
        self._next_sample = clock() if clock is not None else 0.0
        self._regs = bytearray(HCTL_SPACE)
        # the encoder reading at each of the last HISTORY samples, for position_at()
        self._hist_t = [0.0] * HISTORY
        self._hist_a = [0] * HISTORY
        self._hist_n = 0
        self.reset()

    # -- reset and mode bookkeeping --------------------------------------------------------------
    def reset(self, *, keep_counter: bool = False) -> None:
        """Board chip reset: power-up register values, init/idle, actual position counter 0
        (``keep_counter``: the counter goes on counting, as on a chip whose reset does not clear
        it, :attr:`ChipVariant.reset_clears`)."""
        counter: tuple[int, int] | None = (self._act_offset, self._actual) if keep_counter else None
        self._regs[:] = bytes(HCTL_SPACE)
        for reg, value in POWER_UP.items():
            self._regs[reg] = value
        # program-counter state: RESET, INIT_IDLE, or POSITION meaning "control", where the flags
        # choose the mode (see ``mode``)
        self._state = Mode.INIT_IDLE
        self._flags = _F1
        self._cmd = 0
        self._staged = [0, 0]  # R0CH, R0DH until R0EH commits
        if counter is None:
            self._act_offset: int = self.plant.encoder_counts
            self._actual: int = 0
            self._hist_n = 0
        else:
            self._act_offset, self._actual = counter
        self._latch = 0
        self._x_prev = 0
        self._mc_prev = 0
        self._trap: _Trapezoid | None = None
        self._trap_k = 0
        self._iv_velocity = 0.0
        self._iv_position = 0.0
        self._gain_written = False
        self._timer_written = False
        self._timer_changed()
        self._forget_rest()

    def _forget_rest(self) -> None:
        """Anything written may change the dynamics: stop skipping idle periods."""
        self._sig_old: tuple[object, ...] | None = None
        self._sig_new: tuple[object, ...] | None = None
        self._rest_mcs = (0, 0)
        self._quiescent = False
        self._fixed = False
        self._rest_stalled = False

    def _mode_of(self, state: Mode, flags: int) -> Mode:
        if state is not Mode.POSITION:
            return state
        if flags & _F0:
            return Mode.TRAPEZOID
        if flags & _F3:
            return Mode.PROPORTIONAL_VELOCITY
        if flags & _F5:
            return Mode.INTEGRAL_VELOCITY
        return Mode.POSITION

    def _enter(self, old: Mode, new: Mode) -> None:
        """Set the profile generators up for a new mode (no audit here)."""
        if new is old:
            return
        if new in (Mode.INIT_IDLE, Mode.RESET):
            self._flags &= ~_F0
            self._regs[Reg.MOTOR_COMMAND] = 0x80
            self._x_prev = 0
            self._mc_prev = 0
            self._trap = None
        elif new is Mode.TRAPEZOID:
            accel = ((self._regs[Reg.ACCEL_MSB] << 8) | self._regs[Reg.ACCEL_LSB]) / 256.0
            self._trap = _Trapezoid(self._cmd, self.final_position, accel, self.max_velocity)
            self._trap_k = 0
        elif new is Mode.INTEGRAL_VELOCITY:
            self._iv_velocity = 0.0
            self._iv_position = float(self._cmd)
        if old is Mode.TRAPEZOID:
            self._trap = None

    # -- audit -------------------------------------------------------------------------------------
    def _moving(self) -> bool:
        speed = abs(self.plant.velocity_counts_per_s) * self.sample_period
        return speed > MOVING_COUNTS_PER_SAMPLE

    def _record(self, rule: Rule, detail: str, **extra: int) -> None:
        if self._audit is None:
            return
        registers = {
            "FLAG": self._flags,
            "STATUS": self._status(),
            "CMD_POS": self._cmd,
            "ACT_POS": self._actual,
            "FINAL_POS": self.final_position,
            "FILTER_GAIN": self._regs[Reg.FILTER_GAIN],
            "SAMPLE_TIMER": self._regs[Reg.SAMPLE_TIMER],
            "VELOCITY_COUNTS_PER_S": round(self.plant.velocity_counts_per_s),
        }
        registers.update(extra)
        self._audit.record(rule, f"{self.name}: {detail}", **registers)

    def _head_crossed(self, theta: float) -> None:
        """The true head left the window :meth:`step` watches: an excursion begins or ends.

        The window is narrowed to the side the head left by, so that a head hunting around the
        limit, or wound a whole revolution and held there, is one record, not one per sample.
        """
        limit, rearm = self._head_limit, self._head_rearm
        if not self._head_out:  # it was inside: beyond the limit now
            self._head_out = True
            if theta > 0.0:
                self._head_low, self._head_high = rearm, math.inf
            else:
                self._head_low, self._head_high = -math.inf, -rearm
            self._record(
                Rule.HEAD_BEYOND_LIMIT,
                f"the true head is {theta:+.1f} counts from true zero (sample ending at "
                f"t={self._next_sample:.6f} s), beyond +-{limit:g} = 0x{MOTION_LIMIT_COUNTS:X} + "
                f"{limit - MOTION_LIMIT_COUNTS:g} of overshoot, while the counter reads "
                f"{self._actual}: the cable is being wound",
                TRUE_POS=round(theta),
                HEAD_LIMIT=round(limit),
            )
        else:  # back within the envelope: the next excursion is a new one
            self._head_out = False
            self._head_low, self._head_high = -limit, limit

    def _check_start(self, old: Mode, new: Mode) -> None:
        """Audit a mode change caused by the host (R00H or R05H)."""
        if new is old:
            return
        if new in _MOVES and not (self._gain_written and self._timer_written):
            missing = [
                name
                for name, done in (("R22H gain", self._gain_written), ("R0FH", self._timer_written))
                if not done
            ]
            self._record(
                Rule.MOTION_WHILE_UNINITIALISED,
                f"{new.value} started before {' and '.join(missing)} written since reset",
            )
        if new is Mode.TRAPEZOID and abs(self.final_position) > MOTION_LIMIT_COUNTS:
            self._record(
                Rule.MOTOR_BEYOND_LIMIT,
                f"trapezoid to {self.final_position} beyond +-0x{MOTION_LIMIT_COUNTS:X}",
            )

    # -- bus side ----------------------------------------------------------------------------------
    def _sync(self) -> None:
        """Catch up to now before an access, by at most :data:`ACCESS_TICKS` samples: a sample
        timer the host cannot simulate in time would otherwise make every access longer than
        the last, without end (the board's :data:`sim.tech80._ACCESS_TICKS` reasons alike)."""
        if self._clock is not None:
            self.advance_to(self._clock(), ACCESS_TICKS)

    def bus_read(self, reg: int) -> int:
        """One byte as the host reads it; reading R14H latches the actual position."""
        self._sync()
        return self.bus_read_now(reg)

    def bus_read_now(self, reg: int) -> int:
        """:meth:`bus_read` of a chip its caller has just caught up (a board reading several
        bytes in one transaction)."""
        if reg == Reg.ACT_POS_LSB:
            self._latch = self._actual & 0xFF_FFFF
            return self._latch & 0xFF
        if reg == Reg.ACT_POS_MID:
            return (self._latch >> 8) & 0xFF
        if reg == Reg.ACT_POS_MSB:
            return (self._latch >> 16) & 0xFF
        return self.peek(reg)

    def bus_write(self, reg: int, value: int) -> None:
        """One byte as the host writes it, with the chip's side effects and the audit."""
        self._check_reg(reg)
        value &= 0xFF
        self._sync()
        self._forget_rest()
        if reg in _READ_ONLY:
            self._record(
                Rule.WRITE_TO_READ_ONLY,
                f"write of 0x{value:02X} to read-only {Reg(reg).name}",
                REGISTER=reg,
                VALUE=value,
            )
            return
        if reg == Reg.FLAG:
            self._write_flag(value)
        elif reg == Reg.PROGRAM_COUNTER:
            self._write_program_counter(value)
        elif reg == Reg.STATUS:
            self._regs[Reg.STATUS] = value & 0x0F  # only bits 3..0 are writable
        elif reg == Reg.MOTOR_COMMAND:
            if self._state in (Mode.INIT_IDLE, Mode.RESET):
                self._regs[Reg.MOTOR_COMMAND] = value
        elif reg in (Reg.CMD_POS_MSB, Reg.CMD_POS_MID):
            self._staged[reg - Reg.CMD_POS_MSB] = value
        elif reg == Reg.CMD_POS_LSB:
            self._commit_command((self._staged[0] << 16) | (self._staged[1] << 8) | value)
        elif reg == Reg.ACT_POS_MID and self.variant.r13h_clears:
            self._act_offset = self.plant.encoder_counts
            self._actual = 0
            self._hist_n = 0  # the counter's earlier readings are on another zero
        elif reg in _STORED:
            self._regs[reg] = value & _MASKS.get(reg, 0xFF)
            if reg == Reg.FILTER_GAIN:
                self._gain_written = True
            elif reg == Reg.SAMPLE_TIMER:
                self._timer_written = True
                self._timer_changed()

    def _write_flag(self, value: int) -> None:
        number, on = value & 0x07, bool(value & 0x08)
        if number == 1 or number > 5:
            return  # F1 is the chip's; F6/F7 do not exist
        old = self.mode
        if on:
            self._flags |= 1 << number
        else:
            self._flags &= ~(1 << number)
        new = self.mode
        self._check_start(old, new)
        if new is Mode.POSITION and old in _MOVES:
            running = old is Mode.TRAPEZOID
            if running or self._moving():
                why = "a trapezoid was running" if running else "the head was turning"
                self._record(
                    Rule.POSITION_MODE_WHILE_MOVING,
                    f"flag write 0x{value:02X} left {old.value} for position control while {why}",
                )
        self._enter(old, new)

    def _write_program_counter(self, value: int) -> None:
        old = self.mode
        if value == 0x00:
            self.reset(keep_counter=not self.variant.reset_clears)
            self._state = Mode.RESET
            return
        if value == 0x01:
            self._state = Mode.INIT_IDLE
            self._flags |= _F1
        elif value in (0x02, 0x03):
            if self._state is Mode.POSITION:
                return  # already in control: ignored
            if value == 0x02:
                self._flags &= ~_CONTROL_FLAGS
            self._state = Mode.POSITION
            self._flags &= ~_F1
            self._x_prev = 0
            self._mc_prev = 0
        else:
            return
        new = self.mode
        self._check_start(old, new)
        if new is Mode.POSITION and old is not Mode.POSITION:
            if self._moving():
                self._record(
                    Rule.POSITION_MODE_WHILE_MOVING,
                    f"program counter 0x{value:02X} entered position control while the head turned",
                )
            elif abs(_wrap24(self._cmd - self._actual)) > JUMP_COUNTS:
                self._record(
                    Rule.POSITION_MODE_WHILE_MOVING,
                    f"program counter 0x{value:02X} entered position control with the command "
                    f"position {self._cmd} {self._cmd - self._actual} counts from the actual "
                    f"{self._actual}: the head jumps to it",
                )
        self._enter(old, new)

    def _commit_command(self, raw: int) -> None:
        target = to_signed24(raw)
        if abs(target) > MOTION_LIMIT_COUNTS:
            self._record(
                Rule.MOTOR_BEYOND_LIMIT,
                f"command position {target} beyond +-0x{MOTION_LIMIT_COUNTS:X}",
                NEW_CMD_POS=target,
            )
        if (
            self.mode is Mode.POSITION
            and abs(_wrap24(target - self._actual)) > JUMP_COUNTS
            and self._moving()
        ):
            self._record(
                Rule.POSITION_MODE_WHILE_MOVING,
                f"command position {target} committed {target - self._actual} counts away "
                "while the head turned",
                NEW_CMD_POS=target,
            )
        self._cmd = target
        if self.mode is Mode.INTEGRAL_VELOCITY:
            self._iv_position = float(target)

    # -- backdoor --------------------------------------------------------------------------------
    @staticmethod
    def _check_reg(reg: int) -> None:
        if not 0 <= reg < HCTL_SPACE:
            raise ValueError(f"HCTL register 0x{reg:02X} out of range")

    def _status(self) -> int:
        status = _STATUS_FIXED | self._regs[Reg.STATUS]
        if self._flags & _F0:
            status |= _STATUS_PROFILE
        if self._state in (Mode.INIT_IDLE, Mode.RESET):
            status |= _STATUS_IDLE
        return status

    def peek(self, reg: int) -> int:
        """The byte a bus read would return, with no side effect.

        The actual position reads live (as a driver reading R14H, R13H, R12H in order sees it),
        not the latch.
        """
        self._check_reg(reg)
        if reg == Reg.FLAG:
            return self._flags
        if reg == Reg.STATUS:
            return self._status()
        if Reg.CMD_POS_MSB <= reg <= Reg.CMD_POS_LSB:
            return (self._cmd & 0xFF_FFFF) >> (8 * (Reg.CMD_POS_LSB - reg)) & 0xFF
        if Reg.ACT_POS_MSB <= reg <= Reg.ACT_POS_LSB:
            return (self._actual & 0xFF_FFFF) >> (8 * (Reg.ACT_POS_LSB - reg)) & 0xFF
        if reg in _STORED or reg in (Reg.MOTOR_COMMAND, Reg.ACT_VEL_LSB, Reg.ACT_VEL_MSB):
            return self._regs[reg]
        return 0

    def poke(self, reg: int, value: int) -> None:
        """Set a register's content directly: no commit, latch, audit or mode-change side effect.

        Flags poked take effect as the chip's own state (a trapezoid poked on starts from the
        present command position). R05H is not a register: use :meth:`reset` or the bus.
        """
        self._check_reg(reg)
        value &= 0xFF
        self._forget_rest()
        if reg == Reg.FLAG:
            old = self.mode
            self._flags = (value & 0x3F & ~_F1) | (self._flags & _F1)
            self._enter(old, self.mode)
        elif reg == Reg.STATUS:
            self._regs[Reg.STATUS] = value & 0x0F
        elif Reg.CMD_POS_MSB <= reg <= Reg.CMD_POS_LSB:
            self._cmd = to_signed24(_replace_byte(self._cmd, Reg.CMD_POS_LSB - reg, value))
        elif Reg.ACT_POS_MSB <= reg <= Reg.ACT_POS_LSB:
            wanted = to_signed24(_replace_byte(self._actual, Reg.ACT_POS_LSB - reg, value))
            self._act_offset += self._actual - wanted
            self._actual = wanted
            self._hist_n = 0
        elif reg in _STORED or reg in (Reg.MOTOR_COMMAND, Reg.ACT_VEL_LSB, Reg.ACT_VEL_MSB):
            self._regs[reg] = value & _MASKS.get(reg, 0xFF)
            self._timer_changed()
        else:
            raise ValueError(f"HCTL register 0x{reg:02X} has no content to poke")

    @property
    def mode(self) -> Mode:
        return self._mode_of(self._state, self._flags)

    @property
    def flags(self) -> int:
        """F0..F5 as bits 0..5."""
        return self._flags

    @property
    def actual_position(self) -> int:
        """The actual position counter at the last sample (24-bit signed)."""
        return self._actual

    def position_at(self, t: float) -> int:
        """The actual position counter as it read at clock time ``t`` (at or before now).

        A reader that samples the encoder "at" a moment (BIRIS tagging mid-exposure) may run
        late on a busy machine, after a bus access has already carried the chip past that
        moment; reading the counter then would tag the acquisition with a later position. So
        each sample's reading is kept for :data:`HISTORY` samples. A moment older than that, or
        than the last reset or preset of the counter, gets the oldest reading still on the
        counter's present zero.
        """
        self.advance_to(t)
        n = self._hist_n
        times, values = self._hist_t, self._hist_a
        oldest = max(0, n - HISTORY)
        for j in range(n - 1, oldest - 1, -1):
            if times[j & _HIST_MASK] <= t:
                return values[j & _HIST_MASK]
        return values[oldest & _HIST_MASK] if n else self._actual

    @property
    def command_position(self) -> int:
        return self._cmd

    @property
    def final_position(self) -> int:
        r = self._regs
        return to_signed24(
            (r[Reg.FINAL_POS_MSB] << 16) | (r[Reg.FINAL_POS_MID] << 8) | r[Reg.FINAL_POS_LSB]
        )

    @property
    def max_velocity(self) -> int:
        return self._regs[Reg.MAX_VELOCITY]

    @property
    def profile_active(self) -> bool:
        """F0: a trapezoid is being generated (status bit 4)."""
        return bool(self._flags & _F0)

    @property
    def motor_command(self) -> int:
        """R08H as a signed command, -128..127."""
        return self._regs[Reg.MOTOR_COMMAND] - 0x80

    @property
    def filter(self) -> tuple[int, int, int]:
        """(A, B, K): zero, pole, gain."""
        r = self._regs
        return r[Reg.FILTER_ZERO], r[Reg.FILTER_POLE], r[Reg.FILTER_GAIN]

    @property
    def sample_timer(self) -> int:
        return self._regs[Reg.SAMPLE_TIMER]

    @property
    def sample_period(self) -> float:
        """Seconds of the next sample period: 16(T+1)/f_clk."""
        return self._period

    def _timer_changed(self) -> None:
        timer = max(self._regs[Reg.SAMPLE_TIMER], SAMPLE_TIMER_MIN)
        self._period = 16.0 * (timer + 1) / self._f_clk

    @property
    def next_sample_time(self) -> float:
        """Hardware time of the next sample (the chip has simulated everything before it)."""
        return self._next_sample

    def profile_end_eta(self) -> float | None:
        """Hardware time of the sample that will issue the last setpoint, or None.

        None when no profile runs or when it can never end (no acceleration). The shaft plays no
        part: a stalled plant's profile ends on time.
        """
        trap = self._trap
        if trap is None or trap.n_samples is None:
            return None
        if self.mode is not Mode.TRAPEZOID:
            return None
        return self._next_sample + (trap.n_samples - self._trap_k - 1) * self.sample_period

    # -- time --------------------------------------------------------------------------------------
    def advance_to(self, t: float, max_ticks: int | None = None) -> bool:
        """Run every sample due by ``t``; False if ``max_ticks`` cut the catch-up short.

        Periods in which nothing can change are skipped two at a time (the longest cycle the
        truncating filter settles into), which keeps an idle or holding chip almost free. A
        sample left over in a fixed point (the last three samples alike) only steps the plant:
        the chip's registers would come out as they are.
        """
        cap = math.inf if max_ticks is None else max_ticks
        ticks = 0
        step = self.step
        while self._next_sample <= t:
            if ticks >= cap:
                return False
            if self._quiescent and self._still_quiescent():
                period = self._period
                pairs = int((t - self._next_sample) / (2.0 * period))
                if pairs > 0:
                    self._next_sample += 2 * pairs * period
                    continue
                if self._fixed and self.plant.stalled == self._rest_stalled:
                    # A sample in a fixed point recomputes the same registers: only the plant
                    # (the held motor's winding current) and the time move, exactly as step().
                    self.plant.step(self._regs[_R_MOTOR_COMMAND] - 0x80, period)
                    self._next_sample += period
                    ticks += 1
                    continue
            step()
            ticks += 1
        return True

    def _still_quiescent(self) -> bool:
        plant = self.plant
        first, second = self._rest_mcs
        if not plant.holds_at_rest(first):
            return False
        return first == second or plant.holds_at_rest(second)

    def step(self) -> None:
        """One sample period: encoder, profile generator, filter, R08H, then the plant.

        The per-sample path of a busy simulator, so written out in one function with plain
        integer register indices; the arithmetic is the module docstring's, in the same order.
        """
        regs = self._regs
        plant = self.plant
        period = self._period
        prev_actual = self._actual
        actual = ((plant.encoder_counts - self._act_offset + 0x80_0000) & 0xFF_FFFF) - 0x80_0000
        self._actual = actual
        n = self._hist_n
        self._hist_t[n & _HIST_MASK] = self._next_sample
        self._hist_a[n & _HIST_MASK] = actual
        self._hist_n = n + 1
        ended = False
        if self._state is _POSITION:
            flags = self._flags
            if flags & _F3 and not flags & _F0:
                velocity = ((actual - prev_actual + 0x80_0000) & 0xFF_FFFF) - 0x80_0000
                regs[_R_ACT_VEL_LSB] = velocity & 0xFF
                regs[_R_ACT_VEL_MSB] = (velocity >> 8) & 0xFF
                raw = (regs[_R_CMD_VEL_MSB] << 8) | regs[_R_CMD_VEL_LSB]
                command = (raw - 0x10000 if raw & 0x8000 else raw) / 16.0
                mc = int(regs[_R_FILTER_GAIN] * 0.25 * (command - velocity))
                mc = -128 if mc < -128 else (127 if mc > 127 else mc)
                self._cmd = actual
                self._x_prev = 0
                self._mc_prev = mc
            else:
                if flags & _F0:
                    trap = self._trap
                    if trap is not None and trap.n_samples is not None:
                        k = self._trap_k = self._trap_k + 1
                        self._cmd = trap.setpoint(k)
                        if k >= trap.n_samples:
                            self._flags = flags & ~_F0
                            self._trap = None
                            ended = True
                elif flags & _F5:
                    self._integral_velocity()
                # the position filter: MC = (K/4)(X - (A/256) X[n-1]) - (B/256) MC[n-1]
                x = ((self._cmd - actual + 0x80_0000) & 0xFF_FFFF) - 0x80_0000
                mc = int(
                    regs[_R_FILTER_GAIN]
                    * 0.25
                    * (x - regs[_R_FILTER_ZERO] * (1.0 / 256.0) * self._x_prev)
                    - regs[_R_FILTER_POLE] * (1.0 / 256.0) * self._mc_prev
                )
                mc = -128 if mc < -128 else (127 if mc > 127 else mc)
                self._x_prev = x
                self._mc_prev = mc
            if flags & _F2 and mc < 0:
                mc = 0
            regs[_R_MOTOR_COMMAND] = mc + 0x80
        else:
            if self._state is _RESET:
                self._state = _INIT_IDLE
            mc = regs[_R_MOTOR_COMMAND] - 0x80
        plant.step(mc, period)
        self._next_sample += period
        theta = plant.true_azimuth_counts
        if theta < self._head_low or theta > self._head_high:
            self._head_crossed(theta)
        if plant.holds_at_rest(mc):
            self._note_rest(mc)
        elif self._sig_new is not None:
            self._forget_rest()
        if ended and self.on_profile_end is not None:
            self.on_profile_end()

    def _integral_velocity(self) -> None:
        regs = self._regs
        target = regs[Reg.INT_VELOCITY]
        target = target - 0x100 if target & 0x80 else target
        accel = ((regs[Reg.ACCEL_MSB] << 8) | regs[Reg.ACCEL_LSB]) / 256.0
        v = self._iv_velocity
        v = min(float(target), v + accel) if v < target else max(float(target), v - accel)
        self._iv_velocity = v
        self._iv_position += v
        self._cmd = _wrap24(math.floor(self._iv_position + 0.5))

    def _note_rest(self, mc: int) -> None:
        """Remember the state of a still head, to recognise a fixed point or a two-cycle.

        :meth:`step` calls it only while the plant holds at rest under ``mc``.
        """
        trap_k = self._trap_k if self._trap is not None else -1
        sig = (
            self._state,
            self._flags,
            self._cmd,
            self._actual,
            self._x_prev,
            self._mc_prev,
            trap_k,
            self._iv_velocity,
            self._iv_position,
            self._regs[Reg.MOTOR_COMMAND],
        )
        self._quiescent = sig == self._sig_old
        self._fixed = self._quiescent and sig == self._sig_new
        self._rest_stalled = self.plant.stalled
        self._sig_old, self._sig_new = self._sig_new, sig
        self._rest_mcs = (self._rest_mcs[1], mc)


def _replace_byte(value: int, index: int, byte: int) -> int:
    """``value`` (24-bit) with byte ``index`` (0 = LSB) replaced."""
    shift = 8 * index
    return ((value & 0xFF_FFFF) & ~(0xFF << shift)) | (byte << shift)
