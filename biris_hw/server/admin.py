"""The BIRIS server's administrator: one thread, blocked on nothing but its inbox.

It owns all server state and decides everything; it never sends, never sleeps and never touches
a register. Workers get their orders in *replies*; clients that must wait (wait_idle,
READY_FOR_DATA, reset) are parked and replied to later. Rules of the report kept here:

* a new BIRIS command only after BIRIS_CMD of the previous one was serviced (``biris_ready``);
* a scan completes when both AZ_SCAN_DONE and BIRIS_CMD_COMPLETE have arrived (in continuous
  acquisition, AZ_SCAN_DONE and SWEEP_DATA_DONE);
* continuous scans alternate CW and CCW and start the next sweep by themselves, until
  BIRIS_STOP_SCAN_RQST, which ends scanning at the completion of the current sweep;
* data are buffered per direction and double-buffered: a client always gets the last complete
  scan of a direction, never a mix;
* BIRIS_HOME is pending while the motor moves or a motion is pending, and during continuous
  scanning it waits for STOP; HOME and new motor parameters use the trapezoid only;
* every motor destination goes through _Scan_limit (+-0x1000 counts);
* "any change in sensor elevation must be completed before an acquisition scan is executed", with
  the calibration table for the new elevation loaded: see *Elevation* below;
* Appendix D's continuous mode: see *Continuous acquisition* below.

**Elevation** (the report's future tilt axis). SET_ELEVATION is clamped to the init record's
``elevation_limits_counts``, replied at once with the destination used, and carried out as a
*tilt*: the tilt motor moves (through el_scan_start / el_scan_notifier) while BI_LOAD_LUT loads
that elevation's calibration table, and the tilt is over when both are. No acquisition runs
meanwhile: a tilt asked for during a scan waits for the end of that sweep (in continuous scanning,
it happens between two sweeps), and a scan asked for during a tilt *waits* for the tilt (the
request is accepted and replied at once; the sweep starts when the tilt is over; a second scan
request meanwhile is refused as for any scan in progress). A BI_LOAD_LUT that BIRIS refuses (no
table for that elevation) is a ``protocol`` fault: the record's limits promise tables BIRIS does
not have.

**Continuous acquisition** (Appendix D, ``BirisInitRecord.continuous_acquisition``). BIRIS is
started once (BI_START_CONTINUOUS) after initialisation and keeps acquiring into its ring, so the
240 ms start-up is paid once, not per sweep; it is stopped for a tilt (no acquisition while
tilting) and restarted after. A sweep starts only once the ring is *live* (its first acquisition
has begun), and needs no BIRIS command: the azimuth worker opens the sweep (data interrupts
back on) once the motor runs, and the sweep's data are complete when the acquisition in
exposure as the motor came to rest has been read (SWEEP_DATA_DONE). Acquisitions made with the
head standing at either end of the sweep (before it left the start, and after the first one at
the destination) are *dropped* from the scan and counted (``constant_azimuth``); a scan's
``dropped`` still counts only acquisitions lost.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from biris_hw.angles import clamp_counts
from biris_hw.data import ConnectionKind, Direction, Point, Scan
from biris_hw.errors import (
    BirisError,
    ConnectionClosed,
    FaultKind,
    HardwareFault,
    RequestError,
)
from biris_hw.ipc import Envelope, Mailbox, TaskStopped
from biris_hw.records import BirisInitRecord, MotorParams, acquisitions_for
from biris_hw.server import messages as m
from biris_hw.server.delivery import ClientConn, check_policy, stamp
from biris_hw.server.initialiser import InitResult
from biris_hw.server.motion import AxisState, Motion
from biris_hw.server.tasks import DeadlineTimer
from regs.biexec import BiCommand, BiStatus, decode_param
from regs.tech80 import Axis

__all__ = ["Administrator"]

log = logging.getLogger(__name__)

STILL_COUNTS = 2
"""How near (counts) to where a continuous-mode sweep starts or ends an acquisition counts as made
with the head standing there: a head at rest may sit a count or two off its command."""


@dataclass
class _Command:
    code: int
    param: str
    n: int
    seq_id: int
    on_done: Callable[[int, bytes], object]
    on_fail: Callable[[BaseException], object]
    token: int = 0


@dataclass
class _ActiveScan:
    direction: Direction
    destination: int
    n: int
    seq_id: int
    elevation: int = 0
    ring: bool = False
    """Continuous acquisition: the sweep's data come from the ring, not from a BI_ACQUIRE."""
    start: int = 0
    left_start: bool = False
    """Continuous acquisition: an acquisition away from the start has been kept."""
    at_end: bool = False
    """Continuous acquisition: an acquisition at the destination has been kept."""
    acqs: dict[int, m.Acquisition] = field(default_factory=dict)
    lost: int = 0
    az_done: bool = False
    cmd_done: bool = False
    status: int = 0


@dataclass
class _Tilt:
    destination: int
    moved: bool = False
    lut: bool = False


def _status_name(status: int) -> str:
    try:
        return BiStatus(status).name
    except ValueError:
        return "error"


def _ring_answer(param: bytes) -> int:
    try:
        return int(decode_param(param).strip(), 10)
    except ValueError:
        return 0


class Administrator:
    """State and decisions of the BIRIS server; ``run()`` is the administrator thread."""

    def __init__(
        self,
        record: BirisInitRecord,
        inbox: Mailbox,
        clock: Callable[[], float],
        biris_timeout: DeadlineTimer,
        motor_watchdog: DeadlineTimer,
        start_initialiser: Callable[[], None],
        elevation_watchdog: DeadlineTimer | None = None,
    ) -> None:
        self.record = record
        self.mount = record.mount
        self.inbox = inbox
        self.clock = clock
        self.biris_timeout = biris_timeout
        self._start_initialiser = start_initialiser
        self.phase = "initialising"
        self.fault: HardwareFault | None = None
        self.init_waiters: list[Envelope] = []
        self.init_commands: list[_Command] = []
        # workers parked on their last report
        self.transfer_env: Envelope | None = None
        self.cmd_notifier_env: Envelope | None = None
        # BIRIS commands
        self.cmd_queue: deque[_Command] = deque()
        self.current_cmd: _Command | None = None
        self.biris_ready = True
        self.cmd_token = 0
        self.timeout_enabled = False
        self.timeout_gen = -1
        # motion: one record per axis (the tilt's watchdog is the pan's if none is given)
        self.az = AxisState(Axis.AZIMUTH, motor_watchdog, record.motor)
        self.el = AxisState(Axis.ELEVATION, elevation_watchdog or motor_watchdog, record.motor)
        # scanning
        self.seq_counter = 0
        self.scan: _ActiveScan | None = None
        self.deferred_scan: Callable[[], None] | None = None
        """A scan accepted while it could not start (tilting, ring not live): its start."""
        self.continuous: tuple[int, int] | None = None
        self.stop_pending = False
        self.home_pending = False
        self.homing = False
        self.params_pending: MotorParams | None = None
        self.buffers: dict[Direction, Scan | None] = {Direction.CW: None, Direction.CCW: None}
        self.seq: dict[Direction, int] = {Direction.CW: 0, Direction.CCW: 0}
        self.latest_point: Point | None = None
        self.samples = 0
        # elevation
        self.elevation = 0
        """Where the tilt stands (counts) once the last tilt is over."""
        self.lut: int | None = None
        """Elevation (counts) of the calibration table BIRIS holds, None when unknown."""
        self.tilt: _Tilt | None = None
        self.elevation_pending: int | None = None
        # continuous acquisition (Appendix D)
        self.ring_mode = record.continuous_acquisition
        self.ring = "off"
        """BIRIS's continuous acquisition: off, starting, live or stopping."""
        self.ring_stop_waiters: list[Callable[[], None]] = []
        # clients
        self.conns: dict[int, ClientConn] = {}
        self.next_conn = 1
        self.idle_waiters: list[Envelope] = []
        self.closed_drops = 0
        # counters for status()
        self.counters: dict[str, int] = {
            "acquisitions": 0,
            "scans": 0,
            "dropped_acquisitions": 0,
            "discarded_samples": 0,
            "constant_azimuth": 0,
            "deliveries": 0,
            "tilts": 0,
            "lut_loads": 0,
            "continuous_starts": 0,
            "faults": 0,
            "spurious_motor_end": 0,
            "stale_acquisitions": 0,
            "stale_completions": 0,
        }
        self._handlers: dict[type, Callable[[Envelope, Any], None]] = {
            m.NewPoint: self._on_new_point,
            m.CmdTransferRdy: self._on_cmd_transfer_rdy,
            m.AzReady: lambda env, msg: self._on_axis_ready(self.az, env, msg.error),
            m.AzScanDone: lambda env, msg: self._on_axis_done(self.az, env),
            m.ElReady: lambda env, msg: self._on_axis_ready(self.el, env, msg.error),
            m.ElScanDone: lambda env, msg: self._on_axis_done(self.el, env),
            m.BirisCmdComplete: self._on_cmd_complete,
            m.ContinuousLive: self._on_continuous_live,
            m.SweepDataDone: self._on_sweep_data_done,
            m.BirisTimeoutErr: self._on_timeout_err,
            m.MotorWatchdogErr: self._on_watchdog_err,
            m.BirisBusErr: lambda env, msg: self._task_fault(
                env, "bus", "bus error on the BIRIS VMEbus"
            ),
            m.BirisParityErr: lambda env, msg: self._task_fault(
                env, "parity", "parity error on the coupler"
            ),
            m.InitCommand: self._on_init_command,
            m.InitMove: self._on_init_move,
            m.InitDone: self._on_init_done,
            m.OpenRequest: self._on_open,
            m.CloseRequest: self._on_close,
            m.RequestPoint: self._on_request_point,
            m.RequestScanData: self._on_request_scan_data,
            m.TimeoutEnable: self._on_timeout_enable,
            m.TimeoutDisable: self._on_timeout_disable,
            m.BirisMotorParams: self._on_motor_params,
            m.SingleScanRqst: self._on_single_scan,
            m.ContScanRqst: self._on_cont_scan,
            m.StopScanRqst: self._on_stop_scan,
            m.BirisHome: self._on_home,
            m.SetElevation: self._on_set_elevation,
            m.ReadyForData: self._on_ready_for_data,
            m.WaitIdle: self._on_wait_idle,
            m.ResetRequest: self._on_reset,
            m.StatusRequest: self._on_status,
        }

    # ============================================================================ the loop
    def run(self) -> None:
        while True:
            try:
                env = self.inbox.receive()
            except TaskStopped:
                return
            handler = self._handlers.get(type(env.message))
            if handler is None:
                env.fail(RequestError(f"unknown message {type(env.message).__name__}"))
                continue
            try:
                handler(env, env.message)
            except BirisError as exc:  # RequestError, HardwareFault, ConnectionClosed: the caller's
                _fail(env, exc)
            except Exception as exc:  # a bug must not kill the server silently
                log.exception("administrator: %s failed", type(env.message).__name__)
                _fail(env, exc)

    # ============================================================================ helpers
    @property
    def motor(self) -> MotorParams:
        """The pan motor's parameters in force."""
        return self.az.motor

    @property
    def position(self) -> int:
        """Where the pan axis stands, or will once its current move ends (counts)."""
        return self.az.position

    def _axis(self, axis: Axis) -> AxisState:
        return self.az if axis is Axis.AZIMUTH else self.el

    def _conn(self, ident: int, *, data: bool = False) -> ClientConn:
        conn = self.conns.get(ident)
        if conn is None:
            raise ConnectionClosed(f"connection {ident} is not open")
        if data and conn.kind is not ConnectionKind.DATA:
            raise RequestError("READY_FOR_DATA needs a DATA connection")
        return conn

    def _check_usable(self) -> None:
        if self.fault is not None:
            raise self.fault
        if self.phase == "initialising":
            raise RequestError("the server is initialising")

    def _scan_busy(self) -> bool:
        """A scan runs or waits to start."""
        return self.scan is not None or self.deferred_scan is not None

    def is_idle(self) -> bool:
        return (
            self.phase == "idle"
            and not self._scan_busy()
            and not self.az.busy()
            and not self.el.busy()
            and self.tilt is None
            and self.elevation_pending is None
            and not self.home_pending
            and self.params_pending is None
            and self.current_cmd is None
            and not self.cmd_queue
            and self.ring in ("off", "live")
        )

    def _check_idle_waiters(self) -> None:
        if self.idle_waiters and self.is_idle():
            waiters, self.idle_waiters = self.idle_waiters, []
            for env in waiters:
                env.reply(None)

    # ============================================================================ commands
    def _submit_command(self, cmd: _Command) -> None:
        self.cmd_queue.append(cmd)
        self._pump_commands()

    def _pump_commands(self) -> None:
        if self.fault is not None or not self.biris_ready or self.transfer_env is None:
            return
        if not self.cmd_queue:
            return
        cmd = self.cmd_queue.popleft()
        self.current_cmd = cmd
        self.biris_ready = False
        if self.cmd_notifier_env is not None:  # put the notifier back on its interrupt first
            self.cmd_notifier_env.reply(None)
            self.cmd_notifier_env = None
        env, self.transfer_env = self.transfer_env, None
        self.cmd_token += 1
        cmd.token = self.cmd_token
        env.reply(m.TransferOrder(cmd.code, cmd.param, cmd.seq_id, cmd.n, cmd.token))
        self._rearm_timeout()

    def _on_cmd_transfer_rdy(self, env: Envelope, msg: m.CmdTransferRdy) -> None:
        self.transfer_env = env
        self._pump_commands()

    def _on_cmd_complete(self, env: Envelope, msg: m.BirisCmdComplete) -> None:
        self.cmd_notifier_env = env  # replied just before the next command is issued
        if self.current_cmd is None or msg.token != self.current_cmd.token:
            self.counters["stale_completions"] += 1
            return
        cmd, self.current_cmd = self.current_cmd, None
        self.biris_ready = True
        self._rearm_timeout()
        cmd.on_done(msg.status, msg.param)
        self._pump_commands()
        self._check_idle_waiters()

    # -- the BIRIS timeout: armed whenever BIRIS owes the server an answer ------------------------
    def _biris_expected(self) -> bool:
        """BIRIS owes a completion, a continuous-mode sweep's data, or its ring's start."""
        scan = self.scan
        return (
            self.current_cmd is not None
            or (scan is not None and scan.ring and not scan.cmd_done)
            or self.ring == "starting"
        )

    def _rearm_timeout(self) -> None:
        if self.timeout_enabled and self._biris_expected():
            self.timeout_gen = self.biris_timeout.arm(self.record.timeout_s)
        else:
            self.biris_timeout.disarm()

    def _on_timeout_err(self, env: Envelope, msg: m.BirisTimeoutErr) -> None:
        env.reply(None)
        if msg.generation == self.timeout_gen and self._biris_expected():
            self._fault(
                "timeout", f"BIRIS did not respond for {self.record.timeout_s:g} s of hardware time"
            )

    def _on_timeout_enable(self, env: Envelope, msg: m.TimeoutEnable) -> None:
        self._conn(msg.conn)
        self._check_usable()
        self.timeout_enabled = True
        self._rearm_timeout()
        env.reply(None)

    def _on_timeout_disable(self, env: Envelope, msg: m.TimeoutDisable) -> None:
        self._conn(msg.conn)
        self._check_usable()
        self.timeout_enabled = False
        self.biris_timeout.disarm()
        env.reply(None)

    # ============================================================================ motion
    def _submit_motion(self, axis: AxisState, job: Motion) -> None:
        axis.submit(job)
        self._pump_motion(axis)

    def _pump_motion(self, axis: AxisState) -> None:
        if self.fault is None:
            axis.dispatch()

    def _on_axis_ready(self, axis: AxisState, env: Envelope, error: str | None) -> None:
        """AZ_READY / EL_READY: the worker is parked again; a parameter load is then done."""
        axis.env = env
        job = axis.current
        if job is not None:
            if error is not None:
                axis.finish_current()
                self._fault("motor_stall" if "profile" in error else "bus", error)
                return
            if isinstance(job.order, m.ParamsOrder):
                axis.finish_current()
                job.on_done(None)
        self._pump_motion(axis)
        self._check_idle_waiters()

    def _on_axis_done(self, axis: AxisState, env: Envelope) -> None:
        """AZ_SCAN_DONE / EL_SCAN_DONE: the move has ended and the axis has come to rest."""
        env.reply(None)
        job = axis.current
        if job is None or not isinstance(job.order, m.MoveOrder):
            self.counters["spurious_motor_end"] += 1
            return
        axis.finish_current()
        job.on_done(None)
        self._pump_motion(axis)
        self._check_idle_waiters()

    def _on_watchdog_err(self, env: Envelope, msg: m.MotorWatchdogErr) -> None:
        env.reply(None)
        axis = self._axis(msg.axis)
        if msg.generation == axis.watchdog_gen and axis.current is not None:
            self._fault("motor_stall", f"the {axis.name} motor did not reach its destination")

    # ============================================================================ scans
    def _direction_to(self, dest: int) -> Direction:
        return Direction.CCW if dest > self.position else Direction.CW

    def _ready_to_acquire(self) -> bool:
        """No tilt under way, and in continuous acquisition the ring is live."""
        return self.tilt is None and (not self.ring_mode or self.ring == "live")

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

    def _start_scan(self, dest: int) -> None:
        if dest == self.position:
            raise RequestError(f"the head is already at {dest} counts; a scan needs a length")
        direction = self._direction_to(dest)
        self.seq_counter += 1
        if self.ring_mode:
            self._start_sweep(dest, direction)
            return
        n = acquisitions_for(abs(dest - self.position), self._record_with_motor())
        scan = _ActiveScan(direction, dest, n, self.seq_counter, elevation=self.elevation)
        self.scan = scan
        self._submit_command(
            _Command(
                int(BiCommand.BI_ACQUIRE),
                str(n),
                n,
                scan.seq_id,
                on_done=lambda status, param: self._scan_part_done(scan, cmd_status=status),
                on_fail=lambda exc: None,
            )
        )
        self._submit_motion(
            self.az,
            Motion(
                m.MoveOrder(dest),
                on_done=lambda err: self._scan_part_done(scan, motion=True),
                on_fail=lambda exc: None,
            ),
        )

    def _start_sweep(self, dest: int, direction: Direction) -> None:
        """A continuous-acquisition scan: only the motor is ordered; the ring supplies data."""
        scan = _ActiveScan(
            direction,
            dest,
            0,
            self.seq_counter,
            elevation=self.elevation,
            ring=True,
            start=self.position,
        )
        self.scan = scan
        self._submit_motion(
            self.az,
            Motion(
                m.MoveOrder(dest, sweep=scan.seq_id),
                on_done=lambda err: self._scan_part_done(scan, motion=True),
                on_fail=lambda exc: None,
            ),
        )
        self._rearm_timeout()

    def _record_with_motor(self) -> BirisInitRecord:
        """The record with the motor parameters the next move will run with: a parameter load
        still queued ahead of it counts, since the motion queue is served in order."""
        motor = self.az.motor_for_next_move()
        return self.record if motor == self.record.motor else replace(self.record, motor=motor)

    def _scan_part_done(
        self, scan: _ActiveScan, *, motion: bool = False, cmd_status: int | None = None
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

    def _on_sweep_data_done(self, env: Envelope, msg: m.SweepDataDone) -> None:
        env.reply(None)
        scan = self.scan
        if scan is None or not scan.ring or scan.seq_id != msg.seq_id:
            self.counters["stale_completions"] += 1
            return
        self._scan_part_done(scan, cmd_status=int(BiStatus.OK))

    def _finish_scan(self, scan: _ActiveScan) -> None:
        self.scan = None
        if scan.status != BiStatus.OK:
            self._fault("protocol", f"BI_ACQUIRE ended with STATUS {scan.status}")
            return
        result = self._build_scan(scan)
        self.buffers[scan.direction] = result
        self.seq[scan.direction] += 1
        self.counters["scans"] += 1
        self.counters["dropped_acquisitions"] += result.dropped
        self._deliver(result)
        following: int | None = None
        if self.continuous is not None and not self.stop_pending:
            cw, ccw = self.continuous
            following = ccw if scan.destination == cw else cw  # the other limit
        else:
            self.continuous = None
            self.stop_pending = False
        pending = self.elevation_pending
        if pending is not None:  # a tilt asked for during the sweep goes between sweeps
            if following is not None:
                dest = following
                self.deferred_scan = lambda: self._start_scan(dest)
            self._start_tilt(pending)
            self._after_motion_settles()
        elif following is not None:
            self._start_scan(following)
        else:
            self._after_motion_settles()
        self._check_idle_waiters()

    def _build_scan(self, scan: _ActiveScan) -> Scan:
        acqs = [scan.acqs[k] for k in sorted(scan.acqs)]
        samples = self.samples
        n = len(acqs)
        azimuth = np.fromiter((a.azimuth for a in acqs), dtype=np.int32, count=n)
        closest = np.fromiter((a.closest_mm for a in acqs), dtype=np.int16, count=n)
        t = np.fromiter((a.t for a in acqs), dtype=np.float64, count=n)
        if n:
            rng = np.stack([a.profile for a in acqs]).astype(np.int16)
            inten = np.stack([a.intensity for a in acqs]).astype(np.int16)
        else:
            rng = np.zeros((0, samples), dtype=np.int16)
            inten = np.zeros((0, samples), dtype=np.int16)
        dropped = scan.lost if scan.ring else max(0, scan.n - n)
        if dropped:
            log.warning(
                "scan %d (%s): %d acquisitions lost",
                scan.seq_id,
                scan.direction.name,
                dropped,
            )
        return Scan(
            direction=scan.direction,
            seq=self.seq[scan.direction] + 1,
            azimuth=azimuth,
            range_mm=rng,
            closest_mm=closest,
            intensity=inten,
            t=t,
            dropped=dropped,
            elevation=scan.elevation,
            mount=self.mount,
        )

    def _on_new_point(self, env: Envelope, msg: m.NewPoint) -> None:
        env.reply(None)
        scan = self.scan
        if self.timeout_enabled and self._biris_expected():
            self.timeout_gen = self.biris_timeout.arm(self.record.timeout_s)  # BIRIS is alive
        points: list[Point] = []
        for acq in msg.acquisitions:
            if scan is None or acq.seq_id != scan.seq_id:
                self.counters["stale_acquisitions"] += 1
                continue
            if scan.ring:
                if not self._head_moving(scan, acq.azimuth):
                    self.counters["constant_azimuth"] += 1  # the head stood still: dropped
                    continue
                acq = dataclasses.replace(acq, index=len(scan.acqs))
            scan.acqs[acq.index] = acq
            self.counters["acquisitions"] += 1
            self.counters["discarded_samples"] += acq.discarded
            point = Point(
                azimuth=acq.azimuth,
                range_mm=acq.closest_mm,
                profile=acq.profile,
                intensity=acq.intensity,
                t=acq.t,
                acq=acq.index,
                scan_seq=self.seq[scan.direction] + 1,
                elevation=scan.elevation,
                mount=self.mount,
            )
            self.latest_point = point
            points.append(point)
        if scan is not None:
            scan.lost += msg.lost
        if points or (scan is not None and msg.lost):
            self._deliver_points(points, msg.lost if scan is not None else 0)

    @staticmethod
    def _head_moving(scan: _ActiveScan, azimuth: int) -> bool:
        """Whether a continuous-mode acquisition belongs to the sweep: not made while the head
        still stood at the start, nor after one was made with it standing at the end.

        Only the ends are judged: those are where the report expects "samples at constant
        azimuth". An acquisition in between is kept whatever its tag, so that a stall or a
        tagging hiccup shows in the data instead of being hidden.
        """
        if not scan.left_start:
            if abs(azimuth - scan.start) <= STILL_COUNTS:
                return False
            scan.left_start = True
        if scan.at_end:
            return False
        if abs(azimuth - scan.destination) <= STILL_COUNTS:
            scan.at_end = True
        return True

    # ============================================================================ delivery
    def _live_conns(self) -> list[ClientConn]:
        """Open connections whose owners still run; the others are released on the way."""
        live = []
        for conn in list(self.conns.values()):
            if not conn.alive:
                self._drop_conn(conn, "its owning thread has ended")
                continue
            live.append(conn)
        return live

    def _deliver(self, scan: Scan) -> None:
        now = self.clock()
        for conn in self._live_conns():
            if conn.wants_scans:
                before = conn.delivered
                conn.offer(scan, now)
                self.counters["deliveries"] += conn.delivered - before

    def _deliver_points(self, points: list[Point], lost: int) -> None:
        now = self.clock()
        for conn in self._live_conns():
            if not conn.wants_points:
                continue
            if lost:
                conn.lost(lost)
            before = conn.delivered
            for point in points:
                conn.offer(point, now)
            self.counters["deliveries"] += conn.delivered - before

    def _hand_over(self, env: Envelope, conn: ClientConn, item: Scan | Point | None) -> None:
        """Answer REQUEST_POINT / REQUEST_SCAN_DATA: stamped, and its latency recorded."""
        if item is None:
            env.reply(None)
            return
        sent = stamp(item, self.clock())
        if env.reply(sent) is not False:
            conn.record(sent)
            self.counters["deliveries"] += 1

    def _after_motion_settles(self) -> None:
        """Pending HOME and motor parameters run once nothing else moves."""
        if self.scan is not None or self.az.busy() or self.fault is not None:
            return
        if self.params_pending is not None:
            params, self.params_pending = self.params_pending, None
            self._load_params(params)
        if self.home_pending and self.continuous is None and self.deferred_scan is None:
            self.home_pending = False
            self._go_home()

    def _load_params(self, params: MotorParams) -> None:
        def done(err: str | None) -> None:
            if err is None:
                self.az.motor = params
            self._after_motion_settles()

        self._submit_motion(
            self.az, Motion(m.ParamsOrder(params), on_done=done, on_fail=lambda e: None)
        )

    def _go_home(self) -> None:
        if self.position == 0:
            return
        self.homing = True

        def done(err: str | None) -> None:
            self.homing = False
            self._after_motion_settles()

        self._submit_motion(self.az, Motion(m.MoveOrder(0), on_done=done, on_fail=lambda e: None))

    # ============================================================================ elevation
    def _on_set_elevation(self, env: Envelope, msg: m.SetElevation) -> None:
        self._conn(msg.conn)
        self._check_usable()
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
        """Tilt to ``dest`` and load its table; BIRIS must not be acquiring meanwhile."""
        self.elevation_pending = None
        tilt = _Tilt(dest)
        self.tilt = tilt
        self.counters["tilts"] += 1
        if self.ring in ("starting", "live", "stopping"):
            self._stop_ring(lambda: self._tilt_go(tilt))
        else:
            self._tilt_go(tilt)

    def _tilt_go(self, tilt: _Tilt) -> None:
        if self.tilt is not tilt or self.fault is not None:
            return
        dest = tilt.destination
        if dest != self.el.position:
            self._submit_motion(
                self.el,
                Motion(
                    m.MoveOrder(dest),
                    on_done=lambda err: self._tilt_part(tilt, moved=True),
                    on_fail=lambda exc: None,
                ),
            )
        else:
            tilt.moved = True
        self._submit_command(
            _Command(
                int(BiCommand.BI_LOAD_LUT),
                str(dest),
                0,
                0,
                on_done=lambda status, param: self._tilt_lut_loaded(tilt, status),
                on_fail=lambda exc: None,
            )
        )

    def _tilt_lut_loaded(self, tilt: _Tilt, status: int) -> None:
        if self.tilt is not tilt:
            return
        if status != BiStatus.OK:
            self._fault(
                "protocol",
                f"BI_LOAD_LUT {tilt.destination} failed: STATUS {status} ({_status_name(status)})"
                " -- BIRIS has no calibration for an elevation the init record allows",
            )
            return
        self.lut = tilt.destination
        self.counters["lut_loads"] += 1
        tilt.lut = True
        self._tilt_part(tilt)

    def _tilt_part(self, tilt: _Tilt, *, moved: bool = False) -> None:
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

    # ============================================================================ continuous mode
    def _start_ring(self) -> None:
        """BI_START_CONTINUOUS, unless BIRIS already acquires continuously (or cannot)."""
        if not self.ring_mode or self.ring != "off" or self.fault is not None:
            return
        if self.phase != "idle" or self.tilt is not None:
            return
        self.ring = "starting"

        def started(status: int, param: bytes) -> None:
            if status != BiStatus.OK or _ring_answer(param) <= 0:
                self._fault(
                    "protocol",
                    f"BI_START_CONTINUOUS failed: STATUS {status} ({_status_name(status)}), "
                    f"answer {param.split(bytes(1))[0]!r}",
                )

        self._submit_command(
            _Command(int(BiCommand.BI_START_CONTINUOUS), "", 0, 0, started, lambda e: None)
        )

    def _on_continuous_live(self, env: Envelope, msg: m.ContinuousLive) -> None:
        env.reply(None)
        if self.ring != "starting":
            return  # stopped again before its first acquisition
        self.ring = "live"
        self.counters["continuous_starts"] += 1
        self._rearm_timeout()
        self._run_deferred()
        self._check_idle_waiters()

    def _stop_ring(self, then: Callable[[], None]) -> None:
        """BI_STOP_CONTINUOUS, then ``then`` (also when a stop is already on its way)."""
        self.ring_stop_waiters.append(then)
        if self.ring == "stopping":
            return
        self.ring = "stopping"

        def stopped(status: int, param: bytes) -> None:
            self.ring = "off"
            waiters, self.ring_stop_waiters = self.ring_stop_waiters, []
            for waiter in waiters:
                waiter()
            self._check_idle_waiters()

        self._submit_command(
            _Command(int(BiCommand.BI_STOP_CONTINUOUS), "", 0, 0, stopped, lambda e: None)
        )

    # ============================================================================ client requests
    def _on_open(self, env: Envelope, msg: m.OpenRequest) -> None:
        kind = ConnectionKind(msg.kind)
        policy, depth = check_policy(kind, msg.policy, msg.depth)
        owner = msg.owner_ident
        assert isinstance(owner, threading.Thread)
        ident = self.next_conn
        self.next_conn += 1
        self.conns[ident] = ClientConn(ident, kind, weakref.ref(owner), policy, depth)
        env.reply((ident, policy, depth))

    def _on_close(self, env: Envelope, msg: m.CloseRequest) -> None:
        conn = self.conns.get(msg.conn)
        if conn is not None:
            self._drop_conn(conn, "closed")
        env.reply(None)

    def _drop_conn(self, conn: ClientConn, why: str) -> None:
        self.conns.pop(conn.ident, None)
        self.closed_drops += conn.dropped
        if conn.waiting is not None:
            _fail(conn.waiting, ConnectionClosed(f"connection {conn.ident} {why}"))
            conn.waiting = None
        log.debug("connection %d released: %s", conn.ident, why)

    def _on_request_point(self, env: Envelope, msg: m.RequestPoint) -> None:
        conn = self._conn(msg.conn)
        self._check_usable()
        self._hand_over(env, conn, self.latest_point)

    def _on_request_scan_data(self, env: Envelope, msg: m.RequestScanData) -> None:
        conn = self._conn(msg.conn)
        self._check_usable()
        self._hand_over(env, conn, self.buffers[Direction(msg.direction)])

    def _on_motor_params(self, env: Envelope, msg: m.BirisMotorParams) -> None:
        self._conn(msg.conn)
        self._check_usable()
        if not self._scan_busy() and not self.az.moving():
            self._load_params(msg.params)
        else:
            self.params_pending = msg.params
        env.reply(None)

    def _check_can_scan(self) -> None:
        if self._scan_busy() or self.continuous is not None:
            raise RequestError("a scan is in progress; stop it or wait for it to end first")
        if self.az.moving() or self.home_pending:
            raise RequestError("the motor is moving; wait until it is idle")
        if self.params_pending is not None:  # cannot be: it is only set while moving
            self._load_params(self.params_pending)
            self.params_pending = None

    def _on_single_scan(self, env: Envelope, msg: m.SingleScanRqst) -> None:
        self._conn(msg.conn)
        self._check_usable()
        self._check_can_scan()
        dest = clamp_counts(msg.destination)
        if dest == self.position:
            raise RequestError(f"the head is already at {dest} counts; a scan needs a length")
        self._when_ready(lambda: self._start_scan(dest))
        env.reply(dest)

    def _on_cont_scan(self, env: Envelope, msg: m.ContScanRqst) -> None:
        self._conn(msg.conn)
        self._check_usable()
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
        self._conn(msg.conn)
        self._check_usable()
        if self.continuous is not None:
            if self.scan is None and self.deferred_scan is not None:
                self.deferred_scan = None  # no sweep has started yet: nothing to complete
                self.continuous = None
                self._after_motion_settles()
            else:
                self.stop_pending = True
        env.reply(None)
        self._check_idle_waiters()

    def _on_home(self, env: Envelope, msg: m.BirisHome) -> None:
        self._conn(msg.conn)
        self._check_usable()
        if not self._scan_busy() and not self.az.busy() and self.params_pending is None:
            self._go_home()
        else:
            self.home_pending = True
        env.reply(None)

    def _on_ready_for_data(self, env: Envelope, msg: m.ReadyForData) -> None:
        conn = self._conn(msg.conn, data=True)
        self._check_usable()
        before = conn.delivered
        conn.ready(env, self.clock())
        self.counters["deliveries"] += conn.delivered - before

    def _on_wait_idle(self, env: Envelope, msg: m.WaitIdle) -> None:
        self._conn(msg.conn)
        self._check_usable()
        if self.is_idle():
            env.reply(None)
        else:
            self.idle_waiters.append(env)

    def _on_status(self, env: Envelope, msg: m.StatusRequest) -> None:
        env.reply(self.status())

    def state(self) -> str:
        """What the server is doing, for status(): the most telling of its activities."""
        if self.fault is not None:
            return f"fault:{self.fault.kind}"
        if self.phase == "initialising":
            return "initialising"
        if self.homing:
            return "homing"
        if self.tilt is not None:
            return "tilting"
        if self._scan_busy() or self.continuous is not None:
            return "scanning"
        return "idle"

    def status(self) -> dict[str, Any]:
        counters = dict(self.counters)
        counters["dropped_deliveries"] = self.closed_drops + sum(
            c.dropped for c in self.conns.values()
        )
        return {
            "state": self.state(),
            "azimuth": self.position,
            "elevation": self.el.position,
            "calibration": self.lut,
            "continuous": self.continuous is not None,
            "acquisition": "continuous" if self.ring_mode else "single",
            "ring": self.ring,
            "counters": counters,
            "connections": {c.ident: c.summary() for c in self.conns.values()},
        }

    # ============================================================================ init / reset
    def _on_reset(self, env: Envelope, msg: m.ResetRequest) -> None:
        if msg.conn:
            self._conn(msg.conn)
        if self.phase == "initialising" and self.init_waiters:
            raise RequestError("initialisation is already running")
        self.init_waiters.append(env)
        self.phase = "initialising"
        self.fault = None
        self._clear_activity()
        self.ring = "off"
        self._start_initialiser()

    def _clear_activity(self) -> None:
        """Forget every scan, tilt and motion under way or waiting (reset, fault)."""
        self.scan = None
        self.deferred_scan = None
        self.continuous = None
        self.stop_pending = self.home_pending = self.homing = False
        self.params_pending = None
        self.tilt = None
        self.elevation_pending = None
        self.ring_stop_waiters.clear()
        for axis in (self.az, self.el):
            axis.queue.clear()
            axis.current = None
            axis.watchdog.disarm()

    def _on_init_command(self, env: Envelope, msg: m.InitCommand) -> None:
        cmd = _Command(
            msg.code,
            msg.param,
            0,
            0,
            on_done=lambda status, param: _reply(env, (status, param)),
            on_fail=lambda exc: _fail(env, exc),
        )
        self.init_commands.append(cmd)
        self._submit_command(cmd)

    def _on_init_move(self, env: Envelope, msg: m.InitMove) -> None:
        def done(err: str | None) -> None:
            if err is None:
                _reply(env, None)
            else:
                _fail(env, HardwareFault("motor_stall", err))

        self._submit_motion(
            self._axis(msg.axis),
            Motion(m.MoveOrder(msg.destination), on_done=done, on_fail=lambda exc: _fail(env, exc)),
        )

    def _on_init_done(self, env: Envelope, msg: m.InitDone) -> None:
        env.reply(None)
        waiters, self.init_waiters = self.init_waiters, []
        # commands the initialiser gave up on must not be issued later
        stale = {id(c) for c in self.init_commands}
        self.cmd_queue = deque(c for c in self.cmd_queue if id(c) not in stale)
        self.init_commands.clear()
        if msg.error is not None:
            exc = msg.error
            fault = (
                exc
                if isinstance(exc, HardwareFault)
                else HardwareFault("protocol", f"initialisation failed: {exc}")
            )
            self.phase = "idle"
            self._fault(fault.kind, fault.message)
            for w in waiters:
                _fail(w, fault)
            return
        result = msg.addressing
        assert isinstance(result, InitResult)
        self.samples = result.samples
        self.phase = "idle"
        self.az.position = 0
        self.el.position = 0
        self.elevation = 0
        self.lut = 0  # the initialiser loaded the table for the level head
        for w in waiters:
            _reply(w, result)
        self._start_ring()
        self._check_idle_waiters()

    # ============================================================================ faults
    def _task_fault(self, env: Envelope, kind: FaultKind, text: str) -> None:
        env.reply(None)
        self._fault(kind, text)

    def _fault(self, kind: FaultKind, text: str) -> None:
        """Enter the fault state: every blocked and later call gets the HardwareFault."""
        if self.fault is not None:
            return
        fault = HardwareFault(kind, text)
        log.error("hardware fault: %s", fault)
        self.fault = fault
        self.counters["faults"] += 1
        self.biris_timeout.disarm()
        for axis in (self.az, self.el):
            axis.fail_all(fault)  # before forgetting them: the initialiser may wait on one
        self._clear_activity()
        for cmd in list(self.cmd_queue):
            cmd.on_fail(fault)
        self.cmd_queue.clear()
        if self.current_cmd is not None and self.current_cmd in self.init_commands:
            self.current_cmd.on_fail(fault)
        waiters, self.idle_waiters = self.idle_waiters, []
        for env in waiters:
            _fail(env, fault)
        for conn in self.conns.values():
            if conn.waiting is not None:
                _fail(conn.waiting, fault)
                conn.waiting = None

    def shutdown(self) -> None:
        """Called by the server after this thread has ended: nobody may stay blocked."""
        stopped = ConnectionClosed("the BIRIS server has stopped")
        for env in self.idle_waiters + self.init_waiters:
            _fail(env, stopped)
        for conn in self.conns.values():
            if conn.waiting is not None:
                _fail(conn.waiting, stopped)


def _reply(env: Envelope, value: object) -> bool:
    """Reply, reporting whether anyone was still waiting for it."""
    result = env.reply(value)
    return result is not False


def _fail(env: Envelope, exc: BaseException) -> None:
    try:
        env.fail(exc)
    except Exception:  # already answered: nothing more to tell the sender
        log.debug("envelope already answered", exc_info=True)
