"""The ``biris`` command: a dispatcher over one module per subcommand.

Each subcommand's module provides ``add_arguments(parser)`` and ``run(args) -> int``; this file
only knows their names, a one-line summary, and where they live. A command's module is imported
only when that command is asked for, so ``biris --help`` is instant, a missing optional piece
(the simulator process, matplotlib) breaks only the command that needs it, and that command
says so in one line.

While a command runs, what the server says it is doing (homing, booting BIRIS, waiting for a
command to finish) is shown on stderr when a person watches it
(:func:`~biris_hw.commands.console.progress_to_stderr`), and what the driver warns about (a scan
that came out short, acquisitions lost) always is, one ``biris: warning: ...`` line each
(:func:`~biris_hw.commands.console.log_to_stderr`; ``--debug`` shows the whole log instead). A
service (:attr:`Command.service`: ``biris serve``) logs instead, from INFO up, one line per event
in the journal's form.

Ctrl-C is exit status 130, after the command has kept what it could. SIGTERM -- what systemd,
``docker stop``, ``timeout`` and launch files send -- takes the same path
(:class:`_TermAsInterrupt`: the signal raises :class:`~biris_hw.commands.failures.Terminated`, a
KeyboardInterrupt, in the main thread), so every
long-running command closes its files and prints its summary as after Ctrl-C, and the status is
then 143 (128 + 15).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from types import FrameType, TracebackType
from typing import Any, NamedTuple, NoReturn, Protocol, cast

from biris_hw import __version__
from biris_hw.commands.console import log_to_stderr, progress_to_stderr, wants_progress
from biris_hw.commands.failures import (
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    EXIT_USAGE,
    Terminated,
    report_error,
)

__all__ = ["COMMANDS", "Command", "build_parser", "main"]


class Command(NamedTuple):
    """A subcommand: its name, where its module lives, and what ``biris --help`` says (a
    NamedTuple rather than a dataclass: ``biris --help`` does not pay for importing
    :mod:`dataclasses`)."""

    name: str
    module: str
    summary: str
    description: str
    service: bool = False
    """A long-running service read from a log rather than watched: it logs from INFO up, one
    line per event (:func:`~biris_hw.commands.console.log_to_stderr`'s ``service``)."""


COMMANDS: tuple[Command, ...] = (
    Command(
        "demo",
        "biris_hw.commands.demo",
        "the server at work on a simulated robot, with pictures",
        "Sweep a simulated room with the BIRIS server for a while, show progress live, then "
        "write pictures of what it saw (polar, top-down and 3-D) to a folder.",
    ),
    Command(
        "scan",
        "biris_hw.commands.scan",
        "one scan, or continuous sweeps; summary, files, picture",
        "Scan once to an azimuth (--to) or sweep between two limits (--cw/--ccw --sweeps N); "
        "print a summary of each scan, save them (--save), or draw them (--plot).",
    ),
    Command(
        "point",
        "biris_hw.commands.point",
        "the latest acquisition (makes one if needed)",
        "Print the latest acquisition: azimuth, closest range and the profile along the "
        "laser line. A fresh server has none, so a short scan makes one first.",
    ),
    Command(
        "watch",
        "biris_hw.commands.watch",
        "live server status",
        "Show the server's status (state, azimuth, counters, interrupts, connections), "
        "refreshed, for --duration seconds or until Ctrl-C; optionally while sweeping.",
    ),
    Command(
        "home",
        "biris_hw.commands.home",
        "initialise and drive the head to 0 degrees",
        "Start the server (which finds the zero index) and drive the head to 0 degrees.",
    ),
    Command(
        "motor-params",
        "biris_hw.commands.motor_params",
        "show or set the pan motor's HCTL-1000 parameters",
        "Show the pan motor's parameters, as the init record gives them and as the chip holds "
        "them; set any of them with the flags; --save-init writes a record to start from.",
    ),
    Command(
        "serve",
        "biris_hw.commands.serve",
        "run the sensor as a network service (Zenoh) for other programs",
        "Start the server on --sim, --target or --attach and serve it on Zenoh as --name on the "
        "--listen endpoints until Ctrl-C or SIGTERM; other programs use it with --connect NAME, "
        "and those with controller credentials (--credentials FILE) may command it. It logs to "
        "stderr (the journal under systemd); --auto-reset N resets the sensor after a fault.",
        service=True,
    ),
    Command(
        "reset",
        "biris_hw.commands.reset",
        "reset a served sensor after a fault (a controller's request)",
        "Ask the service --connect NAME to reset its sensor (re-run its initialisation: the way "
        "back from a fault), as one of its controllers; exit 0 once the sensor is back.",
    ),
    Command(
        "list",
        "biris_hw.commands.list_services",
        "the services reachable, with name and state",
        "List the BIRIS services reachable by multicast scouting or on --endpoint (or "
        "$BIRIS_ENDPOINT, the profile's): name, state, whether a controller is connected, "
        "clients, and whether each serves a sensor or a recording.",
    ),
    Command(
        "record",
        "biris_hw.commands.record",
        "record the sensor to MCAP (ROS 2 message types)",
        "Record scans, profiles, transforms and status to an MCAP file (ros2 bag, Foxglove, "
        "Lichtblick) while sweeping (--cw/--ccw), scanning once (--to) or just listening.",
    ),
    Command(
        "replay",
        "biris_hw.commands.replay",
        "play a recording back as a sensor",
        "Serve an MCAP recording through the client API; print, --json or --plot its scans, "
        "or --check them against the scan invariants (a .npz scan file too).",
    ),
    Command(
        "grid",
        "biris_hw.commands.grid",
        "the certainty grid from a recording or a simulated drive",
        "Build the 2-D certainty grid (occupancy in the odom frame) from a recording's scans and "
        "poses, or from the simulator (--sim, with --drive: its default drive through the room, "
        "scored against the scene's truth); print what went in and came out, --plot draws it.",
    ),
    Command(
        "view",
        "biris_hw.commands.view",
        "live view in Foxglove or Lichtblick (WebSocket)",
        "Serve the sensor (or --replay FILE) as a Foxglove WebSocket on --port; open the URL it "
        "prints (Lichtblick 1.22.1 or later, or Foxglove).",
    ),
    Command(
        "sim",
        "sim.process",
        "run the simulator as a process other programs can reach",
        "Run the BIRIS simulator in its own process, its windows in shared memory.",
    ),
    Command(
        "regdump",
        "biris_hw.regdump",
        "decode the registers of a target image (file, mmap or shared memory)",
        "Decode the coupler, Model 7600 and BIRIS registers of a target image.",
    ),
)


class _Module(Protocol):
    def add_arguments(self, parser: argparse.ArgumentParser) -> None: ...

    def run(self, args: argparse.Namespace) -> int: ...


class _OneLineParser(argparse.ArgumentParser):
    """Reports a usage error as one line (``biris scan: ...``) and exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: {message}\n")


class _Unavailable(Exception):
    """The chosen command's module cannot be imported (an optional part is not installed)."""


def _chosen(argv: Sequence[str]) -> str | None:
    """The subcommand named on the command line: the first word that is not an option."""
    for word in argv:
        if word == "--":
            return None
        if not word.startswith("-"):
            return word
    return None


def _load(command: Command) -> _Module:
    try:
        return cast(_Module, importlib.import_module(command.module))
    except ModuleNotFoundError as exc:
        if exc.name is not None and command.module.startswith(exc.name):
            raise _Unavailable(
                f"not available in this installation ({command.module} is missing)"
            ) from exc
        raise


def build_parser(chosen: str | None = None) -> argparse.ArgumentParser:
    """The parser for a command line that names ``chosen``: only that command's module is
    imported to declare its flags, and when ``chosen`` is a command only its parser is made (a
    line names one; argparse spends most of making a parser in message-catalogue lookups, 6 ms
    for all sixteen against 1 ms for one). Without a command (``biris --help``) or with a
    mistyped one, every command's parser is made, for the list and the "invalid choice"."""
    parser = _OneLineParser(
        prog="biris",
        description="Driver, server and simulator for the NRC BIRIS laser range camera.",
        epilog="biris COMMAND --help shows a command's flags. Exit status: 0 done, 1 hardware "
        "fault, 2 usage or configuration error, 130 interrupted (Ctrl-C), 143 terminated "
        "(SIGTERM).",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks and the log")
    parser.add_argument("--version", action="version", version=f"biris-hw {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_OneLineParser)
    named = any(command.name == chosen for command in COMMANDS)
    for command in COMMANDS:
        if named and command.name != chosen:
            continue
        child = sub.add_parser(command.name, help=command.summary, description=command.description)
        if command.name == chosen:
            from biris_hw.commands.options import add_debug_argument

            module = _load(command)
            module.add_arguments(child)
            with contextlib.suppress(argparse.ArgumentError):  # the module may declare it
                add_debug_argument(child)
            child.set_defaults(run=module.run)
    return parser


class _TermAsInterrupt:
    """While the block runs, SIGTERM is Ctrl-C: the first one raises
    :class:`~biris_hw.commands.failures.Terminated` (a KeyboardInterrupt) in the main thread, so
    the command ends by the path it has for Ctrl-C (a recording closed complete, a sweep
    stopped, a summary printed) and :attr:`received` says it was SIGTERM.

    Later SIGTERMs are ignored while that path runs: a supervisor may send the signal again,
    and an interrupt in the middle of a recorder's or a service's close would leave a file
    without its summary, or threads up (SIGKILL remains for a command that hangs). Outside the
    main thread (a test, an embedding program) nothing is installed: signals reach the main
    thread only. The previous handler is back when the block ends.
    """

    def __init__(self) -> None:
        self.received = False
        self._previous: Any = None
        self._installed = False

    def _on_term(self, signum: int, frame: FrameType | None) -> None:
        if self.received:
            return
        self.received = True
        raise Terminated

    def __enter__(self) -> _TermAsInterrupt:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGTERM, self._on_term)
            self._installed = True
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._installed:
            signal.signal(signal.SIGTERM, self._previous)
            self._installed = False

    def status(self, code: int) -> int:
        """The command's exit status, 143 for an interruption SIGTERM caused."""
        return EXIT_TERMINATED if self.received and code == EXIT_INTERRUPTED else code


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``biris``; returns the exit status (the console script exits with it)."""
    words = list(sys.argv[1:] if argv is None else argv)
    chosen = _chosen(words)
    prog = f"biris {chosen}" if chosen in {c.name for c in COMMANDS} else "biris"
    debug = "--debug" in words
    try:
        parser = build_parser(chosen)
    except _Unavailable as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as exc:  # the command's module failed to import
        return report_error(prog, exc, debug=debug)
    try:
        args, extra = parser.parse_known_args(words)
    except SystemExit as exc:  # --help, --version, or a usage error already reported
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    if extra:  # named after the command they were given to, not "biris"
        print(f"{prog}: unrecognized arguments: {' '.join(extra)}", file=sys.stderr)
        return EXIT_USAGE
    run = cast("Callable[[argparse.Namespace], int] | None", getattr(args, "run", None))
    if run is None:
        print("biris: say which command to run (biris --help lists them)", file=sys.stderr)
        return EXIT_USAGE
    debug = bool(getattr(args, "debug", False))
    service = any(c.service for c in COMMANDS if c.name == chosen)
    progress = wants_progress(args) and not service  # a service's log says it already
    with (
        log_to_stderr(debug, service=service),
        progress_to_stderr(prog, progress),
        _TermAsInterrupt() as term,
    ):
        try:
            return term.status(int(run(args)))
        except KeyboardInterrupt:
            return term.status(EXIT_INTERRUPTED)
        except Exception as exc:
            return report_error(prog, exc, debug=debug)


if __name__ == "__main__":
    sys.exit(main())
