"""What the BIRIS server's administrator knows, and what its topics ask of one another.

The report's server is one task with one set of variables and a case statement per message. We
keep the one set of variables: every field is here, on the one object that only the administrator
thread touches, so no field needs a lock and none can be half-updated when the next message
arrives. The cases are grouped by topic in sibling modules (mixins of :class:`AdminState`); what
one topic asks of another is declared below as an abstract operation, so every seam between
topics is listed in one place and mypy holds each topic to it.
"""

from __future__ import annotations

import abc
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from biris_hw.data import ConnectionKind, Direction, Point, Scan
from biris_hw.errors import ConnectionClosed, FaultKind, HardwareFault, RequestError
from biris_hw.ipc import Envelope, Mailbox
from biris_hw.records import BirisInitRecord, MotorParams
from biris_hw.server.connections import Connections, fail_quietly
from biris_hw.server.delivery import ClientConn
from biris_hw.server.messages import MoveOrder
from biris_hw.server.motion import AxisState, Motion
from biris_hw.server.scan_assembly import ActiveScan
from biris_hw.server.tasks import DeadlineTimer
from regs.biexec import BiStatus
from regs.tech80 import Axis

__all__ = [
    "AdminState",
    "BirisCommand",
    "Tilt",
    "fail_quietly",
    "ignore_failure",
    "log",
    "status_name",
]

log = logging.getLogger("biris_hw.server.admin")
"""The administrator thread's messages, whichever module writes them: one name to configure."""


def ignore_failure(exc: BaseException) -> None:
    """For jobs whose own failure needs no action: the fault that caused it tells everyone."""


@dataclass
class BirisCommand:
    """One BIEXEC_COM command on its way to BIRIS, and what its completion leads to."""

    code: int
    param: str
    on_done: Callable[[int, bytes], object]
    """Called with STATUS and PARAM when BIRIS_CMD_COMPLETE arrives."""
    n: int = 0
    """Acquisitions a BI_ACQUIRE asks for (0 for any other command)."""
    seq_id: int = 0
    on_fail: Callable[[BaseException], object] = ignore_failure
    token: int = 0
    """Which transfer this is, so a late completion of an abandoned one is recognised."""


def status_name(status: int) -> str:
    """A BIEXEC_COM STATUS's name, for a fault's message."""
    try:
        return BiStatus(status).name
    except ValueError:
        return "error"


@dataclass
class Tilt:
    """A tilt under way: over when the tilt motor has moved *and* BI_LOAD_LUT has loaded."""

    destination: int
    moved: bool = False
    lut: bool = False


class AdminState(abc.ABC):
    """The administrator's fields, the checks every case makes, and the seams between topics."""

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
        self.init_commands: list[BirisCommand] = []
        # workers parked on their last report
        self.transfer_env: Envelope | None = None
        self.cmd_notifier_env: Envelope | None = None
        # BIRIS commands
        self.cmd_queue: deque[BirisCommand] = deque()
        self.current_cmd: BirisCommand | None = None
        self.biris_ready = True
        self.cmd_token = 0
        self.timeout_enabled = False
        self.timeout_gen = -1
        # motion: one record per axis (the tilt's watchdog is the pan's if none is given)
        self.az = AxisState(Axis.AZIMUTH, motor_watchdog, record.motor)
        self.el = AxisState(Axis.ELEVATION, elevation_watchdog or motor_watchdog, record.tilt_motor)
        # scanning
        self.seq_counter = 0
        self.scan: ActiveScan | None = None
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
        self.tilt: Tilt | None = None
        self.elevation_pending: int | None = None
        # continuous acquisition (Appendix D)
        self.ring_mode = record.continuous_acquisition
        self.ring = "off"
        """BIRIS's continuous acquisition: off, starting, live or stopping."""
        self.ring_stop_waiters: list[Callable[[], None]] = []
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
        # clients
        self.clients = Connections(clock, self.counters)
        self.idle_waiters: list[Envelope] = []

    # -- where things stand ------------------------------------------------------------------
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

    def _scan_busy(self) -> bool:
        """A scan runs or waits to start."""
        return self.scan is not None or self.deferred_scan is not None

    def _ready_to_acquire(self) -> bool:
        """No tilt under way, and in continuous acquisition the ring is live."""
        return self.tilt is None and (not self.ring_mode or self.ring == "live")

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

    # -- what every client case checks first -------------------------------------------------
    def _conn(self, ident: int, *, data: bool = False) -> ClientConn:
        """The open connection a client message names (READY_FOR_DATA needs a DATA one)."""
        conn = self.clients.get(ident)
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

    def _usable_conn(self, ident: int, *, data: bool = False) -> ClientConn:
        """:meth:`_conn`, then :meth:`_check_usable`: the start of nearly every client case."""
        conn = self._conn(ident, data=data)
        self._check_usable()
        return conn

    def _check_idle_waiters(self) -> None:
        """Release every wait_idle caller once nothing is under way or waiting."""
        if self.idle_waiters and self.is_idle():
            waiters, self.idle_waiters = self.idle_waiters, []
            for env in waiters:
                env.reply(None)

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

    # -- seams: what the topics ask of one another (each implemented in the module named) ----
    @abc.abstractmethod
    def _submit_command(self, cmd: BirisCommand) -> None:
        """Queue a BIRIS command; issued once BIRIS is ready (cmd_transfer)."""

    @abc.abstractmethod
    def _rearm_timeout(self) -> None:
        """Arm the BIRIS timeout if BIRIS owes an answer, else disarm it (cmd_transfer)."""

    @abc.abstractmethod
    def _note_biris_alive(self) -> None:
        """BIRIS has shown life: restart the BIRIS timeout if it runs (cmd_transfer)."""

    @abc.abstractmethod
    def _submit_motion(self, axis: AxisState, job: Motion) -> None:
        """Queue an order for an axis worker (motor_control)."""

    @abc.abstractmethod
    def _move(self, axis: AxisState, order: MoveOrder, then: Callable[[], None]) -> None:
        """Order a move whose own failure needs no action; ``then`` when it ends (motor_control)."""

    @abc.abstractmethod
    def _after_motion_settles(self) -> None:
        """Run a pending HOME or parameter load once nothing else moves (motor_control)."""

    @abc.abstractmethod
    def _load_params(self, params: MotorParams) -> None:
        """Load new pan motor parameters through the azimuth worker (motor_control)."""

    @abc.abstractmethod
    def _run_deferred(self) -> None:
        """Start a scan that waited for a tilt or for the ring, if it may start now (scanning)."""

    @abc.abstractmethod
    def _start_tilt(self, dest: int) -> None:
        """Tilt to ``dest`` and load its calibration table (elevation)."""

    @abc.abstractmethod
    def _start_ring(self) -> None:
        """BI_START_CONTINUOUS, unless BIRIS already acquires continuously (continuous_mode)."""

    @abc.abstractmethod
    def _stop_ring(self, then: Callable[[], None]) -> None:
        """BI_STOP_CONTINUOUS, then ``then`` (continuous_mode)."""

    @abc.abstractmethod
    def _fault(self, kind: FaultKind, text: str) -> None:
        """Enter the fault state (faults)."""
