"""One contract, three sensors: what every :class:`biris_hw.sensor.Sensor` does.

The suite runs over every kind of sensor, as python-can runs one suite over every interface: a
local :class:`~biris_hw.BirisServer` on a virtual-time rig, a
:class:`~biris_hw.io.net.RemoteSensor` reaching a served server over Zenoh on loopback (scaled
time: Zenoh's threads are outside the time base), and a
:class:`~biris_hw.io.record.ReplayServer` of a recording made here. A program written against
the Protocol may count on everything checked below, whichever sensor it is given.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from biris_hw import BirisInitRecord, BirisServer, ConnectionKind, DeliveryPolicy, Direction
from biris_hw.data import Point, Scan
from biris_hw.errors import ConnectionClosed, RequestError
from biris_hw.io import codec
from biris_hw.io.record import RAW_POINT_TOPIC, RAW_SCAN_TOPIC, RAW_STATUS_TOPIC
from biris_hw.io.record.mcapfile import McapFile
from biris_hw.io.record.replay import ReplayRefused, ReplayServer
from biris_hw.records import MotorParams
from biris_hw.sensor import Connection, Sensor
from biris_hw.status import ServerState, ServerStatus
from tests.conftest import WAIT, RigFactory, idle_status, join, spawn
from tests.test_record_support import points_of, synthetic_scans

CONTROLLERS = {"op": "s3cret"}

KINDS = [
    pytest.param("local", id="local"),
    pytest.param("remote", id="remote", marks=pytest.mark.realtime),
    pytest.param("replay", id="replay"),
]


@dataclass
class Subject:
    """A sensor of one kind, and how to make it produce data."""

    kind: str
    sensor: Sensor
    produce: Callable[[], None]
    """Makes data come: one scan (a server), the whole recording (a replay)."""


def _scan_once(sensor: Sensor) -> None:
    with sensor.open() as conn:
        at = sensor.status().azimuth
        conn.single_scan(-20.0 if at > 0 else 20.0)
        conn.wait_idle(timeout=WAIT)


def _recording(path: Path) -> Path:
    """A recording as the recorder makes one: every acquisition, every scan, and statuses that
    say something new (idle, scanning at each scan's start, idle at the end), with the init
    record in its metadata."""
    scans = synthetic_scans(4)
    file = McapFile(path)
    file.metadata("biris", {"init_record": json.dumps(BirisInitRecord().to_dict())})

    def status(t: float, state: ServerState, azimuth: int) -> None:
        data = codec.encode_status(idle_status(state=state, azimuth=azimuth), t)
        file.write(
            RAW_STATUS_TOPIC,
            codec.STATUS,
            codec.full_definition(codec.STATUS),
            data,
            round(t * 1e9),
        )

    status(float(scans[0].t[0]) - 1.0, ServerState.IDLE, 0)
    for scan in scans:
        status(float(scan.t[0]) - 0.01, ServerState.SCANNING, int(scan.azimuth[-1]))
        for point in points_of(scan):
            file.write(
                RAW_POINT_TOPIC,
                codec.POINT,
                codec.full_definition(codec.POINT),
                codec.encode_point(point),
                round(point.t * 1e9),
            )
        assert scan.t_delivered is not None
        file.write(
            RAW_SCAN_TOPIC,
            codec.SCAN,
            codec.full_definition(codec.SCAN),
            codec.encode_scan(scan),
            round(scan.t_delivered * 1e9),
        )
    status(float(scans[-1].t[-1]) + 1.0, ServerState.IDLE, int(scans[-1].azimuth[-1]))
    assert file.close()
    return path


def _settled(remote: Sensor) -> None:
    """Until the service's own connections (its feed's) are open and the remote has heard all
    about them: half a second without a change, so a test starts from a status that stays put."""
    status = remote.status()
    while True:
        try:
            status = remote.status(newer_than=status.change, timeout=0.5)
        except TimeoutError:
            return


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    """Zenoh's runtime threads and descriptors start on first use and stay: started before any
    test's leak check takes its snapshot (tests/net_helpers.py)."""
    from tests.net_helpers import warm_up_zenoh

    warm_up_zenoh()


@pytest.fixture(scope="module")
def _served(_zenoh_runtime: None) -> Iterator[str]:
    """One service for the module's remote tests (its endpoint): serving a sensor costs most of
    a second, which every test would pay again. Each test connects a RemoteSensor of its own
    (:func:`subject`), starts from the sensor idle and without a fault, and leaves it so."""
    from biris_hw.io.net import serve
    from sim import Scene, SimulatedBiris
    from tests.conftest import SCALED_TIME_SCALE
    from tests.net_helpers import endpoint, free_port

    where = endpoint(free_port())
    rig = SimulatedBiris(scene=Scene.circle(2.0), time_scale=SCALED_TIME_SCALE, seed=11)
    with (
        rig.start(),
        BirisServer(rig.hardware, BirisInitRecord()) as server,
        serve(server, name="c", listen=[where], controllers=CONTROLLERS, multicast=False),
    ):
        yield where
        assert rig.audit.violations == []


@pytest.fixture(params=KINDS)
def subject(
    request: pytest.FixtureRequest, make_rig: RigFactory, tmp_path: Path, _served: str
) -> Iterator[Subject]:
    kind = str(request.param)
    with contextlib.ExitStack() as stack:
        if kind == "replay":
            path = _recording(tmp_path / "run.mcap")
            replay = stack.enter_context(ReplayServer(path, speed=None, autostart=False))

            def play() -> None:
                replay.start()
                assert replay.wait_done(WAIT)

            yield Subject(kind, replay, play)
            return
        if kind == "local":
            server = stack.enter_context(BirisServer(make_rig().hardware, BirisInitRecord()))
            yield Subject(kind, server, lambda: _scan_once(server))
            return
        from biris_hw.io.net import connect

        def reach() -> Sensor:
            return stack.enter_context(
                connect("c", [_served], multicast=False, user="op", password="s3cret")
            )

        keeper, remote = reach(), reach()  # the keeper: the test may close its own remote
        with keeper.open() as conn:
            if keeper.status().fault is not None:  # an earlier test's failure, not this one's
                conn.reset()
            conn.wait_idle(timeout=WAIT)
        yield Subject(kind, remote, lambda: _scan_once(remote))
        fault = keeper.status().fault
        if fault is not None:
            with keeper.open() as conn:
                conn.reset()
            pytest.fail(f"the test left the shared sensor in a fault: {fault}")


# -- lifecycle ---------------------------------------------------------------------------------


def test_open_and_close_are_idempotent_and_context_managers(subject: Subject) -> None:
    sensor = subject.sensor
    with sensor.open() as conn:
        opened = conn.closed, repr(conn)
        assert conn.kind is ConnectionKind.NORMAL and isinstance(conn.ident, int)
    assert opened[0] is False and opened[1].endswith("open>")
    assert conn.closed and repr(conn).endswith("closed>")
    conn.close()  # again: nothing
    data = sensor.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=4)
    assert (data.kind, data.policy, data.depth, data.dropped) == (
        ConnectionKind.DATA,
        DeliveryPolicy.EVERY_BUFFER,
        4,
        0,
    )
    data.close()
    data.close()
    with sensor as same:
        assert same is sensor
    sensor.close()  # again: nothing
    with pytest.raises(ConnectionClosed):
        sensor.open()
    with pytest.raises(ConnectionClosed):
        sensor.status()


def _control_calls(conn: Connection[Any]) -> list[Callable[[], object]]:
    """Every motion and configuration message, with valid arguments."""
    return [
        lambda: conn.single_scan(10.0),
        lambda: conn.continuous_scan(-10.0, 10.0),
        lambda: conn.set_elevation(5.0),
        conn.stop_scan,
        conn.start_continuous,
        conn.stop_continuous,
        conn.home,
        lambda: conn.set_motor_params(MotorParams()),
        conn.timeout_enable,
        conn.timeout_disable,
        conn.reset,
    ]


def test_a_closed_connection_refuses_every_call(subject: Subject) -> None:
    conn = subject.sensor.open()
    data = subject.sensor.open(ConnectionKind.DATA)
    conn.close()
    data.close()
    calls: list[Callable[[], object]] = [
        conn.request_point,
        lambda: conn.request_scan_data(Direction.CW),
        lambda: data.ready_for_data(timeout=0),
        lambda: data.ready_for_data(timeout=1.0),
        lambda: conn.wait_idle(timeout=0),
        conn.status,
        lambda: conn.status(newer_than=0, timeout=0),
        *_control_calls(conn),
    ]
    for call in calls:
        with pytest.raises(ConnectionClosed):
            call()


def test_closing_a_connection_ends_a_wait_on_it(subject: Subject) -> None:
    """What a service relies on to stop its feeds and its status watch at once."""
    data = subject.sensor.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
    watch = subject.sensor.open()
    if subject.kind == "remote":
        _settled(subject.sensor)  # the publication of these opens is not a wake below
    latest = watch.status()
    ended: dict[str, BaseException] = {}

    def wait(name: str, call: Callable[[], object]) -> None:
        try:
            call()
        except BaseException as exc:
            ended[name] = exc

    readers = [
        spawn(wait, "read", lambda: data.ready_for_data(timeout=None)),
        spawn(wait, "status", lambda: watch.status(newer_than=latest.change, timeout=None)),
    ]
    watch.close()  # first: closing ``data`` changes the status, which would end its wait
    data.close()
    assert all(join(thread) for thread in readers)
    assert isinstance(ended["read"], ConnectionClosed)
    assert isinstance(ended["status"], ConnectionClosed)


# -- status ------------------------------------------------------------------------------------


def test_status_has_the_fields(subject: Subject) -> None:
    sensor = subject.sensor
    conn = sensor.open()
    for status in (sensor.status(), conn.status()):
        assert isinstance(status, ServerStatus)
        assert isinstance(status.state, ServerState) and status.fault is None
        assert status["state"] == status.state_name and isinstance(status["state"], str)
        assert isinstance(status.azimuth, int) and isinstance(status.elevation, int)
        assert status.acquisition in ("single", "continuous")
        assert isinstance(status.counters, Mapping)
        assert all(isinstance(v, int) for v in status.counters.values())
        assert conn.ident in status.connections
        assert status.connections[conn.ident].kind == "NORMAL"
        assert isinstance(status.change, int) and status.change >= 0
        assert dict(status)["change"] == status.change  # reads as a mapping too
    assert isinstance(sensor.playback, bool) and isinstance(sensor.paced, bool)


def test_status_is_pushed_on_change(subject: Subject) -> None:
    sensor = subject.sensor
    if subject.kind == "remote":  # what the module's earlier tests changed has all been heard
        _settled(sensor)
    before = sensor.status()
    with pytest.raises(TimeoutError):  # nothing has changed: a poll says so at once
        sensor.status(newer_than=before.change, timeout=0)
    with pytest.raises(TimeoutError):  # and a wait waits for it
        sensor.status(newer_than=before.change, timeout=0.2)
    assert sensor.status(newer_than=before.change - 1, timeout=0).change == before.change
    got: list[ServerStatus] = []
    watcher = spawn(lambda: got.append(sensor.status(newer_than=before.change, timeout=WAIT)))
    conn = sensor.open()  # a connection more: the status has changed
    assert join(watcher) and got
    assert got[0].change > before.change and conn.ident in got[0].connections
    again = sensor.status(newer_than=before.change, timeout=WAIT)  # at once: it is newer
    assert again.change > before.change


def test_the_clock_never_goes_back(subject: Subject) -> None:
    sensor = subject.sensor
    seen = [sensor.clock()]
    subject.produce()
    seen.append(sensor.clock())
    sensor.status()
    seen.append(sensor.clock())
    assert all(isinstance(t, float) and math.isfinite(t) for t in seen)
    assert seen == sorted(seen) and seen[-1] > 0.0


# -- data --------------------------------------------------------------------------------------


def test_data_requests_return_their_types(subject: Subject) -> None:
    conn = subject.sensor.open()
    subject.produce()
    point = conn.request_point()
    assert isinstance(point, Point) and point.t_delivered is not None
    scans = [conn.request_scan_data(d) for d in (Direction.CW, Direction.CCW, 0, 1)]
    assert any(isinstance(scan, Scan) for scan in scans)
    assert all(scan is None or isinstance(scan, Scan) for scan in scans)
    for bad in (7, -1, True, "cw", None):
        with pytest.raises(RequestError):
            conn.request_scan_data(bad)  # type: ignore[arg-type]


def test_ready_for_data_under_each_policy(subject: Subject) -> None:
    sensor = subject.sensor
    latest = sensor.open(ConnectionKind.DATA)
    every = sensor.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
    points = sensor.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
    normal = sensor.open()
    for conn in (latest, every, points):
        with pytest.raises(TimeoutError):
            conn.ready_for_data(timeout=0)  # nothing yet: a poll answers at once
    with pytest.raises(RequestError):
        normal.ready_for_data(timeout=0)  # READY_FOR_DATA is for DATA connections
    subject.produce()
    scan = latest.ready_for_data(timeout=WAIT)
    assert isinstance(scan, Scan) and scan.t_delivered is not None
    assert isinstance(every.ready_for_data(timeout=WAIT), Scan)
    point = points.ready_for_data(timeout=WAIT)
    assert isinstance(point, Point) and point.t_delivered is not None
    for conn in (latest, every, points):
        assert isinstance(conn.dropped, int) and conn.dropped >= 0
    normal.wait_idle(timeout=WAIT)
    normal.wait_idle(timeout=0)  # idle now (a replay: played to its end)


# -- refusals ----------------------------------------------------------------------------------


def test_bad_input_is_refused_and_changes_nothing(subject: Subject) -> None:
    sensor = subject.sensor
    conn = sensor.open()
    data = sensor.open(ConnectionKind.DATA)
    if subject.kind == "remote":  # the publications of these opens are heard first
        _settled(sensor)
    before = sensor.status()
    nan, inf = float("nan"), float("inf")
    refusals: list[Callable[[], object]] = [
        lambda: conn.single_scan(nan),
        lambda: conn.single_scan("10"),  # type: ignore[arg-type]
        lambda: conn.continuous_scan(inf, 10.0),
        lambda: conn.set_elevation(None),  # type: ignore[arg-type]
        lambda: conn.set_motor_params({"gain": 1}),  # type: ignore[arg-type]
        lambda: data.ready_for_data(timeout=-1.0),
        lambda: data.ready_for_data(timeout=nan),
        lambda: conn.wait_idle(timeout="soon"),  # type: ignore[arg-type]
        lambda: sensor.status(newer_than="1"),  # type: ignore[arg-type]
        lambda: sensor.status(newer_than=True),
        lambda: sensor.status(newer_than=1.5),  # type: ignore[arg-type]
        lambda: sensor.status(timeout=-1.0),
        lambda: conn.status(newer_than=before.change, timeout=-1.0),
        lambda: sensor.open(7),  # type: ignore[call-overload]
        lambda: sensor.open(ConnectionKind.DATA, depth=0),
        lambda: sensor.open(ConnectionKind.DATA, policy="fast"),  # type: ignore[call-overload]
        lambda: sensor.open(ConnectionKind.NORMAL, policy=DeliveryPolicy.EVERY_BUFFER),
    ]
    for refusal in refusals:
        with pytest.raises(RequestError):
            refusal()
    after = sensor.status()
    assert after.signature() == before.signature() and after.change == before.change
    assert not conn.closed and not data.closed


def test_a_recording_refuses_motion_itself_and_a_live_sensor_moves(subject: Subject) -> None:
    sensor = subject.sensor
    record = sensor.record
    assert record is not None and record == BirisInitRecord()
    conn: Connection[Any] = sensor.open()
    if not sensor.playback:
        dest = conn.single_scan(15.0 if sensor.status().azimuth <= 0 else -15.0)
        assert isinstance(dest, int)
        conn.wait_idle(timeout=WAIT)
        assert sensor.status().azimuth == dest
        return
    assert subject.kind == "replay"
    before = sensor.status()
    for call in _control_calls(conn):
        with pytest.raises(ReplayRefused):
            call()
    assert sensor.status().signature() == before.signature()


# -- names -------------------------------------------------------------------------------------


def test_the_names_are_one_and_open_sensor_is_loaded_on_first_use() -> None:
    import biris_hw.client
    import biris_hw.opening
    import biris_hw.sensor

    assert biris_hw.client.Sensor is biris_hw.sensor.Sensor  # the old name, the same object
    assert biris_hw.sensor.open_sensor is biris_hw.opening.open_sensor
    assert "open_sensor" in biris_hw.sensor.__all__ and "open_sensor" in dir(biris_hw.sensor)
    with pytest.raises(AttributeError):
        biris_hw.sensor.no_such_name  # type: ignore[attr-defined]  # noqa: B018


@pytest.mark.realtime
def test_a_served_recording_says_so_through_the_network(tmp_path: Path) -> None:
    """A network client of a served recording is a recording too: ``playback`` and the init
    record come from the service, motion is refused with the replay's own refusal."""
    from biris_hw.io.net import Service, connect, serve
    from tests.net_helpers import endpoint, free_port

    where = endpoint(free_port())
    with (
        ReplayServer(_recording(tmp_path / "run.mcap"), speed=1.0, autostart=False) as replay,
        serve(replay, name="r", listen=[where], multicast=False),
        connect("r", [where], multicast=False) as remote,
    ):
        assert remote.playback and remote.paced and remote.record == BirisInitRecord()
        with remote.open() as conn, pytest.raises(RequestError, match="cannot move"):
            conn.single_scan(10.0)
    unpaced = ReplayServer(tmp_path / "run.mcap", speed=None)  # waits for its slowest reader
    with unpaced, pytest.raises(RequestError, match="slowest reader"):
        Service(unpaced, "s", multicast=False)
