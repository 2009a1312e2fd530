"""The Technology 80 Model 7600 board: two HCTL-1000s, their motors, and the motor interrupt.

The driver sees one byte-wide window (``regs.tech80``): azimuth chip registers at 0x00-0x3F,
elevation at 0x40-0x7F, board registers from 0x80. The board turns the end of a trapezoidal
profile into MOTOR_END_OF_SCAN: the axis's IRQ_STATUS bit is set when its chip clears F0 and, if
that axis is enabled in IRQ_ENABLE at that moment, ``raise_irq()`` is called (the rig wires it to
the level-3 line). The interrupt is edge-like: enabling an axis whose status bit is already set
does not raise it again. INDEX_STATUS shows each plant's index-seen latch (write 1 to clear);
CHIP_RESET resets a chip (write 1); IRQ_LEVEL reads 3 (jumpered); IRQ_STATUS bits are cleared by
writing 1. The azimuth chip also audits the pan head's *true* position after every sample
(``HEAD_BEYOND_LIMIT``, see :mod:`sim.hctl1000`): the cable allows +-0x1000 counts from true zero
plus the filter's overshoot, whatever the chip's counter reads.

Every board register is our reading (no Model 7600 manual survives), so a board can be made to
differ where a driver might otherwise take the reading for granted (:class:`BoardVariant`,
``board.variant``, settable at any time under ``board.lock``): a CHIP_RESET that does nothing,
an INDEX_STATUS that shows the live index level (asserted while the encoder is within
``index_width`` counts past true zero, modulo a revolution; writes are ignored) instead of a
latch, or a latch that a write does not clear. Each chip has variants of its own
(:class:`sim.hctl1000.ChipVariant`, ``board.azimuth.variant``).

Time: both chips are caught up to ``clock.now()`` on every bus access (whole sample periods, each
chip at its own period), and a background thread (:meth:`Model7600.start`) keeps them moving so
that profile ends, and their interrupts, happen on time without any bus access: it waits, through
the clock's time base, until the next expected profile end or for at most the hardware time of
2 ms of real time at the clock's scale (its nominal scale in virtual time), and a bus write that
starts a profile ending sooner wakes it. Everything runs under one ``RLock``, ``board.lock``,
which the driver's :class:`sim.device.DeviceWindow` shares. Backdoor users (fault injection, the
rig's true azimuth) take that lock too, and call :meth:`Model7600.catch_up` before reading a
plant, e.g. ``with board.lock: board.plants[0].stalled = True``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from biris_hw.timebase import HwThread, VirtualTimeDeadlock
from regs.hctl1000 import HCTL_SPACE
from regs.tech80 import MOTION_WINDOW_SIZE, MOTOR_IRQ_LEVEL, AxisBit, BoardReg
from sim.audit import Audit, Rule
from sim.clock import SimClock
from sim.device import DeviceWindow
from sim.hctl1000 import ACCESS_TICKS, HEAD_LIMIT_COUNTS, Hctl1000
from sim.motor import MotorPlant

__all__ = ["INDEX_KINDS", "BoardVariant", "Model7600"]

log = logging.getLogger(__name__)

_AXIS_BITS = (int(AxisBit.AZIMUTH), int(AxisBit.ELEVATION))

INDEX_KINDS = ("latch", "level", "stuck")
"""What INDEX_STATUS shows: a latch set when the head crosses the index and cleared by writing 1
(the reading the driver homes with by default), the index's live level, or a latch that a write
does not clear."""


@dataclass(frozen=True)
class BoardVariant:
    """How this board differs from our reading of it (the defaults: as read)."""

    chip_reset: bool = True
    """A write of 1 to CHIP_RESET resets that axis's chip (False: the register does nothing)."""
    index: Literal["latch", "level", "stuck"] = "latch"
    """See :data:`INDEX_KINDS`."""
    index_width: float = 1.0
    """Counts the index level stays asserted past each multiple of a revolution (``index =
    "level"``): one quadrature count, a gated index."""

    def __post_init__(self) -> None:
        if self.index not in INDEX_KINDS:
            raise ValueError(f"index must be one of {', '.join(INDEX_KINDS)}, not {self.index!r}")
        if not (math.isfinite(self.index_width) and 0.0 < self.index_width < 2048.0):
            raise ValueError(f"index_width must be in (0, 2048) counts, not {self.index_width}")


_POLL_REAL_S = 0.002
"""Shortest sleep of the background thread between catch-ups on scaled time, real seconds (at
x100 and beyond, where :data:`_SCALED_POLL_HW_S` would be shorter)."""
_SCALED_POLL_HW_S = 0.1
"""Longest sleep of the background thread between catch-ups on scaled time, hardware seconds
(the longer of this and :data:`_POLL_REAL_S`): how far behind an idle board's chips fall between
accesses, 70 samples at Appendix B's sample timer, which an access catches up in well under a
millisecond (a chip at rest skips its samples in pairs). A profile end wakes the thread on time
whatever this is. Bounded by 2 ms of real time alone, an idle rig at x10 would wake it 500
times a second (measured: 60 ms of CPU a second for the rig, against 33 ms with this bound)."""
_VIRTUAL_POLL_HW_S = 1.0
"""The same bound on virtual time, in hardware seconds: there the host is never behind, so the
only reason to wake is to keep a catch-up within :data:`_ACCESS_TICKS` (a held chip's samples
count, 5.8 s of them); a profile end still wakes the thread on time. At the scaled bound an idle
board's thread would wake 10 times a hardware second, each a thread hand-over."""
_MIN_SLEEP_REAL_S = 0.00005
"""Shortest sleep towards a profile end in scaled time, real seconds: a wake is no more precise
than the host's scheduling. Nothing in virtual time (``hw_from_real``), where a wake is exact
and a profile end is always after the present."""
_BATCH_TICKS = 256
"""Sample periods per chip simulated before the thread lets a bus access in."""
_ACCESS_TICKS = ACCESS_TICKS
"""Most sample periods per chip one bus access (or backdoor look) simulates to catch up: 5.8 s
of hardware time at Appendix B's sample timer, never reached while the board's thread keeps up.
A sample timer the host cannot simulate in time (0 is 8 us: 1.25 million samples a real second
at x10) leaves the chips ever further behind; an access that caught them up fully would take
longer the further behind they are, and the time it took would put them further behind still,
without end. Capped, the access reads the board as far as it has been simulated, late, and the
rig's lag says so."""


class Model7600:
    """The board model; implements the :class:`sim.device.BusDevice` protocol."""

    def __init__(
        self,
        clock: SimClock,
        rng: np.random.Generator,
        *,
        raise_irq: Callable[[], None],
        audit: Audit | None = None,
        azimuth_plant: MotorPlant | None = None,
        elevation_plant: MotorPlant | None = None,
    ) -> None:
        self.lock = threading.RLock()
        self._clock = clock
        self._raise_irq = raise_irq
        self._audit = audit
        az = azimuth_plant if azimuth_plant is not None else MotorPlant(rng)
        el = elevation_plant if elevation_plant is not None else MotorPlant(rng)
        self.plants: tuple[MotorPlant, MotorPlant] = (az, el)
        # the pan head's cable is audited (HEAD_BEYOND_LIMIT); the tilt's travel is not a cable's
        self.azimuth = Hctl1000(
            "azimuth", az, audit=audit, clock=clock.now, head_limit=HEAD_LIMIT_COUNTS
        )
        self.elevation = Hctl1000("elevation", el, audit=audit, clock=clock.now)
        self.chips: tuple[Hctl1000, Hctl1000] = (self.azimuth, self.elevation)
        for axis, chip in enumerate(self.chips):
            chip.on_profile_end = self._profile_end_handler(axis)
        self._irq_vector = 0
        self._irq_enable = 0
        self._irq_status = 0
        self.variant = BoardVariant()
        """Where this board departs from our reading (module notes); change it under ``lock``."""
        self._tb = clock.timebase
        self._wake = self._tb.Condition(self.lock)
        """The background thread waits on it (releasing ``lock``); stop() and a bus write that
        starts an earlier profile end notify it."""
        self._stopping = False
        self._wake_at = math.inf
        """Hardware time the waiting thread will wake at by itself; inf while it is not waiting
        (guarded by ``lock``)."""
        self._thread: HwThread | None = None

    # -- interrupts ------------------------------------------------------------------------------
    def _profile_end_handler(self, axis: int) -> Callable[[], None]:
        bit = _AXIS_BITS[axis]

        def ended() -> None:
            was_set = self._irq_status & bit
            self._irq_status |= bit
            if not was_set and self._irq_enable & bit:
                self._raise_irq()

        return ended

    @property
    def irq_status(self) -> int:
        """IRQ_STATUS without side effects (backdoor)."""
        return self._irq_status

    # -- time --------------------------------------------------------------------------------------
    def position_at(self, axis: int, t: float) -> int:
        """Axis ``axis``'s actual position counter as it read at clock time ``t`` (see
        :meth:`Hctl1000.position_at`)."""
        with self.lock:
            return self.chips[axis].position_at(t)

    def catch_up(self) -> None:
        """Bring both chips and plants up to now (backdoor readers call it first)."""
        with self.lock:
            self._sync(_ACCESS_TICKS)

    def _sync(self, max_ticks: int | None = None) -> bool:
        """Catch both chips up to now; False if ``max_ticks`` stopped either short."""
        now = self._clock.now()
        done = True
        for chip in self.chips:
            done = chip.advance_to(now, max_ticks) and done
        return done

    def start(self) -> None:
        """Run the background thread that keeps the chips on time between bus accesses."""
        if self._thread is not None:
            return
        with self.lock:
            self._stopping = False
        self._thread = self._tb.Thread(self._run, name="model7600", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop and join the background thread; calling it again does nothing.

        The join is a wait in the time base, so a participant (a virtual-time test's own
        thread) may stop the board.
        """
        thread = self._thread
        if thread is None:
            return
        with self.lock:
            self._stopping = True
            self._wake.notify_all()
        if thread is not threading.current_thread():
            self._tb.join_thread(thread)
        self._thread = None

    def _run(self) -> None:
        clock = self._clock
        tb = self._tb
        poll_hw = (
            _VIRTUAL_POLL_HW_S
            if clock.virtual
            else max(tb.timeout_hw(_POLL_REAL_S), _SCALED_POLL_HW_S)
        )
        floor_hw = tb.hw_from_real(_MIN_SLEEP_REAL_S)
        while True:
            with self.lock:
                if self._stopping:
                    return
                if self._sync(_BATCH_TICKS):
                    now = clock.now()
                    wake = now + poll_hw
                    for chip in self.chips:
                        eta = chip.profile_end_eta()
                        if eta is not None:
                            wake = min(wake, max(eta, now + floor_hw))
                    if not wake > now:  # a wait must move time on, or virtual time stands still
                        wake = math.nextafter(now, math.inf)
                    self._wake_at = wake
                    try:
                        self._wake.wait(
                            clock.timeout_until(wake, now), what="model7600 next profile end"
                        )
                    except VirtualTimeDeadlock:
                        # the domain is dead and the driver was told who waited on what: the
                        # board stops with it rather than raise the same report a second time
                        log.debug("Model 7600 thread stopped by a virtual time deadlock")
                        return
                    finally:
                        self._wake_at = math.inf
                    continue
            time.sleep(0)  # yield, so a waiting bus access gets the lock between batches

    def _wake_for(self, chip: Hctl1000) -> None:
        """After a write to ``chip`` (lock held): wake the background thread if the chip's
        profile now ends before the thread would wake by itself, so its interrupt is on time."""
        eta = chip.profile_end_eta()
        if eta is not None and eta < self._wake_at:
            self._wake.notify()

    # -- bus side ----------------------------------------------------------------------------------
    @staticmethod
    def _check_offset(offset: int) -> None:
        if not 0 <= offset < MOTION_WINDOW_SIZE:
            raise ValueError(f"board offset 0x{offset:X} outside the Model 7600 window")

    def bus_read(self, offset: int) -> int:
        """One byte as the driver reads it (HCTL side effects included)."""
        self._check_offset(offset)
        with self.lock:
            self._sync(_ACCESS_TICKS)
            if offset < 2 * HCTL_SPACE:
                return self.chips[offset // HCTL_SPACE].bus_read(offset % HCTL_SPACE)
            return self._board_read(offset)

    def bus_read_block(self, offsets: Sequence[int]) -> list[int]:
        """The bytes at ``offsets``, in order, as :meth:`bus_read` reads each, in one
        transaction: the chips are caught up once, at its start (a settling poll's six bytes
        are the simulator's commonest access; the microseconds the real transaction takes hold
        no sample in virtual time, and in scaled time at most one that the next poll sees)."""
        for offset in offsets:
            self._check_offset(offset)
        chips = self.chips
        with self.lock:
            self._sync(_ACCESS_TICKS)
            return [
                chips[offset // HCTL_SPACE].bus_read_now(offset % HCTL_SPACE)
                if offset < 2 * HCTL_SPACE
                else self._board_read(offset)
                for offset in offsets
            ]

    def bus_write(self, offset: int, value: int) -> None:
        """One byte as the driver writes it."""
        self._check_offset(offset)
        value &= 0xFF
        with self.lock:
            self._sync(_ACCESS_TICKS)
            if offset < 2 * HCTL_SPACE:
                chip = self.chips[offset // HCTL_SPACE]
                chip.bus_write(offset % HCTL_SPACE, value)
                self._wake_for(chip)
                return
            self._board_write(offset, value)

    def _board_read(self, offset: int) -> int:
        if offset == BoardReg.IRQ_VECTOR:
            return self._irq_vector
        if offset == BoardReg.IRQ_ENABLE:
            return self._irq_enable
        if offset == BoardReg.IRQ_STATUS:
            return self._irq_status
        if offset == BoardReg.INDEX_STATUS:
            seen = zip(_AXIS_BITS, self.plants, strict=True)
            if self.variant.index == "level":
                return sum(bit for bit, plant in seen if self._on_index(plant))
            return sum(bit for bit, plant in seen if plant.index_seen)
        if offset == BoardReg.IRQ_LEVEL:
            return MOTOR_IRQ_LEVEL
        return 0  # CHIP_RESET is write-only; the rest is unmapped

    def _board_write(self, offset: int, value: int) -> None:
        if offset == BoardReg.IRQ_VECTOR:
            self._irq_vector = value
        elif offset == BoardReg.IRQ_ENABLE:
            self._irq_enable = value & 0x03
        elif offset == BoardReg.IRQ_STATUS:
            self._irq_status &= ~value
        elif offset == BoardReg.CHIP_RESET:
            if not self.variant.chip_reset:
                return
            for bit, chip in zip(_AXIS_BITS, self.chips, strict=True):
                if value & bit:
                    chip.reset()
        elif offset == BoardReg.INDEX_STATUS:
            if self.variant.index != "latch":
                return  # a live level, or a latch that does not clear
            for bit, plant in zip(_AXIS_BITS, self.plants, strict=True):
                if value & bit:
                    plant.clear_index()
        elif offset == BoardReg.IRQ_LEVEL and self._audit is not None:
            self._audit.record(
                Rule.WRITE_TO_READ_ONLY,
                f"Model 7600: write of 0x{value:02X} to read-only IRQ_LEVEL",
                REGISTER=offset,
                VALUE=value,
            )

    def _on_index(self, plant: MotorPlant) -> bool:
        """The index's live level: the head within ``index_width`` counts past a multiple of a
        revolution (the plant's true position; the encoder counts from elsewhere)."""
        cpr = plant.params.counts_per_rev
        return plant.true_azimuth_counts % cpr < self.variant.index_width

    # -- backdoor --------------------------------------------------------------------------------
    def window(self) -> DeviceWindow:
        """A bus window over the board, as the driver's ``motion`` window."""
        return DeviceWindow(self, MOTION_WINDOW_SIZE, lock=self.lock)

    def snapshot(self) -> bytes:
        """All window bytes as a driver would read them, without any side effect."""
        with self.lock:
            self._sync(_ACCESS_TICKS)
            out = bytearray(MOTION_WINDOW_SIZE)
            for axis, chip in enumerate(self.chips):
                base = axis * HCTL_SPACE
                for reg in range(HCTL_SPACE):
                    out[base + reg] = chip.peek(reg)
            for offset in range(2 * HCTL_SPACE, MOTION_WINDOW_SIZE):
                out[offset] = self._board_read(offset)
            return bytes(out)
