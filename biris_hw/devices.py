"""One driver object per physical device: BIEXEC_COM, the two HCTL-1000s, the Model 7600, the Bit 3.

Register sequences for the devices the server drives, one small class each, and :class:`Devices`,
the bundle of them that :class:`~biris_hw.hardware.BirisHardware` builds *once* (its ``devices``
field). Everything that touches a device -- the server's workers and notifiers, the initialiser,
``BirisServer.status()`` in a client's thread, the CLI -- goes through that one bundle, so a lock
kept by a driver (the HCTL-1000's latched position read, say) holds across all of them. Two
drivers over the same window would each have their own lock, and their reads could interleave.

The administrator never touches a register. Every access is width-explicit
(``read8``/``write16``...), because the HCTL-1000 latches on reads and BIRIS acts on the COMMAND
write.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from biris_hw.angles import clamp_counts
from biris_hw.axes.base import (
    SETTLE_HOLD_S,
    SETTLE_LIMIT_S,
    AxisSet,
    MotionAxis,
    MotionController,
)
from biris_hw.axes.base import wait_settled as settle_poll
from biris_hw.axes.base import wait_still as still_poll
from biris_hw.bus.base import BusWindow
from biris_hw.errors import HardwareFault
from biris_hw.pan_reference import PanReference
from biris_hw.records import MotorParams
from biris_hw.timebase import StopEvent, timebase_of
from regs import biexec
from regs.bit3 import Bit3Reg, LocalCommand, LocalIntControl
from regs.hctl1000 import (
    Flag,
    ProgramCounter,
    Reg,
    Status,
    flag_write,
    pos24_from_msb_first,
    pos24_lsb_first,
    pos24_msb_first,
)
from regs.tech80 import AXIS_BASE, Axis, AxisBit, BoardReg

__all__ = [
    "LEVEL2_PREFETCH",
    "LEVEL2_VECTOR",
    "LEVEL3_PREFETCH",
    "SETTLE_HOLD_S",
    "SETTLE_LIMIT_S",
    "AxisDriver",
    "BirisLink",
    "Coupler",
    "Devices",
    "MotionBoard",
    "prefetch_reads",
]

log = logging.getLogger(__name__)


LEVEL2_VECTOR = 0x42
"""The vector the driver programs for every level-2 (BIRIS) interrupt; a transport that matches
interrupts by vector (the VM-USB's ISV entries) is told it."""

LEVEL2_PREFETCH = (("coupler", int(Bit3Reg.LOCAL_STATUS), 8), ("biexec", biexec.OFF_COMMAND, 16))
"""What a line that reads registers at interrupt time (a VM-USB IRQ stack) reads for level 2,
in this order: the coupler's LOCAL_STATUS (D8) and COMMAND (D16, at that offset from
BIEXEC_COM in BIRIS memory). :class:`~biris_hw.server.isr.Level2Demux` decides from them."""

LEVEL3_PREFETCH = (("motion", int(BoardReg.IRQ_STATUS), 8),)
"""The same for level 3: the Model 7600's IRQ_STATUS (D8), which
:class:`~biris_hw.server.isr.Level3Demux` decides from."""


def prefetch_reads(
    level: int,
    *,
    biris: BusWindow,
    motion: BusWindow | None,
    coupler: BusWindow,
    biexec_offset: int,
) -> list[tuple[BusWindow, int, int]]:
    """``(window, offset, width_bits)`` of each register the interrupt of ``level`` (2 or 3)
    should read as it is serviced, for lines that can (``VmUsbLine(reads=...)``).

    Raises:
        ValueError: no such level, or level 3 without a ``motion`` window (axes on CAN have no
            board to read: their end of motion comes as CAN frames).
    """
    table = {2: LEVEL2_PREFETCH, 3: LEVEL3_PREFETCH}.get(level)
    if table is None:
        raise ValueError(f"no interrupt level {level} in BIRIS (2 or 3)")
    windows = {"biris": biris, "biexec": biris, "motion": motion, "coupler": coupler}
    reads: list[tuple[BusWindow, int, int]] = []
    for name, offset, width in table:
        window = windows[name]
        if window is None:
            raise ValueError(f"level {level} reads the {name} window, and there is none")
        reads.append((window, offset + (biexec_offset if name == "biexec" else 0), width))
    return reads


_AXIS_BIT = {Axis.AZIMUTH: int(AxisBit.AZIMUTH), Axis.ELEVATION: int(AxisBit.ELEVATION)}


class MotionBoard:
    """The Model 7600's own registers: end-of-scan interrupt, chip resets, index latches."""

    def __init__(self, window: BusWindow) -> None:
        self.window = window

    def reset_chip(self, axis: Axis) -> None:
        self.window.write8(BoardReg.CHIP_RESET, _AXIS_BIT[axis])

    def enable_end_of_scan(self, axis: Axis, vector: int, enabled: bool = True) -> None:
        self.window.write8(BoardReg.IRQ_VECTOR, vector)
        mask = self.window.read8(BoardReg.IRQ_ENABLE)
        mask = mask | _AXIS_BIT[axis] if enabled else mask & ~_AXIS_BIT[axis]
        self.window.write8(BoardReg.IRQ_ENABLE, mask & 0xFF)

    def disable_all(self) -> None:
        self.window.write8(BoardReg.IRQ_ENABLE, 0)

    def index_seen(self, axis: Axis) -> bool:
        return bool(self.window.read8(BoardReg.INDEX_STATUS) & _AXIS_BIT[axis])

    def clear_index(self, axis: Axis) -> None:
        self.window.write8(BoardReg.INDEX_STATUS, _AXIS_BIT[axis])

    def ended_axes(self) -> int:
        """IRQ_STATUS: the axes (AxisBit) whose profile ended and is not acknowledged yet."""
        return self.window.read8(BoardReg.IRQ_STATUS) & (
            int(AxisBit.AZIMUTH) | int(AxisBit.ELEVATION)
        )

    def acknowledge(self, axis: Axis) -> None:
        self.window.write8(BoardReg.IRQ_STATUS, _AXIS_BIT[axis])

    def take_fault(self) -> HardwareFault | None:
        """None: the board has no faults of its own to hold (a failed access raises then)."""
        return None


class AxisDriver:
    """One HCTL-1000 on the board: configure it, start trapezoids, read positions, and tell when
    the motor has come to rest.

    ``clock`` is the hardware clock (seconds) and ``time_scale`` hardware seconds per real
    second: the settling polls are paced in hardware time, as the chip's sample timer is.

    ``reference`` (the pan chip's only) is the bundle's :class:`PanReference`: every move is
    recorded there *before* it is commanded, and cut so that the head stays within +-0x1000 of
    TRUE zero; every settle position and parameter load is reported too, so that a reset or a
    restarted driver knows where the head is and whether the chip kept its count.
    """

    def __init__(
        self,
        window: BusWindow,
        axis: Axis,
        clock: Callable[[], float] = time.monotonic,
        time_scale: float = 1.0,
        reference: PanReference | None = None,
    ) -> None:
        self.window = window
        self.axis = axis
        self.reference = reference
        self._base = AXIS_BASE[axis]
        self._clock = clock
        self._scale = time_scale
        self._latch = timebase_of(clock, time_scale).Lock()  # held across reads: TimeBase.Lock
        self._prepared: tuple[int, int] | None = None
        """(start, destination) recorded ahead by :meth:`prepare_trapezoid`, until started."""
        """A position is three byte reads that must not interleave with another thread's: the
        R14H read latches R13H/R12H, and a second latch between them would mix two readings.
        The parameter block is written and read back under it too, so a reader never sees half
        of a BIRIS_MOTOR_PARAMS load. One lock per chip, because :class:`Devices` makes one
        driver per chip."""

    def _wr(self, reg: int, value: int) -> None:
        self.window.write8(self._base + reg, value & 0xFF)

    def _rd(self, reg: int) -> int:
        return self.window.read8(self._base + reg)

    # -- state -------------------------------------------------------------------------------
    def status(self) -> int:
        return self._rd(Reg.STATUS)

    def profile_active(self) -> bool:
        """F0 as the chip reports it; clear does not mean the motor has stopped."""
        return bool(self.status() & Status.PROFILE)

    def actual_position(self) -> int:
        """Counts; R14H is read first because that read latches R13H and R12H."""
        base = self._base
        with self._latch:  # one bus transaction where the window can (a VM-USB list)
            lsb, mid, msb = self.window.read_many(
                [
                    (base + Reg.ACT_POS_LSB, 1),
                    (base + Reg.ACT_POS_MID, 1),
                    (base + Reg.ACT_POS_MSB, 1),
                ]
            )
        return pos24_from_msb_first(msb[0], mid[0], lsb[0])

    def positions(self) -> tuple[int, int]:
        """(actual, command) in one bus transaction where the window can: what a settling poll
        compares."""
        base = self._base
        with self._latch:
            lsb, mid, msb, cmd_msb, cmd_mid, cmd_lsb = self.window.read_many(
                [
                    (base + Reg.ACT_POS_LSB, 1),
                    (base + Reg.ACT_POS_MID, 1),
                    (base + Reg.ACT_POS_MSB, 1),
                    (base + Reg.CMD_POS_MSB, 1),
                    (base + Reg.CMD_POS_MID, 1),
                    (base + Reg.CMD_POS_LSB, 1),
                ]
            )
        return (
            pos24_from_msb_first(msb[0], mid[0], lsb[0]),
            pos24_from_msb_first(cmd_msb[0], cmd_mid[0], cmd_lsb[0]),
        )

    def command_position(self) -> int:
        base = self._base
        with self._latch:
            msb, mid, lsb = self.window.read_many(
                [
                    (base + Reg.CMD_POS_MSB, 1),
                    (base + Reg.CMD_POS_MID, 1),
                    (base + Reg.CMD_POS_LSB, 1),
                ]
            )
        return pos24_from_msb_first(msb[0], mid[0], lsb[0])

    # -- configuration -------------------------------------------------------------------------
    def configure(self, params: MotorParams) -> None:
        """Sample timer, filter and profile limits: BIRIS_MOTOR_PARAMS' six values.

        The pan chip's values are read back and reported to the reference: a chip that still
        holds them later has not been reset or power-cycled, so its count is still good.
        """
        with self._latch, self.window.transaction():
            self._wr(Reg.SAMPLE_TIMER, params.sample)
            self._wr(Reg.FILTER_ZERO, params.zero)
            self._wr(Reg.FILTER_POLE, params.pole)
            self._wr(Reg.FILTER_GAIN, params.gain)
            self._wr(Reg.MAX_VELOCITY, params.max_vel)
            self._wr(Reg.ACCEL_LSB, params.max_accel & 0xFF)
            self._wr(Reg.ACCEL_MSB, (params.max_accel >> 8) & 0x7F)
            held = self._read_params() if self.reference is not None else {}
        if self.reference is not None:
            self.reference.configured(held)

    def read_params(self) -> dict[str, int]:
        """The six parameters as the chip holds them now, in Appendix B's order (the keys of
        :meth:`MotorParams.to_dict`). Plain reads: none of these registers latches or clears.

        Raw register values, not a :class:`MotorParams`: a chip that did not take the writes may
        hold values no record would accept, and showing them is the point.
        """
        with self._latch:
            return self._read_params()

    def _read_params(self) -> dict[str, int]:
        return {
            "sample": self._rd(Reg.SAMPLE_TIMER),
            "zero": self._rd(Reg.FILTER_ZERO),
            "pole": self._rd(Reg.FILTER_POLE),
            "gain": self._rd(Reg.FILTER_GAIN),
            "max_vel": self._rd(Reg.MAX_VELOCITY),
            "max_accel": (self._rd(Reg.ACCEL_MSB) << 8) | self._rd(Reg.ACCEL_LSB),
        }

    def idle(self) -> None:
        """Init/idle: motor command held at zero, filter history cleared."""
        self._wr(Reg.PROGRAM_COUNTER, ProgramCounter.INIT_IDLE)

    def hold_here(self, zero_counter: bool = False) -> None:
        """Enter position control holding the present position, so nothing jumps.

        Called in init/idle only: the command position is made equal to the actual one (or both
        zeroed, when ``zero_counter`` defines this spot as the origin) before control starts.
        """
        with self.window.transaction():
            self._hold_here(zero_counter)

    def _hold_here(self, zero_counter: bool) -> None:
        if zero_counter:
            self._wr(Reg.ACT_POS_MID, 0)  # any write to R13H clears the counter
            target = 0
        else:
            target = self.actual_position()
        for reg, byte in zip(
            (Reg.CMD_POS_MSB, Reg.CMD_POS_MID, Reg.CMD_POS_LSB),
            pos24_msb_first(target),
            strict=True,
        ):
            self._wr(reg, byte)
        for flag in (Flag.F0_TRAPEZOID, Flag.F3_PROPORTIONAL_VELOCITY, Flag.F5_INTEGRAL_VELOCITY):
            self._wr(Reg.FLAG, flag_write(flag, False))
        self._wr(Reg.PROGRAM_COUNTER, ProgramCounter.CONTROL)

    def prepare_trapezoid(self, destination: int) -> None:
        """Record the move :meth:`start_trapezoid` of ``destination`` will make in the pan
        reference's journal now (a durable file write, which can take milliseconds), so that
        the start itself is only the chip's registers. Nothing on the tilt."""
        if self.reference is None:
            return
        dest = self.reference.safe_destination(clamp_counts(destination))
        start = self.command_position()
        self.reference.record_move(start, dest)
        self._prepared = (start, dest)

    def start_trapezoid(self, destination: int) -> int:
        """Start a trapezoidal move from the present command position; returns the destination.

        The destination is clamped to +-0x1000 here as well as in the server: the motor must never
        be commanded beyond +-360 degrees whatever reaches this layer. On the pan, that is
        +-0x1000 of TRUE zero too (the reference's cut, which differs from the counter's own
        only while the counter is not yet referenced, during initialisation), and the move is
        recorded before F0 starts it: a driver that dies mid-move leaves its span behind.
        """
        with self.window.transaction():
            return self._start_trapezoid(destination)

    def _start_trapezoid(self, destination: int) -> int:
        dest = clamp_counts(destination)
        if self.reference is not None:
            dest = self.reference.safe_destination(dest)
        if dest != destination:
            log.warning("destination %d clamped to %d", destination, dest)
        if self.profile_active():
            # the previous move never ended: the motor's fault, not BIRIS's
            raise HardwareFault("motor_stall", f"axis {self.axis.name}: profile already running")
        prepared, self._prepared = self._prepared, None
        if self.reference is not None and (prepared is None or prepared[1] != dest):
            # unless recorded ahead (the command position cannot change while the chip holds
            # the head: what was recorded then is this move)
            self.reference.record_move(self.command_position(), dest)
        for reg, byte in zip(
            (Reg.FINAL_POS_LSB, Reg.FINAL_POS_MID, Reg.FINAL_POS_MSB),
            pos24_lsb_first(dest),
            strict=True,
        ):
            self._wr(reg, byte)
        self._wr(Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, True))
        return dest

    # -- waiting for the motor -------------------------------------------------------------------
    def wait_settled(
        self,
        stop: StopEvent,
        limit_s: float = SETTLE_LIMIT_S,
        sample_s: float = 0.0015,
    ) -> bool:
        """Poll until the actual position equals the command position and holds there
        (:func:`biris_hw.axes.base.wait_settled`: held for at least 3 polls and SETTLE_HOLD_S
        of hardware time, bounded by ``limit_s``, a still head watched a little past it); both
        positions are read in one bus transaction per poll. False if not settled, or if
        ``stop`` is set; the settle position goes to the pan reference."""
        pos = settle_poll(self.positions, self._clock, self._scale, stop, limit_s, sample_s)
        if pos is None:
            return False
        if self.reference is not None:
            self.reference.settled(pos)
        return True

    def wait_still(self, stop: StopEvent, limit_s: float = 2.0, sample_s: float = 0.002) -> None:
        """Poll until the encoder stops changing (:func:`biris_hw.axes.base.wait_still`): after
        a chip reset the motor coasts, and nothing is commanded to compare it with."""
        still_poll(self.actual_position, self._clock, self._scale, stop, limit_s, sample_s)


class Coupler:
    """The Bit 3 local node: error interrupts, sticky error bits, the level-2 vector."""

    def __init__(self, window: BusWindow) -> None:
        self.window = window

    def status(self) -> int:
        return self.window.read8(Bit3Reg.LOCAL_STATUS)

    def clear_errors(self) -> None:
        self.window.write8(Bit3Reg.LOCAL_COMMAND, LocalCommand.CLR_ERROR)

    def enable_interrupts(self, vector: int) -> None:
        self.window.write8(Bit3Reg.LEVEL2_VECTOR, vector)
        self.window.write8(
            Bit3Reg.LOCAL_INT_CONTROL,
            LocalIntControl.NORMAL_INT_ENABLE | LocalIntControl.ERROR_INT_ENABLE | 2,
        )

    def disable_interrupts(self) -> None:
        self.window.write8(Bit3Reg.LOCAL_INT_CONTROL, 0)


class BirisLink:
    """BIEXEC_COM through the coupler: PARAM, COMMAND, STATUS, ACQ_LINE and the three flags."""

    def __init__(self, window: BusWindow, biexec_offset: int) -> None:
        self.window = window
        self.base = biexec_offset

    def issue(self, code: int, param: str) -> None:
        """Copy the parameter string to PARAM, then write COMMAND (in that order: BIRIS acts on
        the COMMAND write)."""
        with self.window.transaction():
            self.window.write(self.base + biexec.OFF_PARAM, biexec.encode_param(param))
            self.window.write16(self.base + biexec.OFF_COMMAND, code)

    def command(self) -> int:
        return _s16(self.window.read16(self.base + biexec.OFF_COMMAND))

    def status(self) -> int:
        return _s16(self.window.read16(self.base + biexec.OFF_STATUS))

    def acq_line(self) -> int:
        return _s16(self.window.read16(self.base + biexec.OFF_ACQ_LINE))

    def param_raw(self) -> bytes:
        return self.window.read(self.base + biexec.OFF_PARAM, biexec.BIEXEC_PARAM_SIZE)

    def set_flags(
        self,
        *,
        cmd_int: bool | None = None,
        data_int: bool | None = None,
        motor_access: bool | None = None,
    ) -> None:
        for offset, value in (
            (biexec.OFF_CMD_INT_ENABLE, cmd_int),
            (biexec.OFF_DATA_INT_ENABLE, data_int),
            (biexec.OFF_MOTOR_ACCESS, motor_access),
        ):
            if value is not None:
                self.window.write16(self.base + offset, 1 if value else 0)


def _s16(raw: int) -> int:
    return raw - 0x10000 if raw & 0x8000 else raw


@dataclass(frozen=True, eq=False)
class Devices:
    """The one driver object of each physical device, shared by every thread that touches it.

    Built once per hardware bundle (``BirisHardware.devices``); nothing else constructs the
    drivers, so a driver's lock is the device's lock.
    """

    link: BirisLink
    """BIEXEC_COM in BIRIS memory, through the coupler."""
    azimuth: MotionAxis
    """The pan axis: the HCTL-1000 at axis 0 of the Model 7600, or an axis set's pan."""
    elevation: MotionAxis
    """The tilt axis: the HCTL-1000 at axis 1, or an axis set's tilt."""
    board: MotionController
    """The Model 7600's own registers, or the axis set's controller."""
    coupler: Coupler
    """The Bit 3 local node."""

    @classmethod
    def over(
        cls,
        *,
        biris: BusWindow,
        biexec_offset: int,
        motion: BusWindow | None,
        coupler: BusWindow,
        clock: Callable[[], float],
        time_scale: float,
        pan_reference: PanReference | None = None,
        axes: AxisSet | None = None,
    ) -> Devices:
        """One driver per device over these windows. Touches no register. The pan driver
        reports to ``pan_reference`` (the bundle's).

        With ``axes`` the axes and their controller are that set's (CiA 402 drives, say) and
        ``motion`` is not used; without, they are the Model 7600's on ``motion``.

        Raises:
            ValueError: neither ``axes`` nor a ``motion`` window.
        """
        if axes is not None:
            if pan_reference is not None:
                axes.use_pan_reference(pan_reference)
            return cls(
                link=BirisLink(biris, biexec_offset),
                azimuth=axes.azimuth,
                elevation=axes.elevation,
                board=axes.controller,
                coupler=Coupler(coupler),
            )
        if motion is None:
            raise ValueError("no motion window and no axis set: the axes cannot be driven")
        return cls(
            link=BirisLink(biris, biexec_offset),
            azimuth=AxisDriver(motion, Axis.AZIMUTH, clock, time_scale, pan_reference),
            elevation=AxisDriver(motion, Axis.ELEVATION, clock, time_scale),
            board=MotionBoard(motion),
            coupler=Coupler(coupler),
        )

    def axis(self, axis: Axis) -> MotionAxis:
        """The driver of ``axis``."""
        return self.azimuth if axis is Axis.AZIMUTH else self.elevation
