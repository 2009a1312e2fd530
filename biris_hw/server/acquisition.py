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

**Accounts.** Every acquisition BIRIS completes leaves the reader exactly once, in a
:class:`Drained`: read (``acquisitions``), known lost (``lost``: overwritten in the ring before it
could be read), or, in continuous mode, passed over unread because no sweep wanted it (``idle``).
Idle ring frames are those BIRIS completes between the ring going live and the first sweep,
between sweeps that do not follow straight on, and after the last sweep until the ring stops.
The reader does not read the ring while idle, so it counts them when it next looks at it:

* when a sweep opens without following -- it resynchronises on ACQ_LINE, and every frame from
  the first not yet accounted for up to the one now in exposure is idle;
* when the ring stops (BI_STOP_CONTINUOUS completed, or ACQ_LINE reads -128 under a sweep):
  BIRIS then names in CURRENT_FRAME the last frame it completed (the one in exposure is
  abandoned), and every frame up to it not yet accounted for is read -- if it belongs to a
  sweep still open, whose acquisitions the administrator will find stale -- or counted idle.

So nothing is counted as the ring goes live (the frames before the first sweep are counted when
it opens). The reader numbers the frames of a ring's life continuously (frame k sits in slot
``k % ring``), and what it learns at each look is a slot. Counts found where the reader cannot
post (a sweep opening, the ring stopping) are handed over with the next drain, which follows at
once: the sweep's first data interrupt, or the command notifier's drain after the stop.

**Laps, on evidence.** The frames begun between two looks are the slot advance plus whole laps,
and only the hardware clock can tell the laps (:func:`frames_between`) -- on the assumption that
BIRIS acquired at its data rate all the while. A BIRIS that hung (and perhaps resumed) made
fewer; the clock would book a lap of frames BIRIS never made for every 34 s of hang. So laps
are booked from the clock only where the evidence bears the assumption out
(:meth:`AcquisitionReader._begun_since`): the clock's count agrees with the time that passed
to within the looks' jitter, and no look since the previous one found the ring standing still.
Otherwise the slot advance alone is booked: no frame is accounted for that BIRIS is not known
to have made. Between looks less than half a lap apart the slot advance is the count whatever
happened, so the laps are only ever in doubt over a long unwatched stretch, and a live ring is
watched:

**The ring must progress.** While the ring is live and no sweep reads it, nothing else looks at
it: data interrupts are off. The administrator counts the ring's progress as something BIRIS
owes, so the BIRIS timeout runs for it as for a command (when the timeout is enabled), and each
time it runs out the level-2 routine looks (:meth:`AcquisitionReader.watch_ring`, called by
:class:`~biris_hw.server.tasks.BirisRecheck`). A look that finds no frame begun since a look at
least the tolerance earlier (:meth:`AcquisitionReader.tolerance_s`) has found the ring standing
still: BIRIS is hung, which is the ``timeout`` fault, and the ring is marked *stalled*, so that
no later look books laps across the hang. Any other look keeps the laps resolvable, since it
comes a BIRIS timeout (4 s, 120 frames) after the previous one.

**CURRENT_FRAME after a stop** names the last slot the stopped ring completed, -1 when it
completed none (stopped in its start-up or during its first exposure). A slot left there by an
earlier ring would otherwise read as frames of this one.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from biris_hw.bus.base import BusWindow
from biris_hw.devices import BirisLink
from biris_hw.server.messages import Acquisition
from biris_hw.timebase import timebase_of
from regs.biexec import ACQ_LINE_END, ACQ_LINE_STARTUP, OFF_CURRENT_FRAME, decode_param
from regs.layout import AZIMUTH_DTYPE, FRAME_DTYPE, FrameAddressing

__all__ = [
    "STARTUP_S",
    "AcquisitionReader",
    "Drained",
    "RingState",
    "frames_between",
    "ring_length",
]

log = logging.getLogger(__name__)

LOOK_JITTER_FRAMES = 2.0
"""How far (acquisition periods) the clock's count of frames between two looks may stray from
the slots they saw while BIRIS acquires at its data rate: each look falls somewhere within the
period of the frame it sees, under one period either way."""

LOOK_SLACK_REAL_S = 0.1
"""Real seconds a busy host may take between reading ACQ_LINE and reading the clock (the BIRIS
timeout's own real slack), added to :data:`LOOK_JITTER_FRAMES`
(:meth:`AcquisitionReader.tolerance_s`): scaled to hardware time by the time base, so nothing
on virtual time, where a look takes no time."""

STARTUP_S = 0.240
"""The report's start-up of an acquisition sequence: BIRIS acquires nothing for this long after
BI_ACQUIRE or BI_START_CONTINUOUS (the simulator rounds it up to whole video fields). A ring's
first frame therefore begins no sooner than this after it was started."""


def ring_length(param: bytes) -> int:
    """BI_START_CONTINUOUS's answer (PARAM): the ring's length in frames, in decimal.

    0 when the answer is unreadable or not positive: no ring to read, whoever asks (the command
    notifier, which tells the reader; the administrator, which faults on it).
    """
    try:
        return max(0, int(decode_param(param).strip(), 10))
    except ValueError:
        return 0


def frames_between(advance: int, elapsed: float, ring: int) -> int:
    """How many frames a ring of ``ring`` slots began between two looks at it.

    ``advance`` is how far the slot moved, ``(slot_now - slot_then) % ring``; ``elapsed`` the
    hardware time between the looks in acquisition periods. The true count is ``advance`` plus
    a whole number of laps, ``advance + ring * m``; ``elapsed`` estimates it with an error ``e``
    that is only the looks' jitter: each look falls somewhere within the period of the frame it
    sees (under one period either way), plus how stale a register read is against the clock
    read beside it, plus any drift of the host clock against BIRIS's video clock. Then
    ``(elapsed - advance) / ring = m + e / ring``, which rounds to ``m`` exactly while ``|e|`` is
    below half a lap (512 frames, 17 s, for the 1024-frame ring at 2 fields an acquisition).
    The result may be ``advance - ring`` when the estimate says the slot did not move forward at
    all (the caller bounds it).
    """
    if ring <= 0:
        return 0
    laps = math.floor((elapsed - advance) / ring + 0.5)
    return advance + ring * laps


class RingState(enum.Enum):
    """Where continuous acquisition stands, as the reader sees it (module notes)."""

    OFF = "off"
    PRIMING = "priming"
    IDLE = "idle"
    SWEEP = "sweep"
    ENDING = "ending"


@dataclass(frozen=True)
class Drained:
    """What one look at BIRIS memory found; every acquisition made leaves the reader in
    exactly one of ``acquisitions``, ``lost`` and ``idle`` (module notes, "Accounts")."""

    acquisitions: tuple[Acquisition, ...]
    lost: int
    """Acquisitions known to be gone: overwritten in the ring before they could be read, or a
    sequence's that BIRIS finished without announcing."""
    finished: bool
    live: bool = False
    """Continuous mode: the ring has just become live (first acquisition begun)."""
    sweep_done: int = 0
    """Continuous mode: the seq_id of the sweep whose last acquisition this drain read."""
    idle: int = 0
    """Continuous mode: ring frames BIRIS completed while no sweep wanted them, skipped unread
    (before the first sweep, between sweeps that do not follow straight on, after the last one
    until the ring stopped)."""
    started: int = 0
    """A BI_ACQUIRE sequence's seq_id, the first time a drain sees its start-up over (ACQ_LINE
    no longer -1): the moment a report-mode scan's motor starts (SEQUENCE_STARTED)."""
    started_at: float = 0.0
    """With ``started``: the bound on when acquisition 0 began (hardware clock)."""
    untrusted: int = 0
    """Of ``lost``: frames read but dropped because BIRIS was seen entering their ring slot
    again while they were read (:meth:`AcquisitionReader._read_frames`)."""


_NOTHING = Drained((), 0, False)


class AcquisitionReader:
    """Catch-up reader for one acquisition sequence, or for continuous-mode sweeps."""

    def __init__(
        self,
        window: BusWindow,
        link: BirisLink,
        clock: Callable[[], float],
        max_range: int,
        *,
        look_slack_real_s: float = LOOK_SLACK_REAL_S,
    ) -> None:
        self._look_slack_real_s = look_slack_real_s
        """:data:`LOOK_SLACK_REAL_S` unless told (a test's scripted clock is no busy host)."""
        # a lock on the time base: a drain holds it across bus reads, which a simulator may slow
        # by sleeping in hardware time (on virtual time, a waiter for a plain lock holds time)
        self._timebase = timebase_of(clock)
        self.lock = self._timebase.Lock()
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
        """The next acquisition to read; in continuous mode, the first ring frame (numbered
        over the ring's life) not yet accounted for."""
        self._t0 = math.inf
        self._started = False
        """The BI_ACQUIRE sequence's start-up has been seen over (SEQUENCE_STARTED sent)."""
        self._written = False
        """BI_ACQUIRE has been written to COMMAND (:meth:`written`)."""
        self._written_at = -math.inf
        self._seen_running = False
        """ACQ_LINE has been seen at -1 or at an acquisition since BI_ACQUIRE was written: this
        sequence's own, so a -128 seen after it is this sequence's end."""
        # continuous mode
        self._ring_state = RingState.OFF
        self._ring = 0
        self._exposing = 0
        """The ring frame (numbered over the ring's life) seen in exposure at ``_seen``."""
        self._end: int | None = None
        self._index = 0
        self._followable = False
        self._seen = -math.inf
        self._primed_at = -math.inf
        self._halted = False
        """BIRIS was seen to have stopped the ring and every frame it made is accounted for."""
        self._moved_at = -math.inf
        """When a look last found a frame begun since the look before (or the ring live)."""
        self._stalled = False
        """A look found the ring standing still, and none has seen it move since: the clock
        cannot tell the laps from then on (module notes, "Laps, on evidence")."""
        self._stop_written_at = math.inf
        """When BI_STOP_CONTINUOUS was last written to this ring (:meth:`stop_written`)."""
        # accounted for, not handed over yet (module notes)
        self._owed_acqs: list[Acquisition] = []
        self._owed_lost = 0
        self._owed_idle = 0
        self._untrusted = 0
        """Frames dropped as untrusted since the last hand-over (each counted in a lost)."""

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

    def _hand(self, drained: Drained) -> Drained:
        """``drained`` with what was accounted for where nothing could be posted (a sweep
        opening, the ring stopping), and the untrusted frames among everything lost so far:
        each such count is handed over exactly once."""
        if not (self._owed_acqs or self._owed_lost or self._owed_idle or self._untrusted):
            return drained
        handed = dataclasses.replace(
            drained,
            acquisitions=(*self._owed_acqs, *drained.acquisitions),
            lost=drained.lost + self._owed_lost,
            idle=drained.idle + self._owed_idle,
            untrusted=drained.untrusted + self._untrusted,
        )
        self._owed_acqs, self._owed_lost, self._owed_idle, self._untrusted = [], 0, 0, 0
        return handed

    # -- single sequences (BI_ACQUIRE) ----------------------------------------------------------
    def begin(self, seq_id: int, n: int) -> None:
        """A BI_ACQUIRE of ``n`` acquisitions is about to be written; call before COMMAND."""
        with self.lock:
            self._active = True
            self._seq_id = seq_id
            self._n = n
            self._next = 0
            self._t0 = math.inf
            self._started = False
            self._written = False
            self._seen_running = False

    def written(self) -> float:
        """BI_ACQUIRE has just been written to COMMAND (by biris_cmd_transfer, after
        :meth:`begin`); returns the hardware time of the write, noted as the sequence's.

        Until then BIEXEC_COM still shows the previous sequence (COMMAND 0, ACQ_LINE -128):
        see :meth:`_sequence_line`."""
        now = self._clock()  # before the lock: a drain holding it must not make it late
        with self.lock:
            self._written = True
            self._written_at = now
        return now

    def drain(self, final: bool = False) -> Drained:
        """Read every acquisition completed since the last drain. Hold ``self.lock``.

        In continuous mode this is the ring's drain; otherwise the sequence's (see
        :meth:`drain_sequence`).
        """
        with self._window.transaction():  # ACQ_LINE and the frames: one stop of a VM-USB
            if self._ring_state is not RingState.OFF:
                return self._hand(self._drain_ring())
            return self.drain_sequence(final)

    def drain_sequence(self, final: bool = False, ran: bool = True) -> Drained:
        """The BI_ACQUIRE sequence's drain. Hold ``self.lock``.

        ``final`` is set by the command notifier: BIRIS has finished the sequence, so whatever
        ACQ_LINE says, nothing more will complete; ``ran`` False with it when BIRIS refused the
        BI_ACQUIRE (a bad STATUS), whose frames are then an earlier sequence's. It also hands
        over what a ring's stop accounted for (the command notifier drains so right after
        :meth:`stop_ring`).
        """
        return self._hand(self._drain_sequence(final, ran))

    def _sequence_line(self, final: bool, ran: bool) -> int | None:
        """ACQ_LINE, if it can be trusted to be this sequence's; None when it cannot.

        BIEXEC_COM is shared by every sequence: from :meth:`begin` until BIRIS sees the new
        command (at its next vertical sync, up to a field after the write) it still says the
        previous sequence ended (ACQ_LINE -128), and a data interrupt the host delivers late
        can wake the reader then. Taken at its word, that -128 would read the previous
        sequence's frames as this one's, all of them, and end this one before it began. So a
        -128 is this sequence's end only when it is known to follow this sequence: ACQ_LINE
        was seen at -1 (BIRIS's start-up) or at an acquisition since the write, or BIRIS has
        completed the command (COMMAND read back 0 after the write, before ACQ_LINE: the
        command cannot complete before its sequence ends), or the command notifier says so
        (``final``). Otherwise the reader waits: the completion will tell. ACQ_LINE -1 or an
        acquisition index are only ever this sequence's once it has been written (the
        previous one ended at -128 before its command completed).
        """
        if final:
            if not ran and not self._seen_running:
                return None  # refused: nothing of this sequence was ever made
            return self._link.acq_line()
        if not self._written:
            return None  # COMMAND not written yet: all of BIEXEC_COM is the previous sequence's
        if self._seen_running:
            return self._link.acq_line()
        completed = self._link.command() == 0
        line = self._link.acq_line()
        if line == ACQ_LINE_STARTUP or line >= 0:
            self._seen_running = True
            return line
        if line == ACQ_LINE_END and completed:
            return line
        return None

    def _drain_sequence(self, final: bool, ran: bool = True) -> Drained:
        if not self._active or self._addr is None:
            return _NOTHING  # no sequence: a spurious or late wake
        read = self._sequence_line(final, ran)
        if read is None:
            if not final:
                return _NOTHING
            self._active = False  # refused: nothing was made, nothing is lost
            return Drained((), 0, True)
        line = read
        if line == ACQ_LINE_STARTUP or line >= 0:
            self._seen_running = True
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
        drained = Drained(tuple(out), lost, finished)
        if not self._started and (line == ACQ_LINE_END or line >= 0 or finished):
            self._started = True  # announced once, however late (an end with no interrupt)
            began = self._t0 if math.isfinite(self._t0) else now
            drained = dataclasses.replace(drained, started=self._seq_id, started_at=began)
        return drained

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
            self._halted = False
            self._stalled = False
            self._exposing = self._next = 0  # a new ring: its frames are numbered from 0
            self._end = None
            self._t0 = math.inf
            self._primed_at = self._seen = self._moved_at = self._clock()
            self._stop_written_at = math.inf
            self._link.set_flags(data_int=True)

    def ring_started(self, ring: int) -> None:
        """BI_START_CONTINUOUS completed: BIRIS answered the ring length (0 if it did not)."""
        with self.lock:
            self._ring = max(0, ring)

    def stop_ring(self) -> None:
        """BI_STOP_CONTINUOUS completed (or the start failed): back to sequences.

        BIRIS has stopped: every frame it completed and the reader has not accounted for yet is
        accounted for now (module notes), and handed over by the next drain.
        """
        with self.lock:
            state = self._ring_state
            try:
                if state is not RingState.OFF:
                    out, lost = self._stopped(
                        self._clock(), read=state in (RingState.SWEEP, RingState.ENDING)
                    )
                    self._owed_acqs += out
                    self._owed_lost += lost
            finally:  # a bus error reading the ring must not leave the reader in it
                self._ring_state = RingState.OFF
                self._ring = 0
                self._end = None
                self._followable = False
            self._link.set_flags(data_int=True)  # single sequences announce every frame

    def stop_written(self) -> None:
        """BI_STOP_CONTINUOUS is about to be written (by biris_cmd_transfer): BIRIS stops the
        ring no sooner than now, which bounds when it stopped (:meth:`_frames_done`)."""
        now = self._clock()  # before the lock, as written() does
        with self.lock:
            self._stop_written_at = min(self._stop_written_at, now)

    def open_sweep(self, seq_id: int, follows: bool = False) -> None:
        """The motor scan of sweep ``seq_id`` starts now: turn data interrupts back on and
        collect from the frame in exposure -- or, when the sweep ``follows`` the one just
        ended (continuous scanning turns straight round), from the frame after that sweep's
        last, so that the turn-around loses no acquisition.

        Following needs the previous sweep to have ended cleanly and less than a lap of the
        ring ago (beyond a lap its frames after the last are overwritten); otherwise the sweep
        resynchronises as a new one does, and the frames it skips are idle (module notes).
        """
        with self.lock:
            if self._ring_state is not RingState.IDLE:
                return
            line = self._link.acq_line()
            now = self._clock()
            ring = self._ring
            seen = 0 <= line < ring
            if seen:
                self._exposing = self._advance(line, now)
            # the previous sweep's frames after its last are still in the ring while less than
            # a lap has begun since (counted in frames: idle looks keep the count)
            following = (
                seen and follows and self._followable and self._exposing - self._next < ring - 1
            )
            if not following:
                self._owed_idle += max(0, self._exposing - self._next)
                self._next = self._exposing
                self._t0 = math.inf
            if seen:
                self._observe(now, self._exposing)
            self._followable = False
            self._seq_id = seq_id
            self._index = 0
            self._end = None
            self._ring_state = RingState.SWEEP
            self._link.set_flags(data_int=True)

    def end_sweep(self) -> Drained:
        """The motor has come to rest: what is complete now, and mark the frame after the one
        in exposure as the sweep's last (module notes). Hold ``self.lock``."""
        if self._ring_state is not RingState.SWEEP:
            return self._hand(_NOTHING)
        line = self._link.acq_line()
        now = self._clock()
        if line < 0:
            return self._hand(self._cut_short(line, now))
        out, lost = self._read_ring_to(line, now)
        self._end = self._exposing + 1
        self._ring_state = RingState.ENDING
        return self._hand(Drained(tuple(out), lost, False))

    def _drain_ring(self) -> Drained:
        state = self._ring_state
        if self._addr is None or state is RingState.IDLE:
            return _NOTHING  # a completion's wake, or an interrupt from before the gate shut
        line = self._link.acq_line()
        now = self._clock()
        if state is RingState.PRIMING:
            if 0 <= line < self._ring:
                self._go_live(line, now)
                return Drained((), 0, False, live=True)
            return _NOTHING
        if line == ACQ_LINE_STARTUP:
            return _NOTHING
        if line < 0:
            return self._cut_short(line, now)
        out, lost = self._read_ring_to(line, now)
        if state is RingState.ENDING and self._end is not None and self._next > self._end:
            return self._close_sweep(out, lost, clean=True)
        return Drained(tuple(out), lost, False)

    def _go_live(self, line: int, now: float) -> None:
        """The ring's first look: slot ``line`` in exposure. Frame 0 began no sooner than the
        start-up after priming, which resolves the laps; nothing is accounted for yet."""
        self._ring_state = RingState.IDLE
        self._link.set_flags(data_int=False)
        begun = (now - self._primed_at - STARTUP_S) / self._period if self._period > 0 else 0.0
        self._exposing = max(line, self._begun_since(line, begun))
        self._seen = self._moved_at = now
        self._next = 0

    def tolerance_s(self) -> float:
        """How far (hardware seconds) two looks may disagree with the clock while BIRIS
        acquires at its data rate: :data:`LOOK_JITTER_FRAMES` periods, plus the host's own
        delay (:data:`LOOK_SLACK_REAL_S` unless told) scaled to hardware time."""
        slack = self._timebase.hw_from_real(self._look_slack_real_s)
        return LOOK_JITTER_FRAMES * self._period + slack

    def _begun_since(self, advance: int, elapsed: float, earliest: float | None = None) -> int:
        """Frames begun since the last look, the slot having moved ``advance`` in ``elapsed``
        periods: the clock's count (:func:`frames_between`) where the evidence bears out that
        BIRIS acquired all the while, else the slot advance alone (module notes, "Laps, on
        evidence"). Never negative (the ring never goes back).

        ``earliest`` (periods, at most ``elapsed``): BIRIS stopped acquiring somewhere between
        then and ``elapsed`` by design (a stop), so a count anywhere in that span is borne out.
        """
        frames = max(0, frames_between(advance, elapsed, self._ring))
        if frames <= advance:
            return frames  # within the lap the slot shows: no lap to doubt
        tolerance = self.tolerance_s() / self._period if self._period > 0 else 0.0
        low = elapsed if earliest is None else min(earliest, elapsed)
        borne_out = low - tolerance <= frames <= elapsed + tolerance
        if self._stalled or not borne_out:
            log.warning(
                "continuous acquisition: the ring went %.1f s unwatched while BIRIS was %s; "
                "%d frame(s) booked, not the %d the clock would give: BIRIS is not known to "
                "have made them",
                elapsed * self._period,
                "seen standing still" if self._stalled else "not acquiring at its data rate",
                advance,
                frames,
            )
            return advance
        return frames

    def _advance(self, line: int, now: float) -> int:
        """The ring frame in exposure now, seen as slot ``line``: the frame seen last, plus
        the frames begun since (:meth:`_begun_since`; the ring never goes back).

        A frame begun since is the ring moving (``_moved_at``); none begun for longer than the
        tolerance since one was is the ring standing still (``_stalled``)."""
        ring = self._ring
        advance = (line - self._exposing) % ring
        elapsed = (now - self._seen) / self._period if self._period > 0 else float(advance)
        self._halted = False  # BIRIS is acquiring into the ring
        exposing = self._exposing + self._begun_since(advance, elapsed)
        if exposing > self._exposing:
            self._moved_at, self._stalled = now, False
        elif now - self._moved_at > self.tolerance_s():
            self._stalled = True
        return exposing

    def watch_ring(self) -> bool:
        """Look at a ring no sweep reads (module notes, "The ring must progress"); True when
        the ring is seen moving, False when it stands still or there is nothing to watch (no
        idle ring; ACQ_LINE not a slot). Hold ``self.lock``.

        The look keeps the frame in exposure, so that the laps stay resolvable however long
        the ring idles; the frames begun are counted idle when the next sweep opens or the
        ring stops, as ever."""
        ring = self._ring
        if self._ring_state is not RingState.IDLE or ring <= 0:
            return False
        line = self._link.acq_line()
        now = self._clock()
        if not 0 <= line < ring:
            return False  # BIRIS stopped the ring: a completion, if any, speaks for it
        self._exposing = self._advance(line, now)
        self._seen = now
        return not self._stalled

    def _read_ring_to(self, line: int, now: float) -> tuple[list[Acquisition], int]:
        """Read every frame completed before slot ``line`` (now in exposure)."""
        ring = self._ring
        if not 0 <= line < ring:
            return [], 0
        self._exposing = self._advance(line, now)
        self._observe(now, self._exposing)
        return self._read_frames(self._exposing, self._exposing - ring + 1)

    def _read_frames(self, upto: int, oldest: int) -> tuple[list[Acquisition], int]:
        """Read the sweep's frames from ``_next`` to ``upto - 1`` (to its last, once known);
        those older than ``oldest``, the oldest the ring still holds, are counted lost."""
        last = upto - 1
        if self._end is not None:
            last = min(last, self._end)
        lost = max(0, min(oldest, last + 1) - self._next)  # overwritten by a later lap
        self._next += lost
        ring = self._ring
        first = self._next
        out: list[Acquisition] = []
        for k in range(first, last + 1):
            out.append(self._read(k % ring, self._index, self._time_of(k)))
            self._index += 1
        self._next = max(self._next, last + 1)
        if out:
            out, dropped = self._trusted(out, first)
            lost += dropped
        return out, lost

    def _trusted(self, out: list[Acquisition], first: int) -> tuple[list[Acquisition], int]:
        """The frames just read (``out``, frame numbers from ``first``) that BIRIS cannot have
        begun to overwrite while they were read; the number dropped.

        ACQ_LINE is read again after the frames: a ring slot holds frame k until frame k + ring
        begins in it, so every frame up to ``exposing - ring`` (``exposing`` read after) may
        have been torn by the next lap while it was read. What ACQ_LINE said before the read
        bounded what was read; what it says after bounds what can be trusted. (Far behind
        only: a lap is 34 s at 2 fields an acquisition.) A frame so dropped is lost, and
        counted as untrusted; the sweep's later frames are kept.
        """
        line = self._link.acq_line()
        if not 0 <= line < self._ring:
            return out, 0  # BIRIS stopped (-128): nothing more can be written over them
        now = self._clock()
        self._exposing = self._advance(line, now)
        self._observe(now, self._exposing)
        limit = self._exposing - self._ring  # frames <= this may be torn
        drop = max(0, min(len(out), limit - first + 1))
        if drop:
            self._untrusted += drop
        return out[drop:], drop

    def _cut_short(self, line: int, now: float) -> Drained:
        """ACQ_LINE negative under a sweep: BIRIS stopped (-128), or worse; the sweep ends with
        what BIRIS completed for it (module notes) and cannot be followed."""
        out, lost = self._stopped(now, read=True) if line == ACQ_LINE_END else ([], 0)
        return self._close_sweep(out, lost)

    def _stopped(self, now: float, *, read: bool) -> tuple[list[Acquisition], int]:
        """BIRIS has stopped the ring: account for every frame it completed, once. ``read``:
        a sweep is open, and its frames are read (the rest, after its last, are idle)."""
        if self._halted:
            return [], 0
        done = self._frames_done(now)
        if read and not math.isfinite(self._t0):
            # a sweep opened as the stop landed (ACQ_LINE already -128): frame ``done``, the
            # one the stop abandoned, had begun by now -- the only bound its frames' times have
            self._observe(now, done)
        out, lost = self._read_frames(done, done - self._ring) if read else ([], 0)
        self._owed_idle += max(0, done - self._next)
        self._next = max(self._next, done)
        self._exposing, self._seen = self._next, now
        self._halted = True
        return out, lost

    def _frames_done(self, now: float) -> int:
        """How many frames the stopped ring completed in its life.

        CURRENT_FRAME names the last completed slot (-1: none); the frames after the one last
        seen in exposure resolve into laps on evidence (:meth:`_begun_since`). BIRIS stopped
        between BI_STOP_CONTINUOUS's write (:meth:`stop_written`) and ``now`` (the command's
        completion came after), so the clock's count is borne out anywhere in that span: a
        stop noticed late is no stall. Before the report's start-up and one period have
        passed since priming, no frame can have completed.
        """
        ring, period = self._ring, self._period
        if ring <= 0 or period <= 0:
            return self._next  # no ring ever started
        since_first = (now - self._primed_at - STARTUP_S) / period
        if since_first < 1:
            return self._next
        if self._ring_state is RingState.PRIMING:
            # never seen live: from frame 0's earliest start
            index, origin = 0, self._primed_at + STARTUP_S
        else:
            index, origin = self._exposing, self._seen
        elapsed = (now - origin) / period
        earliest = min(elapsed, (self._stop_written_at - origin) / period)
        last = self._current_frame()
        if not 0 <= last < ring:
            return max(self._next, index)  # unreadable: nothing beyond what was seen
        advance = (last + 1 - index) % ring
        return max(self._next, index + self._begun_since(advance, elapsed, earliest))

    def _current_frame(self) -> int:
        """CURRENT_FRAME, signed: once BIRIS has stopped a ring, the slot of the last frame it
        completed, -1 when it completed none (Appendix D: BIEXEC_COM "would be used to point to
        the most recent acquisition"). Read through the link's window: BirisLink has no
        accessor for it."""
        link = self._link
        raw = link.window.read16(link.base + OFF_CURRENT_FRAME)
        return raw - 0x10000 if raw & 0x8000 else raw

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
        # one read_many: the frames and the azimuth entry in one bus transaction where the
        # window can (the VM-USB builds one list of them: one round trip per acquisition)
        azimuth_span = (addr.azimuth_entry(slot), AZIMUTH_DTYPE.itemsize)
        if gap % 2 == 0 and nbytes <= gap <= 2 * nbytes:
            # the two frames (nearly) abut: one span, one conversion
            frames, raw_az = window.read_many([(start, gap + nbytes), azimuth_span])
            both = np.frombuffer(frames, dtype=FRAME_DTYPE).astype(np.int16)
            rng, inten = both[:count], both[gap // 2 : gap // 2 + count]
        else:
            raw, raw_i, raw_az = window.read_many(
                [(start, nbytes), (addr.intensity_frame(slot), nbytes), azimuth_span]
            )
            rng = np.frombuffer(raw, dtype=FRAME_DTYPE, count=count).astype(np.int16)
            inten = np.frombuffer(raw_i, dtype=FRAME_DTYPE, count=count).astype(np.int16)
        # AZIMUTH_DTYPE is a big-endian signed integer
        azimuth = int.from_bytes(raw_az, "big", signed=True)
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
