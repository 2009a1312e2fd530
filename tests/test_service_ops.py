"""A service that is heard, and recovers or says so.

The service's log (:class:`~biris_hw.commands.console.ServiceLines`): the journal's form under
systemd, a time and a level elsewhere, one line per event; commands show the simulator's warnings
too. The watcher (:class:`~biris_hw.commands.reset.AutoReset`) on virtual time: it says a fault,
resets the sensor itself when asked to, and gives up after its tries, a fault that each reset
only hides for a moment included. Then ``biris serve --auto-reset`` through Zenoh, end to end:
its log, a reset it makes and the data after it, an access refused, and status 1 when a fault
persists; and ``biris reset --connect``: 0 once the sensor is back, 1 when the reset failed, 2
without a controller's credentials.
"""

from __future__ import annotations

import io
import logging
import os
import re
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from biris_hw import BirisServer
from biris_hw.cli import build_parser
from biris_hw.commands import serve as serve_command
from biris_hw.commands import session as cli_session
from biris_hw.commands.console import ServiceLines, journal_stream, log_to_stderr
from biris_hw.commands.failures import error_line, exit_status
from biris_hw.commands.reset import STABLE_S, AutoReset
from biris_hw.errors import AccessDenied, HardwareFault
from biris_hw.status import ServerState
from sim import SimulatedBiris
from tests.conftest import Run, until
from tests.net_helpers import endpoint, free_port, warm_up_zenoh

WAIT = 30.0
WATCHER = "biris_hw.commands.reset"


def _record(
    level: int, message: str, *args: object, name: str = "biris_hw.io.net.service"
) -> logging.LogRecord:
    return logging.LogRecord(name, level, __file__, 1, message, args, None)


def _emit(handler: logging.Handler, record: logging.LogRecord) -> None:
    """As a logger hands a record to a handler (its level first)."""
    if record.levelno >= handler.level:
        handler.handle(record)


# -- the log's form --------------------------------------------------------------------------------


def test_under_systemd_a_line_is_the_journals_form(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """stderr is the journal's stream ($JOURNAL_STREAM names its device and inode): each record
    is one line with the sd-daemon priority prefix and no time; below INFO nothing."""
    journal = tmp_path / "journal"
    with journal.open("w") as stream:
        found = os.fstat(stream.fileno())
        monkeypatch.setenv("JOURNAL_STREAM", f"{found.st_dev}:{found.st_ino}")
        monkeypatch.setattr(sys, "stderr", stream)
        assert journal_stream(stream)
        handler = ServiceLines()
        _emit(handler, _record(logging.WARNING, "access refused:\n  client %s", "c1"))
        _emit(handler, _record(logging.INFO, "the sensor is back", name="x.reset"))
        _emit(handler, _record(logging.ERROR, "gave up"))
        _emit(handler, _record(logging.DEBUG, "not for the journal at INFO"))
    assert journal.read_text().splitlines() == [
        "<4>service: access refused: client c1",
        "<6>reset: the sensor is back",
        "<3>service: gave up",
    ]


def test_elsewhere_a_line_has_its_time_and_level(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A terminal or a file (or a $JOURNAL_STREAM that names another stream): the time and the
    level lead; an exception is folded onto its line."""
    monkeypatch.setenv("JOURNAL_STREAM", "1:2")
    record = _record(logging.ERROR, "publishing %s failed", "/point")
    try:
        raise ValueError("bad\nthing")
    except ValueError:
        record.exc_info = sys.exc_info()
    ServiceLines().handle(record)
    err = capsys.readouterr().err
    when = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d"
    assert re.fullmatch(
        rf"{when} ERROR service: publishing /point failed \(ValueError: bad thing\)\n", err
    )


def test_a_fault_record_is_left_to_the_watcher_unless_debug(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The server's own line for a fault would say it twice (the watcher says it, with what is
    done about it); --debug shows it, and a traceback a line each."""
    monkeypatch.delenv("JOURNAL_STREAM", raising=False)
    fault = HardwareFault("parity", "parity error on the coupler")
    ServiceLines().handle(_record(logging.ERROR, "hardware fault: %s", fault, name="x.faults"))
    assert capsys.readouterr().err == ""
    record = _record(logging.ERROR, "hardware fault: %s", fault, name="x.faults")
    try:
        raise fault
    except HardwareFault:
        record.exc_info = sys.exc_info()
    ServiceLines(logging.DEBUG, tracebacks=True, faults=True).handle(record)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].endswith("ERROR faults: hardware fault: parity: parity error on the coupler")
    assert len(lines) > 2 and all(line.startswith("  ") for line in lines[1:])
    assert lines[-1] == "  biris_hw.errors.HardwareFault: parity: parity error on the coupler"


def test_a_service_logs_from_info_up_and_commands_show_warnings_only(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``biris serve``: INFO and up (the simulator's from WARNING), DEBUG with --debug; any
    other command: the driver's and the simulator's warnings, a plain line each."""
    monkeypatch.delenv("JOURNAL_STREAM", raising=False)
    service = logging.getLogger("biris_hw.io.net.service")
    simulator = logging.getLogger("sim.cia402")
    with log_to_stderr(False, service=True):
        service.info("client %s connected (status)", "c1")
        service.debug("not shown")
        simulator.info("not shown either")
        simulator.warning("node 2: RPDO refused")
    said = [line.split(" ", 2)[2] for line in capsys.readouterr().err.splitlines()]
    assert said == [
        "INFO service: client c1 connected (status)",
        "WARNING cia402: node 2: RPDO refused",
    ]
    with log_to_stderr(True, service=True):
        service.debug("shown with --debug")
    assert capsys.readouterr().err.endswith("DEBUG service: shown with --debug\n")
    with log_to_stderr(False):
        service.info("not shown")
        simulator.warning("node 2: RPDO refused (%s)", "busy")
        service.warning("2 acquisitions lost")
    assert capsys.readouterr().err.splitlines() == [
        "biris: warning: simulator: node 2: RPDO refused (busy)",
        "biris: warning: 2 acquisitions lost",
    ]


def test_a_flood_of_refusals_is_one_line_per_period_counting_the_rest() -> None:
    """The service logs a refusal (access refused, Busy) at most once per period and kind; the
    next line says how many it left out (a flood of wrong passwords must not flood the log)."""
    from biris_hw.io.net.service import Quieter

    quiet = Quieter(10.0)
    assert quiet.allow("access refused", 100.0) == 0
    assert [quiet.allow("access refused", 100.0 + t) for t in (1.0, 2.0, 9.9)] == [None] * 3
    assert quiet.allow("busy", 101.0) == 0  # each kind on its own
    assert quiet.allow("access refused", 110.0) == 3
    assert quiet.allow("access refused", 125.0) == 0


# -- the watcher, on virtual time ------------------------------------------------------------------


def _said(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == WATCHER]


def test_the_watcher_resets_a_faulted_sensor_and_it_serves_again(
    rig: SimulatedBiris, server: BirisServer, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=WATCHER)
    with AutoReset(server, tries=2, delay_s=0.0) as watch, server.open() as conn:
        conn.continuous_scan(-20.0, 20.0)
        until(lambda: server.status().state is ServerState.SCANNING, what="a sweep")
        rig.faults.parity_error()
        until(lambda: watch.recoveries == 1, what="the sensor back after the watcher's reset")
        assert (watch.faults, watch.resets, watch.gave_up) == (1, 1, None)
        assert conn.single_scan(10.0) == 114  # serves again
        conn.wait_idle(timeout=WAIT)
    assert _said(caplog) == [
        "the sensor is in a fault (parity): parity error on the coupler; resetting it (at most "
        "2 tries)",
        "resetting the sensor (try 1 of 2)",
        "the sensor is back (idle) after 1 reset(s)",
    ]


def test_the_watcher_gives_up_on_a_fault_no_reset_cures(
    rig: SimulatedBiris, server: BirisServer, caplog: pytest.LogCaptureFixture
) -> None:
    """BIRIS hangs: every reset times out. After the second the watcher gives up, hands the
    fault over (``biris serve`` then exits 1) and tries nothing more."""
    caplog.set_level(logging.INFO, logger=WATCHER)
    gave: list[HardwareFault] = []
    with (
        AutoReset(server, tries=2, delay_s=0.0, on_give_up=gave.append) as watch,
        server.open() as conn,
    ):
        rig.faults.hang_supervisor()
        with pytest.raises(HardwareFault, match="timeout"):
            conn.single_scan(10.0)
            conn.wait_idle(timeout=WAIT)
        until(lambda: gave, what="the watcher to give up")
        assert (watch.resets, watch.recoveries) == (2, 0)
        assert gave == [watch.gave_up]
        assert gave[0].kind == "timeout"
        assert gave[0].message.endswith("(still so after 2 reset(s): gave up)")
        said = _said(caplog)
        rig.faults.clear_hang()
        conn.reset()  # back, so that the server closes as usual
    assert said[0].startswith("the sensor is in a fault (timeout): BIRIS did not respond")
    assert said[0].endswith("; resetting it (at most 2 tries)")
    assert said[1] == "resetting the sensor (try 1 of 2)"
    assert said[2].startswith("reset 1 of 2 failed (timeout): BIRIS still busy")
    assert said[3] == "resetting the sensor (try 2 of 2)"
    assert said[4].startswith("reset 2 of 2 failed (timeout): ")
    assert said[5] == "the sensor is still in a fault (timeout) after 2 reset(s): giving up"
    assert len(said) == 6


@pytest.mark.parametrize(("stable_s", "gives_up"), [(STABLE_S, True), (0.0, False)])
def test_a_fault_each_reset_only_hides_uses_up_the_tries(
    rig: SimulatedBiris, server: BirisServer, stable_s: float, gives_up: bool
) -> None:
    """A fault that comes back soon after a reset cured it belongs to the same episode: with
    one try, the second fault is given up on at once. Once the sensor has run ``stable_s``
    without a fault, a new fault has its tries afresh."""
    gave: list[HardwareFault] = []
    with (
        AutoReset(server, tries=1, delay_s=0.0, stable_s=stable_s, on_give_up=gave.append) as w,
        server.open() as conn,
    ):
        rig.faults.parity_error()
        until(lambda: w.recoveries == 1, what="the first fault reset")
        rig.faults.parity_error()
        until(lambda: gave or w.recoveries == 2, what="the second fault handled")
        assert (bool(gave), w.resets, w.faults) == (gives_up, 1 if gives_up else 2, 2)
        if gives_up:
            conn.reset()


def test_without_tries_the_watcher_only_says_what_happens(
    rig: SimulatedBiris, server: BirisServer, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=WATCHER)
    with AutoReset(server) as watch, server.open() as conn:
        rig.faults.parity_error()
        until(lambda: watch.faults == 1, what="the fault said")
        conn.reset()  # a controller's
        until(lambda: "the sensor is back (idle)" in _said(caplog), what="the recovery said")
        assert watch.resets == 0
    said = _said(caplog)
    assert said[0] == (
        "the sensor is in a fault (parity): parity error on the coupler; waiting for a "
        "controller's reset (biris reset --connect)"
    )
    assert said[-1] == "the sensor is back (idle)"
    assert set(said[1:-1]) <= {"the sensor is being reset (its initialisation runs again)"}


def test_a_recording_cannot_be_reset(tmp_path: Path) -> None:
    """``--auto-reset`` with ``--replay`` is refused before anything is opened."""
    from biris_hw.commands.failures import UsageError

    recording = tmp_path / "run.mcap"
    recording.write_bytes(b"")
    args = build_parser("serve").parse_args(
        ["serve", "--replay", str(recording), "--auto-reset", "2"]
    )
    with pytest.raises(UsageError, match="a recording cannot be reset"):
        serve_command.run(args, io.StringIO())


def test_a_watcher_needs_sensible_settings(server: BirisServer) -> None:
    with pytest.raises(ValueError, match="tries"):
        AutoReset(server, tries=-1)
    with pytest.raises(ValueError, match="delay_s"):
        AutoReset(server, delay_s=float("nan"))


# -- through Zenoh: biris serve --auto-reset, biris reset --connect --------------------------------


@pytest.fixture(scope="module")
def _zenoh_runtime() -> None:
    warm_up_zenoh()


def _in_order(lines: list[str], patterns: list[str]) -> None:
    """Each pattern matches a line, in this order (other lines may come between)."""
    at = 0
    for pattern in patterns:
        while at < len(lines) and not re.search(pattern, lines[at]):
            at += 1
        assert at < len(lines), f"no line like {pattern!r} (in order) in:\n" + "\n".join(lines)
        at += 1


@pytest.mark.realtime
@pytest.mark.usefixtures("_zenoh_runtime", "no_target_env", "no_leaks")
def test_biris_serve_is_heard_resets_itself_and_exits_1_when_a_fault_persists(
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
    tmp_path: Path,
) -> None:
    """A controller sweeps through the service; a parity fault is reset by the service itself
    and a new sweep's data are published; a wrong password is refused and logged; then BIRIS
    hangs, the one try left of the episode fails, and the service ends with the fault (status
    1). Its log says each of these, one line each."""
    from biris_hw.io.net import connect

    monkeypatch.delenv("JOURNAL_STREAM", raising=False)
    caplog.set_level(logging.INFO, logger="biris_hw")
    rigs: list[SimulatedBiris] = []
    start_rig = cli_session._start_rig

    def keep(args: Any) -> SimulatedBiris:
        rigs.append(start_rig(args))
        return rigs[-1]

    monkeypatch.setattr(cli_session, "_start_rig", keep)
    credentials = tmp_path / "service.toml"
    credentials.write_text('[controllers]\nop = "pw"\n')
    credentials.chmod(0o600)
    where = endpoint(free_port())
    stop = threading.Event()
    failure: list[BaseException] = []

    def logged(text: str) -> bool:
        return any(text in r.getMessage() for r in list(caplog.records))

    def meddle() -> None:
        try:
            with connect(
                "svc", [where], multicast=False, user="op", password="pw", timeout=60
            ) as r:
                points: list[object] = []
                faults: list[HardwareFault] = []
                r.subscribe("point", points.append)
                r.subscribe("fault", faults.append)
                conn = r.open()
                conn.continuous_scan(-20.0, 20.0)
                until(lambda: points, WAIT, "points published")
                rigs[-1].faults.parity_error()
                until(lambda: faults and str(r.status()["state"]) == "idle", WAIT, "reset")
                before = len(points)
                conn.continuous_scan(-20.0, 20.0)
                until(lambda: len(points) > before + 3, WAIT, "points again after the reset")
                conn.stop_scan()
                conn.wait_idle(timeout=WAIT)
                with (
                    connect("svc", [where], multicast=False, user="op", password="no") as bad,
                    pytest.raises(AccessDenied),
                ):
                    bad.open().stop_scan()
                until(lambda: logged(" left"), WAIT, "the intruder's leaving logged")
                rigs[-1].faults.hang_supervisor()
                with pytest.raises(HardwareFault, match="timeout"):
                    conn.single_scan(10.0)
                    conn.wait_idle(timeout=WAIT)
        except BaseException as exc:
            failure.append(exc)
            stop.set()

    argv = [
        "serve",
        "--sim",
        "--time-scale",
        "10",
        "--scene",
        "circle:2",
        "--seed",
        "3",
        "--name",
        "svc",
        "--listen",
        where,
        "--no-multicast",
        "--credentials",
        str(credentials),
        "--auto-reset",
        "2",
        "--reset-delay",
        "0.05",
        "--duration",
        "120",
    ]
    args = build_parser("serve").parse_args(argv)
    helper = threading.Thread(target=meddle, name="test-meddle")
    helper.start()
    try:
        with log_to_stderr(False, service=True), pytest.raises(HardwareFault) as ended:
            serve_command.run(args, io.StringIO(), stop=stop)
    finally:
        stop.set()
        helper.join(WAIT)
    assert not failure, failure
    assert exit_status(ended.value) == 1
    assert error_line(ended.value).startswith("hardware fault (timeout): ")
    assert error_line(ended.value).endswith("(still so after 2 reset(s): gave up)")
    lines = capsys.readouterr().err.splitlines()
    when = r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d "
    assert all(
        re.match(when, line) or line.startswith("biris serve: warning: ") for line in lines
    ), lines
    up = rf"INFO service: service 'svc' up on {where} \(1 controller\(s\); reading free\)$"
    # the command's banner follows the service's start; a client may connect in between (it
    # did beside CPU-bound processes): the two orders are checked apart
    _in_order(
        lines,
        [
            up,
            r"INFO serve: serving the simulator \(scene circle:2, x10, seed 3\); after a fault: "
            r"reset at most 2 time\(s\), 0.05 s after it",
        ],
    )
    _in_order(
        lines,
        [
            up,
            r"INFO service: client \S+ connected \(status\)$",
            r"INFO service: client \S+ controls the sensor as 'op'$",
            r"ERROR reset: the sensor is in a fault \(parity\): parity error on the coupler; "
            r"resetting it \(at most 2 tries\)$",
            r"WARNING reset: resetting the sensor \(try 1 of 2\)$",
            r"INFO progress: homing the pan",
            r"INFO reset: the sensor is back \(idle\) after 1 reset\(s\)$",
            r"WARNING service: access refused: client \S+ \(user op\): stop_scan: needs a "
            r"controller's credentials; nothing was done$",
            r"INFO service: client \S+ left$",
            r"ERROR reset: the sensor is in a fault \(timeout\): BIRIS did not respond",
            r"WARNING reset: resetting the sensor \(try 2 of 2\)$",
            r"ERROR reset: reset 2 of 2 failed \(timeout\): ",
            r"ERROR reset: the sensor is still in a fault \(timeout\) after 2 reset\(s\): "
            r"giving up$",
            r"INFO serve: stopping svc$",
            r"INFO service: service 'svc' down$",
        ],
    )
    assert not any("hardware fault: " in line for line in lines)  # the watcher's words only


@pytest.mark.realtime
@pytest.mark.usefixtures("_zenoh_runtime")
def test_biris_reset_connect(
    biris: Run, rig: SimulatedBiris, server: BirisServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """0 once the sensor is back (its state said); 2 without a controller's credentials or
    with a wrong password, nothing done; 1 with the fault's line when the reset fails."""
    from biris_hw.io.net import serve

    where = endpoint(free_port())
    reset = ["reset", "--connect", "rs", "--endpoint", where]
    with serve(server, name="rs", listen=[where], controllers={"op": "pw"}, multicast=False):
        rig.faults.parity_error()
        until(lambda: server.status().state is ServerState.FAULT, what="the fault")
        assert biris(*reset) == (
            2,
            "",
            "biris reset: a reset is a controller's request: give --user USER (the password "
            "in $BIRIS_PASSWORD) or --credentials FILE\n",
        )
        monkeypatch.setenv("BIRIS_PASSWORD", "wrong")
        code, out, err = biris(*reset, "--user", "op")
        assert (code, out) == (2, ""), err
        # the service's warning comes first: it runs in this process, and its log with it
        assert err.splitlines()[-1] == (
            "biris reset: reset: the service refused the credentials of user 'op' (a wrong"
            " password or an unknown user, or a reader's rather than a controller's); nothing was"
            " done"
        )
        assert server.status().state is ServerState.FAULT  # nothing done
        monkeypatch.setenv("BIRIS_PASSWORD", "pw")
        assert biris(*reset, "--user", "op") == (
            0,
            "rs: idle after the reset (it was fault:parity)\n",
            "",
        )
        assert server.status().state is ServerState.IDLE
        rig.faults.hang_supervisor()
        with server.open() as conn, pytest.raises(HardwareFault):
            conn.single_scan(10.0)
            conn.wait_idle(timeout=WAIT)
        code, out, err = biris(*reset, "--user", "op")
        assert (code, out) == (1, ""), err
        assert err.startswith("biris reset: hardware fault (timeout): BIRIS still busy with ")
        rig.faults.clear_hang()
        with server.open() as conn:
            conn.reset()
