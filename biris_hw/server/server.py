"""``BirisServer``: creates the report's tasks in order, initialises, and hands out connections.

The threads, in creation order (Appendix B's task list, plus the demultiplexers that play the
interrupt service routine and the initialiser that plays _Create_server's start-up):
level-2 demultiplexer, which is also biris_data_notifier (it drains the acquisitions itself rather
than wake a thread for them); level-3 demultiplexer; biris_cmd_notifier, biris_cmd_transfer,
biris_az_notifier, az_scan_start, biris_timeout, biris_parity_err, biris_bus_err; the report's
future tilt tasks el_scan_notifier and el_scan_start; the two motor watchdogs; the
administrator. ``close()`` stops them in reverse and leaves no thread behind.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable
from types import TracebackType
from typing import Any, Literal, overload

from biris_hw.affinity import check_cpus, pinned
from biris_hw.client import Connection
from biris_hw.data import ConnectionKind, DeliveryPolicy, Point, Scan
from biris_hw.errors import BirisError, ConnectionClosed, HardwareFault
from biris_hw.hardware import BirisHardware
from biris_hw.ipc import Mailbox
from biris_hw.irq.demux import Level2Demux, Level3Demux, Logical
from biris_hw.records import BirisInitRecord
from biris_hw.server import tasks
from biris_hw.server.acquisition import AcquisitionReader
from biris_hw.server.admin import Administrator
from biris_hw.server.devices import AxisDriver, BirisLink, Coupler, MotionBoard
from biris_hw.server.initialiser import Initialiser, InitResult, run_initialiser, wait_settled
from biris_hw.server.messages import (
    BirisTimeoutErr,
    InitDone,
    MotorWatchdogErr,
    OpenRequest,
    ResetRequest,
    StatusRequest,
)
from regs.tech80 import Axis

__all__ = ["BirisServer"]

log = logging.getLogger(__name__)


class BirisServer:
    """The BIRIS server of the report, on a :class:`BirisHardware` bundle.

    Construction creates every task and runs initialisation (homing, boot); it raises
    :class:`HardwareFault` if that fails, after stopping what it started. Use it as a context
    manager, or call :meth:`close`.
    """

    def __init__(self, hardware: BirisHardware, record: BirisInitRecord | None = None) -> None:
        self.hardware = hardware
        self.record = record if record is not None else BirisInitRecord()
        if self.record.cpus:
            check_cpus(self.record.cpus)  # before anything starts: a bad set changes nothing
        hw = hardware
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._closed = False
        self.inbox = Mailbox("BIRISSERV")
        self.link = BirisLink(hw.biris, hw.biexec_offset)
        self.azimuth = AxisDriver(hw.motion, Axis.AZIMUTH)
        self.elevation = AxisDriver(hw.motion, Axis.ELEVATION)
        self.board = MotionBoard(hw.motion)
        self.coupler = Coupler(hw.coupler)
        self.reader = AcquisitionReader(hw.biris, self.link, hw.clock, self.record.max_range)
        self.ledger = tasks.CommandLedger()
        self.level2 = Level2Demux(hw.level2, hw.coupler, hw.biris, hw.biexec_offset)
        self.level3 = Level3Demux(hw.level3, hw.motion)
        self.biris_timeout = tasks.DeadlineTimer(
            "biris_timeout", self.inbox, hw.clock, hw.time_scale, BirisTimeoutErr
        )
        self.motor_watchdog = tasks.DeadlineTimer(
            "az_watchdog", self.inbox, hw.clock, hw.time_scale, MotorWatchdogErr
        )
        self.elevation_watchdog = tasks.DeadlineTimer(
            "el_watchdog",
            self.inbox,
            hw.clock,
            hw.time_scale,
            lambda generation: MotorWatchdogErr(generation, Axis.ELEVATION),
        )
        self.admin = Administrator(
            self.record,
            self.inbox,
            hw.clock,
            self.biris_timeout,
            self.motor_watchdog,
            self._start_initialiser,
            self.elevation_watchdog,
        )
        try:
            with pinned(self.record.cpus) if self.record.cpus else contextlib.nullcontext():
                self._create_tasks()  # every task inherits the CPUs (biris_hw.affinity)
            self._initialise()
        except BaseException:
            self.close()
            raise

    # -- task creation ---------------------------------------------------------------------
    def _spawn(self, name: str, target: Callable[..., None], *args: Any) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()

    def _settle(self, axis: AxisDriver) -> None:
        wait_settled(axis, self.hardware.clock, self.hardware.time_scale, self._stop)

    def _create_tasks(self) -> None:
        # biris_data_notifier runs in the level-2 demultiplexer's thread (see biris_hw.irq.demux)
        self.level2.attach_data_notifier(tasks.BirisDataNotifier(self.inbox, self.reader))
        self.level2.start()
        self.level3.start()
        inbox = self.inbox
        self._spawn(
            "biris_cmd_notifier",
            tasks.biris_cmd_notifier,
            self.level2.line(Logical.BIRIS_CMD),
            inbox,
            self.link,
            self.reader,
            self.ledger,
            self.level2.set_continuous,
        )
        self._spawn(
            "biris_cmd_transfer",
            tasks.biris_cmd_transfer,
            inbox,
            self.link,
            self.reader,
            self.ledger,
            self.level2.set_continuous,
        )
        self._spawn(
            "biris_az_notifier",
            tasks.biris_az_notifier,
            self.level3.line(Logical.MOTOR_END_OF_SCAN),
            inbox,
            self.azimuth,
            self._settle,
            self.reader,
        )
        self._spawn("az_scan_start", tasks.az_scan_start, inbox, self.azimuth, self.reader)
        self.biris_timeout.start()
        self._spawn(
            "biris_parity_err", tasks.biris_parity_err, self.level2.line(Logical.BIT3_PERR), inbox
        )
        self._spawn(
            "biris_bus_err", tasks.biris_bus_err, self.level2.line(Logical.BIT3_BERR), inbox
        )
        self._spawn(
            "el_scan_notifier",
            tasks.el_scan_notifier,
            self.level3.line(Logical.ELEVATION_END_OF_SCAN),
            inbox,
            self.elevation,
            self._settle,
        )
        self._spawn("el_scan_start", tasks.el_scan_start, inbox, self.elevation)
        self.motor_watchdog.start()
        self.elevation_watchdog.start()
        self._spawn("biris_server", self.admin.run)

    def _start_initialiser(self) -> None:
        """Called by the administrator (on reset): never blocks, the work runs in a thread."""
        init = Initialiser(self.hardware, self.record, self.inbox, self._stop)

        def report(result: InitResult | BaseException) -> None:
            if isinstance(result, InitResult):
                self.reader.configure(result.addressing, result.samples, result.period_s)
                message = InitDone(None, result)
            else:
                message = InitDone(result)
            try:
                self.inbox.send(message)
            except ConnectionClosed:
                pass

        thread = threading.Thread(
            target=run_initialiser, args=(init, report), name="biris_init", daemon=True
        )
        self._threads = [t for t in self._threads if t.is_alive()]
        self._threads.append(thread)
        thread.start()

    def _initialise(self) -> None:
        self.inbox.send(ResetRequest(0))

    # -- public ----------------------------------------------------------------------------
    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.EVERY_ACQUISITION],
        depth: int | None = ...,
    ) -> Connection[Point]: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.LATEST, DeliveryPolicy.EVERY_BUFFER] = ...,
        depth: int | None = ...,
    ) -> Connection[Scan]: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: DeliveryPolicy,
        depth: int | None = ...,
    ) -> Connection[Scan] | Connection[Point]: ...

    def open(
        self,
        kind: ConnectionKind = ConnectionKind.NORMAL,
        *,
        policy: DeliveryPolicy = DeliveryPolicy.LATEST,
        depth: int | None = None,
    ) -> Connection[Scan] | Connection[Point]:
        """OPEN_REQUEST: a NORMAL connection, or a DATA one that is sent data as they come.

        ``policy`` (DATA connections only) says what READY_FOR_DATA delivers and what a slow
        client loses; ``depth`` how much waits for it (default: the policy's). A bad choice is a
        RequestError. The connection belongs to the calling thread and is released when that
        thread ends.
        """
        if self._closed:
            raise ConnectionClosed("the BIRIS server has stopped")
        owner = threading.current_thread()
        answer = self.inbox.send(OpenRequest(ConnectionKind(kind), owner, policy, depth))
        assert isinstance(answer, tuple)
        number, chosen, used = answer
        if chosen is DeliveryPolicy.EVERY_ACQUISITION:
            return Connection[Point](self.inbox, number, ConnectionKind(kind), chosen, used)
        return Connection[Scan](self.inbox, number, ConnectionKind(kind), chosen, used)

    def status(self) -> dict[str, Any]:
        """What the server is doing and has done: ``state`` (initialising, idle, scanning,
        homing, tilting, fault:<kind>), ``azimuth`` and ``elevation`` (counts: where the axes
        were last sent), ``azimuth_live`` and ``elevation_live`` (counts: the encoders now, None
        while initialising or if the board cannot be read), ``counters``,
        ``interrupts`` by logical kind, and per connection its policy, queue, deliveries, drops
        and delivery-latency histogram with p50 and p99 (see the README)."""
        if self._closed:
            raise ConnectionClosed("the BIRIS server has stopped")
        result = self.inbox.send(StatusRequest())
        assert isinstance(result, dict)
        result["interrupts"] = {
            **{k.name: v for k, v in self.level2.counts.items()},
            **{k.name: v for k, v in self.level3.counts.items()},
        }
        homed = result["state"] != "initialising"
        result["azimuth_live"] = self._encoder(self.azimuth) if homed else None
        result["elevation_live"] = self._encoder(self.elevation) if homed else None
        return result

    @staticmethod
    def _encoder(axis: AxisDriver) -> int | None:
        """Where the axis is now, by its encoder, not where it was sent: ``azimuth`` is the
        latter. Read here, in the caller's thread, because the administrator never waits on the
        bus; None when the board cannot be read (the fault is reported by the tasks that hit it).
        """
        try:
            return axis.actual_position()
        except BirisError:
            return None

    def reset(self) -> None:
        """Re-run initialisation (the way back after a HardwareFault); raises if it fails."""
        if self._closed:
            raise ConnectionClosed("the BIRIS server has stopped")
        self.inbox.send(ResetRequest(0))

    def close(self) -> None:
        """Stop every task, disable the interrupts we enabled, leave no thread behind."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        quieting: tuple[Callable[[], None], ...] = (
            lambda: self.link.set_flags(cmd_int=False, data_int=False),
            self.board.disable_all,
            self.coupler.disable_interrupts,
        )
        for quiet in quieting:
            try:
                quiet()
            except Exception:  # the hardware may be what failed; closing must still finish
                log.debug("could not quiet the hardware on close", exc_info=True)
        self.inbox.close()
        self.level2.close()
        self.level3.close()
        self.biris_timeout.stop()
        self.motor_watchdog.stop()
        self.elevation_watchdog.stop()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join()
        self.admin.shutdown()

    def __enter__(self) -> BirisServer:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


_ = HardwareFault  # re-exported for readers of this module's docstring
