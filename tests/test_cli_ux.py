"""The ``biris`` command for people: what it says while it waits and when it is interrupted, what
it checks before touching the sensor, and what it refuses or warns about.

Every command runs in-process against the simulator it starts (``--sim``), as in
``tests/test_cli.py``; a "real target" is that same simulator handed to the command through
``--target`` (``_open_target`` patched), so the questions a real head asks can be tested without
one. Interruptions are a ``KeyboardInterrupt`` raised from inside the command's loop, not a
signal: the same exception, at a known moment.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import os
import re
import threading
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from biris_hw import opening
from biris_hw.cli import build_parser
from biris_hw.commands import argtypes, console, demo, failures, options, watch
from biris_hw.commands import session as cli_session
from biris_hw.commands.failures import EXIT_INTERRUPTED
from biris_hw.commands.session import HALF_TURN_COUNTS
from biris_hw.errors import HardwareFault
from biris_hw.hardware import BirisHardware
from biris_hw.io.scanfile import load_scans
from biris_hw.io.sweeps import Sweeps
from biris_hw.records import BirisInitRecord
from biris_hw.server import BirisServer
from sim import Scene, SimulatedBiris
from sim.clock import LAG_WARNING_S, SimClock
from tests.conftest import Run
from tests.test_cli import PNG, SIM

pytestmark = pytest.mark.usefixtures("no_target_env")


@pytest.fixture
def rigs(monkeypatch: pytest.MonkeyPatch) -> list[SimulatedBiris]:
    """The simulators the commands start with --sim, for the test to look at (or break)."""
    started: list[SimulatedBiris] = []
    start = cli_session._start_rig

    def keep(args: argparse.Namespace) -> SimulatedBiris:
        rig = start(args)
        started.append(rig)
        return rig

    monkeypatch.setattr(cli_session, "_start_rig", keep)
    return started


@pytest.fixture
def target(monkeypatch: pytest.MonkeyPatch, no_leaks: None) -> Iterator[list[SimulatedBiris]]:
    """``--target FILE`` opens a simulator, as if it were a real head: what only a real target
    asks (``--yes``) can be tested. The simulators run on virtual time (what a one-shot scan
    answers depends on the seed, not the host's load) and are closed after the test."""
    started: list[SimulatedBiris] = []

    def open_target(file: object) -> BirisHardware:
        rig = SimulatedBiris(scene=Scene.circle(2.0), seed=3, clock="virtual").start()
        started.append(rig)
        return rig.hardware

    monkeypatch.setattr(opening, "_open_target", open_target)
    yield started
    for rig in started:
        rig.close()


def _lines(err: str) -> list[str]:
    """What the command itself said on stderr: the driver's warnings (``biris: warning: ...``,
    e.g. a scan that started late on a loaded host) are left out, since whether one comes
    depends on the machine, not on what is tested here."""
    return [line for line in err.splitlines() if not line.startswith("biris: warning: ")]


def _said(err: str) -> list[str]:
    """:func:`_lines` less the simulator's lag warning, which a loaded machine adds to any
    command (tests of that warning use :func:`_lines`)."""
    return [line for line in _lines(err) if "cannot keep up with" not in line]


# -- 1. --continuous -------------------------------------------------------------------------------


def test_continuous_scan_runs_appendix_d(biris: Run, rigs: list[SimulatedBiris]) -> None:
    """One BI_START_CONTINUOUS for the whole run, where report mode starts a BI_ACQUIRE per
    sweep."""
    argv = ["scan", "--cw", "-20", "--ccw", "20", "--sweeps", "3", *SIM]
    code, out, err = biris(*argv, "--continuous")
    assert code == 0, err
    assert len([line for line in out.splitlines() if "#" in line]) == 3
    code, _, err = biris(*argv)
    assert code == 0, err
    continuous, report = (rig.supervisor.sequences_started for rig in rigs)
    assert continuous == 1
    assert report >= 3


@pytest.mark.slow  # scan --continuous covers the flag in the fast tier
def test_continuous_watch_says_the_acquisition_mode(biris: Run) -> None:
    code, out, err = biris(
        "watch", "--duration", "0.3", "--interval", "0.1", "--continuous",
        "--cw", "-15", "--ccw", "15", *SIM,
    )  # fmt: skip
    assert code == 0, err
    last = dict(word.split("=", 1) for word in out.splitlines()[-1].split() if "=" in word)
    assert last["acquisition"] == "continuous"
    code, out, err = biris("watch", "--duration", "0.1", "--interval", "0.1", *SIM)
    assert code == 0, err
    assert "acquisition=single" in out.splitlines()[-1]


@pytest.mark.parametrize(
    "command", [["point"], ["scan", "--to", "10"], ["watch", "--duration", "0.1"]]
)
def test_continuous_reaches_the_server_on_every_command(
    biris: Run, monkeypatch: pytest.MonkeyPatch, command: list[str]
) -> None:
    records: list[BirisInitRecord] = []

    def spy(hardware: BirisHardware, record: BirisInitRecord) -> Any:
        records.append(record)
        return BirisServer(hardware, record)

    monkeypatch.setattr("biris_hw.server.BirisServer", spy)
    code, _, err = biris(*command, "--continuous", *SIM)
    # watch runs on scaled time: a host too loaded for the time scale may make BIRIS late, and
    # the fault then says the simulator was behind its clock (the point here is the record)
    assert code == 0 or "behind its clock" in err, err
    assert [r.continuous_acquisition for r in records] == [True]


def test_the_demo_takes_continuous() -> None:
    parser = build_parser("demo")
    assert parser.parse_args(["demo", "--continuous"]).continuous is True


# -- 2. progress, and the command a silent target was waiting for ----------------------------------


@pytest.fixture
def says_progress(monkeypatch: pytest.MonkeyPatch, rigs: list[SimulatedBiris]) -> None:
    """stderr is a terminal, and the server says something on the progress logger as soon as
    its simulator has started (the sentence is the test's, not the server's)."""
    monkeypatch.setattr(console, "stderr_is_terminal", lambda: True)
    start = cli_session._start_rig

    def start_and_say(args: argparse.Namespace) -> SimulatedBiris:
        rig = start(args)
        logging.getLogger(console.PROGRESS_LOGGER).info("testing the progress line")
        logging.getLogger(console.PROGRESS_LOGGER).info("%d things done.", 2)
        return rig

    monkeypatch.setattr(cli_session, "_start_rig", start_and_say)


def test_progress_is_shown_while_a_command_waits(biris: Run, says_progress: None) -> None:
    code, out, err = biris("home", *SIM)
    assert code == 0, err
    assert "biris home: testing the progress line..." in _lines(err)
    assert "biris home: 2 things done." in _lines(err)
    assert "testing" not in out  # stdout stays the command's data
    # the handler is gone once the command has ended
    assert not logging.getLogger(console.PROGRESS_LOGGER).handlers


def test_progress_is_not_shown_when_quiet(biris: Run, says_progress: None) -> None:
    code, _, err = biris("home", "--quiet", *SIM)
    assert code == 0, err
    assert "progress" not in err


def test_progress_is_not_shown_when_nobody_watches_stderr(biris: Run) -> None:
    """Not a terminal (a log, a pipe, a script): stderr keeps its one-line error contract."""
    logging.getLogger(console.PROGRESS_LOGGER).info("not for a pipe")  # outside any command
    code, _, err = biris("home", *SIM)
    assert code == 0, err
    assert _lines(err) == []


def test_a_fault_names_the_biris_command_not_its_code() -> None:
    fault = HardwareFault("timeout", "BIRIS still busy after 4.0 s (COMMAND 7): it does not answer")
    line = failures.error_line(fault)
    assert "COMMAND 7 (BI_STOP_CONTINUOUS)" in line
    hex_code = failures.error_line(HardwareFault("protocol", "command 0x05 and COMMAND 08 refused"))
    assert "command 0x05 (BI_ACQUIRE) and COMMAND 08 (BI_LOAD_LUT) refused" in hex_code
    named = HardwareFault("timeout", "BIRIS did not respond to BI_ACQUIRE (COMMAND 5)")
    assert failures.error_line(named) == f"hardware fault (timeout): {named.message}"


def test_a_timeout_names_the_command_biris_still_holds() -> None:
    """A timeout whose message names no command gets the one COMMAND still holds."""
    hardware: Any = SimpleNamespace(
        devices=SimpleNamespace(link=SimpleNamespace(command=lambda: 7))
    )
    fault = HardwareFault("timeout", "BIRIS did not respond for 4 s of hardware time")
    named = opening._name_unanswered(fault, hardware)
    assert named.kind == "timeout"
    assert named.message.endswith("(waiting for BIRIS to finish BI_STOP_CONTINUOUS)")
    idle: Any = SimpleNamespace(devices=SimpleNamespace(link=SimpleNamespace(command=lambda: 0)))
    assert opening._name_unanswered(fault, idle) is fault  # nothing outstanding: nothing to add
    stall = HardwareFault("motor_stall", "the shaft did not follow")
    assert opening._name_unanswered(stall, hardware) is stall


def test_a_hung_biris_is_reported_by_the_command_it_was_waiting_for(
    biris: Run, rigs: list[SimulatedBiris], monkeypatch: pytest.MonkeyPatch
) -> None:
    """BIRIS hangs under a single scan: the line names a BI_ command, never a bare code."""
    from biris_hw.client import Connection

    scan = Connection.single_scan

    def scan_then_hang(self: Connection, to_deg: float) -> int:
        dest = scan(self, to_deg)
        rigs[-1].faults.hang_supervisor()
        return dest

    monkeypatch.setattr(Connection, "single_scan", scan_then_hang)
    code, _, err = biris("scan", "--to", "90", *SIM)
    assert code == 1
    (line,) = _lines(err)
    assert line.startswith("biris scan: hardware fault (timeout): ")
    assert "BI_ACQUIRE" in line


# -- 3. biris sim's time scale ---------------------------------------------------------------------


def test_biris_sim_defaults_to_the_time_scale_of_the_other_commands() -> None:
    sim_args = build_parser("sim").parse_args(["sim", "--shm", "x"])
    scan_args = build_parser("scan").parse_args(["scan", "--sim", "--to", "10"])
    options.check_target_arguments(scan_args)
    demo_args = build_parser("demo").parse_args(["demo"])
    assert sim_args.time_scale == scan_args.time_scale == demo_args.time_scale
    assert sim_args.time_scale == argtypes.DEFAULT_TIME_SCALE


# -- 4. clamped destinations and long moves --------------------------------------------------------


def test_a_clamped_destination_is_reported(biris: Run) -> None:
    code, out, err = biris("scan", "--to", "400", *SIM)
    assert code == 0, err
    assert _said(err) == [
        "biris scan: --to 400\N{DEGREE SIGN} is beyond the head's travel: clamped to "
        "+360\N{DEGREE SIGN}"
    ]
    assert out.startswith("CCW #1: ")


def test_clamped_sweep_limits_are_reported(biris: Run) -> None:
    code, _, err = biris("scan", "--cw=-1e9", "--ccw", "-350", "--sweeps", "1", *SIM)
    assert code == 0, err
    assert _said(err) == [
        "biris scan: --cw -1e+09\N{DEGREE SIGN} is beyond the head's travel: clamped to "
        "-360\N{DEGREE SIGN}"
    ]


def test_an_unclamped_destination_says_nothing(biris: Run) -> None:
    code, _, err = biris("scan", "--to", "-30", *SIM)
    assert (code, err) == (0, "")


def test_a_long_move_on_a_real_head_needs_yes(
    biris: Run, target: list[SimulatedBiris], tmp_path: Path
) -> None:
    robot = str(tmp_path / "robot.toml")
    code, out, err = biris("scan", "--target", robot, "--to", "200")
    assert (code, out) == (2, "")
    (line,) = _lines(err)
    assert line.startswith("biris scan: --to 200 turns the head 200\N{DEGREE SIGN} (from +0.0")
    assert line.endswith("more than half a turn: make sure the cable and the space around the "
                         "head allow it, then add --yes")  # fmt: skip
    assert abs(target[-1].azimuth_counts) < 16  # the head stayed home
    code, out, err = biris("scan", "--target", robot, "--to", "200", "--yes")
    assert code == 0, err
    first = out.splitlines()[0]
    span = re.search(r"over ([+-][\d.]+)\.\.([+-][\d.]+) deg", first)
    assert first.startswith("CCW #1: ") and span is not None, first
    # the long move was made (on virtual time the host's latency cuts nothing off the scan)
    assert "partial sweep" not in first, first
    assert 180.0 < float(span[2]) <= 200.2, first  # the head may stand a count or two past


def test_a_sweep_wider_than_half_a_turn_on_a_real_head_needs_yes(
    biris: Run, target: list[SimulatedBiris], tmp_path: Path
) -> None:
    robot = str(tmp_path / "robot.toml")
    code, _, err = biris("scan", "--target", robot, "--cw", "-100", "--ccw", "100")
    assert code == 2
    assert "--ccw 100 turns the head 200\N{DEGREE SIGN} (from -100.0" in err
    code, _, err = biris("scan", "--target", robot, "--cw", "-80", "--ccw", "80", "--sweeps", "1")
    assert code == 0, err  # 160 degrees: no question


def test_the_simulator_never_asks(biris: Run) -> None:
    code, _, err = biris("scan", "--to", "200", *SIM)
    assert (code, err) == (0, "")


def test_home_asks_only_for_a_head_more_than_half_a_turn_away() -> None:
    def session(azimuth: int, simulated: bool = False) -> Any:
        server = SimpleNamespace(status=lambda: {"azimuth": azimuth})
        return SimpleNamespace(server=server, simulated=simulated)

    move = [("driving home to 0\N{DEGREE SIGN}", 0)]
    no = argparse.Namespace(yes=False)
    cli_session.confirm_moves(session(HALF_TURN_COUNTS), no, move)  # exactly half a turn: fine
    with pytest.raises(failures.UsageError, match="driving home to 0° turns the head 190°"):
        cli_session.confirm_moves(session(-2162), no, move)
    cli_session.confirm_moves(session(-2162), argparse.Namespace(yes=True), move)
    cli_session.confirm_moves(session(-2162, simulated=True), no, move)


# -- 5. output paths, checked before anything starts -----------------------------------------------


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--save", "{file}/run"], "is not a folder"),
        (["--save", "{dir}"], "is a folder; name the files"),
        (["--plot", "{dir}"], "is a folder; give a file name"),
        (["--plot", "{dir}/run.txt"], "unknown extension '.txt'; use one of"),
        (["--plot", "{dir}/run"], "no extension; use one of"),
        (["--plot", "{file}/deeper/run.png"], "is not a folder"),
    ],
)
def test_a_bad_output_path_is_refused_before_the_sensor_is_touched(
    biris: Run, tmp_path: Path, _leak_and_audit_check: Any, argv: list[str], words: str
) -> None:
    file = tmp_path / "a-file"
    file.write_text("")
    given = [word.format(file=file, dir=tmp_path) for word in argv]
    code, out, err = biris("scan", "--to", "10", *given, *SIM)
    assert (code, out) == (2, "")
    (line,) = _lines(err)
    assert line.startswith(f"biris scan: {given[0]} {given[1]}") and words in line
    assert _leak_and_audit_check.rigs == []  # no simulator was started


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_an_unwritable_folder_is_refused_before_the_sensor_is_touched(
    biris: Run, tmp_path: Path, _leak_and_audit_check: Any
) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        code, _, err = biris("scan", "--to", "10", "--save", str(locked / "new" / "run"), *SIM)
    finally:
        locked.chmod(0o700)
    assert code == 2
    assert f"cannot write in {locked} (permission denied)" in err
    assert _leak_and_audit_check.rigs == []


def test_a_folder_without_write_permission_is_refused(
    biris: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, _leak_and_audit_check: Any
) -> None:
    """The same as above for any user (root may write anywhere): the permission is asked of
    the operating system, which here says no."""
    monkeypatch.setattr(os, "access", lambda path, mode: False)
    code, _, err = biris("scan", "--to", "10", "--plot", str(tmp_path / "new" / "run.png"), *SIM)
    assert code == 2
    assert _lines(err) == [
        f"biris scan: --plot {tmp_path / 'new' / 'run.png'}: cannot write in {tmp_path} "
        "(permission denied)"
    ]
    assert _leak_and_audit_check.rigs == []


def test_demo_out_must_be_a_folder(biris: Run, tmp_path: Path, _leak_and_audit_check: Any) -> None:
    file = tmp_path / "pictures"
    file.write_text("")
    code, out, err = biris("demo", "--out", str(file), "--duration", "1")
    assert (code, out) == (2, "")
    assert _lines(err) == [f"biris demo: --out {file}: is a file, not a folder"]
    assert _leak_and_audit_check.rigs == []


def test_motor_params_save_init_is_checked_first(
    biris: Run, tmp_path: Path, _leak_and_audit_check: Any
) -> None:
    code, _, err = biris("motor-params", "--save-init", str(tmp_path), *SIM)
    assert code == 2
    assert "is a folder; give a file name" in err
    assert _leak_and_audit_check.rigs == []


def test_missing_folders_are_made(fonts_open: None, biris: Run, tmp_path: Path) -> None:
    picture = tmp_path / "new" / "deeper" / "run.svg"
    code, out, err = biris("scan", "--to", "20", "--plot", str(picture), *SIM)
    assert code == 0, err
    assert f"picture: {picture}" in out.splitlines()
    assert picture.read_text().lstrip().startswith("<?xml")


# -- 6. Ctrl-C keeps what was acquired -------------------------------------------------------------


def test_ctrl_c_during_sweeps_writes_the_sweeps_completed(
    fonts_open: None, biris: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    take = Sweeps._take
    taken: list[int] = []

    def interrupt_the_third(self: Sweeps, timeout: float) -> Any:
        if len(taken) == 2:
            raise KeyboardInterrupt
        taken.append(1)
        return take(self, timeout)

    monkeypatch.setattr(Sweeps, "_take", interrupt_the_third)
    run, picture = tmp_path / "run", tmp_path / "run.png"
    code, out, err = biris(
        "scan", "--cw", "-20", "--ccw", "20", "--sweeps", "5",
        "--save", str(run), "--plot", str(picture), *SIM,
    )  # fmt: skip
    assert code == EXIT_INTERRUPTED
    assert [line.split(":")[0] for line in out.splitlines() if "#" in line] == ["CW #1", "CCW #1"]
    assert _lines(err) == [
        f"biris scan: interrupted: wrote 2 of 5 sweeps to {run}.npz, {run}.csv and {picture}"
    ]
    assert [(s.direction.name, s.seq) for s in load_scans(f"{run}.npz")] == [("CW", 1), ("CCW", 1)]
    assert picture.read_bytes()[:8] == PNG


def test_ctrl_c_before_any_sweep_writes_nothing(
    biris: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupted(self: Sweeps, timeout: float) -> Any:
        raise KeyboardInterrupt

    monkeypatch.setattr(Sweeps, "_take", interrupted)
    code, _, err = biris(
        "scan", "--cw", "-20", "--ccw", "20", "--save", str(tmp_path / "run"), *SIM
    )
    assert code == EXIT_INTERRUPTED
    assert _lines(err) == [
        "biris scan: interrupted before the first of 2 sweeps completed: nothing written"
    ]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow  # scan --sweeps keeps the Ctrl-C rule in the fast tier
def test_ctrl_c_in_the_demo_draws_what_it_has(
    fonts_open: None, biris: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    refresh = demo._refresh
    fired: list[int] = []

    def interrupt_after_two_sweeps(status: demo.DemoStatus, *args: Any) -> None:
        refresh(status, *args)
        if status.total_sweeps >= 2 and not fired:
            fired.append(status.total_sweeps)
            raise KeyboardInterrupt

    monkeypatch.setattr(demo, "_refresh", interrupt_after_two_sweeps)
    out_dir = tmp_path / "demo"
    code, out, err = biris(
        "demo", "--duration", "60", "--time-scale", "30", "--scene", "circle:2",
        "--cw", "-20", "--ccw", "20", "--out", str(out_dir),
    )  # fmt: skip
    assert code == EXIT_INTERRUPTED, err
    made = fired[0]
    assert _said(err) == [
        f"biris demo: interrupted: wrote the latest 2 of {made} sweeps to {out_dir}"
    ]
    assert f"biris demo: {made} sweeps (" in out
    for name in ("demo-polar.png", "demo-top.png", "demo-3d.png"):
        assert (out_dir / name).read_bytes()[:8] == PNG
    scans = load_scans(out_dir / "latest-scans.npz")
    assert sorted(s.direction.name for s in scans) == ["CCW", "CW"]


# -- 7. watch goes on through a fault -------------------------------------------------------------


def _watch_args(*argv: str) -> argparse.Namespace:
    return build_parser("watch").parse_args(["watch", *argv])


def test_watch_goes_on_through_a_fault_and_says_it_once(
    rigs: list[SimulatedBiris],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    no_leaks: None,
) -> None:
    """A fault nobody resets: watch keeps refreshing (the fault in every status line), says
    once what the fault is and how to recover, and its exit status says the server was still
    in the fault at the end."""
    update = watch._Lines.update
    shown: list[str] = []
    stop = threading.Event()

    def update_and_break(self: watch._Lines, status: Any, elapsed: float) -> None:
        update(self, status, elapsed)
        shown.append(str(status["state"]))
        if len(shown) == 2:
            rigs[-1].faults.parity_error()
        if shown.count("fault:parity") == 4:
            stop.set()  # four looks at the fault: watch did not stop at the first

    monkeypatch.setattr(watch._Lines, "update", update_and_break)
    out = io.StringIO()
    args = _watch_args("--interval", "0.02", "--duration", "30", *SIM)
    code = watch.run(args, out, stop=stop)
    assert code == 1
    assert "fault:parity" not in shown[:2] and shown.count("fault:parity") == 4
    assert shown[-4:] == ["fault:parity"] * 4
    lines = out.getvalue().splitlines()
    assert len(lines) == len(shown) and "state=fault:parity" in lines[-1]
    said = _said(capsys.readouterr().err)
    assert len(said) == 2, said
    assert said[0].startswith("biris watch: hardware fault (parity): parity error on the coupler; ")
    assert "reset the server (conn.reset() or restart the command)" in said[0]
    assert said[0].endswith("watch goes on showing the status")
    assert said[1] == "biris watch: ended with the server still in the fault (parity)"


def test_watch_shows_the_server_again_once_it_is_reset(
    rigs: list[SimulatedBiris],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    no_leaks: None,
) -> None:
    """A fault in the middle of ``watch --cw --ccw``, then a reset from another thread (as a
    controller elsewhere would): watch shows the fault, then the server again, sweeps again
    once it is idle, and ends with status 0."""
    sessions: list[cli_session.Session] = []
    open_session = cli_session.open_session

    @contextlib.contextmanager
    def keep(args: argparse.Namespace) -> Iterator[cli_session.Session]:
        with open_session(args) as session:
            sessions.append(session)
            yield session

    monkeypatch.setattr(watch, "open_session", keep)
    update = watch._Lines.update
    shown: list[str] = []
    stop = threading.Event()
    resets: list[threading.Thread] = []

    def update_and_act(self: watch._Lines, status: Any, elapsed: float) -> None:
        update(self, status, elapsed)
        state = str(status["state"])
        shown.append(state)
        if len(shown) == 3:
            rigs[-1].faults.parity_error()
        elif state.startswith("fault") and not resets:
            server = sessions[-1].server
            assert isinstance(server, BirisServer)
            resets.append(threading.Thread(target=server.reset))
            resets[0].start()
        elif resets and state == "scanning":
            stop.set()  # sweeping again after the reset

    monkeypatch.setattr(watch._Lines, "update", update_and_act)
    out = io.StringIO()
    args = _watch_args("--interval", "0.02", "--duration", "30", "--cw", "-20", "--ccw", "20", *SIM)
    try:
        code = watch.run(args, out, stop=stop)
    finally:
        for thread in resets:
            thread.join()
    assert code == 0
    fault = shown.index("fault:parity")
    assert "scanning" in shown[:fault] and shown[-1] == "scanning"
    assert "idle" in shown[fault:]  # after the reset, before the new sweep
    said = _said(capsys.readouterr().err)
    assert len(said) == 3, said
    assert said[0].startswith("biris watch: hardware fault (parity): ")
    assert said[1].startswith("biris watch: the server has left the fault (state ")
    assert said[2] == "biris watch: sweeping again"


# -- 8. a time scale the host cannot keep up with --------------------------------------------------


class _FakeTime:
    def __init__(self) -> None:
        self.now = 100.0

    def monotonic(self) -> float:
        return self.now


def test_the_clock_measures_how_late_its_waits_run(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = _FakeTime()
    monkeypatch.setattr("sim.clock.time", fake)
    monkeypatch.setattr("biris_hw.timebase.time", fake)
    clock, stop = SimClock(10.0), threading.Event()
    assert clock.lateness() == 0.0
    fake.now += 1.0  # a second of real time: ten of hardware time
    assert clock.wait_until(clock.now() - 2.0, stop)  # due two hardware seconds ago
    assert clock.lateness() == pytest.approx(2.0 * (1.0 - np.exp(-2.0)))
    assert clock.lateness() > LAG_WARNING_S
    fake.now += 5.0
    assert clock.wait_until(clock.now(), stop)  # on time
    assert clock.lateness() < 0.001


def test_a_rig_that_keeps_up_is_not_behind(no_leaks: None) -> None:
    rig = SimulatedBiris(time_scale=4.0)
    assert rig.lag_s() == 0.0  # not started
    with rig:
        assert rig.lag_s() < LAG_WARNING_S and not rig.behind()
    assert rig.lag_s() == 0.0  # closed


class _LaggingRig:
    """Behind or not, look by look, as the test says; ``done`` once the looks have run out or
    the warning has been given (the only reader of :meth:`lag_s`)."""

    time_scale = 300.0
    lag_bound_s = LAG_WARNING_S

    def __init__(self, looks: list[bool]) -> None:
        self._looks = list(looks)
        self.done = threading.Event()

    def lag_s(self) -> float:
        self.done.set()
        return 0.5

    def behind(self) -> bool:
        if not self._looks:
            self.done.set()
            return False
        return self._looks.pop(0)


@pytest.mark.parametrize(
    ("looks", "warned"),
    [([True, False, True, False, False], False), ([False, True, True, False], True)],
)
def test_the_lag_watch_needs_two_looks_in_a_row(
    looks: list[bool], warned: bool, capsys: pytest.CaptureFixture[str], no_leaks: None
) -> None:
    rig = _LaggingRig(looks)
    lag = cli_session.LagWatch(rig, "biris test", every_s=0.001).start()
    assert rig.done.wait(5.0)
    lag.stop()
    err = capsys.readouterr().err
    assert lag.warned is warned
    if warned:
        assert _lines(err) == [
            "biris test: warning: the simulator runs 500 ms of hardware time late (more than "
            "33 ms): this machine cannot keep up with --time-scale 300, so timings and faults "
            "(motor_stall, timeout) may be wrong; use a smaller --time-scale"
        ]
    else:
        assert err == ""


def test_a_command_warns_once_when_the_simulator_falls_behind(
    biris: Run, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(cli_session, "LAG_CHECK_S", 0.005)
    monkeypatch.setattr(SimulatedBiris, "behind", lambda self: True)
    monkeypatch.setattr(SimulatedBiris, "lag_s", lambda self: 0.25)
    code, _, err = biris("home", *SIM)
    assert code == 0, err
    assert _lines(err) == [
        "biris home: warning: the simulator runs 250 ms of hardware time late (more than 33 ms): "
        "this machine cannot keep up with --time-scale 30, so timings and faults (motor_stall, "
        "timeout) may be wrong; use a smaller --time-scale"
    ]


def test_biris_sim_warns_once_too() -> None:
    from sim.process import _Mirror

    said: list[str] = []
    rig: Any = _LaggingRig([True])
    mirror = _Mirror(rig, None, None, 0.02, warn=said.append)  # type: ignore[arg-type]
    mirror._check_lag()
    mirror._check_lag()
    assert len(said) == 1 and said[0].startswith("warning: the simulator runs 500 ms")
