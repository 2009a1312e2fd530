"""The report's future tilt axis: SET_ELEVATION, carried out as a *tilt*.

SET_ELEVATION is clamped to the init record's ``elevation_limits_counts``, replied at once with
the destination used, and carried out as a tilt: the tilt motor moves (through _el_scan_start /
_el_scan_notifier) while BI_LOAD_LUT loads that elevation's calibration table -- "a calibration
must exist for each angle of elevation" -- and the tilt is over when both are. "Data acquisitions
will not occur during elevation changes": a tilt asked for during a scan waits for the end of
that sweep (in continuous scanning, it happens between two sweeps), and a scan asked for during a
tilt waits for the tilt (see :mod:`biris_hw.server.scanning`). In continuous acquisition the
ring is stopped for the tilt and restarted after. A BI_LOAD_LUT that BIRIS refuses (no table for
that elevation) is a ``protocol`` fault: the record's limits promise tables BIRIS does not have.
"""

from __future__ import annotations

from biris_hw.angles import clamp_counts
from biris_hw.ipc import Envelope
from biris_hw.server import messages as m
from biris_hw.server.admin_state import AdminState, BirisCommand, Tilt, status_name
from regs.biexec import BiCommand, BiStatus

__all__ = ["Elevation"]


class Elevation(AdminState):
    """SET_ELEVATION and the tilts it starts."""

    def _on_set_elevation(self, env: Envelope, msg: m.SetElevation) -> None:
        self._usable_conn(msg.conn)
        lo, hi = self.record.elevation_limits_counts
        dest = min(max(clamp_counts(msg.destination), lo), hi)
        if self.scan is not None or self.tilt is not None:
            # after the sweep under way (or the tilt under way); the latest request wins
            settled = self.tilt is None and dest == self.elevation and self.lut == dest
            self.elevation_pending = None if settled else dest
        elif dest != self.elevation or self.lut != dest:
            self._start_tilt(dest)
        env.reply(dest)

    def _start_tilt(self, dest: int) -> None:
        self.elevation_pending = None
        tilt = Tilt(dest)
        self.tilt = tilt
        self.counters["tilts"] += 1
        if self.ring in ("starting", "live", "stopping"):
            self._stop_ring(lambda: self._tilt_go(tilt))
        else:
            self._tilt_go(tilt)

    def _tilt_go(self, tilt: Tilt) -> None:
        if self.tilt is not tilt or self.fault is not None:
            return
        dest = tilt.destination
        if dest != self.el.position:
            self._move(self.el, m.MoveOrder(dest), lambda: self._tilt_part(tilt, moved=True))
        else:
            tilt.moved = True
        self._submit_command(
            BirisCommand(
                int(BiCommand.BI_LOAD_LUT),
                str(dest),
                lambda status, param: self._tilt_lut_loaded(tilt, status),
            )
        )

    def _tilt_lut_loaded(self, tilt: Tilt, status: int) -> None:
        if self.tilt is not tilt:
            return
        if status != BiStatus.OK:
            self._fault(
                "protocol",
                f"BI_LOAD_LUT {tilt.destination} failed: STATUS {status} ({status_name(status)})"
                " -- BIRIS has no calibration for an elevation the init record allows",
            )
            return
        self.lut = tilt.destination
        self.counters["lut_loads"] += 1
        tilt.lut = True
        self._tilt_part(tilt)

    def _tilt_part(self, tilt: Tilt, *, moved: bool = False) -> None:
        """One half of the tilt is done; when both are, what waited for it goes on."""
        if self.tilt is not tilt:
            return
        if moved:
            tilt.moved = True
        if not (tilt.moved and tilt.lut):
            return
        self.tilt = None
        self.elevation = tilt.destination
        pending, self.elevation_pending = self.elevation_pending, None
        if pending is not None and (pending != self.elevation or self.lut != pending):
            self._start_tilt(pending)
            return
        if self.ring_mode:
            self._start_ring()
        self._run_deferred()
        self._after_motion_settles()
        self._check_idle_waiters()
