"""How a ``biris`` command fails: one line on stderr, and an exit status a script can act on.

Errors are for people: ``biris <command>: <what went wrong>``, in the user's terms (a fault
names the BIRIS command by its name, a missing module says which extra to install). The exit
status says whose move it is: 2 means "fix what you asked for" (a flag, a file, a device node
or its permissions, a controller's credentials), 1 means "the hardware failed" (a fault, a bus
error while running, no answer in time, a rule the simulator's audit caught the driver
breaking, the network to the service lost), 130 is Ctrl-C and 143 SIGTERM (128 + the signal's
number, as a shell reports a process the signal ended: the command has kept what it could, as
for Ctrl-C). ``--debug`` adds the traceback. What a library below says in its own terms is
cleaned on the way (:func:`error_line`): Zenoh's errors lose the Rust source paths they carry.

The dispatcher (:mod:`biris_hw.cli`) imports this module to run every command, ``biris --help``
included, so it imports nothing of the server, the hardware or the outside world.
"""

from __future__ import annotations

import re
import sys
import traceback
from typing import TextIO

from biris_hw.errors import (
    AccessDenied,
    BirisError,
    BusError,
    ConnectionClosed,
    ConnectionLost,
    HardwareFault,
    RequestError,
    SetupError,
    UnknownKind,
)

__all__ = [
    "EXIT_FAULT",
    "EXIT_INTERRUPTED",
    "EXIT_TERMINATED",
    "EXIT_USAGE",
    "AuditFailure",
    "SetupError",
    "Terminated",
    "UsageError",
    "error_line",
    "exit_status",
    "report_error",
]

EXIT_FAULT = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143
"""SIGTERM (systemd's stop, ``docker stop``, ``timeout``, a launch file): ended as Ctrl-C ends a
command, with 128 + 15 as the status."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread as Ctrl-C's KeyboardInterrupt is (:mod:`biris_hw.cli`):
    every ``except KeyboardInterrupt`` takes it, so a command ends by its Ctrl-C path.

    A class of its own, not KeyboardInterrupt itself: CPython marks the process to end by
    SIGINT (status 130, whatever ``sys.exit`` said) when a KeyboardInterrupt *exactly* passes
    out of code run from a string (``exec``: dataclasses make their methods so, and an import
    interrupted there is enough), even if it is caught further up; a subclass is not marked.
    """


class UsageError(BirisError, ValueError):
    """The command line asks for something impossible (exit 2)."""


class AuditFailure(BirisError):
    """The simulator recorded a hardware rule the driver broke (exit 1: a driver bug)."""


def exit_status(exc: BaseException) -> int:
    """2 for what the user must fix, 1 for what the hardware (or the network to the service)
    did, 130 for Ctrl-C."""
    if isinstance(exc, Terminated):
        return EXIT_TERMINATED
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    if isinstance(exc, ConnectionLost):  # an OSError too, but not the user's to fix
        return EXIT_FAULT
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
    text = _RUST_SOURCE.sub("", text)
    lines = text.splitlines()
    return lines[0] if lines and lines[0] else type(exc).__name__


_RUST_SOURCE = re.compile(r"[ \t]*\bat[ \t]+\S*?\.rs(?::\d+)+\.?")
"""`` at /root/.cargo/git/checkouts/zenoh-.../unicast.rs:61.``: where in Zenoh's source an error
was made (the network service's errors carry them), which tells a user nothing."""


_COMMAND_NAME = re.compile(r"\bBI_[A-Z_]+")
_COMMAND_CODE = re.compile(r"\b(COMMAND|command) (0x[0-9A-Fa-f]+|\d+)\b")


def _named_commands(message: str) -> str:
    """``COMMAND 7`` in a fault's message read as ``COMMAND 7 (BI_STOP_CONTINUOUS)``: a person
    cannot look a code up, and the code table is ours, not the report's. A message that names
    its commands already is left alone."""
    if _COMMAND_NAME.search(message):
        return message
    from regs.biexec import BiCommand  # only for a fault: the code table costs an import

    def named(match: re.Match[str]) -> str:
        digits = match.group(2)
        code = int(digits, 16) if digits[:2] in ("0x", "0X") else int(digits)
        try:
            name = BiCommand(code).name
        except ValueError:
            name = f"unknown BIRIS command {code}"
        return f"{match.group(0)} ({name})"

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
