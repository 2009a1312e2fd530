"""The Model 7600 board: axis offsets, board registers, interrupts, lazy and threaded time."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from biris_hw.bus.base import BusWindow
from biris_hw.timebase import VirtualTime
from regs.hctl1000 import (
    Flag,
    ProgramCounter,
    Reg,
    Status,
    flag_write,
    pos24_lsb_first,
    pos24_msb_first,
    sample_period,
)
from regs.tech80 import AXIS_BASE, MOTION_WINDOW_SIZE, Axis, AxisBit, BoardReg
from sim.audit import Audit, Rule
from sim.clock import SimClock
from sim.hctl1000 import POWER_UP, Mode
from sim.motor import MotorPlant
from sim.tech80 import Model7600

PERIOD_B = sample_period(0xAF)


class ManualClock(SimClock):
    """A clock that only moves when the test says so."""

    def __init__(self) -> None:
        super().__init__(1.0)
        self.t = 0.0

    def now(self) -> float:
        return self.t


class Rig:
    """A board, its motion window, and a record of every raise_irq (hardware time)."""

    def __init__(
        self,
        clock: SimClock,
        seed: int = 5,
        azimuth_plant: MotorPlant | None = None,
        elevation_plant: MotorPlant | None = None,
    ) -> None:
        self.clock = clock
        self.raised: list[float] = []
        # the clock's time base's event: on virtual time a test waits for it in the domain
        self.irq = clock.timebase.Event()
        self.audit = Audit(clock.now)
        self.board = Model7600(
            clock,
            np.random.default_rng(seed),
            raise_irq=self._raise,
            audit=self.audit,
            azimuth_plant=azimuth_plant,
            elevation_plant=elevation_plant,
        )
        self.win: BusWindow = self.board.window()

    @property
    def hand(self) -> ManualClock:
        """The clock, when the test moves it by hand."""
        assert isinstance(self.clock, ManualClock)
        return self.clock

    def _raise(self) -> None:
        self.raised.append(self.clock.now())
        self.irq.set()

    def wr(self, axis: Axis, reg: int, value: int) -> None:
        self.win.write8(AXIS_BASE[axis] + reg, value)

    def rd(self, axis: Axis, reg: int) -> int:
        return self.win.read8(AXIS_BASE[axis] + reg)

    def actual(self, axis: Axis) -> int:
        lsb = self.rd(axis, Reg.ACT_POS_LSB)
        mid = self.rd(axis, Reg.ACT_POS_MID)
        msb = self.rd(axis, Reg.ACT_POS_MSB)
        raw = (msb << 16) | (mid << 8) | lsb
        return raw - (1 << 24) if raw & 0x80_0000 else raw

    def initialise(self, axis: Axis) -> None:
        """Appendix B parameters, then hold the present position in position control."""
        for reg, value in (
            (Reg.SAMPLE_TIMER, 0xAF),
            (Reg.FILTER_ZERO, 0x7F),
            (Reg.FILTER_POLE, 0xEF),
            (Reg.FILTER_GAIN, 0x3F),
            (Reg.MAX_VELOCITY, 2),
            (Reg.ACCEL_LSB, 0x22),
            (Reg.ACCEL_MSB, 0x33),
        ):
            self.wr(axis, reg, value)
        here = self.actual(axis)
        for reg, byte in zip(
            (Reg.CMD_POS_MSB, Reg.CMD_POS_MID, Reg.CMD_POS_LSB), pos24_msb_first(here), strict=True
        ):
            self.wr(axis, reg, byte)
        self.wr(axis, Reg.PROGRAM_COUNTER, ProgramCounter.CONTROL)

    def start_move(self, axis: Axis, final: int) -> float:
        """Start a trapezoid; a hardware time at or before the one at which F0 was written.

        Read before the write, not after: on a loaded machine this thread may be preempted between
        the write and a later clock read, which would make the profile look shorter than it was.
        """
        for reg, byte in zip(
            (Reg.FINAL_POS_LSB, Reg.FINAL_POS_MID, Reg.FINAL_POS_MSB),
            pos24_lsb_first(final),
            strict=True,
        ):
            self.wr(axis, reg, byte)
        written = self.clock.now()
        self.wr(axis, Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, True))
        return written


@pytest.fixture
def manual() -> Iterator[Rig]:
    rig = Rig(ManualClock())
    yield rig
    rig.win.close()


# -- layout and board registers ------------------------------------------------------------------
def test_axis_register_files_sit_at_their_offsets(manual: Rig) -> None:
    manual.win.write8(0x22, 0x11)
    manual.win.write8(0x40 + 0x22, 0x33)
    assert manual.board.azimuth.filter[2] == 0x11
    assert manual.board.elevation.filter[2] == 0x33
    assert manual.win.read8(0x40 + Reg.STATUS) == 0xE0
    assert manual.board.plants == (manual.board.azimuth.plant, manual.board.elevation.plant)
    assert manual.win.size == MOTION_WINDOW_SIZE


def test_board_registers(manual: Rig) -> None:
    win = manual.win
    assert win.read8(BoardReg.IRQ_LEVEL) == 3
    win.write8(BoardReg.IRQ_LEVEL, 5)
    assert win.read8(BoardReg.IRQ_LEVEL) == 3
    assert [v.rule for v in manual.audit.violations] == [Rule.WRITE_TO_READ_ONLY]
    win.write8(BoardReg.IRQ_VECTOR, 0x70)
    assert win.read8(BoardReg.IRQ_VECTOR) == 0x70
    win.write8(BoardReg.IRQ_ENABLE, 0xFF)
    assert win.read8(BoardReg.IRQ_ENABLE) == 0x03
    assert win.read8(0x90) == 0  # unmapped
    with pytest.raises(ValueError):
        manual.board.bus_read(MOTION_WINDOW_SIZE)


def test_profile_end_raises_only_when_enabled_and_acknowledge_clears(manual: Rig) -> None:
    for axis in Axis:
        manual.initialise(axis)
    manual.win.write8(BoardReg.IRQ_ENABLE, AxisBit.AZIMUTH)
    manual.start_move(Axis.AZIMUTH, 100)
    manual.hand.t = 0.060  # 100 counts at 2 counts/sample: 50 samples, 70 ms
    assert manual.win.read8(BoardReg.IRQ_STATUS) == 0
    manual.hand.t = 0.080
    assert manual.win.read8(BoardReg.IRQ_STATUS) == AxisBit.AZIMUTH  # the read caught it up
    assert len(manual.raised) == 1
    manual.win.write8(BoardReg.IRQ_STATUS, AxisBit.AZIMUTH)
    assert manual.win.read8(BoardReg.IRQ_STATUS) == 0

    manual.start_move(Axis.ELEVATION, -100)  # elevation is not enabled
    manual.hand.t = 0.5
    assert manual.win.read8(BoardReg.IRQ_STATUS) == AxisBit.ELEVATION
    assert len(manual.raised) == 1
    manual.win.write8(BoardReg.IRQ_ENABLE, AxisBit.AZIMUTH | AxisBit.ELEVATION)
    assert len(manual.raised) == 1  # enabling a pending bit raises nothing (edge)

    manual.start_move(Axis.AZIMUTH, 0)  # status still set for elevation only
    manual.hand.t = 1.0
    assert manual.win.read8(BoardReg.IRQ_STATUS) == AxisBit.AZIMUTH | AxisBit.ELEVATION
    assert len(manual.raised) == 2
    manual.start_move(Axis.AZIMUTH, 100)  # ends while its bit is still pending: no new edge
    manual.hand.t = 1.5
    assert manual.board.irq_status == AxisBit.AZIMUTH | AxisBit.ELEVATION
    assert len(manual.raised) == 2
    assert manual.audit.violations == []


def test_chip_reset_resets_only_the_chosen_axis(manual: Rig) -> None:
    for axis in Axis:
        manual.initialise(axis)
    manual.win.write8(BoardReg.CHIP_RESET, AxisBit.AZIMUTH)
    assert manual.board.azimuth.mode is Mode.INIT_IDLE
    assert manual.board.azimuth.filter[2] == POWER_UP[Reg.FILTER_GAIN]
    assert manual.board.elevation.mode is Mode.POSITION
    assert manual.board.elevation.filter[2] == 0x3F
    assert manual.win.read8(BoardReg.CHIP_RESET) == 0


def test_index_status_follows_the_plants_and_clears() -> None:
    rng = np.random.default_rng(0)
    rig = Rig(
        ManualClock(),
        azimuth_plant=MotorPlant(rng, initial_azimuth_counts=-3.5),
        elevation_plant=MotorPlant(rng, initial_azimuth_counts=500.5),
    )
    assert rig.win.read8(BoardReg.INDEX_STATUS) == 0
    for axis in Axis:
        rig.wr(axis, Reg.MOTOR_COMMAND, 0x90)  # open loop in init/idle: creep forwards
    rig.hand.t = 0.2
    assert rig.win.read8(BoardReg.INDEX_STATUS) == AxisBit.AZIMUTH  # elevation is far from 0
    assert rig.board.plants[0].true_azimuth_counts > 0.0
    assert rig.board.plants[1].true_azimuth_counts > 510.0  # it moved too, without crossing
    rig.win.write8(BoardReg.INDEX_STATUS, AxisBit.AZIMUTH)
    assert rig.win.read8(BoardReg.INDEX_STATUS) == 0
    rig.win.close()


def test_snapshot_reads_everything_without_side_effects(manual: Rig) -> None:
    manual.wr(Axis.AZIMUTH, Reg.MOTOR_COMMAND, 0xC0)
    manual.hand.t = 0.05
    latched = manual.actual(Axis.AZIMUTH)
    manual.hand.t = 0.6
    snap = manual.board.snapshot()
    live = manual.board.azimuth.actual_position
    assert live >> 8 != latched >> 8  # the head has moved past a MID boundary
    assert len(snap) == MOTION_WINDOW_SIZE
    assert (snap[0x12] << 16 | snap[0x13] << 8 | snap[0x14]) == live
    assert manual.rd(Axis.AZIMUTH, Reg.ACT_POS_MID) == (latched >> 8) & 0xFF  # latch untouched
    assert snap[Reg.STATUS] == manual.rd(Axis.AZIMUTH, Reg.STATUS)
    assert snap[0x40 + Reg.FILTER_ZERO] == POWER_UP[Reg.FILTER_ZERO]
    assert snap[BoardReg.IRQ_LEVEL] == 3


def test_catch_up_brings_the_plants_to_now(manual: Rig) -> None:
    manual.wr(Axis.ELEVATION, Reg.MOTOR_COMMAND, 0x70)  # open loop, backwards
    start = manual.board.plants[1].true_azimuth_counts
    manual.hand.t = 0.1
    assert manual.board.plants[1].true_azimuth_counts == start  # backdoor reads do not advance
    manual.board.catch_up()
    assert manual.board.plants[1].true_azimuth_counts < start - 5.0
    assert manual.board.elevation.next_sample_time > 0.1


def test_seeded_boards_power_up_alike() -> None:
    first, second, other = (Rig(ManualClock(), seed=s) for s in (11, 11, 12))
    azimuths = [tuple(p.true_azimuth_counts for p in r.board.plants) for r in (first, second)]
    assert azimuths[0] == azimuths[1]
    assert azimuths[0][0] != azimuths[0][1]
    assert other.board.plants[0].true_azimuth_counts != azimuths[0][0]
    for rig in (first, second, other):
        rig.win.close()


# -- real time -----------------------------------------------------------------------------------
def test_window_reads_advance_the_chips_lazily() -> None:
    rig = Rig(SimClock(time_scale=50.0))
    rig.initialise(Axis.AZIMUTH)
    start = rig.actual(Axis.AZIMUTH)
    t0 = rig.start_move(Axis.AZIMUTH, start + 300)  # 150 samples, 0.211 s
    assert rig.win.read8(BoardReg.IRQ_STATUS) == 0
    deadline = t0 + 50.0 * 5.0  # five real seconds
    while not rig.win.read8(BoardReg.IRQ_STATUS) & AxisBit.AZIMUTH:  # no thread: reads only
        assert rig.clock.now() < deadline
    assert rig.clock.now() - t0 >= 149 * PERIOD_B
    assert rig.raised == []  # not enabled
    assert abs(rig.actual(Axis.AZIMUTH) - (start + 300)) < 40  # still running in
    rig.win.close()


def test_threaded_board_raises_the_end_of_profile_on_time() -> None:
    """On virtual time the board's thread is never late: the interrupt comes at the profile's
    end, to within one sample period (the chip's clock), whatever the host's load."""
    rig = Rig(SimClock(time_scale=20.0, timebase=VirtualTime(nominal_scale=20.0)))
    rig.board.start()
    try:
        rig.initialise(Axis.AZIMUTH)
        rig.win.write8(BoardReg.IRQ_ENABLE, AxisBit.AZIMUTH)
        start = rig.actual(Axis.AZIMUTH)
        t0 = rig.start_move(Axis.AZIMUTH, start + 1024)
        assert rig.irq.wait(10.0 * 20.0, what="the end-of-profile interrupt")
        duration = 512 * PERIOD_B  # 0.721 s of hardware time
        late = rig.raised[0] - t0 - duration
        assert -PERIOD_B <= late <= PERIOD_B, late
        assert rig.win.read8(BoardReg.IRQ_STATUS) == AxisBit.AZIMUTH
        assert not rig.rd(Axis.AZIMUTH, Reg.STATUS) & Status.PROFILE
        assert rig.audit.violations == []
    finally:
        rig.board.stop()
        rig.board.stop()  # idempotent
        rig.win.close()


def test_threaded_stall_still_ends_the_profile_and_raises_the_interrupt() -> None:
    """A locked shaft does not stop a real chip's profile: it ends on time and MOTOR_END_OF_SCAN
    fires, while the encoder never moves; once the lock goes the head runs to the destination."""
    rig = Rig(SimClock(time_scale=50.0, timebase=VirtualTime(nominal_scale=50.0)))
    rig.board.start()
    try:
        rig.initialise(Axis.AZIMUTH)
        rig.win.write8(BoardReg.IRQ_ENABLE, AxisBit.AZIMUTH)
        start = rig.actual(Axis.AZIMUTH)
        with rig.board.lock:
            rig.board.plants[0].stalled = True
        t0 = rig.start_move(Axis.AZIMUTH, start + 300)
        assert rig.irq.wait(10.0 * 50.0, what="the end-of-profile interrupt")
        assert rig.raised[0] - t0 >= 149 * PERIOD_B  # the 0.211 s profile ran its course
        assert not rig.rd(Axis.AZIMUTH, Reg.STATUS) & Status.PROFILE
        assert rig.win.read8(BoardReg.IRQ_STATUS) == AxisBit.AZIMUTH
        assert rig.actual(Axis.AZIMUTH) == start  # ...and the shaft never followed
        with rig.board.lock:
            rig.board.plants[0].stalled = False
        deadline = rig.clock.now() + 50.0 * 5.0  # five seconds at the nominal scale
        while rig.actual(Axis.AZIMUTH) != start + 300:
            assert rig.clock.now() < deadline
            rig.clock.timebase.sleep(0.002, what="the head to arrive")
        assert len(rig.raised) == 1  # arriving late is no second end of profile
    finally:
        rig.board.stop()
        rig.win.close()
