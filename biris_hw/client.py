"""``Connection``: one method per client message of the report (DESIGN.md section 3).

A connection is a handle on the server's administrator; every call is a Send that blocks until
the administrator replies. Angles are degrees in and counts out: each motion request returns the
destination actually used after _Scan_limit clamping.
"""

from __future__ import annotations

import math
import threading
from types import TracebackType

from biris_hw.angles import deg_to_counts
from biris_hw.data import ConnectionKind, Direction, Point, Scan
from biris_hw.errors import ConnectionClosed, RequestError
from biris_hw.ipc import Mailbox
from biris_hw.records import MotorParams
from biris_hw.server import messages as m

__all__ = ["Connection"]


def _counts(value: float, what: str) -> int:
    try:
        return deg_to_counts(value)
    except ValueError as exc:
        raise RequestError(f"{what}: {exc}") from None


def _timeout(value: float | None) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
        raise RequestError(f"timeout must be a number of seconds, not {value!r}")
    return max(0.0, float(value))


class Connection:
    """A client's connection to the BIRIS server (NORMAL or DATA)."""

    def __init__(self, inbox: Mailbox, ident: int, kind: ConnectionKind) -> None:
        self._inbox = inbox
        self.ident = ident
        self.kind = kind
        self.owner = threading.current_thread()
        self.dropped = 0
        """Buffers this DATA connection missed because it was not ready in time."""
        self._closed = False

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<Connection {self.ident} {self.kind.name} {state}>"

    def _call(self, message: object, timeout: float | None = None) -> object:
        if self._closed:
            raise ConnectionClosed(f"connection {self.ident} is closed")
        return self._inbox.send(message, timeout=timeout)

    # -- data --------------------------------------------------------------------------------
    def request_point(self) -> Point | None:
        """REQUEST_POINT: the latest acquisition (full profile), or None before the first."""
        result = self._call(m.RequestPoint(self.ident))
        assert result is None or isinstance(result, Point)
        return result

    def request_scan_data(self, direction: Direction | int) -> Scan | None:
        """REQUEST_SCAN_DATA: the latest complete scan in that direction, or None."""
        try:
            d = Direction(direction)
        except ValueError:
            raise RequestError(f"no direction {direction!r}; use Direction.CW or CCW") from None
        result = self._call(m.RequestScanData(self.ident, d))
        assert result is None or isinstance(result, Scan)
        return result

    def ready_for_data(self, timeout: float | None = None) -> Scan:
        """READY_FOR_DATA: block until the next complete buffer (DATA connections only).

        Raises TimeoutError when none completes within ``timeout`` seconds.
        """
        result = self._call(m.ReadyForData(self.ident), _timeout(timeout))
        assert isinstance(result, tuple)
        scan, dropped = result
        self.dropped = int(dropped)
        assert isinstance(scan, Scan)
        return scan

    # -- control -----------------------------------------------------------------------------
    def single_scan(self, to_deg: float) -> int:
        """BIRIS_SINGLE_SCAN_RQST: scan to ``to_deg``; returns the destination used (counts)."""
        dest = _counts(to_deg, "scan destination")
        result = self._call(m.SingleScanRqst(self.ident, dest))
        assert isinstance(result, int)
        return result

    def continuous_scan(self, cw_deg: float, ccw_deg: float) -> tuple[int, int]:
        """BIRIS_CONT_SCAN_RQST: sweep between the limits until stop_scan(); returns them in
        counts after clamping. CW is the lower (clockwise) limit."""
        cw = _counts(cw_deg, "CW limit")
        ccw = _counts(ccw_deg, "CCW limit")
        result = self._call(m.ContScanRqst(self.ident, cw, ccw))
        assert isinstance(result, tuple)
        return int(result[0]), int(result[1])

    def stop_scan(self) -> None:
        """BIRIS_STOP_SCAN_RQST: continuous scanning ends when the current sweep completes."""
        self._call(m.StopScanRqst(self.ident))

    def home(self) -> None:
        """BIRIS_HOME: drive to 0 degrees (pending while a scan or motion runs)."""
        self._call(m.BirisHome(self.ident))

    def set_motor_params(self, params: MotorParams) -> None:
        """BIRIS_MOTOR_PARAMS: new sample timer, filter and profile limits for the pan motor."""
        if not isinstance(params, MotorParams):
            raise RequestError("set_motor_params takes a MotorParams")
        self._call(m.BirisMotorParams(self.ident, params))

    def timeout_enable(self) -> None:
        """BIRIS_TIMEOUT_ENABLE: report BIRIS silence as HardwareFault('timeout')."""
        self._call(m.TimeoutEnable(self.ident))

    def timeout_disable(self) -> None:
        """BIRIS_TIMEOUT_DISABLE."""
        self._call(m.TimeoutDisable(self.ident))

    def wait_idle(self, timeout: float | None = None) -> None:
        """Block until the motor is stationary, no motion is pending and no acquisition runs.

        Raises TimeoutError when that does not happen within ``timeout`` seconds.
        """
        self._call(m.WaitIdle(self.ident), _timeout(timeout))

    def reset(self) -> None:
        """Re-run the server's initialisation: the way back after a HardwareFault."""
        self._call(m.ResetRequest(self.ident))

    # -- lifecycle ---------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """CLOSE_REQUEST; calling it again does nothing."""
        if self._closed:
            return
        try:
            self._call(m.CloseRequest(self.ident))
        except ConnectionClosed:
            pass
        finally:
            self._closed = True

    def __enter__(self) -> Connection:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
