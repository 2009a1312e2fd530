"""The BIRIS server's administrator: one thread, blocked on nothing but its inbox.

It owns all server state and decides everything; it never sends, never sleeps and never touches
a register. Workers get their orders in *replies*; clients that must wait (wait_idle,
READY_FOR_DATA, reset) are parked and replied to later. "With the arrival of a message at the
server, an appropriate case statement is executed and the server again blocks awaiting the next
request": :meth:`Administrator.run` is that loop, and :meth:`Administrator._cases` maps every
message to its case. The cases live with their topic:

* :mod:`~biris_hw.server.cmd_transfer` -- BIRIS commands, one at a time (``Biris_ready``), and
  the BIRIS timeout;
* :mod:`~biris_hw.server.motor_control` -- the axis workers' reports, BIRIS_HOME,
  BIRIS_MOTOR_PARAMS (every destination through _Scan_limit);
* :mod:`~biris_hw.server.scanning` -- single and continuous scans, NEW_POINT, double-buffered
  data per direction;
* :mod:`~biris_hw.server.elevation` -- SET_ELEVATION: tilts, with the calibration table reloaded;
* :mod:`~biris_hw.server.continuous_mode` -- Appendix D's ring (BI_START_CONTINUOUS);
* :mod:`~biris_hw.server.faults` and :mod:`~biris_hw.server.reset` -- the fault state, reset and
  the initialiser's requests;
* here -- connections, data requests, wait_idle and status, which need no topic of their own.

Their shared fields are in :class:`~biris_hw.server.admin_state.AdminState`, with the operations
one topic asks of another.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from biris_hw.data import ConnectionKind, Direction
from biris_hw.errors import BirisError, RequestError
from biris_hw.ipc import Envelope, TaskStopped
from biris_hw.server import messages as m
from biris_hw.server.admin_state import fail_quietly, log
from biris_hw.server.cmd_transfer import BirisCommands
from biris_hw.server.continuous_mode import ContinuousMode
from biris_hw.server.elevation import Elevation
from biris_hw.server.faults import Faults
from biris_hw.server.motor_control import MotorControl
from biris_hw.server.reset import Reset
from biris_hw.server.scanning import Scanning

__all__ = ["Administrator"]

Case = Callable[[Envelope, Any], None]


class Administrator(
    Scanning, Elevation, ContinuousMode, MotorControl, BirisCommands, Reset, Faults
):
    """State and decisions of the BIRIS server; ``run()`` is the administrator thread."""

    def _cases(self) -> dict[type, Case]:
        """The report's case statements: every message the server receives, and its case."""
        az, el = self.az, self.el
        return {
            # from internal tasks: notifiers, workers, timers
            m.NewPoint: self._on_new_point,  # NEW_POINT
            m.CmdTransferRdy: self._on_cmd_transfer_rdy,  # CMD_TRANSFER_RDY
            m.BirisCmdComplete: self._on_cmd_complete,  # BIRIS_CMD_COMPLETE
            m.AzReady: lambda env, msg: self._on_axis_ready(az, env, msg.error),  # AZ_READY
            m.AzScanDone: lambda env, msg: self._on_axis_done(az, env),  # AZ_SCAN_DONE
            m.ElReady: lambda env, msg: self._on_axis_ready(el, env, msg.error),  # EL_READY
            m.ElScanDone: lambda env, msg: self._on_axis_done(el, env),  # EL_SCAN_DONE
            m.ContinuousLive: self._on_continuous_live,  # CONTINUOUS_LIVE (Appendix D)
            m.SweepDataDone: self._on_sweep_data_done,  # SWEEP_DATA_DONE (Appendix D)
            m.BirisTimeoutErr: self._on_timeout_err,  # BIRIS_TIMEOUT_ERR
            m.MotorWatchdogErr: self._on_watchdog_err,  # beyond the report
            m.BirisBusErr: lambda env, msg: self._task_fault(  # BIRIS_BUS_ERR
                env, "bus", "bus error on the BIRIS VMEbus"
            ),
            m.BirisParityErr: lambda env, msg: self._task_fault(  # BIRIS_PARITY_ERR
                env, "parity", "parity error on the coupler"
            ),
            # from the initialiser
            m.InitCommand: self._on_init_command,
            m.InitMove: self._on_init_move,
            m.InitDone: self._on_init_done,
            # from clients
            m.OpenRequest: self._on_open,  # OPEN_REQUEST
            m.CloseRequest: self._on_close,  # CLOSE_REQUEST
            m.RequestPoint: self._on_request_point,  # REQUEST_POINT
            m.RequestScanData: self._on_request_scan_data,  # REQUEST_SCAN_DATA
            m.TimeoutEnable: self._on_timeout_enable,  # BIRIS_TIMEOUT_ENABLE
            m.TimeoutDisable: self._on_timeout_disable,  # BIRIS_TIMEOUT_DISABLE
            m.BirisMotorParams: self._on_motor_params,  # BIRIS_MOTOR_PARAMS
            m.SingleScanRqst: self._on_single_scan,  # BIRIS_SINGLE_SCAN_RQST
            m.ContScanRqst: self._on_cont_scan,  # BIRIS_CONT_SCAN_RQST
            m.StopScanRqst: self._on_stop_scan,  # BIRIS_STOP_SCAN_RQST
            m.BirisHome: self._on_home,  # BIRIS_HOME
            m.SetElevation: self._on_set_elevation,  # the report's future elevation message
            m.ReadyForData: self._on_ready_for_data,  # READY_FOR_DATA
            m.WaitIdle: self._on_wait_idle,  # beyond the report, as are the two below
            m.ResetRequest: self._on_reset,
            m.StatusRequest: self._on_status,
        }

    # ============================================================================ the loop
    def run(self) -> None:
        handlers = self._cases()
        while True:
            try:
                env = self.inbox.receive()
            except TaskStopped:
                return
            handler = handlers.get(type(env.message))
            if handler is None:
                env.fail(RequestError(f"unknown message {type(env.message).__name__}"))
                continue
            try:
                handler(env, env.message)
            except BirisError as exc:  # RequestError, HardwareFault, ConnectionClosed: the caller's
                fail_quietly(env, exc)
            except Exception as exc:  # a bug must not kill the server silently
                log.exception("administrator: %s failed", type(env.message).__name__)
                fail_quietly(env, exc)

    # ============================================================================ client cases
    def _on_open(self, env: Envelope, msg: m.OpenRequest) -> None:
        conn = self.clients.open(ConnectionKind(msg.kind), msg.policy, msg.depth, msg.owner_ident)
        env.reply((conn.ident, conn.policy, conn.depth))

    def _on_close(self, env: Envelope, msg: m.CloseRequest) -> None:
        self.clients.close(msg.conn)
        env.reply(None)

    def _on_request_point(self, env: Envelope, msg: m.RequestPoint) -> None:
        conn = self._usable_conn(msg.conn)
        self.clients.hand_over(env, conn, self.latest_point)

    def _on_request_scan_data(self, env: Envelope, msg: m.RequestScanData) -> None:
        conn = self._usable_conn(msg.conn)
        self.clients.hand_over(env, conn, self.buffers[Direction(msg.direction)])

    def _on_ready_for_data(self, env: Envelope, msg: m.ReadyForData) -> None:
        conn = self._usable_conn(msg.conn, data=True)
        self.clients.ready(env, conn)

    def _on_wait_idle(self, env: Envelope, msg: m.WaitIdle) -> None:
        self._usable_conn(msg.conn)
        if self.is_idle():
            env.reply(None)
        else:
            self.idle_waiters.append(env)

    def _on_status(self, env: Envelope, msg: m.StatusRequest) -> None:
        env.reply(self.status())

    # ============================================================================ status
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
        counters["dropped_deliveries"] = self.clients.dropped()
        return {
            "state": self.state(),
            "azimuth": self.position,
            "elevation": self.el.position,
            "calibration": self.lut,
            "continuous": self.continuous is not None,
            "acquisition": "continuous" if self.ring_mode else "single",
            "ring": self.ring,
            "counters": counters,
            "connections": self.clients.summaries(),
        }
