"""``Connection``: one method per client message of the report (README.md, "Python API").

A connection is a handle on the server's administrator; every call is a Send that blocks until
the administrator replies. Angles are degrees in and counts out: each motion request returns the
destination actually used after _Scan_limit clamping (and, for the tilt, the elevation limits).

A DATA connection is generic in what READY_FOR_DATA hands out: ``Connection[Scan]`` (the
default, also what a bare ``Connection`` means) for the LATEST and EVERY_BUFFER policies,
``Connection[Point]`` for EVERY_ACQUISITION; ``BirisServer.open`` picks the right one from the
policy, so a type checker knows what ``ready_for_data`` returns.
"""

from __future__ import annotations

import math
from types import TracebackType
from typing import TYPE_CHECKING, Generic, cast

from biris_hw import protocol as m
from biris_hw.angles import deg_to_counts
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Point, Scan
from biris_hw.errors import ConnectionClosed, RequestError
from biris_hw.ipc import Mailbox
from biris_hw.records import MotorParams

if TYPE_CHECKING:  # the default needs PEP 696; at run time a plain TypeVar does the same job
    from typing_extensions import TypeVar

    D = TypeVar("D", Scan, Point, default=Scan)
else:
    from typing import TypeVar

    D = TypeVar("D", Scan, Point)

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


class Connection(Generic[D]):
    """A client's connection to the BIRIS server (NORMAL or DATA)."""

    def __init__(
        self,
        inbox: Mailbox,
        ident: int,
        kind: ConnectionKind,
        policy: DeliveryPolicy = DeliveryPolicy.LATEST,
        depth: int = 1,
    ) -> None:
        self._inbox = inbox
        self.ident = ident
        self.kind = kind
        self.policy = policy
        """What READY_FOR_DATA delivers and what a slow client loses (DATA connections)."""
        self.depth = depth
        """How many buffers (or points) wait for the client at most."""
        self.dropped = 0
        """Buffers (points) this DATA connection missed, as of its last READY_FOR_DATA: replaced
        or pushed out of a full queue because the client was not ready in time, or (points)
        lost by the server. ``server.status()`` has the running figure."""
        self._closed = False

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        policy = f" {self.policy.name}" if self.kind is ConnectionKind.DATA else ""
        return f"<Connection {self.ident} {self.kind.name}{policy} {state}>"

    def _call(self, message: object, timeout: float | None = None) -> object:
        if self._closed:
            raise ConnectionClosed(f"connection {self.ident} is closed")
        return self._inbox.send(message, timeout=timeout)

    # -- data --------------------------------------------------------------------------------
    def request_point(self) -> Point | None:
        """REQUEST_POINT: the latest acquisition (full profile), or None before the first.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: the server is initialising.
        """
        result = self._call(m.RequestPoint(self.ident))
        assert result is None or isinstance(result, Point)
        return result

    def request_scan_data(self, direction: Direction | int) -> Scan | None:
        """REQUEST_SCAN_DATA: the latest complete scan in that direction, or None.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: no such direction, or the server is initialising.
        """
        try:
            d = Direction(direction)
        except ValueError:
            raise RequestError(f"no direction {direction!r}; use Direction.CW or CCW") from None
        result = self._call(m.RequestScanData(self.ident, d))
        assert result is None or isinstance(result, Scan)
        return result

    def ready_for_data(self, timeout: float | None = None) -> D:
        """READY_FOR_DATA: block until the next buffer (DATA connections only).

        A complete Scan under LATEST and EVERY_BUFFER; under EVERY_ACQUISITION the next Point,
        as soon as its acquisition has been read. Either carries ``t_delivered``. Updates
        :attr:`dropped`. Raises TimeoutError when nothing comes within ``timeout`` seconds.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: not a DATA connection, a bad timeout, or a newer READY_FOR_DATA
                superseded this one.
            TimeoutError: nothing came within ``timeout`` seconds.
        """
        result = self._call(m.ReadyForData(self.ident), _timeout(timeout))
        assert isinstance(result, tuple)
        item, dropped = result
        self.dropped = int(dropped)
        assert isinstance(item, (Scan, Point))
        return cast(D, item)  # the server sends what the policy says

    # -- control -----------------------------------------------------------------------------
    def single_scan(self, to_deg: float) -> int:
        """BIRIS_SINGLE_SCAN_RQST: scan to ``to_deg``; returns the destination used (counts).

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: a destination that is not a finite number, the head is already
                there, or a scan or motion is under way.
        """
        dest = _counts(to_deg, "scan destination")
        result = self._call(m.SingleScanRqst(self.ident, dest))
        assert isinstance(result, int)
        return result

    def continuous_scan(self, cw_deg: float, ccw_deg: float) -> tuple[int, int]:
        """BIRIS_CONT_SCAN_RQST: sweep between the limits until stop_scan(); returns them in
        counts after clamping. CW is the lower (clockwise) limit.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: limits that are not finite numbers or the wrong way round, or a
                scan or motion is under way.
        """
        cw = _counts(cw_deg, "CW limit")
        ccw = _counts(ccw_deg, "CCW limit")
        result = self._call(m.ContScanRqst(self.ident, cw, ccw))
        assert isinstance(result, tuple)
        return int(result[0]), int(result[1])

    def set_elevation(self, deg: float) -> int:
        """Tilt the head to ``deg`` (positive looks up); returns the destination used, counts.

        Clamped to the init record's ``elevation_limits_counts``. Returns once accepted; the
        tilt, and the loading of that elevation's calibration table into BIRIS, follow (at the
        end of the sweep under way, if a scan runs), and no acquisition happens meanwhile: a
        scan asked for during a tilt starts when it is over. ``wait_idle`` waits for the tilt.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: an elevation that is not a finite number.
        """
        dest = _counts(deg, "elevation")
        result = self._call(m.SetElevation(self.ident, dest))
        assert isinstance(result, int)
        return result

    def stop_scan(self) -> None:
        """BIRIS_STOP_SCAN_RQST: continuous scanning ends when the current sweep completes.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: the server is initialising.
        """
        self._call(m.StopScanRqst(self.ident))

    def home(self) -> None:
        """BIRIS_HOME: drive to 0 degrees (pending while a scan or motion runs).

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: the server is initialising.
        """
        self._call(m.BirisHome(self.ident))

    def set_motor_params(self, params: MotorParams) -> None:
        """BIRIS_MOTOR_PARAMS: new sample timer, filter and profile limits for the pan motor.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: not a MotorParams, or the server is initialising.
        """
        if not isinstance(params, MotorParams):
            raise RequestError("set_motor_params takes a MotorParams")
        self._call(m.BirisMotorParams(self.ident, params))

    def timeout_enable(self) -> None:
        """BIRIS_TIMEOUT_ENABLE: report BIRIS silence as HardwareFault('timeout').

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: the server is initialising.
        """
        self._call(m.TimeoutEnable(self.ident))

    def timeout_disable(self) -> None:
        """BIRIS_TIMEOUT_DISABLE.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: the server is initialising.
        """
        self._call(m.TimeoutDisable(self.ident))

    def wait_idle(self, timeout: float | None = None) -> None:
        """Block until the motor is stationary, no motion is pending and no acquisition runs.

            Raises:
        ConnectionClosed: this connection or the server is closed.
        HardwareFault: the server is in a fault state (until a reset).
        RequestError: a bad timeout.
        TimeoutError: not idle within ``timeout`` seconds.
        """
        self._call(m.WaitIdle(self.ident), _timeout(timeout))

    def reset(self) -> None:
        """Re-run the server's initialisation: the way back after a HardwareFault.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: initialisation failed (the server stays in that fault).
            RequestError: an initialisation is already running.
        """
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

    def __enter__(self) -> Connection[D]:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
