"""What every ``biris`` subcommand shares: where the sensor is, how to open it, how to fail.

Every command that talks to the sensor takes the same flags, so that a person who learned one
knows them all: ``--sim`` (with ``--scene``, ``--samples``, ``--time-scale``, ``--seed``),
``--target FILE`` or ``--attach NAME`` (a ``biris sim`` process), ``--init FILE``, ``--quiet``
and ``--debug``; those that acquire take ``--continuous``, those that move the head ``--yes``.
:func:`open_session` turns them into a running :class:`~biris_hw.BirisServer` and takes
everything down again, in order, however the command ends.

A command respects the person running it: it says what it is waiting for (the server's progress
log, :func:`progress_to_stderr`, while a terminal watches), checks the files it will write before
it touches the sensor (:func:`check_output_file`, :func:`check_output_folder`), says when an angle
was clamped (:func:`note_clamped`), asks before turning a real head more than half a turn
(:func:`confirm_moves`), and says when the simulator cannot keep up with its time scale
(:class:`LagWatch`).

Errors are for people: one line on stderr, ``biris <command>: <what went wrong>``, and an exit
status a script can act on. 2 means "fix what you asked for" (a flag, a file, a device node or its
permissions), 1 means "the hardware failed" (a fault, a bus error while running, no answer in
time), 130 is Ctrl-C. ``--debug`` adds the traceback and the driver's log.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import logging
import os
import re
import sys
import threading
import traceback
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TextIO

from biris_hw.angles import counts_to_deg, deg_to_counts
from biris_hw.client import Sensor
from biris_hw.commands.argtypes import (
    DEFAULT_TIME_SCALE,
    SIM_DEFAULTS,
    add_simulator_arguments,
    path,
    seconds,
    time_scale_warning,
)
from biris_hw.errors import (
    AccessDenied,
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
from regs.biexec import BiCommand
from regs.hctl1000 import COUNTS_PER_REV

if TYPE_CHECKING:
    from sim import Scene, SimulatedBiris

__all__ = [
    "DEFAULT_TIME_SCALE",
    "EXIT_FAULT",
    "EXIT_INTERRUPTED",
    "EXIT_USAGE",
    "HALF_TURN_COUNTS",
    "LAG_CHECK_S",
    "LINK_PASSWORD_ENV",
    "PASSWORD_ENV",
    "PROGRESS_LOGGER",
    "TARGET_ENV",
    "AuditFailure",
    "LagWatch",
    "Lagging",
    "Sensor",
    "Session",
    "SetupError",
    "UsageError",
    "add_continuous_argument",
    "add_debug_argument",
    "add_quiet_argument",
    "add_service_client_arguments",
    "add_target_arguments",
    "add_timeout_argument",
    "add_yes_argument",
    "check_output_file",
    "check_output_folder",
    "check_target_arguments",
    "confirm_moves",
    "error_line",
    "exit_status",
    "is_terminal",
    "log_to_stderr",
    "make_scene",
    "note_clamped",
    "open_session",
    "parse_zenoh_options",
    "prog_of",
    "progress_to_stderr",
    "read_toml",
    "report_error",
    "stderr_is_terminal",
    "sweep_chosen",
    "wants_progress",
]

EXIT_FAULT = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

PASSWORD_ENV = "BIRIS_PASSWORD"
"""With ``--user``: the controller's password (never on the command line, where ``ps`` shows it)."""

LINK_PASSWORD_ENV = "BIRIS_LINK_PASSWORD"
"""With ``--link-user``: the password of Zenoh's link authentication (never on the command line)."""

TARGET_ENV = "BIRIS_TARGET"
"""A target file to use when neither --sim nor --target is given: set once on the robot."""

DEFAULT_WAIT_S = 60.0

PROGRESS_LOGGER = "biris_hw.progress"
"""The logger on which the server says, in a short sentence per INFO record, what it is doing
while a caller waits (homing the pan, booting BIRIS...): what a person sees during the seconds
a server takes to start."""

HALF_TURN_COUNTS = COUNTS_PER_REV // 2
"""A move longer than this (180 degrees) on a real head asks for ``--yes``."""

LAG_CHECK_S = 0.25
"""Real seconds between two looks at whether the simulator keeps up (:class:`LagWatch`)."""


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


def add_target_arguments(parser: argparse.ArgumentParser, *, remote: bool = True) -> None:
    """The sensor to use and how to start its server: the flags every hardware command takes.

    ``remote``: also ``--connect NAME`` and its flags (a running service instead of a server of
    our own); ``biris serve``, which is the service, says False.
    """
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
    if remote:
        choice.add_argument(
            "--connect",
            metavar="NAME",
            help="a running sensor service (`biris serve --name NAME`) instead of a server of "
            "our own",
        )
        add_service_client_arguments(parser)
    where.add_argument(
        "--init",
        type=path,
        metavar="FILE",
        help="server init record (TOML; default: the report's)",
    )
    sim = parser.add_argument_group("simulator (with --sim)")
    add_simulator_arguments(sim, default_time_scale=DEFAULT_TIME_SCALE, deferred=True, clocks=True)
    add_quiet_argument(parser)
    add_debug_argument(parser)


def add_service_client_arguments(parser: argparse.ArgumentParser) -> None:
    """How to reach a service with ``--connect``: endpoints, credentials, TLS (no passwords on
    the command line: a file, or ``$BIRIS_PASSWORD`` with ``--user``)."""
    net = parser.add_argument_group("service (with --connect)")
    net.add_argument(
        "--endpoint",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint of the service, e.g. tcp/robot:7447 (repeatable; default: "
        "found by multicast scouting)",
    )
    net.add_argument(
        "--user",
        metavar="USER",
        help=f"controller's user name; the password is read from ${PASSWORD_ENV}",
    )
    net.add_argument(
        "--credentials",
        type=path,
        metavar="FILE",
        help='controller\'s credentials, a TOML file: user = "...", password = "..."',
    )
    net.add_argument(
        "--tls-ca",
        type=path,
        metavar="FILE",
        help="root CA certificate (PEM) for a tls/ endpoint",
    )
    net.add_argument(
        "--read-credentials",
        action="store_true",
        help="send the credentials with reads too, for a service that requires reader "
        "credentials (default: only with motion and configuration)",
    )
    net.add_argument(
        "--link-user",
        metavar="USER",
        help="user of Zenoh's link authentication (a hardened service's "
        f"transport/auth/usrpwd); the password is read from ${LINK_PASSWORD_ENV} or "
        "--link-password-file",
    )
    net.add_argument(
        "--link-password-file",
        type=path,
        metavar="FILE",
        help="file holding the link password (its first line), for --link-user",
    )
    net.add_argument(
        "--zenoh-option",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="any Zenoh setting of the client, e.g. transport/link/tls/enable_mtls=true "
        "(repeatable; no passwords: see --link-user)",
    )


_SECRET_OPTION = re.compile(r"password", re.IGNORECASE)


def parse_zenoh_options(items: Sequence[str]) -> dict[str, Any]:
    """``KEY=JSON`` items (``--zenoh-option``) as Zenoh options; a bare word is a string.

    Raises:
        UsageError: an item without ``=``, or one that would put a password on the command
            line (where ``ps`` shows it to every user).
    """
    import json

    options: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UsageError(f"--zenoh-option {item!r}: expected KEY=JSON")
        if _SECRET_OPTION.search(key):
            raise UsageError(
                f"--zenoh-option {key}: no passwords on the command line (every user's `ps` "
                f"shows them); use --link-user with ${LINK_PASSWORD_ENV} or "
                "--link-password-file, or a dictionary file on the service"
            )
        try:
            options[key] = json.loads(value)
        except ValueError:
            options[key] = value
    return options


def _link_options(args: argparse.Namespace) -> dict[str, str]:
    """Zenoh's link user and password (``--link-user``), the password from a file or env."""
    user = getattr(args, "link_user", None)
    file = getattr(args, "link_password_file", None)
    if user is None:
        if file is not None:
            raise UsageError("--link-password-file goes with --link-user")
        return {}
    if file is not None:
        try:
            lines = Path(file).read_text(encoding="utf-8").splitlines()
        except OSError as exc:
            raise SetupError(f"cannot read {file}: {exc.strerror or exc}") from exc
        password = lines[0].strip() if lines else ""
    else:
        password = os.environ.get(LINK_PASSWORD_ENV, "")
    if not password:
        where = str(file) if file is not None else f"${LINK_PASSWORD_ENV}"
        raise UsageError(f"--link-user {user} needs the link password in {where}")
    return {"transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": password}


def add_quiet_argument(parser: argparse.ArgumentParser) -> None:
    """``--quiet``: no progress lines on stderr (errors and warnings are still said)."""
    parser.add_argument(
        "--quiet",
        action="store_true",
        help="no progress lines on stderr while waiting (shown only when stderr is a terminal)",
    )


def add_continuous_argument(parser: argparse.ArgumentParser) -> None:
    """``--continuous``: Appendix D's continuous acquisition for this run (see open_session)."""
    parser.add_argument(
        "--continuous",
        action="store_true",
        help="Appendix D's continuous acquisition: BIRIS started once and acquiring until "
        "stopped (default: the report's BI_ACQUIRE per scan)",
    )


def sweep_chosen(args: argparse.Namespace) -> bool:
    """Whether the command was asked to sweep (``--cw``/``--ccw``) rather than scan once
    (``--to``), checked the same way for every command that moves the head.

    Raises:
        UsageError: ``--to`` with ``--cw``/``--ccw``, one limit without the other, or ``--cw``
            not clockwise of (below) ``--ccw``.
    """
    sweep = args.cw is not None or args.ccw is not None
    if getattr(args, "to", None) is not None and sweep:
        raise UsageError("give either --to, or --cw and --ccw, not both")
    if sweep and (args.cw is None or args.ccw is None):
        raise UsageError("sweeping needs both --cw and --ccw")
    if sweep and args.cw >= args.ccw:
        raise UsageError(f"--cw ({args.cw:g}) must lie clockwise of (below) --ccw ({args.ccw:g})")
    return sweep


def add_yes_argument(parser: argparse.ArgumentParser) -> None:
    """``--yes``: allow a move of more than half a turn on a real head (:func:`confirm_moves`)."""
    parser.add_argument(
        "--yes",
        action="store_true",
        help="on a real target, allow a move of more than half a turn (180 deg) from where "
        "the head stands (the simulator never asks)",
    )


def add_timeout_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--timeout",
        type=seconds,
        default=DEFAULT_WAIT_S,
        metavar="S",
        help=f"give up after S real seconds without an answer (default {DEFAULT_WAIT_S:g})",
    )


_SIM_ONLY = ("scene", "samples", "time_scale", "seed", "clock")

_REAL_TIME_COMMANDS = frozenset({"serve", "view", "watch", "record", "demo"})
"""Commands that run for as long as someone watches: their simulator keeps scaled time (a
virtual clock would run the idle sensor's fields at the CPU's speed, and a network peer or a
viewer lives in real time)."""


def check_target_arguments(args: argparse.Namespace) -> None:
    """Resolve --sim / --target / $BIRIS_TARGET and the simulator's defaults, in place."""
    attach = getattr(args, "attach", None)
    if getattr(args, "connect", None) is not None:
        given = [key for key in (*_SIM_ONLY, "init") if getattr(args, key, None) is not None]
        if given:
            flag = "--" + given[0].replace("_", "-")
            raise UsageError(f"{flag} does not apply to a running service (--connect)")
        return
    if getattr(args, "endpoint", None) or getattr(args, "user", None):
        raise UsageError("--endpoint and --user go with --connect NAME")
    for flag in ("link_user", "link_password_file", "zenoh_option", "read_credentials"):
        if getattr(args, flag, None):
            raise UsageError(f"--{flag.replace('_', '-')} goes with --connect NAME")
    if not args.sim and args.target is None and attach is None:
        args.target = os.environ.get(TARGET_ENV) or None
        if args.target is None:
            raise UsageError(
                f"say which sensor to use: --sim, --target FILE or --attach NAME "
                f"(or set {TARGET_ENV})"
            )
    if args.sim and getattr(args, "clock", None) == "virtual":
        command = getattr(args, "command", None)
        if command in _REAL_TIME_COMMANDS:
            raise UsageError(
                f"--clock virtual does not apply to biris {command}: it serves or shows the "
                "sensor as time passes, which a person (or a network peer) watches in real time"
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

    server: Sensor
    """The sensor: a server of this command's own, or a running service (--connect)."""
    hardware: BirisHardware | None
    """The hardware under a server of our own; None through a service."""
    record: BirisInitRecord
    rig: SimulatedBiris | None = None
    """The simulator, with --sim: its scene, true azimuth and audit."""
    simulated: bool = True
    """A simulator (--sim, or a ``biris sim`` process with --attach), not a real head: nothing
    breaks if it turns a long way, so it is never asked for --yes."""
    prog: str = "biris"
    """``biris <command>``: what the command's own lines on stderr start with."""
    remote: bool = False
    """Through a running service (--connect): the record is the default one, not the
    service's, and the server is not ours to home or stop."""


def prog_of(args: argparse.Namespace) -> str:
    """``biris scan`` for a scan's arguments (the dispatcher records the command's name)."""
    name = getattr(args, "command", None)
    return f"biris {name}" if name else "biris"


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
    from biris_hw.simlink import attach

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
        clock=getattr(args, "clock", None) or "scaled",
    ).start()


@contextlib.contextmanager
def open_session(args: argparse.Namespace) -> Iterator[Session]:
    """Start the sensor (simulator or target) and a server on it; stop both on the way out.

    ``--continuous`` builds the server with Appendix D's continuous acquisition
    (``BirisInitRecord.continuous_acquisition``) on top of whatever ``--init`` says, so it works
    the same on every sensor. The server is closed before the hardware under it. With --sim a
    :class:`LagWatch` says if the host cannot keep up with the time scale, and the audit is
    read last: a rule the driver broke makes the command fail (:class:`AuditFailure`) even if
    it got its data, because such a run would have misused real hardware. A ``timeout`` fault
    leaves naming the BIRIS command that was not answered (:func:`_name_unanswered`).
    """
    check_target_arguments(args)
    if getattr(args, "connect", None) is not None:
        with _connect(args) as session:
            yield session
        return
    record = _load_record(args.init)
    if getattr(args, "continuous", False):
        record = dataclasses.replace(record, continuous_acquisition=True)
    prog = prog_of(args)
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
            watch = LagWatch(rig, prog)
            watch.start()
            stack.callback(watch.stop)
        try:
            server = BirisServer(hardware, record)
            stack.callback(server.close)
            yield Session(server, hardware, record, rig, args.target is None, prog)
        except HardwareFault as exc:
            named = _name_unanswered(exc, hardware)
            if named is exc:
                raise
            raise named from exc
    if rig is not None and rig.audit.violations:
        found = rig.audit.violations
        raise AuditFailure(
            f"the simulator's audit recorded {len(found)} driver rule violation(s); "
            f"first: {found[0]}"
        )


def quiet_collector() -> None:
    """Take what a command has built to run (modules, the server, a simulator's scene) out of
    the cyclic garbage collector's reach: a full collection over it stalled the data path for
    40-75 ms on a quiet machine and 100-180 ms on a busy one (``make bench``'s streaming p99),
    and after ``gc.freeze()`` it costs under a millisecond. Done by the long-running commands
    (serve, view, watch, record, demo) once their sensor is open: one process, one sensor; a
    one-shot command would pay the collection for nothing, and a library user decides this for
    their own program."""
    gc.collect()
    gc.freeze()


def _credentials(args: argparse.Namespace) -> tuple[str | None, str | None]:
    """(user, password) from --credentials FILE or --user and $BIRIS_PASSWORD, or (None, None)."""
    file = getattr(args, "credentials", None)
    user = getattr(args, "user", None)
    if file is not None:
        table = read_toml(file)
        found_user, password = table.get("user"), table.get("password")
        if not isinstance(found_user, str) or not isinstance(password, str):
            raise SetupError(f'{file}: needs user = "..." and password = "..."')
        if user is not None and user != found_user:
            raise UsageError(f"--user {user} disagrees with {file} (user {found_user})")
        return found_user, password
    if user is not None:
        password = os.environ.get(PASSWORD_ENV)
        if not password:
            raise UsageError(f"--user {user} needs the password in ${PASSWORD_ENV}")
        return user, password
    return None, None


def read_toml(file: str | os.PathLike[str]) -> dict[str, Any]:
    """A TOML file's table (credentials files); SetupError naming the file if it cannot be."""
    if sys.version_info >= (3, 11):
        import tomllib
    else:  # tomli is a declared dependency below 3.11
        import tomli as tomllib  # type: ignore[import-not-found, unused-ignore]
    try:
        with open(file, "rb") as stream:
            table: dict[str, Any] = tomllib.load(stream)
    except OSError as exc:
        raise SetupError(f"cannot read {file}: {exc.strerror or exc}") from exc
    except ValueError as exc:  # tomllib.TOMLDecodeError
        raise SetupError(f"{file}: not TOML: {exc}") from exc
    return table


@contextlib.contextmanager
def _connect(args: argparse.Namespace) -> Iterator[Session]:
    """A session on a running service: nothing is started, homed or stopped on the way out."""
    try:
        from biris_hw.io.net import RemoteSensor, tls_options
    except ImportError as exc:
        raise SetupError(
            f"--connect needs the net extra (pip install 'biris-hw[net]'): {exc}"
        ) from exc
    user, password = _credentials(args)
    ca = getattr(args, "tls_ca", None)
    options: dict[str, Any] = tls_options(root_ca=str(ca)) if ca is not None else {}
    options.update(parse_zenoh_options(getattr(args, "zenoh_option", None) or []))
    options.update(_link_options(args))
    try:
        remote = RemoteSensor(
            args.connect,
            getattr(args, "endpoint", None),
            user,
            password,
            options=options or None,
            reader_credentials=bool(getattr(args, "read_credentials", False)),
        )
    except ConnectionClosed as exc:
        raise SetupError(str(exc)) from exc
    with remote:
        yield Session(remote, None, BirisInitRecord(), None, False, prog_of(args), remote=True)


def _name_unanswered(exc: HardwareFault, hardware: BirisHardware) -> HardwareFault:
    """A ``timeout`` fault, naming the BIRIS command that was not answered if it does not.

    The server's message says what it waited for; if it names no command (an older server,
    or a wait the message does not describe), BIRIS's COMMAND register still holds the one it
    never finished, and a person needs its name (BI_STOP_CONTINUOUS), not its code, to know
    what the sensor was doing. Reading COMMAND has no side effect; if even that fails, the
    fault stays as it was.
    """
    if exc.kind != "timeout" or _COMMAND_NAME.search(exc.message):
        return exc
    try:
        code = hardware.devices.link.command()
    except (BirisError, OSError):
        return exc
    if code == 0:
        return exc
    return HardwareFault(exc.kind, f"{exc.message} (waiting for BIRIS to finish {_bi_name(code)})")


def _bi_name(code: int) -> str:
    try:
        return BiCommand(code).name
    except ValueError:
        return f"unknown BIRIS command {code}"


_COMMAND_NAME = re.compile(r"\bBI_[A-Z_]+")
_COMMAND_CODE = re.compile(r"\b(COMMAND|command) (0x[0-9A-Fa-f]+|\d+)\b")


# -- what a person is told ---------------------------------------------------------------------


class Lagging(Protocol):
    """What :class:`LagWatch` reads of a simulator (:class:`sim.SimulatedBiris` has it)."""

    @property
    def time_scale(self) -> float: ...

    @property
    def lag_bound_s(self) -> float: ...

    def lag_s(self) -> float: ...

    def behind(self) -> bool: ...


class LagWatch:
    """Says once, on stderr, that the simulator cannot keep up with its time scale.

    A time scale is a promise that a hardware second takes ``1/scale`` real seconds; past what
    the host can compute, the simulator runs late (:meth:`sim.SimulatedBiris.lag_s`) and the
    driver's hardware-time deadlines stop meaning what they mean on the robot. The run goes
    on (it may still be what the person wanted) but they are told, once. A thread of its own
    looks every :data:`LAG_CHECK_S` and needs two looks in a row beyond the bound, so that one
    stall of a busy host is not called falling behind.
    """

    def __init__(
        self,
        rig: Lagging,
        prog: str,
        *,
        every_s: float | None = None,
        err: TextIO | None = None,
    ) -> None:
        self._rig = rig
        self._prog = prog
        self._every = LAG_CHECK_S if every_s is None else every_s
        self._err = err
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.warned = False

    def start(self) -> LagWatch:
        self._thread = threading.Thread(target=self._run, name="biris-lag-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _run(self) -> None:
        behind_before = False
        while not self._stop.wait(self._every):
            behind = self._rig.behind()
            if behind and behind_before:
                self.warn()
                return
            behind_before = behind

    def warn(self) -> None:
        """Say it now (once)."""
        if self.warned:
            return
        self.warned = True
        stream = self._err or sys.stderr
        rig = self._rig
        text = time_scale_warning(rig.lag_s(), rig.lag_bound_s, rig.time_scale)
        print(f"{self._prog}: {text}", file=stream, flush=True)


def note_clamped(
    prog: str, flag: str, asked_deg: float, used_counts: int, err: TextIO | None = None
) -> bool:
    """Say that ``flag``'s angle was clamped by _Scan_limit (+-360 degrees) to ``used_counts``,
    the destination the server reports it used; True if it was. Silent otherwise: a person who
    asked for 400 degrees must learn that the head went to 360, not find out from the data."""
    if deg_to_counts(asked_deg) == used_counts:
        return False
    print(
        f"{prog}: {flag} {asked_deg:g}\N{DEGREE SIGN} is beyond the head's travel: clamped to "
        f"{counts_to_deg(used_counts):+.0f}\N{DEGREE SIGN}",
        file=err or sys.stderr,
        flush=True,
    )
    return True


def confirm_moves(
    session: Session, args: argparse.Namespace, moves: Sequence[tuple[str, int]]
) -> None:
    """Refuse (:class:`UsageError`, exit 2) a move of more than half a turn on a real head
    unless ``--yes`` was given.

    ``moves`` are (what the person asked, destination in counts after clamping); each is
    measured from where the head stands now (``status().azimuth``) and, in order, from the
    previous destination, so a sweep's limits count as the sweep they make. A real head carries
    a cable and turns among real things; a long turn nobody expected is worth one flag. The
    simulator never asks.
    """
    if session.simulated or getattr(args, "yes", False) or not moves:
        return
    here = int(session.server.status()["azimuth"])
    start = here
    for what, dest in moves:
        for origin in dict.fromkeys((here, start)):
            if abs(dest - origin) > HALF_TURN_COUNTS:
                raise UsageError(
                    f"{what} turns the head {counts_to_deg(abs(dest - origin)):.0f}\N{DEGREE SIGN} "
                    f"(from {counts_to_deg(origin):+.1f}\N{DEGREE SIGN} to "
                    f"{counts_to_deg(dest):+.1f}\N{DEGREE SIGN}), more than half a turn: make "
                    f"sure the cable and the space around the head allow it, then add --yes"
                )
        start = dest


# -- output files ----------------------------------------------------------------------------------


def _writable_folder(flag: str, given: Path, folder: Path) -> None:
    """``folder`` is, or can be made as, a folder we may write in; UsageError otherwise."""
    probe = folder
    while not probe.exists():
        if probe.is_symlink():  # a dangling link: mkdir would fail
            raise UsageError(f"{flag} {given}: {probe} is a broken link")
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise UsageError(f"{flag} {given}: {probe} is not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise UsageError(f"{flag} {given}: cannot write in {probe} (permission denied)")


def check_output_file(flag: str, file: Path, *, suffixes: Collection[str] | None = None) -> Path:
    """Refuse, before the sensor is touched, a file that cannot be written: ``file`` is a
    folder, its folder cannot be made or written, or (with ``suffixes``) its extension is not
    one of them. A missing folder is fine: the command makes it when it writes.

    Returns ``file``. Raises :class:`UsageError` (exit 2) naming the flag and the reason.
    """
    if file.is_dir():
        raise UsageError(f"{flag} {file}: is a folder; give a file name")
    if suffixes is not None and file.suffix.lower() not in suffixes:
        known = ", ".join(sorted(suffixes))
        what = f"unknown extension {file.suffix!r}" if file.suffix else "no extension"
        raise UsageError(f"{flag} {file}: {what}; use one of {known}")
    _writable_folder(flag, file, file.parent)
    if file.exists() and not os.access(file, os.W_OK):
        raise UsageError(f"{flag} {file}: cannot overwrite it (permission denied)")
    return file


def check_output_folder(flag: str, folder: Path) -> Path:
    """Refuse, before the sensor is touched, a folder that cannot be written into: it is a
    file, or it (or the folder it would be made in) is not writable. Returns ``folder``."""
    if folder.exists() and not folder.is_dir():
        raise UsageError(f"{flag} {folder}: is a file, not a folder")
    _writable_folder(flag, folder, folder)
    return folder


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
    usage = (UsageError, SetupError, RequestError, UnknownKind, ModuleNotFoundError, AccessDenied)
    if isinstance(exc, usage):  # AccessDenied: give a controller's credentials
        return EXIT_USAGE
    if isinstance(exc, (HardwareFault, AuditFailure, ConnectionClosed, BusError, TimeoutError)):
        return EXIT_FAULT
    if isinstance(exc, OSError):  # a file we were asked to write or read
        return EXIT_USAGE
    return EXIT_FAULT


def error_line(exc: BaseException) -> str:
    """One line that says what went wrong, in the user's terms."""
    if isinstance(exc, HardwareFault):
        text = f"hardware fault ({exc.kind}): {_named_commands(exc.message)}"
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


def _named_commands(message: str) -> str:
    """``COMMAND 7`` in a fault's message read as ``COMMAND 7 (BI_STOP_CONTINUOUS)``: a person
    cannot look a code up, and the code table is ours, not the report's. A message that names
    its commands already is left alone."""
    if _COMMAND_NAME.search(message):
        return message

    def named(match: re.Match[str]) -> str:
        digits = match.group(2)
        code = int(digits, 16) if digits[:2] in ("0x", "0X") else int(digits)
        return f"{match.group(0)} ({_bi_name(code)})"

    return _COMMAND_CODE.sub(named, message)


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


def stderr_is_terminal() -> bool:
    """A person watches stderr (progress lines are for them, never for a log or a pipe)."""
    return is_terminal(sys.stderr)


def wants_progress(args: argparse.Namespace) -> bool:
    """Progress lines for this run: stderr is a terminal, and neither --quiet nor --debug (whose
    log shows the same records, and more) was given."""
    if getattr(args, "quiet", False) or getattr(args, "debug", False):
        return False
    return stderr_is_terminal()


class _ProgressLines(logging.Handler):
    """``biris scan: homing the pan...``: one line on stderr per progress record.

    stderr is looked up at each record, not kept: a live display (rich) that takes stderr over
    while it runs then prints the line above itself instead of being scribbled over.
    """

    def __init__(self, prog: str) -> None:
        super().__init__(logging.INFO)
        self._prog = prog

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage().strip()
            if not text:
                return
            if text[-1] not in ".!?:":
                text += "..."
            stream = sys.stderr
            stream.write(f"{self._prog}: {text}\n")
            stream.flush()
        except Exception:
            self.handleError(record)


@contextlib.contextmanager
def progress_to_stderr(prog: str, enabled: bool) -> Iterator[None]:
    """While the block runs, the server's progress records (:data:`PROGRESS_LOGGER`) are shown
    on stderr as ``prog: sentence...``, if ``enabled``; otherwise nothing changes.

    The server starts by homing both axes and booting BIRIS, seconds in which a command that
    says nothing looks hung; these lines say what it is doing instead.
    """
    if not enabled:
        yield
        return
    logger = logging.getLogger(PROGRESS_LOGGER)
    handler = _ProgressLines(prog)
    level = logger.level
    logger.addHandler(handler)
    if logger.getEffectiveLevel() > logging.INFO:
        logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def _carries_fault(record: logging.LogRecord) -> bool:
    """The record announces a :class:`HardwareFault` (one of its arguments, or its exception)."""
    args = record.args if isinstance(record.args, tuple) else ()
    exc = record.exc_info[1] if record.exc_info else None
    return isinstance(exc, HardwareFault) or any(isinstance(a, HardwareFault) for a in args)


class _WarningLines(logging.Handler):
    """``biris: warning: 2 acquisitions lost``: one line on stderr per warning or error record.

    What the server warns about (a scan that came out short, acquisitions lost, a task that
    failed) is what a person running a command must not miss, so it is shown without --debug,
    but plainly: one line, no logger name or time, a multi-line message folded onto it, an
    exception's traceback reduced to its type and text (--debug shows it whole). stderr is looked
    up at each record, not kept, as for the progress lines: a live display that has taken stderr
    over prints the line above itself instead of being scribbled over.

    A record that announces a hardware fault (a :class:`HardwareFault` among its arguments) is
    left out: the server hands that fault to every caller, so the command reports it in its own
    words -- its one error line, ``watch``'s state, the demo's fault count -- and a second line
    saying the same would break the one-line error contract.
    """

    def __init__(self) -> None:
        super().__init__(logging.WARNING)

    def emit(self, record: logging.LogRecord) -> None:
        if _carries_fault(record):
            return
        try:
            text = " ".join(record.getMessage().split())
            if record.exc_info and record.exc_info[1] is not None:
                exc = record.exc_info[1]
                text += f" ({type(exc).__name__}: {' '.join(str(exc).split())})"
            kind = "warning" if record.levelno < logging.ERROR else "error"
            stream = sys.stderr
            stream.write(f"biris: {kind}: {text}\n")
            stream.flush()
        except Exception:
            self.handleError(record)


@contextlib.contextmanager
def log_to_stderr(debug: bool) -> Iterator[None]:
    """The driver's warnings and errors on stderr, a plain line each (``biris: warning: ...``);
    with --debug its whole log instead, every record with its time and logger.

    The simulator's log (``sim``) is shown with --debug only: it is about the simulation, not
    the sensor. Without some handler Python's last resort would print warnings in its own form
    (and the simulator's too); here every record goes through one of ours or none.
    """
    loggers = [logging.getLogger(name) for name in ("biris_hw", "sim")]
    handlers: list[logging.Handler]
    if debug:
        shared = logging.StreamHandler(sys.stderr)
        shared.setFormatter(logging.Formatter("%(relativeCreated)8.0f ms %(name)s: %(message)s"))
        handlers = [shared, shared]
    else:
        handlers = [_WarningLines(), logging.NullHandler()]
    saved: list[tuple[logging.Logger, int]] = []
    for logger, handler in zip(loggers, handlers, strict=True):
        saved.append((logger, logger.level))
        logger.addHandler(handler)
        if debug:
            logger.setLevel(logging.DEBUG)
        elif logger.name == "biris_hw" and logger.getEffectiveLevel() > logging.WARNING:
            logger.setLevel(logging.WARNING)  # a quieter root must not hide the warnings
    try:
        yield
    finally:
        for (logger, level), handler in zip(saved, handlers, strict=True):
            logger.removeHandler(handler)
            logger.setLevel(level)
