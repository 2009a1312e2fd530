"""``Connection``: one method per client message of the report (README.md, "Python API").

A connection is a handle on the server's administrator; every call is a Send that blocks until
the administrator replies. Angles are degrees in and counts out: each motion request returns the
destination actually used after _Scan_limit clamping (and, for the tilt, the elevation limits).

Refused means unchanged: every argument is checked here, in the caller's thread, before a message
is sent, so a bad one is a :class:`~biris_hw.errors.RequestError` naming the argument and the
server never hears of it. Numbers may be of any real type (``int``, ``float``, ``Fraction``,
numpy scalars: any ``numbers.Real``, never a bool) and are converted exactly, so a huge finite angle
clamps like any other (``1e308`` degrees is +0x1000 counts) instead of overflowing; NaN,
infinite angles, None and strings are refused. A timeout is None (wait as long as it takes), 0
(poll: the administrator answers at once) or a positive number of seconds (infinity, or more than
``threading.TIMEOUT_MAX``, waits as long as it takes); a negative timeout is refused.

A DATA connection is generic in what READY_FOR_DATA hands out: ``Connection[Scan]`` (the
default, also what a bare ``Connection`` means) for the LATEST and EVERY_BUFFER policies,
``Connection[Point]`` for EVERY_ACQUISITION; ``BirisServer.open`` picks the right one from the
policy, so a type checker knows what ``ready_for_data`` returns.

``ready_for_data`` on an idle sensor costs the administrator nothing once it has said "nothing
waits": the administrator publishes an epoch (:class:`biris_hw.protocol.Bulletin`) that moves
after every message that may change an answer, and while it stays at the epoch of that answer a
poll is answered here and a wait is spent here, waking when the epoch moves. A feed that polls,
or waits in short slices, asks the server only when something has happened.

:class:`Connection` is one of three classes that answer to the :class:`biris_hw.sensor.Connection`
Protocol (with the network's and the replay's); :class:`~biris_hw.sensor.Sensor`, imported here
for the callers that still name it ``biris_hw.client.Sensor``, is defined in :mod:`biris_hw.sensor`.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from fractions import Fraction
from typing import cast

from biris_hw import protocol as m
from biris_hw.angles import RealLike, destination_counts, exact_real, is_real, shown
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Point, Scan
from biris_hw.errors import ConnectionClosed, RequestError
from biris_hw.ipc import Mailbox
from biris_hw.records import MotorParams
from biris_hw.sensor import ConnectionBase, D
from biris_hw.sensor import Sensor as Sensor
from biris_hw.status import ServerStatus, check_change

__all__ = ["Connection", "D", "Sensor", "checked_timeout"]


POLL = 0.0
"""What :func:`checked_timeout` returns for a poll (``timeout=0``)."""


def _is_plus_infinity(value: object) -> bool:
    """True for +inf of any real type; False for NaN, -inf and anything that will not compare."""
    try:
        return bool(value > 0) and bool(value == value)  # type: ignore[operator]
    except (ArithmeticError, TypeError, ValueError):
        return False


def checked_timeout(value: object) -> float | None:
    """A call's ``timeout`` argument, checked: None (no deadline), :data:`POLL`, or seconds.

    Any real number type. A deadline no lock can wait for -- infinity, ``10**400``, or anything
    beyond ``threading.TIMEOUT_MAX`` (some 292 years) -- is no deadline: that is what it means,
    and a lock would raise OverflowError for it.

    Raises:
        RequestError: NaN, a negative number, or not a number. A negative timeout is refused
            rather than taken as a poll: it is nearly always a deadline computed too late, and
            the caller should learn that rather than silently get a different kind of call.
    """
    if value is None:
        return None
    wanted = "timeout: must be None, 0 (poll) or a positive number of seconds"
    if not is_real(value):
        raise RequestError(f"{wanted}, not {type(value).__name__}")
    try:
        seconds: Fraction = exact_real(value, "timeout")
    except RequestError:
        if _is_plus_infinity(value):
            return None
        raise RequestError(f"{wanted}, not {shown(value)}") from None
    if seconds < 0:
        raise RequestError(f"{wanted}, not {shown(value)}")
    if seconds == 0:
        return POLL
    if seconds >= threading.TIMEOUT_MAX:
        return None
    return max(float(seconds), math.ulp(0.0))  # a positive deadline, however small, is not a poll


class Connection(ConnectionBase[D]):
    """A client's connection to the BIRIS server (NORMAL or DATA)."""

    def __init__(
        self,
        inbox: Mailbox,
        ident: int,
        kind: ConnectionKind,
        policy: DeliveryPolicy = DeliveryPolicy.LATEST,
        depth: int = 1,
        bulletin: m.Bulletin | None = None,
    ) -> None:
        super().__init__(ident, kind, policy, depth)
        self._inbox = inbox
        self._bulletin = bulletin
        """The administrator's epoch (:class:`biris_hw.protocol.Bulletin`), when the server gave
        it: lets a poll that cannot have a different answer be answered here."""
        self._empty_at: int | None = None
        """The epoch at which this connection's last timed READY_FOR_DATA ran out."""
        self._polled_empty_at: int | None = None
        """The epoch at which the administrator last answered this connection's poll with
        "nothing waits"."""

    def _call(self, message: object, timeout: float | None = None) -> object:
        self._check_open()
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
        result = self._call(m.RequestScanData(self.ident, self._direction(direction)))
        assert result is None or isinstance(result, Scan)
        return result

    def ready_for_data(self, timeout: RealLike | None = None) -> D:
        """READY_FOR_DATA: block until the next buffer (DATA connections only).

        A complete Scan under LATEST and EVERY_BUFFER; under EVERY_ACQUISITION the next Point,
        as soon as its acquisition has been read. Either carries ``t_delivered``. Updates
        :attr:`dropped`.

        Args:
            timeout: seconds to wait (any real number type); None waits as long as it takes;
                0 polls: what already waits for this connection, or TimeoutError at once,
                answered by the server however busy it is (no deadline of the client's own).

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: not a DATA connection, a timeout that is negative, NaN or not a
                number, or a newer READY_FOR_DATA superseded this one.
            TimeoutError: nothing came within ``timeout`` seconds (at once for a poll).
        """
        seconds = checked_timeout(timeout)
        result = self._poll() if seconds == POLL else self._wait(seconds)
        assert isinstance(result, tuple)
        item, dropped = result
        self.dropped = int(dropped)
        assert isinstance(item, (Scan, Point))
        return cast(D, item)  # the server sends what the policy says

    def _unchanged(self, *, waited: bool = False) -> int | None:
        """The administrator's epoch now, if it is the one at which this connection was last
        told that nothing waits for it (so nothing can have come since); else None. With
        ``waited``, only a timed wait that ran out counts (:meth:`_wait`)."""
        bulletin = self._bulletin
        if bulletin is None or self._inbox.closed:
            return None
        epoch = bulletin.epoch
        if epoch == self._empty_at or (not waited and epoch == self._polled_empty_at):
            return epoch
        return None

    def _moved_from(self, epoch: int) -> Callable[[], bool]:
        """Whether the administrator's epoch has moved from ``epoch`` (or the server stopped)."""
        bulletin, inbox = self._bulletin, self._inbox
        assert bulletin is not None
        return lambda: bulletin.epoch != epoch or inbox.closed

    def _poll(self) -> object:
        """READY_FOR_DATA as a poll: the administrator's answer, or, when it said "nothing
        waits" at the epoch that still holds, that answer again without asking.

        The epoch is read before the request is sent, so a change that races the answer moves
        it on and the next poll asks again: a poll answered here is one whose answer could not
        have been different (nothing was delivered, nothing faulted or closed since).
        """
        self._check_open()
        if self._unchanged() is not None:
            raise TimeoutError(f"no data waiting for connection {self.ident}")  # as the server says
        epoch = None if self._bulletin is None else self._bulletin.epoch
        try:
            return self._call(m.ReadyForData(self.ident, poll=True))
        except TimeoutError:
            self._polled_empty_at = epoch
            raise

    def _wait(self, seconds: float | None) -> object:
        """READY_FOR_DATA with a deadline (or none): parked in the administrator until data
        come, as the report has it -- unless the last wait ran out at the epoch that still
        holds. Then nothing can have come since, and the wait is spent here, for the epoch to
        move, before the administrator is asked again: a reader that waits on an idle sensor in
        short slices (a feed) posts nothing while nothing happens. A poll that found nothing does
        not count: the wait after it is parked in the administrator, which replies the moment
        the data come (a reader that polls, then waits, between acquisitions -- the service's
        feed -- would otherwise pay a round trip more per acquisition)."""
        bulletin = self._bulletin
        while True:
            self._check_open()
            unchanged = self._unchanged(waited=True)
            if unchanged is not None:
                assert bulletin is not None
                try:
                    seconds = bulletin.wait_until(self._moved_from(unchanged), seconds)
                except TimeoutError:
                    raise TimeoutError(f"no data for connection {self.ident} in time") from None
                continue
            epoch = None if bulletin is None else bulletin.epoch
            try:
                return self._call(m.ReadyForData(self.ident), seconds)
            except TimeoutError:
                self._empty_at = epoch
                raise

    # -- control -----------------------------------------------------------------------------
    def single_scan(self, to_deg: RealLike) -> int:
        """BIRIS_SINGLE_SCAN_RQST: scan to ``to_deg``; returns the destination used (counts).

        Args:
            to_deg: the destination in degrees, any real number type; clamped to +-360 degrees
                (+-0x1000 counts), however large.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: a destination that is not a finite real number, the head is already
                there, or a scan or motion is under way.
        """
        dest = destination_counts(to_deg, "to_deg")
        result = self._call(m.SingleScanRqst(self.ident, dest))
        assert isinstance(result, int)
        return result

    def continuous_scan(self, cw_deg: RealLike, ccw_deg: RealLike) -> tuple[int, int]:
        """BIRIS_CONT_SCAN_RQST: sweep between the limits until stop_scan(); returns them in
        counts after clamping. CW is the lower (clockwise) limit.

        Args:
            cw_deg: the clockwise limit in degrees, any real number type; clamped to +-360.
            ccw_deg: the counter-clockwise limit, likewise.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: limits that are not finite real numbers or, once clamped, not the
                right way round (CW below CCW), or a scan or motion is under way.
        """
        cw = destination_counts(cw_deg, "cw_deg")
        ccw = destination_counts(ccw_deg, "ccw_deg")
        result = self._call(m.ContScanRqst(self.ident, cw, ccw))
        assert isinstance(result, tuple)
        return int(result[0]), int(result[1])

    def set_elevation(self, deg: RealLike) -> int:
        """Tilt the head to ``deg`` (positive looks up); returns the destination used, counts.

        Clamped to the init record's ``elevation_limits_counts`` (any real number type, however
        large). Returns once accepted; the tilt, and the loading of that elevation's calibration
        table into BIRIS, follow (at the end of the sweep under way, if a scan runs), and no
        acquisition happens meanwhile: a scan asked for during a tilt starts when it is over.
        ``wait_idle`` waits for the tilt.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: an elevation that is not a finite real number.
        """
        dest = destination_counts(deg, "deg")
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

    def start_continuous(self) -> None:
        """START_CONTINUOUS (Appendix D): acquire continuously into BIRIS's ring from now on.

        Scans then become motor sweeps over a BIRIS that never stops acquiring, so the 240 ms
        start-up is paid once, not per scan. Returns once accepted. With no scan running the
        ring starts at once (``wait_idle`` returns when it is live); while a scan runs, or
        continuous scanning is on, the switch is pending, as BIRIS_HOME is, and takes effect
        when scanning ends: ``status()["acquisition"]`` says the mode in force,
        ``status()["acquisition_pending"]`` a switch that waits, and every :class:`Scan` and
        :class:`Point` the mode it was taken in (``acquisition``). Calling it again changes
        nothing. A reset returns to the init record's ``continuous_acquisition``.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset); nothing changes.
            RequestError: the server is initialising; nothing changes.
        """
        self._call(m.StartContinuous(self.ident))

    def stop_continuous(self) -> None:
        """STOP_CONTINUOUS (Appendix D): cease continuous acquisition immediately.

        Single acquisition (one BI_ACQUIRE per scan) from now on, and a pending
        :meth:`start_continuous` is withdrawn. BIRIS is stopped at once, even in the middle of a
        sweep: that sweep keeps the acquisitions made before the stop and is delivered when the
        head arrives (its ``acquisition`` is ``"continuous"``; it covers only part of its length
        and says so with ``partial``); the motion is not stopped (:meth:`stop_scan` does that),
        and continuous scanning goes on, its next sweeps in single acquisition. Calling it
        again, or in single acquisition, changes nothing.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset); nothing changes.
            RequestError: the server is initialising; nothing changes.
        """
        self._call(m.StopContinuous(self.ident))

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

        ``params`` was checked when it was made: a MotorParams never holds a value outside its
        register, nor a zero gain, max_vel or max_accel (a motor that can never move).

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: not a MotorParams, or the server is initialising.
        """
        if not isinstance(params, MotorParams):
            raise RequestError(
                f"params: set_motor_params takes a MotorParams, not {type(params).__name__}"
            )
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

    def wait_idle(self, timeout: RealLike | None = None) -> None:
        """Block until the motor is stationary, no motion is pending and no acquisition runs.

        Args:
            timeout: seconds to wait (any real number type); None waits as long as it takes;
                0 polls: returns at once if the server is idle, TimeoutError at once if not,
                answered by the server however busy it is (no deadline of the client's own).

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: the server is in a fault state (until a reset).
            RequestError: a timeout that is negative, NaN or not a number.
            TimeoutError: not idle within ``timeout`` seconds (at once for a poll).
        """
        seconds = checked_timeout(timeout)
        if seconds == POLL:
            self._call(m.WaitIdle(self.ident, poll=True))
        else:
            self._call(m.WaitIdle(self.ident), seconds)

    def reset(self) -> None:
        """Re-run the server's initialisation: the way back after a HardwareFault.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            HardwareFault: initialisation failed (the server stays in that fault).
            RequestError: an initialisation is already running.
        """
        self._call(m.ResetRequest(self.ident))

    def status(
        self, *, newer_than: int | None = None, timeout: RealLike | None = None
    ) -> ServerStatus:
        """The server's status (as :meth:`BirisServer.status <biris_hw.BirisServer.status>`),
        asked on this connection: a wait for a newer one (``newer_than``) also ends, with
        ConnectionClosed, when this connection is closed from another thread.

        Raises:
            ConnectionClosed: this connection or the server is closed.
            RequestError: a ``newer_than`` that is not a whole number, or a bad timeout.
            TimeoutError: no newer status within ``timeout`` (at once for a poll).
        """
        self._check_open()
        return status_request(self._inbox, self.ident, newer_than, timeout, self._bulletin)

    # -- lifecycle ---------------------------------------------------------------------------
    def _close(self) -> None:
        try:
            self._call(m.CloseRequest(self.ident))
        except ConnectionClosed:
            pass


def status_request(
    inbox: Mailbox,
    conn: int | None,
    newer_than: int | None,
    timeout: RealLike | None,
    bulletin: m.Bulletin | None = None,
) -> ServerStatus:
    """STATUS sent to ``inbox``: now, or (``newer_than``) once the status has changed since.

    Shared by :meth:`Connection.status` and ``BirisServer.status``, which differ only in the
    connection the request belongs to. With the administrator's ``bulletin`` the wait for a
    change is spent on it, and the administrator is asked once the change has come (or, for a
    request that names a connection, once that connection may have closed): a watcher costs
    nothing while nothing changes. Without one, the request is parked in the administrator.

    Raises:
        RequestError: a ``newer_than`` that is not a whole number, or a bad timeout.
        TimeoutError: no newer status within ``timeout`` (at once for a poll).
    """
    seconds = checked_timeout(timeout)
    after = check_change(newer_than)
    if after is not None and bulletin is not None and bulletin.change <= after:
        if seconds == POLL:
            raise TimeoutError(f"the status has not changed since {after}")
        try:
            seconds = bulletin.wait_until(lambda: bulletin.change > after or inbox.closed, seconds)
        except TimeoutError:
            raise TimeoutError(f"no status newer than change {after} in {timeout} s") from None
    if newer_than is None:
        result = inbox.send(m.StatusRequest(conn))
    elif seconds == POLL:
        result = inbox.send(m.StatusRequest(conn, newer_than, poll=True))
    else:
        try:
            result = inbox.send(m.StatusRequest(conn, newer_than), seconds)
        except TimeoutError:
            raise TimeoutError(
                f"no status newer than change {newer_than} in {seconds:g} s"
            ) from None
    assert isinstance(result, ServerStatus)
    return result
