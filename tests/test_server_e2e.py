"""The BIRIS server end to end against the simulator: every message and rule of the report.

Each test runs at two time scales (see conftest), ends with the audit clean and no thread or
descriptor left behind.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from biris_hw import (
    BirisInitRecord,
    ConnectionKind,
    Direction,
    HardwareFault,
    MotorParams,
    RequestError,
)
from biris_hw.errors import ConnectionClosed
from biris_hw.server import BirisServer
from biris_hw.server.scan_timing import trapezoid_s
from regs.layout import acquisition_period_s
from sim import POISON, SimulatedBiris
from tests.conftest import RigFactory, join, spawn

WAIT = 30.0  # generous real-time bound for anything that should take well under a second
PERIOD = acquisition_period_s(64)
"""The real acquisition period at 64 samples: 2 video fields."""
DEFAULT_MOTOR = BirisInitRecord().motor


def _true_deg(rig: SimulatedBiris) -> float:
    return rig.azimuth_counts * 360.0 / 4096.0


def test_initialisation_homes_to_the_zero_index(rig: SimulatedBiris, server: BirisServer) -> None:
    assert abs(rig.azimuth_counts) <= 3.0
    assert server.status()["state"] == "idle"
    assert rig.supervisor.booted


@pytest.mark.parametrize("dest_deg", [90.0, -60.0])
def test_single_scan_either_way(rig: SimulatedBiris, server: BirisServer, dest_deg: float) -> None:
    conn = server.open()
    dest = conn.single_scan(dest_deg)
    assert dest == round(dest_deg * 4096 / 360)
    conn.wait_idle(timeout=WAIT)
    direction = Direction.CCW if dest > 0 else Direction.CW
    scan = conn.request_scan_data(direction)
    assert scan is not None
    assert conn.request_scan_data(Direction(1 - direction)) is None
    assert scan.direction is direction and scan.seq == 1
    # as many as the trapezoid lasts in real acquisition periods; the first on the way
    assert abs(scan.n_acq - trapezoid_s(dest, DEFAULT_MOTOR) / PERIOD) <= 2
    assert 0 < abs(int(scan.azimuth[0])) <= abs(dest) / scan.n_acq * 2.5
    assert scan.dropped == 0
    assert scan.samples == 64
    # azimuths run the scan's way, and end at the destination
    steps = np.diff(scan.azimuth.astype(np.int64))
    assert np.all(steps * (1 if dest > 0 else -1) >= -2)  # settling may wobble a count
    assert abs(int(scan.azimuth[-1]) - dest) <= 2
    # a 2 m circle: every valid sample reads about 2000 mm, never the poison pattern
    valid = scan.range_mm[scan.range_mm > 0]
    assert valid.size > 0.9 * scan.range_mm.size
    assert np.all(np.abs(valid.astype(np.int64) - 2000) < 200)
    assert not np.any(scan.range_mm == POISON) and not np.any(scan.closest_mm == POISON)
    assert np.all(np.diff(scan.t) > 0)
    assert abs(_true_deg(rig) - dest_deg) < 0.5


def test_request_point_is_the_latest_acquisition(server: BirisServer) -> None:
    conn = server.open()
    assert conn.request_point() is None
    conn.single_scan(45.0)
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.CCW)
    point = conn.request_point()
    assert scan is not None and point is not None
    assert point.acq == scan.n_acq - 1
    assert point.azimuth == scan.azimuth[-1]
    assert point.profile.shape == (64,)
    assert np.array_equal(point.profile, scan.range_mm[-1])
    assert point.range_mm == scan.closest_mm[-1]


def test_continuous_scanning_feeds_every_data_connection_in_order(server: BirisServer) -> None:
    conn = server.open()
    data = [server.open(ConnectionKind.DATA) for _ in range(3)]
    received: list[list[tuple[Direction, int]]] = [[] for _ in data]
    errors: list[BaseException] = []

    def consume(i: int) -> None:
        try:
            for _ in range(4):
                scan = data[i].ready_for_data(timeout=WAIT)
                received[i].append((scan.direction, scan.seq))
        except BaseException as exc:  # report in the main thread
            errors.append(exc)

    threads = [spawn(consume, i) for i in range(len(data))]
    cw, ccw = conn.continuous_scan(-20.0, 20.0)
    assert (cw, ccw) == (-228, 228)
    for t in threads:
        join(t)
    conn.stop_scan()
    conn.wait_idle(timeout=WAIT)
    assert not errors, errors
    expected = [(Direction.CW, 1), (Direction.CCW, 1), (Direction.CW, 2), (Direction.CCW, 2)]
    for got in received:
        assert got == expected
    assert all(d.dropped == 0 for d in data)
    last_cw = conn.request_scan_data(Direction.CW)
    assert last_cw is not None and last_cw.seq >= 2


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_stop_ends_continuous_scanning_at_the_end_of_the_sweep(server: BirisServer) -> None:
    conn = server.open()
    data = server.open(ConnectionKind.DATA)
    conn.continuous_scan(-10.0, 10.0)
    first = data.ready_for_data(timeout=WAIT)
    conn.stop_scan()
    conn.wait_idle(timeout=WAIT)
    status = server.status()
    assert status["state"] == "idle" and not status["continuous"]
    # only the sweep that was running when STOP arrived completes after it
    scans = status["counters"]["scans"]
    assert first.seq == 1 and scans in (2, 3)
    # the newest buffer completed after `first` waits for this connection; any older one it
    # replaced is counted, never lost silently
    last = data.ready_for_data(timeout=WAIT)
    order = [(Direction.CW, 1), (Direction.CCW, 1), (Direction.CW, 2)]
    assert (last.direction, last.seq) == order[scans - 1]
    assert data.dropped == scans - 2
    with pytest.raises(TimeoutError):
        data.ready_for_data(timeout=0.3)
    assert server.status()["counters"]["scans"] == scans


def test_home_is_pending_during_a_single_scan(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    conn.single_scan(60.0)
    conn.home()  # pending: the scan is running
    assert server.status()["state"] == "scanning"
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None and abs(int(scan.azimuth[-1]) - 683) <= 2  # the scan was not cut
    assert abs(rig.azimuth_counts) <= 3.0
    assert server.status()["azimuth"] == 0


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_home_during_continuous_scanning_waits_for_stop(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    conn = server.open()
    data = server.open(ConnectionKind.DATA)
    conn.continuous_scan(10.0, 30.0)
    conn.home()
    data.ready_for_data(timeout=WAIT)
    data.ready_for_data(timeout=WAIT)  # still sweeping: HOME did not end it
    assert server.status()["continuous"]
    conn.stop_scan()
    conn.wait_idle(timeout=WAIT)
    assert abs(rig.azimuth_counts) <= 3.0


@pytest.mark.parametrize(
    ("asked", "used"), [(720.0, 0x1000), pytest.param(-1000.0, -0x1000, marks=pytest.mark.slow)]
)
def test_destinations_are_clamped_to_plus_minus_360(
    rig: SimulatedBiris, server: BirisServer, asked: float, used: int
) -> None:
    conn = server.open()
    assert conn.single_scan(asked) == used
    conn.wait_idle(timeout=WAIT)
    assert abs(rig.azimuth_counts - used) <= 2.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "90"])
def test_bad_angles_are_refused_and_nothing_moves(
    rig: SimulatedBiris, server: BirisServer, bad: object
) -> None:
    conn = server.open()
    before = rig.azimuth_counts
    with pytest.raises(RequestError):
        conn.single_scan(bad)  # type: ignore[arg-type]
    with pytest.raises(RequestError):
        conn.continuous_scan(bad, 10.0)  # type: ignore[arg-type]
    assert server.status()["state"] == "idle"
    assert abs(rig.azimuth_counts - before) < 1.0


def test_bad_requests_change_nothing(server: BirisServer) -> None:
    conn = server.open()
    with pytest.raises(RequestError):
        conn.ready_for_data(timeout=1.0)  # a NORMAL connection
    with pytest.raises(RequestError):
        conn.continuous_scan(20.0, -20.0)  # limits the wrong way round
    with pytest.raises(RequestError):
        conn.single_scan(0.0)  # already there
    with pytest.raises(RequestError):
        conn.request_scan_data(7)
    conn.single_scan(30.0)
    with pytest.raises(RequestError):
        conn.single_scan(-30.0)  # one scan at a time
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None and abs(int(scan.azimuth[-1]) - 341) <= 2
    assert conn.request_scan_data(Direction.CW) is None


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_coalesced_and_lost_interrupts_lose_no_acquisition(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    conn = server.open()
    rig.faults.coalesce_interrupts(True, burst=4)
    conn.single_scan(45.0)
    rig.faults.drop_data_interrupt()
    conn.wait_idle(timeout=WAIT)
    rig.faults.coalesce_interrupts(False)
    scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None
    # every acquisition BIRIS made is in the scan or was made standing at one of its ends
    standing = server.status()["counters"]["constant_azimuth"]
    assert scan.n_acq + standing == rig.supervisor.acquisitions_made
    assert scan.dropped == 0
    assert not np.any(scan.range_mm == POISON)
    assert server.status()["counters"]["dropped_acquisitions"] == 0


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_spurious_interrupts_are_harmless(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    rig.faults.spurious_interrupt()
    conn.single_scan(20.0)
    rig.faults.spurious_interrupt()
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None and scan.dropped == 0


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_128_sample_mode(make_rig: RigFactory) -> None:
    rig = make_rig(samples=128)
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        conn.single_scan(-30.0)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CW)
        assert scan is not None
        assert scan.samples == 128 and scan.range_mm.shape[1] == 128
        period = np.median(np.diff(scan.t))
        assert period == pytest.approx(3 / 59.94, rel=0.05)
        assert not np.any(scan.range_mm == POISON)


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_motor_parameters_change_speed_and_acquisition_count(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    conn = server.open()
    slow = MotorParams(max_vel=1)
    conn.set_motor_params(slow)
    conn.single_scan(45.0)
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None
    # twice as long at half the speed: twice the acquisitions
    assert abs(scan.n_acq - trapezoid_s(512, slow) / PERIOD) <= 2
    assert scan.n_acq > 1.8 * trapezoid_s(512, DEFAULT_MOTOR) / PERIOD
    assert rig.board.azimuth.max_velocity == 1


@pytest.mark.parametrize(
    ("inject", "kind"),
    [("parity_error", "parity"), pytest.param("bus_error", "bus", marks=pytest.mark.slow)],
)
def test_coupler_faults_reach_every_caller_and_reset_recovers(
    rig: SimulatedBiris, server: BirisServer, inject: str, kind: str
) -> None:
    conn = server.open()
    other = server.open()
    conn.single_scan(90.0)
    caught: list[BaseException] = []
    waiter = spawn(_catch, other.wait_idle, caught)
    getattr(rig.faults, inject)()
    join(waiter)
    assert len(caught) == 1 and isinstance(caught[0], HardwareFault)
    assert caught[0].kind == kind
    with pytest.raises(HardwareFault) as later:
        conn.request_point()
    assert later.value.kind == kind
    assert server.status()["state"] == f"fault:{kind}"
    conn.reset()
    assert server.status()["state"] == "idle"
    conn.single_scan(10.0)
    conn.wait_idle(timeout=WAIT)
    assert conn.request_scan_data(Direction.CCW) is not None


def _catch(fn: object, into: list[BaseException]) -> None:
    try:
        fn(timeout=WAIT)  # type: ignore[operator]
    except BaseException as exc:
        into.append(exc)


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_a_hung_biris_times_out_when_enabled(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    conn.timeout_enable()
    rig.faults.hang_supervisor()
    conn.single_scan(30.0)
    with pytest.raises(HardwareFault) as fault:
        conn.wait_idle(timeout=WAIT)
    assert fault.value.kind == "timeout"
    rig.faults.clear_hang()
    conn.reset()
    conn.single_scan(20.0)
    conn.wait_idle(timeout=WAIT)


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_without_the_timeout_a_hang_is_only_a_wait(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    conn = server.open()
    conn.timeout_disable()
    rig.faults.hang_supervisor()
    conn.single_scan(10.0)
    with pytest.raises(TimeoutError):
        conn.wait_idle(timeout=6.0 / rig.time_scale)  # 6 s of hardware time, beyond 4 s
    assert server.status()["state"] == "scanning"
    rig.faults.clear_hang()
    conn.wait_idle(timeout=WAIT)


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_a_stalled_motor_is_reported(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    conn.single_scan(90.0)
    rig.faults.stall_motor()
    with pytest.raises(HardwareFault) as fault:
        conn.wait_idle(timeout=WAIT)
    assert fault.value.kind == "motor_stall"
    rig.faults.clear_stall()
    conn.reset()
    assert abs(rig.azimuth_counts) <= 3.0


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_a_connection_whose_thread_ended_is_released(server: BirisServer) -> None:
    conn = server.open()
    made: list[int] = []

    def open_and_leave() -> None:
        made.append(server.open(ConnectionKind.DATA).ident)

    join(spawn(open_and_leave))
    assert made[0] in server.status()["connections"]
    conn.single_scan(10.0)
    conn.wait_idle(timeout=WAIT)
    assert made[0] not in server.status()["connections"]


def test_closed_connections_and_servers_refuse_calls(rig: SimulatedBiris) -> None:
    server = BirisServer(rig.hardware)
    conn = server.open()
    conn.close()
    conn.close()
    with pytest.raises(ConnectionClosed):
        conn.request_point()
    live = server.open()
    server.close()
    with pytest.raises(ConnectionClosed):
        live.request_point()
    with pytest.raises(ConnectionClosed):
        server.open()


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_garbage_from_biris_is_a_protocol_fault_and_reset_recovers(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    conn = server.open()
    rig.faults.garbage_param()  # the next query answer (re-initialisation asks three) is garbage
    with pytest.raises(HardwareFault) as fault:
        conn.reset()
    assert fault.value.kind == "protocol"
    assert server.status()["state"] == "fault:protocol"
    conn.reset()
    assert server.status()["state"] == "idle"
    conn.single_scan(10.0)
    conn.wait_idle(timeout=WAIT)


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_a_fault_during_reset_ends_it_promptly(rig: SimulatedBiris, server: BirisServer) -> None:
    conn = server.open()
    rig.faults.stall_motor()  # re-initialisation homes the head: the stall stops it
    with pytest.raises(HardwareFault) as fault:
        conn.reset()
    assert fault.value.kind == "motor_stall"
    rig.faults.clear_stall()
    conn.reset()
    assert abs(rig.azimuth_counts) <= 3.0
