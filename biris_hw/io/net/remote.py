"""``connect``: a BIRIS service on Zenoh, used like a local server.

:class:`RemoteSensor` has ``open``/``status``/``close`` like a :class:`~biris_hw.BirisServer`,
and its connections (:class:`RemoteConnection`) the methods, results and errors of a local
:class:`~biris_hw.client.Connection`: arguments are checked here first with the same rules (so a
bad one never leaves the process and changes nothing), each call is one Zenoh query, and the
reply is turned back into the same value or exception. Besides, :meth:`RemoteSensor.subscribe`
receives the service's publications (every acquisition, every scan, status, faults).

A :class:`RemoteSensor` is a :class:`biris_hw.sensor.Sensor`: when it connects it asks the
service once what it serves (``playback``, ``paced``, the init record); ``status(newer_than=...)``
waits for the service's status publications (published when the status changes), so a watcher
asks nothing while nothing changes; ``clock()`` is the newest hardware time seen in a status
reply or a datum's stamp.

**A service that goes away** is noticed through its liveliness token: every call waiting for a
reply is woken and raises :class:`~biris_hw.errors.ConnectionClosed`, as soon as Zenoh notices
the link is gone (the kernel closing a dead process's socket: well under a second), and at the
latest after :data:`~biris_hw.io.net.keys.MAX_WAIT_S` plus :data:`REPLY_MARGIN_S`. Blocking
calls (``ready_for_data``, ``wait_idle``) wait in slices of at most ``MAX_WAIT_S`` for this
reason, however long the caller's timeout.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import struct
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any, Literal, cast, overload

import zenoh

from biris_hw.angles import RealLike, counts_to_deg, destination_counts
from biris_hw.client import POLL, D, checked_timeout
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Point, Scan
from biris_hw.errors import BirisError, ConnectionClosed, RequestError
from biris_hw.io import codec
from biris_hw.io.net.keys import (
    CONTROL_OPS,
    MAX_WAIT_S,
    RESET_WAIT_S,
    Keys,
    check_name,
    raise_error,
)
from biris_hw.io.net.warm import warm
from biris_hw.io.net.zconfig import make_config
from biris_hw.records import BirisInitRecord, MotorParams
from biris_hw.sensor import ConnectionBase
from biris_hw.status import ServerStatus, StatusChanges, check_change

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor

__all__ = ["RemoteConnection", "RemoteSensor", "Subscription", "connect"]

REPLY_MARGIN_S = 5.0
"""How much longer than the service's own bound a call waits for a reply before it gives up."""

CONNECT_TIMEOUT_S = 10.0


class Subscription:
    """One subscription to the service's publications; counts what it missed.

    Each publication carries the service's counter of that kind, so a jump is a publication this
    subscriber never got (Zenoh dropped it rather than slow the sensor): :attr:`dropped`.
    """

    def __init__(self) -> None:
        self.received = 0
        self.dropped = 0
        self._last: dict[str, int] = {}
        self._subscriber: Any = None

    def _count(self, key: str, attachment: zenoh.ZBytes | None) -> None:
        self.received += 1
        if attachment is None:
            return
        raw = attachment.to_bytes()
        if len(raw) != 8:
            return
        (number,) = struct.unpack("<Q", raw)
        last = self._last.get(key)
        if last is not None and number > last + 1:
            self.dropped += number - last - 1
        self._last[key] = number

    def close(self) -> None:
        """Stop receiving (idempotent)."""
        if self._subscriber is not None:
            with contextlib.suppress(Exception):
                self._subscriber.undeclare()
            self._subscriber = None

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RemoteSensor:
    """A BIRIS service reached over Zenoh (made by :func:`connect`)."""

    def __init__(
        self,
        name: str,
        endpoints: Sequence[str] | None = None,
        user: str | None = None,
        password: str | None = None,
        *,
        multicast: bool | None = None,
        options: dict[str, Any] | None = None,
        timeout: float = CONNECT_TIMEOUT_S,
        reader_credentials: bool = False,
    ) -> None:
        self.name = check_name(name, "name")
        self.keys = Keys(self.name)
        self.client = uuid.uuid4().hex
        """This client's id: its liveliness token and the ``client`` of each request."""
        self.reader_credentials = bool(reader_credentials)
        """Send the credentials with reads too (for a service that requires reader credentials);
        otherwise they go only with control operations, never with status, open or reads."""
        self._credentials: dict[str, str] = {}
        if user is not None or password is not None:
            if not isinstance(user, str) or not isinstance(password, str):
                raise RequestError("user and password go together, both strings")
            self._credentials = {"user": user, "password": password}
        self._closed = False
        self._alive = threading.Event()
        self._gone = threading.Event()
        self._waiters: set[_Waiter] = set()
        self._lock = threading.Lock()
        self._connections: list[RemoteConnection[Any]] = []
        self._news = threading.Condition()
        """Guards what the status publications tell (:meth:`status` with ``newer_than`` waits
        on it), and is notified when the service goes, this object closes, or a connection
        closes under a wait."""
        self._changes = StatusChanges()
        self._latest: ServerStatus | None = None
        self._clock_s = 0.0
        self.playback = False
        """The service serves a recording (it says so when we connect)."""
        self.paced = True
        """The service's sensor keeps its own pace (it says so when we connect)."""
        self.record: BirisInitRecord | None = None
        """The init record of the service's sensor, as the service said when we connected."""
        self._status_sub: Any = None
        endpoints = list(endpoints or [])
        config = make_config(
            connect=endpoints,
            multicast=(not endpoints) if multicast is None else multicast,
            options=options,
        )
        try:
            self._session = zenoh.open(config)
        except Exception as exc:  # zenoh.ZError: a malformed endpoint, a TLS file missing...
            raise RequestError(f"cannot start the Zenoh session: {exc}") from exc
        try:
            self._service_sub = self._session.liveliness().declare_subscriber(
                self.keys.service_token, self._on_service_token, history=True
            )
            self._token = self._session.liveliness().declare_token(
                self.keys.client_token(self.client)
            )
            if not self._alive.wait(timeout):
                where = ", ".join(endpoints) or "multicast scouting"
                raise ConnectionClosed(
                    f"no BIRIS service {self.name!r} answered within {timeout:g} s ({where})"
                )
            self._status_sub = self._session.declare_subscriber(
                self.keys.status, self._on_status_sample
            )
            self._learn()
        except BaseException:
            self._session.close()  # type: ignore[no-untyped-call]
            raise

    def _learn(self) -> None:
        """Ask the service what it serves (a recording? paced? its init record) and take its
        status as the one the publications are compared with. A service that says nothing of
        the kind (an older one) serves a live sensor whose record is unknown."""
        try:
            payload, _, attachment = self._query("status", {"info": True})
        except (BirisError, TimeoutError):  # a service that wants reader credentials we do not
            return  # send, a sensor closed behind it: the calls that need them will say so
        info = self._attachment(attachment)
        playback, paced = info.get("playback"), info.get("paced")
        self.playback = playback if isinstance(playback, bool) else False
        self.paced = paced if isinstance(paced, bool) else True
        record = info.get("record")
        if isinstance(record, dict):
            try:
                self.record = BirisInitRecord.from_dict(record)
            except (ValueError, TypeError, BirisError):
                self.record = None
        status = codec.decode_status(payload)
        with self._news:
            if self._latest is None:  # no publication has come meanwhile
                self._changes.see(status.signature())
                self._latest = dataclasses.replace(status, change=self._changes.change)

    def _attachment(self, attachment: bytes | None) -> dict[str, Any]:
        """A status reply's attachment (JSON: the sensor's clock, and what :meth:`_learn`
        asked), the clock noted; {} when there is none or it does not read."""
        if attachment is None:
            return {}
        try:
            info = json.loads(attachment)
        except ValueError:
            return {}
        if not isinstance(info, dict):
            return {}
        clock = info.get("clock")
        if isinstance(clock, (int, float)) and not isinstance(clock, bool):
            self._saw(float(clock))
        return info

    def _saw(self, t: float) -> None:
        """A hardware time the service's sensor has reached (a status, an item's stamp)."""
        with self._news:
            if t > self._clock_s:
                self._clock_s = t

    def _on_status_sample(self, sample: zenoh.Sample) -> None:
        """A status publication (Zenoh's thread): the newest status, numbered if it says
        something new, and the waiters woken."""
        try:
            status = codec.decode_status(sample.payload.to_bytes())
        except codec.WireError:
            return
        with self._news:
            changed = self._changes.see(status.signature())
            self._latest = dataclasses.replace(status, change=self._changes.change)
            if changed:
                self._news.notify_all()

    def _wake(self) -> None:
        """Every status wait looks again (the service went, we closed, a connection closed)."""
        with self._news:
            self._news.notify_all()

    def _on_service_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._gone.clear()
            self._alive.set()
            return
        self._gone.set()
        with self._lock:
            waiters = list(self._waiters)
        for waiter in waiters:
            waiter.wake()
        self._wake()

    @property
    def gone(self) -> bool:
        """The service has gone (its liveliness token was withdrawn)."""
        return self._gone.is_set()

    # -- requests --------------------------------------------------------------------------------
    def _query(
        self, op: str, body: dict[str, Any], wait_s: float = 0.0
    ) -> tuple[bytes, str, bytes | None]:
        """One request; (payload, encoding, attachment) of the reply, or its error raised."""
        if self._closed:
            raise ConnectionClosed(f"the connection to service {self.name!r} is closed")
        if self._gone.is_set():
            raise ConnectionClosed(f"service {self.name!r} has gone")
        request: dict[str, Any] = {**body, "client": self.client}
        if op in CONTROL_OPS or self.reader_credentials:
            request.update(self._credentials)
        waiter = _Waiter()
        with self._lock:
            self._waiters.add(waiter)
        try:
            self._session.get(
                self.keys.rpc(op),
                zenoh.handlers.Callback(waiter.reply, waiter.done),
                payload=json.dumps(request).encode(),
                encoding=zenoh.Encoding.APPLICATION_JSON,
                timeout=wait_s + REPLY_MARGIN_S,
            )
            reply = waiter.wait(wait_s + 2 * REPLY_MARGIN_S)
        finally:
            with self._lock:
                self._waiters.discard(waiter)
        if reply is None:
            if self._gone.is_set() or self._closed:
                raise ConnectionClosed(f"service {self.name!r} has gone ({op} not answered)")
            raise TimeoutError(f"{op}: no reply from service {self.name!r}")
        ok = reply.ok
        if ok is None:
            err = reply.err
            raise_error(err.payload.to_bytes() if err is not None else b"", op)
            raise AssertionError("unreachable")  # raise_error always raises
        attachment = ok.attachment
        return (
            ok.payload.to_bytes(),
            str(ok.encoding),
            attachment.to_bytes() if attachment is not None else None,
        )

    def _json(self, op: str, body: dict[str, Any], wait_s: float = 0.0) -> Any:
        payload, _, _ = self._query(op, body, wait_s)
        try:
            return json.loads(payload)
        except ValueError:
            raise RequestError(f"{op}: unreadable reply from the service") from None

    # -- the server's API ------------------------------------------------------------------------
    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.EVERY_ACQUISITION],
        depth: int | None = ...,
    ) -> RemoteConnection[Point]: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.LATEST, DeliveryPolicy.EVERY_BUFFER] = ...,
        depth: int | None = ...,
    ) -> RemoteConnection[Scan]: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: DeliveryPolicy,
        depth: int | None = ...,
    ) -> RemoteConnection[Scan] | RemoteConnection[Point]: ...

    def open(
        self,
        kind: ConnectionKind = ConnectionKind.NORMAL,
        *,
        policy: DeliveryPolicy = DeliveryPolicy.LATEST,
        depth: int | None = None,
    ) -> RemoteConnection[Scan] | RemoteConnection[Point]:
        """A connection on the service's server, as ``BirisServer.open`` gives one.

        Raises:
            RequestError: a kind, policy or depth the server refuses.
            ConnectionClosed: the service has gone, or this object is closed.
            AccessDenied: the service requires reader credentials and has none from us.
        """
        try:
            kind = ConnectionKind(kind)
            policy = DeliveryPolicy(policy)
        except ValueError:
            raise RequestError(f"open: no kind {kind!r} or policy {policy!r}") from None
        answer = self._json("open", {"kind": kind.name, "policy": policy.value, "depth": depth})
        if kind is ConnectionKind.DATA:  # the codec's first use here, not on the first item
            warm("point" if policy is DeliveryPolicy.EVERY_ACQUISITION else "scan")
        try:
            token, ident, depth_used = (
                str(answer["conn"]),
                int(answer["ident"]),
                int(answer["depth"]),
            )
        except (KeyError, TypeError, ValueError):
            raise RequestError("open: unreadable reply from the service") from None
        conn: RemoteConnection[Any] = RemoteConnection(self, ident, kind, policy, depth_used, token)
        with self._lock:
            self._connections.append(conn)
        return conn

    def status(
        self, *, newer_than: int | None = None, timeout: RealLike | None = None
    ) -> ServerStatus:
        """The service's sensor's status; with ``newer_than``, the push.

        Now: one query. ``newer_than`` (a status's ``change``): waits, up to ``timeout``, for a
        status publication that says something new since -- the service publishes the status
        when it changes (and unchanged every ``status_period`` seconds, which wakes nobody).
        ``change`` is numbered here, by this object, for the publications it has received: a
        status asked for now carries the number of the newest one. So a wait right after such a
        status may be woken once by the publication of that same state, still on its way when
        the status was asked for (a wake to be read as "look again", as a condition's is).

        Raises:
            ConnectionClosed: the service has gone, or this object is closed.
            RequestError: a ``newer_than`` that is not a whole number, or a bad timeout.
            TimeoutError: no newer status within ``timeout``.
        """
        return self._status(newer_than, timeout, None)

    def _status(
        self, newer_than: object, timeout: object, conn: RemoteConnection[Any] | None
    ) -> ServerStatus:
        """:meth:`status`; asked on ``conn``, the wait also ends when ``conn`` closes."""
        seconds = checked_timeout(timeout)
        after = check_change(newer_than)
        if after is None:
            payload, _, attachment = self._query("status", {})
            self._attachment(attachment)
            status = codec.decode_status(payload)
            with self._news:
                return dataclasses.replace(status, change=self._changes.change)
        deadline = None if seconds is None else time.monotonic() + seconds
        with self._news:
            while True:
                if self._closed:
                    raise ConnectionClosed(f"the connection to service {self.name!r} is closed")
                if self._gone.is_set():
                    raise ConnectionClosed(f"service {self.name!r} has gone")
                if conn is not None and conn.closed:
                    raise ConnectionClosed(f"connection {conn.ident} is closed")
                latest = self._latest
                if latest is not None and self._changes.change > after:
                    return latest
                left = None if deadline is None else deadline - time.monotonic()
                if seconds == POLL or (left is not None and left <= 0):
                    raise TimeoutError(f"the status of {self.name!r} has not changed since {after}")
                self._news.wait(left)

    def clock(self) -> float:
        """The newest hardware time the service's sensor has been seen at (in a status reply
        or a datum's stamp); 0.0 before any."""
        with self._news:
            return self._clock_s

    def subscribe(
        self,
        what: Literal["point", "scan", "status", "fault"],
        callback: Callable[[Any], None],
        *,
        direction: Direction | None = None,
    ) -> Subscription:
        """Call ``callback`` with every publication of ``what``: a Point per acquisition, a Scan
        per completed scan (of ``direction``, or both), a ServerStatus, a HardwareFault.

        The callback runs on a Zenoh thread: keep it short (hand work to a queue). A payload
        that does not decode is counted in the subscription's ``dropped`` and skipped.
        """
        decode: Callable[[bytes], Any]
        keys = self.keys
        if what == "point":
            key, decode = keys.point, codec.decode_point
        elif what == "scan":
            key = keys.scans if direction is None else keys.scan(Direction(direction).name.lower())
            decode = codec.decode_scan
        elif what == "status":
            key, decode = keys.status, codec.decode_status
        elif what == "fault":
            key, decode = keys.fault, codec.decode_fault
        else:
            raise RequestError(f"subscribe: nothing called {what!r}")
        # the codec's first use costs ~0.1 s of interpreter time: paid here, on the caller's
        # thread, rather than by the first publications, which would queue behind it
        warm(what)
        subscription = Subscription()

        def on_sample(sample: zenoh.Sample) -> None:
            subscription._count(str(sample.key_expr), sample.attachment)
            try:
                value = decode(sample.payload.to_bytes())
            except codec.WireError:
                subscription.dropped += 1
                return
            callback(value)

        subscription._subscriber = self._session.declare_subscriber(key, on_sample)
        return subscription

    def close(self) -> None:
        """Close every connection opened here, then leave (idempotent)."""
        if self._closed:
            return
        with self._lock:
            connections = list(self._connections)
        if not self._gone.is_set():
            for conn in connections:
                with contextlib.suppress(BirisError, TimeoutError):
                    conn.close()
        self._closed = True
        with self._lock:
            waiters = list(self._waiters)
        for waiter in waiters:
            waiter.wake()
        self._wake()
        if self._status_sub is not None:
            with contextlib.suppress(Exception):
                self._status_sub.undeclare()
            self._status_sub = None
        self._session.close()  # type: ignore[no-untyped-call]

    def __enter__(self) -> RemoteSensor:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class _Waiter:
    """The reply to one query, handed from Zenoh's thread to the caller's."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._reply: zenoh.Reply | None = None
        self._over = False

    def reply(self, reply: zenoh.Reply) -> None:
        with self._cond:
            if self._reply is None:
                self._reply = reply
            self._cond.notify_all()

    def done(self) -> None:
        self.wake()

    def wake(self) -> None:
        with self._cond:
            self._over = True
            self._cond.notify_all()

    def wait(self, timeout: float) -> zenoh.Reply | None:
        with self._cond:
            self._cond.wait_for(lambda: self._reply is not None or self._over, timeout)
            return self._reply


class RemoteConnection(ConnectionBase[D]):
    """A connection through the service: the methods, results and errors of a local one."""

    def __init__(
        self,
        sensor: RemoteSensor,
        ident: int,
        kind: ConnectionKind,
        policy: DeliveryPolicy,
        depth: int,
        token: str,
    ) -> None:
        super().__init__(ident, kind, policy, depth)
        self._sensor = sensor
        self._token = token
        """What names it to the service: only its holder may use or close it."""

    def _where(self) -> str:
        return f"{self._sensor.name}:"

    def _call(self, op: str, body: dict[str, Any] | None = None, wait_s: float = 0.0) -> Any:
        self._check_open()
        return self._sensor._json(op, {"conn": self._token, **(body or {})}, wait_s)

    def _data(self, op: str, body: dict[str, Any], wait_s: float = 0.0) -> Any:
        self._check_open()
        payload, encoding, attachment = self._sensor._query(
            op, {"conn": self._token, **body}, wait_s
        )
        if attachment is not None:
            with contextlib.suppress(ValueError, KeyError, TypeError):
                self.dropped = int(json.loads(attachment)["dropped"])
        if encoding.endswith(codec.SCAN):
            scan = codec.decode_scan(payload)
            if scan.n_acq:
                self._sensor._saw(float(scan.t[-1]))
            return scan
        if encoding.endswith(codec.POINT):
            point = codec.decode_point(payload)
            self._sensor._saw(float(point.t))
            return point
        if json.loads(payload) is None:
            return None
        raise RequestError(f"{op}: unexpected reply of type {encoding}")

    # -- data ------------------------------------------------------------------------------------
    def request_point(self) -> Point | None:
        """REQUEST_POINT (see :meth:`biris_hw.client.Connection.request_point`)."""
        return cast("Point | None", self._data("request_point", {}))

    def request_scan_data(self, direction: Direction | int) -> Scan | None:
        """REQUEST_SCAN_DATA (see :meth:`biris_hw.client.Connection.request_scan_data`)."""
        d = self._direction(direction)
        return cast("Scan | None", self._data("request_scan_data", {"direction": int(d)}))

    def ready_for_data(self, timeout: RealLike | None = None) -> D:
        """READY_FOR_DATA (see :meth:`biris_hw.client.Connection.ready_for_data`).

        Waits in slices of at most MAX_WAIT_S on the service, so that a service that dies is
        noticed whatever ``timeout`` is.
        """
        return cast(D, self._blocking("ready_for_data", timeout))

    def _blocking(self, op: str, timeout: RealLike | None) -> Any:
        seconds = checked_timeout(timeout)
        if seconds == POLL:
            return self._data(op, {"timeout": 0})
        deadline = None if seconds is None else time.monotonic() + seconds
        while True:
            left = MAX_WAIT_S if deadline is None else deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"{op}: nothing within {seconds:g} s")
            wait = min(left, MAX_WAIT_S)
            try:
                return self._data(op, {"timeout": wait}, wait)
            except TimeoutError:
                if deadline is not None and time.monotonic() >= deadline:
                    raise

    # -- control ---------------------------------------------------------------------------------
    def single_scan(self, to_deg: RealLike) -> int:
        """BIRIS_SINGLE_SCAN_RQST; returns the destination used (counts)."""
        dest = destination_counts(to_deg, "to_deg")
        return int(self._call("single_scan", {"to_deg": counts_to_deg(dest)})["counts"])

    def continuous_scan(self, cw_deg: RealLike, ccw_deg: RealLike) -> tuple[int, int]:
        """BIRIS_CONT_SCAN_RQST; returns the limits used (counts)."""
        cw = destination_counts(cw_deg, "cw_deg")
        ccw = destination_counts(ccw_deg, "ccw_deg")
        answer = self._call(
            "continuous_scan", {"cw_deg": counts_to_deg(cw), "ccw_deg": counts_to_deg(ccw)}
        )
        return int(answer["cw"]), int(answer["ccw"])

    def set_elevation(self, deg: RealLike) -> int:
        """Tilt the head; returns the destination used (counts)."""
        dest = destination_counts(deg, "deg")
        return int(self._call("set_elevation", {"deg": counts_to_deg(dest)})["counts"])

    def stop_scan(self) -> None:
        self._call("stop_scan")

    def start_continuous(self) -> None:
        self._call("start_continuous")

    def stop_continuous(self) -> None:
        self._call("stop_continuous")

    def home(self) -> None:
        self._call("home")

    def set_motor_params(self, params: MotorParams) -> None:
        """BIRIS_MOTOR_PARAMS (a :class:`~biris_hw.records.MotorParams`)."""
        if not isinstance(params, MotorParams):
            raise RequestError(
                f"params: set_motor_params takes a MotorParams, not {type(params).__name__}"
            )
        fields = ("sample", "zero", "pole", "gain", "max_vel", "max_accel")
        self._call("set_motor_params", {"params": {f: getattr(params, f) for f in fields}})

    def timeout_enable(self) -> None:
        self._call("timeout_enable")

    def timeout_disable(self) -> None:
        self._call("timeout_disable")

    def wait_idle(self, timeout: RealLike | None = None) -> None:
        """Block until the server is idle (see :meth:`biris_hw.client.Connection.wait_idle`)."""
        self._blocking("wait_idle", timeout)

    def reset(self) -> None:
        """Re-run the server's initialisation (see :meth:`biris_hw.client.Connection.reset`).

        Waits as long as an initialisation may take (:data:`~biris_hw.io.net.keys.
        RESET_WAIT_S`), not a blocking read's slice: the reset carries on in the server
        whatever the caller does, and one that fails raises its HardwareFault here. A service
        that goes away meanwhile still raises ConnectionClosed at once.
        """
        self._call("reset", wait_s=RESET_WAIT_S)

    def status(
        self, *, newer_than: int | None = None, timeout: RealLike | None = None
    ) -> ServerStatus:
        """The service's sensor's status (:meth:`RemoteSensor.status`); a wait for a newer one
        also ends, with ConnectionClosed, when this connection is closed."""
        self._check_open()
        return self._sensor._status(newer_than, timeout, self)

    # -- lifecycle -------------------------------------------------------------------------------
    def _close(self) -> None:
        # closed here first: a status wait on this connection ends with ConnectionClosed, not
        # with the publication of the change the close itself makes
        self._closed = True
        self._sensor._wake()
        try:
            self._sensor._json("close", {"conn": self._token})
        except (ConnectionClosed, TimeoutError):
            pass


if TYPE_CHECKING:

    def _is_a_sensor(remote: RemoteSensor) -> Sensor:
        return remote  # mypy holds RemoteSensor to biris_hw.sensor.Sensor


def connect(
    name: str,
    endpoints: Sequence[str] | None = None,
    user: str | None = None,
    password: str | None = None,
    **options: Any,
) -> RemoteSensor:
    """The BIRIS service ``name`` (DESIGN.md 3b); blocks until it answers.

    Args:
        name: the service's name (``biris serve --name``).
        endpoints: Zenoh endpoints to connect to (``tcp/robot:7447``); none means multicast
            scouting finds it on the local network.
        user, password: a controller's credentials, needed for motion and configuration; sent
            with control operations only (unless ``reader_credentials``).
        multicast: (keyword) scouting on or off (default: on only without endpoints).
        options: (keyword) further Zenoh settings ``{"key/path": value}``: for TLS the root CA,
            ``{"transport/link/tls/root_ca_certificate": "ca.pem"}``.
        timeout: (keyword) seconds to wait for the service (default 10).
        reader_credentials: (keyword) send the credentials with every request, reads included:
            for a service that requires reader credentials (default False: a password goes to
            the service only when it is needed, with a control operation).

    Raises:
        ConnectionClosed: no such service answered in time.
    """
    return RemoteSensor(name, endpoints, user, password, **options)
