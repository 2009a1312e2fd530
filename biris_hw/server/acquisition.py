"""Reading completed acquisitions out of BIRIS memory, by ACQ_LINE rather than by interrupt.

BIRIS asserts its data interrupt *during* acquisition k, so the interrupt means k-1 is complete and
frame k still holds garbage. Interrupts can also arrive coalesced, or not at all; so the reader
never counts them. Each time it is woken it looks at ACQ_LINE and reads every acquisition from the
last one it delivered up to ACQ_LINE-1 (all of them once ACQ_LINE reads -128). An acquisition is
therefore lost only if its frame was overwritten first, and then it is counted, never silent.

Acquisition times. BIRIS does not time-stamp its frames, but its acquisitions are exactly one
period apart (2 or 3 video fields) and ACQ_LINE = k tells that acquisition k has begun: so the
start of acquisition 0 lies at or before ``now - k * period`` at every wake. The reader keeps the
earliest such bound (the wake that came soonest after its interrupt) and stamps acquisition k
with the middle of its exposure, ``t0 + (k + 0.5) * period``. An acquisition read early carries the
bound known then (``t_origin``); the finished scan re-times all of them from the tightest one, so a
scan's times are exactly periodic, increasing, and only as late as the promptest wake of the
sequence, whatever a busy machine does to the others.

Both the data notifier and the command notifier drain through one reader, under its lock, and
send what they drained before releasing the lock: the administrator's inbox is FIFO, so every
acquisition of a sequence reaches it before BIRIS_CMD_COMPLETE does.

**Continuous mode** (Appendix D). After BI_START_CONTINUOUS, BIRIS acquires for ever into a ring
of frames; ACQ_LINE is the ring slot being exposed. The reader then works in sweeps, and owns
``_Biris_data_int_enable`` to do what the report asks: data interrupts are off between motor
scans and back on once the next one has started. Its states:

* ``priming`` -- BI_START_CONTINUOUS written, data interrupts on, waiting for the 240 ms
  start-up to end; the first acquisition makes the ring *live* (reported, interrupts off);
* ``idle`` -- live, interrupts off: the head stands still, nothing is read;
* ``sweep`` -- the azimuth worker is starting a motor scan and has opened the sweep: the reader
  resynchronises on ACQ_LINE (whatever was acquired while idle is at a constant azimuth and is
  skipped) -- or, when continuous scanning turns straight round into it, carries on from the
  previous sweep's last frame -- and reads as in a sequence, the ring slot giving the frame;
* ``ending`` -- the motor has come to rest; the acquisition *after* the one being exposed at that
  moment is the sweep's last (the one in exposure may have sampled the azimuth before the head
  arrived; the next one starts, and samples, with the head at rest), and once it has been read
  the sweep is done (reported) and interrupts go off.

Acquisitions are numbered from 0 within a sweep. A few at each end are still made at a constant
azimuth (the exposure under way when the motor starts, and the one when it stops): the reader
hands them over, and the administrator decides: a sweep ends with its first acquisition at the
destination; those after it are the start of the next sweep when one follows straight on, and
are dropped (counted) otherwise, as are those made before the head left a start it had stood
at.
"""

from __future__ import annotations

import enum
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from biris_hw.bus.base import BusWindow
from biris_hw.devices import BirisLink
from biris_hw.server.messages import Acquisition
from regs.biexec import ACQ_LINE_END, ACQ_LINE_STARTUP, decode_param
from regs.layout import AZIMUTH_DTYPE, FRAME_DTYPE, FrameAddressing

__all__ = ["AcquisitionReader", "Drained", "RingState", "ring_length"]


def ring_length(param: bytes) -> int:
    """BI_START_CONTINUOUS's answer (PARAM): the ring's length in frames, in decimal.

    0 when the answer is unreadable or not positive: no ring to read, whoever asks (the command
    notifier, which tells the reader; the administrator, which faults on it).
    """
    try:
        return max(0, int(decode_param(param).strip(), 10))
    except ValueError:
        return 0


class RingState(enum.Enum):
    """Where continuous acquisition stands, as the reader sees it (module notes)."""

    OFF = "off"
    PRIMING = "priming"
    IDLE = "idle"
    SWEEP = "sweep"
    ENDING = "ending"


@dataclass(frozen=True)
class Drained:
    acquisitions: tuple[Acquisition, ...]
    lost: int
    finished: bool
    live: bool = False
    """Continuous mode: the ring has just become live (first acquisition begun)."""
    sweep_done: int = 0
    """Continuous mode: the seq_id of the sweep whose last acquisition this drain read."""


_NOTHING = Drained((), 0, False)


class AcquisitionReader:
    """Catch-up reader for one acquisition sequence, or for continuous-mode sweeps."""

    def __init__(
        self,
        window: BusWindow,
        link: BirisLink,
        clock: Callable[[], float],
        max_range: int,
    ) -> None:
        self.lock = threading.Lock()
        self._window = window
        self._link = link
        self._clock = clock
        self._max_range = max_range
        self._addr: FrameAddressing | None = None
        self._samples = 0
        self._period = 0.0
        self._active = False
        self._seq_id = 0
        self._n = 0
        self._next = 0
        self._t0 = math.inf
        # continuous mode
        self._ring_state = RingState.OFF
        self._ring = 0
        self._exposing = 0
        self._end: int | None = None
        self._index = 0
        self._followable = False
        self._seen = -math.inf

    def configure(self, addressing: FrameAddressing, samples: int, period_s: float) -> None:
        """Where the frames are, as learned from BIRIS at initialisation."""
        with self.lock:
            self._addr = addressing
            self._samples = samples
            self._period = period_s

    @property
    def samples(self) -> int:
        return self._samples

    @property
    def ring_state(self) -> RingState:
        return self._ring_state

    # -- single sequences (BI_ACQUIRE) ----------------------------------------------------------
    def begin(self, seq_id: int, n: int) -> None:
        """A BI_ACQUIRE of ``n`` acquisitions is about to be written; call before COMMAND."""
        with self.lock:
            self._active = True
            self._seq_id = seq_id
            self._n = n
            self._next = 0
            self._t0 = math.inf

    def drain(self, final: bool = False) -> Drained:
        """Read every acquisition completed since the last drain. Hold ``self.lock``.

        In continuous mode this is the ring's drain; otherwise the sequence's (see
        :meth:`drain_sequence`).
        """
        if self._ring_state is not RingState.OFF:
            return self._drain_ring()
        return self.drain_sequence(final)

    def drain_sequence(self, final: bool = False) -> Drained:
        """The BI_ACQUIRE sequence's drain. Hold ``self.lock``.

        ``final`` is set by the command notifier: BIRIS has finished the sequence, so whatever
        ACQ_LINE says, nothing more will complete.
        """
        if not self._active or self._addr is None:
            return _NOTHING  # no sequence: a spurious or late wake
        line = self._link.acq_line()
        now = self._clock()
        if line == ACQ_LINE_END:
            last, ref = self._n - 1, float(self._n)
        elif line >= 0:
            last, ref = min(line - 1, self._n - 1), float(line)
        elif line == ACQ_LINE_STARTUP:
            last, ref = -1, 0.0
        else:  # garbage in ACQ_LINE: read nothing now, the end of the sequence will tell
            last, ref = -1, 0.0
        if line == ACQ_LINE_END or line >= 0:
            self._observe(now, ref)
        out: list[Acquisition] = []
        for k in range(self._next, last + 1):
            out.append(self._read(k, k, self._time_of(k)))
        self._next = max(self._next, last + 1)
        finished = line == ACQ_LINE_END or final
        lost = 0
        if finished:
            lost = max(0, self._n - self._next) if final else 0
            self._active = False
        return Drained(tuple(out), lost, finished)

    def _observe(self, now: float, begun: float) -> None:
        """Acquisition ``begun`` has started by ``now``: tighten the bound on acquisition 0's."""
        self._t0 = min(self._t0, now - begun * self._period)
        self._seen = now

    def _time_of(self, k: int) -> float:
        """Middle of acquisition k's exposure, on the hardware clock."""
        return self._t0 + (k + 0.5) * self._period

    # -- continuous mode (BI_START_CONTINUOUS) ----------------------------------------------------
    def prime_ring(self) -> None:
        """BI_START_CONTINUOUS is about to be written: wait, interrupts on, for the first frame."""
        with self.lock:
            self._active = False
            self._ring_state = RingState.PRIMING
            self._ring = 0
            self._followable = False
            self._link.set_flags(data_int=True)

    def ring_started(self, ring: int) -> None:
        """BI_START_CONTINUOUS completed: BIRIS answered the ring length (0 if it did not)."""
        with self.lock:
            self._ring = max(0, ring)

    def stop_ring(self) -> None:
        """BI_STOP_CONTINUOUS completed (or the start failed): back to sequences."""
        with self.lock:
            self._ring_state = RingState.OFF
            self._ring = 0
            self._end = None
            self._followable = False
            self._link.set_flags(data_int=True)  # single sequences announce every frame

    def open_sweep(self, seq_id: int, follows: bool = False) -> None:
        """The motor scan of sweep ``seq_id`` starts now: turn data interrupts back on and
        collect from the frame in exposure -- or, when the sweep ``follows`` the one just
        ended (continuous scanning turns straight round), from the frame after that sweep's
        last, so that the turn-around loses no acquisition.

        Following needs the previous sweep to have ended cleanly and less than a lap of the
        ring ago (ACQ_LINE is a ring slot: beyond a lap, how far the ring went is ambiguous);
        otherwise the sweep resynchronises as a new one does.
        """
        with self.lock:
            if self._ring_state is not RingState.IDLE:
                return
            line = self._link.acq_line()
            now = self._clock()
            ring = self._ring
            if (
                follows
                and self._followable
                and 0 <= line < ring
                and now - self._seen < (ring - 1) * self._period
            ):
                self._exposing += (line - self._exposing) % ring
            else:
                self._exposing = max(0, line)
                self._next = self._exposing
                self._t0 = math.inf
            self._followable = False
            self._seq_id = seq_id
            self._index = 0
            self._end = None
            self._observe(now, self._exposing)
            self._ring_state = RingState.SWEEP
            self._link.set_flags(data_int=True)

    def end_sweep(self) -> Drained:
        """The motor has come to rest: what is complete now, and mark the frame after the one
        in exposure as the sweep's last (module notes). Hold ``self.lock``."""
        if self._ring_state is not RingState.SWEEP:
            return _NOTHING
        line = self._link.acq_line()
        if line < 0:
            return self._close_sweep([], 0)
        out, lost = self._read_ring_to(line)
        self._end = self._exposing + 1
        self._ring_state = RingState.ENDING
        return Drained(tuple(out), lost, False)

    def _drain_ring(self) -> Drained:
        state = self._ring_state
        if self._addr is None or state is RingState.IDLE:
            return _NOTHING  # a completion's wake, or an interrupt from before the gate shut
        line = self._link.acq_line()
        if state is RingState.PRIMING:
            if line >= 0 and self._ring > 0:
                self._ring_state = RingState.IDLE
                self._link.set_flags(data_int=False)
                return Drained((), 0, False, live=True)
            return _NOTHING
        if line == ACQ_LINE_STARTUP:
            return _NOTHING
        if line < 0:  # BIRIS stopped under the sweep: nothing more will come
            return self._close_sweep([], 0)
        out, lost = self._read_ring_to(line)
        if state is RingState.ENDING and self._end is not None and self._next > self._end:
            return self._close_sweep(out, lost, clean=True)
        return Drained(tuple(out), lost, False)

    def _read_ring_to(self, line: int) -> tuple[list[Acquisition], int]:
        """Read every frame completed before slot ``line`` (now in exposure)."""
        ring = self._ring
        if ring <= 0 or line >= ring:
            return [], 0
        self._exposing += (line - self._exposing) % ring
        self._observe(self._clock(), self._exposing)
        last = self._exposing - 1
        if self._end is not None:
            last = min(last, self._end)
        lost = max(0, (self._exposing - ring + 1) - self._next)  # overwritten by a later lap
        self._next += lost
        out: list[Acquisition] = []
        for k in range(self._next, last + 1):
            out.append(self._read(k % ring, self._index, self._time_of(k)))
            self._index += 1
        self._next = max(self._next, last + 1)
        return out, lost

    def _close_sweep(self, out: list[Acquisition], lost: int, clean: bool = False) -> Drained:
        """Back to idle; ``clean`` when every frame up to the sweep's last was read, so that a
        following sweep may carry on from the next one."""
        self._ring_state = RingState.IDLE
        self._followable = clean
        self._end = None
        self._link.set_flags(data_int=False)
        return Drained(tuple(out), lost, True, sweep_done=self._seq_id)

    # -- frames -----------------------------------------------------------------------------------
    def _read(self, slot: int, index: int, t: float) -> Acquisition:
        addr = self._addr
        assert addr is not None
        count = self._samples + 1
        nbytes = 2 * count
        start = addr.range_frame(slot)
        gap = addr.frame_size  # intensity(k) starts one frame after range(k)
        window = self._window
        if gap % 2 == 0 and nbytes <= gap <= 2 * nbytes:
            # the two frames (nearly) abut: one bus read, one conversion
            words = np.frombuffer(window.read(start, gap + nbytes), dtype=FRAME_DTYPE)
            both = words.astype(np.int16)
            rng, inten = both[:count], both[gap // 2 : gap // 2 + count]
        else:
            raw = window.read(start, nbytes)
            rng = np.frombuffer(raw, dtype=FRAME_DTYPE, count=count).astype(np.int16)
            raw_i = window.read(addr.intensity_frame(slot), nbytes)
            inten = np.frombuffer(raw_i, dtype=FRAME_DTYPE, count=count).astype(np.int16)
        # AZIMUTH_DTYPE is a big-endian signed integer
        azimuth = int.from_bytes(
            window.read(addr.azimuth_entry(slot), AZIMUTH_DTYPE.itemsize), "big", signed=True
        )
        max_range = self._max_range
        profile = rng[1:].copy()
        if max_range >= 0:
            # beyond max_range or negative, in one comparison: seen unsigned, a negative sample
            # is above 0x7FFF (and a zero is never out of range)
            bad = profile.view(np.uint16) > min(max_range, 0x7FFF)
            discarded = int(np.count_nonzero(bad))
        else:
            bad = (profile > max_range) | (profile < 0)
            discarded = int(np.count_nonzero(bad & (profile != 0)))
        profile[bad] = 0
        closest = int(rng[0])
        if closest > max_range or closest < 0:
            closest = 0
        profile.setflags(write=False)
        intensity = inten[1:].copy()
        intensity.setflags(write=False)
        return Acquisition(
            seq_id=self._seq_id,
            index=index,
            azimuth=azimuth,
            closest_mm=closest,
            profile=profile,
            intensity=intensity,
            t=t,
            discarded=discarded,
            t_origin=self._t0,
        )
