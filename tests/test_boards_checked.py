"""Boards that are checked, not assumed (issue 26, items 10 and 12).

What the driver assumes a board did is read back: the counter after the R13H clear, after a
chip reset, the index latch after it is cleared. Each check is proved by a simulated board that
behaves otherwise (``sim.hctl1000.ChipVariant``, ``sim.tech80.BoardVariant``): the driver falls
back to the datasheet's software reset where there is one, and otherwise refuses with a
``protocol`` fault naming the register, and never commits a command far from the head (the
simulator's audit, checked after every test, records such a jump as
POSITION_MODE_WHILE_MOVING). Without the checks these tests fail: a jump, a wrong zero, or
"pan position lost".

Item 12: a board whose INDEX_STATUS is the index's live level is homed by a slow sweep that
polls it, chosen in the target file (``[homing] index = "level"``).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from biris_hw import BirisInitRecord, MotorParams
from biris_hw.bus.base import BusWindow
from biris_hw.devices import AxisDriver, IndexKind, MotionBoard
from biris_hw.errors import HardwareFault, RequestError
from biris_hw.server import BirisServer
from biris_hw.server.initialiser import level_poll_s
from biris_hw.target import target_from_dict
from regs.hctl1000 import Reg
from regs.tech80 import Axis, BoardReg
from sim import SimulatedBiris
from sim.audit import Audit, Rule
from sim.clock import SimClock
from sim.hctl1000 import ChipVariant, Mode
from sim.motor import COUNTS_PER_REV, MotorPlant
from sim.tech80 import BoardVariant, Model7600
from tests.conftest import WAIT, RigFactory

HOMED = 3.0
"""Counts from true zero (or level) a homed head may stand."""


def scan_to(server: BirisServer, degrees: float) -> None:
    conn = server.open()
    conn.single_scan(degrees)
    conn.wait_idle(timeout=WAIT)
    conn.close()


def vary_chips(rig: SimulatedBiris, variant: ChipVariant) -> None:
    with rig.board.lock:
        for chip in rig.board.chips:
            chip.variant = variant


def vary_board(rig: SimulatedBiris, variant: BoardVariant) -> None:
    with rig.board.lock:
        rig.board.variant = variant


# -- a board and its drivers, no server ------------------------------------------------------------


class StillClock(SimClock):
    """Hardware time that stands still: the head stays where it is put."""

    def __init__(self) -> None:
        super().__init__(1.0)

    def now(self) -> float:
        return 0.0


class Bench:
    """A Model 7600 (pan plant at true count ``true``, its counter reading 700) and the
    driver's board and pan driver over its window."""

    def __init__(self, true: float = 700.5) -> None:
        self.clock = StillClock()
        self.audit = Audit(self.clock.now)
        plant = MotorPlant(np.random.default_rng(1), initial_azimuth_counts=true)
        self.board = Model7600(
            self.clock,
            np.random.default_rng(2),
            raise_irq=lambda: None,
            audit=self.audit,
            azimuth_plant=plant,
        )
        self.chip = self.board.azimuth
        self.chip.poke(Reg.ACT_POS_MID, 0x02)
        self.chip.poke(Reg.ACT_POS_LSB, 0xBC)  # counter 700
        self.window: BusWindow = self.board.window()
        self.pan = AxisDriver(self.window, Axis.AZIMUTH, self.clock.now)
        self.tilt = AxisDriver(self.window, Axis.ELEVATION, self.clock.now)
        self.driver_board = MotionBoard(
            self.window, {Axis.AZIMUTH: self.pan, Axis.ELEVATION: self.tilt}
        )

    def close(self) -> None:
        self.window.close()


@pytest.fixture
def bench() -> Iterator[Bench]:
    b = Bench()
    yield b
    b.close()


def test_a_hold_that_zeroes_reads_the_counter_back(bench: Bench) -> None:
    bench.pan.configure(MotorParams())
    bench.pan.hold_here(zero_counter=True)
    assert bench.chip.actual_position == 0 and bench.chip.command_position == 0
    assert bench.chip.mode is Mode.POSITION
    assert bench.audit.violations == []


def test_an_r13h_that_does_not_clear_falls_back_to_the_software_reset(
    bench: Bench, caplog: pytest.LogCaptureFixture
) -> None:
    bench.chip.variant = ChipVariant(r13h_clears=False)
    bench.pan.configure(MotorParams(gain=0x20))
    with caplog.at_level(logging.WARNING, logger="biris_hw.devices"):
        bench.pan.hold_here(zero_counter=True)
    assert "R05H = 00H" in caplog.text
    assert bench.chip.actual_position == 0 and bench.chip.command_position == 0
    assert bench.chip.mode is Mode.POSITION
    assert bench.chip.filter[2] == 0x20, "the parameters were loaded again after the reset"
    assert bench.audit.violations == []


def test_a_counter_that_nothing_clears_is_refused_and_nothing_is_committed(bench: Bench) -> None:
    bench.chip.variant = ChipVariant(r13h_clears=False, reset_clears=False)
    bench.pan.configure(MotorParams())
    with pytest.raises(HardwareFault) as refused:
        bench.pan.hold_here(zero_counter=True)
    assert refused.value.kind == "protocol"
    assert "R13H" in refused.value.message and "R05H" in refused.value.message
    assert bench.chip.mode is not Mode.POSITION, "control was never entered"
    assert bench.audit.violations == []


def test_without_the_read_back_the_simulator_sees_the_jump(bench: Bench) -> None:
    """What the unchecked driver did (R13H, command 0, control) on a chip that kept counting:
    the audit's jump rule, which the tests above rely on."""
    bench.chip.variant = ChipVariant(r13h_clears=False)
    bench.pan.configure(MotorParams())
    bench.window.write8(Reg.ACT_POS_MID, 0)
    for reg in (Reg.CMD_POS_MSB, Reg.CMD_POS_MID, Reg.CMD_POS_LSB):
        bench.window.write8(reg, 0)
    bench.window.write8(Reg.PROGRAM_COUNTER, 0x03)
    assert [v.rule for v in bench.audit.violations] == [Rule.POSITION_MODE_WHILE_MOVING]
    assert "jumps" in bench.audit.violations[0].detail


def test_a_chip_reset_is_read_back_and_the_software_reset_stands_in(
    bench: Bench, caplog: pytest.LogCaptureFixture
) -> None:
    bench.driver_board.reset_chip(Axis.AZIMUTH)
    assert bench.chip.actual_position == 0
    bench.chip.poke(Reg.ACT_POS_LSB, 0x40)
    vary = BoardVariant(chip_reset=False)
    bench.board.variant = vary
    with caplog.at_level(logging.WARNING, logger="biris_hw.devices"):
        bench.driver_board.reset_chip(Axis.AZIMUTH)
    assert "CHIP_RESET" in caplog.text
    assert bench.chip.actual_position == 0
    bench.chip.poke(Reg.ACT_POS_LSB, 0x40)
    bench.chip.variant = ChipVariant(reset_clears=False)
    with pytest.raises(HardwareFault) as refused:
        bench.driver_board.reset_chip(Axis.AZIMUTH)
    assert refused.value.kind == "protocol"
    assert f"0x{int(BoardReg.CHIP_RESET):02X}" in refused.value.message
    assert "R05H" in refused.value.message
    assert bench.audit.violations == []


def test_an_index_that_still_shows_after_a_clear_is_refused() -> None:
    on_index = Bench(true=4096.5)  # on the index, one revolution round
    try:
        on_index.driver_board.clear_index(Axis.AZIMUTH)  # a latch, never crossed: clear
        on_index.board.variant = BoardVariant(index="level")  # the live level: it shows
        with pytest.raises(HardwareFault) as refused:
            on_index.driver_board.clear_index(Axis.AZIMUTH, check=True)
        assert refused.value.kind == "protocol"
        assert "INDEX_STATUS" in refused.value.message and '"level"' in refused.value.message
    finally:
        on_index.close()


def test_index_and_position_are_read_together(bench: Bench) -> None:
    bench.board.variant = BoardVariant(index="level")
    assert bench.driver_board.index_and_position(Axis.AZIMUTH) == (False, 700)
    on_index = Bench(true=0.25)
    try:
        on_index.board.variant = BoardVariant(index="level")
        assert on_index.driver_board.index_and_position(Axis.AZIMUTH) == (True, 700)
    finally:
        on_index.close()


# -- the server on boards that differ --------------------------------------------------------------


def test_an_r13h_that_does_not_clear_still_homes_on_true_zero(
    make_rig: RigFactory, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: the index found, R13H written (ignored), command 0 committed with the counter
    170 counts away: the head jumped (audit) and zero was where the head jumped to."""
    rig = make_rig(initial_azimuth_counts=170.0)
    vary_chips(rig, ChipVariant(r13h_clears=False))
    with (
        caplog.at_level(logging.WARNING, logger="biris_hw.devices"),
        BirisServer(rig.hardware, BirisInitRecord()) as server,
    ):
        assert abs(rig.azimuth_counts) <= HOMED
        assert abs(rig.elevation_counts) <= HOMED
        scan_to(server, 90.0)
        assert abs(rig.azimuth_counts - 1024) <= HOMED
    assert "R13H" in caplog.text


def test_a_counter_nothing_clears_fails_initialisation_with_protocol(
    make_rig: RigFactory,
) -> None:
    rig = make_rig(initial_azimuth_counts=170.0)
    vary_chips(rig, ChipVariant(r13h_clears=False, reset_clears=False))
    with pytest.raises(HardwareFault) as refused:
        BirisServer(rig.hardware, BirisInitRecord())
    assert refused.value.kind == "protocol"
    assert "R13H" in refused.value.message and "R05H" in refused.value.message
    assert abs(rig.azimuth_counts) <= HOMED, "the head stayed on the index: nothing jumped"


def test_a_chip_reset_that_does_nothing_is_made_good_by_the_software_reset(
    make_rig: RigFactory, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: the reference took the count to restart at 0 at +90 degrees and looked for true
    zero's index a quarter turn away from it: "pan position lost" at every reset."""
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        scan_to(server, 90.0)
        vary_board(rig, BoardVariant(chip_reset=False))
        with caplog.at_level(logging.WARNING, logger="biris_hw.devices"):
            server.reset()
        assert "CHIP_RESET" in caplog.text
        assert abs(rig.azimuth_counts) <= HOMED
        scan_to(server, -45.0)
        assert abs(rig.azimuth_counts + 512) <= HOMED
        vary_chips(rig, ChipVariant(reset_clears=False))
        scan_to(server, 45.0)
        with pytest.raises(HardwareFault) as refused:
            server.reset()
        assert refused.value.kind == "protocol"
        assert "CHIP_RESET" in refused.value.message


def test_an_index_latch_that_does_not_clear_is_refused(make_rig: RigFactory) -> None:
    """Before: every look after the first crossing saw the latch set, and the bisection homed
    on the low end of the bracket, up to 256 counts from the index."""
    rig = make_rig(initial_azimuth_counts=170.0)
    vary_board(rig, BoardVariant(index="stuck"))
    with pytest.raises(HardwareFault) as refused:
        BirisServer(rig.hardware, BirisInitRecord())
    assert refused.value.kind == "protocol"
    assert "INDEX_STATUS" in refused.value.message


def test_a_head_dithering_on_the_index_edge_is_no_stuck_latch(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A head at rest within a count of true zero's index crosses it as it dithers, so its
    latch sets again as it is cleared. The referenced pan's search starts standing on that
    index: before, its first read-back there failed every such reset as "INDEX_STATUS still
    shows the index" (a CI run of test_feed_survives, the head stopped on true zero by a reset
    during a sweep across it). The latch is read again a few counts off the index."""
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        assert rig.hardware.pan_reference.referenced
        pan = rig.board.plants[0]
        cleared = MotorPlant.clear_index

        def dithering(plant: MotorPlant) -> None:
            cleared(plant)
            if plant is pan:
                turn = plant.true_azimuth_counts % COUNTS_PER_REV
                if min(turn, COUNTS_PER_REV - turn) < 1.0:  # on the edge: crossed again at once
                    plant._index_seen = True

        monkeypatch.setattr(MotorPlant, "clear_index", dithering)
        assert abs(pan.true_azimuth_counts) < 1.0  # homed: standing on true zero's index
        with caplog.at_level(logging.INFO, logger="biris_hw.server.initialiser"):
            server.reset()
        assert "showed again where the head stood" in caplog.text
        assert abs(rig.azimuth_counts) <= HOMED
        assert rig.hardware.pan_reference.referenced
        scan_to(server, 10.0)


def test_a_level_index_homed_as_a_latch_says_what_to_check(make_rig: RigFactory) -> None:
    rig = make_rig(initial_azimuth_counts=170.0)
    vary_board(rig, BoardVariant(index="level"))
    with pytest.raises(HardwareFault) as refused:
        BirisServer(rig.hardware, BirisInitRecord())
    assert '[homing] index = "level"' in refused.value.message


# -- item 12: a live index level, homed by a slow sweep -------------------------------------------


@pytest.mark.parametrize(
    ("woke", "width"), [(170.0, 1), pytest.param(-300.0, 4, marks=pytest.mark.slow)]
)
def test_a_live_index_level_is_homed_by_a_slow_sweep(
    make_rig: RigFactory, woke: float, width: int
) -> None:
    rig = make_rig(initial_azimuth_counts=woke)
    vary_board(rig, BoardVariant(index="level", index_width=float(width)))
    board = rig.hardware.devices.board
    assert isinstance(board, MotionBoard)
    board.set_index(IndexKind.LEVEL, width)
    started = rig.clock.now()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        print(f"level homing from {woke:+.0f} counts: {rig.clock.now() - started:.2f} s hw")
        assert abs(rig.azimuth_counts) <= HOMED
        assert abs(rig.elevation_counts) <= HOMED
        assert rig.hardware.pan_reference.referenced
        chip = rig.board.azimuth
        assert chip.filter[2] == MotorParams().gain and chip.max_velocity == MotorParams().max_vel
        scan_to(server, 90.0)
        assert abs(rig.azimuth_counts - 1024) <= HOMED
        server.reset()  # referenced now: the narrow window around true zero
        assert abs(rig.azimuth_counts) <= HOMED


def test_a_level_polled_too_seldom_is_swept_again_then_refused(
    make_rig: RigFactory, caplog: pytest.LogCaptureFixture
) -> None:
    """Every read 10 ms late: the polls are counts apart, and a pulse could pass between them."""
    rig = make_rig(initial_azimuth_counts=170.0)
    vary_board(rig, BoardVariant(index="level"))
    board = rig.hardware.devices.board
    assert isinstance(board, MotionBoard)
    board.set_index("level")
    rig.faults.slow_reads(0.01)
    with (
        caplog.at_level(logging.WARNING, logger="biris_hw.server.initialiser"),
        pytest.raises(HardwareFault) as refused,
    ):
        BirisServer(rig.hardware, BirisInitRecord())
    rig.faults.clear_slow_reads()
    assert refused.value.kind == "timeout"
    assert "polled often enough" in refused.value.message
    assert "sweeping" in caplog.text


def test_the_poll_period_fits_the_pulse() -> None:
    """At Appendix B's sample timer a slow sweep peaks near 250 counts/s: a 1-count pulse
    lasts 4 ms, polled 2.5 times."""
    poll = level_poll_s(MotorParams())
    assert 0.0015 < poll < 0.0017
    assert level_poll_s(MotorParams(), 4) == pytest.approx(4 * poll)


# -- the target file -------------------------------------------------------------------------------


def _target(extra: dict[str, Any]) -> dict[str, Any]:
    return {
        "biris": {"kind": "memory", "size": 0x2000},
        "motion": {"kind": "memory", "size": 0x100},
        "coupler": {"kind": "memory", "size": 0x20},
        "level2": {"kind": "eventfd"},
        "level3": {"kind": "eventfd"},
        "pan_journal": "",
        **extra,
    }


def test_the_target_file_chooses_the_homing(no_leaks: None) -> None:
    hw = target_from_dict(_target({}))
    try:
        board = hw.devices.board
        assert isinstance(board, MotionBoard) and board.index_kind is IndexKind.LATCH
    finally:
        hw.close()
    hw = target_from_dict(_target({"homing": {"index": "level", "index_width": 2}}))
    try:
        board = hw.devices.board
        assert isinstance(board, MotionBoard)
        assert (board.index_kind, board.index_width) == (IndexKind.LEVEL, 2)
    finally:
        hw.close()


@pytest.mark.parametrize(
    ("homing", "says"),
    [
        ({"index": "pulse"}, "homing.index: must be one of 'latch', 'level'"),
        ({"index": "latch", "index_width": 2}, 'homing.index_width: only with index = "level"'),
        ({"index": "level", "index_width": 0}, "homing.index_width"),
        ({"index": "level", "width": 2}, "homing.width: not an option"),
        ("level", "homing: must be a table"),
    ],
)
def test_a_bad_homing_table_is_refused_by_name(
    homing: object, says: str, no_leaks: None, tmp_path: Path
) -> None:
    with pytest.raises(RequestError) as refused:
        target_from_dict(_target({"homing": homing}))
    assert says in str(refused.value)
