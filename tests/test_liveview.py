"""The live view, checked from the other end: a real WebSocket client (``websockets``) speaking
the Foxglove protocol sees the channels advertised and receives messages that decode; through a
fault it stays open, says ERROR on /diagnostics and gets data again after a reset. ``biris
view`` itself is run in-process through a fault and a reset from another thread. A view nobody
closes is closed by the garbage collector, or at the interpreter's exit."""

from __future__ import annotations

import argparse
import functools
import gc
import io
import json
import subprocess
import sys
import threading
import time
import weakref
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore
from websockets.sync.client import connect

from biris_hw import BirisServer
from biris_hw.cli import build_parser
from biris_hw.commands import session as cli_session
from biris_hw.commands import view as view_command
from biris_hw.errors import ConnectionLost
from biris_hw.io import codec as ros2
from biris_hw.io import liveview
from biris_hw.io.liveview import FAULT_POLL_S, LiveView
from biris_hw.io.record.replay import ReplayServer
from biris_hw.status import ServerState
from sim import SimulatedBiris
from tests import foxglove_client as fox
from tests.conftest import until
from tests.foxglove_client import SUBPROTOCOL
from tests.test_cli import SIM as CLI_SIM
from tests.test_record_support import cloud_xyz, synthetic_scans, write_raw

# the Foxglove WebSocket server's threads call into the server: scaled real time
pytestmark = pytest.mark.realtime


@functools.cache
def standard() -> Typestore:
    """rosbags' own ROS 2 Humble typestore, as a stranger's reader holds it (built on first use:
    building it at import cost every test worker a quarter of a second of collection)."""
    return get_typestore(Stores.ROS2_HUMBLE)


WAIT = 10.0


@pytest.fixture(scope="module", autouse=True)
def _foxglove_runtime() -> None:
    """foxglove-sdk keeps its runtime (an epoll, an eventfd, a socket pair) for the life of the
    process once a server has run: start it before any test's leak check takes its snapshot."""
    import foxglove

    foxglove.start_server(port=0, context=foxglove.Context()).stop()


def test_live_view_advertises_and_delivers_decodable_messages(tmp_path: Path) -> None:
    scans = synthetic_scans(4, n_acq=80, samples=32)  # more acquisitions than one batch takes
    path = write_raw(tmp_path / "run.mcap", scans)
    replay = ReplayServer(path, speed=None, autostart=False)
    view = LiveView(replay, port=0, status_period_s=0.05, sweep_period_s=0.0)
    with replay, view, connect(f"ws://127.0.0.1:{view.port}", subprotocols=[SUBPROTOCOL]) as ws:
        channels = fox.advertised(ws, len(ros2.TOPICS))
        assert set(channels) == set(ros2.TOPICS)
        for topic, channel in channels.items():
            assert channel["encoding"] == "cdr"
            assert channel["schemaName"] == ros2.TOPICS[topic]
            assert channel["schemaEncoding"] == "ros2msg"
            text = standard().generate_msgdef(channel["schemaName"], ros_version=2)[0]
            assert channel["schema"] == text
        stream = fox.messages(ws, fox.subscribe(ws, channels.values()), standard())
        acquisitions = sum(s.n_acq for s in scans)
        want = {"/biris/points": len(scans), "/biris/profile": acquisitions, "/tf": acquisitions}
        swept = sum(int((s.range_mm > 0).sum()) for s in scans)
        got: dict[str, list[Any]] = {}
        started = False
        while (
            any(len(got.get(t, [])) < n for t, n in want.items())
            or not all(t in got for t in ("/diagnostics", "/tf_static"))
            or sum(m.width for m in got.get("/biris/sweep", [])) < swept
        ):
            if not started and view.published.get("/diagnostics"):
                replay.start()  # the subscriptions are in place
                started = True
            topic, message, _ = next(stream)
            got.setdefault(topic, []).append(message)
    for scan, cloud in zip(scans, got["/biris/points"], strict=False):
        np.testing.assert_allclose(cloud_xyz(cloud), scan.points(), atol=1e-5)
    # /biris/sweep: each message the acquisitions since the previous one, every point sent once
    # (not the whole sweep again each time), which put together are the scans' clouds
    sweep = got["/biris/sweep"]
    assert len(sweep) > 1 and all(m.header.frame_id == ros2.VEHICLE_FRAME for m in sweep)
    assert all(len(m.data) == m.width * m.point_step for m in sweep)
    assert sum(m.width for m in sweep) == swept
    pieces = np.concatenate([cloud_xyz(m) for m in sweep])
    np.testing.assert_allclose(pieces, np.concatenate([s.points() for s in scans]), atol=1e-5)
    assert got["/diagnostics"][0].status[0].name == "server"  # shown as "biris: server"


def test_the_layout_keeps_the_sweep_pieces_long_enough_to_show_a_sweep() -> None:
    """The layout (liveview.LAYOUT_FILE) shows every cloud topic in its 3-D panel; /biris/sweep
    carries only the points since its previous message, so the panel must keep them (a decay
    time)."""
    layout = json.loads(liveview.LAYOUT_FILE.read_text())
    topics = layout["configById"]["3D!biris"]["topics"]
    clouds = {t for t, msgtype in ros2.TOPICS.items() if msgtype == ros2.POINT_CLOUD2}
    assert clouds <= set(topics)
    assert topics["/biris/sweep"]["decayTime"] > 0


def _subscribe(ws: Any, topics: list[str]) -> dict[int, dict[str, Any]]:
    """Subscribe to ``topics``; the subscriptions by id (the channel's)."""
    channels = fox.advertised(ws, len(ros2.TOPICS))
    return fox.subscribe(ws, [channels[t] for t in topics])


def _messages(ws: Any, subs: dict[int, dict[str, Any]]) -> Iterator[tuple[str, Any]]:
    """(topic, decoded message) for every message the server sends, for as long as asked (a
    TimeoutError if the view went quiet)."""
    for topic, message, _ in fox.messages(ws, subs, standard()):
        yield topic, message


def _stamp(message: Any) -> float:
    return float(message.header.stamp.sec + message.header.stamp.nanosec * 1e-9)


def test_a_fault_shows_on_diagnostics_while_the_view_serves_on(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    """A parity fault mid-sweep: the WebSocket stays open, /diagnostics says ERROR with the
    fault's kind and the server's message (and keeps saying it), the sensor is asked for data
    only every FAULT_POLL_S meanwhile, and after reset() new acquisitions arrive again."""
    view = LiveView(server, port=0, status_period_s=0.1)
    with (
        view,
        # no bound on what waits unread: the test stops reading while the view still sends,
        # and a full queue would keep the client from seeing the close (a 10 s timeout)
        connect(
            f"ws://127.0.0.1:{view.port}",
            subprotocols=[SUBPROTOCOL],  # type: ignore[list-item]
            max_queue=None,
        ) as ws,
        server.open() as conn,
    ):
        subs = _subscribe(ws, ["/diagnostics", "/biris/profile"])
        messages = _messages(ws, subs)
        conn.continuous_scan(-20.0, 20.0)
        assert any(topic == "/biris/profile" for topic, _ in messages)  # data flow
        rig.faults.parity_error()
        faulted = time.monotonic()
        errors = []
        for topic, message in messages:
            if topic == "/diagnostics" and message.status[0].level == 2:  # ERROR
                errors.append(message.status[0])
                if len(errors) == 2:  # said again at the status period: the view goes on
                    break
        for status in errors:
            assert status.name == "server"
            assert status.message == "fault:parity: parity error on the coupler"
        assert not view.failed.is_set()
        assert 1 <= view.faults_met <= 2 + (time.monotonic() - faulted) / FAULT_POLL_S
        conn.reset()
        reset_at = rig.clock.now()
        conn.continuous_scan(-20.0, 20.0)
        ok = new_data = False
        for topic, message in messages:
            if topic == "/diagnostics":
                ok = ok or message.status[0].level == 0
            elif _stamp(message) > reset_at:
                new_data = True
            if ok and new_data:
                break
        conn.stop_scan()
        conn.wait_idle(timeout=WAIT)
    assert view.error is None


def test_a_reset_while_the_view_reads_does_not_end_it(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    """While a reset initialises the sensor, every ask for data is refused (the server is
    initialising); the view reads on, on the same connections, and the data come back."""

    def delivered() -> int:  # to the view's every-acquisition connection, by the server
        conns = server.status().connections.values()
        return sum(c.delivered for c in conns if c.policy == "EVERY_ACQUISITION")

    view = LiveView(server, port=0)
    with view, server.open() as conn:
        conn.continuous_scan(-20.0, 20.0)
        until(lambda: delivered() > 0, what="acquisitions read by the view")
        conn.reset()  # the view asks every 50 ms meanwhile: a reset takes longer than that
        before = delivered()
        conn.continuous_scan(-20.0, 20.0)
        until(lambda: delivered() > before, what="acquisitions read again after the reset")
        assert not view.failed.is_set(), view.error
        conn.stop_scan()
        conn.wait_idle(timeout=WAIT)


def test_closing_a_view_in_a_fault_does_not_wait_out_its_pause(
    rig: SimulatedBiris, server: BirisServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The feed pauses between asks while the sensor is in a fault; a close ends the pause at
    once (made 60 s here, so that waiting it out would show)."""
    monkeypatch.setattr(liveview, "FAULT_POLL_S", 60.0)
    view = LiveView(server, port=0).start()
    try:
        rig.faults.parity_error()
        until(lambda: view.faults_met >= 2, what="the feed to meet the fault and pause")
    finally:
        started = time.monotonic()
        view.close()
    assert time.monotonic() - started < WAIT
    with server.open() as conn:
        conn.reset()


def test_biris_view_serves_on_through_a_fault(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], no_target_env: None
) -> None:
    """``biris view --sim --cw --ccw`` meets a fault mid-sweep: it says so once and serves on;
    a reset (from another thread, as a controller elsewhere would) brings the sweep back, and
    the view ends with status 0."""
    rigs: list[SimulatedBiris] = []
    start_rig = cli_session._start_rig

    def keep(args: argparse.Namespace) -> SimulatedBiris:
        rigs.append(start_rig(args))
        return rigs[-1]

    monkeypatch.setattr(cli_session, "_start_rig", keep)
    stop = threading.Event()
    failure: list[BaseException] = []
    helpers: list[threading.Thread] = []

    def meddle(live: LiveView) -> None:
        """Break the sensor once it sweeps, check the view goes on, reset, see it sweep."""
        server = live.source
        assert isinstance(server, BirisServer)
        try:
            until(lambda: server.status().state is ServerState.SCANNING, what="a sweep")
            rigs[-1].faults.parity_error()
            until(lambda: server.status().state is ServerState.FAULT, what="the fault")
            until(lambda: live.faults_met >= 2, what="the view to meet the fault twice")
            assert not live.failed.is_set()
            server.reset()
            until(lambda: server.status().state is ServerState.SCANNING, what="a new sweep")
        except BaseException as exc:
            failure.append(exc)
        finally:
            stop.set()

    def ready(live: LiveView) -> None:
        helpers.append(threading.Thread(target=meddle, args=(live,), name="test-meddle"))
        helpers[0].start()

    argv = ["view", "--port", "0", "--cw", "-20", "--ccw", "20", "--duration", "30", *CLI_SIM]
    try:
        code = view_command.run(
            build_parser("view").parse_args(argv), io.StringIO(), ready=ready, stop=stop
        )
    finally:
        for thread in helpers:
            thread.join()
    assert not failure, failure
    assert code == 0
    # warnings (a scan that began late, a simulator running late) depend on the host's load
    said = [line for line in capsys.readouterr().err.splitlines() if ": warning: " not in line]
    assert len(said) == 3, said
    assert said[0].startswith("biris view: hardware fault (parity): parity error on the coupler")
    assert said[0].endswith("the live view serves on and shows it on /diagnostics")
    assert said[1].startswith("biris view: the server has left the fault (state ")
    assert said[2] == "biris view: sweeping again"


# -- a view nobody closes --------------------------------------------------------------------------


def _listening(port: int) -> bool:
    """A viewer can open the WebSocket (a whole handshake: a bare TCP probe would make the
    server log a failed one from a thread of its own)."""
    try:
        with connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[SUBPROTOCOL],  # type: ignore[list-item]
            open_timeout=WAIT,
        ):
            return True
    except OSError:
        return False


def test_a_view_nobody_closes_is_closed_by_the_garbage_collector(
    rig: SimulatedBiris, server: BirisServer
) -> None:
    """The feed holds a view only weakly: once its owner drops it, the collector takes it, and
    its WebSocket server stops and its sink detaches (the feed, its last, stops reading)."""
    view: LiveView | None = LiveView(server, port=0).start()
    assert view is not None
    port = view.port
    ref = weakref.ref(view)
    assert _listening(port)
    until(lambda: len(server.status().connections) > 0, what="the view's feed reading")
    view = None
    gc.collect()
    assert ref() is None
    until(lambda: not _listening(port), what="the WebSocket server stopped")
    until(lambda: not server.status().connections, what="the feed's connections closed")


_FORGETFUL = """
import logging, sys
logging.basicConfig(stream=sys.stderr, level=logging.WARNING, format="%(message)s")
logging.getLogger("biris_hw.io.liveview").setLevel(logging.DEBUG)
from sim import Scene, SimulatedBiris
from biris_hw import BirisServer
from biris_hw.records import BirisInitRecord
from biris_hw.io.liveview import LiveView
rig = SimulatedBiris(scene=Scene.circle(2.0), clock="virtual", seed=3).start()
server = BirisServer(rig.hardware, BirisInitRecord()).__enter__()
view = LiveView(server, port=0).start()
print(view.port, flush=True)
"""
"""A script that opens a live view (and its sensor) and ends without closing anything."""


def test_a_script_that_forgets_close_ends_and_its_view_is_closed_at_exit() -> None:
    done = subprocess.run(
        [sys.executable, "-c", _FORGETFUL],
        cwd=Path(__file__).parents[1],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    port = int(done.stdout)
    closed = f"live view on ws://127.0.0.1:{port} closed: its owner had not closed it"
    assert closed in done.stderr.splitlines(), done.stderr


# -- log times: the hardware clock's, or the host's wall clock -------------------------------------


class _Clocked:
    """A sensor as LogTimes.anchor_to sees it: a status (that may fail) and a clock."""

    def __init__(self, clock: float, fails: bool = False) -> None:
        self.clock_s = clock
        self.fails = fails
        self.asked = 0

    def status(self) -> None:
        self.asked += 1
        if self.fails:
            raise ConnectionLost("the service cannot be reached now")

    def clock(self) -> float:
        return self.clock_s


def test_wall_log_times_move_every_stamp_by_one_offset() -> None:
    """The offset is measured once (wall now minus the sensor's clock now, a status asked first
    to bring a network sensor's clock up to date); intervals stay the hardware's, a late message
    included; a clock that goes back by more than RESTART_S (a restart) is measured afresh;
    hardware log times are the stamps."""
    wall = iter([1_700_000_000_000_000_000, 1_700_000_100_000_000_000])
    times = ros2.LogTimes("wall", wall_ns=lambda: next(wall))
    sensor = _Clocked(100.0)
    times.anchor_to(sensor)
    assert sensor.asked == 1 and times.offset_ns == 1_700_000_000_000_000_000 - 100 * 10**9
    assert times(100 * 10**9) == 1_700_000_000_000_000_000
    assert times(102_500_000_000) - times(100 * 10**9) == 2_500_000_000  # late by 2.5 s
    assert times.anchors == 1
    assert times(3 * 10**9) == 1_700_000_100_000_000_000  # back by 99.5 s: a restarted clock
    assert times.anchors == 2
    hardware = ros2.LogTimes()
    hardware.anchor_to(_Clocked(10.0))
    assert hardware(123) == 123 and hardware.offset_ns == 0 and hardware.anchors == 0


def test_a_stamp_is_hardware_or_wall() -> None:
    with pytest.raises(ValueError, match="stamp must be one of hardware, wall"):
        ros2.LogTimes("gps")  # type: ignore[arg-type]


def test_without_a_clock_the_first_message_measures_the_offset() -> None:
    """A sensor that cannot say its time yet (a replay not begun, a service out of reach)."""
    times = ros2.LogTimes("wall", wall_ns=lambda: 5 * 10**18)
    for sensor in (_Clocked(0.0), _Clocked(3.0, fails=True)):
        times.anchor_to(sensor)
    assert times.anchors == 1  # the one that failed its status still had a clock: 3.0
    late = ros2.LogTimes("wall", wall_ns=lambda: 5 * 10**18)
    late.anchor_to(_Clocked(0.0))
    assert late.offset_ns is None and late(7 * 10**9) == 5 * 10**18


def test_the_live_view_logs_on_the_wall_clock_and_keeps_hardware_stamps(tmp_path: Path) -> None:
    scans = synthetic_scans(2)
    replay = ReplayServer(write_raw(tmp_path / "run.mcap", scans), speed=None, autostart=False)
    view = LiveView(replay, port=0, stamp="wall", status_period_s=0.05)
    before = time.time_ns()
    with replay, view, connect(f"ws://127.0.0.1:{view.port}", subprotocols=[SUBPROTOCOL]) as ws:
        subs = _subscribe(ws, ["/biris/profile"])
        replay.start()
        offsets = set()
        received = 0
        stream = fox.messages(ws, subs, standard())
        while received < 20:  # profiles of both scans' acquisitions
            _, message, log_time = next(stream)
            stamp = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
            assert 10 * 10**9 <= stamp <= 20 * 10**9  # the hardware clock's seconds, as recorded
            offsets.add(log_time - stamp)
            received += 1
    (offset,) = offsets
    assert offset == view.log_times.offset_ns
    assert before - 20 * 10**9 <= offset + 10 * 10**9 <= time.time_ns()  # today, not 1970


def test_a_recording_logs_on_the_wall_clock_when_asked_and_says_so(tmp_path: Path) -> None:
    """The same data recorded twice: on the wall clock every message is logged one offset later
    than on the hardware clock, the offset the metadata gives, today's date; the messages are
    the same bytes (their stamps the hardware's)."""
    from mcap.reader import make_reader

    from biris_hw.io.record import Recorder

    data_topics = ("/biris/profile", "/tf", "/biris/points", "/biris/raw/point", "/biris/raw/scan")
    found: dict[str, list[tuple[str, int, bytes]]] = {}
    records: dict[str, dict[str, dict[str, str]]] = {}
    for stamp in ("wall", "hardware"):
        out = tmp_path / f"{stamp}.mcap"
        source = ReplayServer(
            write_raw(tmp_path / "source.mcap", synthetic_scans(2)), speed=None, autostart=False
        )
        with source, Recorder(source, out, stamp=stamp) as recorder:  # type: ignore[arg-type]
            source.start()
            assert source.wait_done(WAIT)
        assert recorder.summary is not None and recorder.summary.complete
        with open(out, "rb") as f:
            reader = make_reader(f)
            records[stamp] = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            found[stamp] = [
                (channel.topic, message.log_time, bytes(message.data))
                for _schema, channel, message in reader.iter_messages(log_time_order=False)
            ]
    for stamp in ("wall", "hardware"):
        assert records[stamp]["biris"]["log_time"] == stamp
        assert records[stamp]["biris.recording"]["log_time"] == stamp
    assert "log_time_offset_ns" not in records["hardware"]["biris.recording"]
    offset = int(records["wall"]["biris.recording"]["log_time_offset_ns"])
    assert abs(offset + 10 * 10**9 - time.time_ns()) < 600 * 10**9  # today, not 1970
    for topic in data_topics:
        wall = [(t, data) for name, t, data in found["wall"] if name == topic]
        hardware = [(t, data) for name, t, data in found["hardware"] if name == topic]
        assert wall and [d for _, d in wall] == [d for _, d in hardware], topic
        assert {w - h for (w, _), (h, _) in zip(wall, hardware, strict=True)} == {offset}, topic
    assert min(t for _, t, _ in found["wall"]) >= offset  # every message moved, none in 1970
    profile = next(data for name, _, data in found["hardware"] if name == "/biris/profile")
    header = ros2.typestore().deserialize_cdr(profile, ros2.POINT_CLOUD2).header
    first = next(t for name, t, _ in found["hardware"] if name == "/biris/profile")
    assert first == header.stamp.sec * 10**9 + header.stamp.nanosec  # hardware: the stamp


def test_the_sdk_takes_its_own_subprotocol_only_and_any_origin(tmp_path: Path) -> None:
    """What the module tells of the viewers and of who can connect, as foxglove-sdk does it: the
    old name ``foxglove.websocket.v1`` is refused (HTTP 400: Foxglove Studio 1.x and Lichtblick
    before 1.22.1 cannot connect), ``foxglove.sdk.v1`` is taken, and so is a page of any
    origin. A later SDK that changes either fails this, and the documents should change."""
    from websockets.exceptions import InvalidStatus
    from websockets.typing import Origin, Subprotocol

    recording = write_raw(tmp_path / "run.mcap", synthetic_scans(1))
    with (
        ReplayServer(recording, autostart=False) as replay,
        LiveView(replay, port=0, layout_port=None) as view,
    ):
        url = f"ws://127.0.0.1:{view.port}"
        assert "layout" not in view.urls and "open" not in view.urls
        with pytest.raises(InvalidStatus, match="HTTP 400"):
            connect(url, subprotocols=[Subprotocol("foxglove.websocket.v1")], open_timeout=WAIT)
        offered = [Subprotocol(liveview.SUBPROTOCOL)]
        with connect(url, subprotocols=offered, origin=Origin("https://any.example")) as ws:
            assert ws.subprotocol == liveview.SUBPROTOCOL
            assert json.loads(ws.recv(timeout=WAIT))["op"] == "serverInfo"
