"""SIGTERM ends every ``biris`` command as Ctrl-C does, with exit status 143.

In-process, with this module as a stand-in command (it provides ``add_arguments`` and ``run``,
as a command's module does): the signal interrupts the command where it waits, the command's own
Ctrl-C path runs (and a second SIGTERM does not cut it short), the status is 143, and the
previous handler is back afterwards. In other processes, as systemd or ``timeout`` would: ``biris
record`` leaves a complete recording that replays, ``biris serve`` closes in order.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from biris_hw import cli
from biris_hw.cli import COMMANDS, Command
from biris_hw.commands.failures import EXIT_INTERRUPTED, EXIT_TERMINATED
from tests.conftest import until
from tests.net_helpers import endpoint, free_port

WAIT = 60.0
ROOT = Path(__file__).resolve().parent.parent

# -- this module as a command ----------------------------------------------------------------------

_SEEN: list[str] = []
"""What the stand-in command did, in order."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--again", action="store_true", help="a second SIGTERM while it cleans up")


def run(args: argparse.Namespace) -> int:
    """Send this process SIGTERM and wait to be interrupted; then clean up (sending SIGTERM
    again with --again) and return Ctrl-C's status."""
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        threading.Event().wait(WAIT)  # the signal's KeyboardInterrupt ends this wait
        _SEEN.append("not interrupted")
        return 0
    except KeyboardInterrupt:
        _SEEN.append("interrupted")
    if args.again:
        os.kill(os.getpid(), signal.SIGTERM)  # ignored: the clean path runs to its end
    _SEEN.append("kept what it could")
    return EXIT_INTERRUPTED


@pytest.fixture
def stand_in(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """``biris term-test``: this module, registered as a command; signals reach only the main
    thread, so the test must run there."""
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals are delivered to the main thread only")
    command = Command("term-test", __name__, "a stand-in", "A stand-in command.")
    monkeypatch.setattr(cli, "COMMANDS", (*COMMANDS, command))
    _SEEN.clear()
    previous = signal.getsignal(signal.SIGTERM)
    yield
    assert signal.getsignal(signal.SIGTERM) is previous  # the command's handler is gone


@pytest.mark.usefixtures("stand_in")
def test_sigterm_takes_the_ctrl_c_path_and_exits_143() -> None:
    assert cli.main(["term-test"]) == EXIT_TERMINATED
    assert _SEEN == ["interrupted", "kept what it could"]


@pytest.mark.usefixtures("stand_in")
def test_a_second_sigterm_does_not_cut_the_clean_path_short() -> None:
    assert cli.main(["term-test", "--again"]) == EXIT_TERMINATED
    assert _SEEN == ["interrupted", "kept what it could"]


def test_ctrl_c_stays_130(monkeypatch: pytest.MonkeyPatch) -> None:
    """A KeyboardInterrupt that no SIGTERM caused (Ctrl-C) keeps its status."""

    def interrupted(args: argparse.Namespace) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(sys.modules[__name__], "run", interrupted)
    monkeypatch.setattr(
        cli, "COMMANDS", (*COMMANDS, Command("term-test", __name__, "a stand-in", "A stand-in."))
    )
    assert cli.main(["term-test"]) == EXIT_INTERRUPTED


# -- long-running commands in their own process ----------------------------------------------------

SIM = ["--sim", "--time-scale", "10", "--scene", "circle:2", "--seed", "3"]


def _biris(*argv: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "biris_hw.cli", *argv],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _size(file: Path) -> int:
    return file.stat().st_size if file.exists() else 0


def _finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    try:
        out, err = proc.communicate(timeout=WAIT)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, out, err


def test_sigterm_leaves_a_complete_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``kill -TERM`` of ``biris record`` once it has written data: exit 143, its summary and a
    file that the MCAP reader and ``biris replay`` read to its end."""
    from mcap.reader import make_reader

    out_file = tmp_path / "run.mcap"
    proc = _biris("record", *SIM, "--out", str(out_file), "--cw", "-20", "--ccw", "20",
                  "--duration", "120")  # fmt: skip
    try:
        # data written: past the header and the channels, a chunk (flushed every FLUSH_S)
        until(lambda: _size(out_file) > 4096 or proc.poll() is not None, WAIT, "data recorded")
        proc.send_signal(signal.SIGTERM)
    finally:
        code, out, err = _finish(proc)
    assert code == EXIT_TERMINATED, (out, err)
    assert out.startswith(f"recorded {out_file}: "), out
    assert f"biris record: interrupted: {out_file} is complete up to then" in err
    with out_file.open("rb") as stream:
        assert make_reader(stream).get_summary() is not None  # the footer and summary are there
    assert cli.main(["replay", str(out_file)]) == 0
    assert f"replayed {out_file}: " in capsys.readouterr().out


def _line(proc: subprocess.Popen[str], prefix: str) -> str:
    """The first stdout line starting with ``prefix`` (bounded by WAIT)."""
    assert proc.stdout is not None
    while True:
        ready, _, _ = select.select([proc.stdout], [], [], WAIT)
        assert ready, f"no line starting {prefix!r} within {WAIT:g} s"
        line = proc.stdout.readline()
        assert line, f"the process ended before a line starting {prefix!r}"
        if line.startswith(prefix):
            return line


@pytest.mark.slow  # the fast tier keeps a cheaper test of the same (make test-slow runs this)
def test_sigterm_stops_the_service_in_order() -> None:
    """Two SIGTERMs in a row (a supervisor that insists): the service stops once, in order,
    says so on stdout and in its log, and exits 143."""
    where = endpoint(free_port())
    proc = _biris("serve", *SIM, "--name", "sig", "--listen", where, "--no-multicast")
    try:
        _line(proc, "serving sig on ")
        proc.send_signal(signal.SIGTERM)
        proc.send_signal(signal.SIGTERM)
    finally:
        code, out, err = _finish(proc)
    assert code == EXIT_TERMINATED, err
    assert out == "stopping sig\n"
    # a loaded host adds the simulator's lag warning anywhere: not what is tested here
    lines = [line for line in err.splitlines() if "cannot keep up with" not in line]
    assert lines[-2].endswith(" INFO serve: stopping sig"), err
    assert lines[-1].endswith(" INFO service: service 'sig' down"), err
