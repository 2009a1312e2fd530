"""An idle sensor costs what its watchers need, counted (never timed): round trips to the
administrator and bus reads, on virtual time.

The status reaches a watcher when it changes (``status(newer_than=...)``); a reader that was told
nothing waits is not answered again until something has happened; the encoders are read through
the administrator, at most once a hardware second at rest and ten times while an axis moves
(:mod:`biris_hw.server.encoders`). Counted from outside, as ``make bench``'s ``idle`` section
counts them: every message posted to the administrator's inbox, every read of the bus windows.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pytest

from benchmarks.idle import Tally, count_posts, count_reads
from biris_hw import BirisInitRecord, BirisServer, ConnectionKind, DeliveryPolicy
from biris_hw import protocol as p
from biris_hw.data import Point
from biris_hw.errors import ConnectionClosed
from biris_hw.server import messages as m
from biris_hw.server.encoders import MOVING_PERIOD_S, REST_PERIOD_S
from biris_hw.server.isr import COUPLER_WATCH_S
from biris_hw.status import ServerState, ServerStatus
from sim import SimulatedBiris
from tests.conftest import WAIT, RigFactory, join, spawn

if TYPE_CHECKING:
    from tests.core import Core


def _counted(rig: SimulatedBiris, server: BirisServer) -> tuple[Tally, Tally]:
    posts, reads = Tally(), Tally()
    count_posts(server.inbox, posts)
    count_reads(rig.hardware, reads)
    return posts, reads


def _seconds(rig: SimulatedBiris, hw_s: float) -> float:
    """A caller's timeout that lasts ``hw_s`` hardware seconds on this rig."""
    return hw_s / rig.timebase.timeout_hw(1.0)


def test_a_watcher_of_an_idle_sensor_costs_nothing(make_rig: RigFactory) -> None:
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        status = server.status()
        posts, reads = _counted(rig, server)
        begun = server.clock()
        with pytest.raises(TimeoutError):  # ten hardware seconds without a change
            server.status(newer_than=status.change, timeout=_seconds(rig, 10.0))
        assert server.clock() - begun >= 10.0
        assert sum(posts.snapshot().values()) == 0  # the wait was spent on the bulletin
        # nothing is read but the coupler's status, once a COUPLER_WATCH_S: a crate that loses
        # power is the one thing an idle sensor must still notice (issue 26)
        read = reads.snapshot()
        assert set(read) <= {"coupler"}
        assert read["coupler"] <= (server.clock() - begun) / COUPLER_WATCH_S + 1


def test_a_change_is_pushed_to_a_waiting_watcher(make_rig: RigFactory) -> None:
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        status = server.status()
        got: list[object] = []
        watcher = spawn(lambda: got.append(server.status(newer_than=status.change, timeout=WAIT)))
        conn = server.open()
        assert join(watcher)
        pushed = got[0]
        assert isinstance(pushed, type(status)) and pushed.change > status.change
        assert conn.ident in pushed.connections


def test_status_reads_the_encoders_at_the_status_rate_and_no_faster(
    make_rig: RigFactory,
) -> None:
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        posts, reads = _counted(rig, server)
        for _ in range(50):  # back to back, at rest: one reading serves them all
            server.status()
        assert posts.snapshot()["EncoderReading"] <= 1
        assert reads.snapshot()["motion"] <= 2  # one read of each axis's encoder
        # a status asked every quarter of a hardware second, for ten: at rest, a reading a
        # second at most
        posts, reads = _counted(rig, server)
        begun = server.clock()
        asked = 0
        while server.clock() - begun < 10.0:
            status = server.status()
            asked += 1
            with pytest.raises(TimeoutError):
                server.status(newer_than=status.change, timeout=_seconds(rig, 0.25))
        elapsed = server.clock() - begun
        readings = posts.snapshot()["EncoderReading"]
        assert asked >= 40
        assert 1 <= readings <= elapsed / REST_PERIOD_S + 1
        assert reads.snapshot()["motion"] == 2 * readings  # nothing else reads the bus
        assert posts.snapshot()["StatusRequest"] == asked  # a wait for a change asks nothing


def test_a_moving_head_is_read_ten_times_a_second_at_most(make_rig: RigFactory) -> None:
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        conn = server.open()
        posts, _reads = _counted(rig, server)
        begun = server.clock()
        conn.single_scan(180.0)
        seen: set[int] = set()
        status = server.status()
        while status.state.value != "idle":
            if status.azimuth_live is not None:
                seen.add(status.azimuth_live)
            try:  # asked every 20 hardware ms, or on a change
                status = server.status(newer_than=status.change, timeout=_seconds(rig, 0.02))
            except TimeoutError:
                status = server.status()
        elapsed = server.clock() - begun
        readings = posts.snapshot()["EncoderReading"]
        assert len(seen) >= 5  # the head was seen on its way
        assert readings <= elapsed / MOVING_PERIOD_S + 3  # plus the moves' ends
        final = server.status()
        assert final.azimuth_live is not None and abs(final.azimuth_live - final.azimuth) <= 2


def test_an_idle_reader_is_not_answered_twice_that_nothing_waits(make_rig: RigFactory) -> None:
    rig = make_rig()
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        conn = server.open()
        points = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
        posts, _reads = _counted(rig, server)
        for _ in range(100):  # a feed polling an idle sensor
            with pytest.raises(TimeoutError):
                points.ready_for_data(timeout=0)
        for _ in range(20):  # a feed waiting in short slices
            with pytest.raises(TimeoutError):
                points.ready_for_data(timeout=_seconds(rig, 0.05))
        # the first poll, and the first wait (parked in the administrator, as a wait after a
        # poll always is: it is answered the moment data come); then nothing changed
        assert posts.snapshot()["ReadyForData"] == 2
        # a reader waiting here is woken by the first acquisition and given it
        got: list[object] = []
        reader = spawn(lambda: got.append(points.ready_for_data(timeout=WAIT)))
        conn.single_scan(20.0)
        assert join(reader) and isinstance(got[0], Point)
        conn.wait_idle(timeout=WAIT)


# -- the administrator's side, without threads (tests/core.py) ---------------------------------


def test_a_status_request_waits_in_the_administrator_for_a_change(core: Core) -> None:
    """The client message itself: STATUS with ``newer_than`` is parked until the status's
    signature changes, answered at once when it has, and a poll never parks."""
    control = core.open()
    first = core.call(p.StatusRequest())
    assert isinstance(first, ServerStatus)
    parked = core.send(p.StatusRequest(None, first.change))
    with pytest.raises(TimeoutError):
        core.call(p.StatusRequest(None, first.change, poll=True))
    core.call(p.TimeoutEnable(control))  # a request that changes nothing a watcher acts on...
    assert not parked.done  # ...wakes nobody
    conn = core.open()  # a connection more: a change
    pushed = parked.wait(0)
    assert isinstance(pushed, ServerStatus) and pushed.change == first.change + 1
    assert conn in pushed.connections
    closing = core.send(p.StatusRequest(conn, pushed.change))  # parked on the connection...
    core.call(p.CloseRequest(conn))
    with pytest.raises(ConnectionClosed):  # ...ends with it
        closing.wait(0)


def test_the_administrators_signature_is_the_statuses(core: Core) -> None:
    """The administrator numbers changes of a signature it computes without building the
    status; it must be the status's own (ServerStatus.signature)."""

    def same() -> None:
        status = core.admin.status()
        assert core.admin._signature() == status.signature()

    same()
    conn = core.open()
    same()
    core.call(p.SetElevation(conn, 100))
    same()
    core.call(p.StartContinuous(conn))
    same()
    core.send(m.BirisBusErr())
    same()
    assert core.admin.status().state is ServerState.FAULT
