"""What every ``biris`` subcommand shares: where the sensor is, how to open it, how to fail.

Every command that talks to the sensor takes the same flags, so that a person who learned one
knows them all: ``--sim`` (with ``--scene``, ``--samples``, ``--time-scale``, ``--seed``),
``--target FILE`` or ``--attach NAME`` (a ``biris sim`` process), ``--init FILE`` and
``--debug``. :func:`open_session` turns them into a
running :class:`~biris_hw.BirisServer` and takes everything down again, in order, however the
command ends.

Errors are for people: one line on stderr, ``biris <command>: <what went wrong>``, and an exit
status a script can act on. 2 means "fix what you asked for" (a flag, a file, a device node or its
permissions), 1 means "the hardware failed" (a fault, a bus error while running, no answer in
time), 130 is Ctrl-C. ``--debug`` adds the traceback and the driver's log.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import traceback
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, TextIO

from biris_hw.commands.argtypes import SIM_DEFAULTS, add_simulator_arguments, path, seconds
from biris_hw.errors import (
    BirisError,
    BusError,
    ConnectionClosed,
    HardwareFault,
    RequestError,
    UnknownKind,
)
from biris_hw.hardware import BirisHardware
from biris_hw.records import BirisInitRecord
from biris_hw.server import BirisServer

if TYPE_CHECKING:
    from sim import Scene, SimulatedBiris

__all__ = [
    "DEFAULT_TIME_SCALE",
    "EXIT_FAULT",
    "EXIT_INTERRUPTED",
    "EXIT_USAGE",
    "TARGET_ENV",
    "AuditFailure",
    "Session",
    "SetupError",
    "UsageError",
    "add_debug_argument",
    "add_target_arguments",
    "add_timeout_argument",
    "check_target_arguments",
    "error_line",
    "exit_status",
    "is_terminal",
    "log_to_stderr",
    "make_scene",
    "open_session",
    "report_error",
]

EXIT_FAULT = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

TARGET_ENV = "BIRIS_TARGET"
"""A target file to use when neither --sim nor --target is given: set once on the robot."""

DEFAULT_TIME_SCALE = 4.0
"""The simulator's default speed: four hardware seconds per real second keeps a sweep readable
on screen while initialisation (which turns the head to find its zero index) stays short."""

DEFAULT_WAIT_S = 60.0


class UsageError(BirisError, ValueError):
    """The command line asks for something impossible (exit 2)."""


class SetupError(BirisError):
    """The sensor could not be reached as described: a target or init file, a device node, its
    permissions (exit 2: something on this side must be fixed, the hardware has not failed)."""


class AuditFailure(BirisError):
    """The simulator recorded a hardware rule the driver broke (exit 1: a driver bug)."""


def make_scene(spec: str) -> Scene:
    """The simulator's scene for a ``--scene`` value (:meth:`sim.Scene.from_spec`)."""
    from sim import Scene

    return Scene.from_spec(spec)


# -- flags -----------------------------------------------------------------------------------------


def add_debug_argument(parser: argparse.ArgumentParser) -> None:
    """``--debug`` after the command too; SUPPRESS keeps ``biris --debug cmd`` from being reset."""
    parser.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="show tracebacks and the driver's log on stderr",
    )


def add_target_arguments(parser: argparse.ArgumentParser) -> None:
    """The sensor to use and how to start its server: the flags every hardware command takes."""
    where = parser.add_argument_group("sensor")
    choice = where.add_mutually_exclusive_group()
    choice.add_argument("--sim", action="store_true", help="use the simulator")
    choice.add_argument(
        "--target",
        type=path,
        metavar="FILE",
        help=f"a real VME target described in TOML (default: ${TARGET_ENV})",
    )
    choice.add_argument(
        "--attach",
        metavar="NAME",
        help="a simulator process started with `biris sim --shm NAME`",
    )
    where.add_argument(
        "--init",
        type=path,
        metavar="FILE",
        help="server init record (TOML; default: the report's)",
    )
    sim = parser.add_argument_group("simulator (with --sim)")
    add_simulator_arguments(sim, default_time_scale=DEFAULT_TIME_SCALE, deferred=True)
    add_debug_argument(parser)


def add_timeout_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--timeout",
        type=seconds,
        default=DEFAULT_WAIT_S,
        metavar="S",
        help=f"give up after S real seconds without an answer (default {DEFAULT_WAIT_S:g})",
    )


_SIM_ONLY = ("scene", "samples", "time_scale", "seed")


def check_target_arguments(args: argparse.Namespace) -> None:
    """Resolve --sim / --target / $BIRIS_TARGET and the simulator's defaults, in place."""
    attach = getattr(args, "attach", None)
    if not args.sim and args.target is None and attach is None:
        args.target = os.environ.get(TARGET_ENV) or None
        if args.target is None:
            raise UsageError(
                f"say which sensor to use: --sim, --target FILE or --attach NAME "
                f"(or set {TARGET_ENV})"
            )
    if args.sim:
        defaults = {**SIM_DEFAULTS, "time_scale": DEFAULT_TIME_SCALE}
        for key, value in defaults.items():
            if getattr(args, key) is None:
                setattr(args, key, value)
    else:
        given = [key for key in _SIM_ONLY if getattr(args, key, None) is not None]
        if given:
            flag = "--" + given[0].replace("_", "-")
            raise UsageError(f"{flag} only applies to the in-process simulator (--sim)")


# -- sessions --------------------------------------------------------------------------------------


@dataclass
class Session:
    """A running server on a sensor, as a command sees it."""

    server: BirisServer
    hardware: BirisHardware
    record: BirisInitRecord
    rig: SimulatedBiris | None = None
    """The simulator, with --sim: its scene, true azimuth and audit."""


def _load_record(file: str | os.PathLike[str] | None) -> BirisInitRecord:
    if file is None:
        return BirisInitRecord()
    try:
        return BirisInitRecord.load(file)
    except OSError as exc:
        raise SetupError(f"cannot read init record {file}: {exc.strerror or exc}") from exc
    except RequestError as exc:
        raise SetupError(str(exc)) from exc


def _open_target(file: str | os.PathLike[str]) -> BirisHardware:
    from biris_hw.target import load_target

    try:
        return load_target(file)
    except BusError as exc:
        raise SetupError(f"cannot open the target: {exc}") from exc
    except OSError as exc:
        raise SetupError(f"cannot read target file {file}: {exc.strerror or exc}") from exc
    except RequestError as exc:
        raise SetupError(str(exc)) from exc


def _attach(name: str) -> BirisHardware:
    from biris_hw.remote import attach

    try:
        return attach(name)
    except OSError as exc:
        raise SetupError(f"cannot attach to simulator {name!r}: {exc.strerror or exc}") from exc


def _start_rig(args: argparse.Namespace) -> SimulatedBiris:
    from sim import SimulatedBiris

    return SimulatedBiris(
        scene=make_scene(args.scene),
        samples=args.samples,
        time_scale=args.time_scale,
        seed=args.seed,
    ).start()


@contextlib.contextmanager
def open_session(args: argparse.Namespace) -> Iterator[Session]:
    """Start the sensor (simulator or target) and a server on it; stop both on the way out.

    The server is closed before the hardware under it. With --sim the audit is read last:
    a rule the driver broke makes the command fail (:class:`AuditFailure`) even if it got
    its data, because such a run would have misused real hardware.
    """
    check_target_arguments(args)
    record = _load_record(args.init)
    rig: SimulatedBiris | None = None
    with contextlib.ExitStack() as stack:
        if args.target is not None:
            hardware = _open_target(args.target)
            stack.callback(hardware.close)
        elif getattr(args, "attach", None) is not None:
            hardware = _attach(args.attach)
            stack.callback(hardware.close)
        else:
            rig = _start_rig(args)
            stack.callback(rig.close)
            hardware = rig.hardware
        server = BirisServer(hardware, record)
        stack.callback(server.close)
        yield Session(server, hardware, record, rig)
    if rig is not None and rig.audit.violations:
        found = rig.audit.violations
        raise AuditFailure(
            f"the simulator's audit recorded {len(found)} driver rule violation(s); "
            f"first: {found[0]}"
        )


# -- output and errors -----------------------------------------------------------------------------


def is_terminal(stream: TextIO) -> bool:
    """True when a person is watching ``stream`` (live displays), False for pipes and files."""
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def exit_status(exc: BaseException) -> int:
    """2 for what the user must fix, 1 for what the hardware did, 130 for Ctrl-C."""
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    if isinstance(exc, (UsageError, SetupError, RequestError, UnknownKind, ModuleNotFoundError)):
        return EXIT_USAGE
    if isinstance(exc, (HardwareFault, AuditFailure, ConnectionClosed, BusError, TimeoutError)):
        return EXIT_FAULT
    if isinstance(exc, OSError):  # a file we were asked to write or read
        return EXIT_USAGE
    return EXIT_FAULT


def error_line(exc: BaseException) -> str:
    """One line that says what went wrong, in the user's terms."""
    if isinstance(exc, HardwareFault):
        text = f"hardware fault ({exc.kind}): {exc.message}"
    elif isinstance(exc, TimeoutError):
        text = f"no answer in time: {exc}" if str(exc) else "no answer in time"
    elif isinstance(exc, ModuleNotFoundError):
        text = str(exc) if exc.name and "pip install" in str(exc) else _missing_module(exc)
    elif isinstance(exc, OSError) and not isinstance(exc, BirisError) and exc.strerror:
        where = f"{exc.filename}: " if exc.filename else ""
        text = f"{where}{exc.strerror}"
    else:
        text = str(exc).strip()
    known = (BirisError, OSError, TimeoutError, ModuleNotFoundError)
    if not isinstance(exc, known):
        text = f"internal error: {type(exc).__name__}: {text} (--debug shows where)"
    lines = text.splitlines()
    return lines[0] if lines and lines[0] else type(exc).__name__


def _missing_module(exc: ModuleNotFoundError) -> str:
    name = exc.name or "a module"
    if name.split(".")[0] in ("matplotlib", "rich"):
        return f"{name} is not installed: pip install 'biris-hw[demo]'"
    return f"{name} is not installed"


def report_error(prog: str, exc: BaseException, *, debug: bool, err: TextIO | None = None) -> int:
    """Print ``prog: message`` (after the traceback with --debug) and return the exit status."""
    stream = err or sys.stderr
    if debug:
        traceback.print_exception(type(exc), exc, exc.__traceback__, file=stream)
    print(f"{prog}: {error_line(exc)}", file=stream)
    stream.flush()
    return exit_status(exc)


@contextlib.contextmanager
def log_to_stderr(debug: bool) -> Iterator[None]:
    """The driver's log on stderr with --debug; silence otherwise.

    Without a handler Python prints warnings to stderr by itself, which would add lines to the
    one-line error contract and scribble over live displays; the command reports what matters.
    """
    loggers = [logging.getLogger(name) for name in ("biris_hw", "sim")]
    handler: logging.Handler
    if debug:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(relativeCreated)8.0f ms %(name)s: %(message)s"))
    else:
        handler = logging.NullHandler()
    saved: list[tuple[logging.Logger, int]] = []
    for logger in loggers:
        saved.append((logger, logger.level))
        logger.addHandler(handler)
        if debug:
            logger.setLevel(logging.DEBUG)
    try:
        yield
    finally:
        for logger, level in saved:
            logger.removeHandler(handler)
            logger.setLevel(level)
