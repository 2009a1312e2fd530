"""The BIRIS server's internal tasks (report Fig. 4), one function or class each.

Which of them the server starts, on which thread, what each waits on and what it sends, is the
task table, :mod:`biris_hw.server.task_table`; this module is their bodies.

Notifiers block on an interrupt and *send* to the administrator: ``biris_cmd_notifier``,
``biris_az_notifier``, ``el_scan_notifier``, ``biris_parity_err``, ``biris_bus_err``; and
:class:`BirisDataNotifier`, which the level-2 interrupt service routine runs for each
BIRIS_DATA_DEV and which therefore *posts one-way* (it must never wait on the administrator).
Workers report ready and block until the administrator *replies* with an order:
``biris_cmd_transfer`` (writes the next BIRIS command), ``az_scan_start`` and ``el_scan_start``
(start the next pan or tilt trapezoid). ``biris_timeout`` and the motor watchdogs are timers
(:class:`DeadlineTimer`). Every task ends when its line is closed or the administrator's mailbox
stops. ``el_scan_notifier`` and ``el_scan_start`` are the report's "future tasks" for a tilt
axis, "similar to [the azimuth ones] except that they apply to the elevation scan".

What a notifier has drained from BIRIS memory (NEW_POINT, CONTINUOUS_LIVE, SWEEP_DATA_DONE) is
always posted one-way, under the reader's lock: so the inbox holds it in the reader's order,
and no task ever waits for the administrator while holding that lock -- which the level-2
routine takes for every acquisition.

Continuous mode (Appendix D) touches three tasks: ``biris_cmd_transfer`` raises the
continuous-mode flag of the level-2 demultiplexer and primes the reader before it writes
BI_START_CONTINUOUS; ``biris_cmd_notifier`` lowers the flag once BI_STOP_CONTINUOUS has completed;
``az_scan_start`` re-enables the data interrupts (opens the sweep) once the motor is moving, and
``biris_az_notifier`` marks the sweep's end when the motor has come to rest.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from biris_hw.devices import AxisDriver, BirisLink
from biris_hw.errors import BirisError, BusError, LineClosed
from biris_hw.ipc import Mailbox, TaskStopped
from biris_hw.irq.base import InterruptLine
from biris_hw.server.acquisition import AcquisitionReader, Drained, ring_length
from biris_hw.server.messages import (
    AzReady,
    AzScanDone,
    BirisBusErr,
    BirisCmdComplete,
    BirisParityErr,
    CmdTransferRdy,
    ContinuousLive,
    ElReady,
    ElScanDone,
    MoveOrder,
    NewPoint,
    ParamsOrder,
    SweepDataDone,
    TransferOrder,
)
from regs.biexec import BiCommand, BiStatus

__all__ = [
    "BirisDataNotifier",
    "CommandLedger",
    "DeadlineTimer",
    "az_scan_start",
    "biris_az_notifier",
    "biris_bus_err",
    "biris_cmd_notifier",
    "biris_cmd_transfer",
    "biris_parity_err",
    "el_scan_notifier",
    "el_scan_start",
]

log = logging.getLogger(__name__)


def _await(line: InterruptLine) -> int | None:
    """Harmony's _Await_interrupt: the count, or None once the line is closed."""
    try:
        return line.wait()
    except LineClosed:
        return None


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

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.outstanding: TransferOrder | None = None


def _post_drained(admin: Mailbox, drained: Drained) -> None:
    """What a drain produced, as one-way messages, in order: NEW_POINT, then what it completed.

    Called under the reader's lock (see the module notes); raises TaskStopped once the
    administrator has stopped.
    """
    if drained.acquisitions or drained.lost:
        admin.post_oneway(NewPoint(drained.acquisitions, drained.lost))
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
            with reader.lock:
                _post_drained(admin, reader.drain_sequence(final=True))
            admin.send(BirisCmdComplete(status, param, order.token))
        except TaskStopped:
            return
        except BusError:
            log.exception("biris_cmd_notifier: bus error reading BIEXEC_COM")


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
    """

    def __init__(self, admin: Mailbox, reader: AcquisitionReader) -> None:
        self._admin = admin
        self._reader = reader

    def __call__(self, count: int = 1) -> bool:
        """One interrupt (``count`` coalesced); False once the administrator has stopped."""
        try:
            with self._reader.lock:
                _post_drained(self._admin, self._reader.drain())
        except TaskStopped:
            return False
        except BusError:
            log.exception("biris_data_notifier: bus error reading a frame")
        return True


def _axis_notifier(
    line: InterruptLine,
    admin: Mailbox,
    axis: AxisDriver,
    stop: threading.Event,
    done: object,
    reader: AcquisitionReader | None = None,
) -> None:
    """Shared body of the two motor notifiers: end of profile -> settled -> ``done``."""
    while _await(line) is not None:
        try:
            axis.wait_settled(stop)
            if reader is not None:
                with reader.lock:
                    _post_drained(admin, reader.end_sweep())
            admin.send(done)
        except TaskStopped:
            return
        except BusError:
            log.exception("%s notifier: bus error while settling", axis.axis.name.lower())


def biris_az_notifier(
    line: InterruptLine,
    admin: Mailbox,
    axis: AxisDriver,
    stop: threading.Event,
    reader: AcquisitionReader | None = None,
) -> None:
    """MOTOR_END_OF_SCAN -> AZ_SCAN_DONE, once the head has actually come to rest.

    The chip signals the end of the profile when it issues the last setpoint, not when the motor
    stops; the notifier polls the position briefly (:meth:`AxisDriver.wait_settled`, given up
    when ``stop`` is set) so that AZ_SCAN_DONE means what the report says: motion has
    terminated. In continuous mode it then tells the reader that the sweep ends with the frame
    in exposure (and posts what is already complete) first.
    """
    _axis_notifier(line, admin, axis, stop, AzScanDone(), reader)


def el_scan_notifier(
    line: InterruptLine,
    admin: Mailbox,
    axis: AxisDriver,
    stop: threading.Event,
) -> None:
    """ELEVATION_END_OF_SCAN -> EL_SCAN_DONE, once the tilt has come to rest (the report's
    future _el_scan_notifier)."""
    _axis_notifier(line, admin, axis, stop, ElScanDone())


def error_notifier(line: InterruptLine, admin: Mailbox, message: object) -> None:
    """Shared body of biris_parity_err and biris_bus_err: each interrupt is one report."""
    while _await(line) is not None:
        try:
            admin.send(message)
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
    classifies the first data interrupt right.
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
        try:
            with ledger.lock:
                ledger.outstanding = order
                link.issue(order.code, order.param)
        except BirisError:
            log.exception("biris_cmd_transfer: could not write command %d", order.code)


def _axis_worker(
    admin: Mailbox,
    axis: AxisDriver,
    make_ready: Callable[[str | None], object],
    reader: AcquisitionReader | None = None,
) -> None:
    """Shared body of the two motor workers: report ready, carry out the reply; forever."""
    ready = make_ready(None)
    while True:
        try:
            order = admin.send(ready)
        except TaskStopped:
            return
        try:
            if isinstance(order, MoveOrder):
                if order.sweep and reader is not None:
                    # just before the motor starts, so that a worker the machine runs late
                    # cannot cost the sweep its beginning; what is read before the head
                    # moves is at the start azimuth, and the administrator drops it (or, in
                    # a sweep that turns straight round, keeps it as the turn-around's)
                    reader.open_sweep(order.sweep, follows=order.follows)
                axis.start_trapezoid(order.destination)
            elif isinstance(order, ParamsOrder):
                axis.configure(order.params)
            ready = make_ready(None)
        except BirisError as exc:
            ready = make_ready(str(exc))


def az_scan_start(
    admin: Mailbox, axis: AxisDriver, reader: AcquisitionReader | None = None
) -> None:
    """AZ_READY, then start the motion the reply carries; forever.

    A continuous-mode sweep's order also opens the sweep as the motor starts: data interrupts
    back on, "after the next scan is started" (Appendix D) -- here an instant before, so that
    the head's first move is never missed.
    """
    _axis_worker(admin, axis, lambda error: AzReady(error=error), reader)


def el_scan_start(admin: Mailbox, axis: AxisDriver) -> None:
    """EL_READY, then start the tilt the reply carries; forever (the report's future
    _el_scan_start)."""
    _axis_worker(admin, axis, lambda error: ElReady(error=error))


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
        clock: Callable[[], float],
        time_scale: float,
        make: Callable[[int], object],
    ) -> None:
        self.name = name
        self._admin = admin
        self._clock = clock
        self._scale = time_scale
        self._make = make
        self._cond = threading.Condition()
        self._deadline: float | None = None
        self._generation = 0
        self._stopped = False
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Run the task in a thread of its own, named :attr:`name`."""
        thread = threading.Thread(target=self.run, name=self.name, daemon=True)
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
        on a fast simulator clock is many hardware seconds.
        """
        with self._cond:
            self._generation += 1
            deadline = self._clock() + hw_seconds + real_slack_s * self._scale
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
            thread.join()

    def run(self) -> None:
        """The task's body, for an owner that makes the thread itself (:meth:`start` runs it
        too); returns once :meth:`stop` is called or the administrator has stopped."""
        with self._cond:
            if self._thread is None:
                self._thread = threading.current_thread()
            while not self._stopped:
                if self._deadline is None:
                    self._cond.wait()
                    continue
                remaining = self._deadline - self._clock()
                if remaining > 0:
                    self._cond.wait(remaining / self._scale)
                    continue
                generation = self._generation
                self._deadline = None
                self._cond.release()
                try:
                    self._admin.send(self._make(generation))
                except TaskStopped:
                    return
                finally:
                    self._cond.acquire()
