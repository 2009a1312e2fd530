"""A scan while its acquisitions arrive, and the :class:`Scan` it becomes when it completes.

Acquisitions reach the administrator in NEW_POINT messages, possibly several at once on catch-up
and possibly out of a sweep that is already over; a scan keeps only those of its own sequence,
by index, so the finished :class:`Scan` is in acquisition order whatever the arrival order was.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from biris_hw.data import Direction, Point, Scan
from biris_hw.geometry import Mount
from biris_hw.scancheck import coverage_shortfall
from biris_hw.server.messages import Acquisition
from biris_hw.server.start_schedule import StartSchedule

__all__ = ["STILL_COUNTS", "ActiveScan", "build_scan", "point_of"]

log = logging.getLogger("biris_hw.server.admin")
"""The administrator thread's messages, whichever module writes them: one name to configure."""

STILL_COUNTS = 2
"""How near (counts) to where a scan starts or ends an acquisition counts as made with the head
standing there: a head at rest may sit a count or two off its command."""


@dataclass
class ActiveScan:
    """A sweep under way: ended when both its motion and its data are done."""

    direction: Direction
    destination: int
    n: int
    seq_id: int
    elevation: int = 0
    ring: bool = False
    """Continuous acquisition: the sweep's data come from the ring, not from a BI_ACQUIRE."""
    partial: bool = False
    """A continuous scan's sweep that did not start at the opposite limit (the first one, from
    wherever the head stood), or one whose ring STOP_CONTINUOUS stopped under it: its data
    cover only part of the span. A scan found short of its span when it completes is partial
    too (:func:`build_scan`)."""
    partial_reason: str = ""
    """Why ``partial``, in words (the scan's :attr:`~biris_hw.data.Scan.partial_reason`)."""
    start: int = 0
    left_start: bool = False
    """Continuous acquisition: an acquisition away from the start has been kept -- or the sweep
    turns straight round from the previous one, so its first acquisitions (head still at the
    turn-around) are kept and the stream has no hole."""
    at_end: bool = False
    """Continuous acquisition: an acquisition at the destination has been kept."""
    tail: list[Acquisition] = field(default_factory=list)
    """Continuous acquisition: acquisitions after the one at the destination -- the start of
    the next sweep if one follows straight on."""
    acqs: dict[int, Acquisition] = field(default_factory=dict)
    lost: int = 0
    start_budget_s: float = 0.0
    """Report mode: how late the motor could start (after its schedule) without the scan ending
    short: the lateness its acquisition count allowed for."""
    schedule: StartSchedule | None = None
    """Report mode: when its trapezoid starts (:mod:`~biris_hw.server.start_schedule`)."""
    standing: int = 0
    """Acquisitions made with the head standing at either end: dropped and counted
    (``constant_azimuth``), not lost."""
    standing_start: int = 0
    """Of ``standing``: those made before the head left its start (report mode: how late the
    motor really started after BIRIS's first acquisition, in acquisitions)."""
    az_done: bool = False
    """AZ_SCAN_DONE has arrived: the motor has come to rest at the destination."""
    cmd_done: bool = False
    """BIRIS_CMD_COMPLETE of its BI_ACQUIRE (SWEEP_DATA_DONE in continuous mode) has arrived."""
    status: int = 0
    completed: bool = False
    """:meth:`~biris_hw.server.scanning.ScanSequencer.complete` has made it a Scan: its kept
    acquisitions are counted in ``acquisitions_in_scans`` (only its tail may still be pending)."""

    def mark_partial(self, reason: str) -> None:
        """The scan will not cover its span, for ``reason`` (reasons accumulate, first first)."""
        self.partial = True
        if reason and reason not in self.partial_reason:
            joined = f"{self.partial_reason}; {reason}" if self.partial_reason else reason
            self.partial_reason = joined

    @property
    def acquisition(self) -> str:
        """How BIRIS acquired the scan's data, as :class:`~biris_hw.data.Scan` says it."""
        return "continuous" if self.ring else "single"

    def pending(self) -> int:
        """Acquisitions it holds that no counter has settled yet (the accounts' "in progress"):
        those it kept, until it completes or is abandoned, and its turn-around tail, until the
        next sweep takes it or it is dropped."""
        return len(self.tail) + (0 if self.completed else len(self.acqs))

    def head_moving(self, azimuth: int) -> bool:
        """Whether an acquisition belongs to the scan: not made while the head
        still stood at the start (unless the sweep follows straight on from another, whose end
        that start is), nor after one was made with it standing at the end.

        Only the ends are judged: those are where the report expects "samples at constant
        azimuth". An acquisition in between is kept whatever its tag, so that a stall or a
        tagging hiccup shows in the data instead of being hidden.
        """
        if not self.left_start:
            if abs(azimuth - self.start) <= STILL_COUNTS:
                return False
            self.left_start = True
        if self.at_end:
            return False
        if abs(azimuth - self.destination) <= STILL_COUNTS:
            self.at_end = True
        return True


def point_of(acq: Acquisition, scan: ActiveScan, scan_seq: int, mount: Mount | None) -> Point:
    """REQUEST_POINT's answer for one acquisition of ``scan`` (to be scan ``scan_seq``)."""
    return Point(
        azimuth=acq.azimuth,
        range_mm=acq.closest_mm,
        profile=acq.profile,
        intensity=acq.intensity,
        t=acq.t,
        acq=acq.index,
        scan_seq=scan_seq,
        elevation=scan.elevation,
        mount=mount,
        acquisition=scan.acquisition,
    )


def build_scan(scan: ActiveScan, samples: int, seq: int, mount: Mount | None) -> Scan:
    """The completed ``scan`` as buffer number ``seq`` of its direction.

    Its frames are copied once, stacked straight into the scan's int16 arrays, and every array
    is frozen here: :class:`~biris_hw.data.Scan` keeps a read-only array as it is given and
    copies only a writable one, and the delivery code shares these arrays between connections.
    """
    acqs = [scan.acqs[k] for k in sorted(scan.acqs)]
    n = len(acqs)
    azimuth = np.fromiter((a.azimuth for a in acqs), dtype=np.int32, count=n)
    closest = np.fromiter((a.closest_mm for a in acqs), dtype=np.int16, count=n)
    t = np.fromiter((a.t for a in acqs), dtype=np.float64, count=n)
    if n:
        # re-time from the tightest origin: each acquisition moves earlier by how much looser
        # the bound it was stamped with was (AcquisitionReader's notes)
        origin = np.fromiter((a.t_origin for a in acqs), dtype=np.float64, count=n)
        t -= origin - origin.min()
    if n:
        rng = np.stack([a.profile for a in acqs], dtype=np.int16)
        inten = np.stack([a.intensity for a in acqs], dtype=np.int16)
    else:
        rng = np.zeros((0, samples), dtype=np.int16)
        inten = np.zeros((0, samples), dtype=np.int16)
    for array in (azimuth, closest, t, rng, inten):
        array.flags.writeable = False
    # report mode: what BIRIS was asked for and neither kept nor dropped as standing was lost
    dropped = scan.lost if scan.ring else max(0, scan.n - n - scan.standing)
    if dropped:
        log.warning(
            "scan %d (%s): %d acquisitions lost",
            scan.seq_id,
            scan.direction.name,
            dropped,
        )
    short = coverage_shortfall(azimuth, scan.start, scan.destination)
    if short is not None:
        scan.mark_partial(short + _why_short(scan))
        log.warning("scan %d (%s): partial: %s", scan.seq_id, scan.direction.name, short)
    return Scan(
        direction=scan.direction,
        seq=seq,
        azimuth=azimuth,
        range_mm=rng,
        closest_mm=closest,
        intensity=inten,
        t=t,
        dropped=dropped,
        elevation=scan.elevation,
        mount=mount,
        acquisition=scan.acquisition,
        partial=scan.partial,
        partial_reason=scan.partial_reason,
        span=(scan.start, scan.destination),
    )


def _why_short(scan: ActiveScan) -> str:
    """What made a report-mode scan short, when the server knows: its motor started later than
    its acquisition count allowed for (the host woke the azimuth worker late)."""
    schedule = scan.schedule
    if schedule is None:
        return ""
    worker = schedule.late_s or 0.0
    if worker > scan.start_budget_s:
        return (
            f" (its motor started {worker * 1000.0:.0f} ms after its schedule, "
            f"{scan.start_budget_s * 1000.0:.0f} ms allowed: the host was late)"
        )
    if scan.standing_start:
        return (
            f" (the head still stood at its start for {scan.standing_start} acquisitions: "
            "its start reached the motor late)"
        )
    return ""
