"""``open_sensor``: each kind of sensor opened from its description, taken down in order, and
every mistake refused with a typed error before anything is opened."""

from __future__ import annotations

import contextlib
import os
import re
import select
import signal
import subprocess
import sys
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import biris_hw.target
from biris_hw import BirisInitRecord, BirisServer, ConnectionKind, DeliveryPolicy, Direction
from biris_hw.commands import session as cli_session
from biris_hw.errors import ConnectionClosed, HardwareFault, RequestError
from biris_hw.hardware import BirisHardware
from biris_hw.io.record import ReplayServer, write_scans
from biris_hw.io.record.replay import EndOfRecording, ReplayRefused
from biris_hw.opening import SetupError, open_sensor
from biris_hw.status import ServerState
from sim import Scene, SimulatedBiris
from tests.conftest import RigFactory, Run
from tests.test_cli import SIM
from tests.test_record_support import assert_same_scan, synthetic_scans

WAIT = 30.0
"""Generous real-time bound for a scan or a boot (virtual time takes far less)."""


def _closest_mm(scan: Any) -> int:
    """The median closest return of a scan: the circle's radius, on Scene.circle."""
    closest = scan.closest_mm[scan.closest_mm > 0]
    assert closest.size, "no return at all"
    return int(np.median(closest))


def _scan_to(sensor: Any, to_deg: float) -> Any:
    """One single scan from where the head stands to ``to_deg``: the scan delivered."""
    with sensor.open() as conn:
        start = int(sensor.status()["azimuth"])
        dest = conn.single_scan(to_deg)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.of_motion(start, dest))
    assert scan is not None
    return scan


# -- sim= ------------------------------------------------------------------------------------------


def test_a_simulator_gets_a_server_and_stays_the_callers(rig: SimulatedBiris) -> None:
    with open_sensor(sim=rig) as sensor:
        assert isinstance(sensor, BirisServer) and sensor.hardware is rig.hardware
        assert abs(_closest_mm(_scan_to(sensor, 30.0)) - 2000) < 150
    with pytest.raises(ConnectionClosed):
        sensor.open()  # the server is closed with the block
    with open_sensor(sim=rig) as again:  # the rig is not: a second server boots on it
        assert again.status().state is ServerState.IDLE


def test_a_simulator_not_yet_started_is_started(no_leaks: None) -> None:
    rig = SimulatedBiris(scene=Scene.circle(2.0), time_scale=30.0, seed=3, clock="virtual")
    try:
        with open_sensor(sim=rig) as sensor:
            assert sensor.status().state is ServerState.IDLE
    finally:
        rig.close()
    with pytest.raises(SetupError, match=r"the simulator cannot start: .*shut down"):
        open_sensor(sim=rig).__enter__()


def test_the_init_record_and_continuous_reach_the_server(
    rig: SimulatedBiris, tmp_path: Path
) -> None:
    path = tmp_path / "init.toml"
    BirisInitRecord(data_rate_ms=40).save(path)
    with open_sensor(sim=rig, init=path, continuous=True) as sensor:
        assert sensor.record.data_rate_ms == 40
        assert sensor.record.continuous_acquisition is True
        assert sensor.status()["acquisition"] == "continuous"
    given = BirisInitRecord(continuous_acquisition=True)
    with open_sensor(sim=rig, init=given, continuous=False) as sensor:
        assert sensor.record.continuous_acquisition is False  # continuous= has the last word
        assert sensor.status()["acquisition"] == "single"


# -- target= ---------------------------------------------------------------------------------------


class _Targets:
    """What the fake target loader did, in order, and the faults to give each rig first."""

    def __init__(self) -> None:
        self.events: list[tuple[str, object]] = []
        self.breaks: list[Callable[[SimulatedBiris], None]] = []


@pytest.fixture
def targets(monkeypatch: pytest.MonkeyPatch, make_rig: RigFactory) -> _Targets:
    """A target file opens a simulator's hardware, as if it were the real head (the loader is
    the target module's; what open_sensor does with what it returns is under test), and the
    order in which open_sensor closes the server and the hardware is written down."""
    seen = _Targets()
    closing = BirisServer.close

    def load_target(file: object) -> BirisHardware:
        rig = make_rig()
        for fault in seen.breaks:
            fault(rig)
        seen.events.append(("load", file))
        hardware = rig.hardware
        close = hardware.close

        def close_and_note() -> None:
            seen.events.append(("close hardware", file))
            close()

        hardware.close = close_and_note  # type: ignore[method-assign]
        return hardware

    def close_server(self: BirisServer) -> None:
        seen.events.append(("close server", None))
        closing(self)

    monkeypatch.setattr(biris_hw.target, "load_target", load_target)
    monkeypatch.setattr(BirisServer, "close", close_server)
    return seen


def test_a_target_gets_a_server_closed_before_its_hardware(
    targets: _Targets, tmp_path: Path
) -> None:
    file = tmp_path / "robot.toml"
    with open_sensor(target=file) as sensor:
        assert isinstance(sensor, BirisServer)
        assert abs(_closest_mm(_scan_to(sensor, -30.0)) - 2000) < 150
    assert targets.events[0] == ("load", file)
    closes = [what for what, _ in targets.events[1:]]
    assert closes.index("close server") < closes.index("close hardware")


def test_a_fault_while_the_server_starts_closes_the_target(
    targets: _Targets, tmp_path: Path
) -> None:
    """BIRIS hung before the server boots it: the boot's timeout is raised, naming the command
    BIRIS left unanswered, and the target's hardware is closed all the same."""
    targets.breaks.append(lambda rig: rig.faults.hang_supervisor())
    with pytest.raises(HardwareFault) as caught, open_sensor(target=tmp_path / "robot.toml"):
        pytest.fail("a hung BIRIS booted")
    assert caught.value.kind == "timeout"
    assert re.search(r"\bBI_[A-Z_]+", caught.value.message), caught.value.message
    assert targets.events[-1][0] == "close hardware"


def _target_file(tmp_path: Path, windows: str) -> Path:
    path = tmp_path / "target.toml"
    path.write_text(
        f"biris = {windows}\nmotion = {windows}\ncoupler = {windows}\n"
        'level2 = { kind = "eventfd" }\nlevel3 = { kind = "eventfd" }\n'
    )
    return path


def test_a_target_that_cannot_be_opened_is_a_setup_error(tmp_path: Path, no_leaks: None) -> None:
    with pytest.raises(SetupError, match=r"cannot read target file .*none.toml") as caught:
        open_sensor(target=tmp_path / "none.toml").__enter__()
    assert isinstance(caught.value.__cause__, FileNotFoundError)
    bad_key = tmp_path / "bad.toml"
    bad_key.write_text('biris = { kind = "mmap" }\nbogus = 1\n')
    with pytest.raises(SetupError, match="unknown key 'bogus'"):
        open_sensor(target=bad_key).__enter__()
    missing = f'{{ kind = "mmap", path = "{tmp_path}/no-such-dev", offset = 0, size = 0x100 }}'
    with pytest.raises(SetupError, match=r"cannot open the target: .*No such file"):
        open_sensor(target=_target_file(tmp_path, missing)).__enter__()


# -- attach= ---------------------------------------------------------------------------------------


SIM_PROCESS = (sys.executable, "-m", "sim.process")
"""What ``biris sim`` runs."""


@pytest.fixture
def sim_process() -> Iterator[str]:
    """``python -m sim.process --shm NAME`` (what ``biris sim`` runs), up to its ready line."""
    if sys.version_info < (3, 13):  # attaching starts the resource tracker: not a leak
        from multiprocessing import resource_tracker

        resource_tracker.ensure_running()
    name = f"biris-open-test-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    proc = subprocess.Popen(
        [*SIM_PROCESS, "--shm", name, "--time-scale", "10", "--scene", "circle:2", "--seed", "3"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], WAIT)
        assert ready and proc.stdout.readline().startswith(b"ready "), "no ready line"
        yield name
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=WAIT)


@pytest.mark.realtime  # another process on scaled time
def test_a_simulator_process_is_attached_and_let_go(sim_process: str, no_leaks: None) -> None:
    """And let go: no_leaks holds the link's socket and shared memory to being closed."""
    with open_sensor(attach=sim_process) as sensor:
        assert isinstance(sensor, BirisServer)
        _scan_to(sensor, -30.0)  # across processes the first scan teaches the start delay
        assert abs(_closest_mm(_scan_to(sensor, 30.0)) - 2000) < 150


def test_attaching_to_nothing_is_a_setup_error(no_leaks: None) -> None:
    with pytest.raises(SetupError, match="cannot attach to simulator 'biris-nobody-here'"):
        open_sensor(attach="biris-nobody-here").__enter__()


# -- connect= --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def zenoh_runtime() -> None:
    """Zenoh's runtimes (threads, descriptors) started once, before any test's leak check takes
    its snapshot: Zenoh keeps them for the life of the process."""
    pytest.importorskip("zenoh")
    from tests.net_helpers import warm_up_zenoh

    warm_up_zenoh()


@pytest.mark.realtime  # the service's Zenoh threads call into the server
def test_a_service_is_reached_with_credentials(zenoh_runtime: None, rig: SimulatedBiris) -> None:
    from biris_hw.io.net import RemoteSensor, serve
    from tests.net_helpers import endpoint, free_port

    where = endpoint(free_port())
    with (
        BirisServer(rig.hardware, BirisInitRecord()) as server,
        serve(server, name="opened", listen=[where], controllers={"op": "pw"}, multicast=False),
    ):
        with open_sensor(
            connect="opened", endpoints=[where], multicast=False, user="op", password="pw"
        ) as remote:
            assert isinstance(remote, RemoteSensor)
            assert remote.status().state is ServerState.IDLE
            assert abs(_closest_mm(_scan_to(remote, 30.0)) - 2000) < 150  # a controller moves
        with pytest.raises(ConnectionClosed):
            remote.open()
        assert server.status().state is ServerState.IDLE  # the service's server runs on


def test_no_service_is_a_setup_error(zenoh_runtime: None, no_leaks: None) -> None:
    from tests.net_helpers import endpoint, free_port

    nobody = [endpoint(free_port())]
    with pytest.raises(SetupError, match="no BIRIS service") as caught:
        open_sensor(connect="nobody", endpoints=nobody, multicast=False, timeout=0.3).__enter__()
    assert isinstance(caught.value.__cause__, ConnectionClosed)


# -- replay= ---------------------------------------------------------------------------------------


def test_a_recording_is_played_back_equal(tmp_path: Path) -> None:
    scans = synthetic_scans(4)
    path = write_scans(tmp_path / "run.mcap", scans)
    with open_sensor(replay=path, speed=None, autostart=False) as replay:
        assert isinstance(replay, ReplayServer)
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=8)
        with pytest.raises(TimeoutError):
            data.ready_for_data(timeout=0)  # autostart=False: nothing plays before start()
        replay.start()
        got = []
        with contextlib.suppress(EndOfRecording):
            while True:
                got.append(data.ready_for_data(timeout=WAIT))
        with pytest.raises(ReplayRefused):
            replay.open().single_scan(10.0)
    assert len(got) == len(scans)
    for played, recorded in zip(got, scans, strict=True):
        assert_same_scan(played, recorded)
    with pytest.raises(ConnectionClosed):
        replay.open()


def test_a_file_that_is_not_a_recording_is_a_setup_error(tmp_path: Path) -> None:
    with pytest.raises(SetupError, match=r"cannot read .*none.mcap"):
        open_sensor(replay=tmp_path / "none.mcap").__enter__()
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not mcap at all")
    with pytest.raises(SetupError, match="not a readable MCAP file"):
        open_sensor(replay=junk).__enter__()


# -- refusals --------------------------------------------------------------------------------------


@pytest.fixture
def nothing_opens(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every opener open_sensor could reach, replaced by one that notes it was called."""
    called: list[str] = []

    def note(what: str) -> Any:
        def opener(*args: object, **kwargs: object) -> None:
            called.append(what)
            raise AssertionError(f"{what} was reached")

        return opener

    monkeypatch.setattr(biris_hw.target, "load_target", note("load_target"))
    monkeypatch.setattr("biris_hw.simlink.attach", note("attach"))
    monkeypatch.setattr("biris_hw.io.net.RemoteSensor", note("RemoteSensor"))
    monkeypatch.setattr("biris_hw.io.record.replay.ReplayServer", note("ReplayServer"))
    monkeypatch.setattr(BirisServer, "__init__", note("BirisServer"))
    return called


class _Rig:
    """Enough of a simulator for open_sensor to accept it (it is never started here)."""

    hardware: Any = None

    def start(self) -> None:
        raise AssertionError("started")


REFUSED: list[tuple[dict[str, Any], type[Exception], str]] = [
    ({}, TypeError, r"needs the sensor to open: one of sim=, target=, attach=, connect= or"),
    (
        {"target": "t.toml", "replay": "r.mcap"},
        TypeError,
        "opens one sensor: give one of target= and replay=",
    ),
    (
        {"replay": "r.mcap", "continuous": True},
        TypeError,
        r"continuous= does not apply to replay= \(it goes with sim= or target= or attach=\)",
    ),
    ({"connect": "x", "speed": 2.0}, TypeError, r"speed= does not apply to connect="),
    ({"target": "t.toml", "endpoints": ["tcp/h:1"]}, TypeError, "endpoints= does not apply"),
    ({"attach": "x", "colour": "red"}, TypeError, "unknown option colour="),
    ({"sim": object()}, TypeError, r"sim= takes a simulator \(sim.SimulatedBiris\), not object"),
    ({"target": 7}, TypeError, "target= takes a file name, not int"),
    ({"target": ""}, RequestError, "target=: an empty file name"),
    ({"attach": b"x"}, TypeError, r"attach= takes a name \(str\), not bytes"),
    ({"connect": ""}, RequestError, "connect=: an empty name"),
    ({"sim": _Rig(), "continuous": "yes"}, TypeError, "continuous= takes True, False or None"),
    ({"sim": _Rig(), "init": 42}, TypeError, "init= takes a BirisInitRecord or the name of"),
    (
        {"connect": "x", "endpoints": "tcp/h:1"},
        TypeError,
        r"endpoints= takes a list of endpoints",
    ),
    ({"connect": "x", "endpoints": [""]}, RequestError, "endpoints=: each must be a non-empty"),
    ({"connect": "x", "user": 1}, TypeError, "user= takes a str, not int"),
    ({"connect": "x", "zenoh_options": ["a"]}, TypeError, "zenoh_options= takes a mapping"),
    ({"connect": "x", "timeout": -1.0}, RequestError, "timeout= must be a positive finite"),
    ({"connect": "x", "multicast": "no"}, TypeError, "multicast= takes True, False or None"),
    ({"replay": "r.mcap", "speed": 0.0}, RequestError, "speed= must be a positive finite"),
    ({"replay": "r.mcap", "speed": float("nan")}, RequestError, "speed= must be a positive"),
    ({"replay": "r.mcap", "speed": True}, TypeError, "speed= takes a number or None, not bool"),
    ({"replay": "r.mcap", "autostart": None}, TypeError, "autostart= takes True or False"),
]


@pytest.mark.parametrize(("given", "error", "words"), REFUSED)
def test_a_mistake_is_refused_when_called_and_opens_nothing(
    nothing_opens: list[str], given: dict[str, Any], error: type[Exception], words: str
) -> None:
    with pytest.raises(error, match=words):
        open_sensor(**given)
    assert nothing_opens == []


def test_a_bad_init_file_is_a_setup_error_before_anything_opens(
    nothing_opens: list[str], tmp_path: Path
) -> None:
    with pytest.raises(SetupError, match=r"cannot read init record .*none.toml"):
        open_sensor(target="t.toml", init=tmp_path / "none.toml")
    impossible = tmp_path / "init.toml"
    impossible.write_text("data_rate_ms = 0\n")
    with pytest.raises(SetupError, match="data_rate_ms"):
        open_sensor(attach="x", init=impossible)
    assert nothing_opens == []


def test_a_bad_value_is_a_value_error_too() -> None:
    """RequestError derives from ValueError, so a caller that catches ValueError for a bad
    value catches open_sensor's too."""
    with pytest.raises(ValueError, match="speed="):
        open_sensor(replay="r.mcap", speed=-1.0)


def test_the_sensor_module_offers_open_sensor() -> None:
    from biris_hw.opening import open_sensor as here
    from biris_hw.sensor import open_sensor as there

    assert there is here


# -- the commands open through it ------------------------------------------------------------------


def test_a_command_opens_its_sensor_with_open_sensor(
    biris: Run, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``biris point --sim``: the CLI builds the simulator and hands it to open_sensor with the
    init record it read; what open_sensor yields is the command's server."""
    calls: list[dict[str, Any]] = []
    real = cli_session.open_sensor

    def spy(**given: Any) -> Any:
        calls.append(given)
        return real(**given)

    monkeypatch.setattr(cli_session, "open_sensor", spy)
    code, out, err = biris("point", "--continuous", *SIM)
    assert code == 0, err
    assert "closest" in out
    (given,) = calls
    assert set(given) == {"sim", "init"}
    assert isinstance(given["sim"], SimulatedBiris)
    assert given["init"].continuous_acquisition is True


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--connect", "biris0", "--continuous"], "--continuous does not apply to a running"),
        (["--connect", "biris0", "--init", "i.toml"], "--init does not apply to a running"),
        (["--sim", "--tls-ca", "ca.pem"], "--tls-ca goes with --connect NAME"),
        (["--sim", "--credentials", "c.toml"], "--credentials goes with --connect NAME"),
    ],
)
def test_the_commands_refuse_a_flag_the_sensor_would_ignore(
    biris: Run, argv: list[str], words: str
) -> None:
    code, out, err = biris("point", *argv)
    assert (code, out) == (2, "")
    assert err.startswith(f"biris point: {words}"), err
