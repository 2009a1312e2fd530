"""``BirisServer``: creates the report's tasks in order, initialises, and hands out connections.

The tasks, their threads and their order are the task table (:mod:`biris_hw.server.task_table`):
the server starts each row's thread from it, with the body :meth:`BirisServer._task_bodies`
gives that row, and refuses to start if the two disagree. Every thread runs its body under the
server's :class:`~biris_hw.server.tasks.Supervisor`. A task that fails is reported to the
administrator as a fault (``bus`` or ``internal``) and runs again at the next reset, so no
exception kills a task for good. ``close()`` stops every task and leaves no thread behind. The
devices are the hardware bundle's one set of drivers (``BirisHardware.devices``), shared with the
initialiser, ``status()`` and the CLI.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
from collections.abc import Callable
from types import TracebackType
from typing import TYPE_CHECKING, Any, Literal, overload

from biris_hw.affinity import check_cpus, pinned
from biris_hw.angles import RealLike
from biris_hw.client import Connection, status_request
from biris_hw.data import ConnectionKind, DeliveryPolicy, Point, Scan
from biris_hw.errors import BirisError, ConnectionClosed, RequestError
from biris_hw.hardware import BirisHardware
from biris_hw.ipc import Mailbox, TaskStopped
from biris_hw.protocol import OpenRequest, ResetRequest
from biris_hw.records import BirisInitRecord
from biris_hw.server import tasks
from biris_hw.server.acquisition import AcquisitionReader
from biris_hw.server.admin import Administrator
from biris_hw.server.crate_watch import CrateWatch
from biris_hw.server.initialiser import Initialiser, InitResult, run_initialiser
from biris_hw.server.isr import Level2Demux, Level3Demux, Logical
from biris_hw.server.messages import (
    BirisTimeoutErr,
    InitDone,
    MotionRechecked,
    MotorWatchdogErr,
)
from biris_hw.server.task_table import TASKS, Starts, TaskSpec, task
from biris_hw.status import ServerStatus
from biris_hw.timebase import HwThread
from regs.tech80 import Axis

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor

__all__ = ["BirisServer"]

log = logging.getLogger(__name__)


class BirisServer:
    """The BIRIS server of the report, on a :class:`BirisHardware` bundle.

    Construction creates every task and runs initialisation (homing, boot). Use it as a context
    manager, or call :meth:`close`.

    Raises:
        HardwareFault: initialisation failed (everything started is stopped first).
        RequestError: the record asks for CPUs the process cannot use (nothing is started).
    """

    def __init__(self, hardware: BirisHardware, record: BirisInitRecord | None = None) -> None:
        self.hardware = hardware
        self.record = record if record is not None else BirisInitRecord()
        if self.record.cpus:
            check_cpus(self.record.cpus)  # before anything starts: a bad set changes nothing
        hw = hardware
        tb = self.timebase = hw.timebase
        """Every wait of every task goes through it (:mod:`biris_hw.timebase`): scaled real time
        on the target and by default, virtual time on a simulator made with ``clock="virtual"``."""
        self._stop = tb.Event()
        self._threads: list[HwThread] = []
        self._closed = False
        self.inbox = Mailbox("BIRISSERV", timebase=tb)
        self.devices = hw.devices  # the bundle's one driver per device (biris_hw.devices)
        self.link = self.devices.link
        self.azimuth = self.devices.azimuth
        self.elevation = self.devices.elevation
        self.board = self.devices.board
        self.coupler = self.devices.coupler
        self.reader = AcquisitionReader(hw.biris, self.link, hw.clock, self.record.max_range)
        self.ledger = tasks.CommandLedger(tb)
        self.az_moves = tasks.MoveLedger(hw.clock)
        self.el_moves = tasks.MoveLedger(hw.clock)
        self.supervisor = tasks.Supervisor(self.inbox, tb)
        self.level2 = Level2Demux(hw.level2, hw.coupler, hw.biris, hw.biexec_offset, timebase=tb)
        self.level3 = Level3Demux(hw.level3, self.devices.board, timebase=tb)
        self.biris_timeout = tasks.DeadlineTimer(
            task("biris_timeout").thread, self.inbox, tb, BirisTimeoutErr
        )
        self.motor_watchdog = tasks.DeadlineTimer(
            task("az_watchdog").thread, self.inbox, tb, MotorWatchdogErr
        )
        self.elevation_watchdog = tasks.DeadlineTimer(
            task("el_watchdog").thread,
            self.inbox,
            tb,
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
            hw.time_scale,
            self.level3.recheck,
            self.level2.recheck,
            hw.lag,
            self._status_extras,
            lambda: self.supervisor.resets,
        )
        self.level2.attach_recheck(
            tasks.BirisRecheck(self.inbox, self.reader, self.link, self.ledger)
        )
        self.level3.attach_look_report(self._report_motion_look)
        self.crate_watch: CrateWatch | None = None
        """The crate monitor's poller (``hardware.crate``), or None without one."""
        try:
            with pinned(self.record.cpus) if self.record.cpus else contextlib.nullcontext():
                self._create_tasks()  # every task inherits the CPUs (biris_hw.affinity)
                if hw.crate is not None:
                    self.crate_watch = CrateWatch(hw.crate, hw.crate_poll_s).start()
            self._initialise()
        except BaseException:
            self.close()
            raise

    def _report_motion_look(self, ended: int) -> None:
        """The level-3 routine's answer to a motor watchdog (in its thread): what the
        controller said, and when each axis's worker last started a move."""
        az, el = self.az_moves, self.el_moves
        started = {Axis.AZIMUTH: az.started, Axis.ELEVATION: el.started}
        noticed = {Axis.AZIMUTH: az.noticed, Axis.ELEVATION: el.noticed}
        with contextlib.suppress(TaskStopped):
            self.inbox.post_oneway(MotionRechecked(ended, started, noticed))

    # -- task creation ---------------------------------------------------------------------
    def _spawn(self, spec: TaskSpec, body: Callable[[], None]) -> None:
        """Start ``spec``'s thread, running ``body`` under the supervisor."""
        thread = self.timebase.Thread(
            target=self.supervisor.run,
            args=(spec.name, body, spec.restart),
            name=spec.thread,
            daemon=True,
        )
        self._threads.append(thread)
        thread.start()

    def _task_bodies(self) -> dict[str, Callable[[], None]]:
        """Each task of the table, by name: its thread's body, or, for a task that runs in
        another task's thread, what puts it there."""
        inbox, reader, ledger, stop = self.inbox, self.reader, self.ledger, self._stop
        level2, level3 = self.level2, self.level3
        set_continuous = level2.set_continuous
        data_failed = functools.partial(self.supervisor.failed, "biris_data_notifier")
        return {
            "biris_cmd_notifier": lambda: tasks.biris_cmd_notifier(
                level2.line(Logical.BIRIS_CMD), inbox, self.link, reader, ledger, set_continuous
            ),
            "biris_cmd_transfer": lambda: tasks.biris_cmd_transfer(
                inbox, self.link, reader, ledger, set_continuous
            ),
            "biris_data_notifier": lambda: level2.attach_data_notifier(
                tasks.BirisDataNotifier(inbox, reader, data_failed)
            ),
            "biris_az_notifier": lambda: tasks.biris_az_notifier(
                level3.line(Logical.MOTOR_END_OF_SCAN),
                inbox,
                self.azimuth,
                stop,
                reader,
                self.az_moves,
            ),
            "az_scan_start": lambda: tasks.az_scan_start(
                inbox, self.azimuth, reader, self.az_moves
            ),
            "biris_timeout": self.biris_timeout.run,
            "biris_parity_err": lambda: tasks.biris_parity_err(
                level2.line(Logical.BIT3_PERR), inbox
            ),
            "biris_bus_err": lambda: tasks.biris_bus_err(level2.line(Logical.BIT3_BERR), inbox),
            "el_scan_notifier": lambda: tasks.el_scan_notifier(
                level3.line(Logical.ELEVATION_END_OF_SCAN),
                inbox,
                self.elevation,
                stop,
                self.el_moves,
            ),
            "el_scan_start": lambda: tasks.el_scan_start(inbox, self.elevation, self.el_moves),
            "encoder_reader": lambda: tasks.encoder_reader(inbox, self.azimuth, self.elevation),
            "az_watchdog": self.motor_watchdog.run,
            "el_watchdog": self.elevation_watchdog.run,
            "level2_isr": level2.serve,  # serve, not run: a lost line is raised, and reported
            "level3_isr": level3.serve,
            "biris_server": self.admin.run,
            "biris_init": self._start_initialiser,
        }

    def _create_tasks(self) -> None:
        """Start the table's tasks in its order: a thread per row that has its own, and the
        rows that share a thread put into it (as the supervisor's guests, put back by a reset
        after they have failed)."""
        bodies = self._task_bodies()
        if set(bodies) != {spec.name for spec in TASKS}:
            raise RuntimeError(
                "the task table and the server disagree: "
                f"{sorted(set(bodies) ^ {spec.name for spec in TASKS})}"
            )
        for spec in TASKS:
            if spec.starts is not Starts.WITH_SERVER:
                continue  # started by the administrator (the initialiser, on reset)
            if spec.own_thread:
                self._spawn(spec, bodies[spec.name])
            else:
                self.supervisor.guest(spec.name, bodies[spec.name])

    def _start_initialiser(self) -> None:
        """Called by the administrator (on reset): never blocks, the work runs in a thread.

        The initialiser first re-links what was lost (the hardware bundle's ``relink``), then
        runs every task that failed since the last reset again
        (:meth:`~biris_hw.server.tasks.Supervisor.reset`, handed to it as ``restart_tasks``),
        so that an interrupt routine is never restarted on a line still lost, and the
        initialiser's moves and commands find live workers and notifiers.
        """
        init = Initialiser(
            self.hardware, self.record, self.inbox, self._stop, restart_tasks=self.supervisor.reset
        )

        def report(result: InitResult | BaseException) -> None:
            if isinstance(result, InitResult):
                try:
                    self.reader.configure(result.addressing, result.samples, result.period_s)
                    message = InitDone(None, result)
                except Exception as exc:  # the reset must still end, and say why
                    log.exception("could not configure the acquisition reader")
                    message = InitDone(exc)
            else:
                message = InitDone(result)
            try:
                self.inbox.send(message)
            except ConnectionClosed:
                pass  # the server has stopped
            except BirisError as exc:  # the administrator's case failed; it has said so
                log.error("INIT_DONE refused: %s", exc)

        thread = self.timebase.Thread(
            target=run_initialiser,
            args=(init, report),
            name=task("biris_init").thread,
            daemon=True,
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
        client loses; ``depth`` how much waits for it (default: the policy's). The connection
        belongs to the calling thread and is released when that thread ends.

        Raises:
            ConnectionClosed: the server has stopped.
            RequestError: an unknown kind, policy or depth.
        """
        if self._closed:
            raise ConnectionClosed("the BIRIS server has stopped")
        try:
            kind = ConnectionKind(kind)
        except ValueError:
            raise RequestError(
                f"no connection kind {kind!r}; use ConnectionKind.NORMAL or DATA"
            ) from None
        owner = threading.current_thread()
        answer = self.inbox.send(OpenRequest(kind, owner, policy, depth))
        assert isinstance(answer, tuple)
        number, chosen, used = answer
        bulletin = self.admin.bulletin
        if chosen is DeliveryPolicy.EVERY_ACQUISITION:
            return Connection[Point](
                self.inbox, number, ConnectionKind(kind), chosen, used, bulletin
            )
        return Connection[Scan](self.inbox, number, ConnectionKind(kind), chosen, used, bulletin)

    def status(
        self, *, newer_than: int | None = None, timeout: RealLike | None = None
    ) -> ServerStatus:
        """What the server is doing and has done (:class:`biris_hw.status.ServerStatus`).

        ``state`` (a :class:`~biris_hw.status.ServerState`; ``status["state"]`` reads
        initialising, idle, scanning, homing, tilting, busy or fault:<kind>), ``fault`` (the kind),
        ``azimuth`` and ``elevation`` (counts: where the axes were last sent),
        ``azimuth_live`` and ``elevation_live`` (counts: the encoders, None while initialising
        or if the board cannot be read), ``counters``, ``interrupts`` by logical
        kind, the tasks that failed and wait for a reset (``tasks_down``, ``task_failures``),
        the VME crate's last reading when the hardware has a crate monitor (``crate``,
        ``crate_error``), per connection its policy, queue, deliveries, drops and
        delivery-latency histogram with p50 and p99 (see the README), and ``change``.

        The administrator answers; nothing is read from the bus in the caller's thread. The
        encoders are read for it by a worker, at most 10 times a hardware second while an axis
        moves and once a second at rest, whatever the rate of asking
        (:mod:`biris_hw.server.encoders`).

        Args:
            newer_than: a status's ``change``: return once the status has changed since (the
                state, a fault, where the axes were sent, the modes, the connections: what
                :meth:`ServerStatus.signature <biris_hw.status.ServerStatus.signature>`
                covers), at once if it has already. None: now.
            timeout: how long to wait for that (None: as long as it takes; 0: a poll).

        Raises:
            ConnectionClosed: the server has stopped.
            RequestError: a ``newer_than`` that is not a whole number, or a bad timeout.
            TimeoutError: no newer status within ``timeout`` (at once for a poll).
        """
        if self._closed:
            raise ConnectionClosed("the BIRIS server has stopped")
        return status_request(self.inbox, None, newer_than, timeout, self.admin.bulletin)

    def _status_extras(self) -> dict[str, Any]:
        """The status's parts that live outside the administrator, for it to add (in its
        thread; each is a copy under a short lock, none reads the bus)."""
        return {
            "interrupts": {
                **{k.name: v for k, v in self.level2.counts.items()},
                **{k.name: v for k, v in self.level3.counts.items()},
            },
            "tasks_down": tuple(sorted(self.supervisor.down)),
            "task_failures": self.supervisor.failure_counts(),
            **self._crate(),
        }

    def _crate(self) -> dict[str, Any]:
        """``crate`` and ``crate_error`` for status(), from what the poller holds (no wait)."""
        if self.crate_watch is None:
            return {}
        reading, error = self.crate_watch.latest()
        return {"crate": reading, "crate_error": error}

    def clock(self) -> float:
        """Hardware seconds now (the hardware bundle's clock)."""
        return float(self.hardware.clock())

    playback = False
    """A live sensor: it carries out motion and configuration (:class:`biris_hw.sensor.Sensor`)."""

    paced = True
    """Its data come at the hardware's pace, whatever the readers do."""

    def reset(self) -> None:
        """Re-run initialisation (the way back after a HardwareFault).

        Raises:
            ConnectionClosed: the server has stopped.
            HardwareFault: initialisation failed (the server stays in that fault).
            RequestError: an initialisation is already running.
        """
        if self._closed:
            raise ConnectionClosed("the BIRIS server has stopped")
        self.inbox.send(ResetRequest(0))

    def close(self) -> None:
        """Stop every task, disable the interrupts we enabled, leave no thread behind."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self.supervisor.close()  # first: a task waiting for a reset ends, and nothing is reported
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
        self.admin.bulletin.advance()  # a reader waiting for the epoch looks, and finds it closed
        self.level2.close()
        self.level3.close()
        self.biris_timeout.stop()
        self.motor_watchdog.stop()
        self.elevation_watchdog.stop()
        if self.crate_watch is not None:
            self.crate_watch.close()
        for thread in self._threads:
            if thread is not threading.current_thread():
                self.timebase.join_thread(thread)
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


if TYPE_CHECKING:

    def _is_a_sensor(server: BirisServer) -> Sensor:
        return server  # mypy holds BirisServer to biris_hw.sensor.Sensor
