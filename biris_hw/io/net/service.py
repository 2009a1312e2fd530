"""``serve``: one BirisServer made available on Zenoh, for several readers and its controllers.

The service is a client of the server like any other (DESIGN.md section 2, "outside world"): it
holds local :class:`~biris_hw.client.Connection` objects on behalf of remote clients, takes its
publications from the sensor's feed (:mod:`biris_hw.io.feed`), and never reaches into the
server. So whatever the
server guarantees a local client -- refused requests change nothing, a slow DATA connection
loses the oldest buffers and counts them -- holds for a remote one by construction.

Threads and why:

* Zenoh hands each query to :meth:`Service._on_query` on the network thread that received it
  (a direct callback, not one queue for all peers: a flooding peer's backlog waits on its own
  link, not in front of everyone's requests). That call only reads and admits the query (size,
  nesting and JSON, the client's id, the connection token, credentials -- failed ones limited
  per client and for the service --, rate and in-flight limits per client, a cap on new
  clients and on blocking reads in all) and answers at once what it refuses, from replies made
  in advance where it can: a flood is answered "Busy" cheaply and never queues behind the
  sensor. Whatever a query holds, it is answered. Admitted requests run on one of two bounded
  pools (a full one is "Busy" too), which serve waiting requests one client at a time, in
  turn: control operations on a small pool of their own, which blocking reads never reach, so
  that no number of readers waiting in READY_FOR_DATA or wait_idle (each held at most
  :data:`~biris_hw.io.net.keys.MAX_WAIT_S`) can delay a controller's ``stop_scan``; everything
  else on the shared pool, where blocking reads are capped (:data:`MAX_BLOCKING`) below its
  size so that quick reads always find a worker.
* A janitor thread releases the connections of clients whose liveliness token went (after
  checking that no token of that client is left: anyone may withdraw a token of the same key)
  and of clients that never declared one and have asked nothing for :data:`CLIENT_LEASE_S`
  (their requests renew a lease), forgets idle clients, and, with
  ``stop_when_controllers_leave``, stops the head when the last controller has gone.
* The publications come from the process's one feed of the sensor (:mod:`biris_hw.io.feed`),
  whose reader reads every acquisition and every buffer once and encodes each once, for the
  service and for a recorder or a live view of the same sensor in the process alike. The
  service is a ``prompt`` sink: the reader hands each acquisition over as soon as it is read,
  since a publication *is* a delivery to clients. Its own thread publishes with
  ``CongestionControl.DROP``: a subscriber that cannot keep up loses samples (each carries a
  publication counter, so it can count them), it never slows the feed; what the service's
  queue in the feed, or the feed's in the server, had no room for is counted
  (:attr:`Service.dropped_points`).
* The same sink publishes the status when it changes and, unchanged, every ``status_period``
  seconds, and a fault when the sensor enters one: the feed's status thread waits for the
  sensor to push a change (``status(newer_than=...)``), asking nothing while nothing changes.
* On a moving robot (``poses=``, and ``grid=``, ``proximity=``) a second sink, not prompt, with
  a thread and a queue of its own, publishes what a
  :class:`~biris_hw.io.moving_sink.MovingEncoder` makes of the same acquisitions -- the
  vehicle's poses on ``odom`` and ``tf``, each scan deskewed on ``cloud``, the certainty grid on
  ``grid``, the proximity alarm's answers on ``proximity`` -- as a recording and the live view
  carry them:
  deskewing a scan or writing a grid (some 13 ms) never runs in the reader's thread, so the
  acquisitions go out as promptly as without it.

What a supervisor reads in the log (logger ``biris_hw.io.net.service``): the service up (name,
endpoints, who may do what) and down at INFO; each client's first request ("connected"), the
first control operation it is granted (with the controller's name), a reset it asks for, and
its leaving (its token withdrawn or its lease run out, its connections released) at INFO;
refusals -- access refused, authentications limited, Busy -- at WARNING, at most one line per
:data:`REFUSAL_LOG_S` for each kind (a flood of wrong passwords does not flood the log: the
lines count what they left out); a request that met a bug in the service, at ERROR, as
rarely; and
acquisitions or scans that could not be published, at WARNING, once per status period at most.
The sensor's own faults, resets and recoveries are its watcher's to say
(:class:`biris_hw.commands.reset.AutoReset` in ``biris serve``).
"""

from __future__ import annotations

import collections
import contextlib
import functools
import hmac
import json
import logging
import math
import queue
import secrets
import struct
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh

from biris_hw.client import checked_timeout
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Scan
from biris_hw.errors import (
    AccessDenied,
    BirisError,
    ConnectionClosed,
    RequestError,
)
from biris_hw.io import codec, feed
from biris_hw.io.moving_sink import (
    GridOption,
    MovingEncoder,
    PoseFeed,
    ProximityOption,
    moving_encoder,
)
from biris_hw.io.net.keys import (
    BLOCKING_OPS,
    CONTROL_OPS,
    MAX_WAIT_S,
    OPS,
    AuthLimited,
    BadRequest,
    Busy,
    Keys,
    ServiceClosing,
    UnknownConnection,
    check_client,
    check_name,
    check_token,
    error_payload,
    parse_request,
)
from biris_hw.io.net.warm import warm_all
from biris_hw.io.net.zconfig import make_config, zenoh_message
from biris_hw.records import MotorParams
from biris_hw.sensor import Connection, Sensor

__all__ = ["Quieter", "Sensor", "Service", "serve"]

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

MAX_CONNECTIONS = 256
"""Open connections all remote clients together may hold (a fresh client id per ``open`` does
not get round :data:`MAX_CONNECTIONS_PER_CLIENT`)."""

MAX_CLIENTS = 256
"""Clients the service keeps account of; idle ones are forgotten to make room, and a new one is
answered Busy while every entry is in use."""

NEW_CLIENT_RATE = 20.0
"""New client ids accepted per second, all peers together (a bucket of :data:`NEW_CLIENT_BURST`):
a flood that takes a fresh id per request, to dodge the per-client limits, runs dry at once."""

NEW_CLIENT_BURST = 64.0

CLIENT_IDLE_S = 60.0
"""A client that holds no connection and has asked nothing for this long is forgotten."""

CLIENT_LEASE_S = 10.0
"""A client whose liveliness token the service does not see (it never declared one, or access
control keeps it from the service) holds its connections on a lease that each of its requests
renews: asking nothing for this long, with nothing in flight, it is let go and its connections
closed. Longer than :data:`~biris_hw.io.net.keys.MAX_WAIT_S`, so that a reader that waits in
READY_FOR_DATA again and again never lapses. A client whose token the service sees keeps its
connections until the token goes."""

LEASE_CHECK_S = 1.0
"""How often the janitor looks for lapsed leases: a client that went quiet without a token is
let go within :data:`CLIENT_LEASE_S` + this."""

MAX_LIVE_TOKENS = 4 * MAX_CLIENTS
"""Client tokens the service keeps track of; beyond (a peer declaring tokens by the thousand),
a further client is treated as one without a token (on a lease)."""

AUTH_FAILURES_PER_CLIENT = 5.0
"""Failed authentications one client may have in a burst; then :data:`AUTH_RATE_PER_CLIENT`.
Beyond, its credentials are not checked at all (AuthLimited, a Busy): a guesser learns nothing."""

AUTH_RATE_PER_CLIENT = 0.2

AUTH_FAILURES = 20.0
"""Failed authentications all clients together may have in a burst; then :data:`AUTH_RATE`.
Zenoh does not tell a queryable which peer sent a query, and a client id costs nothing, so
this bound, not the per-client one, is what holds a guesser with many ids: at most a few
guesses a second in all (a 6-letter lowercase password: a year on average, not a day). A
client that has authenticated before, asking about a connection it holds (its token is a
secret only it has), is not held by it: a guesser cannot lock out a controller already
working."""

AUTH_RATE = 3.0

MAX_BLOCKING = 32
"""Blocking reads (ready_for_data, wait_idle with a timeout) held at once, all clients together;
beyond, Busy. Below :data:`READ_WORKERS`, so that quick reads always find a worker."""

READ_WORKERS = MAX_BLOCKING + 16
"""Worker threads for everything but control operations."""

READ_QUEUE = 256
"""Admitted requests waiting for a read worker; beyond, Busy."""

CONTROL_WORKERS = 4
"""Worker threads for control operations only (a reset holds one while the head homes)."""

CONTROL_QUEUE = 32
"""Control requests waiting for a control worker; beyond, Busy."""

REFUSAL_LOG_S = 10.0
"""At most one log line per this many seconds for each kind of refusal (access refused, Busy):
the next says how many were left out meanwhile."""

RELEASE_CHECK_S = 1.0
"""How long the janitor asks Zenoh whether a client's token is still declared somewhere."""

FEED_DEPTH = 1024
"""Acquisitions that may wait for the service's publications in the feed (34 s at 30 Hz)."""

SCAN_DEPTH = 8
"""Scans that may wait for the service's publications in the feed."""

_MOVING_KINDS = {
    codec.ODOM_TOPIC: "odom",
    codec.TF_TOPIC: "tf",
    codec.POINTS_TOPIC: "cloud",
    codec.GRID_TOPIC: "grid",
    codec.PROXIMITY_TOPIC: "proximity",
}
"""The moving robot's topics (:class:`~biris_hw.io.moving_sink.MovingEncoder`) and the
:class:`~biris_hw.io.net.keys.Keys` each is published on (its counter's name too)."""

_PUBLISHED = frozenset(
    {codec.RAW_POINT_TOPIC, codec.RAW_SCAN_TOPIC, codec.RAW_STATUS_TOPIC, codec.RAW_FAULT_TOPIC}
)
"""What the service takes from the feed: the lossless payloads, as it publishes them."""


def _refusal(exc: BirisError) -> tuple[BirisError, bytes]:
    """A refusal and its reply, made once: a flood is answered without building either."""
    return exc, error_payload(exc)


_TOO_MANY = _refusal(
    Busy(
        f"too many requests from this client (at most {MAX_INFLIGHT_PER_CLIENT} at once, "
        f"{RATE_PER_CLIENT:g}/s): not done"
    )
)
_TOO_MANY_NEW = _refusal(Busy(f"too many new clients (at most {NEW_CLIENT_RATE:g}/s): not done"))
_TOO_MANY_BLOCKING = _refusal(Busy(f"{MAX_BLOCKING} blocking reads are held already: not done"))
_GUESSING = _refusal(
    AuthLimited(
        "too many failed authentications by this client: credentials not checked, nothing done"
    )
)
_READ_FULL = _refusal(Busy("the service's read queue is full: not done"))
_CONTROL_FULL = _refusal(Busy("the service's control queue is full: not done"))
_GUESSING_ALL = _refusal(
    AuthLimited(
        "too many failed authentications on this service lately: credentials not checked, "
        "nothing done"
    )
)


@dataclass
class _Bucket:
    """A token bucket: ``size`` tokens, refilled at ``rate`` a second."""

    size: float
    rate: float
    tokens: float = -1.0
    refilled: float = field(default_factory=time.monotonic)

    def __post_init__(self) -> None:
        if self.tokens < 0:
            self.tokens = self.size

    def has(self, now: float) -> bool:
        """Whether a token is there (refilled up to ``now``), without taking it."""
        self.tokens = min(self.size, self.tokens + (now - self.refilled) * self.rate)
        self.refilled = now
        return self.tokens >= 1.0

    def take(self, now: float) -> bool:
        """Take a token if one is there."""
        if not self.has(now):
            return False
        self.tokens -= 1.0
        return True


@dataclass
class _Client:
    """What the service knows of one remote client."""

    ident: str
    connections: dict[str, Connection[Any]] = field(default_factory=dict)
    """By connection token (what ``open`` returned)."""
    inflight: int = 0
    requests: _Bucket = field(default_factory=lambda: _Bucket(BURST, RATE_PER_CLIENT))
    failures: _Bucket = field(
        default_factory=lambda: _Bucket(AUTH_FAILURES_PER_CLIENT, AUTH_RATE_PER_CLIENT)
    )
    """Failed authentications it may still have."""
    refused: int = 0
    """Requests answered Busy (a flood)."""
    seen: float = field(default_factory=time.monotonic)
    """When it last asked anything (its lease runs from here)."""
    released: bool = False
    """Its token went, its lease ran out, or the service closed: it may hold nothing any more."""
    controller: bool = False
    """It has been granted a control operation (counts for ``stop_when_controllers_leave``)."""
    trusted: bool = False
    """Its credentials have passed a check."""

    def idle(self, now: float, older_than: float) -> bool:
        """Holds nothing, asks nothing, and has not asked for ``older_than`` seconds."""
        return (
            not self.connections
            and self.inflight == 0
            and not self.controller
            and now - self.seen >= older_than
        )

    def lapsed(self, now: float) -> bool:
        """Holds connections on a lease (no token seen) that has run out."""
        return bool(self.connections) and self.inflight == 0 and now - self.seen >= CLIENT_LEASE_S

    def admit(self, now: float) -> bool:
        """Take one request token and an in-flight slot, or say no (and count it)."""
        if self.inflight >= MAX_INFLIGHT_PER_CLIENT or not self.requests.take(now):
            self.refused += 1
            return False
        self.inflight += 1
        return True


class Quieter:
    """Says whether a log line about ``kind`` may be written now: at most one per ``period_s``
    for each kind, so that a flood (of wrong passwords, of requests) does not flood the log;
    the line that may be written is told how many were left out since the last. Not
    thread-safe: its owner holds a lock."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._kinds: dict[str, tuple[float, int]] = {}
        """Per kind: until when the log stays quiet about it, and how many it left out."""

    def allow(self, kind: str, now: float) -> int | None:
        """None: stay quiet (counted); else the number left out since the last line."""
        quiet_until, unsaid = self._kinds.get(kind, (-math.inf, 0))
        if now < quiet_until:
            self._kinds[kind] = (quiet_until, unsaid + 1)
            return None
        self._kinds[kind] = (now + self.period_s, 0)
        return unsaid


def _credentials(table: Mapping[str, str] | None, what: str) -> dict[str, str] | None:
    if table is None:
        return None
    checked: dict[str, str] = {}
    for user, password in table.items():
        if not isinstance(user, str) or not isinstance(password, str) or not user or not password:
            raise RequestError(f"{what}: users and passwords must be non-empty strings")
        checked[user] = password
    return checked


_Task = tuple[Callable[..., object], tuple[Any, ...]]


class _FairPool:
    """Worker threads that serve waiting requests one client at a time, in turn (round robin),
    each client's own in the order they came: a client with many requests waiting delays
    another's by at most one of its own per turn, where a first-come queue would put the other
    behind all of them. Bounded: :meth:`submit` says False rather than hold more than
    ``workers + waiting`` requests. Workers are started as they are needed."""

    def __init__(self, workers: int, waiting: int, name: str) -> None:
        self._workers = workers
        self._room = workers + waiting
        self._name = name
        self._cond = threading.Condition()
        self._waiting: dict[str, collections.deque[_Task]] = {}
        """Per client: its requests not yet taken by a worker."""
        self._turns: collections.deque[str] = collections.deque()
        """Clients with requests waiting, in the order they are served."""
        self._held = 0
        """Requests waiting or running."""
        self._idle = 0
        """Workers waiting for a request, not yet woken for one."""
        self._threads: list[threading.Thread] = []
        self._closed = False

    def submit(self, client: str, fn: Callable[..., object], *args: Any) -> bool:
        """Run ``fn(*args)`` on a worker in ``client``'s turn; False (nothing done) when full.

        Raises:
            RuntimeError: the pool is shut down.
        """
        with self._cond:
            if self._closed:
                raise RuntimeError("the pool is shut down")
            if self._held >= self._room:
                return False
            self._held += 1
            waiting = self._waiting.get(client)
            if waiting is None:
                waiting = self._waiting[client] = collections.deque()
                self._turns.append(client)
            waiting.append((fn, args))
            if self._idle:
                self._idle -= 1  # this one is woken for it
                self._cond.notify()
            elif len(self._threads) < self._workers:
                worker = threading.Thread(
                    target=self._serve, name=f"{self._name}-{len(self._threads)}", daemon=True
                )
                self._threads.append(worker)
                worker.start()
        return True

    def _next(self) -> _Task | None:
        """The next request in turn (waited for), or None once shut down with none left."""
        with self._cond:
            while not self._turns:
                if self._closed:
                    return None
                self._idle += 1
                self._cond.wait()
            client = self._turns.popleft()
            waiting = self._waiting[client]
            task = waiting.popleft()
            if waiting:
                self._turns.append(client)  # its next one after everyone else's
            else:
                del self._waiting[client]
            return task

    def _serve(self) -> None:
        while (task := self._next()) is not None:
            fn, args = task
            try:
                fn(*args)
            except Exception:  # the task answers its own errors: this is a bug
                log.exception("a request's worker failed")
            finally:
                with self._cond:
                    self._held -= 1

    def shutdown(self) -> None:
        """Take no more; serve what waits (each is answered), then end the workers."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            threads = list(self._threads)
        for thread in threads:
            thread.join()


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
        playback: bool | None = None,
        stop_when_controllers_leave: bool = False,
        poses: PoseFeed | None = None,
        grid: GridOption | None = None,
        proximity: ProximityOption | None = None,
    ) -> None:
        self.server = server
        self.moving: MovingEncoder | None = moving_encoder(poses, grid, proximity)
        """With ``poses``: what makes the vehicle's odometry, the deskewed clouds, the grid and
        the proximity alarm's answers, published from a sink of their own
        (:meth:`_publish_moving`); its counts, its grid and its alarm (``service.moving.grid``,
        ``service.moving.alarm``)."""
        recording = server.playback
        if playback and not recording:
            raise RequestError(
                f"playback=True, but {type(server).__name__} is not a recording (it can move the "
                "head): its control operations stay for controllers only"
            )
        if not server.paced:
            raise RequestError(
                f"{type(server).__name__} waits for its slowest reader (a recording played with "
                "speed=None), so one stalled remote reader would stall every client: give it a "
                "speed"
            )
        self.playback = recording if playback is None else bool(playback)
        """The sensor is a recording that refuses motion and configuration itself (a
        :class:`~biris_hw.io.record.ReplayServer`): control operations are handed to it whoever
        asks, so that a client hears the replay's own refusal, not a misleading AccessDenied.
        Decided from the sensor: ``playback=True`` for one that can move is refused."""
        self.stop_when_controllers_leave = bool(stop_when_controllers_leave)
        """Dead-man: when the last controller's liveliness token goes, issue stop_scan."""
        self.dead_man_stops = 0
        self.data_opened = threading.Event()
        """Set when a remote client first opens a DATA connection (``biris serve --replay``
        starts playing then, so that the first client sees the recording from its start)."""
        self.name = check_name(name, "name")
        self.keys = Keys(self.name)
        self.controllers = _credentials(controllers, "controllers") or {}
        self.readers = _credentials(readers, "readers")
        self.status_period = float(status_period)
        self.published: dict[str, int] = {
            "point": 0,
            "scan/cw": 0,
            "scan/ccw": 0,
            "status": 0,
            "fault": 0,
        }
        if self.moving is not None:
            self.published.update(dict.fromkeys(_MOVING_KINDS.values(), 0))
            if self.moving.feeder is None:
                del self.published["grid"]
            if self.moving.proximity_feeder is None:
                del self.published["proximity"]
        """Publications made, per key expression (the counter each publication carries): one
        per direction for scans, since a subscriber counts gaps per key."""
        self.requests = 0
        """Queries received (whatever became of them). The counters are kept under the
        service's lock: queries are admitted on several of Zenoh's threads at once."""
        self.refused_busy = 0
        """Requests answered Busy (AuthLimited among them)."""
        self.refused_bad = 0
        """Requests that could not be read (BadRequest)."""
        self.refused_access = 0
        """Requests refused for want of the right credentials (AccessDenied): failed
        authentications."""
        self.refused_auth_limited = 0
        """Requests whose credentials were not checked: too many failed authentications
        lately (AuthLimited)."""
        self.internal_errors = 0
        """Requests that met a bug in the service (answered InternalError)."""
        self.expired_clients = 0
        """Clients without a token let go when their lease ran out."""
        self.listen = list(listen)
        """The endpoints given to listen on (what the log says)."""
        self._refusals = Quieter(REFUSAL_LOG_S)
        """How often a refusal (or a bug) is logged (:meth:`_refused`)."""
        self._dropped_said = (0, 0)
        """Acquisitions and scans not published, as the log last said them."""
        self.released_clients = 0
        self.token_checks = 0
        """Withdrawn client tokens the janitor has looked into."""
        self._clients: dict[str, _Client] = {}
        self._conns: dict[str, tuple[_Client, Connection[Any]]] = {}
        """Every remote client's connection by its token (what requests name)."""
        self._live: set[str] = set()
        """Client ids whose liveliness token the service sees declared."""
        self._blocking = 0
        self._new_clients = _Bucket(NEW_CLIENT_BURST, NEW_CLIENT_RATE)
        self._failures = _Bucket(AUTH_FAILURES, AUTH_RATE)
        """Failed authentications all clients together may still have."""
        self._chores: queue.Queue[str | None] = queue.Queue()
        """Client ids whose token went, for the janitor (None: stop)."""
        self._sayer: queue.Queue[tuple[zenoh.Query, _Answer] | None] = queue.Queue()
        """Refusals due a log line, for the sayer: the line, then the reply (None: stop). As
        few as the lines are (one per kind of refusal and :data:`REFUSAL_LOG_S`)."""
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._sink: feed.Sink | None = None
        """The service's sink of the sensor's feed (None if the sensor could not be read)."""
        self._moving_sink: feed.Sink | None = None
        """With ``poses``: the sink that publishes the moving robot's messages, apart from the
        prompt one: a grid message costs some 13 ms, too long for the feed's reader thread."""
        # before anything is served: the codec's first use costs ~0.1 s of interpreter time, which
        # on the feed thread would have stalled the server's threads at the first acquisition
        warm_all()
        if self.moving is not None:
            self.moving.warm()
        self._pool = _FairPool(READ_WORKERS, READ_QUEUE, "biris-net")
        self._control = _FairPool(CONTROL_WORKERS, CONTROL_QUEUE, "biris-net-control")
        config = make_config(listen=listen, connect=connect, multicast=multicast, options=options)
        try:
            self._session = zenoh.open(config)
        except Exception as exc:  # zenoh.ZError: an endpoint in use, a TLS file missing...
            self._pool.shutdown()
            self._control.shutdown()
            raise RequestError(f"cannot start the Zenoh session: {zenoh_message(exc)}") from exc
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
        self._pub_moving: dict[str, tuple[Any, str]] = {}
        """The moving robot's publishers by the encoder's topic, with their counter's name."""
        if self.moving is not None:
            for topic, kind in _MOVING_KINDS.items():
                if kind in self.published:
                    key = getattr(keys, kind)
                    publisher = session.declare_publisher(key, congestion_control=drop)
                    self._pub_moving[topic] = (publisher, kind)
        self._queryable = session.declare_queryable(keys.rpcs, _direct(self._on_query))
        self._clients_sub = session.liveliness().declare_subscriber(
            keys.client_tokens, self._on_client_token, history=True
        )
        janitor = threading.Thread(target=self._janitor, name="biris-net-janitor", daemon=True)
        janitor.start()
        self._threads.append(janitor)
        sayer = threading.Thread(target=self._say_and_answer, name="biris-net-say", daemon=True)
        sayer.start()
        self._threads.append(sayer)
        try:
            self._sink = feed.attach(
                self.server,
                self._publish_batch,
                name="service",
                topics=_PUBLISHED,
                status_period_s=self.status_period,
                status_changes=True,
                prompt=True,
                point_depth=FEED_DEPTH,
                scan_depth=SCAN_DEPTH,
            )
        except BirisError as exc:  # a sensor already closed: the service answers all the same
            log.warning("the service publishes nothing: the sensor cannot be read (%s)", exc)
        if self.moving is not None and self._sink is not None:
            # not prompt: its own thread and queue, so that deskewing a scan and building a grid
            # message never delay the reader (and so the points' publications)
            self._moving_sink = feed.attach(
                self.server,
                self._publish_moving,
                name="service-moving",
                status_period_s=self.status_period,  # poses go on while the head is idle
                point_depth=FEED_DEPTH,
                scan_depth=SCAN_DEPTH,
            )
        self._token = session.liveliness().declare_token(keys.service_token)
        if self.playback:
            who = "a recording: nobody may move or configure it"
        else:
            who = f"{len(self.controllers)} controller(s)" if self.controllers else "read-only"
        reading = "free" if self.readers is None else "with credentials"
        log.info(
            "service %r up on %s (%s; reading %s)",
            self.name,
            " ".join(self.listen) or "Zenoh's default endpoints",
            who,
            reading,
        )

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
        self._chores.put(None)
        self._sayer.put(None)
        with self._lock:
            clients = list(self._clients.values())
            self._clients.clear()
            for client in clients:
                client.released = True
            self._conns.clear()
        for client in clients:
            self._close_all(client)
        if self._moving_sink is not None:
            self._moving_sink.detach()
        if self._sink is not None:
            self._sink.detach()
        for thread in self._threads:
            thread.join()
        self._pool.shutdown()
        self._control.shutdown()
        session.close()  # type: ignore[no-untyped-call]
        log.info("service %r down", self.name)

    # -- publications ----------------------------------------------------------------------------
    def _publish(self, publisher: Any, kind: str, payload: bytes, schema: str) -> None:
        self.published[kind] += 1
        publisher.put(
            payload,
            encoding=zenoh.Encoding.APPLICATION_CDR.with_schema(schema),
            attachment=struct.pack("<Q", self.published[kind]),
        )

    @property
    def dropped_points(self) -> int:
        """Acquisitions the service could not publish: its queue in the feed, or the feed's in
        the sensor, had no room for them."""
        return 0 if self._sink is None else self._sink.dropped_points

    @property
    def dropped_scans(self) -> int:
        return 0 if self._sink is None else self._sink.dropped_scans

    def _publish_batch(self, batch: feed.Batch) -> None:
        """Publish what the feed encoded for the service (its sink's thread): each payload on
        its key, a scan on its direction's. A publication that fails is said and skipped: the
        next one is tried all the same. With a status reading (at most once a status period),
        what could not be published since the last is said."""
        if batch.status is not None:
            self._say_dropped()
        for message in batch.messages:
            try:
                if message.topic == codec.RAW_POINT_TOPIC:
                    self._publish(self._pub_point, "point", message.data, message.msgtype)
                elif message.topic == codec.RAW_SCAN_TOPIC:
                    assert isinstance(message.item, Scan)
                    direction = message.item.direction
                    kind = f"scan/{direction.name.lower()}"
                    self._publish(self._pub_scan[direction], kind, message.data, message.msgtype)
                elif message.topic == codec.RAW_STATUS_TOPIC:
                    self._publish(self._pub_status, "status", message.data, message.msgtype)
                elif message.topic == codec.RAW_FAULT_TOPIC:
                    self._publish(self._pub_fault, "fault", message.data, message.msgtype)
            except Exception:
                log.exception("publishing %s failed", message.topic)

    def _publish_moving(self, batch: feed.Batch) -> None:
        """Publish the moving robot's messages the batch gives (the moving sink's thread), each
        on its key; a publication that fails is said and skipped, as in :meth:`_publish_batch`."""
        assert self.moving is not None
        try:
            messages = self.moving.messages(batch)
        except Exception:
            log.exception("the vehicle's poses, clouds, grid or proximity could not be made")
            return
        for message in messages:
            target = self._pub_moving.get(message.topic)
            if target is None:
                continue
            try:
                self._publish(target[0], target[1], message.data, message.msgtype)
            except Exception:
                log.exception("publishing %s failed", message.topic)

    def _say_dropped(self) -> None:
        """Log the acquisitions and scans that could not be published since the last line."""
        now = (self.dropped_points, self.dropped_scans)
        said, self._dropped_said = self._dropped_said, now
        points, scans = now[0] - said[0], now[1] - said[1]
        if points > 0 or scans > 0:
            log.warning(
                "%d acquisition(s) and %d scan(s) could not be published (the service's queue "
                "was full, or the sensor dropped them for it); %d and %d in all",
                points,
                scans,
                now[0],
                now[1],
            )

    # -- clients ---------------------------------------------------------------------------------
    def _on_client_token(self, sample: zenoh.Sample) -> None:
        """A client's token came (it holds its connections until the token goes) or went (the
        janitor checks and releases: not on Zenoh's thread)."""
        ident = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind != zenoh.SampleKind.DELETE:
                if len(self._live) < MAX_LIVE_TOKENS:
                    self._live.add(ident)
                return
            self._live.discard(ident)  # on a lease until the janitor has looked
            known = ident in self._clients
        if known and not self._stop.is_set():
            self._chores.put(ident)

    def _janitor(self) -> None:
        """Release vanished clients, let go of lapsed leases, forget idle clients, and keep
        the dead-man's watch."""
        now = time.monotonic()
        next_lease, next_idle = now + LEASE_CHECK_S, now + CLIENT_IDLE_S / 4
        while not self._stop.is_set():
            try:
                ident = self._chores.get(timeout=max(0.0, next_lease - time.monotonic()))
            except queue.Empty:
                ident = ""
            if ident is None:
                return
            try:
                if ident:
                    self._release(ident)
                now = time.monotonic()
                if now >= next_lease:
                    self._expire_leases(now)
                    next_lease = now + LEASE_CHECK_S
                if now >= next_idle:
                    self._forget_idle(CLIENT_IDLE_S)
                    next_idle = now + CLIENT_IDLE_S / 4
            except Exception:  # the janitor must outlive any one client
                log.exception("the janitor's round failed (client %s)", ident or "-")

    def _token_alive(self, ident: str) -> bool:
        """Whether some peer still declares client ``ident``'s token. Anyone may declare and
        withdraw a token of the same key; the withdrawal must not release the real client."""
        try:
            replies = self._session.liveliness().get(
                self.keys.client_token(ident), timeout=RELEASE_CHECK_S
            )
            return any(reply.ok is not None for reply in replies)
        except Exception as exc:  # the session is closing: nothing to keep
            log.debug("client token of %s not checked: %s", ident, exc)
            return False

    def _release(self, ident: str) -> None:
        alive = self._token_alive(ident)
        self.token_checks += 1
        if alive:
            with self._lock:
                self._live.add(ident)
            log.warning("a token of client %s was withdrawn, but the client remains", ident)
            return
        with self._lock:
            client = self._clients.get(ident)
        if client is None or self._stop.is_set():
            return
        self._let_go([client], "left", released=True)

    def _expire_leases(self, now: float) -> int:
        """Let go of the clients without a token that have asked nothing for
        :data:`CLIENT_LEASE_S` (their connections closed)."""
        with self._lock:
            lapsed = [
                c for c in self._clients.values() if c.ident not in self._live and c.lapsed(now)
            ]
        if not lapsed:
            return 0
        return self._let_go(
            lapsed, f"let go: no liveliness token, quiet {CLIENT_LEASE_S:g} s", released=False
        )

    def _let_go(self, clients: Sequence[_Client], why: str, *, released: bool) -> int:
        """Forget ``clients`` and close their connections; the dead-man's stop if the last
        controller was among them. How many were let go (not already), counted as released
        (their token went) or expired (their lease ran out) before anything is said."""
        with self._lock:
            gone = []
            for client in clients:
                if self._clients.get(client.ident) is not client:
                    continue  # let go already
                del self._clients[client.ident]
                client.released = True
                for token in client.connections:
                    self._conns.pop(token, None)
                gone.append(client)
            if released:
                self.released_clients += len(gone)
            else:
                self.expired_clients += len(gone)
            controllers_left = any(c.controller for c in self._clients.values())
        for client in gone:
            held = len(client.connections)
            log.info(
                "client %s %s%s",
                client.ident,
                why,
                f": closing its {held} connection(s)" if held else "",
            )
            self._close_all(client)
        controllers = [c for c in gone if c.controller]
        if controllers and not controllers_left and self.stop_when_controllers_leave:
            self._dead_man(controllers[-1].ident)
        return len(gone)

    def _dead_man(self, ident: str) -> None:
        """The last controller has gone: stop the head rather than let it sweep for ever."""
        log.warning("the last controller (%s) has gone: stopping the scan", ident)
        self.dead_man_stops += 1
        try:
            with self.server.open() as conn:
                conn.stop_scan()
        except BirisError as exc:  # nothing to stop, a fault, the server closing: said
            log.warning("dead-man stop_scan: %s", exc)

    def _forget_idle(self, older_than: float) -> int:
        """Forget clients that hold nothing and have been quiet for ``older_than`` s."""
        now = time.monotonic()
        with self._lock:
            idle = [k for k, c in self._clients.items() if c.idle(now, older_than)]
            for ident in idle:
                del self._clients[ident]
        for ident in idle:
            log.debug("client %s forgotten: quiet for %.0f s, holding nothing", ident, older_than)
        return len(idle)

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

    def counters(self) -> dict[str, int]:
        """What the service has counted: requests, refusals by kind, clients and connections
        (what a ``status`` request with ``"counters": true`` is told in its attachment)."""
        with self._lock:
            return {
                "requests": self.requests,
                "refused_busy": self.refused_busy,
                "refused_bad": self.refused_bad,
                "refused_access": self.refused_access,
                "refused_auth_limited": self.refused_auth_limited,
                "internal_errors": self.internal_errors,
                "clients": len(self._clients),
                "connections": len(self._conns),
                "released_clients": self.released_clients,
                "expired_clients": self.expired_clients,
            }

    def _client(self, ident: str, now: float) -> _Client:
        """The account of client ``ident``, opened if new and there is room (under the lock).

        Raises:
            _Refused: too many new clients lately (Busy).
            Busy: every account is in use.
        """
        client = self._clients.get(ident)
        if client is not None:
            return client
        if not self._new_clients.has(now):
            raise _Refused(*_TOO_MANY_NEW)
        if len(self._clients) >= MAX_CLIENTS:
            for key in [k for k, c in self._clients.items() if c.idle(now, 0.0)]:
                del self._clients[key]
            if len(self._clients) >= MAX_CLIENTS:
                raise Busy(f"the service serves {MAX_CLIENTS} clients already: not done")
        self._new_clients.take(now)
        client = self._clients[ident] = _Client(ident)
        return client

    # -- requests --------------------------------------------------------------------------------
    def _on_query(self, query: zenoh.Query) -> None:
        """Admit a query (on the Zenoh thread that received it: cheap checks only) and hand it
        to a pool, or answer it at once. Every query is answered, whatever it holds: refused
        here, or replied to by the worker that serves it.

        Nothing is logged on Zenoh's thread (a log record names its thread, and Python would
        keep a stand-in for Zenoh's for good): a refusal due a log line is handed to the
        service's sayer, which writes the line, then answers (in that order, as a worker
        does); the lines of admitted requests are written by their worker."""
        try:
            refusal = self._admit(query)
        except Exception as exc:  # a bug: the query is answered all the same, the service serves on
            with self._lock:
                self.internal_errors += 1
                unsaid = self._refusals.allow("internal error", time.monotonic())
            say = None if unsaid is None else _say_bug("admitting a request", exc, unsaid)
            refusal = _Answer(exc, None, say)
        if refusal is None:
            return
        if refusal.say is None:
            self._reply_err(query, refusal.error, refusal.payload)
        else:
            self._sayer.put((query, refusal))

    def _say_and_answer(self) -> None:
        """The sayer's thread: for each refusal handed over, its log line, then its reply."""
        while True:
            item = self._sayer.get()
            if item is None:
                break
            self._answer(*item)
        while True:  # whatever came as the service closed: answered all the same
            try:
                item = self._sayer.get_nowait()
            except queue.Empty:
                return
            if item is not None:
                self._answer(*item)

    def _answer(self, query: zenoh.Query, refusal: _Answer) -> None:
        try:
            if refusal.say is not None:
                refusal.say()
        finally:
            self._reply_err(query, refusal.error, refusal.payload)

    def _admit(self, query: zenoh.Query) -> _Answer | None:
        """Read, check and hand ``query`` to a worker: None; else the refusal to answer,
        counted (and its log line, if one is due)."""
        op = ident = "?"
        user: object = None
        now = time.monotonic()
        with self._lock:
            self.requests += 1
        try:
            op, request = self._read(query)
            user = request.get("user")
            ident = check_client(request)
            token = None if op in ("open", "status") else check_token(request.get("conn"))
            blocking = op in BLOCKING_OPS and request.get("timeout", MAX_WAIT_S) != 0
            control = op in CONTROL_OPS
            # a recording refuses every control operation itself, whoever asks
            checked = not self.playback if control else self.readers is not None
            notes: list[tuple[str, tuple[object, ...]]] = []
            with self._lock:
                if self._stop.is_set():
                    raise ServiceClosing("the service is closing")
                conn: Connection[Any] | None = None
                found = None if token is None else self._conns.get(token)
                if found is not None:  # the token names the connection, and so its owner
                    client, conn = found
                elif token is None or checked:  # credentials go before a connection's check
                    if ident not in self._clients:
                        notes.append(("client %s connected (%s)", (ident, op)))
                    client = self._client(ident, now)
                else:
                    raise _unknown()
                client.seen = now
                if checked:
                    self._may_check(client, conn is not None, now)
            if checked:
                self._check_credentials(op, request, client, now)
            if token is not None and conn is None:
                raise _unknown()
            with self._lock:
                if not client.admit(now):
                    raise _Refused(*_TOO_MANY)
                if blocking and self._blocking >= MAX_BLOCKING:
                    client.inflight -= 1
                    raise _Refused(*_TOO_MANY_BLOCKING)
                if blocking:
                    self._blocking += 1
                if control and not self.playback:
                    if not client.controller:
                        who = user[:64] if isinstance(user, str) else _shown(user)
                        notes.append(("client %s controls the sensor as %r", (ident, who)))
                    client.controller = True
        except _Refused as refused:
            return self._refused(refused.error, refused.payload, op, ident, user)
        except BirisError as exc:
            return self._refused(exc, None, op, ident, user)
        pool = self._control if control else self._pool
        try:
            queued = pool.submit(
                ident, self._work, query, op, request, client, conn, blocking, notes
            )
        except RuntimeError:  # shut down meanwhile
            self._done(client, blocking)
            return _Answer(ServiceClosing("the service is closing"), None, None)
        if queued:
            return None
        self._done(client, blocking)
        return self._refused(*(_CONTROL_FULL if control else _READ_FULL), op, ident, user)

    def _may_check(self, client: _Client, named_conn: bool, now: float) -> None:
        """Whether ``client``'s credentials may be checked now (under the lock): not after
        too many failures of its own, nor, unless it has authenticated before and asks about a
        connection it holds, after too many on the service as a whole.

        Raises:
            _Refused: AuthLimited; the credentials are not looked at.
        """
        if not client.failures.has(now):
            raise _Refused(*_GUESSING)
        if not (client.trusted and named_conn) and not self._failures.has(now):
            raise _Refused(*_GUESSING_ALL)

    def _check_credentials(
        self, op: str, request: Mapping[str, Any], client: _Client, now: float
    ) -> None:
        """The request's credentials against the service's (a failure is spent from the
        client's and the service's allowance).

        Raises:
            AccessDenied: they do not let ``client`` do ``op``.
        """
        user, password = request.get("user"), request.get("password")
        if op in CONTROL_OPS:
            passed = self._known(self.controllers, user, password)
        else:
            passed = self._known(self.readers or {}, user, password) or self._known(
                self.controllers, user, password
            )
        with self._lock:
            if passed:
                client.trusted = True
                return
            client.failures.take(now)
            self._failures.take(now)
        if op in CONTROL_OPS:
            raise AccessDenied(f"{op}: needs a controller's credentials; nothing was done")
        raise AccessDenied(f"{op}: this service needs a reader's credentials")

    def _refused(
        self, error: BirisError, payload: bytes | None, op: str, ident: str, user: object
    ) -> _Answer:
        """A refusal counted by its kind, with its log line if one is due (at most one per
        kind and :data:`REFUSAL_LOG_S`, the next counting those left out)."""
        kind = None
        with self._lock:
            if isinstance(error, Busy):
                self.refused_busy += 1
                if isinstance(error, AuthLimited):
                    self.refused_auth_limited += 1
                    kind = "authentication limited"
                else:
                    kind = "busy"
            elif isinstance(error, BadRequest):
                self.refused_bad += 1
            elif isinstance(error, AccessDenied):
                self.refused_access += 1
                kind = "access refused"
            unsaid = None if kind is None else self._refusals.allow(kind, time.monotonic())
        if kind is None or unsaid is None:
            return _Answer(error, payload, None)
        if kind == "busy":
            text = f"client {ident}, {op}: {error}"
        elif kind == "access refused":
            text = f"client {ident} (user {_shown(user)}): {error}"
        else:
            text = f"client {ident} (user {_shown(user)}), {op}: {error}"
        more = f" ({unsaid} more refused since the last line)" if unsaid else ""
        return _Answer(error, payload, functools.partial(log.warning, "%s: %s%s", kind, text, more))

    def _done(self, client: _Client, blocking: bool) -> None:
        with self._lock:
            client.inflight -= 1
            client.seen = time.monotonic()
            if blocking:
                self._blocking -= 1

    @staticmethod
    def _read(query: zenoh.Query) -> tuple[str, dict[str, Any]]:
        """The operation a query names and its request (BadRequest for anything unreadable)."""
        op = str(query.key_expr).rsplit("/", 1)[-1]
        if op not in OPS:
            raise BadRequest(f"unknown operation {op!r}; known: {', '.join(sorted(OPS))}")
        payload = query.payload
        return op, parse_request(payload.to_bytes() if payload is not None else b"{}", op)

    @staticmethod
    def _reply_err(query: zenoh.Query, exc: BaseException, payload: bytes | None = None) -> None:
        """Answer ``query`` with the error reply of ``exc`` (``payload``: that reply, made
        already)."""
        try:
            query.reply_err(error_payload(exc) if payload is None else payload, encoding=JSON)
        except Exception:  # the querier has gone: nothing to tell (and nothing logged: this
            pass  # may be Zenoh's thread)
        finally:
            query.drop()  # type: ignore[no-untyped-call]

    def _work(
        self,
        query: zenoh.Query,
        op: str,
        request: dict[str, Any],
        client: _Client,
        conn: Connection[Any] | None,
        blocking: bool,
        notes: Sequence[tuple[str, tuple[object, ...]]] = (),
    ) -> None:
        """Serve an admitted request (a worker's thread): its log lines, then its reply."""
        try:
            for text, args in notes:
                log.info(text, *args)
            payload, encoding, attachment = self._dispatch(op, request, client, conn)
            query.reply(self.keys.rpc(op), payload, encoding=encoding, attachment=attachment)
        except (BirisError, TimeoutError) as exc:
            if isinstance(exc, Busy):  # open: every connection the service allows is held
                with self._lock:
                    self.refused_busy += 1
            self._reply_err(query, exc)
            return
        except Exception as exc:  # a bug here must still answer, and keep the service up
            with self._lock:
                self.internal_errors += 1
                unsaid = self._refusals.allow("internal error", time.monotonic())
            if unsaid is not None:
                _say_bug(f"request {op}", exc, unsaid)()
            self._reply_err(query, exc)
            return
        finally:
            self._done(client, blocking)
        query.drop()  # type: ignore[no-untyped-call]

    @staticmethod
    def _known(table: Mapping[str, str], user: object, password: object) -> bool:
        if not isinstance(user, str) or not isinstance(password, str):
            return False
        expected = table.get(user)
        # compared in constant time (and a missing user costs the same as a wrong password);
        # a password is any JSON string, lone surrogates included
        given = password.encode("utf-8", "surrogatepass")
        return hmac.compare_digest((expected or "\0").encode(), given) and bool(expected)

    def _dispatch(
        self,
        op: str,
        request: Mapping[str, Any],
        client: _Client,
        conn: Connection[Any] | None,
    ) -> tuple[bytes, zenoh.Encoding, bytes | None]:
        if op == "status":
            return self._status_reply(request)
        if op == "open":
            return self._open(request, client)
        assert conn is not None  # every other operation names its connection (admitted so)
        if op == "close":
            conn.close()
            with self._lock:
                for token in [t for t, c in client.connections.items() if c is conn]:
                    del client.connections[token]
                    self._conns.pop(token, None)
            return _json(None)
        if op == "request_point":
            point = conn.request_point()
            if point is None:
                return _json(None)
            return codec.encode_point(point), _cdr(codec.POINT), None
        if op == "request_scan_data":
            scan = conn.request_scan_data(_field(request, "direction", int))
            if scan is None:
                return _json(None)
            return codec.encode_scan(scan), _cdr(codec.SCAN), None
        if op == "ready_for_data":
            item = conn.ready_for_data(timeout=_wait(request))
            attachment = json.dumps({"dropped": conn.dropped}).encode()
            if isinstance(item, Scan):
                return codec.encode_scan(item), _cdr(codec.SCAN), attachment
            return codec.encode_point(item), _cdr(codec.POINT), attachment
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
        # the rest take no argument: stop_scan, start_continuous, stop_continuous, home,
        # timeout_enable, timeout_disable, reset (answered when the initialisation ends)
        if op not in _SIMPLE:
            raise BadRequest(f"unknown operation {op!r}")
        if op == "reset":
            log.info("client %s (%r) asks for a reset", client.ident, request.get("user"))
        action: Callable[[], None] = getattr(conn, op)
        action()
        return _json(None)

    def _status_reply(
        self, request: Mapping[str, Any]
    ) -> tuple[bytes, zenoh.Encoding, bytes | None]:
        """``status``: the sensor's status, and in the attachment (JSON) its clock; with
        ``"info": true`` also what a client learns once when it connects (a recording? paced?
        the init record), which :class:`~biris_hw.io.net.RemoteSensor` exposes as its own, and
        how many clients hold connections and how many controllers are there (``biris
        list``); with ``"counters": true`` the service's :meth:`counters` (``"service"``)."""
        server = self.server
        status = server.status()
        info: dict[str, Any] = {"clock": server.clock()}
        if request.get("counters") is True:
            info["service"] = self.counters()
        if request.get("info") is True:
            record = server.record
            with self._lock:
                clients = sum(1 for c in self._clients.values() if c.connections)
                controllers = sum(1 for c in self._clients.values() if c.controller)
            info.update(
                playback=self.playback,
                paced=server.paced,
                record=None if record is None else record.to_dict(),
                clients=clients,
                controllers=controllers,
            )
        return codec.encode_status(status), _cdr(codec.STATUS), json.dumps(info).encode()

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
            self._check_room(client)
        conn = self.server.open(kind, policy=policy, depth=depth)
        token = secrets.token_urlsafe(16)
        problem: BirisError | None = None
        with self._lock:
            # released meanwhile (its token went, or the service is closing), or the room taken
            # by others' opens while this one ran: the connection must not outlive the check
            if client.released or self._stop.is_set():
                problem = ConnectionClosed("the client has gone (or the service is closing)")
            else:
                try:
                    self._check_room(client)
                except BirisError as exc:
                    problem = exc
            if problem is None:
                client.connections[token] = conn
                self._conns[token] = (client, conn)
        if problem is not None:
            with contextlib.suppress(BirisError):
                conn.close()
            raise problem
        if kind is ConnectionKind.DATA:
            self.data_opened.set()
        return _json(
            {
                "conn": token,
                "ident": conn.ident,
                "kind": kind.name,
                "policy": policy.value,
                "depth": conn.depth,
            }
        )

    def _check_room(self, client: _Client) -> None:
        """Room for one more connection of ``client`` (under the lock), or RequestError."""
        if len(client.connections) >= MAX_CONNECTIONS_PER_CLIENT:
            raise RequestError(
                f"open: client holds {MAX_CONNECTIONS_PER_CLIENT} connections already"
            )
        if len(self._conns) >= MAX_CONNECTIONS:
            raise Busy(f"open: the service's clients hold {MAX_CONNECTIONS} connections already")


_SIMPLE = frozenset(
    {
        "stop_scan",
        "start_continuous",
        "stop_continuous",
        "home",
        "timeout_enable",
        "timeout_disable",
        "reset",
    }
)


@dataclass(frozen=True)
class _Answer:
    """A refusal to answer: its error, its reply if made in advance, and the log line to write
    first (None: no line is due)."""

    error: BaseException
    payload: bytes | None
    say: Callable[[], None] | None


def _say_bug(what: str, exc: BaseException, unsaid: int) -> Callable[[], None]:
    """The log line of a bug met while serving, with its traceback."""
    more = f" ({unsaid} more since the last line)" if unsaid else ""
    return functools.partial(log.error, "%s failed%s", what, more, exc_info=exc)


class _Refused(Exception):
    """A refusal made in advance (:func:`_refusal`), raised afresh each time it is given."""

    def __init__(self, error: BirisError, payload: bytes) -> None:
        super().__init__(str(error))
        self.error = error
        self.payload = payload


def _unknown() -> UnknownConnection:
    return UnknownConnection("that connection is closed (or was never opened)")


def _shown(value: object) -> str:
    """A client's word (a user name) fit for a log line: as it is if it is a short printable
    string, else its repr cut short."""
    if isinstance(value, str) and len(value) <= 64 and value.isprintable():
        return value
    return repr(value)[:64]


def _direct(callback: Callable[[zenoh.Query], None]) -> Any:
    """``callback`` as Zenoh's handler, called on the network thread that received each query
    (``indirect=False``): the default hands every query to one Python thread through one
    queue, where a flooding peer's backlog would stand in front of everyone's requests. A Zenoh
    without the option takes the callback as it is."""
    try:
        return zenoh.handlers.Callback(callback, indirect=False)
    except TypeError:
        return callback


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
    """A blocking request's timeout, by the local API's rule
    (:func:`biris_hw.client.checked_timeout`: 0 polls, null waits as long as it takes, negative
    or not a number is refused), held here at most :data:`MAX_WAIT_S` (the client asks again)."""
    seconds = checked_timeout(request.get("timeout", MAX_WAIT_S))
    return MAX_WAIT_S if seconds is None else min(seconds, MAX_WAIT_S)


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
        server: any :class:`biris_hw.sensor.Sensor`: a :class:`~biris_hw.BirisServer`, a
            :class:`~biris_hw.io.record.ReplayServer` played at a speed, another service's
            :class:`~biris_hw.io.net.RemoteSensor`.
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
        status_period: (keyword) seconds between status publications when nothing changes (a
            change is published as the sensor pushes it).
        playback: (keyword) whether ``server`` is a recording that refuses motion and
            configuration itself (then control requests reach it whatever the credentials, and
            are answered with its refusal, a RequestError). Default: the sensor's own
            ``playback``; True for a sensor that can move raises RequestError. A sensor that is
            not ``paced`` (a recording played with ``speed=None``) is refused: one stalled
            reader would stall every client.
        stop_when_controllers_leave: (keyword) dead-man: when the last client that was granted
            a control operation has gone (its liveliness token withdrawn), issue ``stop_scan``,
            so that a continuous scan does not go on for ever. Default False.
        poses: (keyword) on a moving robot, the vehicle's pose on the sensor's hardware clock
            (a :class:`~biris_hw.io.pose.PoseBuffer`, or any
            :class:`~biris_hw.io.moving_sink.PoseFeed`): the service also publishes each pose
            sample on ``odom`` (``nav_msgs/msg/Odometry``) and ``tf`` (``odom -> vehicle``),
            and each completed scan deskewed on ``cloud`` (``sensor_msgs/msg/PointCloud2`` in
            ``odom``), from a sink of the feed of their own, not the reader's thread. Default
            None: none of these.
        grid: (keyword; needs ``poses``) a :class:`~biris_hw.io.grid.GridParams`,
            :class:`~biris_hw.io.grid.CertaintyGrid` or :class:`~biris_hw.io.grid.GridFeeder`:
            the certainty grid, fed every acquisition, published on ``grid``
            (``nav_msgs/msg/OccupancyGrid`` in ``odom``) at a few Hz.
        proximity: (keyword; needs ``poses``) a :class:`~biris_hw.io.proximity.ProximityZone`,
            :class:`~biris_hw.io.proximity.ProximityAlarm` or
            :class:`~biris_hw.io.proximity.ProximityFeeder`: the proximity alarm, fed every
            acquisition, its answer published on ``proximity`` (``biris_msgs/msg/Proximity`` in
            ``vehicle``) five times a second of hardware time. The keys are
            :class:`~biris_hw.io.net.keys.Keys`' (docs/wire-format.md, "Key expressions").

    Raises:
        ValueError: ``grid`` or ``proximity`` without ``poses``; TypeError: ``poses``,
            ``grid`` or ``proximity`` of no kind they take. Nothing is started then.

    The server is not closed on the way out: it belongs to the caller.
    """
    service = Service(server, name, listen, controllers, **options)
    try:
        yield service
    finally:
        service.close()
