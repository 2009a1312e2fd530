"""``BirisSupervisor``: the 68020/OS-9 supervisor that executes BIEXEC_COM commands.

The driver reaches BIRIS only through memory (BIEXEC_COM, the frames, the azimuth table) and
level-2 interrupts, so the model works the same way: it shares a buffer window with the driver
and raises interrupts through an :class:`~sim.irqgate.InterruptGate`. How we read the report
(DESIGN.md section 4), where it is silent:

**Vertical sync.** The supervisor thread wakes at every video field (``FIELD_PERIOD`` of clock
time, fields counted from clock time 0) and reads COMMAND. A non-zero COMMAND while idle is
accepted; it completes after a field-synchronised delay plus a seeded jitter of 20 us .. 2 ms
(BI_BOOT two fields later, BI_LOAD_LUT one), so from the host's write to completion takes from
tens of microseconds to tens of milliseconds. Completion writes STATUS, the answer into PARAM
(NUL-terminated ASCII: addresses ``0x%08X``, sizes decimal; a short message on error), clears
COMMAND, then raises the command interrupt if ``_Biris_cmd_int_enable`` is set.

**Busy.** From acceptance to completion the supervisor is busy. A COMMAND value that changes
meanwhile is recorded as ``CMD_WHILE_BUSY`` and the new command is lost (completion clears
COMMAND). Field-rate polling cannot see a rewrite of the same value, nor a second write before
the first was accepted: an in-process rig can call :meth:`BirisSupervisor.note_command_write`
from a write hook, *after* the write has landed, to catch those too.

**BI_ACQUIRE n.** 240 ms start-up (the boot file's ``startup_ms``, rounded up to whole fields:
15 fields, 250 ms) with ACQ_LINE = -1; then acquisition k is exposed for 2 fields (64 samples)
or 3 (128 samples), back to back, on the field grid. At the start of k: range and intensity
frame k are filled with :data:`sim.POISON`, CURRENT_FRAME = ACQ_LINE = k, and the data
interrupt announces that k-1 is complete. At mid-exposure the head's azimuth (and elevation)
are sampled and the optics produce the frames; at the end of k they are written, with azimuth
table entry k (i32 counts, mid-exposure azimuth) if ``_Biris_motor_access`` is set at that
moment. After the last: ACQ_LINE = -128, one more data interrupt (announcing n-1), then the
command completes. Data interrupts need ``_Biris_data_int_enable``. A BI_ACQUIRE while
``_Biris_motor_access`` is clear is recorded as ``ACQUIRE_WITHOUT_MOTOR_ACCESS`` (when
``require_motor_access``); the acquisitions still run and untagged entries keep their old values.

**Continuous (Appendix D).** BI_START_CONTINUOUS completes as soon as it is accepted, answering
the ring's length in frames (decimal, as BI_ACQUIRE answers its count), so the host
can issue BI_STOP_CONTINUOUS (and queries, BI_LOAD_LUT) while acquisitions run; BI_ACQUIRE,
BI_BOOT or a second start are refused with BAD_PARAM meanwhile. After one start-up, acquisitions
run back to back into a ring of ``memory_map.max_acquisitions`` frames; ACQ_LINE and
CURRENT_FRAME give the ring index, each start raises a data interrupt. Because COMMAND is 0
during these interrupts, the driver needs its own continuous-mode flag to demultiplex them, as
the report foresees. BI_STOP_CONTINUOUS ceases at the field it is seen: the frame being exposed
is abandoned and *restored* to what it held before its exposure, so no ring slot is left
poisoned and every slot holds a complete acquisition (of this lap or the previous one) with
its matching azimuth entry; CURRENT_FRAME names the last completed slot, ACQ_LINE = -128, no
further data interrupt. A stop while not continuous just completes.

**Calibration.** Booting loads the boot file's default table; BI_LOAD_LUT n loads the table
for elevation n counts (NO_CALIBRATION outside the boot file's range). At each acquisition
start, ``tilting()`` true is ``ACQUIRE_WHILE_TILTING`` and a table more than one count away
from ``elevation_counts()`` is ``WRONG_CALIBRATION``; each is recorded when it begins (once per
episode within a sequence, not once per acquisition).

**Faults.** :meth:`~BirisSupervisor.hang` freezes the supervisor: nothing is polled, written or
raised; :meth:`~BirisSupervisor.unhang` resumes where it was, the whole schedule shifted by
the hang rounded up to whole fields. :meth:`~BirisSupervisor.garbage_param` makes the next
query answer (BI_GET_*) malformed. :meth:`~BirisSupervisor.drop_data_interrupt` loses the next
data interrupt.
"""

from __future__ import annotations

import heapq
import logging
import math
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from biris_hw.bus.base import BusWindow
from regs.biexec import (
    ACQ_LINE_END,
    ACQ_LINE_STARTUP,
    BIEXEC_COM_SIZE,
    BIEXEC_PARAM_SIZE,
    OFF_ACQ_LINE,
    OFF_CMD_INT_ENABLE,
    OFF_COMMAND,
    OFF_CURRENT_FRAME,
    OFF_CURRENT_PROJ,
    OFF_DATA_INT_ENABLE,
    OFF_MOTOR_ACCESS,
    OFF_PARAM,
    OFF_STATUS,
    BiCommand,
    BiStatus,
    decode_param,
    encode_param,
)
from regs.hctl1000 import COUNTS_PER_REV
from regs.layout import AZIMUTH_DTYPE, FRAME_DTYPE, BirisMemoryMap, fields_per_acquisition
from sim import POISON
from sim.audit import Audit, Rule
from sim.clock import FIELD_PERIOD, SimClock
from sim.irqgate import InterruptGate
from sim.ramdisk import BootParameters, RamDisk

__all__ = ["AcquireFn", "BirisSupervisor", "GarbageKind"]

log = logging.getLogger(__name__)

Frame = NDArray[np.int16]
AcquireFn = Callable[[float, float, float | None], tuple[Frame, Frame]]
"""(azimuth_rad, tilt_rad, lut_tilt_rad) -> (range frame, intensity frame), samples+1 each."""

GarbageKind = Literal["unterminated", "bad_digits"]

JITTER_S = (20e-6, 2e-3)
"""Range of the seeded delay between a command's field and its completion, hardware seconds."""

_EXTRA_FIELDS = {BiCommand.BI_BOOT: 2, BiCommand.BI_LOAD_LUT: 1}
_QUERIES = frozenset(
    {BiCommand.BI_GET_VME_ADDR_DIST, BiCommand.BI_GET_VME_ADDR_AZIM, BiCommand.BI_GET_VME_INC_FRAME}
)
_NOT_HEX = str.maketrans("0123456789ABCDEFabcdef", "GHIJKLMNOPQRSTUVWXYZgh")


def _counts_to_rad(counts: float) -> float:
    return counts * 2.0 * math.pi / COUNTS_PER_REV


def _signed16(raw: int) -> int:
    return raw - 0x10000 if raw & 0x8000 else raw


_INT = re.compile(r"[+-]?[0-9]+")


def _parse_int(text: str | None, *, signed: bool) -> int | None:
    """A decimal PARAM as the 68020's parser would take it: digits only, a sign if allowed."""
    if text is None or not _INT.fullmatch(text) or (not signed and text[0] in "+-"):
        return None
    return int(text)


@dataclass
class _Sequence:
    """An acquisition sequence in progress (single or continuous); times are field numbers."""

    continuous: bool
    count: int
    """Acquisitions to make (single) or ring slots (continuous)."""
    first_field: int
    """Field at which acquisition 0 starts (end of start-up)."""
    fpa: int
    next_index: int = 0
    exposing: int | None = None
    slot: int = 0
    frames: tuple[bytes, bytes] | None = None
    mid_time: float = 0.0
    mid_azimuth: float = 0.0
    saved: bytes = b""
    tilting_noted: bool = False
    wrong_lut_noted: bool = False

    def start_field(self, k: int) -> int:
        return self.first_field + k * self.fpa


@dataclass(order=True)
class _Event:
    time: float
    order: int
    action: Callable[[float], None]


class BirisSupervisor:
    """The BIRIS side of BIEXEC_COM, run by one thread on the simulator clock."""

    def __init__(
        self,
        memory: BusWindow,
        memory_map: BirisMemoryMap,
        clock: SimClock,
        gate: InterruptGate,
        acquire: AcquireFn,
        azimuth_counts: Callable[[], float],
        *,
        audit: Audit | None = None,
        ramdisk: RamDisk | None = None,
        rng: np.random.Generator,
        tilting: Callable[[], bool] | None = None,
        elevation_counts: Callable[[], float] | None = None,
        require_motor_access: bool = True,
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
        self._require_motor_access = require_motor_access
        self._base = memory_map.biexec_offset
        self._fpa = fields_per_acquisition(memory_map.samples)
        self._elements = memory_map.samples + 1
        self._poison = np.full(self._elements, POISON, dtype=FRAME_DTYPE).tobytes()

        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._kick = threading.Event()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._failure: BaseException | None = None

        self._events: list[_Event] = []
        self._event_order = 0
        self._vsync = 0
        self._executing = 0
        self._last_seen = 0
        self._outstanding_write = False
        self._accepted_unnoted = False
        self._seq: _Sequence | None = None
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
        self._acquisition_times: list[float] = []
        self._sequence_starts: list[float] = []
        self._power_up()

    # -- lifecycle --------------------------------------------------------------------------------
    def start(self) -> None:
        """Run the supervisor thread; does nothing if it already runs."""
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                return
            self._stopping = False
            self._kick.clear()
            self._shift_schedule()
            self._thread = threading.Thread(target=self._run, name="biris-supervisor", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the thread and join it; idempotent. State and memory are left as they are."""
        with self._lock:
            self._stopping = True
            thread = self._thread
        self._kick.set()
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    def __enter__(self) -> BirisSupervisor:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- driver-side hook ------------------------------------------------------------------------
    def note_command_write(self, value: int) -> None:
        """Tell the supervisor that the driver has just written ``value`` to COMMAND.

        Call it from a write hook after the write landed. It catches what vsync polling cannot:
        a rewrite of the same code while busy, and a second write before the first was accepted.
        A vsync may fall between the write and the hook: a note matching a command accepted
        since the last note is that command's own write, not a second one.
        """
        value = _signed16(value & 0xFFFF)
        with self._lock:
            if self._accepted_unnoted and value == self._executing:
                self._accepted_unnoted = False
                return
            if self._executing or self._outstanding_write:
                self._record(
                    Rule.CMD_WHILE_BUSY,
                    "COMMAND written before the previous command completed",
                    COMMAND=value,
                    EXECUTING=self._executing,
                )
                self._last_seen = value
            landed = self._get(OFF_COMMAND) != 0
            self._outstanding_write = value != 0 and landed and not self._executing

    # -- faults -----------------------------------------------------------------------------------
    def hang(self) -> None:
        """Freeze: COMMAND is never completed, acquisitions stop, nothing is cleared or raised."""
        with self._lock:
            if self._hung_since is None:
                self._hung_since = self._clock.now()

    def unhang(self) -> None:
        """Resume; the schedule moves on by the hang's length, rounded up to whole fields."""
        with self._lock:
            if self._hung_since is None:
                return
            self._hung_since = None
            self._shift_schedule()
            self._changed.notify_all()
        self._kick.set()

    def _shift_schedule(self) -> None:
        """Resume at the next field: move everything still to come by the time spent frozen.

        Whole fields only, so sequences stay on the field grid. Used after a hang and when the
        thread is started (again); the first start has nothing to move.
        """
        resume = math.floor(self._clock.now() / FIELD_PERIOD) + 1
        shift = max(0, resume - self._vsync)
        self._vsync += shift
        if shift:
            dt = shift * FIELD_PERIOD
            for event in self._events:
                event.time += dt
            if self._seq is not None:
                self._seq.first_field += shift

    def garbage_param(self, kind: GarbageKind | None = None) -> None:
        """Make the next query answer malformed: no NUL terminator, or digits that are not hex.

        With no ``kind`` the seeded generator picks one when the answer is written.
        """
        with self._lock:
            self._garbage_armed = True
            self._garbage = kind

    def drop_data_interrupt(self) -> None:
        """Lose the next data interrupt."""
        self._gate.drop_next("data")

    # -- observability ----------------------------------------------------------------------------
    @property
    def booted(self) -> bool:
        with self._lock:
            return self._boot is not None

    @property
    def busy(self) -> bool:
        """A command has been accepted and not yet completed."""
        with self._lock:
            return self._executing != 0

    @property
    def current_command(self) -> int:
        """The code being executed, 0 when idle."""
        with self._lock:
            return self._executing

    @property
    def continuous(self) -> bool:
        with self._lock:
            return self._continuous

    @property
    def hung(self) -> bool:
        with self._lock:
            return self._hung_since is not None

    @property
    def loaded_lut(self) -> int | None:
        """Elevation (counts) of the calibration table in use, None before boot."""
        with self._lock:
            return self._lut

    @property
    def commands_completed(self) -> int:
        with self._lock:
            return self._commands_completed

    @property
    def acquisitions_made(self) -> int:
        """Acquisitions whose frames were written (abandoned ones do not count)."""
        with self._lock:
            return self._acquisitions_made

    @property
    def acquisitions_abandoned(self) -> int:
        """Exposures cut short by BI_STOP_CONTINUOUS (their slot was restored)."""
        with self._lock:
            return self._acquisitions_abandoned

    @property
    def exposing(self) -> int | None:
        """The frame (ring slot) being exposed now, None in start-up or between sequences."""
        with self._lock:
            seq = self._seq
            return seq.slot if seq is not None and seq.exposing is not None else None

    @property
    def acquisition_times(self) -> list[float]:
        """Mid-exposure clock time of every acquisition made, oldest first."""
        with self._lock:
            return list(self._acquisition_times)

    @property
    def sequence_starts(self) -> list[float]:
        """Clock time (a field) at which each acquisition sequence was accepted."""
        with self._lock:
            return list(self._sequence_starts)

    @property
    def failure(self) -> BaseException | None:
        """What stopped the thread, if it died (a bad frame from ``acquire``, a closed window)."""
        with self._lock:
            return self._failure

    def wait_for(self, predicate: Callable[[BirisSupervisor], bool], timeout: float) -> bool:
        """Block up to ``timeout`` real seconds until ``predicate(self)`` holds; its last value.

        The predicate is re-evaluated whenever the supervisor's state may have changed, so tests
        can wait for "busy", "acquisition k exposed" and the like without sleeping.
        """
        with self._changed:
            return self._changed.wait_for(lambda: predicate(self), timeout)

    # -- the thread -------------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while True:
                with self._lock:
                    if self._stopping:
                        return
                    self._kick.clear()
                    hung = self._hung_since is not None
                    wake = self._vsync * FIELD_PERIOD
                    if self._events and self._events[0].time < wake:
                        wake = self._events[0].time
                if hung:
                    self._kick.wait()
                    continue
                if not self._clock.wait_until(wake, self._kick):
                    continue
                with self._changed:
                    if self._hung_since is None and not self._stopping:
                        self._process_due(self._clock.now())
                    self._changed.notify_all()
        except Exception as exc:
            log.exception("BIRIS supervisor stopped")
            with self._changed:
                self._failure = exc
                self._changed.notify_all()

    def _process_due(self, now: float) -> None:
        """Run every event and vsync due by ``now``, in time order (events first at a tie)."""
        while True:
            t_vsync = self._vsync * FIELD_PERIOD
            if self._events and self._events[0].time <= t_vsync:
                if self._events[0].time > now:
                    return
                event = heapq.heappop(self._events)
                event.action(event.time)
            else:
                if t_vsync > now:
                    return
                self._on_vsync(self._vsync)
                self._vsync += 1

    def _schedule(self, time: float, action: Callable[[float], None]) -> None:
        self._event_order += 1
        heapq.heappush(self._events, _Event(time, self._event_order, action))

    def _jitter(self) -> float:
        return float(self._rng.uniform(*JITTER_S))

    def _on_vsync(self, field: int) -> None:
        """One vertical sync: end the exposure due now, poll COMMAND, start the next exposure."""
        t = field * FIELD_PERIOD
        seq = self._seq
        if (
            seq is not None
            and seq.exposing is not None
            and field == seq.start_field(seq.exposing + 1)
        ):
            self._finish_exposure(seq)
        self._poll_command(field, t)
        seq = self._seq
        if seq is not None and seq.exposing is None and field == seq.start_field(seq.next_index):
            if not seq.continuous and seq.next_index == seq.count:
                self._end_sequence(seq, t)
            else:
                self._start_exposure(seq, t)

    # -- commands ---------------------------------------------------------------------------------
    def _poll_command(self, field: int, t: float) -> None:
        value = self._get(OFF_COMMAND)
        if self._executing:
            if value != self._last_seen:
                self._record(
                    Rule.CMD_WHILE_BUSY,
                    "COMMAND changed while a command executed",
                    COMMAND=value,
                    EXECUTING=self._executing,
                )
                self._last_seen = value
            return
        if value != 0:
            self._accept(value, field, t)

    def _accept(self, code: int, field: int, t: float) -> None:
        """Take command ``code`` at vsync ``field`` and arrange its completion."""
        self._executing = code
        self._last_seen = code
        self._accepted_unnoted = not self._outstanding_write
        self._outstanding_write = False
        try:
            command: BiCommand | None = BiCommand(code)
        except ValueError:
            command = None
        if command is None:
            self._finish_later(t, BiStatus.UNKNOWN_COMMAND, f"unknown command {code}")
            return
        done = t + _EXTRA_FIELDS.get(command, 0) * FIELD_PERIOD
        if command is BiCommand.BI_BOOT:
            self._cmd_boot(done)
        elif command in _QUERIES:
            self._finish_later(done, BiStatus.OK, self._query_answer(command), query=True)
        elif command is BiCommand.BI_ACQUIRE:
            self._cmd_acquire(field, t)
        elif command is BiCommand.BI_START_CONTINUOUS:
            self._cmd_start_continuous(field, t)
        elif command is BiCommand.BI_STOP_CONTINUOUS:
            self._cmd_stop_continuous(done)
        else:
            self._cmd_load_lut(done)

    def _param_text(self) -> str | None:
        """PARAM as the host left it, or None when it is not NUL-terminated ASCII."""
        raw = self._mem.read(self._base + OFF_PARAM, BIEXEC_PARAM_SIZE)
        try:
            return decode_param(raw)
        except (ValueError, UnicodeDecodeError):
            return None

    def _query_answer(self, command: BiCommand) -> str:
        if command is BiCommand.BI_GET_VME_ADDR_DIST:
            return f"0x{self._map.address(self._map.range_offset):08X}"
        if command is BiCommand.BI_GET_VME_ADDR_AZIM:
            return f"0x{self._map.address(self._map.azimuth_offset):08X}"
        return str(self._map.frame_size)

    def _cmd_boot(self, done: float) -> None:
        name = self._param_text()
        if self._continuous:
            self._finish_later(done, BiStatus.BAD_PARAM, "continuous acquisition running")
            return
        if name is None or name not in self._ramdisk:
            self._finish_later(done, BiStatus.NO_BOOT_FILE, "no such boot file")
            return
        try:
            params = BootParameters.parse(self._ramdisk.read(name).decode("ascii"))
        except (ValueError, UnicodeDecodeError, FileNotFoundError) as exc:
            self._finish_later(done, BiStatus.BAD_PARAM, f"bad boot file: {exc}")
            return
        if params.samples != self._map.samples:
            self._finish_later(
                done, BiStatus.BAD_PARAM, f"boot file is for {params.samples} samples"
            )
            return
        if params.lut_file not in self._ramdisk:
            self._finish_later(done, BiStatus.NO_CALIBRATION, "no calibration file")
            return

        def apply() -> None:
            self._boot = params
            self._lut = params.lut_default

        self._finish_later(done, BiStatus.OK, "", apply=apply)

    def _acquisition_refusal(self, t: float) -> tuple[BiStatus, str] | None:
        if self._boot is None:
            return BiStatus.NOT_BOOTED, "not booted"
        if self._continuous:
            return BiStatus.BAD_PARAM, "continuous acquisition running"
        return None

    def _check_motor_access(self) -> None:
        if self._require_motor_access and self._get(OFF_MOTOR_ACCESS) == 0:
            self._record(
                Rule.ACQUIRE_WITHOUT_MOTOR_ACCESS,
                "acquisitions will not be tagged with the azimuth",
                _Biris_motor_access=0,
            )

    def _cmd_acquire(self, field: int, t: float) -> None:
        refusal = self._acquisition_refusal(t)
        if refusal is not None:
            self._finish_later(t, *refusal)
            return
        text = self._param_text()
        count = _parse_int(text, signed=False)
        if count is None or not 0 < count <= self._map.max_acquisitions:
            self._finish_later(t, BiStatus.BAD_PARAM, f"bad acquisition count {text!r}")
            return
        self._check_motor_access()
        self._begin_sequence(field, t, continuous=False, count=count)

    def _cmd_start_continuous(self, field: int, t: float) -> None:
        refusal = self._acquisition_refusal(t)
        if refusal is not None:
            self._finish_later(t, *refusal)
            return
        self._check_motor_access()
        self._begin_sequence(field, t, continuous=True, count=self._map.max_acquisitions)
        self._finish_later(t, BiStatus.OK, str(self._map.max_acquisitions))

    def _cmd_stop_continuous(self, done: float) -> None:
        seq = self._seq
        if self._continuous and seq is not None:
            if seq.exposing is not None:
                self._restore_slot(seq)
            if self._last_slot is not None:
                self._set(OFF_CURRENT_FRAME, self._last_slot)
            self._set(OFF_ACQ_LINE, ACQ_LINE_END)
            self._seq = None
            self._continuous = False
        self._finish_later(done, BiStatus.OK, "")

    def _cmd_load_lut(self, done: float) -> None:
        text = self._param_text()
        elevation = _parse_int(text, signed=True)
        if elevation is None:
            self._finish_later(done, BiStatus.BAD_PARAM, f"bad elevation {text!r}")
            return
        boot = self._boot
        if boot is None:
            self._finish_later(done, BiStatus.NOT_BOOTED, "not booted")
            return
        if not boot.has_calibration(elevation):
            self._finish_later(done, BiStatus.NO_CALIBRATION, f"no table for {elevation}")
            return

        def apply() -> None:
            self._lut = elevation

        self._finish_later(done, BiStatus.OK, "", apply=apply)

    def _finish_later(
        self,
        at: float,
        status: BiStatus,
        answer: str,
        *,
        query: bool = False,
        apply: Callable[[], None] | None = None,
    ) -> None:
        def complete(_: float) -> None:
            if apply is not None:
                apply()
            self._complete(status, answer, query=query)

        self._schedule(at + self._jitter(), complete)

    def _complete(self, status: BiStatus, answer: str, *, query: bool) -> None:
        """STATUS, PARAM, clear COMMAND, then the command interrupt: the driver's order."""
        self._set(OFF_STATUS, int(status))
        self._mem.write(self._base + OFF_PARAM, self._param_bytes(answer, query))
        self._set(OFF_COMMAND, 0)
        self._executing = 0
        self._last_seen = 0
        self._outstanding_write = False
        self._accepted_unnoted = False
        self._commands_completed += 1
        if self._get(OFF_CMD_INT_ENABLE):
            self._gate.raise_irq("cmd")

    def _param_bytes(self, answer: str, query: bool) -> bytes:
        text = answer[: BIEXEC_PARAM_SIZE - 1]
        if not (query and self._garbage_armed):
            return encode_param(text)
        kind = self._garbage
        if kind is None:
            kind = "unterminated" if self._rng.integers(2) == 0 else "bad_digits"
        self._garbage_armed = False
        self._garbage = None
        if kind == "bad_digits":
            head, body = (text[:2], text[2:]) if text.startswith("0x") else ("", text)
            return encode_param(head + body.translate(_NOT_HEX))
        return (text.encode("ascii") + b"#" * BIEXEC_PARAM_SIZE)[:BIEXEC_PARAM_SIZE]

    # -- acquisitions -----------------------------------------------------------------------------
    def _begin_sequence(self, field: int, t: float, *, continuous: bool, count: int) -> None:
        boot = self._boot
        startup_s = (boot.startup_ms if boot is not None else 240) / 1000.0
        startup_fields = math.ceil(startup_s / FIELD_PERIOD - 1e-9)
        self._seq = _Sequence(continuous, count, field + startup_fields, self._fpa)
        self._continuous = continuous
        self._last_slot = None
        self._sequence_starts.append(t)
        self._set(OFF_ACQ_LINE, ACQ_LINE_STARTUP)

    def _start_exposure(self, seq: _Sequence, t: float) -> None:
        k = seq.next_index
        slot = k % seq.count if seq.continuous else k
        seq.exposing, seq.slot, seq.frames = k, slot, None
        seq.next_index += 1
        addr = self._map.addressing
        if seq.continuous:
            seq.saved = self._mem.read(addr.range_frame(slot), 2 * self._map.frame_size)
        self._mem.write(addr.range_frame(slot), self._poison)
        self._mem.write(addr.intensity_frame(slot), self._poison)
        self._set(OFF_CURRENT_FRAME, slot)
        self._set(OFF_CURRENT_PROJ, 0)
        self._set(OFF_ACQ_LINE, slot)
        self._audit_exposure(seq)
        self._data_interrupt()
        mid = (seq.start_field(k) + seq.fpa / 2.0) * FIELD_PERIOD
        self._schedule(mid, lambda when: self._mid_exposure(seq, k, when))

    def _audit_exposure(self, seq: _Sequence) -> None:
        tilting = self._tilting is not None and self._tilting()
        if tilting and not seq.tilting_noted:
            self._record(Rule.ACQUIRE_WHILE_TILTING, "acquisition while the head tilts")
        seq.tilting_noted = tilting
        wrong = False
        if self._elevation is not None and self._lut is not None:
            elevation = self._elevation()
            wrong = abs(self._lut - elevation) > 1.0
            if wrong and not seq.wrong_lut_noted:
                self._record(
                    Rule.WRONG_CALIBRATION,
                    "calibration table for another elevation",
                    LUT=self._lut,
                    ELEVATION=round(elevation),
                )
        seq.wrong_lut_noted = wrong

    def _mid_exposure(self, seq: _Sequence, k: int, t: float) -> None:
        """Sample the head and let the optics expose: what the frame will hold at its end."""
        if self._seq is not seq or seq.exposing != k:
            return  # abandoned by BI_STOP_CONTINUOUS
        azimuth = float(self._azimuth())
        tilt = float(self._elevation()) if self._elevation is not None else 0.0
        lut = _counts_to_rad(self._lut) if self._lut is not None else None
        rng_frame, int_frame = self._acquire(_counts_to_rad(azimuth), _counts_to_rad(tilt), lut)
        seq.frames = (self._checked(rng_frame, "range"), self._checked(int_frame, "intensity"))
        seq.mid_time = t
        seq.mid_azimuth = azimuth

    def _checked(self, frame: Frame, what: str) -> bytes:
        array = np.asarray(frame)
        if array.shape != (self._elements,):
            raise ValueError(
                f"acquire() returned a {what} frame of shape {array.shape}, "
                f"expected ({self._elements},)"
            )
        return array.astype(FRAME_DTYPE).tobytes()

    def _finish_exposure(self, seq: _Sequence) -> None:
        """Write acquisition ``seq.exposing``: frames, then its azimuth entry if allowed."""
        if seq.frames is None:  # pragma: no cover - the mid-exposure event always runs first
            raise RuntimeError("exposure ended before its middle")
        addr = self._map.addressing
        range_bytes, intensity_bytes = seq.frames
        self._mem.write(addr.range_frame(seq.slot), range_bytes)
        self._mem.write(addr.intensity_frame(seq.slot), intensity_bytes)
        if self._get(OFF_MOTOR_ACCESS):
            entry = np.array([round(seq.mid_azimuth)], dtype=AZIMUTH_DTYPE).tobytes()
            self._mem.write(addr.azimuth_entry(seq.slot), entry)
        self._acquisitions_made += 1
        self._acquisition_times.append(seq.mid_time)
        self._last_slot = seq.slot
        seq.exposing, seq.frames = None, None

    def _restore_slot(self, seq: _Sequence) -> None:
        """Put back what the abandoned slot held before its exposure began."""
        self._mem.write(self._map.addressing.range_frame(seq.slot), seq.saved)
        seq.exposing, seq.frames = None, None
        self._acquisitions_abandoned += 1

    def _end_sequence(self, seq: _Sequence, t: float) -> None:
        """After the last acquisition: -128, the interrupt announcing it, then completion."""
        self._set(OFF_ACQ_LINE, ACQ_LINE_END)
        self._data_interrupt()
        self._seq = None
        self._continuous = False
        self._finish_later(t, BiStatus.OK, str(seq.count))

    def _data_interrupt(self) -> None:
        if self._get(OFF_DATA_INT_ENABLE):
            self._gate.raise_irq("data")

    # -- memory -----------------------------------------------------------------------------------
    def _power_up(self) -> None:
        """BIEXEC_COM as OS-9 leaves it at power-up: all clear, no sequence (ACQ_LINE -128)."""
        self._mem.write(self._base, bytes(BIEXEC_COM_SIZE))
        self._set(OFF_ACQ_LINE, ACQ_LINE_END)

    def _get(self, offset: int) -> int:
        return _signed16(self._mem.read16(self._base + offset))

    def _set(self, offset: int, value: int) -> None:
        self._mem.write16(self._base + offset, value & 0xFFFF)

    def _record(self, rule: Rule, detail: str, **registers: int) -> None:
        if self._audit is not None:
            self._audit.record(rule, detail, **registers)
