"""BIRIS_HOME and BIRIS_MOTOR_PARAMS while something else moves: what waits, and for what.

Appendix C: BIRIS_HOME "does not force an immediate motor motion unless the motor is stationary
and no motion requests are pending", and during continuous scanning it waits for
BIRIS_STOP_SCAN_RQST; new motor parameters wait the same way. Both then run as trapezoid
profiles (or a parameter load at rest), never as a switch to position control in mid-motion.
:class:`MotorRequests` owns those pending requests; the administrator runs them once the pan
axis has settled (:meth:`Administrator._after_motion_settles`).
"""

from __future__ import annotations

from biris_hw.records import MotorParams

__all__ = ["MotorRequests"]


class MotorRequests:
    """A HOME or a parameter load waiting for the pan to be free, and a homing under way."""

    def __init__(self) -> None:
        self.home_pending = False
        self.homing = False
        self.params_pending: MotorParams | None = None

    def idle(self) -> bool:
        return not self.home_pending and self.params_pending is None

    def take_params(self) -> MotorParams | None:
        params, self.params_pending = self.params_pending, None
        return params

    def forget(self) -> None:
        """A fault or reset: nothing waits, nothing homes."""
        self.home_pending = self.homing = False
        self.params_pending = None
