"""What a ``biris`` command tells the person running it on stderr while it works.

Three kinds of line, each one line, each starting with the command's name (:func:`prog_of`):
what the server is doing while the person waits (homing, booting BIRIS: the progress log,
:func:`progress_to_stderr`, shown only when a terminal watches), what the driver and the
simulator warn about (a short scan, acquisitions lost: :func:`log_to_stderr`, always), and an
angle the server clamped (:func:`note_clamped`). Failures have their own module
(:mod:`biris_hw.commands.failures`). A long-running command may also keep one line of how it
is doing rewritten in place at the bottom, for a terminal only (:class:`StatusLine`: ``biris
record``'s elapsed time, scans, megabytes and drops); the other lines are written above it.

A service (``biris serve``) is not watched by a person but read from a log: there
:func:`log_to_stderr` writes the whole log from INFO up (DEBUG with ``--debug``), one line per
event in a form the systemd journal reads (:class:`ServiceLines`).

The dispatcher (:mod:`biris_hw.cli`) wraps every command in these, ``biris --help`` included, so
this module imports nothing of the server, the hardware or the outside world.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import TextIO

from biris_hw.errors import HardwareFault

__all__ = [
    "PROGRESS_LOGGER",
    "ServiceLines",
    "StatusLine",
    "is_terminal",
    "journal_stream",
    "log_to_stderr",
    "note_clamped",
    "prog_of",
    "progress_to_stderr",
    "stderr_is_terminal",
    "wants_progress",
]

PROGRESS_LOGGER = "biris_hw.progress"
"""The logger on which the server says, in a short sentence per INFO record, what it is doing
while a caller waits (homing the pan, booting BIRIS...): what a person sees during the seconds
a server takes to start."""


def prog_of(args: argparse.Namespace) -> str:
    """``biris scan`` for a scan's arguments (the dispatcher records the command's name)."""
    name = getattr(args, "command", None)
    return f"biris {name}" if name else "biris"


def is_terminal(stream: TextIO) -> bool:
    """True when a person is watching ``stream`` (live displays), False for pipes and files."""
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def stderr_is_terminal() -> bool:
    """A person watches stderr (progress lines are for them, never for a log or a pipe)."""
    return is_terminal(sys.stderr)


def wants_progress(args: argparse.Namespace) -> bool:
    """Progress lines for this run: stderr is a terminal, and neither --quiet nor --debug (whose
    log shows the same records, and more) was given."""
    if getattr(args, "quiet", False) or getattr(args, "debug", False):
        return False
    return stderr_is_terminal()


def note_clamped(
    prog: str, flag: str, asked_deg: float, used_counts: int, err: TextIO | None = None
) -> bool:
    """Say that ``flag``'s angle was clamped by _Scan_limit (+-360 degrees) to ``used_counts``,
    the destination the server reports it used; True if it was. Silent otherwise: a person who
    asked for 400 degrees must learn that the head went to 360, not find out from the data."""
    from biris_hw.angles import counts_to_deg, deg_to_counts

    if deg_to_counts(asked_deg) == used_counts:
        return False
    print(
        f"{prog}: {flag} {asked_deg:g}\N{DEGREE SIGN} is beyond the head's travel: clamped to "
        f"{counts_to_deg(used_counts):+.0f}\N{DEGREE SIGN}",
        file=err or sys.stderr,
        flush=True,
    )
    return True


STATUS_EVERY_S = 0.5
"""How often a :class:`StatusLine` is rewritten."""


class StatusLine:
    """One line on stderr, rewritten in place every :data:`STATUS_EVERY_S` while a block runs
    (``with StatusLine(prog, text):``): how a long command is doing, for a person at a
    terminal. ``text()`` is called on a thread of the line's own and says what to show.

    Only where a person watches (the caller decides: :func:`wants_progress`); never into a log
    or a pipe, where a line rewritten with carriage returns is noise. The line is erased before
    any other line this module writes (a warning, a progress line: :meth:`write_above`) and drawn
    again at the next tick, and erased when the block ends, so that what the command prints
    then (its summary) starts on a clean line.
    """

    _current: StatusLine | None = None
    _lock = threading.Lock()

    def __init__(
        self,
        prog: str,
        text: Callable[[], str],
        *,
        every_s: float = STATUS_EVERY_S,
        err: TextIO | None = None,
    ) -> None:
        self._prog = prog
        self._text = text
        self._every = every_s
        self._err = err
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._drawn = False
        self.draws = 0
        """Times the line was written (tests)."""

    def _stream(self) -> TextIO:
        return self._err or sys.stderr

    def draw(self) -> None:
        """Write the line now (over the previous one)."""
        try:
            text = self._text()
        except Exception as exc:  # what it reads has gone: say so rather than stop drawing
            text = f"({type(exc).__name__})"
        with StatusLine._lock:
            stream = self._stream()
            stream.write(f"\r\x1b[K{self._prog}: {text}")
            stream.flush()
            self._drawn = True
            self.draws += 1

    def _erase(self) -> None:
        if self._drawn:
            stream = self._stream()
            stream.write("\r\x1b[K")
            stream.flush()
            self._drawn = False

    @classmethod
    def write_above(cls, stream: TextIO, text: str) -> None:
        """Write ``text`` (whole lines) to ``stream``, the line being shown erased first (it is
        drawn again at its next tick), so that the two never share a line."""
        with cls._lock:
            if cls._current is not None:
                cls._current._erase()
            stream.write(text)
            stream.flush()

    def _run(self) -> None:
        while not self._stop.wait(self._every):
            self.draw()

    def __enter__(self) -> StatusLine:
        with StatusLine._lock:
            StatusLine._current = self
        self._thread = threading.Thread(target=self._run, name="biris-status-line", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        with StatusLine._lock:
            if StatusLine._current is self:
                StatusLine._current = None
            self._erase()


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
            StatusLine.write_above(sys.stderr, f"{self._prog}: {text}\n")
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
    exception's traceback reduced to its type and text (--debug shows it whole). The
    simulator's warnings (a rule of a simulated device broken, its supervisor stopped) are
    shown the same way, after ``simulator:``. stderr is looked up at each record, not kept, as
    for the progress lines: a live display that has taken stderr over prints the line above
    itself instead of being scribbled over.

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
            text = _one_line(record)
            if record.name == "sim" or record.name.startswith("sim."):
                text = f"simulator: {text}"
            kind = "warning" if record.levelno < logging.ERROR else "error"
            StatusLine.write_above(sys.stderr, f"biris: {kind}: {text}\n")
        except Exception:
            self.handleError(record)


def _one_line(record: logging.LogRecord) -> str:
    """The record's message on one line, an exception's type and text folded onto it."""
    text = " ".join(record.getMessage().split())
    if record.exc_info and record.exc_info[1] is not None:
        exc = record.exc_info[1]
        text += f" ({type(exc).__name__}: {' '.join(str(exc).split())})"
    return text


def journal_stream(stream: TextIO) -> bool:
    """True when ``stream`` is connected to the systemd journal: systemd names the journal's
    stream in ``$JOURNAL_STREAM`` (``device:inode``) for a service whose stderr goes there, and
    the check against the stream's own device and inode keeps a program it started with
    stderr redirected elsewhere from taking the variable for its own."""
    value = os.environ.get("JOURNAL_STREAM", "")
    if not value:
        return False
    try:
        found = os.fstat(stream.fileno())
    except (AttributeError, OSError, ValueError):  # no file behind it (a test's capture)
        return False
    return value == f"{found.st_dev}:{found.st_ino}"


_PRIORITY = {
    logging.DEBUG: 7,
    logging.INFO: 6,
    logging.WARNING: 4,
    logging.ERROR: 3,
    logging.CRITICAL: 2,
}
"""syslog priorities (debug, info, warning, err, crit), as sd-daemon's ``<N>`` line prefix."""


class ServiceLines(logging.Handler):
    """A service's log on stderr, one line per record, for the journal or for a person.

    Under systemd (:func:`journal_stream`) a line is ``<6>service: client 3fa2 connected``: the
    sd-daemon prefix gives the journal the record's priority (``journalctl -p warning`` finds
    the faults), and no time, which the journal keeps itself. Elsewhere (a terminal, a file, a
    container's log) it is ``2026-11-03 14:02:11 INFO service: client 3fa2 connected``. The name
    is the last part of the logger's (``service``, ``serve``, ``initialiser``); a multi-line
    message is folded onto its line and an exception reduced to its type and text, unless
    ``tracebacks`` (``--debug``) asks for the traceback, a line each.

    Records that carry a :class:`HardwareFault` are left out unless ``faults``: the service
    says a fault itself, with what it does about it (:class:`~biris_hw.commands.reset.AutoReset`),
    and the server's own line would say it a second time. stderr is looked up at each record.
    """

    def __init__(
        self,
        level: int = logging.INFO,
        *,
        journal: bool | None = None,
        tracebacks: bool = False,
        faults: bool = False,
    ) -> None:
        super().__init__(level)
        self._journal = journal
        self._tracebacks = tracebacks
        self._faults = faults

    def line(self, record: logging.LogRecord, journal: bool) -> str:
        """The line (without its newline) that ``record`` is written as."""
        name = record.name.rsplit(".", 1)[-1]
        text = " ".join(record.getMessage().split()) if self._tracebacks else _one_line(record)
        if journal:
            return f"<{_priority(record.levelno)}>{name}: {text}"
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(record.created))
        return f"{when} {record.levelname} {name}: {text}"

    def emit(self, record: logging.LogRecord) -> None:
        if not self._faults and _carries_fault(record):
            return
        try:
            stream = sys.stderr
            journal = journal_stream(stream) if self._journal is None else self._journal
            lines = [self.line(record, journal)]
            if self._tracebacks and record.exc_info and record.exc_info[1] is not None:
                import traceback

                lead = f"<{_priority(record.levelno)}>" if journal else ""
                for chunk in traceback.format_exception(*record.exc_info):
                    lines += [f"{lead}  {part}" for part in chunk.rstrip().splitlines()]
            stream.write("".join(f"{line}\n" for line in lines))
            stream.flush()
        except Exception:
            self.handleError(record)


def _priority(level: int) -> int:
    """The syslog priority of a logging level (a custom level takes the next standard one's)."""
    for standard in sorted(_PRIORITY):
        if level <= standard:
            return _PRIORITY[standard]
    return _PRIORITY[logging.CRITICAL]


@contextlib.contextmanager
def log_to_stderr(debug: bool, *, service: bool = False) -> Iterator[None]:
    """The driver's and the simulator's warnings and errors on stderr, a plain line each
    (``biris: warning: ...``); with --debug the whole log instead, every record with its time
    and logger.

    ``service`` (``biris serve``): the log a supervisor keeps, from INFO up (the service's
    start, its clients coming and going, faults, resets, recoveries, refusals, drops), DEBUG
    with --debug, as :class:`ServiceLines`; the simulator's from WARNING up (DEBUG with
    --debug). Without some handler Python's last resort would print warnings in its own form;
    here every record goes through one of ours.
    """
    loggers = [logging.getLogger(name) for name in ("biris_hw", "sim")]
    handlers: list[logging.Handler]
    levels: list[int]
    if service:
        shared: logging.Handler = ServiceLines(
            logging.DEBUG if debug else logging.INFO, tracebacks=debug, faults=debug
        )
        handlers = [shared, shared]
        levels = [logging.DEBUG, logging.DEBUG] if debug else [logging.INFO, logging.WARNING]
    elif debug:
        shared = logging.StreamHandler(sys.stderr)
        shared.setFormatter(logging.Formatter("%(relativeCreated)8.0f ms %(name)s: %(message)s"))
        handlers = [shared, shared]
        levels = [logging.DEBUG, logging.DEBUG]
    else:
        warnings = _WarningLines()
        handlers = [warnings, warnings]
        levels = [logging.WARNING, logging.WARNING]
    saved: list[tuple[logging.Logger, int]] = []
    for logger, handler, level in zip(loggers, handlers, levels, strict=True):
        saved.append((logger, logger.level))
        logger.addHandler(handler)
        if debug:
            logger.setLevel(level)
        elif logger.getEffectiveLevel() > level:
            logger.setLevel(level)  # a quieter root must not hide what this run shows
    try:
        yield
    finally:
        for (logger, level), handler in zip(saved, handlers, strict=True):
            logger.removeHandler(handler)
            logger.setLevel(level)
