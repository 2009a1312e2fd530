"""The report's future tilt axis: SET_ELEVATION, carried out as a *tilt*.

SET_ELEVATION is clamped to the init record's ``elevation_limits_counts``, replied at once with
the destination used, and carried out as a tilt: the tilt motor moves (through _el_scan_start /
_el_scan_notifier) while BI_LOAD_LUT loads that elevation's calibration table -- "a calibration
must exist for each angle of elevation" -- and the tilt is over when both are. "Data acquisitions
will not occur during elevation changes": a tilt asked for during a scan waits for the end of
that sweep (in continuous scanning, it happens between two sweeps), and a scan asked for during a
tilt waits for the tilt. In continuous acquisition the ring is stopped for the tilt first
(:attr:`TiltPhase.AWAIT_RING_STOP`) and restarted after. A BI_LOAD_LUT that BIRIS refuses (no
table for that elevation) is a ``protocol`` fault: the record's limits promise tables BIRIS does
not have.

:class:`TiltControl` owns where the tilt stands, which table BIRIS holds, the tilt under way and
the one asked for meanwhile; the administrator issues the motion and the command it decides on.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from biris_hw.angles import clamp_counts

__all__ = ["Tilt", "TiltControl", "TiltPhase"]


class TiltPhase(enum.Enum):
    AWAIT_RING_STOP = "await_ring_stop"  # continuous acquisition is being stopped first
    UNDER_WAY = "under_way"  # the tilt motor moves and/or BI_LOAD_LUT runs


@dataclass(eq=False)
class Tilt:
    """A tilt under way: over when the tilt motor has moved *and* BI_LOAD_LUT has loaded."""

    destination: int
    phase: TiltPhase = TiltPhase.UNDER_WAY
    moved: bool = False
    lut: bool = False

    @property
    def over(self) -> bool:
        return self.moved and self.lut


class TiltControl:
    """Where the tilt stands, the calibration BIRIS holds, and the tilt under way or asked for."""

    def __init__(self, limits: tuple[int, int]) -> None:
        self._limits = limits
        self.elevation = 0
        """Where the tilt stands (counts) once the last tilt is over."""
        self.lut: int | None = None
        """Elevation (counts) of the calibration table BIRIS holds, None when unknown."""
        self.current: Tilt | None = None
        self.pending: int | None = None
        """A tilt asked for during a sweep or another tilt: it goes next (the latest wins)."""

    def clamp(self, destination: int) -> int:
        """_Scan_limit, then the record's elevation limits."""
        lo, hi = self._limits
        return min(max(clamp_counts(destination), lo), hi)

    def needed(self, dest: int) -> bool:
        """Whether standing at ``dest`` with its table takes a tilt."""
        return dest != self.elevation or self.lut != dest

    def ask_later(self, dest: int) -> None:
        """Keep ``dest`` for after the sweep or tilt under way (nothing if already there)."""
        settled = self.current is None and not self.needed(dest)
        self.pending = None if settled else dest

    def begin(self, dest: int, *, await_ring: bool) -> Tilt:
        self.pending = None
        phase = TiltPhase.AWAIT_RING_STOP if await_ring else TiltPhase.UNDER_WAY
        self.current = Tilt(dest, phase)
        return self.current

    def is_current(self, tilt: Tilt | None) -> bool:
        return tilt is not None and tilt is self.current

    def finish(self, tilt: Tilt) -> int | None:
        """``tilt`` is over: the elevation is its destination; returns a pending tilt to begin."""
        self.current = None
        self.elevation = tilt.destination
        pending, self.pending = self.pending, None
        if pending is not None and self.needed(pending):
            return pending
        return None

    def forget(self) -> None:
        """A fault or reset: no tilt under way or asked for."""
        self.current = None
        self.pending = None

    def homed(self) -> None:
        """Initialisation stood the tilt level and loaded the table for it."""
        self.elevation = 0
        self.lut = 0
