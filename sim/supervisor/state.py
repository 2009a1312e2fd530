"""What the simulated BIRIS supervisor holds, how it reaches BIEXEC_COM, and its inner seams.

One object, one lock: the supervisor thread and the test's or driver's calls (faults, the
write hook, observation) all take ``_lock``, so each sees the state between two steps, never in
the middle of one. The steps are grouped by topic in sibling modules (mixins of
:class:`SupervisorState`); what one topic asks of another is declared below as an abstract
operation, so every seam is listed here and mypy holds each topic to it.
"""

from __future__ import annotations

import abc
import re
import threading
from array import array
from collections.abc import Callable
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import NDArray

from biris_hw.bus.base import BusWindow
from biris_hw.timebase import HwThread, TimeBase
from regs.biexec import (
    ACQ_LINE_END,
    BIEXEC_COM_SIZE,
    BIEXEC_PARAM_SIZE,
    OFF_ACQ_LINE,
    OFF_DATA_INT_ENABLE,
    OFF_PARAM,
    BiStatus,
    decode_param,
)
from regs.layout import FRAME_DTYPE, BirisMemoryMap, fields_per_acquisition
from sim import POISON
from sim.audit import Audit, Rule
from sim.clock import SimClock
from sim.irqgate import InterruptGate
from sim.ramdisk import BootParameters, RamDisk
from sim.supervisor.schedule import FieldSchedule

if TYPE_CHECKING:
    from sim.supervisor.acquisition import AcquisitionSequence

__all__ = [
    "ACQUISITION_TIMES_KEPT",
    "JITTER_S",
    "SEQUENCE_STARTS_KEPT",
    "AcquireFn",
    "Frame",
    "GarbageKind",
    "SupervisorState",
    "TimeHistory",
    "parse_int",
    "signed16",
]

Frame = NDArray[np.int16]
AcquireFn = Callable[[float, float, float | None], tuple[Frame, Frame]]
"""(azimuth_rad, tilt_rad, lut_tilt_rad) -> (range frame, intensity frame), samples+1 each."""

GarbageKind = Literal["unterminated", "bad_digits"]

JITTER_S = (20e-6, 2e-3)
"""Range of the seeded delay between a command's field and its completion, hardware seconds."""


ACQUISITION_TIMES_KEPT = 65536
"""Mid-exposure times the supervisor remembers (the newest; the count stays exact).

Enough for every test and benchmark run (a throughput trial at 100x makes about 10^4), and
bounded: a long ``biris sim`` once grew by 3.5 MB an hour at x1 keeping them all. At most
1.25 times this many 8-byte doubles are held (640 KiB)."""

SEQUENCE_STARTS_KEPT = 4096
"""Sequence start times the supervisor remembers (the newest; the count stays exact). A
sequence takes at least its 250 ms start-up, so this is over 17 minutes of them at x1."""


class TimeHistory:
    """Clock times appended in order, of which the newest ``keep`` are remembered.

    The count of everything ever appended stays exact; the times themselves live in an array of
    doubles that is cut back to the newest ``keep`` whenever it passes ``keep`` by a quarter, so
    memory is bounded and an append costs O(1) amortised. Not thread-safe: the supervisor's
    lock guards it.
    """

    __slots__ = ("_dropped", "_keep", "_slack", "_times")

    def __init__(self, keep: int) -> None:
        if keep < 1:
            raise ValueError("a history must keep at least one time")
        self._keep = keep
        self._slack = max(1, keep // 4)
        self._times = array("d")
        self._dropped = 0

    def append(self, t: float) -> None:
        times = self._times
        times.append(t)
        if len(times) > self._keep + self._slack:
            cut = len(times) - self._keep
            del times[:cut]
            self._dropped += cut

    @property
    def keep(self) -> int:
        return self._keep

    @property
    def count(self) -> int:
        """How many times were ever appended (exact, however many are remembered)."""
        return self._dropped + len(self._times)

    @property
    def stored(self) -> int:
        """How many times are held now: never more than 1.25 ``keep`` (rounded up)."""
        return len(self._times)

    def recent(self) -> list[float]:
        """The newest ``keep`` times (all of them while fewer were appended), oldest first."""
        return self._times[-self._keep :].tolist()

    def since(self, index: int) -> list[float]:
        """The times from the ``index``-th ever appended (0 = the first) to the newest.

        Raises ValueError when ``index`` is no longer remembered, rather than hand back a list
        that silently starts later than asked.
        """
        first = self.count - min(len(self._times), self._keep)
        if index < first:
            raise ValueError(f"time {index} is no longer kept (the oldest kept is {first})")
        return self._times[index - self._dropped :].tolist()


def signed16(raw: int) -> int:
    """A 16-bit register value as the 68020 reads a ``short``."""
    return raw - 0x10000 if raw & 0x8000 else raw


_INT = re.compile(r"[+-]?[0-9]+")


def parse_int(text: str | None, *, signed: bool) -> int | None:
    """A decimal PARAM as the 68020's parser would take it: digits only, a sign if allowed."""
    if text is None or not _INT.fullmatch(text) or (not signed and text[0] in "+-"):
        return None
    return int(text)


class SupervisorState(abc.ABC):
    """The supervisor's fields, its access to BIEXEC_COM, and the seams between its topics."""

    def __init__(
        self,
        memory: BusWindow,
        memory_map: BirisMemoryMap,
        clock: SimClock,
        gate: InterruptGate,
        acquire: AcquireFn,
        azimuth_counts: Callable[[float], float],
        *,
        audit: Audit | None = None,
        ramdisk: RamDisk | None = None,
        rng: np.random.Generator,
        tilting: Callable[[], bool] | None = None,
        elevation_counts: Callable[[float], float] | None = None,
        true_elevation_counts: Callable[[float], float] | None = None,
        require_motor_access: bool = True,
        times_kept: int = ACQUISITION_TIMES_KEPT,
        starts_kept: int = SEQUENCE_STARTS_KEPT,
        sleep_when_idle: bool = True,
    ) -> None:
        if memory.size < memory_map.size:
            raise ValueError(
                f"memory window of 0x{memory.size:X} bytes is smaller than the BIRIS map "
                f"(0x{memory_map.size:X})"
            )
        self._mem = memory
        self._map = memory_map
        self._clock = clock
        self._gate = gate
        self._acquire = acquire
        self._azimuth = azimuth_counts
        self._audit = audit
        self._ramdisk = ramdisk if ramdisk is not None else RamDisk(samples=memory_map.samples)
        self._rng = rng
        self._tilting = tilting
        self._elevation = elevation_counts
        self._true_elevation = (
            true_elevation_counts if true_elevation_counts is not None else elevation_counts
        )
        """The tilt the optics truly see (counts from level): what the calibration table is
        judged against. The encoder (``elevation_counts``) stops being that when a driver resets
        the tilt's chip while BIRIS still acquires."""
        self._require_motor_access = require_motor_access
        self._base = memory_map.biexec_offset
        self._fpa = fields_per_acquisition(memory_map.samples)
        self._elements = memory_map.samples + 1
        self._poison = np.full(self._elements, POISON, dtype=FRAME_DTYPE).tobytes()

        # Every wait of the supervisor goes through the clock's time base, taken once here: the
        # thread, the kick and the condition belong to it for the object's life.
        self._tb: TimeBase = clock.timebase
        self._lock = threading.RLock()
        self._changed = self._tb.Condition(self._lock)
        self._kick = self._tb.Event()
        self._stopping = False
        self._thread: HwThread | None = None
        self._failure: BaseException | None = None
        self._running_due = False
        self._idle = False
        """The thread sleeps several fields at a time (nothing to do but find COMMAND clear)."""
        self._sleep_when_idle = sleep_when_idle
        """False where COMMAND may be written without :meth:`note_command_write` (BIRIS memory
        shared with a driver in another process): the thread then looks at every field."""

        self._fields = FieldSchedule()
        self._executing = 0
        self._last_seen = 0
        self._outstanding_write = False
        self._accepted_unnoted = False
        self._seq: AcquisitionSequence | None = None
        self._continuous = False
        self._last_slot: int | None = None
        self._boot: BootParameters | None = None
        self._lut: int | None = None
        self._hung_since: float | None = None
        self._garbage: GarbageKind | None = None
        self._garbage_armed = False
        self._commands_completed = 0
        self._acquisitions_made = 0
        self._acquisitions_abandoned = 0
        # bounded: a simulator left running for days must not grow (see TimeHistory)
        self._acquisition_times = TimeHistory(times_kept)
        self._sequence_starts = TimeHistory(starts_kept)
        self._power_up()

    def _shift_schedule(self) -> None:
        """Resume at the next field: move everything still to come by the time spent frozen.

        Whole fields only, so sequences stay on the field grid. Used after a hang and when the
        thread is started (again); the first start has nothing to move.
        """
        shift = self._fields.resume(self._clock.now())
        if shift and self._seq is not None:
            self._seq.first_field += shift

    # -- BIEXEC_COM --------------------------------------------------------------------------
    def _power_up(self) -> None:
        """BIEXEC_COM as OS-9 leaves it at power-up: all clear, no sequence (ACQ_LINE -128)."""
        self._mem.write(self._base, bytes(BIEXEC_COM_SIZE))
        self._set(OFF_ACQ_LINE, ACQ_LINE_END)

    def _get(self, offset: int) -> int:
        return signed16(self._mem.read16(self._base + offset))

    def _set(self, offset: int, value: int) -> None:
        self._mem.write16(self._base + offset, value & 0xFFFF)

    def _param_text(self) -> str | None:
        """PARAM as the host left it, or None when it is not NUL-terminated ASCII."""
        raw = self._mem.read(self._base + OFF_PARAM, BIEXEC_PARAM_SIZE)
        try:
            return decode_param(raw)
        except (ValueError, UnicodeDecodeError):
            return None

    def _finish_later(
        self,
        at: float,
        status: BiStatus,
        answer: str,
        *,
        query: bool = False,
        apply: Callable[[], None] | None = None,
    ) -> None:
        """Complete the command a seeded jitter after ``at``, applying its effect first."""

        def complete(_: float) -> None:
            if apply is not None:
                apply()
            self._complete(status, answer, query=query)

        self._fields.at(at + float(self._rng.uniform(*JITTER_S)), complete)

    def _data_interrupt(self) -> None:
        if self._get(OFF_DATA_INT_ENABLE):
            self._gate.raise_irq("data")

    def _record(self, rule: Rule, detail: str, **registers: int) -> None:
        if self._audit is not None:
            self._audit.record(rule, detail, **registers)

    # -- seams: what the topics ask of one another (each implemented in the module named) ----
    @abc.abstractmethod
    def _poll_command(self, field: int, t: float) -> None:
        """Read COMMAND at vsync ``field``; accept a new command when idle (commands)."""

    @abc.abstractmethod
    def _complete(self, status: BiStatus, answer: str, *, query: bool) -> None:
        """Complete the command under way now (commands)."""

    @abc.abstractmethod
    def _cmd_boot(self, done: float) -> None:
        """BI_BOOT: load the boot file PARAM names from the RAMdisk (boot)."""

    @abc.abstractmethod
    def _cmd_load_lut(self, done: float) -> None:
        """BI_LOAD_LUT: load the calibration table for elevation PARAM (boot)."""

    @abc.abstractmethod
    def _cmd_acquire(self, field: int, t: float) -> None:
        """BI_ACQUIRE n (acquisition)."""

    @abc.abstractmethod
    def _cmd_start_continuous(self, field: int, t: float) -> None:
        """BI_START_CONTINUOUS (acquisition)."""

    @abc.abstractmethod
    def _cmd_stop_continuous(self, done: float) -> None:
        """BI_STOP_CONTINUOUS (acquisition)."""

    @abc.abstractmethod
    def _exposure_ends(self, field: int) -> None:
        """End the exposure due to end at vsync ``field``, if any (acquisition)."""

    @abc.abstractmethod
    def _exposure_starts(self, field: int, t: float) -> None:
        """Start the exposure due at vsync ``field``, or end the sequence (acquisition)."""

    @abc.abstractmethod
    def wake_idle(self) -> None:
        """COMMAND was just written: an idle thread looks again at once (supervisor)."""
