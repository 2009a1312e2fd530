"""Position integrity (issue 11, defect 1): the pan is homed on TRUE zero's index, never the
nearest one, across resets, new servers and restarted driver processes, and nothing is ever
commanded beyond +-0x1000 of true zero.

The end-to-end tests spy on every pan move the driver records and turn its destination into
TRUE counts with the simulator's backdoor (the plant's azimuth minus the chip's counter at that
moment), so they check the head's envelope against the truth, not against the driver's own
bookkeeping; the simulator's HEAD_BEYOND_LIMIT audit (checked after every test) watches the
head itself. A restarted driver process is a second hardware bundle over the same simulator,
with the same journal file: all a new process would share with the old one.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from biris_hw import BirisInitRecord, MotorParams
from biris_hw.errors import HardwareFault
from biris_hw.hardware import BirisHardware
from biris_hw.pan_reference import (
    FRESH_HALF_RANGE,
    JOURNAL_ENV,
    SLACK,
    PanReference,
    default_journal_path,
    forget_journal,
    index_search_range,
)
from biris_hw.server import BirisServer
from regs.hctl1000 import COUNTS_PER_REV, MOTION_LIMIT_COUNTS
from sim import SimulatedBiris
from tests.conftest import RigFactory

WAIT = 30.0
"""Real seconds for a scan that takes well under one at x30; reached only when a test fails."""

HOMED = 3.0
"""Counts from true zero a homed head may stand (the index edge, settling)."""

OVERSHOOT = 64.0
"""Counts a move may overshoot its destination (the filter; the audit's own allowance)."""

POWER_UP = {"sample": 64, "zero": 229, "pole": 0, "gain": 64, "max_vel": 0, "max_accel": 0}
"""The simulated chip's parameters after a reset or power-up (sim.hctl1000.POWER_UP)."""

PARAMS = MotorParams().to_dict()


# -- helpers ---------------------------------------------------------------------------------------


class TrueMoves:
    """Every pan destination a bundle's driver writes, in TRUE counts, and the true head there.

    Installed on the bundle's :class:`PanReference` (the pan driver records each move there just
    before it commands it); the simulator says where the head truly is and what the counter
    reads at that moment, so ``destination + (true - counter)`` is where the move truly goes.
    """

    def __init__(self, rig: SimulatedBiris, hardware: BirisHardware, mp: pytest.MonkeyPatch):
        self.destinations: list[float] = []
        self.heads: list[float] = []
        reference = hardware.pan_reference
        record = reference.record_move

        def spy(start: int, destination: int) -> None:
            with rig.board.lock:
                rig.board.catch_up()
                true = rig.board.plants[0].true_azimuth_counts
                offset = true - rig.board.azimuth.actual_position
            self.destinations.append(destination + offset)
            self.heads.append(true)
            record(start, destination)

        mp.setattr(reference, "record_move", spy)

    def assert_within_envelope(self) -> None:
        assert self.destinations, "no pan move was recorded"
        worst = max(abs(d) for d in self.destinations)
        assert worst <= MOTION_LIMIT_COUNTS + HOMED, f"a move went to {worst:.1f} true counts"
        assert max(abs(h) for h in self.heads) <= MOTION_LIMIT_COUNTS + OVERSHOOT


def process(rig: SimulatedBiris, journal: Path | None) -> BirisHardware:
    """A driver process's own hardware bundle over the simulator: its own drivers and its own
    pan reference (read from ``journal``), over the rig's windows and lines. The rig closes
    those; the bundle is left unclosed on purpose, since it owns nothing."""
    hw = rig.hardware
    return BirisHardware(
        biris=hw.biris,
        motion=hw.motion,
        coupler=hw.coupler,
        level2=hw.level2,
        level3=hw.level3,
        biexec_offset=hw.biexec_offset,
        biris_base=hw.biris_base,
        clock=hw.clock,
        time_scale=hw.time_scale,
        pan_journal=journal,
    )


def scan_to(server: BirisServer, degrees: float) -> None:
    conn = server.open()
    conn.single_scan(degrees)
    conn.wait_idle(timeout=WAIT)
    conn.close()


def power_cycle_pan_chip(rig: SimulatedBiris) -> None:
    """What a power cut does to the pan chip while no driver runs: its count restarts where the
    head stands, its registers go back to their power-up values (a board chip reset does
    exactly that; the head keeps its true position)."""
    with rig.board.lock:
        rig.board.catch_up()
        rig.board.azimuth.reset()


def write_journal(path: Path, **fields: Any) -> None:
    document = {
        "format": "biris-hw pan reference",
        "version": 1,
        "offset": [0, 0],
        "move": [0, 0],
        "params": PARAMS,
    }
    document.update(fields)
    path.write_text(json.dumps(document))


def read_journal(path: Path) -> dict[str, Any]:
    return dict(json.loads(path.read_text()))


# -- the defect, in process ----------------------------------------------------------------------


def test_every_reset_homes_to_true_zero_not_the_nearest_index(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The repro: three rounds of a scan to +360 degrees and a reset. Before, each reset zeroed
    on the index at +360 and the head ended three revolutions round."""
    rig = make_rig(initial_azimuth_counts=100.0)
    moves = TrueMoves(rig, rig.hardware, monkeypatch)
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        assert abs(rig.azimuth_counts) <= HOMED
        for _ in range(3):
            scan_to(server, 360.0)
            assert abs(rig.azimuth_counts - COUNTS_PER_REV) <= HOMED
            server.reset()
            assert abs(rig.azimuth_counts) <= HOMED, "the reset homed on the wrong revolution"
            assert server.status()["azimuth_live"] == pytest.approx(0, abs=HOMED)
    moves.assert_within_envelope()
    assert rig.hardware.pan_reference.referenced


@pytest.mark.parametrize("degrees", [45.0, pytest.param(-45.0, marks=pytest.mark.slow)])
def test_a_reset_with_the_tilt_at_its_limit_finds_level(
    make_rig: RigFactory, degrees: float
) -> None:
    """The tilt counts from level once homed: a reset reads that count before the chip reset
    and searches around level, not around the tilted head (at the limit, level was on the edge
    of the search and the reset failed with "no zero index")."""
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        conn = server.open()
        conn.set_elevation(degrees)
        conn.wait_idle(timeout=WAIT)
        assert abs(rig.elevation_counts) > 400
        server.reset()
        assert abs(rig.elevation_counts) <= HOMED
        assert server.status()["elevation_live"] == pytest.approx(0, abs=HOMED)


def test_a_new_server_on_the_same_bundle_homes_to_true_zero(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    rig = make_rig(initial_azimuth_counts=-300.0)
    moves = TrueMoves(rig, rig.hardware, monkeypatch)
    with BirisServer(rig.hardware, BirisInitRecord()) as first:
        scan_to(first, -360.0)
    assert abs(rig.azimuth_counts + COUNTS_PER_REV) <= HOMED
    with BirisServer(rig.hardware, BirisInitRecord()):
        assert abs(rig.azimuth_counts) <= HOMED
    moves.assert_within_envelope()


@pytest.mark.parametrize("woke", [1500.0, pytest.param(-1900.0, marks=pytest.mark.slow)])
def test_a_fresh_start_away_from_zero_finds_true_zero(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch, woke: float
) -> None:
    """Within +-180 degrees (the operator's precondition) the only index the search may reach
    is true zero's, and it never goes further than half a revolution from where the head woke."""
    rig = make_rig(initial_azimuth_counts=woke)
    moves = TrueMoves(rig, rig.hardware, monkeypatch)
    record = BirisInitRecord(home_index_timeout_revs=2.0)  # asks for more than is ever allowed
    with BirisServer(rig.hardware, record):
        assert abs(rig.azimuth_counts) <= HOMED
    moves.assert_within_envelope()
    reach = max(abs(d - woke) for d in moves.destinations)
    assert reach <= FRESH_HALF_RANGE + 1  # the window is in whole counts of the encoder


# -- restarted driver processes: the journal ------------------------------------------------------


def test_a_restarted_driver_homes_to_true_zero_from_its_journal(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    journal = tmp_path / "pan.json"
    rig = make_rig(initial_azimuth_counts=100.0)
    old = process(rig, journal)
    with BirisServer(old, BirisInitRecord()) as server:
        scan_to(server, 360.0)
    assert abs(rig.azimuth_counts - COUNTS_PER_REV) <= HOMED
    saved = read_journal(journal)
    assert saved["offset"] == [0, 0]
    assert abs(saved["move"][1] - COUNTS_PER_REV) <= 1  # settled at the end of the scan
    assert saved["params"] == PARAMS

    new = process(rig, journal)
    moves = TrueMoves(rig, new, monkeypatch)
    assert new.pan_reference.referenced
    with BirisServer(new, BirisInitRecord()):
        assert abs(rig.azimuth_counts) <= HOMED
    moves.assert_within_envelope()
    assert read_journal(journal)["offset"] == [0, 0]


def test_a_power_cycled_chip_is_homed_from_where_the_journal_left_the_head(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The chip's count restarts at +270 degrees; the journal says the head stood there, and a
    head does not move without power: its true zero is searched for there, not around it."""
    journal = tmp_path / "pan.json"
    rig = make_rig(initial_azimuth_counts=0.0)
    with BirisServer(process(rig, journal), BirisInitRecord()) as server:
        scan_to(server, 270.0)
    power_cycle_pan_chip(rig)
    new = process(rig, journal)
    moves = TrueMoves(rig, new, monkeypatch)
    with BirisServer(new, BirisInitRecord()):
        assert abs(rig.azimuth_counts) <= HOMED  # the nearest index was +360's
    moves.assert_within_envelope()


def test_a_power_cut_during_a_long_move_is_position_lost(
    make_rig: RigFactory, tmp_path: Path
) -> None:
    """The journal's last record is a move from -360 to +360 degrees that never settled, and
    the chip lost its count: the head is somewhere in two revolutions, so no index can be known
    to be true zero's. Nothing moves; the operator's reset then searches afresh."""
    journal = tmp_path / "pan.json"
    rig = make_rig(initial_azimuth_counts=40.0)
    write_journal(journal, move=[-4096, 4096])
    before = rig.azimuth_counts
    with pytest.raises(HardwareFault) as caught:
        BirisServer(process(rig, journal), BirisInitRecord())
    assert caught.value.kind == "motor_stall"
    assert "pan position lost" in caught.value.message
    assert "chip lost its count" in caught.value.message
    assert abs(rig.azimuth_counts - before) <= 1.0
    assert read_journal(journal)["offset"] is None
    # the operator checked the head (within +-180 degrees): the reset searches afresh
    with BirisServer(process(rig, journal), BirisInitRecord()):
        assert abs(rig.azimuth_counts) <= HOMED
    assert read_journal(journal)["offset"] == [0, 0]


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_a_journal_that_does_not_fit_the_counter_is_not_believed(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The chip kept its parameters (no power cycle) but its counter is nowhere near the
    journal's last move: both explanations are searched (the counter's, the journal's), and
    the index found is true zero's because the window is cut where they agree."""
    journal = tmp_path / "pan.json"
    rig = make_rig(initial_azimuth_counts=0.0)
    with BirisServer(process(rig, journal), BirisInitRecord()) as server:
        scan_to(server, 90.0)
    write_journal(journal, move=[-2000, -2000])
    new = process(rig, journal)
    moves = TrueMoves(rig, new, monkeypatch)
    with BirisServer(new, BirisInitRecord()):
        assert abs(rig.azimuth_counts) <= HOMED
    moves.assert_within_envelope()


def test_a_journal_too_far_from_the_counter_is_position_lost(
    make_rig: RigFactory, tmp_path: Path
) -> None:
    journal = tmp_path / "pan.json"
    rig = make_rig(initial_azimuth_counts=0.0)
    with BirisServer(process(rig, journal), BirisInitRecord()) as server:
        scan_to(server, 90.0)
    write_journal(journal, move=[-4000, -4000], params=read_journal(journal)["params"])
    before = rig.azimuth_counts
    with pytest.raises(HardwareFault) as caught:
        BirisServer(process(rig, journal), BirisInitRecord())
    assert caught.value.kind == "motor_stall" and "outside the journal" in caught.value.message
    assert abs(rig.azimuth_counts - before) <= 1.0


def test_an_index_missing_from_the_narrow_window_is_position_lost(
    make_rig: RigFactory, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A journal that lies: it says the head stands on true zero with the chip's very count
    and parameters, but the head truly is 600 counts (53 degrees) away. The narrow window finds
    no index: "position lost", the head never leaves the window, and the reference is dropped,
    so the operator's reset searches afresh (and finds true zero, the head being within 180)."""
    journal = tmp_path / "pan.json"
    rig = make_rig(initial_azimuth_counts=600.0)
    write_journal(journal, params=rig.hardware.devices.azimuth.read_params())
    assert read_journal(journal)["params"] == POWER_UP
    liar = process(rig, journal)
    assert liar.pan_reference.referenced
    moves = TrueMoves(rig, liar, monkeypatch)
    with pytest.raises(HardwareFault) as caught:
        BirisServer(liar, BirisInitRecord())
    fault = caught.value
    assert fault.kind == "motor_stall"
    assert "pan position lost" in fault.message and "22.5 deg" in fault.message
    assert "within +-180 deg of dead ahead" in fault.message  # what the operator must do
    assert all(abs(d - 600.0) <= 256 + 3 for d in moves.destinations)
    assert liar.pan_reference.offset is None
    assert read_journal(journal)["offset"] is None
    with BirisServer(liar, BirisInitRecord()):
        assert abs(rig.azimuth_counts) <= HOMED
    moves.assert_within_envelope()


def test_an_unreadable_journal_is_position_lost_until_checked(
    make_rig: RigFactory, tmp_path: Path
) -> None:
    journal = tmp_path / "pan.json"
    journal.write_text("{ not json")
    rig = make_rig(initial_azimuth_counts=-200.0)
    hw = process(rig, journal)
    with pytest.raises(HardwareFault) as caught:
        BirisServer(hw, BirisInitRecord())
    assert "unreadable" in caught.value.message
    assert abs(rig.azimuth_counts + 200.0) <= 1.0
    with BirisServer(hw, BirisInitRecord()):  # the operator's reset after checking the head
        assert abs(rig.azimuth_counts) <= HOMED
    assert read_journal(journal)["offset"] == [0, 0]


# -- the reference without threads ----------------------------------------------------------------


def test_a_fresh_reference_assumes_the_precondition() -> None:
    reference = PanReference()
    where = reference.locate(300, POWER_UP)
    assert where.how == "fresh"
    assert where.offset == (-FRESH_HALF_RANGE - 300, FRESH_HALF_RANGE - 300)
    reference.chip_reset(300)
    assert reference.offset == (-FRESH_HALF_RANGE, FRESH_HALF_RANGE)
    assert reference.safe_destination(4096) == MOTION_LIMIT_COUNTS - FRESH_HALF_RANGE
    assert reference.safe_destination(-4096) == -MOTION_LIMIT_COUNTS + FRESH_HALF_RANGE


def test_a_kept_count_keeps_the_offset_through_resets() -> None:
    reference = PanReference()
    reference.homed()
    reference.configured(PARAMS)
    reference.record_move(0, 4096)
    reference.settled(4096)
    where = reference.locate(4096, PARAMS)
    assert (where.how, where.offset) == ("referenced", (0, 0))
    reference.chip_reset(4096)
    assert reference.offset == (4096, 4096) and reference.referenced
    assert reference.true_position(-4096) == (0, 0)
    reference.rezeroed(-3840)
    assert reference.offset == (256, 256)
    assert reference.safe_destination(4096) == MOTION_LIMIT_COUNTS - 256


def test_a_chip_that_lost_its_count_is_placed_by_the_recorded_span() -> None:
    reference = PanReference()
    reference.homed()
    reference.configured(PARAMS)
    reference.record_move(0, 1000)  # never settled: the head is somewhere in 0..1000
    where = reference.locate(3, POWER_UP)
    assert where.how == "chip reset"
    assert where.offset == (-SLACK, 1000 + SLACK)


def test_the_journal_round_trips(tmp_path: Path) -> None:
    path = tmp_path / "state" / "pan.json"  # the directory is made on the first write
    reference = PanReference(path)
    reference.homed()
    reference.configured(PARAMS)
    reference.record_move(0, -512)
    again = PanReference(path)
    assert again.state == reference.state
    assert again.referenced
    assert forget_journal(path) and not forget_journal(path)
    assert PanReference(path).offset is None


@pytest.mark.parametrize(
    "text",
    [
        "[]",
        '{"format": "other", "version": 1}',
        '{"format": "biris-hw pan reference", "version": 1, "offset": [5, 1], "move": [0, 0], '
        '"params": null}',
        '{"format": "biris-hw pan reference", "version": 1, "offset": [0, 0], "move": [0], '
        '"params": null}',
    ],
)
def test_a_malformed_journal_is_lost_not_guessed(tmp_path: Path, text: str) -> None:
    path = tmp_path / "pan.json"
    path.write_text(text)
    where = PanReference(path).locate(0, POWER_UP)
    assert where.lost and "unreadable" in where.reason


def test_a_journal_that_cannot_be_written_refuses_the_move(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("")
    reference = PanReference(blocker / "pan.json")
    with pytest.raises(HardwareFault) as caught:
        reference.record_move(0, 100)
    assert caught.value.kind == "internal" and "not moved" in caught.value.message


def test_the_default_journal_lives_in_the_state_directory(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv(JOURNAL_ENV, str(tmp_path))
    assert default_journal_path() == tmp_path / "pan-reference.json"
    assert default_journal_path("sim-rel1") == tmp_path / "pan-reference-sim-rel1.json"


@given(
    lo=st.integers(-6000, 6000),
    width=st.integers(0, MOTION_LIMIT_COUNTS),
    data=st.data(),
)
def test_the_search_window_is_safe_and_unambiguous(lo: int, width: int, data: Any) -> None:
    """Whichever offset of the interval is true: every counter of the window keeps the head
    strictly within +-0x1000 of true zero, so the only index it can meet is true zero's; and
    true zero itself lies in the window whenever the head may safely reach it."""
    hi = lo + width
    low, high = index_search_range((lo, hi))
    assert low <= high  # never empty for an interval of at most a revolution
    true_offset = data.draw(st.integers(lo, hi))
    counter = data.draw(st.integers(low, high))
    assert -MOTION_LIMIT_COUNTS < counter + true_offset < MOTION_LIMIT_COUNTS
    if hi - MOTION_LIMIT_COUNTS < true_offset < lo + MOTION_LIMIT_COUNTS:
        assert low <= -true_offset <= high


def test_the_pan_driver_records_before_it_moves(
    rig: SimulatedBiris, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The move is in the reference before F0 starts it; the settle position after."""
    pan = rig.hardware.devices.azimuth
    reference = rig.hardware.pan_reference
    pan.configure(MotorParams())
    assert reference.state.params == PARAMS
    pan.hold_here()
    start = pan.command_position()
    seen: list[tuple[int, int, bool]] = []
    record = reference.record_move

    def spy(begin: int, destination: int) -> None:
        seen.append((begin, destination, pan.profile_active()))
        record(begin, destination)

    monkeypatch.setattr(reference, "record_move", spy)
    pan.start_trapezoid(start + 200)
    assert seen == [(start, start + 200, False)]
    assert pan.wait_settled(rig.timebase.Event(), limit_s=5.0)
    assert reference.state.move[0] == reference.state.move[1]
    assert abs(reference.state.move[0] - (start + 200)) <= 1
