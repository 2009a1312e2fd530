"""The flags every ``biris`` command that talks to the sensor shares, and what they mean.

A person who learned one command knows them all: ``--sim`` (with ``--scene``, ``--samples``,
``--time-scale``, ``--seed``, ``--clock``), ``--target FILE``, ``--attach NAME`` (a ``biris sim``
process) or ``--connect NAME`` (a running service, with its endpoints, credentials and TLS
flags), ``--init FILE``, ``--quiet`` and ``--debug``; those that acquire take ``--continuous``,
those that move the head ``--yes`` and ``--timeout``. :func:`check_target_arguments` checks
them together (a flag that does not apply to the sensor chosen is a :class:`UsageError`, never
ignored) and :func:`connect_options` turns the service's flags into
:func:`~biris_hw.opening.open_sensor`'s keywords, passwords read from a file or the environment,
never from the command line (where ``ps`` shows them to every user).

Where the flags say nothing, the client's profile does (:mod:`biris_hw.commands.profile`:
``$BIRIS_CONNECT``, ``$BIRIS_ENDPOINT``, ``$BIRIS_USER`` and ``~/.config/biris/client.toml``):
the service to use and how to reach it, so that the ``--connect ... --endpoint ... --user``
tail is typed once. A flag always wins over the environment, the environment over the file.

A command also checks the files it will write before it touches the sensor
(:func:`check_output_file`, :func:`check_output_folder`), so that a typo in a folder name
costs nothing, and the files it will read that hold secrets (:func:`check_private_file`):
one other users may read or write is refused, as ssh refuses such a key.

Only :mod:`biris_hw.commands.argtypes` is imported here (for the argument types): declaring the
flags loads nothing of the server, so ``biris COMMAND --help`` stays quick.
"""

from __future__ import annotations

import argparse
import os
import re
import stat
import sys
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from biris_hw.commands.argtypes import (
    DEFAULT_TIME_SCALE,
    SIM_DEFAULTS,
    add_simulator_arguments,
    path,
    seconds,
)
from biris_hw.commands.failures import SetupError, UsageError

if TYPE_CHECKING:
    from biris_hw.commands.profile import ClientProfile
    from biris_hw.io.codec import Stamp

__all__ = [
    "DEFAULT_WAIT_S",
    "LINK_PASSWORD_ENV",
    "PASSWORD_ENV",
    "STAMPS",
    "TARGET_ENV",
    "add_continuous_argument",
    "add_debug_argument",
    "add_quiet_argument",
    "add_service_client_arguments",
    "add_stamp_argument",
    "add_target_arguments",
    "add_timeout_argument",
    "add_yes_argument",
    "check_output_file",
    "check_output_folder",
    "check_private_file",
    "check_target_arguments",
    "client_profile",
    "connect_options",
    "parse_zenoh_options",
    "profile_hint",
    "read_toml",
    "stamp_of",
    "sweep_chosen",
]

PASSWORD_ENV = "BIRIS_PASSWORD"
"""With ``--user``: the controller's password (never on the command line, where ``ps`` shows it)."""

LINK_PASSWORD_ENV = "BIRIS_LINK_PASSWORD"
"""With ``--link-user``: the password of Zenoh's link authentication (never on the command line)."""

TARGET_ENV = "BIRIS_TARGET"
"""A target file to use when neither --sim nor --target is given: set once on the robot."""

DEFAULT_WAIT_S = 60.0
"""``--timeout``'s default: real seconds a command waits for an answer before it gives up."""


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
            "our own (default: $BIRIS_CONNECT, or the profile's connect)",
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
        "$BIRIS_ENDPOINT, the profile's, else found by multicast scouting)",
    )
    net.add_argument(
        "--user",
        metavar="USER",
        help=f"controller's user name (default $BIRIS_USER, or the profile's); the password "
        f"is read from ${PASSWORD_ENV}",
    )
    net.add_argument(
        "--credentials",
        type=path,
        metavar="FILE",
        help='controller\'s credentials, a TOML file of mode 600: user = "...", password = "..."',
    )
    net.add_argument(
        "--tls-ca",
        type=path,
        metavar="FILE",
        help="root CA certificate (PEM) for a tls/ endpoint (default: the profile's tls_ca)",
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
        check_private_file("--link-password-file", Path(file))
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


STAMPS = ("wall", "hardware")
"""``--stamp``'s choices: :data:`biris_hw.io.codec.STAMPS`, named here so that building a
parser loads nothing of the outside world (``biris view --help`` starts at once)."""


def add_stamp_argument(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--stamp wall|hardware``: what a recording's or the live view's messages are logged at
    (:class:`biris_hw.io.codec.LogTimes`); :func:`stamp_of` gives its value or its default."""
    parser.add_argument(
        "--stamp",
        choices=STAMPS,
        help="log times: the host's wall clock (default on a real sensor) or the hardware "
        "clock's seconds (default on the simulator and a replay); the messages keep their "
        "hardware stamps",
    )


def stamp_of(args: argparse.Namespace) -> Stamp:
    """``--stamp``, or its default: ``wall`` on a real sensor (``--target``, or a service with
    ``--connect``), whose hardware clock keeps pace with the host's, so that the file or the
    view lines up with the robot's other logs; ``hardware`` on the simulator (``--sim``,
    ``--attach``: a time-scaled simulator's seconds are not real ones) and a replay (which
    plays the recorded times)."""
    if getattr(args, "stamp", None) is not None:
        return cast("Stamp", args.stamp)
    simulated = getattr(args, "sim", False) or getattr(args, "attach", None) is not None
    if getattr(args, "replay", None) is not None or simulated:
        return "hardware"
    return "wall"


def add_yes_argument(parser: argparse.ArgumentParser) -> None:
    """``--yes``: allow a move of more than half a turn on a real head (:func:`confirm_moves`)."""
    parser.add_argument(
        "--yes",
        action="store_true",
        help="on a real target, allow a move of more than half a turn (180 deg) from where "
        "the head stands (the simulator never asks)",
    )


def add_timeout_argument(parser: argparse.ArgumentParser) -> None:
    """``--timeout S``: how long a command waits for an answer (a scan, the head at rest) before
    it gives up with "no answer in time" (exit 1) rather than hang."""
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


_CLIENT_ONLY = (
    "credentials",
    "tls_ca",
    "link_user",
    "link_password_file",
    "zenoh_option",
    "read_credentials",
)
"""The service's flags (``add_service_client_arguments``) other than --endpoint and --user."""


def check_target_arguments(args: argparse.Namespace) -> None:
    """Resolve --sim / --target / $BIRIS_TARGET and the simulator's defaults, in place.

    A flag that does not apply to the sensor chosen is refused (:class:`UsageError`), never
    ignored: ``--continuous`` or ``--init`` with ``--connect`` (the service's server is not
    ours to configure), a simulator's flag without ``--sim``, a service's flag without
    ``--connect``.
    """
    attach = getattr(args, "attach", None)
    chosen = args.sim or args.target is not None or attach is not None
    if hasattr(args, "connect") and args.connect is None and not chosen:
        _connect_from_profile(args)
    if getattr(args, "connect", None) is not None:
        given = [key for key in (*_SIM_ONLY, "init") if getattr(args, key, None) is not None]
        if getattr(args, "continuous", False):
            given.append("continuous")
        if given:
            flag = "--" + given[0].replace("_", "-")
            where = getattr(args, "connect_source", "")
            raise UsageError(
                f"{flag} does not apply to a running service (--connect {args.connect}"
                f"{where}): its server is the service's, started with its own settings"
            )
        return
    if getattr(args, "endpoint", None) or getattr(args, "user", None):
        raise UsageError("--endpoint and --user go with --connect NAME")
    if hasattr(args, "connect"):  # biris serve has --credentials and --zenoh-option of its own
        for flag in _CLIENT_ONLY:
            if getattr(args, flag, None):
                raise UsageError(f"--{flag.replace('_', '-')} goes with --connect NAME")
    if not args.sim and args.target is None and attach is None:
        args.target = os.environ.get(TARGET_ENV) or None
        if args.target is None:
            if hasattr(args, "connect"):
                raise UsageError(
                    "say which sensor to use: --sim, --target FILE or --attach NAME, or a "
                    f"service: --connect NAME (or set {TARGET_ENV}, or BIRIS_CONNECT)"
                )
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


def client_profile(args: argparse.Namespace) -> ClientProfile:
    """The client's profile (environment and file), read once per command and kept on
    ``args``.

    Raises:
        SetupError: a profile file that cannot be used
            (:func:`~biris_hw.commands.profile.load_profile`).
    """
    found = getattr(args, "client_profile", None)
    if found is None:
        from biris_hw.commands.profile import load_profile

        found = load_profile()
        args.client_profile = found
    return found


def _connect_from_profile(args: argparse.Namespace) -> None:
    """No sensor flag: the service ``$BIRIS_CONNECT`` names; else ``$BIRIS_TARGET`` (left to
    the caller); else the profile file's ``connect``. The environment before the file, whatever
    each names: a shell that sets ``$BIRIS_TARGET`` means it over a file written long ago."""
    from biris_hw.commands.profile import CONNECT_ENV

    profile = client_profile(args)
    if profile.connect is None:
        return
    from_env = profile.sources.get("connect") == f"${CONNECT_ENV}"
    if from_env or not os.environ.get(TARGET_ENV):
        args.connect = profile.connect
        args.connect_source = profile.source("connect")


# -- what the service flags mean ---------------------------------------------------------------


def connect_options(args: argparse.Namespace) -> dict[str, Any]:
    """``open_sensor(connect=args.connect, **connect_options(args))``: the endpoints, the
    controller's credentials (:func:`_credentials`), the root CA, ``--zenoh-option`` items and
    the link's user and password (:func:`_link_options`), as open_sensor's keywords.

    Raises:
        UsageError: a flag without what it needs (``--user`` without ``$BIRIS_PASSWORD``,
            ``--link-user`` without its password, a password in ``--zenoh-option``).
        SetupError: a credentials or password file that cannot be read, or says too little.
    """
    profile = client_profile(args)
    user, password = _credentials(args, profile)
    zenoh = parse_zenoh_options(getattr(args, "zenoh_option", None) or [])
    zenoh.update(_link_options(args))
    ca = getattr(args, "tls_ca", None)
    if ca is None and profile.tls_ca is not None:
        ca = profile.tls_ca
        _readable(f"tls_ca{profile.source('tls_ca')}", Path(ca))
    elif ca is not None:
        _readable("--tls-ca", Path(ca))
    if profile.tls_cert is not None and profile.tls_key is not None:
        where = profile.source("tls_key")
        _readable(f"tls_cert{where}", profile.tls_cert)
        check_private_file(f"tls_key{where}", profile.tls_key)
        zenoh.setdefault("transport/link/tls/connect_certificate", str(profile.tls_cert))
        zenoh.setdefault("transport/link/tls/connect_private_key", str(profile.tls_key))
    return {
        "endpoints": getattr(args, "endpoint", None) or list(profile.endpoints) or None,
        "user": user,
        "password": password,
        "tls_ca": None if ca is None else str(ca),
        "zenoh_options": zenoh or None,
        "reader_credentials": bool(getattr(args, "read_credentials", False)),
    }


def _credentials(args: argparse.Namespace, profile: ClientProfile) -> tuple[str | None, str | None]:
    """(user, password) from --credentials FILE, or --user and $BIRIS_PASSWORD, or the profile's
    user and $BIRIS_PASSWORD, or (None, None).

    A user the flags name needs its password; one the profile names (``$BIRIS_USER``, the file)
    is used only when ``$BIRIS_PASSWORD`` is there too -- a profile is for every command, and
    those that only read need no password. Without it nothing is sent, and
    ``args.profile_user`` says whose password was missing (:func:`profile_hint`).
    """
    file = getattr(args, "credentials", None)
    user = getattr(args, "user", None)
    if file is not None:
        check_private_file("--credentials", Path(file))
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
    if profile.user is not None:
        password = os.environ.get(PASSWORD_ENV)
        if password:
            return profile.user, password
        args.profile_user = f"{profile.user}{profile.source('user')}"
    return None, None


def profile_hint(args: argparse.Namespace) -> str:
    """What to add to an AccessDenied when the profile named a user whose password was not in
    ``$BIRIS_PASSWORD`` (so no credentials were sent); "" otherwise."""
    user = getattr(args, "profile_user", None)
    if user is None:
        return ""
    return f" (no credentials were sent: user {user} has no password in ${PASSWORD_ENV})"


_OPEN_TO_OTHERS = stat.S_IROTH | stat.S_IWOTH | stat.S_IWGRP
"""Mode bits that let other users read a secret, or others or the group change it. A group may
read (a service's own group, ``root:biris 0640``); nobody else may."""


def check_private_file(flag: str, file: Path) -> Path:
    """Refuse a file that holds secrets (passwords, a private key) when other users may read it
    or others may write it (as ssh refuses such a key): one line naming its mode and the
    ``chmod`` that fixes it. A missing or unreadable file is named too. Returns ``file``.

    Raises:
        SetupError: the file is missing, cannot be read, or is open to others.
    """
    try:
        mode = stat.S_IMODE(file.stat().st_mode)
    except FileNotFoundError:
        raise SetupError(f"{flag} {file}: no such file") from None
    except OSError as exc:
        raise SetupError(f"{flag} {file}: {exc.strerror or exc}") from exc
    if os.name == "posix" and mode & _OPEN_TO_OTHERS:
        what = []
        if mode & stat.S_IROTH:
            what.append("read")
        if mode & (stat.S_IWOTH | stat.S_IWGRP):
            what.append("change")
        raise SetupError(
            f"{flag} {file}: mode {mode:04o} lets other users {' and '.join(what)} it, and it "
            f"holds secrets: chmod 600 {file}"
        )
    return file


def _readable(flag: str, file: Path) -> None:
    """A file the command will read: there, a file, and readable (named before anything
    starts, not found by Zenoh after a timeout)."""
    if not file.exists():
        raise SetupError(f"{flag} {file}: no such file")
    if not file.is_file():
        raise SetupError(f"{flag} {file}: not a file")
    if not os.access(file, os.R_OK):
        raise SetupError(f"{flag} {file}: cannot read it (permission denied)")


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
