"""A recording served on the network like a live sensor (issue 15, point 2, after issue 14).

Fast: the replay, the service and a client in this process, through Zenoh on loopback TCP.
Slow: ``biris serve --replay`` in another process, with ``--foxglove`` (a real WebSocket client
sees the live view's channels), and a client process-side connecting to it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from biris_hw import ConnectionKind, Direction
from biris_hw.data import DeliveryPolicy, Scan
from biris_hw.errors import AccessDenied, ConnectionClosed, RequestError
from biris_hw.io.net import connect, serve
from biris_hw.io.net.keys import error_payload
from biris_hw.io.record import write_scans
from biris_hw.io.record.replay import EndOfRecording, ReplayRefused, ReplayServer
from tests.net_helpers import Helper, endpoint, free_port, warm_up_zenoh
from tests.test_record_support import synthetic_scans
from tests.test_wire import assert_scans_equal

CONTROLLERS = {"op": "s3cret"}
WAIT = 10.0
SPEED = 100.0
"""Fast, but paced: a served recording must have a speed (speed=None is refused, see below)."""


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


@pytest.fixture
def recording(tmp_path: Path) -> tuple[Path, list[Scan]]:
    scans = synthetic_scans(4)
    return write_scans(tmp_path / "run.mcap", scans), scans


@pytest.fixture
def served(recording: tuple[Path, list[Scan]]) -> Iterator[tuple[ReplayServer, str]]:
    path, _ = recording
    where = endpoint(free_port())
    with (
        ReplayServer(path, speed=SPEED, autostart=False) as replay,
        serve(
            replay,
            name="rec",
            listen=[where],
            controllers=CONTROLLERS,
            multicast=False,
            playback=True,
        ),
    ):
        yield replay, where


def test_clients_get_the_recorded_scans_equal(recording: tuple[Path, list[Scan]]) -> None:
    path, scans = recording
    where = endpoint(free_port())
    with (
        ReplayServer(path, speed=SPEED, autostart=False) as replay,
        serve(replay, name="rec", listen=[where], multicast=False) as service,
        connect("rec", [where], multicast=False) as remote,
    ):
        assert not service.data_opened.is_set()  # the service's own feeds do not count
        data = remote.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=16)
        assert service.data_opened.is_set()
        replay.start()  # what `biris serve --replay` does on data_opened
        got = [data.ready_for_data(timeout=WAIT) for _ in scans]
        for sent, back in zip(scans, got, strict=True):
            assert_scans_equal(sent, back)
        # the end of the recording: the replay's EndOfRecording, a ConnectionClosed on the wire
        with pytest.raises(ConnectionClosed, match="played to its end"):
            data.ready_for_data(timeout=WAIT)
        latest = remote.open().request_scan_data(Direction.CCW)
        assert latest is not None
        assert_scans_equal(scans[-1] if scans[-1].direction is Direction.CCW else scans[-2], latest)
        assert remote.status()["state"] == "idle"
        assert data.dropped == 0


def test_motion_is_refused_with_the_replays_error(served: tuple[ReplayServer, str]) -> None:
    replay, where = served
    with (
        connect("rec", [where], multicast=False) as reader,
        connect("rec", [where], "op", "s3cret", multicast=False) as controller,
    ):
        for remote in (reader, controller):  # credentials or not: a recording cannot move
            conn = remote.open()
            with pytest.raises(RequestError, match="cannot move or configure") as caught:
                conn.single_scan(10.0)
            assert not isinstance(caught.value, AccessDenied)
            with pytest.raises(RequestError, match="cannot move or configure"):
                conn.home()
        assert not replay.finished and replay.played["scans"] == 0  # nothing happened


def test_a_replay_without_a_pace_is_refused(recording: tuple[Path, list[Scan]]) -> None:
    """speed=None plays as fast as the slowest reader: one stalled remote EVERY_BUFFER reader
    would stall every client. Refused when served; and the replay is known as one without being
    told (playback is the sensor's property, not the caller's say-so)."""
    path, _ = recording
    with (
        ReplayServer(path, speed=None, autostart=False) as replay,
        pytest.raises(RequestError, match="speed=None"),
        serve(replay, multicast=False),
    ):
        pass


def test_replay_errors_name_their_class_on_the_wire() -> None:
    """For a non-Python client: the base error it must handle, and the exact one."""
    end = json.loads(error_payload(EndOfRecording("run.mcap: played to its end")))
    assert end == {
        "error": "ConnectionClosed",
        "class": "EndOfRecording",
        "message": "run.mcap: played to its end",
    }
    refused = json.loads(error_payload(ReplayRefused("home: a replay cannot move")))
    assert (refused["error"], refused["class"]) == ("RequestError", "ReplayRefused")
    assert "class" not in json.loads(error_payload(RequestError("plain")))


@pytest.mark.slow
def test_biris_serve_replay_with_live_view(
    recording: tuple[Path, list[Scan]], no_leaks: None
) -> None:
    """``biris serve --replay FILE --foxglove 0`` in another process: a client gets the
    recorded scans equal; a WebSocket client sees the live view advertise its channels."""
    from websockets.sync.client import connect as ws_connect
    from websockets.typing import Subprotocol

    from biris_hw.io import codec as ros2

    path, scans = recording
    where = endpoint(free_port())
    args = ["--replay", str(path), "--speed", "50", "--name", "rec2", "--listen", where]
    helper = Helper(["cli-serve", *args, "--no-multicast", "--foxglove", "0"])
    try:
        url = helper.expect("live view: ").split()[2]
        helper.expect("serving rec2")
        with ws_connect(url, subprotocols=[Subprotocol("foxglove.sdk.v1")]) as ws:
            assert json.loads(ws.recv(timeout=WAIT))["op"] == "serverInfo"
            topics: set[str] = set()
            while topics != set(ros2.TOPICS):
                message = json.loads(ws.recv(timeout=WAIT))
                topics |= {channel["topic"] for channel in message.get("channels", [])}
        with connect("rec2", [where], multicast=False) as remote:
            data = remote.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=16)
            got = [data.ready_for_data(timeout=WAIT) for _ in scans]  # playing starts now
            for sent, back in zip(scans, got, strict=True):
                assert_scans_equal(sent, back)
            with pytest.raises(ConnectionClosed, match="played to its end"):
                data.ready_for_data(timeout=WAIT)
    finally:
        assert helper.close() == 143  # SIGTERM ends biris serve as Ctrl-C does: 128 + 15
