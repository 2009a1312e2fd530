"""Scan sequencing: single and continuous scans, and where their data go.

The report's rules kept here:

* a scan completes when both AZ_SCAN_DONE and BIRIS_CMD_COMPLETE have arrived (in continuous
  acquisition, AZ_SCAN_DONE and SWEEP_DATA_DONE);
* continuous scans alternate CW and CCW and start the next sweep by themselves, until
  BIRIS_STOP_SCAN_RQST, which ends scanning at the completion of the current sweep;
* data are buffered per direction and double-buffered: a client always gets the last complete
  scan of a direction, never a mix;
* the number of acquisitions matches the scan length (_Get_acq_rate, :func:`acquisitions_for`),
  with the motor parameters the move will actually run with;
* "any change in sensor elevation must be completed before an acquisition scan is executed": a
  scan asked for while the head tilts (or, in continuous acquisition, before the ring is live)
  is accepted and *deferred*; a tilt asked for during a sweep goes between two sweeps.

In continuous acquisition (Appendix D) a sweep needs no BIRIS command: only the motor is ordered,
the azimuth worker opens the sweep once the motor runs, and a sweep ends with its first
acquisition at the destination. When continuous scanning turns straight round, the acquisitions
made at the turn-around after that one begin the next sweep, and its data carry on from there:
the stream of acquisitions is cut into sweeps without a hole, so the blind time between two
sweeps is one acquisition period. Otherwise (a single scan, a tilt between sweeps) acquisitions
made with the head standing at either end are dropped and counted (``constant_azimuth``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import replace

from biris_hw.angles import clamp_counts
from biris_hw.data import Direction, Point
from biris_hw.errors import RequestError
from biris_hw.ipc import Envelope
from biris_hw.records import BirisInitRecord, acquisitions_for
from biris_hw.server import messages as m
from biris_hw.server.admin_state import AdminState, BirisCommand
from biris_hw.server.scan_assembly import ActiveScan, build_scan, point_of
from regs.biexec import BiCommand, BiStatus

__all__ = ["Scanning"]


class Scanning(AdminState):
    """BIRIS_SINGLE_SCAN_RQST, BIRIS_CONT_SCAN_RQST, BIRIS_STOP_SCAN_RQST, NEW_POINT,
    SWEEP_DATA_DONE, and the end of a scan."""

    # -- client requests ---------------------------------------------------------------------
    def _check_can_scan(self) -> None:
        if self._scan_busy() or self.continuous is not None:
            raise RequestError("a scan is in progress; stop it or wait for it to end first")
        if self.az.moving() or self.home_pending:
            raise RequestError("the motor is moving; wait until it is idle")
        if self.params_pending is not None:  # cannot be: it is only set while moving
            self._load_params(self.params_pending)
            self.params_pending = None

    def _on_single_scan(self, env: Envelope, msg: m.SingleScanRqst) -> None:
        self._usable_conn(msg.conn)
        self._check_can_scan()
        dest = clamp_counts(msg.destination)
        if dest == self.position:
            raise RequestError(f"the head is already at {dest} counts; a scan needs a length")
        self._when_ready(lambda: self._start_scan(dest))
        env.reply(dest)

    def _on_cont_scan(self, env: Envelope, msg: m.ContScanRqst) -> None:
        self._usable_conn(msg.conn)
        self._check_can_scan()
        cw, ccw = clamp_counts(msg.cw_limit), clamp_counts(msg.ccw_limit)
        if cw >= ccw:
            raise RequestError(
                f"the CW limit ({cw} counts) must lie clockwise of the CCW limit ({ccw})"
            )
        self.continuous = (cw, ccw)
        self.stop_pending = False
        self._when_ready(lambda: self._start_scan(cw if self.position != cw else ccw))
        env.reply((cw, ccw))

    def _on_stop_scan(self, env: Envelope, msg: m.StopScanRqst) -> None:
        self._usable_conn(msg.conn)
        if self.continuous is not None:
            if self.scan is None and self.deferred_scan is not None:
                self.deferred_scan = None  # no sweep has started yet: nothing to complete
                self.continuous = None
                self._after_motion_settles()
            else:
                self.stop_pending = True
        env.reply(None)
        self._check_idle_waiters()

    # -- starting a scan ---------------------------------------------------------------------
    def _when_ready(self, start: Callable[[], None]) -> None:
        """Start a scan now if BIRIS may acquire, else once it may (a tilt, the ring)."""
        if self._ready_to_acquire():
            start()
            return
        self.deferred_scan = start
        if self.ring_mode and self.tilt is None:
            self._start_ring()

    def _run_deferred(self) -> None:
        if self.deferred_scan is not None and self._ready_to_acquire() and self.fault is None:
            start, self.deferred_scan = self.deferred_scan, None
            start()

    def _start_scan(self, dest: int, after: ActiveScan | None = None) -> None:
        """Start a scan to ``dest``; ``after`` is the sweep it turns straight round from."""
        if dest == self.position:
            raise RequestError(f"the head is already at {dest} counts; a scan needs a length")
        direction = Direction.CCW if dest > self.position else Direction.CW
        self.seq_counter += 1
        if self.ring_mode:
            self._start_sweep(dest, direction, after)
            return
        n = acquisitions_for(abs(dest - self.position), self._record_with_motor())
        scan = ActiveScan(direction, dest, n, self.seq_counter, elevation=self.elevation)
        self.scan = scan
        self._submit_command(
            BirisCommand(
                int(BiCommand.BI_ACQUIRE),
                str(n),
                lambda status, param: self._scan_part_done(scan, cmd_status=status),
                n=n,
                seq_id=scan.seq_id,
            )
        )
        self._move(self.az, m.MoveOrder(dest), lambda: self._scan_part_done(scan, motion=True))

    def _start_sweep(self, dest: int, direction: Direction, after: ActiveScan | None) -> None:
        """A continuous-acquisition scan: only the motor is ordered; the ring supplies data.

        A sweep that turns straight round from ``after`` starts with ``after``'s tail (made at
        the turn-around after its last acquisition) and reads on from where it ended.
        """
        follows = after is not None and after.ring and after.elevation == self.elevation
        scan = ActiveScan(
            direction,
            dest,
            0,
            self.seq_counter,
            elevation=self.elevation,
            ring=True,
            start=self.position,
            left_start=follows,  # the turn-around's acquisitions begin it
        )
        self.scan = scan
        if after is not None:
            if follows:
                points = [self._keep(scan, acq) for acq in after.tail]
                if points:
                    self.clients.deliver_points(points, 0)
            else:
                self.counters["constant_azimuth"] += len(after.tail)
            after.tail.clear()
        self._move(
            self.az,
            m.MoveOrder(dest, sweep=scan.seq_id, follows=follows),
            lambda: self._scan_part_done(scan, motion=True),
        )
        self._rearm_timeout()

    def _record_with_motor(self) -> BirisInitRecord:
        """The record with the motor parameters the next move will run with: a parameter load
        still queued ahead of it counts, since the motion queue is served in order."""
        motor = self.az.motor_for_next_move()
        return self.record if motor == self.record.motor else replace(self.record, motor=motor)

    # -- data and the end of a scan ----------------------------------------------------------
    def _on_new_point(self, env: Envelope, msg: m.NewPoint) -> None:
        env.reply(None)
        scan = self.scan
        self._note_biris_alive()
        points: list[Point] = []
        for acq in msg.acquisitions:
            if scan is None or acq.seq_id != scan.seq_id:
                self.counters["stale_acquisitions"] += 1
                continue
            if scan.ring and not scan.head_moving(acq.azimuth):
                if scan.at_end:
                    scan.tail.append(acq)  # the next sweep's start, if one follows
                else:
                    self.counters["constant_azimuth"] += 1  # the head stood still: dropped
                continue
            points.append(self._keep(scan, acq))
        if scan is not None:
            scan.lost += msg.lost
        if points or (scan is not None and msg.lost):
            self.clients.deliver_points(points, msg.lost if scan is not None else 0)

    def _keep(self, scan: ActiveScan, acq: m.Acquisition) -> Point:
        """Make ``acq`` part of ``scan`` (a ring sweep numbers its own) and the latest point."""
        if scan.ring:
            acq = dataclasses.replace(acq, seq_id=scan.seq_id, index=len(scan.acqs))
        scan.acqs[acq.index] = acq
        self.counters["acquisitions"] += 1
        self.counters["discarded_samples"] += acq.discarded
        point = point_of(acq, scan, self.seq[scan.direction] + 1, self.mount)
        self.latest_point = point
        return point

    def _on_sweep_data_done(self, env: Envelope, msg: m.SweepDataDone) -> None:
        env.reply(None)
        scan = self.scan
        if scan is None or not scan.ring or scan.seq_id != msg.seq_id:
            self.counters["stale_completions"] += 1
            return
        self._scan_part_done(scan, cmd_status=int(BiStatus.OK))

    def _scan_part_done(
        self, scan: ActiveScan, *, motion: bool = False, cmd_status: int | None = None
    ) -> None:
        if self.scan is not scan:
            return
        if motion:
            scan.az_done = True
        if cmd_status is not None:
            scan.cmd_done = True
            scan.status = cmd_status
            self._rearm_timeout()
        if scan.az_done and scan.cmd_done:
            self._finish_scan(scan)

    def _finish_scan(self, scan: ActiveScan) -> None:
        self.scan = None
        if scan.status != BiStatus.OK:
            self._fault("protocol", f"BI_ACQUIRE ended with STATUS {scan.status}")
            return
        result = build_scan(scan, self.samples, self.seq[scan.direction] + 1, self.mount)
        self.buffers[scan.direction] = result
        self.seq[scan.direction] += 1
        self.counters["scans"] += 1
        self.counters["dropped_acquisitions"] += result.dropped
        self.clients.deliver(result)
        following: int | None = None
        if self.continuous is not None and not self.stop_pending:
            cw, ccw = self.continuous
            following = ccw if scan.destination == cw else cw  # the other limit
        else:
            self.continuous = None
            self.stop_pending = False
        pending = self.elevation_pending
        if pending is not None or following is None:
            self.counters["constant_azimuth"] += len(scan.tail)  # no sweep follows straight on
            scan.tail.clear()
        if pending is not None:  # a tilt asked for during the sweep goes between sweeps
            if following is not None:
                dest = following
                self.deferred_scan = lambda: self._start_scan(dest)
            self._start_tilt(pending)
            self._after_motion_settles()
        elif following is not None:
            self._start_scan(following, after=scan)
        else:
            self._after_motion_settles()
        self._check_idle_waiters()
