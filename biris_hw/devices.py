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

**Checked, not assumed.** No Model 7600 manual survives and the HCTL-1000 is read from the
HCTL-1100's datasheet (docs/registers.md), so what a register write is supposed to have done
is read back wherever a wrong guess would move the head: the counter after an R13H clear
(:meth:`AxisDriver.hold_here`) and after a chip reset (:meth:`MotionBoard.reset_chip`), the
index latch after it is cleared (:meth:`MotionBoard.clear_index`). A board that differs falls
back to the datasheet's own software reset (R05H = 00H) where there is one, and is otherwise
refused with a ``protocol`` HardwareFault naming the register; a command position is only ever
committed from a counter just read, so the head never jumps. The Bit 3 coupler's connection is
checked the way Bit 3's own drivers do before anything crosses it (:meth:`Coupler.check_link`).
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from biris_hw.angles import clamp_counts
from biris_hw.axes.base import (
    SETTLE_HOLD_S,
    SETTLE_LIMIT_S,
    SETTLE_POLL_S,
    AxisSet,
    MotionAxis,
    MotionController,
)
from biris_hw.axes.base import wait_settled as settle_poll
from biris_hw.axes.base import wait_still as still_poll
from biris_hw.bus.base import BusWindow
from biris_hw.errors import FaultKind, HardwareFault
from biris_hw.pan_reference import PanReference
from biris_hw.records import MotorParams
from biris_hw.timebase import HwLock, StopEvent, timebase_of
from regs import biexec
from regs.bit3 import ERROR_MASK, Bit3Reg, LocalCommand, LocalIntControl, LocalStatus
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
    "CLEARED_COUNTS",
    "LEVEL2_PREFETCH",
    "LEVEL2_VECTOR",
    "LEVEL3_PREFETCH",
    "SETTLE_HOLD_S",
    "SETTLE_LIMIT_S",
    "AxisDriver",
    "BirisLink",
    "Coupler",
    "Devices",
    "IndexKind",
    "MotionBoard",
    "coupler_status_text",
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

CLEARED_COUNTS = 2
"""How far from 0 a counter just cleared may read, with the head standing still: an encoder
resting on an edge may flicker by a count. A counter that was not cleared reads where the head
stood, which is further than this unless the head stood there too (and then the difference is
taken into account, not guessed: the callers read the counter back and use what it says)."""


class IndexKind(str, enum.Enum):
    """What the board's INDEX_STATUS shows for an axis's zero index (the target file's
    ``[homing] index``).

    ``LATCH`` (our reading of the Model 7600, the default): set when the head crosses the index,
    cleared by writing 1, so a fast coarse move can be looked at afterwards. ``LEVEL``: the
    index's live level, true only while the encoder is on it (a pulse of ``index_width`` counts
    once per revolution), which homing must poll during a slow sweep
    (:mod:`biris_hw.server.initialiser`)."""

    LATCH = "latch"
    LEVEL = "level"


class MotionBoard:
    """The Model 7600's own registers: end-of-scan interrupt, chip resets, index latches.

    ``drivers`` are the board's two :class:`AxisDriver`\\ s (their latched position reads and
    the datasheet's software reset): with them :meth:`reset_chip` reads each chip's counter back;
    without (a board made over the window alone, as the level-3 routine's may be) it writes
    CHIP_RESET and trusts it. ``index_kind`` and ``index_width`` say what INDEX_STATUS shows
    (:class:`IndexKind`; set from the target file by :meth:`set_index`).
    """

    def __init__(self, window: BusWindow, drivers: Mapping[Axis, AxisDriver] | None = None) -> None:
        self.window = window
        self._drivers = dict(drivers) if drivers is not None else {}
        self.index_kind = IndexKind.LATCH
        self.index_width = 1

    def set_index(self, kind: IndexKind | str, width: int = 1) -> None:
        """Say what INDEX_STATUS shows (:class:`IndexKind`) and, for a live level, how many
        counts it stays asserted. Homing chooses its search from these.

        Raises:
            ValueError: an unknown kind, or a width outside 1..256 counts.
        """
        index_kind = IndexKind(kind)
        if isinstance(width, bool) or not isinstance(width, int) or not 1 <= width <= 256:
            raise ValueError(f"index width must be 1..256 counts, not {width!r}")
        self.index_kind = index_kind
        self.index_width = width

    def reset_chip(self, axis: Axis) -> None:
        """CHIP_RESET for ``axis``, then the chip's counter read back (with its driver, see the
        class notes): a board whose CHIP_RESET left the counter counting gets the datasheet's
        software reset (R05H = 00H) instead, logged as a warning.

        The head must stand still (the initialiser idles it and waits first): a counter read
        while it turns proves nothing.

        Raises:
            HardwareFault: ``protocol``, naming CHIP_RESET and R05H, when neither cleared the
                counter; the chip is left in init/idle and nothing was commanded.
        """
        self.window.write8(BoardReg.CHIP_RESET, _AXIS_BIT[axis])
        driver = self._drivers.get(axis)
        if driver is None:
            return
        counter = driver.actual_position()
        if abs(counter) <= CLEARED_COUNTS:
            return
        log.warning(
            "%s: the counter reads %d after CHIP_RESET (board register 0x%02X): resetting the "
            "chip with the datasheet's software reset (R05H = 00H) instead",
            axis.name.lower(),
            counter,
            int(BoardReg.CHIP_RESET),
        )
        after = driver.software_reset()
        if abs(after) > CLEARED_COUNTS:
            raise HardwareFault(
                "protocol",
                f"{axis.name.lower()}: the actual position counter (R12H..R14H) reads {counter} "
                f"after CHIP_RESET (Model 7600 register 0x{int(BoardReg.CHIP_RESET):02X}) and "
                f"{after} after the datasheet's software reset (R05H = 00H): this board resets "
                f"neither, so the driver cannot tell where the head is; nothing was moved",
            )

    def enable_end_of_scan(self, axis: Axis, vector: int, enabled: bool = True) -> None:
        self.window.write8(BoardReg.IRQ_VECTOR, vector)
        mask = self.window.read8(BoardReg.IRQ_ENABLE)
        mask = mask | _AXIS_BIT[axis] if enabled else mask & ~_AXIS_BIT[axis]
        self.window.write8(BoardReg.IRQ_ENABLE, mask & 0xFF)

    def disable_all(self) -> None:
        self.window.write8(BoardReg.IRQ_ENABLE, 0)

    def index_and_position(self, axis: Axis) -> tuple[bool, int]:
        """INDEX_STATUS for ``axis`` and its counter, read together (one bus transaction where
        the window can): a poll of a live index level, whose count must be known exactly.

        Raises:
            ValueError: a board made without its drivers (see the class notes).
        """
        driver = self._drivers.get(axis)
        if driver is None:
            raise ValueError("this board was made without its axis drivers")
        status, counter = driver.position_with(int(BoardReg.INDEX_STATUS))
        return bool(status & _AXIS_BIT[axis]), counter

    def index_seen(self, axis: Axis) -> bool:
        """INDEX_STATUS for ``axis``: the latch (or, :attr:`IndexKind.LEVEL`, the live level)."""
        return bool(self.window.read8(BoardReg.INDEX_STATUS) & _AXIS_BIT[axis])

    def clear_index(self, axis: Axis, *, check: bool = False) -> None:
        """Clear ``axis``'s index latch (write 1); with ``check``, read it back.

        Checked only where the head cannot stand on the index's edge: there a head at rest
        still dithers a count either way and may set the latch again as it is read, which is no
        fault. The homing search clears and reads back plainly first, and checks only a few
        counts off from where the latch showed again at once
        (:data:`biris_hw.server.initialiser.RECLEAR_STEP_COUNTS`).

        Raises:
            HardwareFault: ``protocol`` (with ``check``), naming INDEX_STATUS, when it still shows
                the index: the board's latch does not clear, or its index is a live level and the
                head stands on it (homing must then be told so: ``[homing] index = "level"``). A
                homing that went on would stop on the first look, at an index that is not there.
        """
        bit = _AXIS_BIT[axis]
        self.window.write8(BoardReg.INDEX_STATUS, bit)
        if check and self.window.read8(BoardReg.INDEX_STATUS) & bit:
            raise HardwareFault(
                "protocol",
                f"{axis.name.lower()}: INDEX_STATUS (Model 7600 register "
                f"0x{int(BoardReg.INDEX_STATUS):02X}) still shows the index after a write of 1 "
                f"cleared it, with the head at rest: the board's index latch does not clear, or "
                f"its index is a live level the head stands on (then say so in the target file: "
                f'[homing] index = "level"); the axis is not homed',
            )

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


class _Reentrant:
    """A time base's lock taken again by the thread that holds it (``threading.RLock`` for a
    :class:`~biris_hw.timebase.HwLock`, which virtual time needs to see every wait)."""

    def __init__(self, lock: HwLock) -> None:
        self._lock = lock
        self._owner: int | None = None
        self._depth = 0

    def __enter__(self) -> _Reentrant:
        me = threading.get_ident()
        if self._owner == me:  # only the holder ever sets it to its own ident
            self._depth += 1
            return self
        self._lock.__enter__()
        self._owner, self._depth = me, 1
        return self

    def __exit__(self, *exc: object) -> None:
        self._depth -= 1
        if self._depth == 0:
            self._owner = None
            self._lock.__exit__(None, None, None)


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
        self._latch = _Reentrant(timebase_of(clock, time_scale).Lock())
        """Held across a latched read (R14H, then R13H and R12H) and, taken first, around a bus
        transaction that reads inside it (:meth:`hold_here`, :meth:`start_trapezoid`): one
        order for the two locks, and reentrant, so a read inside such a transaction takes it
        again (a VM-USB's transaction holds the bridge: the other order deadlocked a mover
        against a notifier)."""
        self._params: MotorParams | None = None
        """The parameters last loaded by :meth:`configure` (what a software reset must reload)."""
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

    def position_with(self, offset: int) -> tuple[int, int]:
        """The byte at board ``offset`` and the actual position, in one bus transaction where the
        window can (the byte first): a board status read at the count it belongs to."""
        base = self._base
        with self._latch:
            byte, lsb, mid, msb = self.window.read_many(
                [
                    (offset, 1),
                    (base + Reg.ACT_POS_LSB, 1),
                    (base + Reg.ACT_POS_MID, 1),
                    (base + Reg.ACT_POS_MSB, 1),
                ]
            )
        return byte[0], pos24_from_msb_first(msb[0], mid[0], lsb[0])

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
        self._params = params
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

    def software_reset(self) -> int:
        """The datasheet's own reset (R05H = 00H), then init/idle (R05H = 01H, so control can
        be entered next whatever the chip does after a reset); returns the counter read back.

        Every register goes back to its power-up value: the caller loads the parameters again
        (:meth:`configure`). Called with the head at rest."""
        with self._latch, self.window.transaction():
            self._wr(Reg.PROGRAM_COUNTER, ProgramCounter.RESET)
            self._wr(Reg.PROGRAM_COUNTER, ProgramCounter.INIT_IDLE)
        return self.actual_position()

    def hold_here(self, zero_counter: bool = False) -> None:
        """Enter position control holding the present position, so nothing jumps.

        Called in init/idle only, with the head at rest: the command position is made equal to
        the counter *as read back* before control starts. With ``zero_counter`` this spot is
        first made the origin: R13H is written (any write clears the counter on the HCTL-1100)
        and the counter read back; one that still counts is cleared by the datasheet's software
        reset instead (logged as a warning; the parameters last configured are loaded again).

        Raises:
            HardwareFault: ``protocol``, naming R13H and R05H, when neither cleared the counter
                (or no parameters were ever configured to reload after the reset): the chip is
                left in init/idle, nothing committed.
        """
        with self._latch, self.window.transaction():
            self._hold_here(zero_counter)

    def _hold_here(self, zero_counter: bool) -> None:
        target = self._zero_counter() if zero_counter else self.actual_position()
        for reg, byte in zip(
            (Reg.CMD_POS_MSB, Reg.CMD_POS_MID, Reg.CMD_POS_LSB),
            pos24_msb_first(target),
            strict=True,
        ):
            self._wr(reg, byte)
        for flag in (Flag.F0_TRAPEZOID, Flag.F3_PROPORTIONAL_VELOCITY, Flag.F5_INTEGRAL_VELOCITY):
            self._wr(Reg.FLAG, flag_write(flag, False))
        self._wr(Reg.PROGRAM_COUNTER, ProgramCounter.CONTROL)

    def _zero_counter(self) -> int:
        """Clear the counter (R13H; the software reset if that did not) and return what it reads
        now: the command position to hold (see :meth:`hold_here`)."""
        before = self.actual_position()
        self._wr(Reg.ACT_POS_MID, 0)  # any write to R13H clears the counter (HCTL-1100)
        after = self.actual_position()
        if abs(after) <= CLEARED_COUNTS:
            return after
        params = self._params
        name = self.axis.name.lower()
        if params is None:
            raise HardwareFault(
                "protocol",
                f"{name}: the actual position counter (R12H..R14H) reads {after} (from "
                f"{before}) after the R13H write that clears it, and no parameters were "
                f"configured to reload after a software reset; nothing was commanded",
            )
        log.warning(
            "%s: the counter reads %d (from %d) after the R13H write that clears it: clearing "
            "it with the datasheet's software reset (R05H = 00H) and loading the parameters "
            "again",
            name,
            after,
            before,
        )
        reset = self.software_reset()
        self.configure(params)
        if abs(reset) <= CLEARED_COUNTS:
            return self.actual_position()
        raise HardwareFault(
            "protocol",
            f"{name}: the actual position counter (R12H..R14H) reads {after} (from {before}) "
            f"after the R13H write that clears it and {reset} after the datasheet's software "
            f"reset (R05H = 00H): this chip clears it neither way, so it cannot be zeroed on "
            f"the index; the axis is left idle, nothing was commanded",
        )

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
        with self._latch, self.window.transaction():
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
        sample_s: float = SETTLE_POLL_S,
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


_STATUS_NAMES = (
    (int(LocalStatus.NO_CONNECT), "NO_CONNECT"),
    (int(LocalStatus.TIMEOUT), "TIMEOUT"),
    (int(LocalStatus.REMOTE_BUS_ERROR), "REMOTE_BUS_ERROR"),
    (int(LocalStatus.PARITY_ERROR), "PARITY_ERROR"),
    (int(LocalStatus.LRC_ERROR), "LRC_ERROR"),
)


def coupler_status_text(status: int) -> str:
    """LOCAL_STATUS as a person reads it: ``0x05 (NO_CONNECT TIMEOUT)``."""
    names = [name for bit, name in _STATUS_NAMES if status & bit]
    return f"0x{status:02X} ({' '.join(names)})" if names else f"0x{status:02X}"


class Coupler:
    """The Bit 3 local node: error interrupts, sticky error bits, the level-2 vector, and the
    connection to the BIRIS crate (NO_CONNECT, TIMEOUT)."""

    def __init__(self, window: BusWindow) -> None:
        self.window = window

    def status(self) -> int:
        return self.window.read8(Bit3Reg.LOCAL_STATUS)

    def clear_errors(self) -> None:
        self.window.write8(Bit3Reg.LOCAL_COMMAND, LocalCommand.CLR_ERROR)

    def check_link(self) -> None:
        """Before anything crosses the coupler, as drivers of the Bit 3 adaptor family start
        (NetBSD's btvmei): LOCAL_STATUS must not show NO_CONNECT; the sticky error bits are
        cleared (CLR_ERROR) and must stay clear. Touches only the coupler's own node, which
        answers whether or not the BIRIS crate has power.

        Raises:
            HardwareFault: ``bus`` when NO_CONNECT is set (the BIRIS crate's power is off or
                the cable is out) or an error bit will not clear; ``parity`` for a parity error
                that will not.
        """
        status = self.status()
        if status & LocalStatus.NO_CONNECT:
            raise HardwareFault(
                "bus",
                f"the Bit 3 coupler is not connected to the BIRIS crate (LOCAL_STATUS "
                f"{coupler_status_text(status)}): its power is off or the cable is out; "
                f"restore it, then reset",
            )
        self.clear_errors()
        status = self.status()
        if status & ERROR_MASK:
            kind: FaultKind = "parity" if status & ERROR_MASK == LocalStatus.PARITY_ERROR else "bus"
            raise HardwareFault(
                kind,
                f"the Bit 3 coupler's error bits do not clear (LOCAL_STATUS "
                f"{coupler_status_text(status)} after CLR_ERROR): check the coupler and its "
                f"cable, then reset",
            )

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
        azimuth = AxisDriver(motion, Axis.AZIMUTH, clock, time_scale, pan_reference)
        elevation = AxisDriver(motion, Axis.ELEVATION, clock, time_scale)
        return cls(
            link=BirisLink(biris, biexec_offset),
            azimuth=azimuth,
            elevation=elevation,
            board=MotionBoard(motion, {Axis.AZIMUTH: azimuth, Axis.ELEVATION: elevation}),
            coupler=Coupler(coupler),
        )

    def axis(self, axis: Axis) -> MotionAxis:
        """The driver of ``axis``."""
        return self.azimuth if axis is Axis.AZIMUTH else self.elevation
