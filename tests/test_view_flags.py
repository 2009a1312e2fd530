"""``biris view``'s flags, every one checked before the sensor is touched, and what it prints.

A port out of range, a port another program listens on, a host that is not this machine's, a
viewer that is not a web address: exit status 2 with a line naming the flag and the cause, and
no sensor opened (``open_session`` and ``open_sensor`` are replaced by ones that fail the test).
A host beyond loopback warns. Started on a small recording, the command prints the WebSocket,
the one URL that opens it with the project's layout, and Foxglove's; the layout it serves over
HTTP is the packaged one. Which log times (``--stamp``) each kind of sensor gets by default.
"""

from __future__ import annotations

import argparse
import io
import json
import socket
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import pytest

from biris_hw.cli import build_parser
from biris_hw.commands import view as view_command
from biris_hw.io import codec, liveview
from biris_hw.io.record import write_scans
from tests.conftest import Run
from tests.test_record_support import synthetic_scans

pytestmark = pytest.mark.usefixtures("no_target_env")

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module", autouse=True)
def _foxglove_runtime() -> None:
    """foxglove-sdk keeps its runtime (an epoll, an eventfd, a socket pair) for the life of the
    process once a server has run: start it before any test's leak check takes its snapshot."""
    import foxglove

    foxglove.start_server(port=0, context=foxglove.Context()).stop()


class Touched(AssertionError):
    """The command opened a sensor although a flag was wrong."""


@pytest.fixture
def untouched(monkeypatch: pytest.MonkeyPatch) -> None:
    """Opening any sensor fails the test."""

    def refuse(*_args: object, **_kwargs: object) -> None:
        raise Touched("the sensor was opened before every flag was checked")

    monkeypatch.setattr(view_command, "open_session", refuse)
    monkeypatch.setattr("biris_hw.opening.open_sensor", refuse)


@pytest.fixture
def taken() -> Iterator[int]:
    """A port on loopback that another program (this test) listens on."""
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        yield int(other.getsockname()[1])


@pytest.mark.usefixtures("untouched")
@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--port", "70000"], "argument --port: a port is 0 (any free one) to 65535, not 70000"),
        (["--port", "-1"], "argument --port: a port is 0 (any free one) to 65535, not -1"),
        (["--port", "http"], "argument --port: a port is a whole number, not 'http'"),
        (["--viewer", "localhost:8080"], "argument --viewer: an http:// or https:// address"),
        (["--stamp", "gps"], "argument --stamp: invalid choice: 'gps'"),
        (["--host", "no-such-host.invalid"], "--host no-such-host.invalid: not an address of"),
        (["--host", "192.0.2.1"], "--host 192.0.2.1 --port 8765: cannot listen there"),
    ],
)
def test_a_wrong_flag_is_a_usage_error_before_the_sensor_is_opened(
    biris: Run, argv: list[str], said: str
) -> None:
    code, out, err = biris("view", "--sim", *argv)
    assert code == 2 and out == ""
    assert said in err, err


@pytest.mark.usefixtures("untouched")
def test_a_port_taken_is_named_as_the_cause(biris: Run, taken: int) -> None:
    code, out, err = biris("view", "--sim", "--cw", "-20", "--ccw", "20", "--port", str(taken))
    assert code == 2 and out == ""
    assert err.strip() == (
        f"biris view: --port {taken}: another program listens on 127.0.0.1:{taken} already "
        "(another biris view?): choose another --port, or --port 0 for any free one"
    )


@pytest.mark.usefixtures("untouched")
def test_a_replays_port_is_checked_before_the_file_is_opened(
    biris: Run, taken: int, tmp_path: Path
) -> None:
    path = write_scans(tmp_path / "run.mcap", synthetic_scans(2))
    code, _, err = biris("view", "--replay", str(path), "--port", str(taken))
    assert code == 2 and "another program listens" in err


@pytest.mark.usefixtures("untouched")
def test_target_flags_are_checked_before_the_port(biris: Run, taken: int) -> None:
    """Without --sim, --target or $BIRIS_TARGET the sensor is not named: that is said first."""
    code, _, err = biris("view", "--port", str(taken))
    assert code == 2 and "say which sensor to use" in err


@pytest.mark.usefixtures("untouched")
def test_a_host_beyond_loopback_warns(biris: Run) -> None:
    """192.0.2.1 (a documentation address, never this machine's) warns, then cannot listen."""
    code, _, err = biris("view", "--sim", "--host", "192.0.2.1", "--port", "0")
    assert code == 2
    warning, error = err.strip().splitlines()
    assert warning.startswith("biris view: warning: --host 192.0.2.1 listens beyond this machine")
    assert "no authentication and checks no Origin" in warning
    assert error.startswith("biris view: --host 192.0.2.1 --port 0: cannot listen there")


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("127.0.0.1", True),
        ("127.0.1.1", True),
        ("localhost", True),
        ("::1", True),
        ("0.0.0.0", False),
        ("::", False),
        ("192.168.1.20", False),
        ("robot.local", False),
    ],
)
def test_loopback_is_this_machine_only(host: str, loopback: bool) -> None:
    assert liveview.is_loopback(host) is loopback


def _args(*argv: str) -> argparse.Namespace:
    args = build_parser("view").parse_args(["view", *argv])
    return args


@pytest.mark.parametrize(
    ("argv", "stamp"),
    [
        (["--sim"], "hardware"),
        (["--attach", "rig"], "hardware"),
        (["--replay", "run.mcap"], "hardware"),
        (["--target", "robot.toml"], "wall"),
        (["--connect", "biris0"], "wall"),
        (["--sim", "--stamp", "wall"], "wall"),
        (["--target", "robot.toml", "--stamp", "hardware"], "hardware"),
    ],
)
def test_log_times_default_to_the_wall_clock_on_a_real_sensor(argv: list[str], stamp: str) -> None:
    assert view_command._stamp(_args(*argv)) == stamp


def test_the_commands_names_are_the_live_views() -> None:
    """The parser names them itself (building it loads nothing of biris_hw.io)."""
    assert set(view_command.STAMPS) == set(codec.STAMPS)
    assert view_command.DEFAULT_PORT == liveview.DEFAULT_PORT
    assert view_command.DEFAULT_VIEWER == liveview.DEFAULT_VIEWER


def test_it_prints_one_url_that_opens_the_layout(tmp_path: Path, no_leaks: None) -> None:
    """On a recording: the WebSocket, Lichtblick's URL with ``ds``, ``ds.url`` and
    ``layoutUrl``, Foxglove's; the layout's URL serves the packaged layout to another origin."""
    path = write_scans(tmp_path / "run.mcap", synthetic_scans(2))
    args = _args(
        "--replay", str(path), "--speed", "1000", "--port", "0", "--duration", "0.1",
        "--viewer", "http://lichtblick.example:8080/",
    )  # fmt: skip
    fetched: dict[str, object] = {}

    def ready(view: liveview.LiveView) -> None:
        request = urllib.request.Request(
            view.urls["layout"], headers={"Origin": "http://lichtblick.example:8080"}
        )
        with urllib.request.urlopen(request, timeout=10) as answer:
            fetched["cors"] = answer.headers["Access-Control-Allow-Origin"]
            fetched["layout"] = json.loads(answer.read())

    out = io.StringIO()
    assert view_command.run(args, out, ready=ready) == 0
    first, lichtblick, foxglove = out.getvalue().splitlines()
    ws = first.split()[3]
    assert first == f"live view on {ws} (Lichtblick 1.22.1 or later, or Foxglove)"
    assert ws.startswith("ws://127.0.0.1:")
    url = urlsplit(lichtblick.split(": ", 1)[1])
    assert (url.scheme, url.netloc, url.path) == ("http", "lichtblick.example:8080", "/")
    query = {k: v[0] for k, v in parse_qs(url.query).items()}
    assert query["ds"] == "foxglove-websocket" and query["ds.url"] == ws
    assert query["layoutUrl"].startswith("http://127.0.0.1:")
    assert query["layoutUrl"].endswith(liveview.LAYOUT_PATH)
    assert foxglove.startswith(f"  or in Foxglove: {liveview.FOXGLOVE_APP}?ds=foxglove-websocket")
    assert f"Import layout: {query['layoutUrl']}" in foxglove
    assert fetched["cors"] == "*"
    assert fetched["layout"] == json.loads(liveview.LAYOUT_FILE.read_text())


def test_the_layout_is_in_the_package_and_names_what_the_view_publishes() -> None:
    """Shipped beside the module (package data); its diagnostics panel selects the server's
    status by the name :func:`codec.diagnostics` gives it, under the hardware id."""
    layout = json.loads(liveview.LAYOUT_FILE.read_text())
    assert liveview.LAYOUT_FILE.parent == Path(liveview.__file__).parent
    status = layout["configById"]["DiagnosticStatusPanel!biris"]
    message: Any = codec.typestore().deserialize_cdr(
        codec.diagnostics({"state": "idle"}, 1.0).data, codec.DIAGNOSTIC_ARRAY
    )
    (server,) = message.status
    assert (status["selectedHardwareId"], status["selectedName"]) == (
        server.hardware_id,
        server.name,
    )
    assert server.name == "server"  # shown as "biris: server", not "biris: biris: server"
    assert not (ROOT / "docs" / "foxglove-layout.json").exists()  # one copy: the packaged one


def test_a_moving_robots_layout_follows_the_vehicle_through_odom_and_shows_the_grid(
    no_leaks: None,
) -> None:
    """With poses the view serves the moving variant: the camera follows the vehicle's position
    (the scene keeps odom's heading), the reference grid is in odom, the certainty grid and the
    deskewed scans (kept long enough to build up the room) are shown, and the proximity alarm is
    plotted. Standing still, the file as shipped."""
    still = json.loads(liveview.LAYOUT_FILE.read_text())
    assert liveview.layout() == still
    moving = liveview.layout(moving=True)
    panel = moving["configById"]["3D!biris"]
    assert (panel["followTf"], panel["followMode"]) == ("vehicle", "follow-position")
    assert panel["layers"]["grid"]["frameId"] == codec.ODOM_FRAME
    assert panel["topics"][codec.GRID_TOPIC]["visible"] is True
    assert panel["topics"][codec.POINTS_TOPIC]["decayTime"] >= 10
    plotted = {p["value"] for p in moving["configById"]["Plot!azimuth"]["paths"]}
    assert plotted == {f"{codec.PROXIMITY_TOPIC}.distance_m", f"{codec.PROXIMITY_TOPIC}.age_s"}
    fields = codec.schema_text(codec.PROXIMITY)
    assert "float64 distance_m" in fields and "float64 age_s" in fields
    assert moving["layout"] == still["layout"]  # the same panels, in the same places
    server = liveview._LayoutServer("127.0.0.1", moving=True)
    try:
        url = f"http://127.0.0.1:{server.port}{liveview.LAYOUT_PATH}"
        with urllib.request.urlopen(url, timeout=10) as answer:
            assert json.loads(answer.read()) == moving
    finally:
        server.stop()
