"""The BIRIS server's administrator: one thread, blocked on nothing but its inbox.

"With the arrival of a message at the server, an appropriate case statement is executed and the
server again blocks awaiting the next request": :meth:`Administrator.run` is that loop,
:meth:`Administrator._cases` maps every message to its case, and :meth:`Administrator.handle`
runs one case -- which is all a test needs to drive the server's decisions without threads (see
``tests/core.py``). The administrator never sends, never sleeps and never touches a register:
workers get their orders in *replies*, and clients that must wait (wait_idle, READY_FOR_DATA,
reset) are parked and replied to later.

Its state lives in components that own their fields and expose named operations:

* :class:`~biris_hw.server.faults.Lifecycle` -- initialising / idle, the fault, who waits;
* :class:`~biris_hw.server.cmd_transfer.CommandChannel` -- BIRIS commands one at a time
  (``Biris_ready``) and the BIRIS timeout;
* :class:`~biris_hw.server.motion.AxisState` (pan and tilt) -- each axis worker's orders and
  watchdog; :class:`~biris_hw.server.motor_control.MotorRequests` -- HOME and motor parameters
  waiting for the pan;
* :class:`~biris_hw.server.scanning.ScanSequencer` -- single and continuous scans, buffers per
  direction, the latest point;
* :class:`~biris_hw.server.elevation.TiltControl` -- SET_ELEVATION's tilts;
* :class:`~biris_hw.server.continuous_mode.Ring` -- Appendix D's continuous acquisition;
* :class:`~biris_hw.server.connections.Connections` -- clients and every hand-over of data;
* :class:`~biris_hw.server.encoders.Encoders` -- the encoder readings a status carries, taken
  by the ``encoder_reader`` worker when a status needs a fresher one.

After every message that may change what a client would be told, the administrator moves the
epoch of its :class:`~biris_hw.protocol.Bulletin` on and numbers a change of the status's
signature (:attr:`ServerStatus.change <biris_hw.status.ServerStatus.change>`): a STATUS request
with ``newer_than`` is parked until then (the push), and clients read the bulletin to know,
without asking, that nothing has happened since they last asked.

The administrator coordinates them: the cases below are the report's, and what follows the end
of a BIRIS command or of a motion is found through the command's or order's *purpose*
(:meth:`_command_done`, :meth:`_motion_done`), not through stored closures.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from biris_hw import protocol as p
from biris_hw.angles import clamp_counts
from biris_hw.data import ConnectionKind, Direction
from biris_hw.devices import SETTLE_LIMIT_S
from biris_hw.errors import (
    BirisError,
    BusError,
    ConnectionClosed,
    FaultKind,
    HardwareFault,
    RequestError,
)
from biris_hw.ipc import Envelope, Mailbox, TaskStopped
from biris_hw.records import BirisInitRecord, MotorParams
from biris_hw.server import messages as m
from biris_hw.server.acquisition import ring_length
from biris_hw.server.cmd_transfer import (
    BirisCommand,
    CommandChannel,
    CommandPurpose,
    Timer,
    command_name,
)
from biris_hw.server.cmd_transfer import status_name as status_name
from biris_hw.server.connections import Connections
from biris_hw.server.continuous_mode import Ring
from biris_hw.server.counters import Counters
from biris_hw.server.delivery import ClientConn
from biris_hw.server.elevation import Tilt, TiltControl, TiltPhase
from biris_hw.server.encoders import Encoders
from biris_hw.server.faults import Lifecycle, Phase, fail_quietly, log
from biris_hw.server.initialiser import InitResult
from biris_hw.server.motion import ARRIVAL_TOLERANCE_COUNTS, AxisState, Motion, MotionPurpose
from biris_hw.server.motor_control import MotorRequests
from biris_hw.server.scan_assembly import ActiveScan
from biris_hw.server.scan_timing import ScanTiming, data_rate_mismatch
from biris_hw.server.scanning import AcquisitionFate, ScanSequencer
from biris_hw.server.start_schedule import StartSchedule
from biris_hw.status import ServerState, ServerStatus, StatusChanges
from biris_hw.timebase import timebase_of
from regs.biexec import BiCommand, BiStatus
from regs.tech80 import Axis

__all__ = ["Administrator"]

Case = Callable[[Envelope, Any], None]

_READS: frozenset[type] = frozenset(
    {
        p.StatusRequest,
        p.ReadyForData,
        p.RequestPoint,
        p.RequestScanData,
        p.WaitIdle,
        m.EncoderReading,
    }
)
"""Messages that change nothing a client could be told but the answer to the sender itself (a
parked wait, a buffer taken from the sender's own queue, a reading of the encoders): after any
other message the administrator moves its epoch on (:class:`biris_hw.protocol.Bulletin`) and
looks whether the status has changed."""

LAG_NOTE_S = 0.005
"""Hardware seconds of lag (:attr:`BirisHardware.lag`) beyond which a timeout or motor_stall
fault's message says the host could not keep up."""


class Administrator:
    """The server's decisions; ``run()`` is the administrator thread, ``handle()`` one case."""

    def __init__(
        self,
        record: BirisInitRecord,
        inbox: Mailbox,
        clock: Callable[[], float],
        biris_timeout: Timer,
        motor_watchdog: Timer,
        start_initialiser: Callable[[], None],
        elevation_watchdog: Timer | None = None,
        time_scale: float = 1.0,
        recheck_motion: Callable[[], None] | None = None,
        recheck_biris: Callable[[], None] | None = None,
        lag: Callable[[], float] | None = None,
        extras: Callable[[], Mapping[str, Any]] | None = None,
        task_generation: Callable[[], int] | None = None,
    ) -> None:
        self.record = record
        self._recheck_motion = recheck_motion
        """Asks the level-3 routine to read the motion controller as if it had interrupted
        (never blocks); None: a watchdog that runs out is a fault at once."""
        self.inbox = inbox
        self.clock = clock
        self._start_initialiser = start_initialiser
        self.counters = Counters()
        self.life = Lifecycle()
        self.commands = CommandChannel(biris_timeout, record.timeout_s, record.timeout_enabled)
        # one record per axis (the tilt's watchdog is the pan's if none is given)
        self.az = AxisState(Axis.AZIMUTH, motor_watchdog, record.motor)
        self.el = AxisState(Axis.ELEVATION, elevation_watchdog or motor_watchdog, record.tilt_motor)
        self.requests = MotorRequests()
        # the host's own latency, in hardware seconds per real one: none on virtual time, where
        # the host takes no hardware time at all
        host_scale = timebase_of(clock, time_scale).hw_from_real(1.0)
        self.scans = ScanSequencer(self.counters, record.mount, ScanTiming(time_scale=host_scale))
        self.tilt = TiltControl(record.elevation_limits_counts)
        self.ring = Ring(record.continuous_acquisition)
        self.clients = Connections(clock, self.counters)
        self._init_syncs: list[Envelope] = []
        """The initialiser's InitSync, while the command worker is still writing."""
        self._time_scale = time_scale
        self._recheck_biris = recheck_biris
        """Asks the level-2 routine to read BIRIS afresh (never blocks); None: a BIRIS timeout
        that runs out is a fault at once."""
        self._lag = lag
        """How far behind its clock the hardware has been running (a simulator on a host that
        cannot keep up), said in a fault's message; None on the real target."""
        self._extras = extras
        """The status's parts kept outside the administrator (interrupt counts, tasks down,
        the crate's reading): read from memory the server's other parts keep, never the bus."""
        self._task_generation = task_generation
        """The supervisor's reset count (:attr:`~biris_hw.server.tasks.Supervisor.resets`), by
        which a task's failure report is told from that of a task run again since; None: every
        report is a fault."""
        self._reset_generation: int | None = None
        """That count when the reset under way began: its initialiser restarts every task that
        failed before, so their reports are not faults of the new initialisation."""
        self.bulletin = p.Bulletin(timebase_of(clock, time_scale))
        """The epoch clients read without a round trip (see :data:`_READS`)."""
        self.changes = StatusChanges()
        """The status's change number (:attr:`ServerStatus.change`)."""
        self.encoders = Encoders()
        """The encoder readings a status carries, and the worker that takes them."""
        self._status_waiters: list[tuple[Envelope, int | None, int]] = []
        """Parked STATUS requests: (envelope, connection, the change they wait to pass)."""
        self._handlers = self._cases()

    def _cases(self) -> dict[type, Case]:
        """The report's case statements: every message the server receives, and its case."""
        az, el = self.az, self.el
        return {
            # from internal tasks: notifiers, workers, timers
            m.NewPoint: self._on_new_point,  # NEW_POINT
            m.CmdTransferRdy: self._on_cmd_transfer_rdy,  # CMD_TRANSFER_RDY
            m.BirisCmdComplete: self._on_cmd_complete,  # BIRIS_CMD_COMPLETE
            m.AzReady: lambda env, msg: self._on_axis_ready(az, env, msg),  # AZ_READY
            m.AzScanDone: lambda env, msg: self._on_axis_done(az, env, msg),  # AZ_SCAN_DONE
            m.ElReady: lambda env, msg: self._on_axis_ready(el, env, msg),  # EL_READY
            m.ElScanDone: lambda env, msg: self._on_axis_done(el, env, msg),  # EL_SCAN_DONE
            m.ContinuousLive: self._on_continuous_live,  # CONTINUOUS_LIVE (Appendix D)
            m.SweepDataDone: self._on_sweep_data_done,  # SWEEP_DATA_DONE (Appendix D)
            m.BirisTimeoutErr: self._on_timeout_err,  # BIRIS_TIMEOUT_ERR
            m.MotorWatchdogErr: self._on_watchdog_err,  # beyond the report, as are the next 3
            m.MotionRechecked: self._on_motion_rechecked,
            m.BirisRechecked: self._on_biris_rechecked,
            m.TaskFailed: self._on_task_failed,
            m.EncoderReading: self._on_encoder_reading,  # beyond the report: for status()
            m.BirisBusErr: lambda env, msg: self._task_fault(  # BIRIS_BUS_ERR
                env, "bus", "bus error on the BIRIS VMEbus"
            ),
            m.BirisParityErr: lambda env, msg: self._task_fault(  # BIRIS_PARITY_ERR
                env, "parity", "parity error on the coupler"
            ),
            # from the initialiser
            m.InitSync: self._on_init_sync,
            m.InitCommand: self._on_init_command,
            m.InitMove: self._on_init_move,
            m.InitDone: self._on_init_done,
            m.SequenceStarted: self._on_sequence_started,
            # from clients
            p.OpenRequest: self._on_open,  # OPEN_REQUEST
            p.CloseRequest: self._on_close,  # CLOSE_REQUEST
            p.RequestPoint: self._on_request_point,  # REQUEST_POINT
            p.RequestScanData: self._on_request_scan_data,  # REQUEST_SCAN_DATA
            p.TimeoutEnable: self._on_timeout_enable,  # BIRIS_TIMEOUT_ENABLE
            p.TimeoutDisable: self._on_timeout_disable,  # BIRIS_TIMEOUT_DISABLE
            p.BirisMotorParams: self._on_motor_params,  # BIRIS_MOTOR_PARAMS
            p.SingleScanRqst: self._on_single_scan,  # BIRIS_SINGLE_SCAN_RQST
            p.ContScanRqst: self._on_cont_scan,  # BIRIS_CONT_SCAN_RQST
            p.StopScanRqst: self._on_stop_scan,  # BIRIS_STOP_SCAN_RQST
            p.BirisHome: self._on_home,  # BIRIS_HOME
            p.SetElevation: self._on_set_elevation,  # the report's future elevation message
            p.StartContinuous: self._on_start_continuous,  # START_CONTINUOUS (Appendix D)
            p.StopContinuous: self._on_stop_continuous,  # STOP_CONTINUOUS (Appendix D)
            p.ReadyForData: self._on_ready_for_data,  # READY_FOR_DATA
            p.WaitIdle: self._on_wait_idle,  # beyond the report, as are the two below
            p.ResetRequest: self._on_reset,
            p.StatusRequest: self._on_status,
        }

    # ============================================================================ the loop
    def run(self) -> None:
        """The administrator thread: receive, handle, until the inbox closes."""
        while True:
            try:
                env = self.inbox.receive()
            except TaskStopped:
                return
            self.handle(env)

    def handle(self, env: Envelope) -> None:
        """One message: its case runs; an error it raises goes back to the sender.

        A RequestError, HardwareFault or ConnectionClosed is the caller's answer. Anything else
        is a bug met half-way through a case, which may have left the components disagreeing:
        the server enters the fault state of kind ``internal`` (logged with its traceback,
        every caller told, the sender too), and reset starts from a clean slate.
        """
        handler = self._handlers.get(type(env.message))
        if handler is None:
            env.fail(RequestError(f"unknown message {type(env.message).__name__}"))
            return
        try:
            handler(env, env.message)
        except BirisError as exc:  # RequestError, HardwareFault, ConnectionClosed: the caller's
            fail_quietly(env, exc)
        except Exception as exc:  # a bug must not kill the server silently
            name = type(env.message).__name__
            log.exception("administrator: %s failed", name)
            fault = HardwareFault("internal", f"the server's {name} case failed: {exc!r}")
            fail_quietly(env, fault)
            try:
                self._fault(fault.kind, fault.message)
            except Exception:  # the fault path itself is broken: the phase still says so
                log.exception("administrator: could not enter the internal fault")
                self.life.enter_fault(fault.kind, fault.message)
        if type(env.message) not in _READS:
            self._after_change()

    def shutdown(self) -> None:
        """Called by the server after this thread has ended: nobody may stay blocked."""
        self._cancel_schedule()
        self.bulletin.advance()
        stopped = ConnectionClosed("the BIRIS server has stopped")
        waiting = [env for env, _conn, _change in self._status_waiters]
        self._status_waiters = []
        for env in self.life.idle_waiters + self.life.init_waiters + waiting:
            fail_quietly(env, stopped)
        for env in self.encoders.worker_gone():
            fail_quietly(env, stopped)
        self.clients.fail_waiting(stopped, forget=False)

    # ======================================================================= where things stand
    @property
    def position(self) -> int:
        """Where the pan axis stands, or will once its current move ends (counts)."""
        return self.az.position

    def _axis(self, axis: Axis) -> AxisState:
        return self.az if axis is Axis.AZIMUTH else self.el

    def is_idle(self) -> bool:
        """Initialised, and no component has anything under way or waiting."""
        return (
            self.life.phase is Phase.IDLE
            and not self.scans.busy()
            and not self.az.busy()
            and not self.el.busy()
            and self.tilt.current is None
            and self.tilt.pending is None
            and self.requests.idle()
            and not self.commands.busy()
            and self.ring.settled()
        )

    def _check_idle_waiters(self) -> None:
        """Release every wait_idle caller once nothing is under way or waiting."""
        if self.life.idle_waiters and self.is_idle():
            self.life.release_idle_waiters()

    def _ready_to_acquire(self) -> bool:
        """No tilt under way, and in continuous acquisition the ring is live."""
        return self.tilt.current is None and self.ring.ready()

    def _conn(self, ident: int, *, data: bool = False) -> ClientConn:
        """The open connection a client message names (READY_FOR_DATA needs a DATA one)."""
        conn = self.clients.get(ident)
        if conn is None:
            raise ConnectionClosed(f"connection {ident} is not open")
        if data and conn.kind is not ConnectionKind.DATA:
            raise RequestError("READY_FOR_DATA needs a DATA connection")
        return conn

    def _usable_conn(self, ident: int, *, data: bool = False) -> ClientConn:
        """:meth:`_conn`, then the lifecycle's check: the start of nearly every client case."""
        conn = self._conn(ident, data=data)
        self.life.check_usable()
        return conn

    # ============================================================================ client cases
    def _on_open(self, env: Envelope, msg: p.OpenRequest) -> None:
        conn = self.clients.open(ConnectionKind(msg.kind), msg.policy, msg.depth, msg.owner_ident)
        env.reply((conn.ident, conn.policy, conn.depth))

    def _on_close(self, env: Envelope, msg: p.CloseRequest) -> None:
        self.clients.close(msg.conn)
        env.reply(None)
        closed = [w for w in self._status_waiters if w[1] == msg.conn]
        if closed:
            self._status_waiters = [w for w in self._status_waiters if w[1] != msg.conn]
            for waiter, _conn, _change in closed:
                fail_quietly(waiter, ConnectionClosed(f"connection {msg.conn} was closed"))

    def _on_request_point(self, env: Envelope, msg: p.RequestPoint) -> None:
        conn = self._usable_conn(msg.conn)
        self.clients.hand_over(env, conn, self.scans.latest_point)

    def _on_request_scan_data(self, env: Envelope, msg: p.RequestScanData) -> None:
        conn = self._usable_conn(msg.conn)
        self.clients.hand_over(env, conn, self.scans.buffers[Direction(msg.direction)])

    def _on_ready_for_data(self, env: Envelope, msg: p.ReadyForData) -> None:
        conn = self._usable_conn(msg.conn, data=True)
        self.clients.ready(env, conn, poll=msg.poll)

    def _on_wait_idle(self, env: Envelope, msg: p.WaitIdle) -> None:
        self._usable_conn(msg.conn)
        if self.is_idle():
            env.reply(None)
        elif msg.poll:  # timeout=0: answered now, never parked
            env.fail(TimeoutError("the server is not idle"))
        else:
            self.life.idle_waiters.append(env)

    # ============================================================================ status
    def _on_status(self, env: Envelope, msg: p.StatusRequest) -> None:
        """STATUS: answered now, or (``newer_than``) parked until the status has changed since.

        Parked requests whose sender has given up (a timeout) are dropped here, so a watcher
        that times out every second leaves nothing behind while nothing changes."""
        if msg.conn is not None:
            self._conn(msg.conn)
        self._status_waiters = [w for w in self._status_waiters if w[0].waiting]
        if msg.newer_than is None or self.changes.change > msg.newer_than:
            self._answer_status(env)
        elif msg.poll:  # timeout=0: answered now, never parked
            env.fail(TimeoutError(f"the status has not changed since {msg.newer_than}"))
        else:
            self._status_waiters.append((env, msg.conn, msg.newer_than))

    def _answer_status(self, env: Envelope) -> None:
        """Reply the status, with encoder readings fresh enough: the held ones, or after the
        reader has read again (:mod:`biris_hw.server.encoders`). None while initialising,
        when the head's position is not known, and nothing to read without a reader."""
        encoders = self.encoders
        moving = self.az.busy() or self.el.busy()
        now = self.clock()
        if self.life.initialising or not encoders.available or encoders.fresh(now, moving):
            env.reply(self.status())
        else:
            encoders.want(env, now, moving)

    def _on_encoder_reading(self, env: Envelope, msg: m.EncoderReading) -> None:
        """ENCODER_READING: the reader parks again with what it read; the statuses that waited
        for it are answered."""
        self._reply_statuses(self.encoders.report(env, msg))

    def _reply_statuses(self, waiters: list[Envelope]) -> None:
        if not waiters:
            return
        status = self.status()  # one status for all of them: it is immutable
        for waiter in waiters:
            if waiter.waiting:
                waiter.reply(status)

    def _after_change(self) -> None:
        """After a message that may have changed something: the epoch moves on, and a status
        whose signature changed is pushed to the requests parked for it."""
        changed = self.changes.see(self._signature())
        self.bulletin.advance(self.changes.change)
        if not changed or not self._status_waiters:
            return
        change = self.changes.change
        due = [w for w in self._status_waiters if change > w[2]]
        self._status_waiters = [w for w in self._status_waiters if change <= w[2]]
        for env, _conn, _after in due:
            if env.waiting:
                self._answer_status(env)

    def _signature(self) -> tuple[Any, ...]:
        """:meth:`ServerStatus.signature` of the status now, without building the status (this
        runs after every message)."""
        fault = self.life.fault
        return (
            self.state(),
            fault.kind if fault is not None else None,
            self.az.position,
            self.el.position,
            self.tilt.lut,
            self.scans.continuous is not None,
            self.ring.name,
            self.ring.pending_name,
            self.ring.state.value,
            self.clients.idents(),
        )

    def state(self) -> ServerState:
        """What the server is doing, for status(): the most telling of its activities."""
        if self.life.fault is not None:
            return ServerState.FAULT
        if self.life.initialising:
            return ServerState.INITIALISING
        if self.requests.homing:
            return ServerState.HOMING
        if self.tilt.current is not None:
            return ServerState.TILTING
        if self.scans.active():
            return ServerState.SCANNING
        if not self.is_idle():
            return ServerState.BUSY
        return ServerState.IDLE

    def status(self) -> ServerStatus:
        """The status now, the encoders as last read (:meth:`_answer_status` sees to it that
        the reading is fresh enough), and the parts kept outside the administrator."""
        counters = self.counters.as_dict()
        counters["dropped_deliveries"] = self.clients.dropped()
        fault = self.life.fault
        homed = not self.life.initialising
        extras = self._extras() if self._extras is not None else {}
        return ServerStatus(
            state=self.state(),
            fault=fault.kind if fault is not None else None,
            azimuth=self.az.position,
            elevation=self.el.position,
            calibration=self.tilt.lut,
            continuous=self.scans.continuous is not None,
            acquisition=self.ring.name,
            acquisition_pending=self.ring.pending_name,
            ring=self.ring.state.value,
            counters=counters,
            acquisitions_in_progress=self.scans.in_progress(),
            connections=self.clients.summaries(),
            azimuth_live=self.encoders.azimuth if homed else None,
            elevation_live=self.encoders.elevation if homed else None,
            change=self.changes.change,
            **extras,
        )

    # ============================================================================ scans
    def _cancel_schedule(self) -> None:
        """The scan under way is abandoned: a worker waiting to start its trapezoid starts
        nothing."""
        scan = self.scans.scan
        if scan is not None and scan.schedule is not None:
            scan.schedule.cancel()

    def _check_can_scan(self) -> None:
        if self.scans.active():
            raise RequestError("a scan is in progress; stop it or wait for it to end first")
        if self.az.moving() or self.requests.home_pending:
            raise RequestError("the motor is moving; wait until it is idle")
        params = self.requests.take_params()  # cannot be: it is only pending while moving
        if params is not None:
            self._load_params(params)

    def _on_single_scan(self, env: Envelope, msg: p.SingleScanRqst) -> None:
        self._usable_conn(msg.conn)
        self._check_can_scan()
        dest = clamp_counts(msg.destination)
        if dest == self.position:
            raise RequestError(f"the head is already at {dest} counts; a scan needs a length")
        self._when_ready(dest)
        env.reply(dest)

    def _on_cont_scan(self, env: Envelope, msg: p.ContScanRqst) -> None:
        self._usable_conn(msg.conn)
        self._check_can_scan()
        cw, ccw = clamp_counts(msg.cw_limit), clamp_counts(msg.ccw_limit)
        if cw >= ccw:
            raise RequestError(
                f"the CW limit ({cw} counts) must lie clockwise of the CCW limit ({ccw})"
            )
        self.scans.start_continuous(cw, ccw)
        try:
            self._when_ready(None)
        except BaseException:  # refused means unchanged: no continuous scan stays behind
            self.scans.forget()
            raise
        env.reply((cw, ccw))

    def _on_stop_scan(self, env: Envelope, msg: p.StopScanRqst) -> None:
        self._usable_conn(msg.conn)
        if self.scans.stop():
            self._after_motion_settles()
        env.reply(None)
        self._check_idle_waiters()

    def _when_ready(self, dest: int | None) -> None:
        """Start a scan now if BIRIS may acquire, else once it may (a tilt, the ring).

        ``dest`` None: a continuous scan's first sweep (its limit is chosen when it starts).
        """
        if self._ready_to_acquire():
            self._start_scan(self._destination(dest))
            return
        self.scans.defer(dest)
        if self.ring.mode and self.tilt.current is None:
            self._start_ring()

    def _destination(self, dest: int | None) -> int:
        return self.scans.first_limit(self.position) if dest is None else dest

    def _run_deferred(self) -> None:
        """Start a scan that waited for a tilt or for the ring, if it may start now."""
        if self.scans.deferred is None or not self._ready_to_acquire():
            return
        if self.life.fault is not None:
            return
        deferred = self.scans.take_deferred()
        assert deferred is not None
        self._start_scan(self._destination(deferred.destination))

    def _start_scan(self, dest: int, after: ActiveScan | None = None) -> None:
        """Start a scan to ``dest``; ``after`` is the sweep it turns straight round from."""
        if dest == self.position:
            raise RequestError(f"the head is already at {dest} counts; a scan needs a length")
        if self.ring.mode:
            self._start_sweep(dest, after)
            return
        motor = self.az.motor_for_next_move()
        timing = self.scans.timing
        n = timing.acquisitions(dest - self.position, motor)
        scan = self.scans.open_scan(dest, self.position, self.tilt.elevation, n)
        scan.start_budget_s = timing.lateness_allowance_s
        # the trapezoid starts at a hardware time fixed by BI_ACQUIRE's write, whenever the
        # host sees BIRIS's interrupts (start_schedule); ordered now, it waits in the worker
        schedule = StartSchedule(timing.startup_lead_s, self.clock, self._time_scale)
        scan.schedule = schedule
        self._submit_command(
            BirisCommand(
                int(BiCommand.BI_ACQUIRE),
                str(n),
                CommandPurpose.ACQUIRE,
                n=n,
                seq_id=scan.seq_id,
                scan=scan,
                schedule=schedule,
            )
        )
        order = m.MoveOrder(dest, schedule=schedule)
        self._submit_motion(self.az, Motion(order, MotionPurpose.SCAN, scan=scan))

    def _on_sequence_started(self, env: Envelope, msg: m.SequenceStarted) -> None:
        """BIRIS has begun the first acquisition of a report-mode scan. Nothing waits for
        this any more (the motor starts by its schedule, whenever the host sees interrupts);
        the start-up is learned when the scan completes, from the sequence's tightest bound."""
        env.reply(None)

    def _start_sweep(self, dest: int, after: ActiveScan | None) -> None:
        """A continuous-acquisition scan: only the motor is ordered; the ring supplies data.

        A sweep that turns straight round from ``after`` starts with ``after``'s tail (made at
        the turn-around after its last acquisition) and reads on from where it ended.
        """
        follows = after is not None and after.ring and after.elevation == self.tilt.elevation
        scan = self.scans.open_scan(
            dest, self.position, self.tilt.elevation, ring=True, follows=follows
        )
        if after is not None:
            points = self.scans.carry_tail(after, scan, follows)
            if points:
                self.clients.deliver_points(points, 0)
        order = m.MoveOrder(dest, sweep=scan.seq_id, follows=follows)
        self._submit_motion(self.az, Motion(order, MotionPurpose.SCAN, scan=scan))
        self._rearm_timeout()

    def _on_new_point(self, env: Envelope, msg: m.NewPoint) -> None:
        env.reply(None)
        scan = self.scans.scan
        self._note_biris_alive()
        self.counters.lost_acquisitions += msg.lost
        self.counters.untrusted_frames += msg.untrusted
        self.counters.idle_ring_frames += msg.idle
        points = []
        for acq in msg.acquisitions:
            fate = self.scans.classify(acq)
            if fate is AcquisitionFate.KEPT:
                assert scan is not None
                points.append(self.scans.keep(scan, acq))
            elif fate is AcquisitionFate.STALE:
                self.counters.stale_acquisitions += 1
            elif fate is AcquisitionFate.STANDING:
                self.counters.constant_azimuth += 1  # the head stood still: dropped
        if scan is not None:
            scan.lost += msg.lost
        if points or (scan is not None and msg.lost):
            self.clients.deliver_points(points, msg.lost if scan is not None else 0)

    def _on_sweep_data_done(self, env: Envelope, msg: m.SweepDataDone) -> None:
        env.reply(None)
        scan = self.scans.scan
        if scan is None or not scan.ring or scan.seq_id != msg.seq_id:
            self.counters.stale_completions += 1
            return
        self._scan_part_done(scan, cmd_status=int(BiStatus.OK))

    def _scan_part_done(
        self, scan: ActiveScan | None, *, motion: bool = False, cmd_status: int | None = None
    ) -> None:
        """AZ_SCAN_DONE (``motion``) or the data's end (``cmd_status``) of ``scan``; the scan
        completes when both have arrived."""
        if scan is None or self.scans.scan is not scan:
            return
        finished = self.scans.part_done(scan, motion=motion, cmd_status=cmd_status)
        if cmd_status is not None:
            self._rearm_timeout()
        if finished:
            self._finish_scan(scan)

    def _learn_timing(self, scan: ActiveScan) -> None:
        """What a completed report-mode scan tells the next ones' schedules and counts.

        How late its motor started after BIRIS's first acquisition: the later of what the
        azimuth worker measured against its schedule and what the data say (the acquisitions
        made with the head still standing at its start: a start the transport delivered late,
        or a start-up estimated long, shows there and nowhere else). And BIRIS's start-up from
        BI_ACQUIRE's write to the first acquisition: the reader's tightest bound on it, never
        early, and as late as the promptest look of the sequence.
        """
        schedule = scan.schedule
        if schedule is None:
            return
        timing = self.scans.timing
        late = schedule.late_s or 0.0
        timing.note_lateness(max(late, scan.standing_start * timing.period_s))
        written = schedule.written_at
        if written is not None and scan.acqs:
            began = min(acq.t_origin for acq in scan.acqs.values())
            timing.note_startup(began - written)

    def _finish_scan(self, scan: ActiveScan) -> None:
        if scan.status != BiStatus.OK:
            self._fault("protocol", f"BI_ACQUIRE ended with STATUS {scan.status}")
            return
        self._learn_timing(scan)
        self.clients.deliver(self.scans.complete(scan))
        following = self.scans.following(scan)
        pending = self.tilt.pending
        if pending is not None or following is None:
            self.scans.drop_tail(scan)  # no sweep follows straight on
        if pending is not None:  # a tilt asked for during the sweep goes between sweeps
            if following is not None:
                self.scans.defer(following)
            self._start_tilt(pending)
            self._after_motion_settles()
        elif following is not None:
            self._start_scan(following, after=scan)
        else:
            self._after_motion_settles()
        self._check_idle_waiters()

    # ============================================================================ BIRIS commands
    def _submit_command(self, cmd: BirisCommand) -> None:
        self.commands.submit(cmd)
        self._pump_commands()

    def _pump_commands(self) -> None:
        if self.life.fault is None and self.commands.pump() is not None:
            self._rearm_timeout()

    def _on_cmd_transfer_rdy(self, env: Envelope, msg: m.CmdTransferRdy) -> None:
        self.commands.worker_ready(env)
        for sync in self._init_syncs:  # the initialiser may now look at COMMAND
            sync.reply(None)
        self._init_syncs.clear()
        self._pump_commands()

    def _on_cmd_complete(self, env: Envelope, msg: m.BirisCmdComplete) -> None:
        cmd = self.commands.complete(env, msg.token)
        if cmd is None:
            self.counters.stale_completions += 1
            return
        self._rearm_timeout()
        self._command_done(cmd, msg.status, msg.param)
        self._pump_commands()
        self._check_idle_waiters()

    def _command_done(self, cmd: BirisCommand, status: int, param: bytes) -> None:
        """What the completion of ``cmd`` leads to, by its purpose."""
        purpose = cmd.purpose
        if purpose is CommandPurpose.ACQUIRE:
            self._scan_part_done(cmd.scan, cmd_status=status)
        elif purpose is CommandPurpose.LOAD_LUT:
            self._tilt_lut_loaded(cmd.tilt, status)
        elif purpose is CommandPurpose.START_CONTINUOUS:
            self._ring_started(status, param)
        elif purpose is CommandPurpose.STOP_CONTINUOUS:
            self._ring_stopped()
        elif cmd.requester is not None:  # INIT
            cmd.requester.reply((status, param))

    def _command_failed(self, cmd: BirisCommand, fault: HardwareFault) -> None:
        """A command given up on by a fault: only the initialiser waits on one."""
        if cmd.purpose is CommandPurpose.INIT and cmd.requester is not None:
            fail_quietly(cmd.requester, fault)

    # -- _Biris_timeout ----------------------------------------------------------------------
    def _biris_owed(self) -> bool:
        """BIRIS owes a completion, a continuous-mode sweep's data, its ring's start, or the
        progress of its live ring (:meth:`_watching_ring`)."""
        scan = self.scans.scan
        return (
            self.commands.current is not None
            or (scan is not None and scan.ring and not scan.cmd_done)
            or self.ring.starting
            or (self.ring.live and self.life.fault is None)
        )

    def _watching_ring(self) -> bool:
        """BIRIS owes nothing but the progress of its live ring: no command, no sweep reads it.

        A live ring must advance at the data rate whether or not a sweep wants its frames, so
        the BIRIS timeout runs for it too, and each time it runs out the level-2 routine looks
        at the ring (:mod:`biris_hw.server.acquisition`, "The ring must progress"): a ring
        standing still is a hung BIRIS (``timeout``), which nothing else would notice while the
        head stands idle. These looks are routine, so they are not logged."""
        scan = self.scans.scan
        return (
            self.ring.live
            and self.life.fault is None
            and self.commands.current is None
            and not (scan is not None and scan.ring and not scan.cmd_done)
        )

    def _rearm_timeout(self) -> None:
        self.commands.rearm_timeout(self._biris_owed())

    def _note_biris_alive(self) -> None:
        if self.commands.timeout_enabled:  # per acquisition: ask nothing more when it is off
            self.commands.note_alive(self._biris_owed())

    def _on_timeout_err(self, env: Envelope, msg: m.BirisTimeoutErr) -> None:
        """_Biris_timeout ran out while BIRIS owed an answer. The countdown ran on the hardware
        clock from the last evidence of life the *host* saw, so before calling BIRIS hung the
        level-2 routine reads it afresh (:meth:`_on_biris_rechecked` decides): a host that did
        not look for 4 s is not a BIRIS that did not progress for 4 s."""
        env.reply(None)
        if not self.commands.timed_out(msg.generation, self._biris_owed()):
            return
        if self._recheck_biris is None:
            self._biris_timed_out()
            return
        if not self.commands.rechecking and not self._watching_ring():
            log.info("BIRIS timeout ran out; reading BIRIS afresh before calling it hung")
        self.commands.begin_recheck()
        self._recheck_biris()

    def _on_biris_rechecked(self, env: Envelope, msg: m.BirisRechecked) -> None:
        """The level-2 routine has read BIRIS afresh: no acquisition and no completion since
        the host last saw one, for the timeout's hardware seconds, is a hang (``timeout``);
        anything new re-arms the countdown (it came in the NEW_POINT or completion ahead)."""
        env.reply(None)
        if self.commands.end_recheck(msg.progressed) and self._biris_owed():
            self._biris_timed_out()
        elif self.commands.timeout_enabled:
            self._rearm_timeout()

    def _biris_timed_out(self) -> None:
        timeout_s = self.commands.timeout_s
        if self._watching_ring():
            self._fault(
                "timeout",
                "BIRIS stopped acquiring: its continuous-acquisition ring did not advance for "
                f"{timeout_s:g} s of hardware time",
            )
            return
        cmd = self.commands.current
        waiting = f" to {command_name(cmd.code)}" if cmd is not None else ""
        self._fault(
            "timeout", f"BIRIS did not respond{waiting} for {timeout_s:g} s of hardware time"
        )

    def _on_timeout_enable(self, env: Envelope, msg: p.TimeoutEnable) -> None:
        self._usable_conn(msg.conn)
        self.commands.enable_timeout(self._biris_owed())
        env.reply(None)

    def _on_timeout_disable(self, env: Envelope, msg: p.TimeoutDisable) -> None:
        self._usable_conn(msg.conn)
        self.commands.disable_timeout()
        env.reply(None)

    # ============================================================================ motion
    def _submit_motion(self, axis: AxisState, job: Motion) -> None:
        self.encoders.moved()
        axis.submit(job)
        self._pump_motion(axis)

    def _pump_motion(self, axis: AxisState) -> None:
        if self.life.fault is None:
            axis.dispatch()

    def _on_axis_ready(self, axis: AxisState, env: Envelope, msg: m.AzReady | m.ElReady) -> None:
        """AZ_READY / EL_READY: the worker is parked again; a parameter load is then done.

        A READY that carries an error reports the order the chip refused: a profile still
        running (the previous move never ended: motor_stall), or the fault kind the driver
        raised (a pan journal that cannot be written is ``internal``)."""
        axis.env = env
        job = axis.current
        error = msg.error
        if job is not None:
            if error is not None:
                axis.finish_current()
                self._fault(_fault_kind(msg.kind), error)
                if self.life.fault is not None:
                    self._motion_failed(job, self.life.fault)
                return
            if isinstance(job.order, m.ParamsOrder):
                axis.finish_current()
                self._motion_done(job)
        self._pump_motion(axis)
        self._check_idle_waiters()

    def _on_axis_done(
        self, axis: AxisState, env: Envelope, msg: m.AzScanDone | m.ElScanDone
    ) -> None:
        """AZ_SCAN_DONE / EL_SCAN_DONE: the profile has ended and the notifier has read where
        the axis came to rest. The chip ends its profile whatever the shaft does, so the move is
        done only if the head came to rest (the notifier's hold) at the destination (within
        ARRIVAL_TOLERANCE_COUNTS); otherwise it is a motor_stall fault, never a completed
        scan."""
        env.reply(None)
        self.encoders.moved()
        job = axis.current
        if not axis.ends_current(msg.token) or job is None:
            self.counters.spurious_motor_end += 1
            return
        assert isinstance(job.order, m.MoveOrder)  # ends_current says so
        dest = job.order.destination  # clamped by dispatch
        if not msg.settled:
            # still hunting: a reading near the destination is a ringing head passing it (a
            # filter it cannot hold), never an arrival (issue 11's random requests, seed 273)
            self._fault(
                "motor_stall",
                f"the {axis.name} motor had not come to rest {SETTLE_LIMIT_S:g} s after its "
                f"profile (last read at {msg.position} counts, destination {dest}): the "
                "filter cannot hold it or the shaft did not follow",
            )
            return
        if msg.position is not None:
            miss = msg.position - dest
            if abs(miss) > ARRIVAL_TOLERANCE_COUNTS:
                self._fault(
                    "motor_stall",
                    f"the {axis.name} motor ended its profile at {msg.position} counts, "
                    f"{miss:+d} from its destination {dest} (tolerance "
                    f"{ARRIVAL_TOLERANCE_COUNTS}): the shaft did not follow",
                )
                return
        axis.finish_current()
        self._motion_done(job)
        self._pump_motion(axis)
        self._check_idle_waiters()

    def _motion_done(self, job: Motion) -> None:
        """What the end of ``job`` leads to, by its purpose."""
        purpose = job.purpose
        if purpose is MotionPurpose.SCAN:
            self._scan_part_done(job.scan, motion=True)
        elif purpose is MotionPurpose.TILT:
            if job.tilt is not None:
                self._tilt_part(job.tilt, moved=True)
        elif purpose is MotionPurpose.HOME:
            self.requests.homing = False
            self._after_motion_settles()
        elif purpose is MotionPurpose.PARAMS:
            assert isinstance(job.order, m.ParamsOrder)
            self.az.motor = job.order.params
            self._after_motion_settles()
        elif job.requester is not None:  # INIT
            job.requester.reply(None)

    def _motion_failed(self, job: Motion, fault: HardwareFault) -> None:
        """An order given up on by a fault: only the initialiser waits on one."""
        if job.purpose is MotionPurpose.INIT and job.requester is not None:
            fail_quietly(job.requester, fault)

    def _on_watchdog_err(self, env: Envelope, msg: m.MotorWatchdogErr) -> None:
        """A move's end was not reported within its bound. The controller is asked whether
        the move had in fact ended (its interrupt lost, or a host that has not run the level-3
        routine): its answer, :meth:`_on_motion_rechecked`, decides. Until it comes the
        watchdog only asks again; with no one to ask, the move is a motor_stall at once."""
        env.reply(None)
        axis = self._axis(msg.axis)
        if msg.generation != axis.watchdog_gen or axis.current is None:
            return
        if self._recheck_motion is None:
            self._fault("motor_stall", f"the {axis.name} motor did not reach its destination")
            return
        if not axis.rechecked:
            log.warning(
                "the %s move's end was not reported within its bound; asking the controller",
                axis.name,
            )
        axis.grace()
        self._recheck_motion()

    def _on_motion_rechecked(self, env: Envelope, msg: m.MotionRechecked) -> None:
        """The controller's answer to a watchdog's question, per axis that asked.

        Ended (latched now, or its end already taken by the notifier, which is verifying the
        arrival: settling has a bound of its own): the watchdog has done its job. Not ended: a
        motor_stall if the move has had its time since it *started* -- the worker's own
        record -- and otherwise
        (a worker the host ran late, a scan's move waiting for its schedule) the watchdog is
        armed for what the move still has, from its start: a late host delays the verdict,
        never invents it.
        """
        env.reply(None)
        for axis in (self.az, self.el):
            job = axis.current
            if not axis.rechecked or job is None or not isinstance(job.order, m.MoveOrder):
                continue
            if msg.ended & axis.end_bit or msg.noticed.get(axis.axis) == job.order.token:
                axis.watchdog.disarm()
                axis.watchdog_gen = -1
                continue
            started = msg.started.get(axis.axis)
            # judged on the hardware's own progress: a simulator running behind its clock has
            # not yet had the time the clock says (the real target's lag is 0)
            lag = self._lag() if self._lag is not None else 0.0
            remaining = axis.remaining_s(started, self.clock() - 2.0 * lag)
            if remaining > 0.0:
                axis.rearm(remaining)
                continue
            self._fault(
                "motor_stall",
                f"the {axis.name} motor did not reach its destination (asked, the controller "
                "had not ended the move)",
            )
            return

    def _on_task_failed(self, env: Envelope, msg: m.TaskFailed) -> None:
        """A task hit a bus error (the target is gone), raised a hardware fault (a CiA 402
        drive's EMCY, taken by the level-3 routine: ``motor_stall``) or an unexpected exception:
        a fault of the kind it reports (anything unknown is ``internal``); the task waits for
        the next reset, which restarts it."""
        env.reply(None)
        if self._failure_overtaken(msg.generation):
            # The task runs again (or will as this reset's initialiser re-links): what it met
            # belongs to the outage the reset is recovering from, e.g. a drive's SDO read that
            # timed out on a cable pulled before the reset. A fault now would stop the new
            # initialisation for a task that is alive.
            self.counters.overtaken_task_failures += 1
            log.warning(
                "%s failed before the reset that restarts it (%s: %s): not a fault of the new "
                "initialisation",
                msg.task,
                msg.kind,
                msg.text,
            )
        else:
            self._fault(_fault_kind(msg.kind), f"{msg.task}: {msg.text}")
        if msg.task == "encoder_reader":  # no reading will come until the reset restarts it
            self._reply_statuses(self.encoders.worker_gone())

    def _failure_overtaken(self, generation: int) -> bool:
        """Whether a task failure of supervisor ``generation`` is of a task that runs again
        since, or that the initialisation under way restarts (it re-links first, then restarts
        every task down: :meth:`~biris_hw.server.initialiser.Initialiser.relink`)."""
        if self._task_generation is None:
            return False
        fresh_from = self._task_generation()
        if self.life.initialising and self._reset_generation is not None:
            fresh_from = max(fresh_from, self._reset_generation + 1)
        return generation < fresh_from

    # -- BIRIS_HOME and BIRIS_MOTOR_PARAMS ---------------------------------------------------
    def _on_motor_params(self, env: Envelope, msg: p.BirisMotorParams) -> None:
        self._usable_conn(msg.conn)
        if not self.scans.busy() and not self.az.moving():
            self._load_params(msg.params)
        else:
            self.requests.params_pending = msg.params
        env.reply(None)

    def _on_home(self, env: Envelope, msg: p.BirisHome) -> None:
        self._usable_conn(msg.conn)
        if not self.scans.busy() and not self.az.busy() and self.requests.params_pending is None:
            self._go_home()
        else:
            self.requests.home_pending = True
        env.reply(None)

    def _after_motion_settles(self) -> None:
        """Run a pending parameter load, then a pending HOME, once nothing else moves."""
        self._take_pending_acquisition()  # a START_CONTINUOUS that waited for scanning to end
        if self.scans.scan is not None or self.az.busy() or self.life.fault is not None:
            return
        params = self.requests.take_params()
        if params is not None:
            self._load_params(params)
        waiting = self.scans.continuous is not None or self.scans.deferred is not None
        if self.requests.home_pending and not waiting:
            self.requests.home_pending = False
            self._go_home()

    def _load_params(self, params: MotorParams) -> None:
        self._submit_motion(self.az, Motion(m.ParamsOrder(params), MotionPurpose.PARAMS))

    def _go_home(self) -> None:
        if self.position == 0:
            return
        self.requests.homing = True
        self._submit_motion(self.az, Motion(m.MoveOrder(0), MotionPurpose.HOME))

    # ============================================================================ the tilt
    def _on_set_elevation(self, env: Envelope, msg: p.SetElevation) -> None:
        self._usable_conn(msg.conn)
        dest = self.tilt.clamp(msg.destination)
        if self.scans.scan is not None or self.tilt.current is not None:
            self.tilt.ask_later(dest)  # after the sweep (or tilt) under way; the latest wins
        elif self.tilt.needed(dest):
            self._start_tilt(dest)
        env.reply(dest)

    def _start_tilt(self, dest: int) -> None:
        """Tilt to ``dest`` and load its calibration table (the ring stopped first)."""
        await_ring = not self.ring.off
        tilt = self.tilt.begin(dest, await_ring=await_ring)
        self.counters.tilts += 1
        if await_ring:
            self._stop_ring()
        else:
            self._tilt_go(tilt)

    def _tilt_go(self, tilt: Tilt) -> None:
        if not self.tilt.is_current(tilt) or self.life.fault is not None:
            return
        tilt.phase = TiltPhase.UNDER_WAY
        dest = tilt.destination
        if dest != self.el.position:
            self._submit_motion(self.el, Motion(m.MoveOrder(dest), MotionPurpose.TILT, tilt=tilt))
        else:
            tilt.moved = True
        self._submit_command(
            BirisCommand(int(BiCommand.BI_LOAD_LUT), str(dest), CommandPurpose.LOAD_LUT, tilt=tilt)
        )

    def _tilt_lut_loaded(self, tilt: Tilt | None, status: int) -> None:
        if tilt is None or not self.tilt.is_current(tilt):
            return
        if status != BiStatus.OK:
            self._fault(
                "protocol",
                f"BI_LOAD_LUT {tilt.destination} failed: STATUS {status} ({status_name(status)})"
                " -- BIRIS has no calibration for an elevation the init record allows",
            )
            return
        self.tilt.lut = tilt.destination
        self.counters.lut_loads += 1
        tilt.lut = True
        self._tilt_part(tilt)

    def _tilt_part(self, tilt: Tilt, *, moved: bool = False) -> None:
        """One half of the tilt is done; when both are, what waited for it goes on."""
        if not self.tilt.is_current(tilt):
            return
        if moved:
            tilt.moved = True
        if not tilt.over:
            return
        pending = self.tilt.finish(tilt)
        if pending is not None:
            self._start_tilt(pending)
            return
        if self.ring.mode:
            self._start_ring()
        self._run_deferred()
        self._after_motion_settles()
        self._check_idle_waiters()

    # ============================================================================ the ring
    def _on_start_continuous(self, env: Envelope, msg: p.StartContinuous) -> None:
        """START_CONTINUOUS (Appendix D): continuous acquisition from now on.

        With no scan running (nor waiting, nor continuous scanning on) the mode switches and
        BI_START_CONTINUOUS is issued at once: Appendix D's START_CONTINUOUS "would produce a
        continuous sequence of acquisitions", so the start-up is paid now, not by the next
        scan, and ``wait_idle`` returns once the ring is live. During a tilt the ring starts
        when the tilt is over, as after any tilt. While scanning, the switch is pending, as
        BIRIS_HOME is (status's ``acquisition_pending``), and takes effect once scanning has
        ended (:meth:`_take_pending_acquisition`): every sweep is acquired in one mode, and
        continuous scanning keeps its mode until BIRIS_STOP_SCAN_RQST ends it. Idempotent.
        Refused like every request in a fault (the HardwareFault) or while initialising
        (RequestError), and then nothing changes.
        """
        self._usable_conn(msg.conn)
        if self.ring.ask_start(scanning=self.scans.active()):
            self._start_ring()
        env.reply(None)
        self._check_idle_waiters()

    def _on_stop_continuous(self, env: Envelope, msg: p.StopContinuous) -> None:
        """STOP_CONTINUOUS (Appendix D): "cease all acquisitions immediately".

        Single acquisition from now on, a pending START_CONTINUOUS withdrawn, and
        BI_STOP_CONTINUOUS issued now if the ring runs -- even under a sweep. That sweep's data
        end with the last acquisition BIRIS completed before the stop; the head finishes its
        move (the message stops acquisitions, not motion: BIRIS_STOP_SCAN_RQST does that) and
        the sweep is delivered then, with what it holds (:meth:`_ring_stopped`), marked
        ``partial`` unless its acquisition at the destination was in already, so no
        acquisition is lost and the accounts add up. Continuous scanning goes on, its next
        sweeps in single acquisition (a BI_ACQUIRE each). A scan waiting for the ring to go
        live starts in single acquisition once the ring has stopped. Idempotent; in single
        acquisition it changes nothing (a BI_ACQUIRE sequence is not stopped: BIRIS has no
        command for it). Refused like every request in a fault or while initialising.
        """
        self._usable_conn(msg.conn)
        if self.ring.ask_stop():
            scan = self.scans.scan
            if scan is not None and scan.ring and not scan.cmd_done and not scan.at_end:
                # its data end at the stop, short of the destination: marked now, since the
                # reader may end the sweep (SWEEP_DATA_DONE) before the stop's completion
                scan.mark_partial("STOP_CONTINUOUS stopped its acquisitions under it")
            self._stop_ring()
        env.reply(None)
        self._check_idle_waiters()

    def _take_pending_acquisition(self) -> None:
        """Scanning has ended: a START_CONTINUOUS that waited for it takes effect now."""
        if self.scans.active() or self.life.fault is not None or self.life.initialising:
            return
        if self.ring.take_pending():
            self._start_ring()

    def _start_ring(self) -> None:
        """BI_START_CONTINUOUS, unless BIRIS already acquires continuously (or may not now)."""
        if self.life.fault is not None or self.life.initialising or self.tilt.current is not None:
            return
        if self.ring.start():
            self._submit_command(
                BirisCommand(
                    int(BiCommand.BI_START_CONTINUOUS), "", CommandPurpose.START_CONTINUOUS
                )
            )

    def _ring_started(self, status: int, param: bytes) -> None:
        if status != BiStatus.OK or ring_length(param) <= 0:
            self._fault(
                "protocol",
                f"BI_START_CONTINUOUS failed: STATUS {status} ({status_name(status)}), "
                f"answer {param.split(bytes(1))[0]!r}",
            )

    def _on_continuous_live(self, env: Envelope, msg: m.ContinuousLive) -> None:
        env.reply(None)
        if not self.ring.went_live():
            return  # stopped again before its first acquisition
        self.counters.continuous_starts += 1
        self._rearm_timeout()
        self._run_deferred()
        self._check_idle_waiters()

    def _stop_ring(self) -> None:
        """BI_STOP_CONTINUOUS (unless one is on its way already)."""
        if self.ring.stop():
            code = int(BiCommand.BI_STOP_CONTINUOUS)
            self._submit_command(BirisCommand(code, "", CommandPurpose.STOP_CONTINUOUS))

    def _ring_stopped(self) -> None:
        """BI_STOP_CONTINUOUS completed: what waited for it goes on.

        A sweep still acquiring (STOP_CONTINUOUS under it) has all its data: the reader has
        handed over every frame BIRIS completed before it stopped, ahead of this completion,
        and no SWEEP_DATA_DONE will come; so its data end here, and it completes when the
        head arrives (marked ``partial`` by :meth:`_on_stop_continuous`). Then a tilt that
        waited for the stop goes on, the ring starts again if START_CONTINUOUS came meanwhile,
        and a scan that waited starts.
        """
        if not self.ring.stopping:
            return  # a stop a reset has forgotten
        self.ring.stopped()
        scan = self.scans.scan
        if scan is not None and scan.ring and not scan.cmd_done:
            self._scan_part_done(scan, cmd_status=int(BiStatus.OK))
        tilt = self.tilt.current
        if tilt is not None and tilt.phase is TiltPhase.AWAIT_RING_STOP:
            self._tilt_go(tilt)
        if self.ring.mode:
            self._start_ring()
        self._run_deferred()
        self._check_idle_waiters()

    # ============================================================================ faults and reset
    def _task_fault(self, env: Envelope, kind: FaultKind, text: str) -> None:
        """A notifier's report of a fault: released at once, then the fault state."""
        env.reply(None)
        self._fault(kind, text)

    def _fault(self, kind: FaultKind, text: str) -> None:
        """The fault state: everything under way ends; every caller waiting is told.

        A fault met while the hardware ran behind its clock (a simulator the host cannot keep
        up with) says so: its hardware-time bounds were then judged on a late host.
        """
        lag = self._lag() if self._lag is not None else 0.0
        if lag >= LAG_NOTE_S and kind in ("timeout", "motor_stall"):
            text += (
                f" (the simulator was running {lag * 1000.0:.0f} ms behind its clock: this host"
                " cannot keep up with its time scale, which alone can cause this)"
            )
        fault = self.life.enter_fault(kind, text)
        if fault is None:
            return
        self.counters.faults += 1
        self.commands.stop_timer()
        for axis in (self.az, self.el):
            for job in axis.abandon():  # the initialiser may wait on one
                self._motion_failed(job, fault)
        self._clear_activity()
        for cmd in self.commands.discard():
            self._command_failed(cmd, fault)
        current = self.commands.current
        if current is not None:
            self._command_failed(current, fault)
        self.clients.fail_waiting(fault)

    def _clear_activity(self) -> None:
        """Forget every scan, tilt and motion under way or waiting (reset, fault)."""
        self._cancel_schedule()
        self.scans.forget()
        self.requests.forget()
        self.tilt.forget()
        for axis in (self.az, self.el):
            axis.abandon()

    def _on_reset(self, env: Envelope, msg: p.ResetRequest) -> None:
        if msg.conn:
            self._conn(msg.conn)
        self.life.begin_reset(env)
        if self._task_generation is not None:
            self._reset_generation = self._task_generation()
        self.encoders.moved()  # the initialiser homes both axes
        self._clear_activity()
        # the ring is forgotten (the initialiser stops BIRIS) and the acquisition mode is the init
        # record's again, a pending START_CONTINUOUS dropped: like the motor parameters, what a
        # client switched at run time is undone by a reset
        self.ring.reset()
        # Abort what runs: the command in flight is given up (its completion will be stale; the
        # initialiser waits, bounded, until BIRIS has finished it before its first command), and
        # no timer stays armed for it -- nothing is owed to this server any more.
        for cmd in self.commands.abandon():
            if cmd.purpose is CommandPurpose.INIT and cmd.requester is not None:
                fail_quietly(cmd.requester, RequestError("a reset has begun"))
        self.commands.stop_timer()
        self._start_initialiser()

    def _on_init_sync(self, env: Envelope, msg: m.InitSync) -> None:
        if self.commands.worker_parked:
            env.reply(None)
        else:  # it is writing what it was handed before the reset: answered when it is back
            self._init_syncs.append(env)

    def _on_init_command(self, env: Envelope, msg: m.InitCommand) -> None:
        if self._init_overtaken(env):
            return
        self._submit_command(BirisCommand(msg.code, msg.param, CommandPurpose.INIT, requester=env))

    def _on_init_move(self, env: Envelope, msg: m.InitMove) -> None:
        if self._init_overtaken(env):
            return
        axis = self._axis(msg.axis)
        # The watchdog's bound must be that of the move the chip really makes. The chip runs the
        # init record's parameters since the initialiser's configure_axes (not what a client
        # loaded before the reset), and the move starts where the initialiser says: after its
        # chip reset or a re-zeroing, the count is not where the last move (perhaps a scan the
        # reset abandoned) was to end.
        axis.motor = self.record.motor if axis is self.az else self.record.tilt_motor
        order = m.MoveOrder(msg.destination)
        job = Motion(order, MotionPurpose.INIT, requester=env, origin=msg.start)
        self._submit_motion(axis, job)

    def _init_overtaken(self, env: Envelope) -> bool:
        """A fault met while initialising (a task failing, a bus error) ends the
        initialisation: what the initialiser asks for next fails at once with that fault, as
        what it was waiting on did, instead of waiting in a queue the fault has stopped until the
        initialiser's own bound blames a ``timeout``."""
        if self.life.fault is None:
            return False
        fail_quietly(env, self.life.fault)
        return True

    def _on_init_done(self, env: Envelope, msg: m.InitDone) -> None:
        env.reply(None)
        waiters = self.life.initialised()
        # commands the initialiser gave up on must not be issued later
        self.commands.discard(keep=lambda c: c.purpose is not CommandPurpose.INIT)
        if msg.error is not None:
            fault = _init_fault(msg.error)
            self._fault(fault.kind, fault.message)
            for w in waiters:
                fail_quietly(w, fault)
            return
        result = msg.addressing
        assert isinstance(result, InitResult)
        self.scans.samples = result.samples
        self.scans.timing.period_s = result.period_s
        mismatch = data_rate_mismatch(self.record.data_rate_ms, result.period_s)
        if mismatch is not None:  # harmless (the real period is used): said, not warned
            log.info("%s", mismatch)
        self.az.position = 0
        self.el.position = 0
        self.encoders.moved()
        # the chips now run the init record's parameters: so does the server (a reset undoes
        # BIRIS_MOTOR_PARAMS; a client that wants its own set sends it again)
        self.az.motor = self.record.motor
        self.el.motor = self.record.tilt_motor
        self.tilt.homed()  # the initialiser stood the tilt level and loaded its table
        for w in waiters:
            w.reply(result)
        self._start_ring()
        self._check_idle_waiters()


def _init_fault(exc: BaseException) -> HardwareFault:
    """What an initialisation that failed with ``exc`` is, as a fault: a bus error means the
    target is gone (``bus``), an exception nobody expected a bug (``internal``), anything else
    BIRIS or the board answering what they should not (``protocol``)."""
    if isinstance(exc, HardwareFault):
        return exc
    if isinstance(exc, BusError):
        return HardwareFault("bus", f"initialisation failed: {exc}")
    if isinstance(exc, BirisError):
        return HardwareFault("protocol", f"initialisation failed: {exc}")
    return HardwareFault("internal", f"initialisation failed: {exc!r}")


def _fault_kind(kind: str | None) -> FaultKind:
    """A task's reported kind as a FaultKind (anything unknown is the server's own bug)."""
    known: tuple[FaultKind, ...] = ("timeout", "bus", "parity", "motor_stall", "protocol")
    for k in known:
        if kind == k:
            return k
    return "internal"
