"""The motors: the axis workers' reports, BIRIS_HOME and BIRIS_MOTOR_PARAMS.

_az_scan_start reports AZ_READY and is replied its next order; _Biris_az_notifier reports
AZ_SCAN_DONE when the head has come to rest (EL_READY and EL_SCAN_DONE are the same for the tilt
axis). Every destination goes through _Scan_limit in :class:`~biris_hw.server.motion.AxisState`.

Appendix C: BIRIS_HOME "does not force an immediate motor motion unless the motor is stationary
and no motion requests are pending", and during continuous scanning it waits for
BIRIS_STOP_SCAN_RQST; new motor parameters wait the same way. Both then run as trapezoid
profiles, never as a switch to position control in mid-motion.
"""

from __future__ import annotations

from collections.abc import Callable

from biris_hw.ipc import Envelope
from biris_hw.records import MotorParams
from biris_hw.server import messages as m
from biris_hw.server.admin_state import AdminState, ignore_failure
from biris_hw.server.motion import AxisState, Motion

__all__ = ["MotorControl"]


class MotorControl(AdminState):
    """AZ_READY/EL_READY, AZ_SCAN_DONE/EL_SCAN_DONE, the watchdogs, BIRIS_HOME,
    BIRIS_MOTOR_PARAMS."""

    def _submit_motion(self, axis: AxisState, job: Motion) -> None:
        axis.submit(job)
        self._pump_motion(axis)

    def _move(self, axis: AxisState, order: m.MoveOrder, then: Callable[[], None]) -> None:
        """Order a move whose failure needs no action of its own (the fault tells everyone)."""
        self._submit_motion(axis, Motion(order, on_done=lambda err: then(), on_fail=ignore_failure))

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

    # -- BIRIS_HOME and BIRIS_MOTOR_PARAMS ---------------------------------------------------
    def _on_motor_params(self, env: Envelope, msg: m.BirisMotorParams) -> None:
        self._usable_conn(msg.conn)
        if not self._scan_busy() and not self.az.moving():
            self._load_params(msg.params)
        else:
            self.params_pending = msg.params
        env.reply(None)

    def _on_home(self, env: Envelope, msg: m.BirisHome) -> None:
        self._usable_conn(msg.conn)
        if not self._scan_busy() and not self.az.busy() and self.params_pending is None:
            self._go_home()
        else:
            self.home_pending = True
        env.reply(None)

    def _after_motion_settles(self) -> None:
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
            self.az, Motion(m.ParamsOrder(params), on_done=done, on_fail=ignore_failure)
        )

    def _go_home(self) -> None:
        if self.position == 0:
            return
        self.homing = True

        def done() -> None:
            self.homing = False
            self._after_motion_settles()

        self._move(self.az, m.MoveOrder(0), done)
