"""The simulator's fast paths compute exactly what the plain model does, bit for bit.

The per-sample code of the HCTL-1000 and its plant is written for speed (plain floats, names
looked up once, the filter written out, idle samples skipped); these tests hold it to the plain
formulation: the motor's sub-step as its docstring writes it, and a chip caught up by many
small ``advance_to`` calls against one stepped sample by sample.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from regs.hctl1000 import Reg, sample_period
from sim.hctl1000 import Hctl1000
from sim.motor import MotorPlant

PERIOD_B = sample_period(0xAF)


def _reference_step(plant: MotorPlant, state: list[float], index: list[bool], mc: int) -> None:
    """One ``MotorPlant.step`` as the module docstring writes it: numpy discretisation (numpy
    scalars), ``f * friction`` per sub-step, no precomputed constants."""
    p = plant.params
    d = plant._discretise(PERIOD_B)
    volts = mc * (p.full_scale_volts / 128.0)
    theta, omega, cur = state
    (p0w, p0i), (p1w, p1i), (p2w, p2i) = d.phi
    v0, v1, v2 = d.volt[0] * volts, d.volt[1] * volts, d.volt[2] * volts
    f0, f1, f2 = d.fric
    k, coulomb, cpr = p.torque_constant, p.coulomb_friction, p.counts_per_rev
    target = volts / p.resistance_ohm
    low = math.floor(theta / cpr) * cpr
    high = low + cpr
    for _ in range(p.substeps):
        if omega == 0.0:
            torque = k * cur
            if -coulomb <= torque <= coulomb:
                cur = target + (cur - target) * d.stuck_decay
                continue
            friction = coulomb if torque > 0.0 else -coulomb
        else:
            friction = coulomb if omega > 0.0 else -coulomb
        theta += p0w * omega + p0i * cur + v0 + f0 * friction
        new_omega = p1w * omega + p1i * cur + v1 + f1 * friction
        cur = p2w * omega + p2i * cur + v2 + f2 * friction
        if (new_omega > 0.0) != (friction > 0.0) and -coulomb <= k * cur <= coulomb:
            new_omega = 0.0
        omega = new_omega
        if theta < low or theta >= high:
            index[0] = True
            low = math.floor(theta / cpr) * cpr
            high = low + cpr
    state[:] = [theta, omega, cur]


def test_plant_step_is_the_plain_integration_bit_for_bit() -> None:
    rng = np.random.default_rng(7)
    plant = MotorPlant(rng, initial_azimuth_counts=4090.25)  # near an index crossing
    state = [plant.true_azimuth_counts, 0.0, 0.0]
    index = [False]
    commands = [0, 3, -3, 127, 127, 60, 0, 0, -128, -40, 2, 1, 0] + [
        int(c) for c in rng.integers(-128, 128, 3000)
    ]
    commands += [0] * 400 + [int(c) for c in rng.integers(-6, 7, 600)]
    for mc in commands:
        plant.step(mc, PERIOD_B)
        _reference_step(plant, state, index, mc)
        got = (plant.true_azimuth_counts, plant.velocity_counts_per_s, plant.current_a)
        want = (state[0], state[1] * plant._counts_per_rad, state[2])
        assert [x.hex() for x in map(float, got)] == [x.hex() for x in map(float, want)]
        assert plant.index_seen == index[0]
    assert index[0]  # the index was crossed at least once


def _ready(azimuth: float = 100.25) -> Hctl1000:
    plant = MotorPlant(np.random.default_rng(0), initial_azimuth_counts=azimuth)
    chip = Hctl1000("azimuth", plant)
    for reg, value in (
        (Reg.SAMPLE_TIMER, 0xAF),
        (Reg.FILTER_ZERO, 0x7F),
        (Reg.FILTER_POLE, 0xEF),
        (Reg.FILTER_GAIN, 0x3F),
        (Reg.MAX_VELOCITY, 2),
        (Reg.ACCEL_LSB, 0x22),
        (Reg.ACCEL_MSB, 0x33),
        (Reg.PROGRAM_COUNTER, 0x03),
    ):
        chip.bus_write(reg, value)
    return chip


def _start(chip: Hctl1000, destination: int) -> None:
    raw = destination & 0xFF_FFFF
    chip.bus_write(Reg.FINAL_POS_LSB, raw & 0xFF)
    chip.bus_write(Reg.FINAL_POS_MID, (raw >> 8) & 0xFF)
    chip.bus_write(Reg.FINAL_POS_MSB, raw >> 16)
    chip.bus_write(Reg.FLAG, 0x08)  # F0 on: the trapezoid starts


def _state(chip: Hctl1000) -> tuple[object, ...]:
    plant = chip.plant
    return (
        chip.actual_position,
        chip.command_position,
        chip.flags,
        chip.motor_command,
        chip.mode,
        float(plant.true_azimuth_counts).hex(),
        float(plant.velocity_counts_per_s).hex(),
        float(plant.current_a).hex(),
        plant.index_seen,
    )


@pytest.mark.parametrize("catch_up", [0.4, 1.0, 1.5, 1.9])
def test_catching_up_in_small_steps_equals_stepping(catch_up: float) -> None:
    """Catch-ups shorter than two sample periods never skip a pair: every sample is simulated,
    through ``step()`` or the fixed-point shortcut, and nothing may differ, not even the held
    motor's winding current."""
    stepped, caught = _ready(), _ready()
    ends: list[tuple[str, int]] = []
    stepped.on_profile_end = lambda: ends.append(("stepped", stepped.command_position))
    caught.on_profile_end = lambda: ends.append(("caught", caught.command_position))
    t = caught.next_sample_time
    for destination in (stepped.command_position + 300, -250, -250, 40, 41):
        for chip in (stepped, caught):
            _start(chip, destination)
        for _ in range(int(700 / catch_up)):  # the move, then a long hold in a fixed point
            t += catch_up * PERIOD_B
            caught.advance_to(t)
            while stepped.next_sample_time < caught.next_sample_time - PERIOD_B / 2:
                stepped.step()
            assert stepped.next_sample_time == pytest.approx(caught.next_sample_time)
            assert _state(stepped) == _state(caught)
    assert [pos for who, pos in ends if who == "stepped"] == [
        pos for who, pos in ends if who == "caught"
    ]
    assert len(ends) == 10


def test_a_stall_cleared_in_a_fixed_point_lets_the_head_move() -> None:
    """A locked shaft whose profile has ended sits in a fixed point (the drive pushing against
    the lock); clearing the stall through the backdoor (no bus access, no note to the chip)
    must let the next sample move again, in the skipping chip as in the stepped one."""
    stepped, caught = _ready(), _ready()
    start = stepped.actual_position
    for chip in (stepped, caught):
        chip.plant.stalled = True
        _start(chip, chip.command_position + 2)
    t = caught.next_sample_time
    for phase in range(2):
        for _ in range(400):
            t += 1.5 * PERIOD_B
            caught.advance_to(t)
            while stepped.next_sample_time < caught.next_sample_time - PERIOD_B / 2:
                stepped.step()
            assert _state(stepped) == _state(caught)
        assert not caught.profile_active
        assert caught.actual_position == start + 2 * phase  # locked, then arrived
        for chip in (stepped, caught):
            chip.plant.stalled = False
