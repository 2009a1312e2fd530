"""Report-mode scans cover what was asked.

The server writes BI_ACQUIRE first and starts the trapezoid one start-up after the write, by a
hardware-time schedule (:mod:`biris_hw.server.start_schedule`), whenever the host sees BIRIS's
interrupts; the count comes from the trapezoid's real duration in real acquisition periods.
Checked three ways: the count arithmetic against the simulator's own trapezoid, the
administrator's ordering without threads (tests.core), and whole scans against the simulator,
whose audit and true azimuths judge.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from biris_hw import BirisServer, ConnectionKind, DeliveryPolicy, Direction, MotorParams
from biris_hw import protocol as p
from biris_hw.records import BirisInitRecord
from biris_hw.server import messages as m
from biris_hw.server.scan_assembly import STILL_COUNTS
from biris_hw.server.scan_timing import (
    FIELD_S,
    HOST_LATENCY_S,
    MAX_LATENESS_S,
    RECENT_KEPT,
    START_AFTER_S,
    STARTUP_FIELDS_S,
    STARTUP_MAX_S,
    STARTUP_S,
    ScanTiming,
    data_rate_mismatch,
    trapezoid_s,
)
from biris_hw.server.start_schedule import StartSchedule
from regs.biexec import BiCommand
from regs.layout import acquisition_period_s
from sim import Scene, SimulatedBiris
from sim.hctl1000 import _Trapezoid
from tests.conftest import RigFactory
from tests.core import Core

WAIT = 30.0
PERIOD = acquisition_period_s(64)
DEFAULT = BirisInitRecord().motor


# -- the arithmetic -------------------------------------------------------------------------------
@pytest.mark.parametrize("distance", [1, 3, 40, 300, 1024, 4096, 8192])
@pytest.mark.parametrize(
    "params",
    [DEFAULT, MotorParams(max_vel=1), MotorParams(max_vel=16, max_accel=0x100), MotorParams()],
)
def test_the_trapezoid_lasts_what_the_chip_takes(distance: int, params: MotorParams) -> None:
    """Within a sample of the simulated HCTL-1000's own profile (which rounds to samples)."""
    chip = _Trapezoid(0, distance, params.max_accel / 256.0, params.max_vel)
    assert chip.n_samples is not None
    samples = trapezoid_s(distance, params) / params.sample_period_s
    assert abs(samples - chip.n_samples) <= 1.0, (samples, chip.n_samples)
    assert trapezoid_s(-distance, params) == trapezoid_s(distance, params)


def test_the_count_covers_the_motion_with_the_arrival_and_one_spare() -> None:
    timing = ScanTiming(PERIOD)
    timing.note_lateness(0.0)  # a prompt server
    assert timing.acquisitions(0, DEFAULT) == 0
    for distance in (1, 100, 1024, 8192):
        n = timing.acquisitions(distance, DEFAULT)
        moving = trapezoid_s(distance, DEFAULT) / PERIOD
        # acquisition n-2 is the first exposed after the arrival; n-1 the spare
        assert (n - 2 + 0.5) * PERIOD >= trapezoid_s(distance, DEFAULT)
        assert n - 2 <= moving + 1.5
    # the report's BIRIS_DATA_RATE (30 ms) and start-up-blind count asked for more, of which
    # ~44 % stood at the destination of a 90 degree scan; this is the motion in real periods,
    # from a start about as BIRIS's first acquisition begins, the host's latency allowed
    start = max(START_AFTER_S, 0.0) + HOST_LATENCY_S
    assert (
        timing.acquisitions(1024, DEFAULT)
        == math.ceil((start + trapezoid_s(1024, DEFAULT)) / PERIOD + 0.25 - 0.5) + 2
    )


def test_the_motor_start_lateness_is_learned_from_recent_scans_and_bounded() -> None:
    timing = ScanTiming(PERIOD)
    # nothing seen yet: the host's latency (a tenth of a period on the real head)
    assert timing.lateness_allowance_s == pytest.approx(HOST_LATENCY_S)
    timing.note_lateness(0.0)
    quick = timing.acquisitions(1024, DEFAULT)
    timing.note_lateness(3 * PERIOD)
    assert timing.acquisitions(1024, DEFAULT) == quick + 3
    for _ in range(RECENT_KEPT):  # forgotten once enough prompter starts are seen
        timing.note_lateness(0.0)
    assert timing.acquisitions(1024, DEFAULT) == quick
    timing.note_lateness(60.0)
    timing.note_lateness(float("nan"))
    timing.note_lateness(-1.0)
    assert timing.lateness_allowance_s == MAX_LATENESS_S


def test_the_start_up_is_learned_as_the_smallest_bound_and_capped_by_the_reports() -> None:
    timing = ScanTiming(PERIOD)
    # before any scan: the report's 240 ms in whole fields, less a quarter field
    assert timing.startup_lead_s == pytest.approx(STARTUP_FIELDS_S + START_AFTER_S)
    assert STARTUP_S < STARTUP_FIELDS_S < STARTUP_S + FIELD_S
    timing.note_startup(0.262)
    timing.note_startup(0.251)  # a prompter look: a tighter bound
    timing.note_startup(0.290)
    assert timing.startup_s == pytest.approx(0.251)
    assert timing.startup_lead_s == pytest.approx(0.251 + START_AFTER_S)
    # bounds made loose by a host that only looked late never push the motor's start beyond
    # the report's longest start-up (a late motor is a short scan)
    loose = ScanTiming(PERIOD)
    for _ in range(3):
        loose.note_startup(0.4)
    assert loose.startup_s == pytest.approx(STARTUP_MAX_S)
    for nonsense in (float("nan"), -0.1, 0.0, 5.0):
        loose.note_startup(nonsense)
    assert loose.startup_s == pytest.approx(STARTUP_MAX_S)


def test_before_any_start_is_seen_a_scaled_simulation_allows_the_hosts_latency() -> None:
    """At x30 three host milliseconds are 90 ms of hardware time: the scan asks for that many
    more (standing at its end, dropped and counted) rather than end short of its
    destination, which a loaded host made it do (9 counts short of +45 degrees, stop 19's CI)."""
    real, scaled = ScanTiming(PERIOD), ScanTiming(PERIOD, time_scale=30.0)
    assert scaled.lateness_allowance_s == pytest.approx(30.0 * HOST_LATENCY_S)
    extra = scaled.acquisitions(512, DEFAULT) - real.acquisitions(512, DEFAULT)
    assert extra == pytest.approx(29.0 * HOST_LATENCY_S / PERIOD, abs=1.0)
    # a late start seen counts, on any scale; and no scale makes the allowance unbounded
    real.note_lateness(0.4)
    assert real.acquisitions(512, DEFAULT) >= scaled.acquisitions(512, DEFAULT)
    assert ScanTiming(PERIOD, time_scale=1e6).lateness_allowance_s == MAX_LATENESS_S


def test_biris_data_rate_is_checked_against_the_real_period() -> None:
    said = data_rate_mismatch(30, PERIOD)  # Appendix B's 30 ms against 2 fields
    assert said is not None and "33.37" in said and "30 ms" in said
    assert data_rate_mismatch(33, PERIOD) is None
    assert data_rate_mismatch(50, acquisition_period_s(128)) is None  # 3 fields: 50.05 ms


# -- the ordering, without threads ---------------------------------------------------------------
def test_the_motor_is_ordered_with_the_command_on_its_schedule(core: Core) -> None:
    """The trapezoid is ordered at once, carrying the same schedule as BI_ACQUIRE: it starts a
    start-up after the write, whenever (or whether) SEQUENCE_STARTED reaches the server."""
    conn = core.open()
    assert core.call(p.SingleScanRqst(conn, 1024)) == 1024
    acquire = core.command(start=False)
    assert acquire is not None and acquire.code == BiCommand.BI_ACQUIRE
    move = core.move()
    assert isinstance(move, m.MoveOrder) and move.destination == 1024
    assert move.schedule is not None and move.schedule is acquire.schedule
    assert move.schedule.lead_s == pytest.approx(core.admin.scans.timing.startup_lead_s)
    core.started(acquire.seq_id + 99)  # another sequence's: ignored, nothing else ordered
    assert core.move() is None


def test_a_fault_cancels_a_motor_start_that_waits_for_its_schedule(core: Core) -> None:
    conn = core.open()
    core.call(p.SingleScanRqst(conn, 1024))
    acquire = core.command(start=False)
    assert acquire is not None and acquire.schedule is not None
    assert not acquire.schedule.cancelled
    core.send(m.BirisParityErr())  # a fault while BIRIS starts up
    assert acquire.schedule.cancelled  # the worker waiting on it starts nothing
    assert not acquire.schedule.wait_start()


def test_a_reset_cancels_the_schedule_too(core: Core) -> None:
    conn = core.open()
    core.call(p.SingleScanRqst(conn, 1024))
    acquire = core.command(start=False)
    assert acquire is not None and acquire.schedule is not None
    core.send(p.ResetRequest(conn))
    assert acquire.schedule.cancelled


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_schedule_starts_when_due_and_says_how_late() -> None:
    clock = _Clock()
    schedule = StartSchedule(0.25, clock)
    assert schedule.start_at is None and schedule.late_s is None
    schedule.written(10.0)
    assert schedule.start_at == pytest.approx(10.25)
    clock.now = 10.30  # the worker woke 50 ms late
    assert schedule.wait_start()
    assert schedule.started_at == pytest.approx(10.30)
    assert schedule.late_s == pytest.approx(0.05)


def test_a_schedule_waits_for_its_due_time_and_a_cancel_ends_the_wait() -> None:
    clock = _Clock()
    schedule = StartSchedule(3600.0, clock)  # due in an hour: only a cancel can end the wait
    schedule.written(0.0)
    result: list[bool] = []
    worker = threading.Thread(target=lambda: result.append(schedule.wait_start()))
    worker.start()
    assert result == []  # not due for an hour: still waiting
    schedule.cancel()
    worker.join(timeout=10.0)
    assert result == [False] and schedule.started_at is None


def test_standing_acquisitions_at_either_end_are_dropped_and_counted(core: Core) -> None:
    conn = core.open()
    core.call(p.SingleScanRqst(conn, 512))
    acquire = core.command()
    assert acquire is not None
    core.move()
    n = acquire.n_acquisitions
    # acquisition 0 before the head moved, then the motion, then two at the destination
    positions = [0, *np.linspace(60, 500, n - 4).astype(int).tolist(), 511, 512, 512]
    core.acquisitions(acquire.seq_id, range(n), azimuth=lambda k: positions[k])
    core.arrive(position=512)
    core.complete(acquire)
    scan = core.admin.scans.buffers[Direction.CCW]
    assert scan is not None
    assert scan.azimuth[0] == 60 and scan.azimuth[-1] == 511  # the first at the destination
    assert scan.dropped == 0  # standing is not lost
    counters = core.admin.status().counters
    assert counters["constant_azimuth"] == 3
    assert core.admin.status().accounts().adds_up


# -- whole scans against the simulator -----------------------------------------------------------
def _scan_to(server: BirisServer, to_deg: float) -> tuple[np.ndarray, int, int]:
    """A single scan; its azimuths (counts), the standing count and the dropped count."""
    conn = server.open()
    start = server.status().azimuth
    before = server.status().counters["constant_azimuth"]
    dest = conn.single_scan(to_deg)
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.CCW if dest > start else Direction.CW)
    assert scan is not None
    standing = server.status().counters["constant_azimuth"] - before
    return scan.azimuth.astype(np.int64), standing, scan.dropped


@pytest.mark.parametrize(
    "to_deg",
    [
        90.0,
        pytest.param(30.0, marks=pytest.mark.slow),
        pytest.param(-360.0, marks=pytest.mark.slow),
    ],
)
def test_a_single_scan_spans_its_length(make_rig: RigFactory, to_deg: float) -> None:
    rig = make_rig(scene=Scene.room())
    with BirisServer(rig.hardware) as server:
        start = server.status().azimuth
        azimuth, standing, dropped = _scan_to(server, to_deg)
        dest = server.status().azimuth
    step = abs(dest - start) / max(1, len(azimuth) - 1)  # counts between acquisitions
    sign = 1 if dest > start else -1
    # the first within one acquisition of the start, moving; the last at the destination
    assert 0 < sign * (azimuth[0] - start) <= 2.5 * step, (azimuth[0], start, step)
    assert abs(azimuth[-1] - dest) <= STILL_COUNTS
    assert np.all(sign * np.diff(azimuth) > 0)  # every kept one taken on the way
    # a couple at either end, and before any start is seen the host's latency in hardware
    # time (3 ms: 0.1 period on the real head, 2.7 periods at x30) at the destination
    allowance = math.ceil(rig.time_scale * HOST_LATENCY_S / PERIOD)
    assert standing <= 4 + allowance and dropped == 0
    # as many as the motion lasts in real acquisition periods (2 fields), not BIRIS_DATA_RATE's
    expected = trapezoid_s(dest - start, DEFAULT) / PERIOD
    assert expected - 1 <= len(azimuth) <= expected + 2
    # the simulator's truth: the head stands where the last acquisition says
    assert abs(rig.azimuth_counts - dest) <= STILL_COUNTS


def test_every_report_mode_sweep_spans_the_limits(rig: SimulatedBiris) -> None:
    """Continuous scanning in report mode: each sweep after the first covers CW..CCW."""
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        data = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        cw, ccw = conn.continuous_scan(-30.0, 30.0)
        scans = [data.ready_for_data(timeout=WAIT) for _ in range(3)]
        conn.stop_scan()
        conn.wait_idle(timeout=WAIT)
    # the first sweep went from where the head stood (0) to a limit: partial, and said so
    assert scans[0].partial and not any(scan.partial for scan in scans[1:])
    assert all(scan.acquisition == "single" for scan in scans)
    step = (ccw - cw) / 10
    for scan in scans[1:]:
        first, last = (cw, ccw) if scan.direction is Direction.CCW else (ccw, cw)
        assert abs(int(scan.azimuth[0]) - first) <= step, (scan.azimuth[0], first)
        assert abs(int(scan.azimuth[-1]) - last) <= STILL_COUNTS
        assert scan.dropped == 0


def test_ring_sweeps_say_how_they_were_acquired_and_the_first_is_partial(
    rig: SimulatedBiris,
) -> None:
    with BirisServer(rig.hardware, BirisInitRecord(continuous_acquisition=True)) as server:
        conn = server.open()
        conn.single_scan(10.0)
        conn.wait_idle(timeout=WAIT)
        single = conn.request_scan_data(Direction.CCW)
        point = conn.request_point()
        data = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        conn.continuous_scan(10.0, 30.0)  # the head stands at the CW limit: a full first sweep
        scans = [data.ready_for_data(timeout=WAIT) for _ in range(3)]
        conn.stop_scan()
        conn.wait_idle(timeout=WAIT)
    assert single is not None and not single.partial and single.acquisition == "continuous"
    assert point is not None and point.acquisition == "continuous"
    assert [scan.direction for scan in scans] == [Direction.CCW, Direction.CW, Direction.CCW]
    assert [scan.partial for scan in scans] == [False, False, False]
    assert all(scan.acquisition == "continuous" for scan in scans)
