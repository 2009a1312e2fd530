"""``serve``: one BirisServer made available on Zenoh, for several readers and its controllers.

The service is a client of the server like any other (DESIGN.md section 2, "outside world"): it
holds local :class:`~biris_hw.client.Connection` objects on behalf of remote clients and three
of its own that feed the publications, and never reaches into the server. So whatever the
server guarantees a local client -- refused requests change nothing, a slow DATA connection
loses the oldest buffers and counts them -- holds for a remote one by construction.

Threads and why:

* Zenoh delivers queries on its own thread; that thread only reads and admits them (size,
  JSON, rate and in-flight limits per client), so a flood from one client is answered "Busy"
  cheaply and never queues behind the sensor. Admitted requests run on a bounded worker pool,
  because some block (READY_FOR_DATA, wait_idle: at most :data:`~biris_hw.net.protocol.
  MAX_WAIT_S` each).
* Two feed threads read the service's own DATA connections (every acquisition, every buffer)
  and publish with ``CongestionControl.DROP``: a subscriber that cannot keep up loses samples
  (each carries a publication counter, so it can count them), it never slows the feed, and the
  feed's own queue in the server is bounded and counted like any DATA connection's.
* A status thread publishes the status when it changes and every ``status_period`` seconds,
  and a fault when the server enters one.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import hmac
import json
import logging
import struct
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, overload

import zenoh

from biris_hw import wire
from biris_hw.client import Connection
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Point, Scan
from biris_hw.errors import (
    AccessDenied,
    BirisError,
    ConnectionClosed,
    HardwareFault,
    RequestError,
)
from biris_hw.net.protocol import (
    CONTROL_OPS,
    MAX_REQUEST,
    MAX_WAIT_S,
    OPS,
    BadRequest,
    Busy,
    Keys,
    check_name,
    error_payload,
)
from biris_hw.net.warm import warm_all
from biris_hw.net.zconfig import make_config
from biris_hw.records import MotorParams
from biris_hw.status import ServerState, ServerStatus

__all__ = ["Sensor", "Service", "serve"]

log = logging.getLogger(__name__)

JSON = zenoh.Encoding.APPLICATION_JSON

MAX_INFLIGHT_PER_CLIENT = 8
"""Requests of one client being worked on at once; more are answered Busy. Enough for a few
DATA connections blocked in READY_FOR_DATA beside a NORMAL one."""

RATE_PER_CLIENT = 1000.0
"""Requests per second one client may make on average (a token bucket of :data:`BURST`)."""

BURST = 2000.0

MAX_CONNECTIONS_PER_CLIENT = 32
"""Open connections one client may hold: each costs the server a queue."""

WORKERS = 64
"""Worker threads of the service (requests being worked on, all clients together)."""

FEED_DEPTH = 1024
"""Queue of the service's own every-acquisition feed in the server (34 s at 30 Hz)."""


class Sensor(Protocol):
    """What the service (and every ``biris`` command) needs of a sensor: a BirisServer, a
    remote one, or a replayed recording."""

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.EVERY_ACQUISITION],
        depth: int | None = ...,
    ) -> Any: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.LATEST, DeliveryPolicy.EVERY_BUFFER] = ...,
        depth: int | None = ...,
    ) -> Any: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: DeliveryPolicy,
        depth: int | None = ...,
    ) -> Any: ...

    def status(self) -> ServerStatus: ...

    def close(self) -> None: ...


@dataclass
class _Client:
    """What the service knows of one remote client."""

    ident: str
    connections: dict[int, Connection[Any]] = field(default_factory=dict)
    inflight: int = 0
    tokens: float = BURST
    refilled: float = field(default_factory=time.monotonic)
    refused: int = 0
    """Requests answered Busy (a flood)."""

    def admit(self, now: float) -> bool:
        """Take one request token and an in-flight slot, or say no (and count it)."""
        self.tokens = min(BURST, self.tokens + (now - self.refilled) * RATE_PER_CLIENT)
        self.refilled = now
        if self.tokens < 1.0 or self.inflight >= MAX_INFLIGHT_PER_CLIENT:
            self.refused += 1
            return False
        self.tokens -= 1.0
        self.inflight += 1
        return True


def _credentials(table: Mapping[str, str] | None, what: str) -> dict[str, str] | None:
    if table is None:
        return None
    checked: dict[str, str] = {}
    for user, password in table.items():
        if not isinstance(user, str) or not isinstance(password, str) or not user or not password:
            raise RequestError(f"{what}: users and passwords must be non-empty strings")
        checked[user] = password
    return checked


class Service:
    """A running service; made and closed by :func:`serve` (use that)."""

    def __init__(
        self,
        server: Sensor,
        name: str = "biris0",
        listen: Sequence[str] = (),
        controllers: Mapping[str, str] | None = None,
        *,
        readers: Mapping[str, str] | None = None,
        connect: Sequence[str] = (),
        multicast: bool = True,
        options: Mapping[str, Any] | None = None,
        status_period: float = 1.0,
        status_poll: float = 0.05,
        playback: bool = False,
    ) -> None:
        self.server = server
        self.playback = bool(playback)
        """The sensor is a recording that refuses motion and configuration itself (a
        :class:`~biris_hw.replay.ReplayServer`): control operations are handed to it whoever asks,
        so that a client hears the replay's own refusal, not a misleading AccessDenied."""
        self.data_opened = threading.Event()
        """Set when a remote client first opens a DATA connection (``biris serve --replay``
        starts playing then, so that the first client sees the recording from its start)."""
        self.name = check_name(name, "name")
        self.keys = Keys(self.name)
        self.controllers = _credentials(controllers, "controllers") or {}
        self.readers = _credentials(readers, "readers")
        self.status_period = float(status_period)
        self.status_poll = float(status_poll)
        self.published: dict[str, int] = {"point": 0, "scan": 0, "status": 0, "fault": 0}
        """Publications made, per kind (the counter each publication carries)."""
        self.requests = 0
        self.refused_busy = 0
        self.refused_bad = 0
        self.released_clients = 0
        self._clients: dict[str, _Client] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._last_fault: HardwareFault | None = None
        self._threads: list[threading.Thread] = []
        self._feeds: list[Connection[Any]] = []
        # before anything is served: the codec's first use costs ~0.1 s of interpreter time, which
        # on the feed thread would have stalled the server's threads at the first acquisition
        warm_all()
        self._pool = concurrent.futures.ThreadPoolExecutor(WORKERS, thread_name_prefix="biris-net")
        config = make_config(listen=listen, connect=connect, multicast=multicast, options=options)
        try:
            self._session = zenoh.open(config)
        except Exception as exc:  # zenoh.ZError: an endpoint in use, a TLS file missing...
            self._pool.shutdown()
            raise RequestError(f"cannot start the Zenoh session: {exc}") from exc
        try:
            self._declare()
        except BaseException:
            self.close()
            raise

    # -- set-up and take-down --------------------------------------------------------------------
    def _declare(self) -> None:
        session, keys = self._session, self.keys
        drop = zenoh.CongestionControl.DROP
        self._pub_point = session.declare_publisher(keys.point, congestion_control=drop)
        self._pub_scan = {
            d: session.declare_publisher(keys.scan(d.name.lower()), congestion_control=drop)
            for d in Direction
        }
        self._pub_status = session.declare_publisher(keys.status, congestion_control=drop)
        self._pub_fault = session.declare_publisher(
            keys.fault, congestion_control=zenoh.CongestionControl.BLOCK
        )
        self._queryable = session.declare_queryable(keys.rpcs, self._on_query)
        self._clients_sub = session.liveliness().declare_subscriber(
            keys.client_tokens, self._on_client_token, history=True
        )
        for target, what in (
            (self._feed_points, "points"),
            (self._feed_scans, "scans"),
            (self._watch_status, "status"),
        ):
            thread = threading.Thread(target=target, name=f"biris-net-{what}", daemon=True)
            thread.start()
            self._threads.append(thread)
        self._token = session.liveliness().declare_token(keys.service_token)
        log.info("BIRIS service %r up", self.name)

    def close(self) -> None:
        """Stop serving: clients' connections closed, threads joined, the session closed."""
        if self._stop.is_set():
            return
        self._stop.set()
        session = self._session
        for undeclare in ("_token", "_queryable", "_clients_sub"):
            thing = getattr(self, undeclare, None)
            if thing is not None:
                with contextlib.suppress(Exception):
                    thing.undeclare()
        with self._lock:
            clients = list(self._clients.values())
            self._clients.clear()
        for client in clients:
            self._close_all(client)
        for feed in self._feeds:
            with contextlib.suppress(BirisError):
                feed.close()
        for thread in self._threads:
            thread.join()
        self._pool.shutdown(wait=True, cancel_futures=True)
        session.close()  # type: ignore[no-untyped-call]
        log.info("BIRIS service %r down", self.name)

    # -- publications ----------------------------------------------------------------------------
    def _publish(self, publisher: Any, kind: str, payload: bytes, schema: str) -> None:
        self.published[kind] += 1
        publisher.put(
            payload,
            encoding=zenoh.Encoding.APPLICATION_CDR.with_schema(schema),
            attachment=struct.pack("<Q", self.published[kind]),
        )

    def _feed(self, policy: DeliveryPolicy, depth: int, publish: Callable[[Any], None]) -> None:
        try:
            feed = self.server.open(ConnectionKind.DATA, policy=policy, depth=depth)
        except BirisError as exc:
            log.warning("service feed %s not opened: %s", policy.value, exc)
            return
        self._feeds.append(feed)
        while not self._stop.is_set():
            try:
                item = feed.ready_for_data(timeout=0.25)
            except TimeoutError:
                continue
            except HardwareFault as exc:
                self._last_fault = exc
                self._stop.wait(0.05)  # the fault stays until a reset: look again shortly
                continue
            except (ConnectionClosed, RequestError):
                return  # the server or the service is closing
            except Exception:  # a sensor that is not a BirisServer may fail otherwise: say so
                log.exception("service feed %s failed", policy.value)
                self._stop.wait(0.1)
                continue
            try:
                publish(item)
            except Exception:  # a publication that fails must not stop the feed
                log.exception("publishing %s failed", policy.value)

    def _feed_points(self) -> None:
        def publish(point: Point) -> None:
            self._publish(self._pub_point, "point", wire.encode_point(point), wire.POINT)

        self._feed(DeliveryPolicy.EVERY_ACQUISITION, FEED_DEPTH, publish)

    def _feed_scans(self) -> None:
        def publish(scan: Scan) -> None:
            self._publish(self._pub_scan[scan.direction], "scan", wire.encode_scan(scan), wire.SCAN)

        self._feed(DeliveryPolicy.EVERY_BUFFER, 8, publish)

    @staticmethod
    def _signature(status: ServerStatus) -> tuple[Any, ...]:
        """What makes a status worth publishing at once (not the ever-changing counters)."""
        return (
            status.state_name,
            status.azimuth,
            status.elevation,
            status.calibration,
            status.continuous,
            status.acquisition,
            status.ring,
            status.acquisition_pending,
            len(status.connections),
        )

    def _watch_status(self) -> None:
        last: tuple[Any, ...] | None = None
        sent = -float("inf")
        in_fault = False
        while not self._stop.wait(0 if last is None else self.status_poll):
            try:
                status = self.server.status()
            except ConnectionClosed:
                return
            except BirisError as exc:
                log.warning("status not read: %s", exc)
                continue
            signature = self._signature(status)
            now = time.monotonic()
            if signature != last or now - sent >= self.status_period:
                self._publish(self._pub_status, "status", wire.encode_status(status), wire.STATUS)
                last, sent = signature, now
            faulted = status.state is ServerState.FAULT
            if faulted and not in_fault:
                fault = self._last_fault
                if fault is None or fault.kind != status.fault:
                    fault = HardwareFault(status.fault or "internal", "the server is in a fault")
                self._publish(self._pub_fault, "fault", wire.encode_fault(fault), wire.FAULT)
            in_fault = faulted

    # -- clients ---------------------------------------------------------------------------------
    def _on_client_token(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.DELETE:
            return
        ident = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            client = self._clients.pop(ident, None)
        if client is not None and not self._stop.is_set():
            self.released_clients += 1
            log.info(
                "client %s vanished: releasing %d connection(s)", ident, len(client.connections)
            )
            with contextlib.suppress(RuntimeError):  # the pool is shutting down: close() does it
                self._pool.submit(self._close_all, client)

    @staticmethod
    def _close_all(client: _Client) -> None:
        for conn in list(client.connections.values()):
            with contextlib.suppress(BirisError):
                conn.close()
        client.connections.clear()

    def clients(self) -> dict[str, int]:
        """Client id -> connections it holds (what ``biris serve`` logs, what tests look at)."""
        with self._lock:
            return {c.ident: len(c.connections) for c in self._clients.values()}

    # -- requests --------------------------------------------------------------------------------
    def _on_query(self, query: zenoh.Query) -> None:
        """Admit a query on Zenoh's thread (cheap checks only), or answer it at once."""
        self.requests += 1
        try:
            op, request = self._read(query)
            try:
                ident = check_name(str(request.get("client")), "client")
            except RequestError as exc:
                raise BadRequest(str(exc)) from None
            with self._lock:
                client = self._clients.get(ident)
                if client is None:
                    if self._stop.is_set():
                        raise ConnectionClosed("the service is closing")
                    client = self._clients[ident] = _Client(ident)
                admitted = client.admit(time.monotonic())
            if not admitted:
                self.refused_busy += 1
                raise Busy(
                    f"too many requests from client {ident} (at most {MAX_INFLIGHT_PER_CLIENT} "
                    f"at once, {RATE_PER_CLIENT:g}/s): not done"
                )
        except RequestError as exc:
            if not isinstance(exc, Busy):
                self.refused_bad += 1
            self._reply_err(query, exc)
            return
        try:
            self._pool.submit(self._work, query, op, request, client)
        except RuntimeError:  # shut down meanwhile
            with self._lock:
                client.inflight -= 1
            self._reply_err(query, ConnectionClosed("the service is closing"))

    def _read(self, query: zenoh.Query) -> tuple[str, dict[str, Any]]:
        op = str(query.key_expr).rsplit("/", 1)[-1]
        if op not in OPS:
            raise BadRequest(f"unknown operation {op!r}; known: {', '.join(sorted(OPS))}")
        payload = query.payload
        raw = payload.to_bytes() if payload is not None else b"{}"
        if len(raw) > MAX_REQUEST:
            raise BadRequest(f"{op}: request of {len(raw)} bytes exceeds {MAX_REQUEST}")
        try:
            request = json.loads(raw)
        except (ValueError, UnicodeDecodeError) as exc:
            raise BadRequest(f"{op}: request is not JSON ({exc})") from None
        if not isinstance(request, dict):
            raise BadRequest(f"{op}: request must be a JSON object")
        return op, request

    @staticmethod
    def _reply_err(query: zenoh.Query, exc: BaseException) -> None:
        try:
            query.reply_err(error_payload(exc), encoding=JSON)
        except Exception as err:  # the querier has gone: nothing to tell
            log.debug("error reply not sent: %s", err)
        finally:
            query.drop()  # type: ignore[no-untyped-call]

    def _work(self, query: zenoh.Query, op: str, request: dict[str, Any], client: _Client) -> None:
        try:
            self._authorise(op, request)
            payload, encoding, attachment = self._dispatch(op, request, client)
            query.reply(self.keys.rpc(op), payload, encoding=encoding, attachment=attachment)
        except (BirisError, TimeoutError) as exc:
            self._reply_err(query, exc)
            return
        except Exception as exc:  # a bug here must still answer, and keep the service up
            log.exception("request %s failed", op)
            self._reply_err(query, exc)
            return
        finally:
            with self._lock:
                client.inflight -= 1
        query.drop()  # type: ignore[no-untyped-call]

    def _authorise(self, op: str, request: Mapping[str, Any]) -> None:
        user, password = request.get("user"), request.get("password")
        if op in CONTROL_OPS:
            if self.playback:
                return  # the recording refuses every one of them itself, changing nothing
            if not self._known(self.controllers, user, password):
                raise AccessDenied(f"{op}: needs a controller's credentials; nothing was done")
        elif self.readers is not None and not (
            self._known(self.readers, user, password)
            or self._known(self.controllers, user, password)
        ):
            raise AccessDenied(f"{op}: this service needs a reader's credentials")

    @staticmethod
    def _known(table: Mapping[str, str], user: object, password: object) -> bool:
        if not isinstance(user, str) or not isinstance(password, str):
            return False
        expected = table.get(user)
        # compared in constant time (and a missing user costs the same as a wrong password)
        return hmac.compare_digest((expected or "\0").encode(), password.encode()) and bool(
            expected
        )

    def _dispatch(
        self, op: str, request: Mapping[str, Any], client: _Client
    ) -> tuple[bytes, zenoh.Encoding, bytes | None]:
        if op == "status":
            return wire.encode_status(self.server.status()), _cdr(wire.STATUS), None
        if op == "open":
            return self._open(request, client)
        conn = self._connection(request, client)
        if op == "close":
            conn.close()
            with self._lock:
                client.connections.pop(conn.ident, None)
            return _json(None)
        if op == "request_point":
            point = conn.request_point()
            if point is None:
                return _json(None)
            return wire.encode_point(point), _cdr(wire.POINT), None
        if op == "request_scan_data":
            scan = conn.request_scan_data(_field(request, "direction", int))
            if scan is None:
                return _json(None)
            return wire.encode_scan(scan), _cdr(wire.SCAN), None
        if op == "ready_for_data":
            item = conn.ready_for_data(timeout=_wait(request))
            attachment = json.dumps({"dropped": conn.dropped}).encode()
            if isinstance(item, Scan):
                return wire.encode_scan(item), _cdr(wire.SCAN), attachment
            return wire.encode_point(item), _cdr(wire.POINT), attachment
        if op == "wait_idle":
            conn.wait_idle(timeout=_wait(request))
            return _json(None)
        if op == "single_scan":
            return _json({"counts": conn.single_scan(_angle(request, "to_deg"))})
        if op == "continuous_scan":
            cw, ccw = conn.continuous_scan(_angle(request, "cw_deg"), _angle(request, "ccw_deg"))
            return _json({"cw": cw, "ccw": ccw})
        if op == "set_elevation":
            return _json({"counts": conn.set_elevation(_angle(request, "deg"))})
        if op == "set_motor_params":
            params = _field(request, "params", dict)
            try:
                motor = MotorParams(**params)
            except (TypeError, ValueError) as exc:
                raise RequestError(f"params: {exc}") from None
            conn.set_motor_params(motor)
            return _json(None)
        simple: dict[str, Callable[[], None]] = {
            "stop_scan": conn.stop_scan,
            "start_continuous": conn.start_continuous,
            "stop_continuous": conn.stop_continuous,
            "home": conn.home,
            "timeout_enable": conn.timeout_enable,
            "timeout_disable": conn.timeout_disable,
            "reset": conn.reset,
        }
        simple[op]()
        return _json(None)

    def _open(
        self, request: Mapping[str, Any], client: _Client
    ) -> tuple[bytes, zenoh.Encoding, bytes | None]:
        try:
            kind = ConnectionKind[str(request.get("kind", "NORMAL"))]
            policy = DeliveryPolicy(str(request.get("policy", "latest")))
        except (KeyError, ValueError):
            raise RequestError(
                "open: kind must be NORMAL or DATA, policy latest, every_buffer or "
                "every_acquisition"
            ) from None
        depth = request.get("depth")
        if depth is not None and (isinstance(depth, bool) or not isinstance(depth, int)):
            raise RequestError(f"open: depth must be a whole number or null, not {depth!r}")
        with self._lock:
            if len(client.connections) >= MAX_CONNECTIONS_PER_CLIENT:
                raise RequestError(
                    f"open: client holds {MAX_CONNECTIONS_PER_CLIENT} connections already"
                )
        conn = self.server.open(kind, policy=policy, depth=depth)
        with self._lock:
            client.connections[conn.ident] = conn
        if kind is ConnectionKind.DATA:
            self.data_opened.set()
        return _json(
            {"conn": conn.ident, "kind": kind.name, "policy": policy.value, "depth": conn.depth}
        )

    def _connection(self, request: Mapping[str, Any], client: _Client) -> Connection[Any]:
        ident = _field(request, "conn", int)
        with self._lock:
            conn = client.connections.get(ident)
        if conn is None:
            raise ConnectionClosed(f"connection {ident} is closed (or not this client's)")
        return conn


def _json(value: object) -> tuple[bytes, zenoh.Encoding, None]:
    return json.dumps(value).encode(), JSON, None


def _cdr(schema: str) -> zenoh.Encoding:
    encoding: zenoh.Encoding = zenoh.Encoding.APPLICATION_CDR.with_schema(schema)
    return encoding


def _field(request: Mapping[str, Any], name: str, kind: type[Any]) -> Any:
    value = request.get(name)
    if isinstance(value, bool) or not isinstance(value, kind):
        raise BadRequest(f"{name}: expected a {kind.__name__}, not {value!r}")
    return value


def _angle(request: Mapping[str, Any], name: str) -> float:
    """An angle in degrees from a request: any JSON number (the connection clamps it)."""
    value = request.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RequestError(f"{name}: expected a number of degrees, not {value!r}")
    if isinstance(value, int):  # a huge whole number clamps like any angle beyond +-360
        return float(max(-(10**6), min(10**6, value)))
    return value


def _wait(request: Mapping[str, Any]) -> float:
    """A blocking request's timeout: 0 polls; at most :data:`MAX_WAIT_S` (the client repeats)."""
    value = request.get("timeout", MAX_WAIT_S)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
        raise RequestError(f"timeout: expected seconds >= 0, not {value!r}")
    return min(float(value), MAX_WAIT_S)


@contextlib.contextmanager
def serve(
    server: Sensor,
    name: str = "biris0",
    listen: Sequence[str] = (),
    controllers: Mapping[str, str] | None = None,
    **options: Any,
) -> Iterator[Service]:
    """Serve ``server`` on Zenoh as ``name`` until the block ends (DESIGN.md 3b).

    Args:
        server: a :class:`~biris_hw.BirisServer` (or anything with its open/status/close).
        name: the service's name, one key chunk: clients ``connect(name)``.
        listen: Zenoh endpoints to listen on (``tcp/0.0.0.0:7447``, ``tls/host:7448``); none
            means Zenoh's default (a random TCP port, found by multicast scouting).
        controllers: user -> password of those who may move and configure the sensor. None or
            empty: nobody may (a read-only service).
        readers: (keyword) user -> password required for reading too; default None: reading
            is free.
        connect: (keyword) endpoints to connect to (a Zenoh router, say).
        multicast: (keyword) multicast scouting, so clients find the service by name without an
            endpoint; default True. Off in tests and on networks that forbid it.
        options: (keyword) further Zenoh settings, ``{"key/path": value}`` (TLS files, user and
            password authentication, access control: see docs/wire-format.md, "Security").
        status_period: (keyword) seconds between status publications when nothing changes.
        playback: (keyword) ``server`` is a recording (:class:`~biris_hw.replay.ReplayServer`)
            that refuses motion and configuration itself: control requests reach it whatever the
            credentials, and are answered with its refusal (a RequestError). Default False.

    The server is not closed on the way out: it belongs to the caller.
    """
    service = Service(server, name, listen, controllers, **options)
    try:
        yield service
    finally:
        service.close()
