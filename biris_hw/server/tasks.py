"""The BIRIS server's internal tasks (report Fig. 4), one function or class each.

Notifiers block on an interrupt and *send* to the administrator: ``biris_cmd_notifier``,
``biris_data_notifier``, ``biris_az_notifier``, ``biris_parity_err``, ``biris_bus_err``.
Workers report ready and block until the administrator *replies* with an order:
``biris_cmd_transfer`` (writes the next BIRIS command) and ``az_scan_start`` (starts the next
trapezoid). ``biris_timeout`` and the motor watchdog are timers. Every task ends when its line is
closed or the administrator's mailbox stops.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from biris_hw.errors import BirisError, BusError, LineClosed
from biris_hw.ipc import Mailbox, TaskStopped
from biris_hw.irq.base import InterruptLine
from biris_hw.server.acquisition import AcquisitionReader
from biris_hw.server.devices import AxisDriver, BirisLink
from biris_hw.server.messages import (
    AzReady,
    AzScanDone,
    BirisBusErr,
    BirisCmdComplete,
    BirisParityErr,
    CmdTransferRdy,
    MoveOrder,
    NewPoint,
    ParamsOrder,
    TransferOrder,
)
from regs.biexec import BiCommand

__all__ = [
    "CommandLedger",
    "DeadlineTimer",
    "az_scan_start",
    "biris_az_notifier",
    "biris_bus_err",
    "biris_cmd_notifier",
    "biris_cmd_transfer",
    "biris_data_notifier",
    "biris_parity_err",
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


def biris_cmd_notifier(
    line: InterruptLine,
    admin: Mailbox,
    link: BirisLink,
    reader: AcquisitionReader,
    ledger: CommandLedger,
) -> None:
    """BIRIS_CMD -> BIRIS_CMD_COMPLETE (after handing over any acquisitions not yet read).

    The administrator holds the reply until it is about to issue the next command, so this task
    is back on the interrupt before that command can complete.
    """
    while _await(line) is not None:
        try:
            with ledger.lock:
                order = ledger.outstanding
                if order is None or link.command() != 0:
                    continue  # stale, spurious, or BIRIS still busy: not a completion
                ledger.outstanding = None
            with reader.lock:
                drained = reader.drain(final=True)
                if drained.acquisitions or drained.lost:
                    admin.send(NewPoint(drained.acquisitions, drained.lost))
            admin.send(BirisCmdComplete(link.status(), link.param_raw(), order.token))
        except TaskStopped:
            return
        except BusError:
            log.exception("biris_cmd_notifier: bus error reading BIEXEC_COM")


def biris_data_notifier(line: InterruptLine, admin: Mailbox, reader: AcquisitionReader) -> None:
    """BIRIS_DATA_DEV -> NEW_POINT with every acquisition completed since the last one."""
    while _await(line) is not None:
        try:
            with reader.lock:
                drained = reader.drain()
                if drained.acquisitions or drained.lost:
                    admin.send(NewPoint(drained.acquisitions, drained.lost))
        except TaskStopped:
            return
        except BusError:
            log.exception("biris_data_notifier: bus error reading a frame")


def biris_az_notifier(
    line: InterruptLine,
    admin: Mailbox,
    axis: AxisDriver,
    settle: Callable[[AxisDriver], None],
) -> None:
    """MOTOR_END_OF_SCAN -> AZ_SCAN_DONE, once the head has actually come to rest.

    The chip signals the end of the profile when it issues the last setpoint, not when the motor
    stops; the notifier polls the position briefly (``settle``) so that AZ_SCAN_DONE means what
    the report says: motion has terminated.
    """
    while _await(line) is not None:
        try:
            settle(axis)
            admin.send(AzScanDone())
        except TaskStopped:
            return
        except BusError:
            log.exception("biris_az_notifier: bus error while settling")


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
    admin: Mailbox, link: BirisLink, reader: AcquisitionReader, ledger: CommandLedger
) -> None:
    """CMD_TRANSFER_RDY, then write whatever command the reply carries; forever."""
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
        try:
            with ledger.lock:
                ledger.outstanding = order
                link.issue(order.code, order.param)
        except BirisError:
            log.exception("biris_cmd_transfer: could not write command %d", order.code)


def az_scan_start(admin: Mailbox, axis: AxisDriver) -> None:
    """AZ_READY, then start the motion the reply carries; forever."""
    ready = AzReady()
    while True:
        try:
            order = admin.send(ready)
        except TaskStopped:
            return
        try:
            if isinstance(order, MoveOrder):
                axis.start_trapezoid(order.destination)
            elif isinstance(order, ParamsOrder):
                axis.configure(order.params)
            ready = AzReady()
        except BirisError as exc:
            ready = AzReady(error=str(exc))


# --- timers --------------------------------------------------------------------------------------


class DeadlineTimer:
    """A task that sends ``make(generation)`` when an armed deadline passes (hardware time).

    ``_Biris_timeout`` in the report is created per command and destroyed on completion; arming
    and disarming one long-lived task is the same contract without thread churn. Arming or
    disarming never blocks the administrator for longer than a lock hand-over.
    """

    def __init__(
        self,
        name: str,
        admin: Mailbox,
        clock: Callable[[], float],
        time_scale: float,
        make: Callable[[int], object],
    ) -> None:
        self._admin = admin
        self._clock = clock
        self._scale = time_scale
        self._make = make
        self._cond = threading.Condition()
        self._deadline: float | None = None
        self._generation = 0
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    @property
    def generation(self) -> int:
        return self._generation

    def arm(self, hw_seconds: float) -> int:
        """(Re)start the countdown; returns the generation an expiry will carry."""
        with self._cond:
            self._generation += 1
            self._deadline = self._clock() + hw_seconds
            self._cond.notify()
            return self._generation

    def disarm(self) -> None:
        with self._cond:
            self._generation += 1
            self._deadline = None
            self._cond.notify()

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join()

    def _run(self) -> None:
        with self._cond:
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
