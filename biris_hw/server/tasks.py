"""The BIRIS server's internal tasks (report Fig. 4), one function or class each.

Which of them the server starts, on which thread, what each waits on and what it sends, is the
task table, :mod:`biris_hw.server.task_table`; this module is their bodies.

Notifiers block on an interrupt and *send* to the administrator: ``biris_cmd_notifier``,
``biris_az_notifier``, ``el_scan_notifier``, ``biris_parity_err``, ``biris_bus_err``; and
:class:`BirisDataNotifier`, which the level-2 interrupt service routine runs for each
BIRIS_DATA_DEV and which therefore *posts one-way* (it must never wait on the administrator).
Workers report ready and block until the administrator *replies* with an order:
``biris_cmd_transfer`` (writes the next BIRIS command), ``az_scan_start`` and ``el_scan_start``
(start the next pan or tilt trapezoid), ``encoder_reader`` (reads both encoders for a status).
``biris_timeout`` and the motor watchdogs are timers (:class:`DeadlineTimer`). Every task ends
when its line is closed or the administrator's mailbox stops. ``el_scan_notifier`` and
``el_scan_start`` are the report's "future tasks" for a tilt axis, "similar to [the azimuth
ones] except that they apply to the elevation scan".

What a notifier has drained from BIRIS memory (NEW_POINT, CONTINUOUS_LIVE, SWEEP_DATA_DONE) is
always posted one-way, under the reader's lock: so the inbox holds it in the reader's order,
and no task ever waits for the administrator while holding that lock -- which the level-2
routine takes for every acquisition.

**Supervision.** The server runs every task under a :class:`Supervisor` (the task table's
``restart`` column). The bodies here therefore catch nothing they cannot carry on from. A
BusError (a register of a target that has gone) and any unexpected exception propagate to the
supervisor, which logs the failure, reports it one-way as TaskFailed (a HardwareFault's own
kind, ``bus`` for any other BusError, ``internal`` for the rest), and restarts the body at the
next reset. A body ends only once the administrator's mailbox has
stopped or its line has been closed, and both happen only when the server closes. What the
administrator *answers* with an error is the administrator's own failure: a notifier or timer
logs the refusal (:func:`_tell`) and carries on with its next interrupt, while a worker, which
would only report ready again at once, waits for the reset.

Continuous mode (Appendix D) touches three tasks: ``biris_cmd_transfer`` raises the
continuous-mode flag of the level-2 demultiplexer and primes the reader before it writes
BI_START_CONTINUOUS; ``biris_cmd_notifier`` lowers the flag once BI_STOP_CONTINUOUS has completed;
``az_scan_start`` re-enables the data interrupts (opens the sweep) once the motor is moving, and
``biris_az_notifier`` marks the sweep's end when the motor has come to rest.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable

from biris_hw.axes.base import MotionAxis
from biris_hw.devices import BirisLink
from biris_hw.errors import BirisError, BusError, FaultKind, HardwareFault, LineClosed
from biris_hw.ipc import Mailbox, TaskStopped
from biris_hw.irq.base import InterruptLine
from biris_hw.server.acquisition import AcquisitionReader, Drained, ring_length
from biris_hw.server.messages import (
    AzReady,
    AzScanDone,
    BirisBusErr,
    BirisCmdComplete,
    BirisParityErr,
    BirisRechecked,
    CmdTransferRdy,
    ContinuousLive,
    ElReady,
    ElScanDone,
    EncoderReading,
    MoveOrder,
    NewPoint,
    ParamsOrder,
    SequenceStarted,
    SweepDataDone,
    TaskFailed,
    TransferOrder,
)
from biris_hw.server.task_table import Restart
from biris_hw.timebase import HwThread, ScaledTime, StopEvent, TimeBase
from regs.biexec import BiCommand, BiStatus

__all__ = [
    "BirisDataNotifier",
    "BirisRecheck",
    "CommandLedger",
    "DeadlineTimer",
    "MoveLedger",
    "Supervisor",
    "az_scan_start",
    "biris_az_notifier",
    "biris_bus_err",
    "biris_cmd_notifier",
    "biris_cmd_transfer",
    "biris_parity_err",
    "el_scan_notifier",
    "el_scan_start",
    "encoder_reader",
    "failure_kind",
]

log = logging.getLogger(__name__)


def _await(line: InterruptLine) -> int | None:
    """Harmony's _Await_interrupt: the count, or None once the line is closed."""
    try:
        return line.wait()
    except LineClosed:
        return None


def _post_quietly(admin: Mailbox, message: object) -> None:
    """Post ``message`` one-way; a mailbox that has stopped has nobody left to tell."""
    try:
        admin.post_oneway(message)
    except Exception:  # TaskStopped, or the reason the mailbox was closed with
        log.debug("not posted (the administrator has stopped): %r", message)


def _tell(admin: Mailbox, message: object) -> object:
    """A notifier's or timer's report: send it and return the reply.

    The administrator answers a report with an error only when its case went wrong, and it has
    then entered a fault itself (a case that fails unexpectedly is an ``internal`` fault, see
    :meth:`Administrator.handle`). So the notifier does not fail with it: it logs the refusal
    and carries on with its next interrupt, which needs nothing from the administrator. It
    reports nothing more: a second report would reach the administrator late -- after a reset
    the client may already have asked for -- and fault the fresh initialisation. TaskStopped
    (the server is closing) is raised on.
    """
    try:
        return admin.send(message)
    except TaskStopped:
        raise
    except BirisError as exc:
        name = threading.current_thread().name
        what = type(message).__name__
        log.error("%s: the administrator refused %s: %s", name, what, exc)
        return None


# --- supervision ---------------------------------------------------------------------------------


def failure_kind(exc: BaseException) -> FaultKind:
    """The fault kind a task's failure with ``exc`` is reported as: a HardwareFault's own
    (a CiA 402 drive's EMCY that the level-3 routine raises is ``motor_stall``; a
    :class:`~biris_hw.axes.cia402.DriveBusError` is ``bus``), ``bus`` for any other BusError
    (a register or interrupt line of a target that has gone), ``internal`` for anything else."""
    if isinstance(exc, HardwareFault):
        return exc.kind
    if isinstance(exc, BusError):
        return "bus"
    return "internal"


class Supervisor:
    """Runs the server's tasks so that an exception never kills one for good (issue 11).

    Each thread the server starts from the task table runs :meth:`run` with its task's body. A
    body that raises anything but TaskStopped has failed, and so has a body that returns while
    the server runs, since every body runs until the server stops. The failure is logged (a bug
    with its traceback) and reported to the administrator one-way as ``TaskFailed(task, kind,
    text)`` (:meth:`failed`): a HardwareFault keeps its own kind (the level-3 routine raising a
    CiA 402 drive's EMCY is ``motor_stall``, its lost heartbeat ``bus``), any other BusError is
    ``bus`` (a register or interrupt line of a target that has gone), anything else ``internal``
    (a bug). The administrator turns it into a fault of that kind and tells every caller --
    unless the report carries a reset count (``TaskFailed.generation``) from before the reset
    under way or already done, which restarts the task: a failure met in the outage that reset
    recovers from. The thread stays alive under its table name and, for ``Restart.ON_RESET``,
    waits until :meth:`reset` (the initialiser of the next reset, once it has re-linked), then
    runs its body again. A task that keeps failing therefore reports once per reset and never
    spins. The administrator's own thread is ``Restart.AT_ONCE``: it carries out resets, so it
    is restarted at once. Its failure is posted to its own inbox and handled as soon as it runs
    again. Should it keep failing, the restarts back off up to :data:`ADMIN_BACKOFF_MAX_S`.

    A task that runs in another task's thread (biris_data_notifier in level2_isr) is a *guest*:
    :meth:`guest` attaches it, it reports its own failure through :meth:`failed`, and its host
    detaches it. :meth:`reset` attaches it again.

    Only :meth:`reset` and :meth:`close` touch a thread other than the caller's, and both only
    notify: the administrator, which calls :meth:`reset`, never waits on a task.
    """

    ADMIN_BACKOFF_MAX_S = 1.0
    """Longest pause between two restarts of a task restarted at once, when it keeps failing."""

    def __init__(self, admin: Mailbox, timebase: TimeBase | None = None) -> None:
        self._admin = admin
        self._timebase = timebase if timebase is not None else ScaledTime()
        self._cond = self._timebase.Condition()
        self._resets = 0
        self._closed = False
        self._down: dict[str, int] = {}
        """Tasks waiting for a reset after a failure, with the reset count at that failure."""
        self._guests: dict[str, Callable[[], None]] = {}
        self.failures: dict[str, int] = {}
        """How many times each task has failed, by name (for status and tests)."""

    # -- what the server and the tests use --------------------------------------------------------
    @property
    def resets(self) -> int:
        """How many resets have restarted the tasks."""
        return self._resets

    @property
    def down(self) -> frozenset[str]:
        """The tasks that have failed and wait for the next reset."""
        with self._cond:
            return frozenset(self._down)

    def failure_counts(self) -> dict[str, int]:
        """:attr:`failures` as of now, copied under the lock (for ``status()``, from any
        thread)."""
        with self._cond:
            return dict(self.failures)

    def wait_down(self, name: str, timeout: float | None = None) -> bool:
        """Block until task ``name`` is waiting for a reset (True) or ``timeout`` passes; for
        tests, which must not sleep to find that out."""
        timeout_hw = None if timeout is None else self._timebase.timeout_hw(timeout)
        with self._cond:
            return self._cond.wait_for(
                lambda: name in self._down, timeout_hw, what=f"task {name!r} down"
            )

    def reset(self) -> None:
        """The server's reset: every task waiting after a failure runs its body again.

        Called by the initialiser once it has re-linked what was lost (``restart_tasks``), before
        its first move or command, so that those find live workers and notifiers; a task revived
        earlier would fail again at once on a link still gone. Never blocks: a revived worker
        reports ready on its own, and until then what the initialiser asks for waits in the
        administrator's queues, as it always does.
        """
        with self._cond:
            self._resets += 1
            guests = [name for name in self._guests if name in self._down]
            for name in guests:
                del self._down[name]
            attach = [self._guests[name] for name in guests]
            self._cond.notify_all()
        for put_back in attach:
            put_back()

    def close(self) -> None:
        """The server is closing: every waiting task ends, and no failure is reported any
        more (a task that fails because its hardware is being shut down has not failed)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    # -- the tasks' side --------------------------------------------------------------------------
    def run(self, name: str, body: Callable[[], None], restart: Restart = Restart.ON_RESET) -> None:
        """The thread of task ``name``: ``body``, supervised, until the server closes."""
        pause = 0.0
        last_failure = float("-inf")
        while not self._closed:
            try:
                body()
            except TaskStopped:
                return
            except Exception as exc:
                if self.closed:
                    return
                self.failed(name, exc)
            else:
                if self.closed:
                    return
                self.failed(name, RuntimeError(f"{name} ended while the server runs"))
            if restart is Restart.NEVER:
                return
            if restart is Restart.AT_ONCE:
                # the back-off is the caller's seconds, on the time base (in virtual time a
                # task failing over and over must still let time pass between restarts)
                tb = self._timebase
                now = tb.now()
                repeated = now - last_failure < tb.timeout_hw(self.ADMIN_BACKOFF_MAX_S)
                pause = min(self.ADMIN_BACKOFF_MAX_S, max(0.001, 2 * pause)) if repeated else 0.0
                last_failure = now
                with self._cond:
                    self._down.pop(name, None)
                    if self._cond.wait_for(
                        lambda: self._closed, tb.timeout_hw(pause), what=f"{name} back-off"
                    ):
                        return
            elif not self._await_reset(name):
                return

    def failed(self, name: str, exc: BaseException) -> None:
        """Task ``name`` failed with ``exc``: log it, report it one-way as TaskFailed of
        :func:`failure_kind`, and mark the task as waiting for the next reset. A bug and a
        BusError are logged with their traceback (where the code broke, where the target was
        found gone); any other HardwareFault, which the hardware reported, with its message
        only, which is also the report's text (its kind is the report's kind)."""
        kind = failure_kind(exc)
        with self._cond:
            if self._closed:
                return
            generation = self._down[name] = self._resets
            self.failures[name] = self.failures.get(name, 0) + 1
            self._cond.notify_all()
        if isinstance(exc, BusError):
            log.error(
                "%s: bus error, the target is gone or unreachable (%s); "
                "it waits for the next reset",
                name,
                exc,
                exc_info=exc,
            )
        elif isinstance(exc, HardwareFault):
            log.error("%s: hardware fault (%s); it waits for the next reset", name, exc)
        else:
            log.error("%s failed; it waits for the next reset", name, exc_info=exc)
        # a hardware fault's message already says what broke; its kind goes in the report
        text = exc.message if isinstance(exc, HardwareFault) else f"{type(exc).__name__}: {exc}"
        _post_quietly(self._admin, TaskFailed(name, kind, text, generation))

    def guest(self, name: str, attach: Callable[[], None]) -> None:
        """Attach guest task ``name`` now, and again at every reset after it has failed."""
        with self._cond:
            self._guests[name] = attach
        attach()

    def _await_reset(self, name: str) -> bool:
        """Wait, after a failure, for the next reset (True) or the server's close (False)."""
        with self._cond:
            failed_at = self._down.get(name, self._resets)
            self._cond.wait_for(
                lambda: self._closed or self._resets != failed_at, what=f"reset ({name} down)"
            )
            self._down.pop(name, None)
            self._cond.notify_all()
            return not self._closed


# --- notifiers -----------------------------------------------------------------------------------


class CommandLedger:
    """Which command BIRIS is executing, shared by biris_cmd_transfer and biris_cmd_notifier.

    Under Harmony the notifier was REPLY-blocked whenever a command was issued, so an interrupt
    could never be mistaken for the completion of a command written after it. Threads give no
    such guarantee: a spurious or late BIRIS_CMD can wake the notifier, which reads COMMAND = 0
    an instant before the next command is written. The ledger closes that gap: the worker records
    the command and writes COMMAND under the lock, and the notifier reads COMMAND under the same
    lock, so a completion always names the command it completes (or is recognised as stale).
    """

    def __init__(self, timebase: TimeBase | None = None) -> None:
        # on the time base: COMMAND is read under it, and a read may be slowed (TimeBase.Lock)
        self.lock = (timebase if timebase is not None else ScaledTime()).Lock()
        self.outstanding: TransferOrder | None = None


class MoveLedger:
    """Which move an axis is making, shared by its worker and its notifier.

    The administrator numbers every move it orders (``MoveOrder.token``) and the notifier names
    the move whose end it reports, so that the end of a move a reset abandoned is never taken
    for the end of the next one. The worker records the token just before it starts the
    trapezoid. The notifier reads it as soon as the end-of-scan interrupt wakes it, before it
    waits for the head to settle, so a move ordered meanwhile cannot lend the ended one its
    name. The token is kept, not cleared, after it has been read: a spurious or repeated end
    then names a move that has already ended, and the administrator ignores it.
    """

    def __init__(self, clock: Callable[[], float] | None = None) -> None:
        self.token: int | None = None
        """The token of the move last started; None before the first (plain stores: atomic)."""
        self._clock = clock
        self.started: tuple[int, float] | None = None
        """(token, hardware time) of the move last started, recorded just before its trapezoid
        was (one tuple: a single atomic store). A watchdog that runs out judges the move from
        when it started, not from when it was ordered: a worker the host ran late has not
        started a move that could have ended."""

    noticed: int | None = None
    """The token of the move whose end the notifier last woke for (it then verifies the
    arrival, however long settling takes): a watchdog asking the controller finds that end
    acknowledged already, and must not take the move for one that never ended."""

    def note_start(self, token: int) -> None:
        """The move ``token`` starts now."""
        self.token = token
        if self._clock is not None:
            self.started = (token, self._clock())


def _post_drained(admin: Mailbox, drained: Drained) -> None:
    """What a drain produced, as one-way messages, in order: NEW_POINT, then what it completed.

    Called under the reader's lock (see the module notes); raises TaskStopped once the
    administrator has stopped.
    """
    if drained.started:  # first: the motor waits for it
        admin.post_oneway(SequenceStarted(drained.started, drained.started_at))
    if drained.acquisitions or drained.lost or drained.idle:
        admin.post_oneway(
            NewPoint(drained.acquisitions, drained.lost, drained.idle, drained.untrusted)
        )
    if drained.live:
        admin.post_oneway(ContinuousLive())
    if drained.sweep_done:
        admin.post_oneway(SweepDataDone(drained.sweep_done))


def biris_cmd_notifier(
    line: InterruptLine,
    admin: Mailbox,
    link: BirisLink,
    reader: AcquisitionReader,
    ledger: CommandLedger,
    set_continuous: Callable[[bool], None],
) -> None:
    """BIRIS_CMD -> BIRIS_CMD_COMPLETE (after handing over any acquisitions not yet read).

    The administrator holds the reply until it is about to issue the next command, so this task
    is back on the interrupt before that command can complete. A completed BI_START_CONTINUOUS
    tells the reader the ring's length; a completed BI_STOP_CONTINUOUS (or a refused start) ends
    continuous mode in the reader and lowers the demultiplexer's flag.

    A BusError reading BIEXEC_COM, or anything unexpected, propagates to the supervisor (module
    notes), which reports it: a BIRIS that can no longer be read is a ``bus`` fault, not a
    timeout some seconds later.
    """
    while _await(line) is not None:
        try:
            with ledger.lock:
                order = ledger.outstanding
                if order is None or link.command() != 0:
                    continue  # stale, spurious, or BIRIS still busy: not a completion
                ledger.outstanding = None
            status, param = link.status(), link.param_raw()
            if order.code == BiCommand.BI_START_CONTINUOUS and status == BiStatus.OK:
                reader.ring_started(ring_length(param))
            elif order.code in (BiCommand.BI_START_CONTINUOUS, BiCommand.BI_STOP_CONTINUOUS):
                reader.stop_ring()
                set_continuous(False)
            ran = order.code != BiCommand.BI_ACQUIRE or status == BiStatus.OK
            with reader.lock:  # a refused BI_ACQUIRE made nothing: its frames are old ones
                _post_drained(admin, reader.drain_sequence(final=True, ran=ran))
            _tell(admin, BirisCmdComplete(status, param, order.token))
        except TaskStopped:
            return


class BirisDataNotifier:
    """The report's _Biris_data_notifier, one step per BIRIS_DATA_DEV: drain, NEW_POINT.

    BIRIS_DATA_DEV -> NEW_POINT with every acquisition completed since the last one; in
    continuous mode also CONTINUOUS_LIVE (the start-up is over) and SWEEP_DATA_DONE (the sweep's
    last acquisition has been sent). The level-2 interrupt service routine runs it in place of
    raising the logical line (:meth:`biris_hw.server.isr.Level2Demux.attach_data_notifier`), so
    its messages are posted one-way: the routine never waits for the administrator, and BIRIS_CMD,
    BIT3_PERR and BIT3_BERR are demultiplexed as soon as the frames are read. Why it shares that
    thread rather than having its own is measured in the task table
    (:mod:`biris_hw.server.task_table`, row ``biris_data_notifier``).

    The administrator answers NEW_POINT at once and nobody waits for the answer; a refusal is
    logged by the mailbox (debug) and by the administrator.

    ``failed`` is how it reports its own failure: the server passes its supervisor's
    :meth:`Supervisor.failed` for this task. A frame that cannot be read (BusError: a ``bus``
    fault) or anything unexpected (``internal``) is reported there, and the notifier returns
    False, so the routine detaches it until the next reset attaches a new one. It does not stay
    attached, so it cannot fail again with every data interrupt of a target that has gone.
    Without ``failed`` the exception propagates to the routine, which logs it.
    """

    def __init__(
        self,
        admin: Mailbox,
        reader: AcquisitionReader,
        failed: Callable[[BaseException], None] | None = None,
    ) -> None:
        self._admin = admin
        self._reader = reader
        self._failed = failed

    def __call__(self, count: int = 1) -> bool:
        """One interrupt (``count`` coalesced); False once the administrator has stopped, or
        once this notifier has failed and reported so."""
        try:
            with self._reader.lock:
                _post_drained(self._admin, self._reader.drain())
        except TaskStopped:
            return False
        except Exception as exc:
            if self._failed is None:
                raise
            self._failed(exc)
            return False
        return True


class BirisRecheck:
    """The BIRIS timeout's question, answered in the level-2 routine's thread: has BIRIS
    progressed since the host last looked? (:meth:`~biris_hw.server.isr.Level2Demux.
    attach_recheck`.)

    It drains the reader as a data interrupt would (posting NEW_POINT for whatever BIRIS made
    meanwhile, which is life), looks at a continuous-acquisition ring that no sweep reads
    (:meth:`AcquisitionReader.watch_ring`: a ring that moves is life, one standing still is
    not), reads COMMAND for a completion not yet serviced, and posts BIRIS_RECHECKED after them
    (one-way, FIFO: the administrator sees the evidence first). Returns True when BIRIS has
    completed the outstanding command, so the routine wakes the command notifier. A BusError
    propagates: a BIRIS that cannot be read is a ``bus`` fault.
    """

    def __init__(
        self, admin: Mailbox, reader: AcquisitionReader, link: BirisLink, ledger: CommandLedger
    ) -> None:
        self._admin = admin
        self._reader = reader
        self._link = link
        self._ledger = ledger

    def __call__(self) -> bool:
        with self._reader.lock:
            drained = self._reader.drain()
            moving = self._reader.watch_ring()
            progressed = bool(
                moving
                or drained.acquisitions
                or drained.lost
                or drained.idle
                or drained.live
                or drained.sweep_done
                or drained.started
                or drained.finished
            )
            try:
                _post_drained(self._admin, drained)
            except TaskStopped:
                return False
        with self._ledger.lock:
            completed = self._ledger.outstanding is not None and self._link.command() == 0
        try:
            self._admin.post_oneway(BirisRechecked(progressed or completed))
        except TaskStopped:
            return False
        return completed


def _axis_notifier(
    line: InterruptLine,
    admin: Mailbox,
    axis: MotionAxis,
    stop: StopEvent,
    done: type[AzScanDone] | type[ElScanDone],
    reader: AcquisitionReader | None = None,
    moves: MoveLedger | None = None,
) -> None:
    """Shared body of the two motor notifiers: end of profile -> settled -> ``done``.

    The report's notifier says only that the move ended. This one also says where the axis
    came to rest and whether it settled in time, because the HCTL-1000 ends its profile
    whatever the shaft does (a locked shaft, a dead amplifier, a gain of 0). The administrator
    compares that position with the destination, so a head that never arrived is a fault, not a
    completed scan. The encoder is read after settling whether or not it settled: an axis still
    hunting is judged by where it stands. A BusError (the board cannot be read) propagates to
    the supervisor as a ``bus`` fault. It is never a done without a position.
    """
    while _await(line) is not None:
        try:
            token = moves.token if moves is not None else None  # before settling: see MoveLedger
            if moves is not None:
                moves.noticed = token
            settled = axis.wait_settled(stop)
            if stop.is_set():
                return  # the server is closing: nobody wants the report
            position = axis.actual_position()
            if reader is not None:
                with reader.lock:
                    _post_drained(admin, reader.end_sweep())
            _tell(admin, done(position=position, settled=settled, token=token))
        except TaskStopped:
            return


def biris_az_notifier(
    line: InterruptLine,
    admin: Mailbox,
    axis: MotionAxis,
    stop: StopEvent,
    reader: AcquisitionReader | None = None,
    moves: MoveLedger | None = None,
) -> None:
    """MOTOR_END_OF_SCAN -> AZ_SCAN_DONE, once the head has actually come to rest.

    The chip signals the end of the profile when it issues the last setpoint, not when the motor
    stops; the notifier polls the position briefly (:meth:`MotionAxis.wait_settled`, given up
    when ``stop`` is set) so that AZ_SCAN_DONE means what the report says: motion has
    terminated. AZ_SCAN_DONE carries where the head stands, whether it settled, and which move
    ended (``moves``, shared with az_scan_start). In continuous mode it first tells the reader
    that the sweep ends with the frame in exposure, and posts what is already complete.
    """
    _axis_notifier(line, admin, axis, stop, AzScanDone, reader, moves)


def el_scan_notifier(
    line: InterruptLine,
    admin: Mailbox,
    axis: MotionAxis,
    stop: StopEvent,
    moves: MoveLedger | None = None,
) -> None:
    """ELEVATION_END_OF_SCAN -> EL_SCAN_DONE, once the tilt has come to rest (the report's
    future _el_scan_notifier); with position, settling and move as AZ_SCAN_DONE."""
    _axis_notifier(line, admin, axis, stop, ElScanDone, None, moves)


def error_notifier(line: InterruptLine, admin: Mailbox, message: object) -> None:
    """Shared body of biris_parity_err and biris_bus_err: each interrupt is one report."""
    while _await(line) is not None:
        try:
            _tell(admin, message)
        except TaskStopped:
            return


def biris_parity_err(line: InterruptLine, admin: Mailbox) -> None:
    """BIT3_PERR -> BIRIS_PARITY_ERR."""
    error_notifier(line, admin, BirisParityErr())


def biris_bus_err(line: InterruptLine, admin: Mailbox) -> None:
    """BIT3_BERR -> BIRIS_BUS_ERR."""
    error_notifier(line, admin, BirisBusErr())


# --- workers -------------------------------------------------------------------------------------


def biris_cmd_transfer(
    admin: Mailbox,
    link: BirisLink,
    reader: AcquisitionReader,
    ledger: CommandLedger,
    set_continuous: Callable[[bool], None],
) -> None:
    """CMD_TRANSFER_RDY, then write whatever command the reply carries; forever.

    Before BI_START_CONTINUOUS the continuous-mode flag goes up, so that the demultiplexer
    classifies the first data interrupt right. Before BI_STOP_CONTINUOUS the reader notes the
    time: BIRIS stops its ring no sooner, which bounds the frames it made (a late completion
    books no lap it did not make, nor drops one it did).

    A command that cannot be written (BusError: the target is gone) propagates to the
    supervisor, which reports a ``bus`` fault. It used to be only logged, and the command then
    never completed. So does a READY the administrator refuses, since re-sending it at once
    could only spin. The ledger forgets a command whose write failed, so no later interrupt is
    taken for its completion.
    """
    ready = CmdTransferRdy()
    while True:
        try:
            order = admin.send(ready)
        except TaskStopped:
            return
        if not isinstance(order, TransferOrder):
            continue
        if order.code == BiCommand.BI_ACQUIRE:
            reader.begin(order.seq_id, order.n_acquisitions)
        elif order.code == BiCommand.BI_START_CONTINUOUS:
            set_continuous(True)
            reader.prime_ring()
        elif order.code == BiCommand.BI_STOP_CONTINUOUS:
            reader.stop_written()  # the soonest BIRIS can stop its ring
        with ledger.lock:
            ledger.outstanding = order
            try:
                link.issue(order.code, order.param)
            except BaseException:
                ledger.outstanding = None
                raise
        if order.code == BiCommand.BI_ACQUIRE:
            written = reader.written()
            if order.schedule is not None:  # the scan's trapezoid starts a start-up from now
                order.schedule.written(written)


def _axis_worker(
    admin: Mailbox,
    axis: MotionAxis,
    make_ready: Callable[[str | None, str | None], object],
    reader: AcquisitionReader | None = None,
    moves: MoveLedger | None = None,
) -> None:
    """Shared body of the two motor workers: report ready, carry out the reply; forever.

    An order the chip refuses (a profile still running) goes back in the next READY, the
    report's way. A BusError (the board cannot be reached) and anything unexpected propagate to
    the supervisor instead, as does a READY the administrator refuses, which re-sent at once
    could only spin.
    """
    ready = make_ready(None, None)
    while True:
        try:
            order = admin.send(ready)
        except TaskStopped:
            return
        try:
            if isinstance(order, MoveOrder):
                if order.schedule is not None:
                    axis.prepare_trapezoid(order.destination)  # the journal's write, ahead
                    if not order.schedule.wait_start():
                        # abandoned (nothing starts, nothing to say), or its BI_ACQUIRE never
                        # written: said, so that the move is not waited for for ever
                        unwritten = (
                            None
                            if order.schedule.cancelled
                            else (
                                "the scan's BI_ACQUIRE was not written in time: its motor was not "
                                "started"
                            )
                        )
                        ready = make_ready(unwritten, "timeout" if unwritten else None)
                        continue
                if order.sweep and reader is not None:
                    # just before the motor starts, so that a worker the machine runs late
                    # cannot cost the sweep its beginning; what is read before the head
                    # moves is at the start azimuth, and the administrator drops it (or, in
                    # a sweep that turns straight round, keeps it as the turn-around's)
                    reader.open_sweep(order.sweep, follows=order.follows)
                _start_move(axis, order, moves)
            elif isinstance(order, ParamsOrder):
                axis.configure(order.params)
            ready = make_ready(None, None)
        except BusError:
            raise
        except BirisError as exc:
            kind = exc.kind if isinstance(exc, HardwareFault) else "protocol"
            ready = make_ready(str(exc), kind)


def _start_move(axis: MotionAxis, order: MoveOrder, moves: MoveLedger | None) -> None:
    """Start ``order``'s trapezoid, its token recorded first (the end may come at once); a
    move that did not start gives the ledger its previous token back."""
    if moves is None:
        axis.start_trapezoid(order.destination)
        return
    previous = moves.token
    moves.note_start(order.token)
    try:
        axis.start_trapezoid(order.destination)
    except BaseException:
        moves.token = previous
        raise


def az_scan_start(
    admin: Mailbox,
    axis: MotionAxis,
    reader: AcquisitionReader | None = None,
    moves: MoveLedger | None = None,
) -> None:
    """AZ_READY, then start the motion the reply carries; forever.

    A continuous-mode sweep's order also opens the sweep as the motor starts: data interrupts
    back on, "after the next scan is started" (Appendix D) -- here an instant before, so that
    the head's first move is never missed.
    """
    _axis_worker(admin, axis, lambda error, kind: AzReady(error, kind), reader, moves)


def el_scan_start(admin: Mailbox, axis: MotionAxis, moves: MoveLedger | None = None) -> None:
    """EL_READY, then start the tilt the reply carries; forever (the report's future
    _el_scan_start)."""
    _axis_worker(admin, axis, lambda error, kind: ElReady(error, kind), None, moves)


def encoder_reader(admin: Mailbox, azimuth: MotionAxis, elevation: MotionAxis) -> None:
    """ENCODER_READING, then read both encoders when the reply orders it; forever.

    Beyond the report: ``status()`` says where the head is now (``azimuth_live``,
    ``elevation_live``), and the administrator never touches a register, so a worker reads the
    encoders for it, when a status asks for a reading fresher than the one it holds (at a
    bounded rate: :mod:`biris_hw.server.encoders`). An axis that cannot be read is reported as
    None and the worker carries on: the fault, if there is one, is reported by the task whose
    work needs that axis, and a status must still be answered.
    """
    reading = EncoderReading(read=False)
    while True:
        try:
            admin.send(reading)
        except TaskStopped:
            return
        reading = EncoderReading(_position(azimuth), _position(elevation))


def _position(axis: MotionAxis) -> int | None:
    """Where ``axis`` is now by its encoder; None when it cannot be read."""
    try:
        return axis.actual_position()
    except BirisError:
        return None


# --- timers --------------------------------------------------------------------------------------


class DeadlineTimer:
    """A task that sends ``make(generation)`` when an armed deadline passes (hardware time).

    ``_Biris_timeout`` in the report is created per command and destroyed on completion; arming
    and disarming one long-lived task is the same contract without thread churn. Arming or
    disarming never blocks the administrator for longer than a lock hand-over.

    The administrator re-arms the BIRIS timeout on every acquisition, so the task is woken only
    when it must act sooner than it would anyway: for a deadline earlier than the one it sleeps
    towards (or when it sleeps without one). A later deadline, or a disarm, is found when the
    earlier wake comes, and the task goes back to sleep.
    """

    def __init__(
        self,
        name: str,
        admin: Mailbox,
        timebase: TimeBase,
        make: Callable[[int], object],
    ) -> None:
        self.name = name
        self._admin = admin
        self._timebase = timebase
        self._clock = timebase.now
        self._make = make
        self._cond = timebase.Condition()
        self._deadline: float | None = None
        self._generation = 0
        self._stopped = False
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Run the task in a thread of its own, named :attr:`name`."""
        thread = self._timebase.Thread(target=self.run, name=self.name, daemon=True)
        with self._cond:
            if self._thread is not None:
                raise RuntimeError(f"{self.name} is already running")
            self._thread = thread
            thread.start()  # returns before run() takes the lock

    @property
    def generation(self) -> int:
        return self._generation

    def arm(self, hw_seconds: float, real_slack_s: float = 0.0) -> int:
        """(Re)start the countdown; returns the generation an expiry will carry.

        ``real_slack_s`` adds real seconds (scaled to hardware time): a watchdog on work that
        threads do (settling polls) must not fire because a busy machine ran them late, which
        on a fast simulator clock is many hardware seconds. None in virtual time, where work
        takes no time (:meth:`TimeBase.hw_from_real <biris_hw.timebase.TimeBase.hw_from_real>`).
        """
        with self._cond:
            self._generation += 1
            now = self._clock()
            deadline = now + hw_seconds + self._timebase.hw_from_real(real_slack_s)
            if hw_seconds > 0.0 and not deadline > now:
                # a delay too small to show in the sum (an ulp of the clock) is still a delay:
                # expiring at once would let a re-arm loop spin with time standing still
                deadline = math.nextafter(now, math.inf)
            sooner = self._deadline is None or deadline < self._deadline
            self._deadline = deadline
            if sooner:
                self._cond.notify()
            return self._generation

    def disarm(self) -> None:
        with self._cond:
            self._generation += 1
            self._deadline = None  # the task finds it so when its present wait ends

    def stop(self) -> None:
        """End the task and join its thread; an expiry not yet sent is dropped."""
        with self._cond:
            self._stopped = True
            self._cond.notify()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            if isinstance(thread, HwThread) and thread.timebase is self._timebase:
                self._timebase.join_thread(thread)
            else:
                thread.join()

    def run(self) -> None:
        """The task's body, for an owner that makes the thread itself (:meth:`start` runs it
        too); returns once :meth:`stop` is called or the administrator has stopped."""
        with self._cond:
            if self._thread is None:
                self._thread = threading.current_thread()
            while not self._stopped:
                if self._deadline is None:
                    self._cond.wait(what=f"{self.name} armed")
                    continue
                remaining = self._deadline - self._clock()
                if remaining > 0:
                    self._cond.wait(remaining, what=f"{self.name} deadline")
                    continue
                generation = self._generation
                self._deadline = None
                self._cond.release()
                try:
                    _tell(self._admin, self._make(generation))
                except TaskStopped:
                    return
                finally:
                    self._cond.acquire()
