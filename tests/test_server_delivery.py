"""Delivery policies of DATA connections, and the hand-over time of every Point and Scan.

Whatever a slow client cannot be given is counted in its connection's ``dropped``: for every
connection, what it was sent, what waits for it and what it dropped add up to what there was.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from biris_hw import (
    BirisInitRecord,
    ConnectionKind,
    DeliveryPolicy,
    Direction,
    Point,
    RequestError,
    Scan,
)
from biris_hw.server import BirisServer
from biris_hw.server.scan_assembly import STILL_COUNTS
from sim import SimulatedBiris
from tests.conftest import RigFactory

WAIT = 30.0


@pytest.fixture
def time_scale() -> float:
    return 20.0


def _sweeps(server: BirisServer, count: int) -> int:
    """Run continuous scanning for at least ``count`` sweeps; returns how many completed."""
    conn = server.open()
    counter = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=64)
    conn.continuous_scan(-10.0, 10.0)
    for _ in range(count):
        counter.ready_for_data(timeout=WAIT)
    conn.stop_scan()
    conn.wait_idle(timeout=WAIT)
    scans = server.status()["counters"]["scans"]
    assert scans in (count, count + 1)
    return int(scans)


def test_every_buffer_keeps_the_newest_depth_scans_and_counts_the_rest(
    server: BirisServer,
) -> None:
    slow = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=2)
    assert slow.policy is DeliveryPolicy.EVERY_BUFFER and slow.depth == 2
    total = _sweeps(server, 5)
    got = [slow.ready_for_data(timeout=WAIT) for _ in range(2)]
    with pytest.raises(TimeoutError):
        slow.ready_for_data(timeout=0.2)
    order = [(Direction.CW, 1), (Direction.CCW, 1), (Direction.CW, 2), (Direction.CCW, 2)]
    order += [(Direction.CW, 3), (Direction.CCW, 3)]
    assert [(s.direction, s.seq) for s in got] == order[total - 2 : total]  # oldest dropped
    assert slow.dropped == total - 2
    assert server.status()["connections"][slow.ident]["dropped"] == total - 2


@pytest.mark.slow  # LATEST is the default every e2e test already reads through
def test_latest_keeps_only_the_newest_scan(server: BirisServer) -> None:
    slow = server.open(ConnectionKind.DATA)  # LATEST is the default
    assert slow.policy is DeliveryPolicy.LATEST and slow.depth == 1
    total = _sweeps(server, 3)
    scan = slow.ready_for_data(timeout=WAIT)
    assert scan.seq == (total + 1) // 2 and slow.dropped == total - 1


@pytest.mark.slow  # fast-tier budget (issue 13 added the transports); make test-slow
def test_every_acquisition_streams_points_as_they_are_read(make_rig: RigFactory) -> None:
    rig = make_rig(time_scale=10.0)  # slower: the sweep lasts ~70 ms of real time
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        stream = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
        points: list[Point] = []
        errors: list[BaseException] = []
        dest = 683  # 60 degrees

        def read() -> None:
            """Up to the scan's last point: the first made at the destination."""
            try:
                while not points or abs(points[-1].azimuth - dest) > STILL_COUNTS:
                    points.append(stream.ready_for_data(timeout=WAIT))
            except BaseException as exc:
                errors.append(exc)

        reader = threading.Thread(target=read)
        reader.start()
        assert conn.single_scan(60.0) == dest
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CCW)
        assert scan is not None
        reader.join(WAIT)
        assert not errors, errors
    assert [p.acq for p in points] == list(range(scan.n_acq))
    for k, point in enumerate(points):
        assert isinstance(point, Point) and point.scan_seq == 1
        assert point.azimuth == scan.azimuth[k]
        assert np.array_equal(point.profile, scan.range_mm[k])
        assert point.t_delivered is not None and point.age is not None and point.age >= 0.0
    # the scan re-times from the promptest wake of the sequence: a streamed time is never
    # earlier than the scan's, and the excess only shrinks as wakes tighten the bound
    excess = np.array([p.t for p in points]) - scan.t
    assert np.all(excess >= -1e-9) and np.all(np.diff(excess) <= 1e-9)
    assert np.all(np.diff(scan.t) > 0)
    # the first acquisitions were in the client's hands before the sweep was over
    first = points[0].t_delivered
    assert first is not None and first < scan.t[-1]
    assert abs(int(scan.azimuth[-1]) - dest) <= 2
    assert stream.dropped == 0


@pytest.mark.slow  # fast-tier budget (issues 13-15); make test-slow
def test_every_acquisition_overflow_drops_the_oldest_points(server: BirisServer) -> None:
    conn = server.open()
    stream = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION, depth=4)
    conn.single_scan(-45.0)
    conn.wait_idle(timeout=WAIT)
    scan = conn.request_scan_data(Direction.CW)
    assert scan is not None
    got = [stream.ready_for_data(timeout=WAIT) for _ in range(4)]
    assert [p.acq for p in got] == list(range(scan.n_acq - 4, scan.n_acq))
    assert stream.dropped == scan.n_acq - 4
    entry = server.status()["connections"][stream.ident]
    assert entry["delivered"] + entry["dropped"] + entry["queued"] == scan.n_acq


def test_scans_and_points_carry_their_hand_over_time(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    conn = server.open()
    assert conn.request_point() is None
    conn.single_scan(30.0)
    conn.wait_idle(timeout=WAIT)
    before = rig.clock.now()
    scan = conn.request_scan_data(Direction.CCW)
    point = conn.request_point()
    after = rig.clock.now()
    assert scan is not None and point is not None
    assert scan.t_delivered is not None and point.t_delivered is not None
    assert before <= scan.t_delivered <= point.t_delivered <= after
    assert scan.age == pytest.approx(scan.t_delivered - scan.t.max())
    ages = scan.ages
    assert ages is not None and ages.shape == scan.t.shape and np.all(ages >= scan.age)
    assert point.age == pytest.approx(point.t_delivered - point.t)
    # asking again hands over the same buffer, stamped anew
    again = conn.request_scan_data(Direction.CCW)
    assert again is not None and again.seq == scan.seq
    assert again.t_delivered is not None and again.t_delivered >= scan.t_delivered


def test_policies_are_checked(server: BirisServer) -> None:
    with pytest.raises(RequestError):
        server.open(policy=DeliveryPolicy.EVERY_BUFFER)  # a NORMAL connection
    with pytest.raises(RequestError):
        server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=0)
    with pytest.raises(RequestError):
        server.open(ConnectionKind.DATA, policy=DeliveryPolicy.LATEST, depth=3)
    with pytest.raises(RequestError):
        server.open(ConnectionKind.DATA, policy="sometimes")  # type: ignore[call-overload]
    defaults = {
        policy: server.open(ConnectionKind.DATA, policy=policy).depth for policy in DeliveryPolicy
    }
    assert defaults == {
        DeliveryPolicy.LATEST: 1,
        DeliveryPolicy.EVERY_BUFFER: 8,
        DeliveryPolicy.EVERY_ACQUISITION: 256,
    }


def test_nothing_is_lost_silently_in_continuous_acquisition(make_rig: RigFactory) -> None:
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord(continuous_acquisition=True)) as server:
        stream = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION, depth=8)
        buffers = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=1)
        total = _sweeps(server, 3)
        status = server.status()
        acquisitions = status["counters"]["acquisitions"]
        for conn, expected in ((stream, acquisitions), (buffers, total)):
            entry = status["connections"][conn.ident]
            assert entry["delivered"] == 0
            assert entry["queued"] + entry["dropped"] == expected
        item = buffers.ready_for_data(timeout=WAIT)
        assert isinstance(item, Scan) and buffers.dropped == total - 1
        assert status["counters"]["dropped_deliveries"] >= total - 1 + acquisitions - 8
