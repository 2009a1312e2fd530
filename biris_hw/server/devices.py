"""Register sequences for the three devices the server drives, one small class each.

Only workers, notifiers and the initialiser use these; the administrator never touches a
register. Every access is width-explicit (``read8``/``write16``...), because the HCTL-1000 latches
on reads and BIRIS acts on the COMMAND write.
"""

from __future__ import annotations

import logging
import threading

from biris_hw.angles import clamp_counts
from biris_hw.bus.base import BusWindow
from biris_hw.errors import HardwareFault
from biris_hw.records import MotorParams
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

__all__ = ["AxisDriver", "BirisLink", "Coupler", "MotionBoard"]

log = logging.getLogger(__name__)

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

    def acknowledge(self, axis: Axis) -> None:
        self.window.write8(BoardReg.IRQ_STATUS, _AXIS_BIT[axis])


class AxisDriver:
    """One HCTL-1000 on the board: configure it, start trapezoids, read positions."""

    def __init__(self, window: BusWindow, axis: Axis) -> None:
        self.window = window
        self.axis = axis
        self._base = AXIS_BASE[axis]
        self._latch = threading.Lock()
        """A position is three byte reads that must not interleave with another thread's: the
        R14H read latches R13H/R12H, and a second latch between them would mix two readings."""

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
        with self._latch:
            lsb = self._rd(Reg.ACT_POS_LSB)
            mid = self._rd(Reg.ACT_POS_MID)
            msb = self._rd(Reg.ACT_POS_MSB)
        return pos24_from_msb_first(msb, mid, lsb)

    def command_position(self) -> int:
        with self._latch:
            return pos24_from_msb_first(
                self._rd(Reg.CMD_POS_MSB), self._rd(Reg.CMD_POS_MID), self._rd(Reg.CMD_POS_LSB)
            )

    # -- configuration -------------------------------------------------------------------------
    def configure(self, params: MotorParams) -> None:
        """Sample timer, filter and profile limits: BIRIS_MOTOR_PARAMS' six values."""
        self._wr(Reg.SAMPLE_TIMER, params.sample)
        self._wr(Reg.FILTER_ZERO, params.zero)
        self._wr(Reg.FILTER_POLE, params.pole)
        self._wr(Reg.FILTER_GAIN, params.gain)
        self._wr(Reg.MAX_VELOCITY, params.max_vel)
        self._wr(Reg.ACCEL_LSB, params.max_accel & 0xFF)
        self._wr(Reg.ACCEL_MSB, (params.max_accel >> 8) & 0x7F)

    def idle(self) -> None:
        """Init/idle: motor command held at zero, filter history cleared."""
        self._wr(Reg.PROGRAM_COUNTER, ProgramCounter.INIT_IDLE)

    def hold_here(self, zero_counter: bool = False) -> None:
        """Enter position control holding the present position, so nothing jumps.

        Called in init/idle only: the command position is made equal to the actual one (or both
        zeroed, when ``zero_counter`` defines this spot as the origin) before control starts.
        """
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

    def start_trapezoid(self, destination: int) -> int:
        """Start a trapezoidal move from the present command position; returns the destination.

        The destination is clamped to +-0x1000 here as well as in the server: the motor must never
        be commanded beyond +-360 degrees whatever reaches this layer.
        """
        dest = clamp_counts(destination)
        if dest != destination:
            log.warning("destination %d clamped to %d", destination, dest)
        if self.profile_active():
            raise HardwareFault("protocol", f"axis {self.axis.name}: profile already running")
        for reg, byte in zip(
            (Reg.FINAL_POS_LSB, Reg.FINAL_POS_MID, Reg.FINAL_POS_MSB),
            pos24_lsb_first(dest),
            strict=True,
        ):
            self._wr(reg, byte)
        self._wr(Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, True))
        return dest


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
        self.window.write(self.base + biexec.OFF_PARAM, biexec.encode_param(param))
        self.window.write16(self.base + biexec.OFF_COMMAND, code)

    def command(self) -> int:
        return _s16(self.window.read16(self.base + biexec.OFF_COMMAND))

    def status(self) -> int:
        return _s16(self.window.read16(self.base + biexec.OFF_STATUS))

    def acq_line(self) -> int:
        return _s16(self.window.read16(self.base + biexec.OFF_ACQ_LINE))

    def current_frame(self) -> int:
        return _s16(self.window.read16(self.base + biexec.OFF_CURRENT_FRAME))

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
