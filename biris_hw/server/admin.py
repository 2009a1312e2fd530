"""The BIRIS server's administrator: one thread, blocked on nothing but its inbox.

It owns all server state and decides everything; it never sends, never sleeps and never touches
a register. Workers get their orders in *replies*; clients that must wait (wait_idle,
READY_FOR_DATA, reset) are parked and replied to later. Rules of the report kept here:

* a new BIRIS command only after BIRIS_CMD of the previous one was serviced (``biris_ready``);
* a scan completes when both AZ_SCAN_DONE and BIRIS_CMD_COMPLETE have arrived;
* continuous scans alternate CW and CCW and start the next sweep by themselves, until
  BIRIS_STOP_SCAN_RQST, which ends scanning at the completion of the current sweep;
* data are buffered per direction and double-buffered: a client always gets the last complete
  scan of a direction, never a mix;
* BIRIS_HOME is pending while the motor moves or a motion is pending, and during continuous
  scanning it waits for STOP; HOME and new motor parameters use the trapezoid only;
* every motor destination goes through _Scan_limit (+-0x1000 counts).
"""

from __future__ import annotations

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
from biris_hw.server.initialiser import InitResult
from biris_hw.server.tasks import DeadlineTimer
from regs.biexec import BiCommand, BiStatus

__all__ = ["Administrator"]

log = logging.getLogger(__name__)


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
class _Motion:
    order: m.MoveOrder | m.ParamsOrder
    on_done: Callable[[str | None], object]
    on_fail: Callable[[BaseException], object]


@dataclass
class _ActiveScan:
    direction: Direction
    destination: int
    n: int
    seq_id: int
    acqs: dict[int, m.Acquisition] = field(default_factory=dict)
    lost: int = 0
    discarded: int = 0
    az_done: bool = False
    cmd_done: bool = False
    status: int = 0


@dataclass
class _Conn:
    ident: int
    kind: ConnectionKind
    owner: weakref.ref[threading.Thread]
    waiting: Envelope | None = None
    pending: Scan | None = None
    dropped: int = 0
    delivered: int = 0


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
    ) -> None:
        self.record = record
        self.motor: MotorParams = record.motor
        self.inbox = inbox
        self.clock = clock
        self.biris_timeout = biris_timeout
        self.motor_watchdog = motor_watchdog
        self._start_initialiser = start_initialiser
        self.phase = "initialising"
        self.fault: HardwareFault | None = None
        self.init_waiters: list[Envelope] = []
        self.init_commands: list[_Command] = []
        # workers parked on their last report
        self.transfer_env: Envelope | None = None
        self.cmd_notifier_env: Envelope | None = None
        self.az_env: Envelope | None = None
        # BIRIS commands
        self.cmd_queue: deque[_Command] = deque()
        self.current_cmd: _Command | None = None
        self.biris_ready = True
        self.cmd_token = 0
        self.timeout_enabled = False
        self.timeout_gen = -1
        # motion
        self.motion_queue: deque[_Motion] = deque()
        self.current_motion: _Motion | None = None
        self.watchdog_gen = -1
        self.position = 0
        # scanning
        self.seq_counter = 0
        self.scan: _ActiveScan | None = None
        self.continuous: tuple[int, int] | None = None
        self.stop_pending = False
        self.home_pending = False
        self.homing = False
        self.params_pending: MotorParams | None = None
        self.buffers: dict[Direction, Scan | None] = {Direction.CW: None, Direction.CCW: None}
        self.seq: dict[Direction, int] = {Direction.CW: 0, Direction.CCW: 0}
        self.latest_point: Point | None = None
        self.samples = 0
        # clients
        self.conns: dict[int, _Conn] = {}
        self.next_conn = 1
        self.idle_waiters: list[Envelope] = []
        # counters for status()
        self.counters: dict[str, int] = {
            "acquisitions": 0,
            "scans": 0,
            "dropped_acquisitions": 0,
            "discarded_samples": 0,
            "faults": 0,
            "spurious_motor_end": 0,
            "stale_acquisitions": 0,
            "stale_completions": 0,
        }
        self._handlers: dict[type, Callable[[Envelope, Any], None]] = {
            m.NewPoint: self._on_new_point,
            m.CmdTransferRdy: self._on_cmd_transfer_rdy,
            m.AzReady: self._on_az_ready,
            m.AzScanDone: self._on_az_scan_done,
            m.BirisCmdComplete: self._on_cmd_complete,
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
    def _conn(self, ident: int, *, data: bool = False) -> _Conn:
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

    def _motion_busy(self) -> bool:
        return self.current_motion is not None or bool(self.motion_queue)

    def is_idle(self) -> bool:
        return (
            self.phase == "idle"
            and self.scan is None
            and not self._motion_busy()
            and not self.home_pending
            and self.params_pending is None
            and self.current_cmd is None
            and not self.cmd_queue
        )

    def _check_idle_waiters(self) -> None:
        if self.idle_waiters and self.is_idle():
            waiters, self.idle_waiters = self.idle_waiters, []
            for env in waiters:
                env.reply(None)

    def _expected_move_s(self, distance: int, params: MotorParams) -> float:
        period = params.sample_period_s
        vmax = max(params.max_vel, 1)
        accel = max(params.max_accel / 256.0, 1.0 / 256.0)
        samples = abs(distance) / vmax + 2.0 * vmax / accel + 2.0
        return samples * period

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
        if self.timeout_enabled:
            self.timeout_gen = self.biris_timeout.arm(self.record.timeout_s)

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
        self.biris_timeout.disarm()
        if cmd is not None:
            cmd.on_done(msg.status, msg.param)
        self._pump_commands()
        self._check_idle_waiters()

    def _on_timeout_err(self, env: Envelope, msg: m.BirisTimeoutErr) -> None:
        env.reply(None)
        if msg.generation == self.timeout_gen and self.current_cmd is not None:
            self._fault(
                "timeout", f"BIRIS did not respond for {self.record.timeout_s:g} s of hardware time"
            )

    def _on_timeout_enable(self, env: Envelope, msg: m.TimeoutEnable) -> None:
        self._conn(msg.conn)
        self._check_usable()
        self.timeout_enabled = True
        if self.current_cmd is not None:
            self.timeout_gen = self.biris_timeout.arm(self.record.timeout_s)
        env.reply(None)

    def _on_timeout_disable(self, env: Envelope, msg: m.TimeoutDisable) -> None:
        self._conn(msg.conn)
        self._check_usable()
        self.timeout_enabled = False
        self.biris_timeout.disarm()
        env.reply(None)

    # ============================================================================ motion
    def _submit_motion(self, job: _Motion) -> None:
        self.motion_queue.append(job)
        self._pump_motion()

    def _pump_motion(self) -> None:
        if self.fault is not None or self.current_motion is not None or self.az_env is None:
            return
        if not self.motion_queue:
            return
        job = self.motion_queue.popleft()
        self.current_motion = job
        env, self.az_env = self.az_env, None
        order = job.order
        if isinstance(order, m.MoveOrder):
            dest = clamp_counts(order.destination)  # _Scan_limit, whatever asked for it
            order = m.MoveOrder(dest)
            duration = self._expected_move_s(dest - self.position, self.motor)
            self.watchdog_gen = self.motor_watchdog.arm(duration * 1.5 + 1.0)
            self.position = dest
        env.reply(order)

    def _on_az_ready(self, env: Envelope, msg: m.AzReady) -> None:
        self.az_env = env
        job = self.current_motion
        if job is not None:
            if msg.error is not None:
                self.current_motion = None
                self.motor_watchdog.disarm()
                self._fault("motor_stall" if "profile" in msg.error else "bus", msg.error)
                return
            if isinstance(job.order, m.ParamsOrder):
                self.current_motion = None
                job.on_done(None)
        self._pump_motion()
        self._check_idle_waiters()

    def _on_az_scan_done(self, env: Envelope, msg: m.AzScanDone) -> None:
        env.reply(None)
        job = self.current_motion
        if job is None or not isinstance(job.order, m.MoveOrder):
            self.counters["spurious_motor_end"] += 1
            return
        self.current_motion = None
        self.motor_watchdog.disarm()
        job.on_done(None)
        self._pump_motion()
        self._check_idle_waiters()

    def _on_watchdog_err(self, env: Envelope, msg: m.MotorWatchdogErr) -> None:
        env.reply(None)
        if msg.generation == self.watchdog_gen and self.current_motion is not None:
            self._fault("motor_stall", "the azimuth motor did not reach its destination")

    # ============================================================================ scans
    def _direction_to(self, dest: int) -> Direction:
        return Direction.CCW if dest > self.position else Direction.CW

    def _start_scan(self, dest: int) -> None:
        if dest == self.position:
            raise RequestError(f"the head is already at {dest} counts; a scan needs a length")
        direction = self._direction_to(dest)
        n = acquisitions_for(abs(dest - self.position), self._record_with_motor())
        self.seq_counter += 1
        scan = _ActiveScan(direction, dest, n, self.seq_counter)
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
            _Motion(
                m.MoveOrder(dest),
                on_done=lambda err: self._scan_part_done(scan, motion=True),
                on_fail=lambda exc: None,
            )
        )

    def _record_with_motor(self) -> BirisInitRecord:
        """The record with the motor parameters the next move will run with: a parameter load
        still queued ahead of it counts, since the motion queue is served in order."""
        motor = self.motor
        for job in [*([self.current_motion] if self.current_motion else []), *self.motion_queue]:
            if isinstance(job.order, m.ParamsOrder):
                motor = job.order.params
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
        if scan.az_done and scan.cmd_done:
            self._finish_scan(scan)

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
        if self.continuous is not None and not self.stop_pending:
            cw, ccw = self.continuous
            self._start_scan(ccw if scan.destination == cw else cw)  # the other limit
        else:
            self.continuous = None
            self.stop_pending = False
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
        dropped = max(0, scan.n - n)
        if dropped:
            log.warning(
                "scan %d (%s): %d of %d acquisitions lost",
                scan.seq_id,
                scan.direction.name,
                dropped,
                scan.n,
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
        )

    def _on_new_point(self, env: Envelope, msg: m.NewPoint) -> None:
        env.reply(None)
        scan = self.scan
        if self.timeout_enabled and self.current_cmd is not None:
            self.timeout_gen = self.biris_timeout.arm(self.record.timeout_s)  # BIRIS is alive
        for acq in msg.acquisitions:
            if scan is None or acq.seq_id != scan.seq_id:
                self.counters["stale_acquisitions"] += 1
                continue
            scan.acqs[acq.index] = acq
            self.counters["acquisitions"] += 1
            self.counters["discarded_samples"] += acq.discarded
            self.latest_point = Point(
                azimuth=acq.azimuth,
                range_mm=acq.closest_mm,
                profile=acq.profile,
                intensity=acq.intensity,
                t=acq.t,
                acq=acq.index,
                scan_seq=self.seq[scan.direction] + 1,
            )
        if scan is not None:
            scan.lost += msg.lost

    def _deliver(self, scan: Scan) -> None:
        for conn in list(self.conns.values()):
            owner = conn.owner()
            if owner is None or not owner.is_alive():
                self._drop_conn(conn, "its owning thread has ended")
                continue
            if conn.kind is not ConnectionKind.DATA:
                continue
            if conn.waiting is not None:
                env, conn.waiting = conn.waiting, None
                if _reply(env, (scan, conn.dropped)):
                    conn.delivered += 1
                    continue
            if conn.pending is not None:
                conn.dropped += 1
            conn.pending = scan

    def _after_motion_settles(self) -> None:
        """Pending HOME and motor parameters run once nothing else moves."""
        if self.scan is not None or self._motion_busy() or self.fault is not None:
            return
        if self.params_pending is not None:
            params, self.params_pending = self.params_pending, None
            self._load_params(params)
        if self.home_pending and self.continuous is None:
            self.home_pending = False
            self._go_home()

    def _load_params(self, params: MotorParams) -> None:
        def done(err: str | None) -> None:
            if err is None:
                self.motor = params
            self._after_motion_settles()

        self._submit_motion(_Motion(m.ParamsOrder(params), on_done=done, on_fail=lambda e: None))

    def _go_home(self) -> None:
        if self.position == 0:
            return
        self.homing = True

        def done(err: str | None) -> None:
            self.homing = False
            self._after_motion_settles()

        self._submit_motion(_Motion(m.MoveOrder(0), on_done=done, on_fail=lambda e: None))

    # ============================================================================ client requests
    def _on_open(self, env: Envelope, msg: m.OpenRequest) -> None:
        ident = self.next_conn
        self.next_conn += 1
        owner = msg.owner_ident
        assert isinstance(owner, threading.Thread)
        self.conns[ident] = _Conn(ident, msg.kind, weakref.ref(owner))
        env.reply(ident)

    def _on_close(self, env: Envelope, msg: m.CloseRequest) -> None:
        conn = self.conns.get(msg.conn)
        if conn is not None:
            self._drop_conn(conn, "closed")
        env.reply(None)

    def _drop_conn(self, conn: _Conn, why: str) -> None:
        self.conns.pop(conn.ident, None)
        if conn.waiting is not None:
            _fail(conn.waiting, ConnectionClosed(f"connection {conn.ident} {why}"))
            conn.waiting = None
        log.debug("connection %d released: %s", conn.ident, why)

    def _on_request_point(self, env: Envelope, msg: m.RequestPoint) -> None:
        self._conn(msg.conn)
        self._check_usable()
        env.reply(self.latest_point)

    def _on_request_scan_data(self, env: Envelope, msg: m.RequestScanData) -> None:
        self._conn(msg.conn)
        self._check_usable()
        env.reply(self.buffers[Direction(msg.direction)])

    def _on_motor_params(self, env: Envelope, msg: m.BirisMotorParams) -> None:
        self._conn(msg.conn)
        self._check_usable()
        if self.scan is None and not self._moving():
            self._load_params(msg.params)
        else:
            self.params_pending = msg.params
        env.reply(None)

    def _moving(self) -> bool:
        """A move (not a parameter load) is running or queued."""
        jobs = [*self.motion_queue, *([self.current_motion] if self.current_motion else [])]
        return any(isinstance(job.order, m.MoveOrder) for job in jobs)

    def _check_can_scan(self) -> None:
        if self.scan is not None or self.continuous is not None:
            raise RequestError("a scan is in progress; stop it or wait for it to end first")
        if self._moving() or self.home_pending:
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
        self._start_scan(dest)
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
        self._start_scan(cw if self.position != cw else ccw)
        env.reply((cw, ccw))

    def _on_stop_scan(self, env: Envelope, msg: m.StopScanRqst) -> None:
        self._conn(msg.conn)
        self._check_usable()
        if self.continuous is not None:
            self.stop_pending = True
        env.reply(None)

    def _on_home(self, env: Envelope, msg: m.BirisHome) -> None:
        self._conn(msg.conn)
        self._check_usable()
        if self.scan is None and not self._motion_busy() and self.params_pending is None:
            self._go_home()
        else:
            self.home_pending = True
        env.reply(None)

    def _on_ready_for_data(self, env: Envelope, msg: m.ReadyForData) -> None:
        conn = self._conn(msg.conn, data=True)
        self._check_usable()
        if conn.pending is not None:
            scan, conn.pending = conn.pending, None
            if _reply(env, (scan, conn.dropped)):
                conn.delivered += 1
            else:
                conn.pending = scan
            return
        if conn.waiting is not None:
            _fail(conn.waiting, RequestError("superseded by a newer READY_FOR_DATA"))
        conn.waiting = env

    def _on_wait_idle(self, env: Envelope, msg: m.WaitIdle) -> None:
        self._conn(msg.conn)
        self._check_usable()
        if self.is_idle():
            env.reply(None)
        else:
            self.idle_waiters.append(env)

    def _on_status(self, env: Envelope, msg: m.StatusRequest) -> None:
        env.reply(self.status())

    def status(self) -> dict[str, Any]:
        if self.fault is not None:
            state = f"fault:{self.fault.kind}"
        elif self.phase == "initialising":
            state = "initialising"
        elif self.homing:
            state = "homing"
        elif self.scan is not None:
            state = "scanning"
        else:
            state = "idle"
        return {
            "state": state,
            "azimuth": self.position,
            "continuous": self.continuous is not None,
            "counters": dict(self.counters),
            "connections": {
                c.ident: {"kind": c.kind.name, "delivered": c.delivered, "dropped": c.dropped}
                for c in self.conns.values()
            },
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
        self.scan = None
        self.continuous = None
        self.stop_pending = self.home_pending = self.homing = False
        self.params_pending = None
        self.motion_queue.clear()
        self.current_motion = None
        self.motor_watchdog.disarm()
        self._start_initialiser()

    def _on_init_command(self, env: Envelope, msg: m.InitCommand) -> None:
        if self.fault is not None:  # a fault during initialisation ends it, at once
            _fail(env, self.fault)
            return
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
        if self.fault is not None:
            _fail(env, self.fault)
            return

        def done(err: str | None) -> None:
            if err is None:
                _reply(env, None)
            else:
                _fail(env, HardwareFault("motor_stall", err))

        self._submit_motion(
            _Motion(m.MoveOrder(msg.destination), on_done=done, on_fail=lambda exc: _fail(env, exc))
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
        self.position = 0
        for w in waiters:
            _reply(w, result)
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
        self.motor_watchdog.disarm()
        self.scan = None
        self.continuous = None
        self.stop_pending = self.home_pending = self.homing = False
        self.params_pending = None
        for job in list(self.motion_queue):
            job.on_fail(fault)
        self.motion_queue.clear()
        if self.current_motion is not None:
            self.current_motion.on_fail(fault)
            self.current_motion = None
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
