"""The pan-axis plant: encoder quantisation, index latch, friction, stall, seeded power-up."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sim.motor import COUNTS_PER_REV, MotorPlant, PlantParams

DT = 16 * (0xAF + 1) / 2_000_000  # Appendix B's sample period, 1.408 ms


def plant_at(azimuth: float) -> MotorPlant:
    return MotorPlant(np.random.default_rng(0), initial_azimuth_counts=azimuth)


def test_encoder_starts_at_zero_and_counts_whole_edges() -> None:
    plant = plant_at(100.7)
    assert plant.encoder_counts == 0
    crossed = set()
    for _ in range(200):
        plant.step(40, DT)
        true = plant.true_azimuth_counts
        assert plant.encoder_counts == math.floor(true) - 100
        crossed.add(plant.encoder_counts)
    assert plant.true_azimuth_counts > 120.0  # it really moved, through many edges
    assert len(crossed) > 10
    for _ in range(400):  # and back below where it started
        plant.step(-60, DT)
        assert plant.encoder_counts == math.floor(plant.true_azimuth_counts) - 100
    assert plant.encoder_counts < 0


def test_index_latches_when_crossing_true_zero_and_clears() -> None:
    plant = plant_at(-30.5)
    while plant.true_azimuth_counts < 0.0:
        assert not plant.index_seen
        plant.step(30, DT)
    assert plant.index_seen
    plant.clear_index()
    assert not plant.index_seen
    for _ in range(20):  # moving on without crossing again leaves it clear
        plant.step(30, DT)
    assert plant.true_azimuth_counts < COUNTS_PER_REV
    assert not plant.index_seen


def test_index_repeats_every_revolution_and_in_reverse() -> None:
    plant = plant_at(COUNTS_PER_REV + 20.25)  # one turn plus 20 counts
    while plant.true_azimuth_counts > COUNTS_PER_REV:
        assert not plant.index_seen
        plant.step(-30, DT)
    assert plant.index_seen


def test_power_up_azimuth_is_seeded() -> None:
    first = [MotorPlant(np.random.default_rng(7)).true_azimuth_counts for _ in range(2)]
    other = MotorPlant(np.random.default_rng(8)).true_azimuth_counts
    assert first[0] == first[1]
    assert other != first[0]
    rng = np.random.default_rng(3)
    azimuths = [MotorPlant(rng).true_azimuth_counts for _ in range(200)]
    assert all(-2048.0 <= a < 2048.0 for a in azimuths)
    assert min(azimuths) < -1500.0 and max(azimuths) > 1500.0  # spread over the revolution
    assert MotorPlant(rng).encoder_counts == 0


def test_friction_holds_against_a_small_command() -> None:
    plant = plant_at(0.5)
    for _ in range(500):
        plant.step(2, DT)
    assert plant.velocity_counts_per_s == 0.0
    assert plant.true_azimuth_counts == 0.5
    assert plant.holds_at_rest(2)
    assert not plant.holds_at_rest(10)
    for _ in range(50):
        plant.step(10, DT)
    assert plant.velocity_counts_per_s > 0.0


def test_full_command_reaches_the_documented_no_load_speed() -> None:
    plant = plant_at(0.0)
    for _ in range(500):  # 0.7 s, many time constants
        plant.step(127, DT)
    # 3.9 rad/s at 10 V less friction, at 127/128 of full scale: about 2500 counts/s
    assert 2350.0 < plant.velocity_counts_per_s < 2560.0


def test_coasting_head_stops_on_friction_and_stays() -> None:
    plant = plant_at(0.0)
    for _ in range(100):
        plant.step(100, DT)
    for _ in range(200):
        plant.step(0, DT)
    assert plant.velocity_counts_per_s == 0.0
    where = plant.true_azimuth_counts
    assert plant.holds_at_rest(0)
    plant.step(0, DT)
    assert plant.true_azimuth_counts == where


def test_integration_is_stable_with_long_steps() -> None:
    fine, coarse = plant_at(0.0), plant_at(0.0)
    for _ in range(400):
        fine.step(80, DT)
    for _ in range(20):
        coarse.step(80, 20 * DT)  # 28 ms steps: still exact for the linear part
    assert coarse.velocity_counts_per_s == pytest.approx(fine.velocity_counts_per_s, rel=0.01)
    assert coarse.true_azimuth_counts == pytest.approx(fine.true_azimuth_counts, rel=0.02)


def test_stalled_shaft_neither_moves_nor_counts_and_recovers() -> None:
    plant = plant_at(10.5)
    for _ in range(20):
        plant.step(100, DT)
    plant.stalled = True
    assert plant.velocity_counts_per_s == 0.0
    where, counts = plant.true_azimuth_counts, plant.encoder_counts
    for _ in range(100):
        plant.step(127, DT)
    assert (plant.true_azimuth_counts, plant.encoder_counts) == (where, counts)
    assert plant.holds_at_rest(127)
    plant.stalled = False
    assert not plant.holds_at_rest(127)  # the current built up while it was held
    plant.step(127, DT)
    assert plant.true_azimuth_counts > where


@pytest.mark.parametrize(
    "field", ["resistance_ohm", "inductance_h", "torque_constant", "inertia", "full_scale_volts"]
)
def test_params_refuse_non_positive_constants(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(PlantParams(), **{field: 0.0})


def test_params_refuse_negative_friction_and_zero_substeps() -> None:
    with pytest.raises(ValueError):
        PlantParams(coulomb_friction=-0.1)
    with pytest.raises(ValueError):
        PlantParams(substeps=0)
