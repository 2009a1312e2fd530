"""Appendix D's continuous acquisition: BIRIS started once, data interrupts gated per sweep.

``BirisInitRecord(continuous_acquisition=True)`` makes the server start BI_START_CONTINUOUS once
after initialisation; scans are then motor sweeps over a ring that never stops, so the 240 ms
start-up is paid once rather than per sweep, and every sweep covers its whole length.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import numpy as np
import pytest

from biris_hw import (
    BirisInitRecord,
    ConnectionKind,
    DeliveryPolicy,
    Direction,
    HardwareFault,
    Scan,
)
from biris_hw.records import acq_rate_counts_per_acq
from biris_hw.server import BirisServer
from regs.biexec import OFF_DATA_INT_ENABLE
from sim import POISON, Scene, SimulatedBiris
from tests.conftest import RigFactory

WAIT = 30.0
CONTINUOUS = BirisInitRecord(continuous_acquisition=True)
ACQ_COUNTS = acq_rate_counts_per_acq(CONTINUOUS)  # ~42.6 counts of pan per acquisition


@pytest.fixture
def time_scale() -> float:
    return 20.0


@pytest.fixture
def cserver(rig: SimulatedBiris) -> Iterator[BirisServer]:
    with BirisServer(rig.hardware, CONTINUOUS) as server:
        server.open().wait_idle(timeout=WAIT)  # the ring is live
        yield server


def _data_int_enabled(rig: SimulatedBiris) -> int:
    return rig.hardware.biris.read16(rig.memory_map.biexec_offset + OFF_DATA_INT_ENABLE)


def _check_sweep(scan: Scan | None, start: int, dest: int, follows: bool = False) -> None:
    assert scan is not None
    az = scan.azimuth.astype(np.int64)
    sign = 1 if dest > start else -1
    # the head's way; at a turn-around the head may still settle back a count or two
    assert np.all(np.diff(az) * sign >= -2)
    # none made with the head standing at the start (but a sweep that turns straight round
    # from another begins with the turn-around's), one at the end
    at_start = np.count_nonzero(np.abs(az - start) <= 2)
    # (as many as the turn-around took the server in acquisition periods: host time, scaled)
    assert at_start <= 5 if follows else at_start == 0
    assert np.count_nonzero(np.abs(az - dest) <= 2) == 1 and abs(int(az[-1]) - dest) <= 2
    assert abs(int(az[0]) - start) < 1.5 * ACQ_COUNTS  # the start of the sweep is not lost
    assert scan.dropped == 0
    assert not np.any(scan.range_mm == POISON)
    assert np.all(np.diff(scan.t) > 0)


def test_the_startup_is_paid_once_and_every_sweep_is_whole(
    rig: SimulatedBiris, cserver: BirisServer
) -> None:
    conn = cserver.open()
    status = cserver.status()
    assert status["acquisition"] == "continuous" and status["ring"] == "live"
    assert cserver.level2.continuous  # Appendix D's flag, for the demultiplexer
    start = 0
    for deg in (90.0, -30.0, 45.0):
        dest = conn.single_scan(deg)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CCW if dest > start else Direction.CW)
        _check_sweep(scan, start, dest)
        start = dest
    assert len(rig.supervisor.sequence_starts) == 1  # one BI_START_CONTINUOUS, ever
    counters = cserver.status()["counters"]
    assert counters["continuous_starts"] == 1 and counters["scans"] == 3
    assert counters["constant_azimuth"] >= 3  # the still head at the ends: dropped, counted


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
def test_single_acquisition_covers_the_start_of_each_sweep_too(rig: SimulatedBiris) -> None:
    """The comparison: BI_ACQUIRE per scan used to start with the head (the first acquisition
    some 4 acquisitions' travel in); the motor now waits for BIRIS's start-up to end."""
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        conn.single_scan(90.0)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None and 0 < int(scan.azimuth[0]) <= 1.5 * ACQ_COUNTS


def test_data_interrupts_are_off_between_sweeps(rig: SimulatedBiris, cserver: BirisServer) -> None:
    conn = cserver.open()
    conn.single_scan(20.0)
    conn.wait_idle(timeout=WAIT)
    assert _data_int_enabled(rig) == 0
    raised = rig.level2_gate.raised_by("data")
    made = rig.supervisor.acquisitions_made
    # the ring keeps acquiring while the head stands still, but raises no interrupt
    assert rig.supervisor.wait_for(lambda s: s.acquisitions_made >= made + 5, WAIT)
    assert rig.level2_gate.raised_by("data") == raised
    conn.single_scan(-20.0)  # and back on for the next sweep
    conn.wait_idle(timeout=WAIT)
    assert rig.level2_gate.raised_by("data") > raised
    assert _data_int_enabled(rig) == 0
    scan = conn.request_scan_data(Direction.CW)
    _check_sweep(scan, 228, -228)


@pytest.mark.slow  # x10 end to end; the ring's sweeps are checked at x30 by the fast tests
def test_continuous_scanning_over_the_ring(make_rig: RigFactory) -> None:
    # x10: a scan's times may be late by the promptest wake of its sweep, and telling which
    # acquisition a time is needs that under a period (3.3 ms of real time here)
    rig = make_rig(time_scale=10.0)
    with BirisServer(rig.hardware, CONTINUOUS) as cserver:
        opened: list[bool] = []
        open_sweep = cserver.reader.open_sweep

        def spy(seq_id: int, follows: bool = False) -> None:
            opened.append(follows)
            open_sweep(seq_id, follows)

        cserver.reader.open_sweep = spy  # type: ignore[method-assign]
        conn = cserver.open()
        conn.wait_idle(timeout=WAIT)
        data = cserver.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        conn.continuous_scan(-25.0, 25.0)
        scans = [data.ready_for_data(timeout=WAIT) for _ in range(4)]
        conn.stop_scan()
        conn.wait_idle(timeout=WAIT)
        counters = cserver.status()["counters"]
    assert [(s.direction, s.seq) for s in scans] == [
        (Direction.CW, 1),
        (Direction.CCW, 1),
        (Direction.CW, 2),
        (Direction.CCW, 2),
    ]
    _check_sweep(scans[0], 0, -284)
    for scan in scans[1:]:
        limit = -284 if scan.direction is Direction.CW else 284
        _check_sweep(scan, -limit, limit, follows=True)  # from the other limit
    # back to back, without a 240 ms start-up in between, and without a hole: each sweep
    # begins with the acquisition after the previous one's last (a gap of one period)
    assert len(rig.supervisor.sequence_starts) == 1
    assert opened[:4] == [False, True, True, True]  # the reader was told to read straight on
    made = np.array(rig.supervisor.acquisition_times)

    def which(t: float) -> int:
        """The acquisition a scan time stands for: the last made at or before it (scan
        times are never early, and late by less than a period)."""
        return int(np.searchsorted(made, t + 1e-9, side="right")) - 1

    for scan in scans:
        assert which(scan.t[-1]) - which(scan.t[0]) + 1 == scan.n_acq  # no hole inside
    for prev, nxt in itertools.pairwise(scans):
        assert which(nxt.t[0]) == which(prev.t[-1]) + 1  # nor between
    assert data.dropped == 0 and counters["dropped_acquisitions"] == 0


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_coalesced_and_lost_interrupts_lose_no_acquisition(
    rig: SimulatedBiris, cserver: BirisServer
) -> None:
    conn = cserver.open()
    conn.single_scan(45.0)
    conn.wait_idle(timeout=WAIT)
    clean = conn.request_scan_data(Direction.CCW)
    rig.faults.coalesce_interrupts(True, burst=4)
    conn.single_scan(0.0)
    rig.faults.drop_data_interrupt()
    conn.wait_idle(timeout=WAIT)
    rig.faults.coalesce_interrupts(False)
    scan = conn.request_scan_data(Direction.CW)
    assert clean is not None and scan is not None
    _check_sweep(scan, 512, 0)
    assert abs(scan.n_acq - clean.n_acq) <= 2
    assert cserver.status()["counters"]["dropped_acquisitions"] == 0


def test_a_tilt_stops_and_restarts_the_ring(rig: SimulatedBiris, cserver: BirisServer) -> None:
    conn = cserver.open()
    conn.set_elevation(8.0)  # no acquisition while tilting: the audit would say so
    conn.wait_idle(timeout=WAIT)
    status = cserver.status()
    assert status["ring"] == "live" and status["elevation"] == 91
    assert len(rig.supervisor.sequence_starts) == 2
    conn.single_scan(30.0)
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None and scan.elevation == 91
    _check_sweep(scan, 0, 341)


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_a_hung_biris_times_out_during_a_sweep(rig: SimulatedBiris, cserver: BirisServer) -> None:
    conn = cserver.open()
    conn.timeout_enable()
    rig.faults.hang_supervisor()
    conn.single_scan(30.0)
    with pytest.raises(HardwareFault) as fault:
        conn.wait_idle(timeout=WAIT)
    assert fault.value.kind == "timeout"
    rig.faults.clear_hang()
    conn.reset()  # stops the ring before booting again
    conn.wait_idle(timeout=WAIT)
    assert cserver.status()["ring"] == "live"
    conn.single_scan(-10.0)
    conn.wait_idle(timeout=WAIT)
    _check_sweep(conn.request_scan_data(Direction.CW), 0, -114)


@pytest.mark.slow  # test_init_busy covers a busy BIRIS at start-up in the fast tier
def test_a_new_server_finds_biris_still_acquiring(make_rig: RigFactory) -> None:
    rig = make_rig(scene=Scene.room())
    with BirisServer(rig.hardware, CONTINUOUS) as first:
        first.open().wait_idle(timeout=WAIT)
    assert rig.supervisor.continuous  # left running: closing does not talk to BIRIS
    with BirisServer(rig.hardware) as second:  # single acquisition: stops it first, boots
        conn = second.open()
        conn.single_scan(15.0)
        conn.wait_idle(timeout=WAIT)
        assert not second.level2.continuous
        assert conn.request_scan_data(Direction.CCW) is not None
