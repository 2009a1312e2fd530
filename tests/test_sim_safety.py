"""The simulator's safety models (issue 11): the pan head's hard stops, the HEAD_BEYOND_LIMIT
audit of the true head, the fault in which the profile runs and the shaft does not follow (a dead
amplifier, a locked shaft), and the supervisor's bounded memory.

Most tests step the models by hand (a plant, or the board on a clock that moves only when told),
so they are exact and fast; the rig-level ones check the wiring a driver meets, through the
registers and the level-3 line, on virtual time (issue 22): hardware time moves only while the
test waits through the rig's time base, so they are exact too.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from biris_hw.bus.memory import MemoryWindow
from regs.biexec import (
    OFF_COMMAND,
    OFF_MOTOR_ACCESS,
    OFF_PARAM,
    OFF_STATUS,
    BiCommand,
    BiStatus,
    encode_param,
)
from regs.hctl1000 import (
    MOTION_LIMIT_COUNTS,
    Flag,
    ProgramCounter,
    Reg,
    Status,
    flag_write,
    pos24_lsb_first,
    pos24_msb_first,
    sample_period,
)
from regs.layout import BirisMemoryMap
from regs.tech80 import AXIS_BASE, Axis, AxisBit, BoardReg
from sim.audit import Audit, Rule, Violation
from sim.clock import FIELD_PERIOD, SimClock
from sim.hctl1000 import HEAD_LIMIT_COUNTS, HEAD_OVERSHOOT_COUNTS, Hctl1000
from sim.irqgate import InterruptGate
from sim.motor import COUNTS_PER_REV, MotorPlant, PlantParams
from sim.ramdisk import BOOT_FILE
from sim.rig import SimulatedBiris
from sim.scene import Scene
from sim.supervisor import BirisSupervisor
from sim.supervisor.state import ACQUISITION_TIMES_KEPT, SEQUENCE_STARTS_KEPT, TimeHistory
from sim.tech80 import Model7600
from tests.conftest import WAIT, until

DT = sample_period(0xAF)  # Appendix B's sample period, 1.408 ms
STOP = COUNTS_PER_REV + 256  # the default stops


def plant_at(azimuth: float, **params: object) -> MotorPlant:
    return MotorPlant(
        np.random.default_rng(0),
        PlantParams(**params),  # type: ignore[arg-type]
        initial_azimuth_counts=azimuth,
    )


def head_records(audit: Audit) -> list[Violation]:
    return [v for v in audit.violations if v.rule is Rule.HEAD_BEYOND_LIMIT]


# -- the stops -------------------------------------------------------------------------------------
def test_the_default_stops_lie_beyond_the_audit_limit_and_short_of_a_revolution() -> None:
    assert PlantParams().stop_counts == STOP
    assert MOTION_LIMIT_COUNTS + HEAD_OVERSHOOT_COUNTS == HEAD_LIMIT_COUNTS < STOP
    assert 32 <= HEAD_OVERSHOOT_COUNTS <= 64
    with pytest.raises(ValueError, match="beyond the stops"):
        plant_at(STOP + 1.0)
    with pytest.raises(ValueError, match="stop_counts"):
        PlantParams(stop_counts=0.0)


@pytest.mark.parametrize("side", [1, -1])
def test_a_head_driven_into_a_stop_stops_dead_and_is_held_there(side: int) -> None:
    plant = plant_at(side * (STOP - 40.5))
    for _ in range(100):  # full drive: 3.5 counts a sample, so the stop is reached in ~12
        plant.step(side * 127, DT)
        assert abs(plant.true_azimuth_counts) <= STOP
    assert plant.true_azimuth_counts == side * STOP  # exactly at the stop...
    assert plant.velocity_counts_per_s == 0.0  # ...and dead still
    pressed = plant.at_stop
    assert pressed
    assert plant.stop_hits == 1  # one arrival, however long it pushes
    assert plant.holds_at_rest(side * 127)  # pushing into the stop moves nothing
    assert not plant.holds_at_rest(-side * 127)  # pulling away would
    volts_per_unit = plant.params.full_scale_volts / 128.0
    assert plant.current_a == pytest.approx(side * 127 * volts_per_unit / 4.0, rel=1e-6)
    for _ in range(50):  # back away: the stop lets go
        plant.step(-side * 60, DT)
    assert side * plant.true_azimuth_counts < STOP - 20.0
    assert not plant.at_stop
    for _ in range(100):
        plant.step(side * 127, DT)
    assert plant.true_azimuth_counts == side * STOP
    # arriving faster than its steady speed, the winding's current is negative at the impact
    # and pulls the head off once more before it settles against the stop: impacts count
    assert plant.stop_hits in (2, 3)


def test_without_stops_the_head_turns_freely() -> None:
    plant = plant_at(STOP - 40.5, stop_counts=None)
    for _ in range(100):
        plant.step(127, DT)
    assert plant.true_azimuth_counts > STOP + 200.0
    assert plant.stop_hits == 0


APPENDIX_B: tuple[tuple[int, int], ...] = (
    (Reg.SAMPLE_TIMER, 0xAF),
    (Reg.FILTER_ZERO, 0x7F),
    (Reg.FILTER_POLE, 0xEF),
    (Reg.FILTER_GAIN, 0x3F),
    (Reg.MAX_VELOCITY, 2),
    (Reg.ACCEL_LSB, 0x22),
    (Reg.ACCEL_MSB, 0x33),
)
"""Appendix B's filter, sample timer and profile limits, as a driver writes them."""


def _ready_chip(azimuth: float, audit: Audit | None = None) -> Hctl1000:
    """An azimuth chip under Appendix B, holding where the head is (counter 0 there)."""
    plant = MotorPlant(np.random.default_rng(0), initial_azimuth_counts=azimuth)
    chip = Hctl1000("azimuth", plant, audit=audit, head_limit=HEAD_LIMIT_COUNTS)
    for reg, value in (*APPENDIX_B, (Reg.PROGRAM_COUNTER, ProgramCounter.CONTROL)):
        chip.bus_write(reg, value)
    return chip


def _trapezoid(chip: Hctl1000, final: int) -> None:
    regs = (Reg.FINAL_POS_LSB, Reg.FINAL_POS_MID, Reg.FINAL_POS_MSB)
    for reg, byte in zip(regs, pos24_lsb_first(final), strict=True):
        chip.bus_write(reg, byte)
    chip.bus_write(Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, True))


def test_a_chip_skipping_idle_samples_at_the_stop_computes_what_stepping_does() -> None:
    """Pressed into a stop the loop sits in a fixed point, whose samples the chip shortcuts
    (``holds_at_rest`` must say so only where it is true): a chip caught up in steps shorter
    than two periods (so that no pair is skipped and even the held current must agree) and one
    stepped sample by sample agree bit for bit, there and on the way back."""
    stepped, caught = _ready_chip(4300.25), _ready_chip(4300.25)
    t = caught.next_sample_time
    for destination in (200, 0):  # into the stop (true 4500 lies beyond it), then away
        for chip in (stepped, caught):
            _trapezoid(chip, destination)
        for _ in range(600):
            t += 1.5 * DT
            caught.advance_to(t)
            while stepped.next_sample_time < caught.next_sample_time - DT / 2:
                stepped.step()
            a, b = stepped.plant, caught.plant
            assert a.true_azimuth_counts.hex() == b.true_azimuth_counts.hex()
            assert a.current_a.hex() == b.current_a.hex()
            assert stepped.motor_command == caught.motor_command
        if destination:
            assert caught.plant.true_azimuth_counts == STOP
            assert caught.motor_command == 127  # pushing, and held
    assert caught.plant.stop_hits >= 1
    assert abs(caught.plant.true_azimuth_counts - 4300.25) < 1.0  # and back where it started


# -- HEAD_BEYOND_LIMIT -----------------------------------------------------------------------------
class ManualClock(SimClock):
    """Hardware time that moves only when the test says so."""

    def __init__(self) -> None:
        super().__init__(1.0)
        self.t = 0.0

    def now(self) -> float:
        return self.t


class Board:
    """A Model 7600 on a manual clock, driven through its registers as a driver would."""

    def __init__(self, azimuth: float, elevation: float = 0.0) -> None:
        self.clock = ManualClock()
        self.audit = Audit(self.clock.now)
        rng = np.random.default_rng(3)
        self.board = Model7600(
            self.clock,
            rng,
            raise_irq=lambda: None,
            audit=self.audit,
            azimuth_plant=MotorPlant(rng, initial_azimuth_counts=azimuth),
            elevation_plant=MotorPlant(rng, initial_azimuth_counts=elevation),
        )
        self.win = self.board.window()

    def wr(self, axis: Axis, reg: int, value: int) -> None:
        self.win.write8(AXIS_BASE[axis] + reg, value)

    def initialise(self, axis: Axis) -> None:
        """Appendix B, then hold the present position (counter 0) in position control."""
        for reg, value in APPENDIX_B:
            self.wr(axis, reg, value)
        for reg, byte in zip(
            (Reg.CMD_POS_MSB, Reg.CMD_POS_MID, Reg.CMD_POS_LSB), pos24_msb_first(0), strict=True
        ):
            self.wr(axis, reg, byte)
        self.wr(axis, Reg.PROGRAM_COUNTER, ProgramCounter.CONTROL)

    def move(self, axis: Axis, final: int, seconds: float = 4.0) -> None:
        """A trapezoid to ``final`` (counter), then ``seconds`` of hardware time."""
        regs = (Reg.FINAL_POS_LSB, Reg.FINAL_POS_MID, Reg.FINAL_POS_MSB)
        for reg, byte in zip(regs, pos24_lsb_first(final), strict=True):
            self.wr(axis, reg, byte)
        self.wr(axis, Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, True))
        self.clock.t += seconds
        self.board.catch_up()

    @property
    def true_azimuth(self) -> float:
        return self.board.plants[0].true_azimuth_counts


def test_the_true_head_beyond_the_envelope_is_recorded_once_per_excursion() -> None:
    """The counter was zeroed near +360 degrees (as a re-homing on the nearest index does), so
    every destination the driver writes is legal, yet the true head leaves the envelope."""
    b = Board(azimuth=4000.25)
    b.initialise(Axis.AZIMUTH)
    b.move(Axis.AZIMUTH, 100)  # true 4100: inside the overshoot allowance
    assert b.true_azimuth == pytest.approx(4100.25, abs=1.0)
    assert b.audit.violations == []
    b.move(Axis.AZIMUTH, 300)  # true 4300: beyond, and held there for seconds
    assert b.true_azimuth == pytest.approx(4300.25, abs=1.0)
    (first,) = b.audit.violations  # nothing else: MOTOR_BEYOND_LIMIT sees only the counter
    assert first.rule is Rule.HEAD_BEYOND_LIMIT
    assert HEAD_LIMIT_COUNTS < first.registers["TRUE_POS"] < HEAD_LIMIT_COUNTS + 5
    assert first.registers["ACT_POS"] < 200  # what the chip's counter said meanwhile
    assert first.registers["HEAD_LIMIT"] == HEAD_LIMIT_COUNTS
    assert "true head" in first.detail
    b.move(Axis.AZIMUTH, 130)  # true 4130: back under the limit, not inside the envelope
    b.move(Axis.AZIMUTH, 300)  # so going out again is the same excursion
    assert len(head_records(b.audit)) == 1
    b.move(Axis.AZIMUTH, 0)  # true 4000: inside the envelope, which re-arms the rule
    b.move(Axis.AZIMUTH, 300)
    assert len(head_records(b.audit)) == 2
    b.move(Axis.AZIMUTH, 600)  # true 4600 lies beyond the stop: the head stops dead at it
    assert b.true_azimuth == STOP
    assert b.board.plants[0].stop_hits == 1
    b.clock.t += 5.0  # pressed against the stop (the drive saturated): it stays
    b.board.catch_up()
    assert b.true_azimuth == STOP
    assert b.board.azimuth.motor_command == 127
    assert len(head_records(b.audit)) == 2  # still the second excursion
    assert b.audit.violations == head_records(b.audit)
    b.move(Axis.AZIMUTH, 0)  # off the stop and home
    assert b.true_azimuth == pytest.approx(4000.25, abs=1.0)
    assert len(head_records(b.audit)) == 2


def test_the_negative_side_is_audited_alike() -> None:
    b = Board(azimuth=-4000.75)
    b.initialise(Axis.AZIMUTH)
    b.move(Axis.AZIMUTH, -300)
    assert b.true_azimuth == pytest.approx(-4300.75, abs=1.0)
    (record,) = b.audit.violations
    assert record.rule is Rule.HEAD_BEYOND_LIMIT
    assert -HEAD_LIMIT_COUNTS - 5 < record.registers["TRUE_POS"] < -HEAD_LIMIT_COUNTS


def test_the_tilt_axis_is_not_audited_as_a_cable() -> None:
    b = Board(azimuth=0.0, elevation=4000.25)
    b.initialise(Axis.ELEVATION)
    b.move(Axis.ELEVATION, 300)
    assert b.board.plants[1].true_azimuth_counts == pytest.approx(4300.25, abs=1.0)
    assert b.audit.violations == []


def _start_rig(**options: object) -> SimulatedBiris:
    options.setdefault("scene", Scene.circle(2.0))
    options.setdefault("time_scale", 20.0)
    options.setdefault("seed", 11)
    options.setdefault("clock", "virtual")
    return SimulatedBiris(**options).start()  # type: ignore[arg-type]


class Motion:
    """The azimuth chip of a rig, driven through the driver's motion window."""

    def __init__(self, rig: SimulatedBiris) -> None:
        self.rig = rig
        self.win = rig.hardware.motion
        base = AXIS_BASE[Axis.AZIMUTH]
        for reg, value in APPENDIX_B:
            self.win.write8(base + reg, value)
        here = self.actual()
        for reg, byte in zip(
            (Reg.CMD_POS_MSB, Reg.CMD_POS_MID, Reg.CMD_POS_LSB), pos24_msb_first(here), strict=True
        ):
            self.win.write8(base + reg, byte)
        self.win.write8(base + Reg.PROGRAM_COUNTER, ProgramCounter.CONTROL)
        self.win.write8(BoardReg.IRQ_ENABLE, AxisBit.AZIMUTH)

    def actual(self) -> int:
        base = AXIS_BASE[Axis.AZIMUTH]
        lsb = self.win.read8(base + Reg.ACT_POS_LSB)  # latches the middle and high bytes
        mid = self.win.read8(base + Reg.ACT_POS_MID)
        msb = self.win.read8(base + Reg.ACT_POS_MSB)
        raw = (msb << 16) | (mid << 8) | lsb
        return raw - (1 << 24) if raw & 0x80_0000 else raw

    def move(self, final: int) -> None:
        base = AXIS_BASE[Axis.AZIMUTH]
        regs = (Reg.FINAL_POS_LSB, Reg.FINAL_POS_MID, Reg.FINAL_POS_MSB)
        for reg, byte in zip(regs, pos24_lsb_first(final), strict=True):
            self.win.write8(base + reg, byte)
        self.win.write8(base + Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, True))

    def profile_running(self) -> bool:
        return bool(self.win.read8(AXIS_BASE[Axis.AZIMUTH] + Reg.STATUS) & Status.PROFILE)


def test_a_rig_records_the_true_head_beyond_the_envelope() -> None:
    """The wiring every test relies on: the rig's board audits its pan head, so any wind-up
    fails the test that caused it (conftest checks each rig's audit)."""
    rig = _start_rig(initial_azimuth_counts=4000.5)
    try:
        motion = Motion(rig)
        motion.move(200)  # true 4200
        until(lambda: motion.actual() == 200 and not motion.profile_running())
        (record,) = rig.audit.violations
        assert record.rule is Rule.HEAD_BEYOND_LIMIT
        assert record.registers["TRUE_POS"] > HEAD_LIMIT_COUNTS
        rig.audit.clear()  # checked: the teardown's audit check then sees only what follows
    finally:
        rig.close()


# -- the profile runs, the shaft does not follow --------------------------------------------------
@pytest.mark.parametrize(
    ("fault", "clear"),
    [("dead_amplifier", "clear_dead_amplifier"), ("stall_motor", "clear_stall")],
)
def test_the_profile_ends_and_interrupts_while_the_head_stays_put(fault: str, clear: str) -> None:
    """What a real HCTL-1000 shows for a dead amplifier or a locked shaft: the trapezoid runs
    its course, MOTOR_END_OF_SCAN arrives on level 3, and the head never moves. Clearing the
    fault lets the chip's position loop bring the head to the destination."""
    rig = _start_rig(initial_azimuth_counts=100.25)
    try:
        motion = Motion(rig)
        start = motion.actual()
        getattr(rig.faults, fault)()
        motion.move(start + 300)  # a 0.211 s profile
        assert rig.hardware.level3.wait(WAIT) == 1
        assert not motion.profile_running()
        assert rig.hardware.motion.read8(BoardReg.IRQ_STATUS) == AxisBit.AZIMUTH
        assert rig.board.azimuth.command_position == start + 300  # the chip is "there"...
        assert rig.azimuth_counts == 100.25  # ...the head has not moved at all
        assert motion.actual() == start
        getattr(rig.faults, clear)()
        until(lambda: motion.actual() == start + 300, what="the head to arrive once cleared")
        assert rig.hardware.level3.wait(0.0) == 0  # arriving late is no second end of scan
    finally:
        rig.close()


def test_a_dead_amplifier_lets_a_moving_head_coast_to_rest() -> None:
    plant = plant_at(0.25)
    for _ in range(300):  # up to full speed
        plant.step(100, DT)
    speed = plant.velocity_counts_per_s
    assert speed > 1500.0
    plant.amplifier_dead = True
    coasted_from = plant.true_azimuth_counts
    for _ in range(200):  # 0.28 s: the winding's back emf and friction brake it
        plant.step(100, DT)
    assert plant.velocity_counts_per_s == 0.0
    rest = plant.true_azimuth_counts
    assert 0.0 < rest - coasted_from < speed * 0.05  # it coasted, briefly
    assert plant.holds_at_rest(127) and plant.holds_at_rest(-128)  # no command moves it
    for _ in range(100):
        plant.step(-127, DT)
    assert plant.true_azimuth_counts == rest
    plant.amplifier_dead = False
    plant.step(-127, DT)
    assert plant.true_azimuth_counts < rest


def test_clear_all_revives_the_amplifier() -> None:
    rig = _start_rig()
    try:
        rig.faults.dead_amplifier()
        assert rig.board.plants[0].amplifier_dead
        assert not rig.board.plants[1].amplifier_dead  # the pan axis only
        rig.faults.clear_all()
        assert not rig.board.plants[0].amplifier_dead
    finally:
        rig.close()


# -- bounded memory --------------------------------------------------------------------------------
def test_a_time_history_keeps_the_newest_and_counts_them_all() -> None:
    history = TimeHistory(keep=8)
    for k in range(1000):
        history.append(float(k))
        assert history.stored <= 10  # 8 + a quarter
        assert history.count == k + 1
    assert history.recent() == [float(k) for k in range(992, 1000)]
    assert history.since(995) == [995.0, 996.0, 997.0, 998.0, 999.0]
    assert history.since(1000) == []
    with pytest.raises(ValueError, match="no longer kept"):
        history.since(991)
    short = TimeHistory(keep=8)
    for k in range(5):
        short.append(float(k))
    assert short.recent() == short.since(0) == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_the_supervisor_defaults_are_bounded() -> None:
    # a day at x1 makes 2.6 million acquisitions; what is kept must not depend on that
    assert ACQUISITION_TIMES_KEPT * 8 * 1.25 <= 1 << 20  # at most 1 MiB of doubles
    assert SEQUENCE_STARTS_KEPT * 8 * 1.25 <= 1 << 16


def test_a_long_run_keeps_the_supervisors_memory_bounded() -> None:
    """Thousands of acquisitions and hundreds of sequences, driven on the caller's thread
    (``run_until``: no real time passes), with small bounds so the trimming is exercised."""
    clock = SimClock(1.0)
    mmap = BirisMemoryMap(samples=64, max_acquisitions=16)
    mem = MemoryWindow(mmap.size)
    gate = InterruptGate(lambda count: None, clock)
    audit = Audit(clock.now)
    frame = np.zeros(mmap.samples + 1, dtype=np.int16)
    sup = BirisSupervisor(
        mem,
        mmap,
        clock,
        gate,
        lambda az, tilt, lut: (frame, frame),
        lambda t: 0.0,
        audit=audit,
        rng=np.random.default_rng(1),
        times_kept=100,
        starts_kept=10,
    )
    base = mmap.biexec_offset
    mem.write16(base + OFF_MOTOR_ACCESS, 1)
    t = 0.0

    def execute(code: BiCommand, param: str = "") -> None:
        nonlocal t
        mem.write(base + OFF_PARAM, encode_param(param))
        mem.write16(base + OFF_COMMAND, int(code))
        sup.note_command_write(int(code))
        while mem.read16(base + OFF_COMMAND):
            t += FIELD_PERIOD
            sup.run_until(t)
        assert mem.read16(base + OFF_STATUS) == BiStatus.OK

    execute(BiCommand.BI_BOOT, BOOT_FILE)
    for _ in range(40):  # 40 sequences of 16: 640 acquisitions
        execute(BiCommand.BI_ACQUIRE, "16")
        assert sup._acquisition_times.stored <= 125
        assert sup._sequence_starts.stored <= 12
    execute(BiCommand.BI_START_CONTINUOUS)
    t += 3000 * 2 * FIELD_PERIOD  # a hundred seconds of continuous acquisition, in one go
    sup.run_until(t)
    execute(BiCommand.BI_STOP_CONTINUOUS)
    made = sup.acquisitions_made
    assert made > 640 + 2900  # every one counted...
    assert sup.sequences_started == 41
    assert sup._acquisition_times.stored <= 125  # ...few remembered
    assert sup._sequence_starts.stored <= 12
    times = sup.acquisition_times
    assert len(times) == 100
    assert len(sup.sequence_starts) == 10
    assert np.allclose(np.diff(times), 2 * FIELD_PERIOD, atol=1e-9)  # the newest, in order
    assert sup.acquisition_times_since(made - 3) == times[-3:]
    with pytest.raises(ValueError, match="no longer kept"):
        sup.acquisition_times_since(made - 101)
    assert audit.violations == []
    assert not math.isnan(times[-1])
