"""The HCTL-1000 model: register side effects, filter, profile generators, closed loop, audit.

The chip is stepped directly (no clock, no threads): each ``step()`` is one sample period.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

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
from sim.audit import Audit, Rule
from sim.hctl1000 import HISTORY, POWER_UP, Hctl1000, Mode
from sim.motor import MotorPlant

APPENDIX_B = {"sample": 0xAF, "zero": 0x7F, "pole": 0xEF, "gain": 0x3F, "vmax": 2, "accel": 0x3322}
PERIOD_B = sample_period(0xAF)


# -- helpers -------------------------------------------------------------------------------------
def make_chip(azimuth: float = 100.25) -> tuple[Hctl1000, MotorPlant, Audit]:
    audit = Audit(lambda: 0.0)
    plant = MotorPlant(np.random.default_rng(0), initial_azimuth_counts=azimuth)
    return Hctl1000("azimuth", plant, audit=audit), plant, audit


def configure(
    chip: Hctl1000,
    *,
    sample: int = 0xAF,
    zero: int = 0x7F,
    pole: int = 0xEF,
    gain: int = 0x3F,
    vmax: int = 2,
    accel: int = 0x3322,
) -> None:
    w = chip.bus_write
    w(Reg.SAMPLE_TIMER, sample)
    w(Reg.FILTER_ZERO, zero)
    w(Reg.FILTER_POLE, pole)
    w(Reg.FILTER_GAIN, gain)
    w(Reg.MAX_VELOCITY, vmax)
    w(Reg.ACCEL_LSB, accel & 0xFF)
    w(Reg.ACCEL_MSB, accel >> 8)


def commit(chip: Hctl1000, position: int) -> None:
    for reg, byte in zip(
        (Reg.CMD_POS_MSB, Reg.CMD_POS_MID, Reg.CMD_POS_LSB), pos24_msb_first(position), strict=True
    ):
        chip.bus_write(reg, byte)


def set_final(chip: Hctl1000, position: int) -> None:
    for reg, byte in zip(
        (Reg.FINAL_POS_LSB, Reg.FINAL_POS_MID, Reg.FINAL_POS_MSB),
        pos24_lsb_first(position),
        strict=True,
    ):
        chip.bus_write(reg, byte)


def read_actual(chip: Hctl1000) -> int:
    lsb = chip.bus_read(Reg.ACT_POS_LSB)
    mid = chip.bus_read(Reg.ACT_POS_MID)
    msb = chip.bus_read(Reg.ACT_POS_MSB)
    raw = (msb << 16) | (mid << 8) | lsb
    return raw - (1 << 24) if raw & 0x80_0000 else raw


def hold_here(chip: Hctl1000) -> None:
    """The driver's sequence: in init/idle, command = actual, control flags clear, PC = 03."""
    commit(chip, read_actual(chip))
    for flag in (Flag.F0_TRAPEZOID, Flag.F3_PROPORTIONAL_VELOCITY, Flag.F5_INTEGRAL_VELOCITY):
        chip.bus_write(Reg.FLAG, flag_write(flag, False))
    chip.bus_write(Reg.PROGRAM_COUNTER, ProgramCounter.CONTROL)


def ready(azimuth: float = 100.25, **params: int) -> tuple[Hctl1000, MotorPlant, Audit]:
    chip, plant, audit = make_chip(azimuth)
    configure(chip, **params)
    hold_here(chip)
    return chip, plant, audit


def start_trapezoid(chip: Hctl1000, final: int) -> None:
    set_final(chip, final)
    chip.bus_write(Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, True))


def run_profile(chip: Hctl1000, limit: int = 20_000) -> list[int]:
    """Step until F0 clears; the command position issued at each sample."""
    setpoints = []
    while chip.profile_active:
        chip.step()
        setpoints.append(chip.command_position)
        assert len(setpoints) < limit
    return setpoints


def rules(audit: Audit) -> list[Rule]:
    return [v.rule for v in audit.violations]


# -- register side effects -----------------------------------------------------------------------
def test_power_up_state() -> None:
    chip, _, audit = make_chip()
    assert chip.mode is Mode.INIT_IDLE
    assert chip.bus_read(Reg.STATUS) == Status.INIT_IDLE | Status.STOP_CLEAR | Status.LIMIT_CLEAR
    assert chip.bus_read(Reg.MOTOR_COMMAND) == 0x80
    assert chip.filter == (POWER_UP[Reg.FILTER_ZERO], POWER_UP[Reg.FILTER_POLE], 0x40)
    assert chip.sample_timer == POWER_UP[Reg.SAMPLE_TIMER]
    assert read_actual(chip) == 0
    assert chip.flags == 0b10  # F1 only
    assert audit.violations == []


def test_reading_r14h_latches_mid_and_msb() -> None:
    chip, plant, _ = make_chip()
    chip.poke(Reg.ACT_POS_MID, 0x01)
    chip.poke(Reg.ACT_POS_LSB, 0xFA)  # actual = 0x0001FA, six counts below a MID change
    assert chip.actual_position == 0x1FA
    assert chip.bus_read(Reg.ACT_POS_LSB) == 0xFA  # latch
    chip.bus_write(Reg.MOTOR_COMMAND, 0xC0)  # open loop, in init/idle
    while chip.actual_position < 0x210:
        chip.step()
    assert chip.peek(Reg.ACT_POS_MID) == 0x02  # the live counter has moved on...
    assert chip.bus_read(Reg.ACT_POS_MID) == 0x01  # ...but the latched bytes have not
    assert chip.bus_read(Reg.ACT_POS_MSB) == 0x00
    assert read_actual(chip) == chip.actual_position  # a new R14H read latches again
    assert plant.encoder_counts > 0


def test_negative_actual_position_reads_as_24_bit_twos_complement() -> None:
    chip, _, _ = make_chip()
    chip.bus_write(Reg.MOTOR_COMMAND, 0x40)  # drive backwards
    for _ in range(100):
        chip.step()
    assert chip.actual_position < -20
    assert chip.bus_read(Reg.ACT_POS_LSB) == chip.actual_position & 0xFF
    assert chip.bus_read(Reg.ACT_POS_MSB) == 0xFF
    assert read_actual(chip) == chip.actual_position


def test_r0eh_write_commits_the_command_position() -> None:
    chip, _, _ = make_chip()
    msb, mid, lsb = pos24_msb_first(-300)
    chip.bus_write(Reg.CMD_POS_MSB, msb)
    chip.bus_write(Reg.CMD_POS_MID, mid)
    assert chip.command_position == 0  # held until the LSB is written
    assert chip.bus_read(Reg.CMD_POS_MSB) == 0x00  # reads show the live command
    chip.bus_write(Reg.CMD_POS_LSB, lsb)
    assert chip.command_position == -300
    assert [chip.bus_read(r) for r in (0x0C, 0x0D, 0x0E)] == list(pos24_msb_first(-300))


def test_any_write_to_r13h_clears_the_actual_position() -> None:
    chip, _, audit = make_chip()
    chip.bus_write(Reg.MOTOR_COMMAND, 0xA0)
    for _ in range(100):
        chip.step()
    assert chip.actual_position > 10
    chip.bus_write(Reg.ACT_POS_MID, 0x5A)
    assert chip.actual_position == 0
    assert read_actual(chip) == 0
    for _ in range(5):
        chip.step()
    assert 0 < chip.actual_position < 20  # counting goes on from the new zero
    assert audit.violations == []  # R13H is writable


def test_flag_write_encoding_and_status_bits() -> None:
    chip, _, _ = ready()
    chip.bus_write(Reg.FLAG, 0x0B)  # set F3
    assert chip.flags & (1 << 3)
    assert chip.mode is Mode.PROPORTIONAL_VELOCITY
    chip.bus_write(Reg.FLAG, 0x03)  # clear F3
    assert chip.mode is Mode.POSITION
    chip.bus_write(Reg.FLAG, 0xFD)  # upper bits ignored: set F5
    assert chip.mode is Mode.INTEGRAL_VELOCITY
    assert chip.bus_read(Reg.FLAG) == 1 << 5
    chip.bus_write(Reg.FLAG, 0x05)
    chip.bus_write(Reg.FLAG, 0x09)  # F1 is the chip's: ignored
    assert chip.flags == 0
    status = chip.bus_read(Reg.STATUS)
    assert status == Status.STOP_CLEAR | Status.LIMIT_CLEAR  # not idle, no profile
    set_final(chip, chip.command_position + 100)
    chip.bus_write(Reg.FLAG, 0x08)  # set F0
    assert chip.bus_read(Reg.STATUS) & Status.PROFILE
    assert chip.profile_active


def test_status_register_only_low_four_bits_writable() -> None:
    chip, _, _ = ready()
    chip.bus_write(Reg.STATUS, 0xFF)
    assert chip.bus_read(Reg.STATUS) == 0xCF
    chip.bus_write(Reg.STATUS, 0x00)
    assert chip.bus_read(Reg.STATUS) == 0xC0


def test_motor_command_writable_only_in_init_idle() -> None:
    chip, plant, _ = make_chip()
    chip.bus_write(Reg.MOTOR_COMMAND, 0xB0)
    assert chip.motor_command == 0x30
    for _ in range(20):
        chip.step()
    assert plant.velocity_counts_per_s > 0.0  # open-loop drive
    configure(chip)
    hold_here(chip)
    chip.step()
    before = chip.motor_command
    chip.bus_write(Reg.MOTOR_COMMAND, 0xFF if before != 127 else 0x00)
    assert chip.motor_command == before  # ignored: the filter owns R08H in control


def test_writes_to_read_only_registers_are_ignored_and_audited() -> None:
    chip, _, audit = make_chip()
    chip.bus_write(Reg.MOTOR_COMMAND, 0xC0)
    for _ in range(50):
        chip.step()
    before = chip.actual_position
    for reg in (Reg.ACT_POS_MSB, Reg.ACT_POS_LSB, Reg.ACT_VEL_LSB, Reg.ACT_VEL_MSB):
        chip.bus_write(reg, 0x55)
    assert chip.actual_position == before
    assert chip.peek(Reg.ACT_VEL_LSB) == 0
    assert rules(audit) == [Rule.WRITE_TO_READ_ONLY] * 4
    assert {v.registers["REGISTER"] for v in audit.violations} == {0x12, 0x14, 0x34, 0x35}


def test_unmapped_registers_read_zero_and_masks_apply() -> None:
    chip, _, audit = make_chip()
    for reg in (0x01, 0x3F, 0x15):
        chip.bus_write(reg, 0xAA)
        assert chip.bus_read(reg) == 0
    chip.bus_write(Reg.MAX_VELOCITY, 0xFF)
    chip.bus_write(Reg.ACCEL_MSB, 0xFF)
    assert chip.bus_read(Reg.MAX_VELOCITY) == 0x7F
    assert chip.bus_read(Reg.ACCEL_MSB) == 0x7F
    assert audit.violations == []
    with pytest.raises(ValueError):
        chip.bus_read(0x40)


def test_peek_and_poke_have_no_side_effects() -> None:
    chip, _, audit = make_chip()
    chip.poke(Reg.ACT_POS_LSB, 0x34)
    assert chip.bus_read(Reg.ACT_POS_LSB) == 0x34  # latches 0x000034
    chip.poke(Reg.ACT_POS_MID, 0x12)
    assert chip.peek(Reg.ACT_POS_MID) == 0x12
    assert chip.bus_read(Reg.ACT_POS_MID) == 0x00  # the latch was not touched
    chip.poke(Reg.CMD_POS_LSB, 0x99)  # no commit needed
    assert chip.command_position == 0x99
    chip.poke(Reg.ACT_POS_MSB, 0x01)  # poking a read-only register is not a violation
    assert audit.violations == []
    with pytest.raises(ValueError):
        chip.poke(Reg.PROGRAM_COUNTER, 0)


# -- program counter and sample timer -----------------------------------------------------------
def test_program_counter_commands() -> None:
    chip, _, _ = ready()
    assert chip.mode is Mode.POSITION
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x01)
    assert chip.mode is Mode.INIT_IDLE
    assert chip.motor_command == 0
    chip.bus_write(Reg.FLAG, flag_write(Flag.F3_PROPORTIONAL_VELOCITY, True))
    assert chip.mode is Mode.INIT_IDLE  # flags wait for the program counter
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x03)
    assert chip.mode is Mode.PROPORTIONAL_VELOCITY
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x02)  # not from control: ignored
    assert chip.mode is Mode.PROPORTIONAL_VELOCITY
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x01)
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x02)  # align: position control on a DC motor
    assert chip.mode is Mode.POSITION
    assert chip.flags == 0


def test_software_reset_restores_power_up_values() -> None:
    chip, _, _ = ready()
    chip.bus_write(Reg.FILTER_GAIN, 0x99)
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x00)
    assert chip.mode is Mode.RESET
    assert chip.filter[2] == POWER_UP[Reg.FILTER_GAIN]
    assert chip.bus_read(Reg.STATUS) & Status.INIT_IDLE
    chip.step()
    assert chip.mode is Mode.INIT_IDLE


def test_init_idle_clears_the_filter_history() -> None:
    chip, plant, _ = ready(gain=0x10, zero=0x80, pole=0x40)
    plant.stalled = True
    commit(chip, chip.actual_position + 5)
    chip.step()
    chip.step()  # history now holds X = 5 and the last output
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x01)
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x03)
    chip.step()
    assert chip.motor_command == 4 * 5  # (K/4) X[n] alone: no X[n-1], no MC[n-1]


def test_sample_period_and_new_timer_takes_effect_after_the_current_period() -> None:
    chip, _, _ = make_chip()
    configure(chip)
    assert chip.sample_period == pytest.approx(1.408e-3)
    assert chip.next_sample_time == 0.0
    chip.advance_to(0.0)  # the sample at t = 0 runs: the period in progress is 1.408 ms long
    assert chip.next_sample_time == pytest.approx(1.408e-3)
    chip.bus_write(Reg.SAMPLE_TIMER, 0x7C)  # 1 ms, written mid-period
    assert chip.next_sample_time == pytest.approx(1.408e-3)  # the current period keeps its end
    chip.advance_to(1.5e-3)
    assert chip.next_sample_time == pytest.approx(2.408e-3)
    chip.bus_write(Reg.SAMPLE_TIMER, 0x00)  # below the datasheet's minimum: runs as 07H
    assert chip.sample_period == pytest.approx(64e-6)


# -- filter --------------------------------------------------------------------------------------
def test_position_filter_matches_a_hand_computation() -> None:
    # K = 0x10 (K/4 = 4), A = 0x80 (0.5), B = 0x40 (0.25); the shaft is locked so X = command.
    chip, plant, _ = ready(gain=0x10, zero=0x80, pole=0x40)
    plant.stalled = True
    base = chip.actual_position
    outputs = []
    for command, samples in ((3, 3), (-2, 2), (100, 2), (-100, 1)):
        commit(chip, base + command)
        for _ in range(samples):
            chip.step()
            outputs.append(chip.motor_command)
            assert chip.bus_read(Reg.MOTOR_COMMAND) == chip.motor_command + 0x80
    # MC = 4 (X - X'/2) - MC'/4, truncated towards zero, clamped to -128..127:
    # 4*3 = 12; 4*1.5 - 3 = 3; 6 - 0.75 -> 5; 4*(-3.5) - 1.25 -> -15; 4*(-1) + 3.75 -> 0;
    # 4*101 -> 127; 4*50 - 31.75 -> 127; 4*(-150) - 31.75 -> -128
    assert outputs == [12, 3, 5, -15, 0, 127, 127, -128]


def test_appendix_b_filter_for_one_count_of_error() -> None:
    chip, plant, _ = ready()
    plant.stalled = True
    commit(chip, chip.actual_position + 1)
    outputs = []
    for _ in range(6):
        chip.step()
        outputs.append(chip.motor_command)
    # c = 15.75 * (1 - 127/256) = 7.9365, p = 239/256 = 0.9336:
    # 15.75 -> 15; c - 14.004 -> -6; c + 5.602 -> 13; c - 12.137 -> -4; c + 3.734 -> 11;
    # c - 10.270 -> -2
    assert outputs == [15, -6, 13, -4, 11, -2]


# -- trapezoid -----------------------------------------------------------------------------------
def test_trapezoid_lands_exactly_and_respects_max_velocity() -> None:
    chip, _, _ = ready(vmax=3, accel=0x0080)  # 0.5 counts/sample^2
    start = chip.command_position
    ends: list[int] = []
    chip.on_profile_end = lambda: ends.append(chip.command_position)
    start_trapezoid(chip, start + 200)
    setpoints = run_profile(chip)
    steps = np.diff([start, *setpoints])
    assert setpoints[-1] == start + 200
    assert int(steps.sum()) == 200
    assert steps.min() >= 0 and steps.max() == 3  # cruise at, never above, the maximum
    assert list(steps[:3]) == [0, 1, 1]  # accelerating: 0.25, 1.0, 2.25 counts along
    assert setpoints[-2] != setpoints[-1]  # F0 cleared with the last setpoint, not later
    assert ends == [start + 200]
    for _ in range(50):
        chip.step()
    assert ends == [start + 200]  # called once
    assert chip.mode is Mode.POSITION
    assert chip.command_position == start + 200


def test_f0_clears_on_the_sample_that_issues_the_last_setpoint() -> None:
    chip, _, _ = ready()
    start = chip.command_position
    start_trapezoid(chip, start + 1024)
    issued = 0
    while True:
        assert chip.bus_read(Reg.STATUS) & Status.PROFILE
        assert chip.command_position != start + 1024
        chip.step()
        issued += 1
        if chip.command_position == start + 1024:
            break
    assert not chip.bus_read(Reg.STATUS) & Status.PROFILE
    assert issued == 512  # 1024 counts at 2 counts/sample


def test_triangle_when_max_velocity_is_not_reached() -> None:
    chip, _, _ = ready(vmax=10, accel=0x0040)  # 0.25 counts/sample^2
    start = chip.command_position
    start_trapezoid(chip, start - 100)
    setpoints = run_profile(chip)
    steps = -np.diff([start, *setpoints])
    assert setpoints[-1] == start - 100
    assert steps.max() <= 5  # peak velocity sqrt(a D) = 5 < 10
    assert steps.max() >= 4
    assert 37 <= len(setpoints) <= 40  # 2 sqrt(D / a) = 40, less the rounding of the tail
    peak = int(np.argmax(steps))
    assert 15 <= peak <= 25  # turns around halfway


def test_zero_length_trapezoid_ends_at_the_next_sample() -> None:
    chip, _, _ = ready()
    ended = []
    chip.on_profile_end = lambda: ended.append(True)
    start_trapezoid(chip, chip.command_position)
    chip.step()
    assert not chip.profile_active
    assert ended == [True]


def test_profile_end_eta_predicts_the_last_sample() -> None:
    chip, _, _ = ready()
    start_trapezoid(chip, chip.command_position + 100)
    eta = chip.profile_end_eta()
    assert eta is not None
    ended_at: list[float] = []
    chip.on_profile_end = lambda: ended_at.append(chip.next_sample_time - chip.sample_period)
    chip.advance_to(eta + 10 * PERIOD_B)
    assert ended_at == [pytest.approx(eta)]
    assert chip.profile_end_eta() is None


def test_a_locked_shaft_does_not_stop_the_profile() -> None:
    """The profile generator knows nothing of the shaft: it ends on time, F0 clears and the end
    is signalled, while the position stays where the shaft locked; released, the head runs in."""
    chip, plant, _ = ready()
    start = chip.command_position
    ended = []
    chip.on_profile_end = lambda: ended.append(True)
    start_trapezoid(chip, start + 400)
    eta = chip.profile_end_eta()
    for _ in range(50):
        chip.step()
    plant.stalled = True
    locked = plant.true_azimuth_counts
    assert chip.profile_end_eta() == eta  # a locked shaft does not move the end
    chip.advance_to(chip.next_sample_time + 5.0)  # five seconds of a locked shaft
    assert ended == [True]
    assert not chip.profile_active
    assert chip.command_position == start + 400
    assert plant.true_azimuth_counts == locked
    assert chip.actual_position < start + 100  # the counter stopped where the shaft did
    assert chip.motor_command == 127  # the filter pushes with everything it has
    plant.stalled = False
    chip.advance_to(chip.next_sample_time + 2.0)
    assert chip.actual_position == start + 400
    assert ended == [True]


# -- velocity modes ------------------------------------------------------------------------------
def test_proportional_velocity_mode() -> None:
    chip, plant, _ = ready(gain=0xFF)
    chip.bus_write(Reg.CMD_VEL_LSB, 0x20)  # 2.0 counts/sample in 12.4
    chip.bus_write(Reg.CMD_VEL_MSB, 0x00)
    chip.bus_write(Reg.FLAG, flag_write(Flag.F3_PROPORTIONAL_VELOCITY, True))
    start = chip.actual_position
    for _ in range(300):
        chip.step()
        measured = chip.bus_read(Reg.ACT_VEL_LSB) | chip.bus_read(Reg.ACT_VEL_MSB) << 8
        measured -= 0x10000 if measured & 0x8000 else 0
        expected = max(-128, min(127, int(0xFF / 4 * (2.0 - measured))))
        assert chip.motor_command == expected  # MC = (K/4)(command - actual velocity)
    moved = chip.actual_position - start
    speed = moved / 300
    assert 1.2 < speed < 2.0  # proportional control: below the command
    assert chip.command_position == chip.actual_position  # follows the head
    chip.bus_write(Reg.CMD_VEL_LSB, 0xE0)  # -2.0
    chip.bus_write(Reg.CMD_VEL_MSB, 0xFF)
    for _ in range(300):
        chip.step()
    assert plant.velocity_counts_per_s < 0.0


def test_integral_velocity_ramps_and_tracks() -> None:
    chip, _, _ = ready(accel=0x0010)  # 1/16 counts/sample^2
    chip.bus_write(Reg.INT_VELOCITY, 2)
    chip.bus_write(Reg.FLAG, flag_write(Flag.F5_INTEGRAL_VELOCITY, True))
    commands = []
    for _ in range(200):
        chip.step()
        commands.append(chip.command_position)
    steps = np.diff(commands)
    assert steps[:10].max() <= 1  # still ramping up
    assert list(steps[-20:]) == [2] * 20  # at the commanded 2 counts/sample
    assert abs(chip.command_position - chip.actual_position) < 30  # the head follows
    chip.bus_write(Reg.INT_VELOCITY, 0xFE)  # -2: reverse through zero at the same ramp
    for _ in range(200):
        chip.step()
        commands.append(chip.command_position)
    assert list(np.diff(commands)[-20:]) == [-2] * 20


# -- closed loop -----------------------------------------------------------------------------------
@pytest.mark.parametrize(("azimuth", "distance"), [(100.25, 1024), (-7.9, -1024), (3.5, 20)])
def test_appendix_b_step_response_is_well_damped(azimuth: float, distance: int) -> None:
    chip, _, audit = ready(azimuth)
    start = chip.command_position
    target = start + distance
    start_trapezoid(chip, target)
    run_profile(chip)
    error = []
    for _ in range(700):  # one second after the profile
        chip.step()
        error.append(target - chip.actual_position)
    sign = 1 if distance > 0 else -1
    overshoot = max(-sign * e for e in error)
    assert overshoot <= 2
    outside = [i for i, e in enumerate(error) if abs(e) > 2]
    settled_after = (outside[-1] + 1 if outside else 0) * PERIOD_B
    assert settled_after <= 0.020
    assert error[-1] == 0
    assert audit.violations == []


@pytest.mark.parametrize(("zero", "pole"), [(0x00, 0xEF), (0x7F, 0x00)])
def test_bad_gain_oscillates(zero: int, pole: int) -> None:
    chip, _, audit = ready()
    configure(chip, zero=zero, pole=pole, gain=0xFF)  # BIRIS_MOTOR_PARAMS with a bad filter
    target = chip.command_position + 1024
    start_trapezoid(chip, target)
    run_profile(chip)
    error = []
    for _ in range(700):
        chip.step()
        error.append(target - chip.actual_position)
    tail = error[350:]  # the last half second
    sign_changes = sum(1 for a, b in itertools.pairwise(tail) if a * b < 0)
    assert sign_changes >= 10
    assert max(abs(e) for e in tail) >= 10
    assert audit.violations == []


def test_idle_and_holding_chips_fast_forward_without_changing_the_outcome(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    stepped, _, _ = ready()
    skipped, _, _ = ready()
    for chip in (stepped, skipped):
        start_trapezoid(chip, chip.command_position + 30)
    n = 5000
    for _ in range(n):
        stepped.step()
    calls = []
    real_step = skipped.step

    def counted_step() -> None:
        calls.append(1)
        real_step()

    monkeypatch.setattr(skipped, "step", counted_step)
    skipped.advance_to((n - 0.5) * PERIOD_B)
    assert len(calls) < n // 2  # most of the time the head was held still and skipped
    assert skipped.next_sample_time == pytest.approx(n * PERIOD_B)
    for chip in (stepped, skipped):
        assert not chip.profile_active
    assert skipped.actual_position == stepped.actual_position
    assert skipped.motor_command == stepped.motor_command
    assert skipped.command_position == stepped.command_position


def test_position_at_reads_the_counter_as_it_stood_then() -> None:
    """A late reader asking for a past moment gets that moment's reading, not the present's."""
    chip, _, _ = ready()
    start_trapezoid(chip, chip.command_position + 400)
    readings: list[tuple[float, int]] = []  # (sample time, the counter after that sample)
    for _ in range(300):
        t = chip.next_sample_time
        chip.step()
        readings.append((t, chip.actual_position))
    assert len({a for _, a in readings}) > 100  # the head moved all along
    for t, actual in readings[-200::7]:
        assert chip.position_at(t) == actual  # a sample's own moment
        assert chip.position_at(t + 0.5 * PERIOD_B) == actual  # held until the next sample
    # ahead of the chip: it runs up to that moment first, then reads
    ahead = chip.next_sample_time + 10.2 * PERIOD_B
    assert chip.position_at(ahead) == chip.actual_position
    assert chip.next_sample_time > ahead
    # older than kept: the oldest reading kept, not the present one
    start_trapezoid(chip, chip.command_position - 3000)  # still moving after HISTORY samples
    kept = []
    for _ in range(HISTORY):
        chip.step()
        kept.append(chip.actual_position)
    assert chip.position_at(0.0) == kept[0] != chip.actual_position
    # a cleared counter forgets readings on the old zero
    chip.bus_write(Reg.ACT_POS_MID, 0)
    assert chip.position_at(readings[-1][0]) == chip.actual_position == 0


# -- audit ---------------------------------------------------------------------------------------
def test_trapezoid_beyond_the_limit_is_audited() -> None:
    chip, _, audit = ready()
    start_trapezoid(chip, 0x1000)
    assert audit.violations == []  # exactly +0x1000 is allowed
    chip.bus_write(Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, False))
    audit.clear()
    run_profile(chip)
    chip2, _, audit2 = ready()
    start_trapezoid(chip2, -0x1001)
    assert rules(audit2) == [Rule.MOTOR_BEYOND_LIMIT]
    assert audit2.violations[0].registers["FINAL_POS"] == -0x1001


def test_command_beyond_the_limit_is_audited() -> None:
    chip, _, audit = make_chip()
    commit(chip, 0x1000)
    assert audit.violations == []
    commit(chip, 0x1001)
    assert rules(audit) == [Rule.MOTOR_BEYOND_LIMIT]
    assert audit.violations[0].registers["NEW_CMD_POS"] == 0x1001


def test_clearing_f0_mid_profile_is_position_mode_while_moving() -> None:
    chip, _, audit = ready()
    start_trapezoid(chip, chip.command_position + 1024)
    for _ in range(100):
        chip.step()
    chip.bus_write(Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, False))
    assert rules(audit) == [Rule.POSITION_MODE_WHILE_MOVING]
    assert "trapezoid" in audit.violations[0].detail


def test_clearing_flags_after_the_profile_ended_is_fine() -> None:
    chip, _, audit = ready()
    start_trapezoid(chip, chip.command_position + 100)
    run_profile(chip)
    for _ in range(100):
        chip.step()
    for flag in (Flag.F0_TRAPEZOID, Flag.F3_PROPORTIONAL_VELOCITY, Flag.F5_INTEGRAL_VELOCITY):
        chip.bus_write(Reg.FLAG, flag_write(flag, False))
    assert audit.violations == []


def test_leaving_velocity_mode_while_turning_is_audited_but_not_at_rest() -> None:
    chip, _, audit = ready(gain=0xFF)
    chip.bus_write(Reg.FLAG, flag_write(Flag.F3_PROPORTIONAL_VELOCITY, True))
    for _ in range(50):  # commanded velocity 0: nothing moves
        chip.step()
    chip.bus_write(Reg.FLAG, flag_write(Flag.F3_PROPORTIONAL_VELOCITY, False))
    assert audit.violations == []
    chip.bus_write(Reg.CMD_VEL_LSB, 0x20)
    chip.bus_write(Reg.FLAG, flag_write(Flag.F3_PROPORTIONAL_VELOCITY, True))
    for _ in range(100):
        chip.step()
    chip.bus_write(Reg.FLAG, flag_write(Flag.F3_PROPORTIONAL_VELOCITY, False))
    assert rules(audit) == [Rule.POSITION_MODE_WHILE_MOVING]


def test_committing_far_from_a_moving_head_is_audited() -> None:
    chip, _, audit = ready()
    start_trapezoid(chip, chip.command_position + 1024)
    run_profile(chip)  # F0 is clear, but the head still runs in on the final position
    commit(chip, chip.actual_position + 10)  # near: no jump
    assert audit.violations == []
    commit(chip, chip.actual_position + 500)
    assert rules(audit) == [Rule.POSITION_MODE_WHILE_MOVING]
    audit.clear()
    for _ in range(2000):
        chip.step()
    commit(chip, chip.actual_position + 500)  # at rest: an ordinary position-control move
    assert audit.violations == []


def test_entering_position_control_while_coasting_is_audited() -> None:
    chip, _, audit = make_chip()
    configure(chip)
    chip.bus_write(Reg.MOTOR_COMMAND, 0xFF)
    for _ in range(100):
        chip.step()
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x03)
    assert rules(audit) == [Rule.POSITION_MODE_WHILE_MOVING]


def test_motion_before_gain_and_timer_are_written_is_audited() -> None:
    chip, _, audit = make_chip()
    chip.bus_write(Reg.FILTER_GAIN, 0x3F)  # but no sample timer
    hold_here(chip)
    assert audit.violations == []  # holding still is not a move
    start_trapezoid(chip, 100)
    assert rules(audit) == [Rule.MOTION_WHILE_UNINITIALISED]
    assert "R0FH" in audit.violations[0].detail
    audit.clear()
    chip.reset()
    chip.bus_write(Reg.SAMPLE_TIMER, 0xAF)
    chip.bus_write(Reg.FLAG, flag_write(Flag.F5_INTEGRAL_VELOCITY, True))
    chip.bus_write(Reg.PROGRAM_COUNTER, 0x03)
    assert rules(audit) == [Rule.MOTION_WHILE_UNINITIALISED]
    assert "gain" in audit.violations[0].detail


def test_a_correct_driver_sequence_breaks_no_rule() -> None:
    chip, _, audit = ready()
    for destination in (1024, -1024, 0x1000, -0x1000, 0):
        start_trapezoid(chip, destination)
        run_profile(chip)
        for _ in range(200):
            chip.step()
    configure(chip, gain=0x20)  # BIRIS_MOTOR_PARAMS while holding
    assert chip.actual_position == 0
    assert audit.violations == []
