"""The scan sequencer: single and continuous scans, their buffers, and the latest point.

The report's rules it keeps:

* a scan completes when both AZ_SCAN_DONE and BIRIS_CMD_COMPLETE have arrived (in continuous
  acquisition, AZ_SCAN_DONE and SWEEP_DATA_DONE): :meth:`ScanSequencer.part_done`;
* continuous scans alternate CW and CCW and start the next sweep by themselves, until
  BIRIS_STOP_SCAN_RQST, which ends scanning at the completion of the current sweep:
  :meth:`ScanSequencer.following`;
* data are buffered per direction and double-buffered: a client always gets the last complete
  scan of a direction, never a mix (:attr:`ScanSequencer.buffers`, replaced whole);
* "any change in sensor elevation must be completed before an acquisition scan is executed": a
  scan asked for while the head tilts (or, in continuous acquisition, before the ring is live)
  is accepted and *deferred* (:class:`DeferredScan`).

In continuous acquisition (Appendix D) a sweep needs no BIRIS command: only the motor is ordered,
the azimuth worker opens the sweep once the motor runs, and a sweep ends with its first
acquisition at the destination. When continuous scanning turns straight round, the acquisitions
made at the turn-around after that one begin the next sweep, and its data carry on from there:
the stream of acquisitions is cut into sweeps without a hole, so the blind time between two
sweeps is one acquisition period. Otherwise (a single scan, a tilt between sweeps) acquisitions
made with the head standing at either end are dropped and counted (``constant_azimuth``).

The sequencer owns that state and decides; the administrator issues the orders it asks for.

It also keeps the administrator's side of the acquisition accounts
(:mod:`~biris_hw.server.counters`): every acquisition NEW_POINT brings is counted as read when
:meth:`ScanSequencer.classify` sees it, and ends up in exactly one of: a completed scan
(:meth:`ScanSequencer.complete`), standing (``constant_azimuth``: made at a sweep's start, or a
turn-around no sweep took), stale, or aborted (:meth:`ScanSequencer.forget`: the scan a fault or
reset abandons, with its tail) -- or is still held by the scan under way, or by the one just
finished until its tail is taken (:meth:`ScanSequencer.in_progress`).
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

from biris_hw.data import Direction, Point, Scan
from biris_hw.geometry import Mount
from biris_hw.server.counters import Counters
from biris_hw.server.messages import Acquisition
from biris_hw.server.scan_assembly import ActiveScan, build_scan, point_of
from biris_hw.server.scan_timing import ScanTiming

__all__ = ["FIRST_SWEEP", "AcquisitionFate", "DeferredScan", "ScanSequencer"]

FIRST_SWEEP = "the first sweep of a continuous scan, from where the head stood, not from a limit"
"""Why a continuous scan's first sweep is partial."""


@dataclass(frozen=True)
class DeferredScan:
    """A scan accepted while BIRIS could not acquire (a tilt, the ring not live yet).

    ``destination`` None: the first sweep of a continuous scan, towards whichever limit the head
    is not at when it starts.
    """

    destination: int | None


class AcquisitionFate(enum.Enum):
    """What NEW_POINT does with one acquisition."""

    KEPT = "kept"
    STALE = "stale"  # of a sequence no longer waited for
    STANDING = "standing"  # made with the head standing at a sweep's end: dropped, counted
    TAIL = "tail"  # after the sweep's end: the next sweep's start, if one follows straight on


class ScanSequencer:
    """Scans under way, asked for, and done: every field of scanning, owned here."""

    def __init__(
        self, counters: Counters, mount: Mount | None, timing: ScanTiming | None = None
    ) -> None:
        self._counters = counters
        self._mount = mount
        self._seq_ids = 0
        self.scan: ActiveScan | None = None
        self._closing: ActiveScan | None = None
        """The scan that has just finished (both halves done), until its acquisitions are
        settled: completed as a Scan, or abandoned by a fault, and its tail taken or dropped."""
        self.deferred: DeferredScan | None = None
        self.continuous: tuple[int, int] | None = None
        """Continuous scanning's (CW, CCW) limits while it runs."""
        self.stop_pending = False
        self.buffers: dict[Direction, Scan | None] = {Direction.CW: None, Direction.CCW: None}
        self._seq: dict[Direction, int] = {Direction.CW: 0, Direction.CCW: 0}
        self.latest_point: Point | None = None
        self.samples = 0
        self.timing = timing if timing is not None else ScanTiming()
        """The acquisition period and motor-start delay report-mode scans are counted with."""

    # -- where scanning stands ---------------------------------------------------------------
    def busy(self) -> bool:
        """A scan runs or waits to start."""
        return self.scan is not None or self.deferred is not None

    def active(self) -> bool:
        """A scan runs, waits, or continuous scanning is on."""
        return self.busy() or self.continuous is not None

    # -- starting ----------------------------------------------------------------------------
    def start_continuous(self, cw: int, ccw: int) -> None:
        self.continuous = (cw, ccw)
        self.stop_pending = False

    def first_limit(self, position: int) -> int:
        """Where a continuous scan's first sweep goes from ``position``."""
        assert self.continuous is not None
        cw, ccw = self.continuous
        return cw if position != cw else ccw

    def defer(self, destination: int | None) -> None:
        self.deferred = DeferredScan(destination)

    def take_deferred(self) -> DeferredScan | None:
        deferred, self.deferred = self.deferred, None
        return deferred

    def open_scan(
        self,
        dest: int,
        position: int,
        elevation: int,
        n: int = 0,
        *,
        ring: bool = False,
        follows: bool = False,
    ) -> ActiveScan:
        """A new scan (report mode: ``n`` acquisitions; ring: a sweep) from ``position``."""
        direction = Direction.CCW if dest > position else Direction.CW
        self._seq_ids += 1
        scan = ActiveScan(
            direction,
            dest,
            n,
            self._seq_ids,
            elevation=elevation,
            ring=ring,
            partial=self._partial(dest, position),
            partial_reason=FIRST_SWEEP if self._partial(dest, position) else "",
            start=position,
            left_start=follows,  # the turn-around's acquisitions begin it
        )
        self.scan = scan
        return scan

    def _partial(self, dest: int, position: int) -> bool:
        """A continuous scan's sweep that does not start at the limit opposite its destination
        covers only part of the span (the first sweep, from wherever the head stood)."""
        if self.continuous is None:
            return False
        cw, ccw = self.continuous
        return position != (ccw if dest == cw else cw)

    def stop(self) -> bool:
        """BIRIS_STOP_SCAN_RQST; True when it ended continuous scanning at once (no sweep had
        started yet: a deferred first sweep is simply forgotten)."""
        if self.continuous is None:
            return False
        if self.scan is None and self.deferred is not None:
            self.deferred = None
            self.continuous = None
            return True
        self.stop_pending = True
        return False

    # -- data --------------------------------------------------------------------------------
    def classify(self, acq: Acquisition) -> AcquisitionFate:
        """Whether NEW_POINT keeps ``acq`` in the scan under way.

        Every acquisition NEW_POINT brings passes here exactly once, so it is counted here as
        read (``acquisitions_read``); its fate's counter settles it.
        """
        self._counters.acquisitions_read += 1
        scan = self.scan
        if scan is None or acq.seq_id != scan.seq_id:
            return AcquisitionFate.STALE
        if not scan.head_moving(acq.azimuth):
            if scan.ring and scan.at_end:
                scan.tail.append(acq)
                return AcquisitionFate.TAIL
            scan.standing += 1
            scan.standing_start += int(not scan.left_start)
            return AcquisitionFate.STANDING
        return AcquisitionFate.KEPT

    def keep(self, scan: ActiveScan, acq: Acquisition) -> Point:
        """Make ``acq`` part of ``scan`` and the latest point. The scan numbers its own rows:
        a ring sweep's frames, and a BI_ACQUIRE's after the ones made standing at its start,
        are not its row numbers (kept in order: the reader reads a sequence in order)."""
        if scan.ring:
            acq = dataclasses.replace(acq, seq_id=scan.seq_id, index=len(scan.acqs))
        elif acq.index != len(scan.acqs):
            acq = dataclasses.replace(acq, index=len(scan.acqs))
        scan.acqs[acq.index] = acq
        self._counters.acquisitions += 1
        self._counters.discarded_samples += acq.discarded
        point = point_of(acq, scan, self._seq[scan.direction] + 1, self._mount)
        self.latest_point = point
        return point

    def carry_tail(self, after: ActiveScan, scan: ActiveScan, follows: bool) -> list[Point]:
        """``after``'s turn-around acquisitions begin ``scan`` if it follows straight on;
        otherwise they were made standing and are dropped (counted)."""
        points = [self.keep(scan, acq) for acq in after.tail] if follows else []
        if not follows:
            self._counters.constant_azimuth += len(after.tail)
        after.tail.clear()
        self._settled(after)
        return points

    def drop_tail(self, scan: ActiveScan) -> None:
        """No sweep follows straight on: the turn-around's acquisitions were made standing."""
        self._counters.constant_azimuth += len(scan.tail)
        scan.tail.clear()
        self._settled(scan)

    def _settled(self, scan: ActiveScan) -> None:
        """``scan`` holds nothing unsettled any more: it is no longer the closing scan."""
        if self._closing is scan and scan.pending() == 0:
            self._closing = None

    def in_progress(self) -> int:
        """Acquisitions read and held, not yet settled in any counter: those of the scan under
        way (kept, and its tail), and the tail of the one just completed until the next sweep
        takes it or it is dropped (the accounts' "in progress")."""
        return sum(scan.pending() for scan in (self.scan, self._closing) if scan is not None)

    # -- the end of a scan -------------------------------------------------------------------
    def part_done(
        self, scan: ActiveScan | None, *, motion: bool = False, cmd_status: int | None = None
    ) -> bool:
        """One half of ``scan`` is done; True when both are (it is then no longer running)."""
        if scan is None or self.scan is not scan:
            return False
        if motion:
            scan.az_done = True
        if cmd_status is not None:
            scan.cmd_done = True
            scan.status = cmd_status
        if scan.az_done and scan.cmd_done:
            self.scan = None
            self._close(scan)
            return True
        return False

    def _close(self, scan: ActiveScan) -> None:
        """``scan`` has finished: it holds its acquisitions until completed or abandoned.

        A previous closing scan still holding something (a tail no sweep took nor dropped: the
        administrator could not start the next sweep) gives it up here, so that nothing is held
        for ever: its tail as standing, anything it kept but never completed as aborted.
        """
        previous = self._closing
        if previous is not None and previous is not scan:
            if not previous.completed:
                self._counters.aborted_acquisitions += len(previous.acqs)
            self._counters.constant_azimuth += len(previous.tail)
            previous.tail.clear()
        self._closing = scan

    def complete(self, scan: ActiveScan) -> Scan:
        """``scan`` as the next buffer of its direction (double-buffered: replaced whole)."""
        result = build_scan(scan, self.samples, self._seq[scan.direction] + 1, self._mount)
        self.buffers[scan.direction] = result
        self._seq[scan.direction] += 1
        self._counters.scans += 1
        self._counters.partial_scans += int(result.partial)
        self._counters.dropped_acquisitions += result.dropped
        self._counters.acquisitions_in_scans += len(scan.acqs)
        scan.completed = True
        self._settled(scan)  # unless its tail waits for the next sweep
        return result

    def following(self, scan: ActiveScan) -> int | None:
        """The next continuous sweep's destination, or None when scanning ends here."""
        if self.continuous is not None and not self.stop_pending:
            cw, ccw = self.continuous
            return ccw if scan.destination == cw else cw  # the other limit
        self.continuous = None
        self.stop_pending = False
        return None

    def forget(self) -> None:
        """A fault or reset: no scan under way, asked for or continuing.

        What the abandoned scans held is counted as aborted (``aborted_acquisitions``): the
        acquisitions the scan under way had kept, and the turn-around tail it, or the sweep just
        completed, held for a next sweep that will not come. A scan that finished but was never
        completed (its BI_ACQUIRE ended with a bad STATUS, which is a fault) counts whole.
        """
        for scan in (self.scan, self._closing):
            if scan is not None:
                self._counters.aborted_acquisitions += scan.pending()
                scan.tail.clear()
        self._closing = None
        self.scan = None
        self.deferred = None
        self.continuous = None
        self.stop_pending = False
