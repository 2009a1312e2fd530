"""What the driver knows about the pan chip's position counter: how it relates to TRUE zero.

The HCTL-1000 counts encoder edges from wherever its counter was last zeroed (a chip reset, a
power-up, an R13H write), and the pan's zero index fires once per revolution. So an index alone
cannot say which revolution the head is in: a driver that zeroes on the *nearest* index, with the
head a revolution round, counts +-0x1000 from the wrong place and winds the cable (issue 11,
defect 1). This module keeps the one fact that prevents it, across resets and driver restarts:

    true azimuth = chip counter + offset,   offset somewhere in [lo, hi]

``lo == hi`` is a *referenced* counter (set by homing to true zero's index; kept exactly by every
re-zeroing the driver does itself, since it reads the counter first). A wider interval is what is
known without that: at a fresh start, the documented precondition that a freshly powered head is
within +-180 degrees of true zero gives ``[-2048 - c, 2048 - c]`` for a counter reading ``c``; a
chip that lost its count behind the driver's back gives the span of the head's last recorded move.
``None`` is nothing known (before the first initialisation, or after a "position lost" fault);
the next initialisation then applies the precondition, and the operator is told to check it.

Two rules follow from the interval, and :func:`index_search_range` computes both: a counter ``c``
may be commanded only if ``c + [lo, hi]`` stays within +-0x1000 (safe whichever offset is the
true one), and an index found at counter ``i`` is true zero's only if ``i + [lo, hi]`` holds no
other multiple of a revolution. Both hold inside ``[-0x1000 - lo, 0x1000 - hi]`` (less a count at
each end), which is why an interval wider than one revolution means the position is lost.

**The journal.** A driver *process* that restarts must know this too, so the state can be backed
by a small JSON file (see :class:`PanReference` for its format). Writes replace the file
atomically (a temporary file, then ``os.replace``). A move record is written *ahead* of the move;
a counter re-zeroing is written *after* the chip did it, because a crash in between then looks
like a chip reset, which :meth:`PanReference.locate` already handles (the head stood inside the
recorded span). Every reference change and every move record is made durable (``fsync`` of the
file and its directory): after a power loss the chip's count is gone as well, and only a durable
journal still says where the head stood; a lost move record could let the journal claim an old,
narrower span. Settle records (the head came to rest at ``p``) are not synced: losing one leaves
the move record before it, whose span contains ``p``, which is merely less precise. The cost is
one ``fsync`` per pan move (milliseconds on flash, against a move of a second or so); in-process
simulators keep no journal at all (their rig dies with the process).

Who may delete the journal: an operator who has put the head within +-180 degrees of dead ahead
(unwinding the cable), exactly as before a fresh power-up; and a simulator that starts a new
plant (whose head wakes within half a revolution of zero). Nobody else: deleting it while the
head stands beyond +-180 degrees makes the next start find the wrong index.

Thread-safety: one lock serialises every change and its journal write (the pan worker records
moves, the motor notifier settle positions, the initialiser everything else).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from biris_hw.errors import HardwareFault
from regs.hctl1000 import COUNTS_PER_REV, MOTION_LIMIT_COUNTS

__all__ = [
    "FRESH_HALF_RANGE",
    "JOURNAL_ENV",
    "JOURNAL_FORMAT",
    "JOURNAL_NAME",
    "NARROW_WINDOW",
    "SLACK",
    "Location",
    "PanReference",
    "PanState",
    "default_journal_path",
    "forget_journal",
    "index_search_range",
]

log = logging.getLogger(__name__)

FRESH_HALF_RANGE = COUNTS_PER_REV // 2
"""The operator's precondition: a freshly powered head is within +-180 degrees of true zero."""

SLACK = 128
"""Counts the head may stand beyond the span of its last recorded move: a coast after the chip
is idled or reset mid-move (about 20 counts in the simulator at any speed), filter overshoot,
and a crash between a re-zeroing and its record. Used where the journal, not this process,
vouches for the counter, and where a chip lost its count."""

NARROW_WINDOW = 256
"""Counts searched either side of where true zero's index should be (22.5 degrees): far more than
a coast or a few counts of slip, far less than the revolution that would make it ambiguous."""

JOURNAL_ENV = "BIRIS_STATE_DIR"
"""Environment variable naming the directory that holds the journal of a target without a
``pan_journal`` key."""

JOURNAL_NAME = "pan-reference.json"
JOURNAL_FORMAT = "biris-hw pan reference"
JOURNAL_VERSION = 1

_PARAM_KEYS = ("sample", "zero", "pole", "gain", "max_vel", "max_accel")


def default_journal_path(name: str | None = None) -> Path:
    """Where a target's journal lives when its description does not say: ``$BIRIS_STATE_DIR``,
    else ``$XDG_STATE_HOME/biris``, else ``~/.local/state/biris``; the file is
    ``pan-reference.json``, or ``pan-reference-NAME.json`` for a named target (a simulator
    process, say), so that two sensors on one host never share one."""
    base = os.environ.get(JOURNAL_ENV)
    if base:
        directory = Path(base)
    else:
        state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
        directory = Path(state) / "biris"
    filename = JOURNAL_NAME if name is None else f"pan-reference-{name}.json"
    return directory / filename


def forget_journal(path: str | os.PathLike[str]) -> bool:
    """Delete a journal (see the module notes for who may); True if there was one."""
    try:
        Path(path).unlink()
    except FileNotFoundError:
        return False
    log.warning(
        "pan reference journal %s deleted: the next start assumes the head is within "
        "+-180 degrees of true zero",
        path,
    )
    return True


def index_search_range(offset: tuple[int, int], window: int = NARROW_WINDOW) -> tuple[int, int]:
    """Counters where true zero's index may be looked for, for an offset interval ``[lo, hi]``.

    True zero is at counter ``-offset``, so somewhere in ``[-hi, -lo]``; ``window`` counts more
    either side tolerate a little slip. The result is cut to ``[-0x1000 - lo + 1, 0x1000 - hi -
    1]``: there, whichever offset is the true one, the head stays within +-0x1000 of true zero,
    and an index found is true zero's (its true position lies strictly inside +-0x1000, where
    the only multiple of a revolution is 0). Empty (``lo > hi`` of the result) when the interval is
    wider than two revolutions; callers refuse intervals wider than one before asking.
    """
    lo, hi = offset
    return (
        max(-hi - window, -MOTION_LIMIT_COUNTS - lo + 1),
        min(-lo + window, MOTION_LIMIT_COUNTS - hi - 1),
    )


@dataclass(frozen=True)
class PanState:
    """What is known, in the chip's present counter coordinates (a snapshot; see the journal)."""

    offset: tuple[int, int] | None = None
    """True azimuth = counter + offset, for some offset in this interval; None: nothing known."""
    move: tuple[int, int] = (0, 0)
    """The last pan move written to the chip (from, to), counter counts; ``from == to`` is a head
    standing there (settled, or where the counter was last re-zeroed)."""
    params: Mapping[str, int] | None = None
    """The six motor parameters the chip was last loaded with (read back), or None when unknown
    or reset since: a chip that still holds them has not been reset or power-cycled since."""

    @property
    def referenced(self) -> bool:
        return self.offset is not None and self.offset[0] == self.offset[1]

    @property
    def span(self) -> tuple[int, int]:
        return (min(self.move), max(self.move))


@dataclass(frozen=True)
class Location:
    """The verdict of :meth:`PanReference.locate` at the start of an initialisation."""

    offset: tuple[int, int] | None
    """The interval now in force (counter coordinates of the reading); None when lost."""
    how: str
    """Which rule gave it: ``referenced``, ``kept``, ``fresh``, ``chip reset``,
    ``inconsistent``, or ``lost``."""
    reason: str
    """One sentence for the log, or the operator's message when lost."""

    @property
    def lost(self) -> bool:
        return self.offset is None


def _hull(a: tuple[int, int], b: tuple[int, int]) -> tuple[int, int]:
    return (min(a[0], b[0]), max(a[1], b[1]))


def _deg(counts: float) -> str:
    return f"{counts * 360.0 / COUNTS_PER_REV:+.1f} deg"


class PanReference:
    """The pan counter's relation to true zero, shared by everything that moves the pan.

    Owned by the hardware bundle (``BirisHardware.pan_reference``), one per bundle like its
    drivers: the pan :class:`~biris_hw.devices.AxisDriver` records each move, settle position and
    parameter load here, and the initialiser asks :meth:`locate` before it resets the chip and
    reports every re-zeroing. ``journal`` is the file that carries it across driver restarts, or
    None to keep it in memory only (an in-process simulator).

    Journal format (JSON, one object; written whole and replaced atomically)::

        {"format": "biris-hw pan reference", "version": 1,
         "offset": [lo, hi] | null,   # true azimuth = counter + offset (counts), lo <= hi
         "move": [from, to],          # last pan move written to the chip (counter counts)
         "params": {"sample": .., "zero": .., "pole": .., "gain": .., "max_vel": ..,
                    "max_accel": ..} | null,   # what the chip was last loaded with
         "written": "2024-05-01T12:00:00Z", "pid": 1234}    # for people; not read

    A file that cannot be read or parsed is not guessed at: :meth:`locate` reports the position
    lost and replaces it with "nothing known", so the operator's next reset (after checking the
    head) applies the precondition.
    """

    def __init__(self, journal: str | os.PathLike[str] | None = None) -> None:
        self.journal: Path | None = Path(journal) if journal is not None else None
        self._lock = threading.Lock()
        self._state = PanState()
        self._from_journal = False
        """The state came from the file and has not yet been checked against the chip: a
        counter outside the recorded span then means the file is not this chip's story."""
        self._unreadable: str | None = None
        if self.journal is not None:
            self._load(self.journal)

    # -- reading ----------------------------------------------------------------------------------
    @property
    def state(self) -> PanState:
        with self._lock:
            return self._state

    @property
    def offset(self) -> tuple[int, int] | None:
        return self.state.offset

    @property
    def referenced(self) -> bool:
        """The counter is exactly true azimuth plus a known offset (0 once homed)."""
        return self.state.referenced

    def true_position(self, counter: int) -> tuple[int, int] | None:
        """Where the head truly is, as an interval, for a counter reading; None if unknown."""
        offset = self.offset
        if offset is None:
            return None
        return (counter + offset[0], counter + offset[1])

    def safe_destination(self, destination: int) -> int:
        """``destination`` cut so that the head stays within +-0x1000 of TRUE zero whichever
        offset of the interval is the true one (unchanged when nothing is known, or when the
        interval cannot be honoured at all: the server's own clamp then still applies)."""
        offset = self.offset
        if offset is None:
            return destination
        lo, hi = -MOTION_LIMIT_COUNTS - offset[0], MOTION_LIMIT_COUNTS - offset[1]
        if lo > hi:
            return destination
        return max(lo, min(hi, destination))

    # -- the initialiser's questions and reports ------------------------------------------------
    def locate(self, counter: int, chip_params: Mapping[str, int]) -> Location:
        """Decide what is known now, from the counter of a head standing still and the six
        parameters the chip holds, before the initialiser resets the chip; the verdict is kept.

        - Nothing known (first start, missing journal, after "position lost"): the precondition,
          the head within +-180 degrees of true zero now (``fresh``).
        - The chip still holds the parameters last loaded, so it was neither reset nor
          power-cycled: the counter has counted every edge and the interval stands (``kept``,
          or ``referenced``). When the state came from the journal, the counter must also lie
          within the recorded move's span (plus :data:`SLACK`), or the journal is not this
          chip's story: then the hull of both explanations below (``inconsistent``).
        - The chip was reset or power-cycled behind the driver's back (other parameters, e.g.
          its power-up values): its count restarted where the head then stood, which was inside
          the last recorded move's span unless someone turned the head by hand while the driver
          was down. The offset is that span's true position, plus :data:`SLACK` (``chip
          reset``). This is the conservative reading of a power-cycled chip: the journal is
          believed about where the head stood (the head cannot move without power), never about
          the lost count, and a span too wide to tell true zero's index from a neighbour's
          (a move of more than about a revolution interrupted by the power cut) is ``lost``
          rather than a guess.

        An interval wider than one revolution (or an unreadable journal) is ``lost``: nothing
        is moved, and the state becomes unknown, so the operator's next reset applies the
        precondition (see docs/targets.md).
        """
        with self._lock:
            state = self._state
            verdict = self._judge(state, counter, dict(chip_params))
            if verdict.offset is None:
                self._state = replace(state, offset=None, move=(counter, counter))
            else:
                self._state = replace(state, offset=verdict.offset, move=(counter, counter))
            self._from_journal = False
            self._unreadable = None
            self._write(durable=True)
        return verdict

    def _judge(self, state: PanState, counter: int, chip: dict[str, int]) -> Location:
        if self._unreadable is not None:
            return Location(
                None,
                "lost",
                f"the pan reference journal {self.journal} is unreadable ({self._unreadable})",
            )
        if state.offset is None:
            fresh = (-FRESH_HALF_RANGE - counter, FRESH_HALF_RANGE - counter)
            return Location(
                fresh,
                "fresh",
                "no reference kept: the head is assumed to be "
                "within +-180 deg of true zero (fresh start)",
            )
        lo, hi = state.span
        a, b = state.offset
        intact = state.params is not None and chip == dict(state.params)
        stood = (lo + a - SLACK, hi + b + SLACK)  # where the head truly stood, recorded
        if intact and (not self._from_journal or lo - SLACK <= counter <= hi + SLACK):
            if a == b:
                return Location(
                    state.offset,
                    "referenced",
                    f"the pan chip kept its count (head at {_deg(counter + a)})",
                )
            return Location(state.offset, "kept", "the pan chip kept its count")
        if intact:
            offset, how = _hull(state.offset, stood), "inconsistent"
            why = (
                f"the counter ({counter}) lies outside the journal's last move "
                f"({state.move[0]}..{state.move[1]})"
            )
        else:
            offset, how = stood, "chip reset"
            where = _deg(lo + a) if lo + a == hi + b else f"{_deg(lo + a)}..{_deg(hi + b)}"
            why = (
                f"the pan chip lost its count (power cycle or reset) while the journal had "
                f"the head at {where}"
            )
        if offset[1] - offset[0] > MOTION_LIMIT_COUNTS:
            return Location(
                None,
                "lost",
                f"{why}, too wide a span to tell true zero's index from the next revolution's",
            )
        return Location(offset, how, why)

    def chip_reset(self, counter_before: int, counter_after: int = 0) -> None:
        """The chip was reset with the head standing still: its counter read ``counter_before``
        just before and ``counter_after`` (as read back: a reset leaves 0, or close to it) just
        after; its parameters are the power-up ones until configured."""
        self._rezero(counter_before, counter_after, params_kept=False)

    def rezeroed(self, counter_before: int, counter_after: int = 0) -> None:
        """The counter was cleared (R13H, or the software reset that stands in for it) with the
        head standing still: ``counter_before`` just before, ``counter_after`` read back after."""
        self._rezero(counter_before, counter_after, params_kept=True)

    def _rezero(self, counter_before: int, counter_after: int, *, params_kept: bool) -> None:
        shift = counter_before - counter_after  # the same place, counted anew
        with self._lock:
            state = self._state
            offset = state.offset
            if offset is not None:
                offset = (offset[0] + shift, offset[1] + shift)
            here = (counter_after, counter_after)
            self._state = PanState(offset, here, state.params if params_kept else None)
            self._write(durable=True)

    def homed(self, counter: int = 0) -> None:
        """The counter was cleared on true zero's index and reads ``counter`` there (0, or
        within a count of it, as read back): referenced, offset ``-counter``."""
        with self._lock:
            offset = (-counter, -counter)
            self._state = PanState(offset, (counter, counter), self._state.params)
            self._write(durable=True)

    def lose(self, reason: str) -> None:
        """The counter can no longer be trusted: nothing known (the next initialisation applies
        the precondition). Never raises: it is called on the way to reporting a fault, and a
        journal that cannot be written then must not hide that fault."""
        with self._lock:
            self._state = replace(self._state, offset=None)
            self._unreadable = None
            try:
                self._write(durable=True)
            except HardwareFault as exc:
                log.error("%s", exc)
        log.error("pan reference lost: %s", reason)

    # -- the pan driver's reports -----------------------------------------------------------------
    def record_move(self, start: int, destination: int) -> None:
        """Written ahead of every pan move (durably, see the module notes); raises
        HardwareFault("internal") when the journal cannot be written, so that the move is not
        made: a restart could not know where it left the head. The same move recorded twice is
        written once (a scheduled start records it ahead, then starts it)."""
        with self._lock:
            if self._state.move == (start, destination):
                return  # recorded ahead already (a scheduled start: prepare_trapezoid)
            self._state = replace(self._state, move=(start, destination))
            self._write(durable=True)

    def settled(self, position: int) -> None:
        """The head came to rest at ``position``: the span narrows to it (not synced; never
        raises, since the notifier that reports it must carry on)."""
        with self._lock:
            if self._state.move == (position, position):
                return
            self._state = replace(self._state, move=(position, position))
            try:
                self._write(durable=False)
            except HardwareFault as exc:
                log.error("%s", exc)

    def configured(self, params: Mapping[str, int]) -> None:
        """The chip now holds these six parameters (read back after loading them)."""
        with self._lock:
            if self._state.params is not None and dict(self._state.params) == dict(params):
                return
            self._state = replace(self._state, params=dict(params))
            self._write(durable=False)

    # -- the journal ------------------------------------------------------------------------------
    def _load(self, path: Path) -> None:
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return
        except OSError as exc:
            self._unreadable = exc.strerror or str(exc)
            return
        try:
            self._state = _parse(json.loads(text))
        except (ValueError, TypeError, KeyError) as exc:
            self._unreadable = f"{type(exc).__name__}: {exc}"
            return
        self._from_journal = self._state.offset is not None
        log.info(
            "pan reference from %s: offset %s, last move %s",
            path,
            self._state.offset,
            self._state.move,
        )

    def _write(self, *, durable: bool) -> None:
        """Replace the journal with the present state (under the lock)."""
        path = self.journal
        if path is None:
            return
        state = self._state
        document: dict[str, Any] = {
            "format": JOURNAL_FORMAT,
            "version": JOURNAL_VERSION,
            "offset": list(state.offset) if state.offset is not None else None,
            "move": list(state.move),
            "params": dict(state.params) if state.params is not None else None,
            "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "pid": os.getpid(),
        }
        data = (json.dumps(document, indent=1) + "\n").encode("utf-8")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
            try:
                with os.fdopen(fd, "wb") as stream:
                    stream.write(data)
                    if durable:
                        stream.flush()
                        os.fsync(stream.fileno())
                os.replace(temporary, path)
            except BaseException:
                with contextlib.suppress(OSError):
                    os.unlink(temporary)
                raise
            if durable:
                _sync_directory(path.parent)
        except OSError as exc:
            raise HardwareFault(
                "internal",
                f"cannot write the pan reference journal {path}: {exc.strerror or exc}; the pan "
                f"is not moved, since a restarted driver could not know where it left the head",
            ) from exc


def _sync_directory(directory: Path) -> None:
    """Make a rename durable (POSIX: the directory entry is the directory's data)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return  # a platform without directory descriptors: the rename is as durable as it gets
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _pair(value: object, what: str) -> tuple[int, int]:
    if (
        not isinstance(value, list)
        or len(value) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)
    ):
        raise ValueError(f"{what} must be a list of two integers, not {value!r}")
    return (value[0], value[1])


def _parse(document: object) -> PanState:
    """A journal's state; ValueError for anything that is not exactly what we write."""
    if not isinstance(document, dict):
        raise ValueError("not a JSON object")
    if document.get("format") != JOURNAL_FORMAT or document.get("version") != JOURNAL_VERSION:
        raise ValueError(f"not a version {JOURNAL_VERSION} {JOURNAL_FORMAT!r} file")
    raw_offset = document["offset"]
    offset = None if raw_offset is None else _pair(raw_offset, "offset")
    if offset is not None and offset[0] > offset[1]:
        raise ValueError(f"offset {offset} is not an interval")
    move = _pair(document["move"], "move")
    raw_params = document["params"]
    params: dict[str, int] | None = None
    if raw_params is not None:
        if not isinstance(raw_params, dict) or sorted(raw_params) != sorted(_PARAM_KEYS):
            raise ValueError(f"params must hold exactly {', '.join(_PARAM_KEYS)}")
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in raw_params.values()):
            raise ValueError("params must be integers")
        params = {k: int(raw_params[k]) for k in _PARAM_KEYS}
    return PanState(offset, move, params)
