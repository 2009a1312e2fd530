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

**A service that cannot be reached** -- it stopped, a router in between restarted, the network
is partitioned -- is a :class:`~biris_hw.errors.ConnectionLost`, never a RequestError: the
service's liveliness token is withdrawn (every call waiting for a reply is woken at once), Zenoh
answers a request itself (its ``Timeout``), or a request reaches no service. The client expects
the service back until it is closed: Zenoh reconnects to its endpoints, the token returns, and
each connection is reopened the first time it is used afterwards (same kind, policy and depth;
a controller's with the same credentials), so the user's connection objects carry on and a loop
that catches ConnectionLost and asks again picks up where it stopped. While the service is
lost, a call waits up to :data:`~biris_hw.io.net.reconnect.LOST_PAUSE_S` (never longer than its
own timeout) for it to return before it raises, which paces such a loop. What a connection of
scans missed meanwhile is counted from the scans' numbers (:attr:`RemoteConnection.missed`)
and logged; :attr:`RemoteSensor.outages` says when and for how long. ConnectionClosed is final:
this object or the connection was closed here, or the service refused a connection and would
not reopen it. ``connect(..., reconnect=False)`` makes a service that goes final too (the
behaviour before reconnection existed). Blocking calls (``ready_for_data``, ``wait_idle``) wait
in slices of at most :data:`~biris_hw.io.net.keys.MAX_WAIT_S` on the service, so that a service
that stops answering is noticed whatever the caller's timeout.

A client that is not closed is closed when it is garbage-collected and when the interpreter
exits, before the interpreter waits for threads (:mod:`biris_hw.io.net.lifetime`): Zenoh's
handler threads would otherwise keep the process alive.

**A service that cannot be found** is said with its reason, as soon as the reason is certain:
the endpoints are probed before Zenoh starts (:mod:`biris_hw.io.net.probe`), and a TLS
handshake that fails on every one (a certificate refused, with OpenSSL's reason; a ``tls/``
endpoint on a port without TLS) is raised at once; a client that has heard nothing of its
service :data:`LOOK_S` after its session opened looks at why: no Zenoh link (a ``tcp/``
endpoint on a TLS port), or services of other names answering on its endpoints (named). A
refused connection is waited through (a service may be starting as its client does) and named
if the service has not answered by the timeout; the command line, which starts no service,
says it at once (:func:`~biris_hw.io.net.probe.reachable`). Each is a ConnectionClosed, as "no
service answered" is. The session is a Zenoh peer with no listener (:func:`make_config`'s
``client``): a client opens no port.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import struct
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any, Literal, NoReturn, cast, overload

import zenoh

from biris_hw.angles import RealLike, counts_to_deg, destination_counts
from biris_hw.client import POLL, D, checked_timeout
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Point, Scan
from biris_hw.errors import AccessDenied, BirisError, ConnectionClosed, ConnectionLost, RequestError
from biris_hw.io import codec
from biris_hw.io.net.keys import (
    CONTROL_OPS,
    MAX_WAIT_S,
    RESET_WAIT_S,
    Busy,
    Keys,
    check_name,
    raise_error,
)
from biris_hw.io.net.lifetime import SessionLife, close_at_exit, weak_callback
from biris_hw.io.net.probe import probe_all, speaks_tls
from biris_hw.io.net.reconnect import LOST_PAUSE_S, LinkWatch, Missed, Outage
from biris_hw.io.net.warm import warm
from biris_hw.io.net.zconfig import make_config, zenoh_message
from biris_hw.records import BirisInitRecord, MotorParams
from biris_hw.sensor import ConnectionBase
from biris_hw.status import ServerStatus, StatusChanges, check_change

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor

__all__ = ["RemoteConnection", "RemoteSensor", "Subscription", "connect"]

log = logging.getLogger(__name__)

REPLY_MARGIN_S = 5.0
"""How much longer than the service's own bound a call waits for a reply before it gives up."""

CLOSE_REPLY_S = 1.0
"""How long a close waits for the service's answer: the service releases whatever a client
leaves behind when the client's token goes, so a close never waits long for a lost one."""

CONNECT_TIMEOUT_S = 10.0

LOOK_S = 1.0
"""How long after its session opens a client that has heard nothing of its service looks at
why (:meth:`RemoteSensor._look`): no Zenoh link to any endpoint, or other services answering
there. A service that is there answers in milliseconds."""

_LOOK_AGAIN_S = 0.25
"""Between two such looks, until the service answers or the timeout is over."""

_DENIED = ("needs a controller's credentials", "needs a reader's credentials")
"""The service's words for credentials it does not accept, the same whether none, wrong ones or
a reader's were sent: the client says which it sent."""

MAX_REOPENS = 3
"""Reopens one call may make before it gives up: a service that refuses each new connection as
unknown at once is not going to keep one."""

_RESEND_FIRST_S = 0.02
"""First pause before a request that reached no service is sent again (then doubled): what
follows a token's return by a moment, until the service's queryable is routed again."""

_SETTLE_S = 2.0
"""How long after the service's return a request answered by nobody is sent again (its
queryable is routed a moment after its token returns); at other times such a request is a
TimeoutError (nothing serves it here: an access-control rule dropped it, say)."""

_GRACE_S = 0.1
"""How long a request answered by nobody waits for the service's token to go (a service that
stops withdraws its queryable first): ConnectionLost then, rather than TimeoutError."""

_CLOSING = ("the service is closing",)
"""Its words for a request that came as it stops (its token goes a moment later)."""

_UNKNOWN = ("that connection is closed (or was never opened)",)
"""Its words for a request naming a connection it does not hold, refused unread."""


class _Released(ConnectionClosed):
    """The service answered ConnectionClosed for a connection this client has not closed:
    it does not hold it (released when the client's token went, or issued by an instance of
    the service that has restarted since), it closed it under a request as it stopped, or it
    released the client while this ``open`` ran. The connection is reopened; a call fails with
    ConnectionClosed only when the service will not reopen it."""

    def __init__(self, message: str, unread: bool) -> None:
        super().__init__(message)
        self.unread = unread
        """Refused before anything was done (the service does not hold the connection), so
        the request may be sent again on the reopened one."""


class Subscription:
    """One subscription to the service's publications; counts what it missed.

    Each publication carries the service's counter of that kind, so a jump is a publication this
    subscriber never got (Zenoh dropped it rather than slow the sensor): :attr:`dropped`. A
    publication is counted in :attr:`received` once the callback has returned from it, so that a
    reader who sees ``received`` reach n has had its callback run n times.
    """

    def __init__(self) -> None:
        self.received = 0
        self.dropped = 0
        self._last: dict[str, int] = {}
        self._subscriber: Any = None
        self._life: SessionLife | None = None

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
            if self._life is not None:
                self._life.untrack(self._subscriber)
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
        reconnect: bool = True,
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
        self.reconnect = bool(reconnect)
        """Expect a service that cannot be reached to come back (ConnectionLost, and the
        connections reopened), rather than take it as gone for good (ConnectionClosed)."""
        self._closed = False
        self._closing = threading.Event()
        self._alive = threading.Event()
        self._gone = threading.Event()
        self._link = LinkWatch(self.name)
        self._missed = 0
        self._reopened = 0
        self._instance: str | None = None
        """The Zenoh session id of the service that answered last."""
        self.restarts = 0
        """Times a new instance of the service answered (it was restarted meanwhile): what its
        sensor made before is numbered afresh, so gaps across a restart are not counted."""
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
            client=True,
        )
        self._probe_options = options
        """The Zenoh options the endpoints are probed with (TLS files)."""
        self._refuse_tls(endpoints)
        try:
            self._session = zenoh.open(config)
        except Exception as exc:  # zenoh.ZError: a malformed endpoint, a TLS file missing...
            raise RequestError(f"cannot start the Zenoh session: {zenoh_message(exc)}") from exc
        self._life = SessionLife(self._session, f"the remote sensor {self.name!r}")
        try:
            # held weakly by Zenoh's threads: an unclosed client can be collected, and closed
            self._service_sub = self._session.liveliness().declare_subscriber(
                self.keys.service_token, weak_callback(self._on_service_token), history=True
            )
            self._life.track(self._service_sub)
            self._token = self._session.liveliness().declare_token(
                self.keys.client_token(self.client)
            )
            self._await_service(timeout, endpoints)
            self._status_sub = self._session.declare_subscriber(
                self.keys.status, weak_callback(self._on_status_sample)
            )
            self._life.track(self._status_sub)
            self._learn()
        except BaseException:
            self._life.close()
            raise
        self._finalizer = self._life.collect_with(self)
        close_at_exit(self)

    def _refuse_tls(self, endpoints: Sequence[str]) -> None:
        """Probe the endpoints (:mod:`biris_hw.io.net.probe`) and raise at once when the TLS
        handshake fails on every one: a certificate refused (its reason said), a ``tls/``
        endpoint on a port without TLS. Waiting would not change that; a refused connection
        might (a service starting as its client does), and is said only if the service has
        not answered by the timeout (:meth:`_not_found`), as the command line says it at once
        (:func:`~biris_hw.io.net.probe.reachable`).

        Raises:
            ConnectionClosed: every endpoint's TLS handshake failed.
            RequestError: a malformed endpoint, TLS files that cannot be used.
        """
        if not endpoints:
            return
        found = probe_all(endpoints, self._probe_options)
        if all(p.verdict in ("tls", "no_tls") for p in found):
            reasons = "; ".join(map(str, found))
            raise ConnectionClosed(f"no BIRIS service {self.name!r} can be reached: {reasons}")

    def _await_service(self, timeout: float, endpoints: Sequence[str]) -> None:
        """Wait up to ``timeout`` for the service's token; look at why it has not come from
        :data:`LOOK_S` on, and raise as soon as the reason is certain.

        Raises:
            ConnectionClosed: no such service (with what was seen instead).
        """
        start = time.monotonic()
        deadline = start + timeout
        look_at = start + LOOK_S
        others_before: list[str] = []
        while not self._alive.wait(max(0.0, min(deadline, look_at) - time.monotonic())):
            now = time.monotonic()
            if now >= deadline:
                break
            look_at = now + _LOOK_AGAIN_S
            if self._linked():
                if not endpoints:
                    continue  # scouting: others may still come
                others = self._services_seen()
                if others and others == others_before:  # twice: the link's whole picture
                    where = ", ".join(endpoints)
                    raise ConnectionClosed(
                        f"no BIRIS service {self.name!r} on {where}: the service there is "
                        f"{_names(others)} (--connect {others[0]}; `biris list` lists them)"
                    )
                others_before = others
                continue
            for each in endpoints:  # not linked: a TLS port spoken to in plain TCP?
                if each.startswith("tcp/") and speaks_tls(each):
                    raise ConnectionClosed(
                        f"no BIRIS service {self.name!r} can be reached: {each} is a TLS port: "
                        f"connect to tls/{each[4:]} (with --tls-ca FILE)"
                    )
        if self._alive.is_set():
            return
        raise ConnectionClosed(self._not_found(timeout, endpoints))

    def _linked(self) -> bool:
        """The session has a Zenoh link to some peer or router."""
        try:
            info = self._session.info
            return any(True for _ in info.peers_zid()) or any(True for _ in info.routers_zid())
        except Exception:  # an unstable Zenoh API: then nothing is concluded from links
            return True

    def _services_seen(self) -> list[str]:
        """Names of the BIRIS services whose liveliness token this session sees (ours aside)."""
        names: set[str] = set()
        try:
            replies = self._session.liveliness().get(Keys("*").service_token, timeout=0.5)
            for reply in replies:
                if reply.ok is not None:
                    parts = str(reply.ok.key_expr).split("/")
                    if len(parts) > 1 and parts[1] != self.name:
                        names.add(parts[1])
        except Exception:  # closed meanwhile: nothing seen
            return []
        return sorted(names)

    def _not_found(self, timeout: float, endpoints: Sequence[str]) -> str:
        """Why no service of our name answered within ``timeout``, with what was seen."""
        where = ", ".join(endpoints) or "multicast scouting"
        text = f"no BIRIS service {self.name!r} answered within {timeout:g} s ({where})"
        with contextlib.suppress(RequestError):
            failed = [p for p in probe_all(endpoints, self._probe_options) if p.failed]
            if failed and len(failed) == len(endpoints):
                return f"{text}: {'; '.join(map(str, failed))}"
        others = self._services_seen()
        if others:
            return f"{text}; answering: {_names(others)} (`biris list` lists them)"
        if not self._linked():
            if endpoints:
                return (
                    f"{text}: no Zenoh session could be set up although the port accepts "
                    "connections (a service behind link authentication, --link-user? mutual "
                    "TLS? not a Zenoh endpoint?)"
                )
            return f"{text}: scouting found no Zenoh peer (give --endpoint tcp/HOST:PORT)"
        return text

    def _learn(self) -> None:
        """Ask the service what it serves (a recording? paced? its init record) and take its
        status as the one the publications are compared with. A service that says nothing of
        the kind (an older one) serves a live sensor whose record is unknown."""
        try:
            payload, _, attachment = self._query("status", {"info": True})
        except (BirisError, TimeoutError, ConnectionLost):  # reader credentials we do not
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
        """The service's liveliness token came or went (Zenoh's thread)."""
        if sample.kind == zenoh.SampleKind.PUT:
            self._gone.clear()
            self._alive.set()
            self._link.back("its liveliness token returned")
            self._wake()
            return
        self._gone.set()
        self._link.lost("its liveliness token was withdrawn")
        with self._lock:
            waiters = list(self._waiters)
        for waiter in waiters:
            waiter.wake()
        self._wake()

    @property
    def gone(self) -> bool:
        """The service's liveliness token is withdrawn (it stopped, or the network between is
        down); it may come back (see :attr:`lost`)."""
        return self._gone.is_set()

    @property
    def lost(self) -> bool:
        """The service cannot be reached now: calls raise ConnectionLost until it is back."""
        return self._link.is_lost

    def lost_for(self) -> float:
        """Seconds since the service was lost (0.0 while it can be reached)."""
        return self._link.lost_for()

    @property
    def outages(self) -> tuple[Outage, ...]:
        """The spans during which the service could not be reached (the last 100), the one
        under way last with ``back_at`` None."""
        return self._link.outages

    @property
    def missed(self) -> int:
        """Scans the service's sensor made that this client's connections never got because
        the service was lost meanwhile (each connection's :attr:`RemoteConnection.missed`,
        closed ones included)."""
        with self._lock:
            return self._missed

    @property
    def reopened(self) -> int:
        """Connections reopened so far after the service had released them (or restarted)."""
        with self._lock:
            return self._reopened

    def _note_reopen(self, conn: RemoteConnection[Any], old_ident: int) -> None:
        with self._lock:
            self._reopened += 1
        log.info("connection %d to %r reopened as %d (%s)", old_ident, self.name, conn.ident, conn)

    def _note_missed(self, conn: RemoteConnection[Any], count: int, words: str) -> None:
        with self._lock:
            self._missed += count
        log.warning(
            "connection %d to %r missed %s while the service was lost", conn.ident, self.name, words
        )

    # -- requests --------------------------------------------------------------------------------
    def _query(
        self,
        op: str,
        body: dict[str, Any],
        wait_s: float = 0.0,
        *,
        pause_s: float | None = None,
        reply_s: float | None = None,
    ) -> tuple[bytes, str, bytes | None]:
        """One request; (payload, encoding, attachment) of the reply, or its error raised.

        ``wait_s`` is how long the service may hold it (a blocking read); ``reply_s`` how much
        longer the reply is waited for (default :data:`REPLY_MARGIN_S`); ``pause_s`` how long
        to wait for a lost service to come back before raising ConnectionLost (default
        :data:`LOST_PAUSE_S`; a request that reached no service is sent again meanwhile:
        nothing was done).

        Raises:
            ConnectionClosed: this object is closed (or, with ``reconnect=False``, the service
                has gone).
            ConnectionLost: the service cannot be reached (see the module).
            TimeoutError: nobody answered, with the service's token there (an access-control
                rule dropped the request, say).
        """
        request: dict[str, Any] = {**body, "client": self.client}
        if op in CONTROL_OPS or self.reader_credentials:
            request.update(self._credentials)
        payload = json.dumps(request).encode()
        give_up = time.monotonic() + (LOST_PAUSE_S if pause_s is None else pause_s)
        resend = _RESEND_FIRST_S
        sent = False
        while True:
            # the pause is for a call made while the service is lost; one that was under way
            # when it went raises at once (the first sign of the loss reaches the caller)
            self._usable(op, time.monotonic() if sent else give_up)
            sent = True
            waiter = self._ask(op, payload, wait_s, REPLY_MARGIN_S if reply_s is None else reply_s)
            reply = waiter.answer
            if reply is None:
                if self._closed:
                    raise ConnectionClosed(f"the connection to service {self.name!r} is closed")
                if self._gone.is_set() and not self.reconnect:
                    raise ConnectionClosed(f"service {self.name!r} has gone ({op} not answered)")
                if waiter.finished and not self._gone.is_set():
                    # over, and answered by nobody: nothing was done. Just after the service's
                    # return its queryable may not be routed yet: ask again, within the pause.
                    left = give_up - time.monotonic()
                    if self._link.back_within(_SETTLE_S) and left > 0:
                        self._closing.wait(min(resend, left))
                        resend *= 2
                        continue
                    # a service that stops withdraws its token a moment after its queryable
                    if not self._gone.wait(_GRACE_S):
                        raise TimeoutError(f"{op}: no reply from service {self.name!r}")
                if not self._gone.is_set():
                    self._link.lost(f"{op} was not answered")
                raise self._link.error(op)
            ok = reply.ok
            if ok is None:
                err = reply.err
                self._raise_error(op, err.payload.to_bytes() if err is not None else b"", reply)
            self._answered(reply)
            attachment = ok.attachment
            return (
                ok.payload.to_bytes(),
                str(ok.encoding),
                attachment.to_bytes() if attachment is not None else None,
            )

    def _usable(self, op: str, give_up: float) -> None:
        """Return when a request may be sent: this object is open and the service's token is
        there (waited for until ``give_up``), or raise what the caller is to see."""
        if self._closed:
            raise ConnectionClosed(f"the connection to service {self.name!r} is closed")
        if not self._gone.is_set():
            return
        if not self.reconnect:
            raise ConnectionClosed(f"service {self.name!r} has gone")
        self._link.wait_back(give_up - time.monotonic())
        if self._closed:
            raise ConnectionClosed(f"the connection to service {self.name!r} is closed")
        if self._gone.is_set():
            raise self._link.error(op)

    def _ask(self, op: str, payload: bytes, wait_s: float, reply_s: float) -> _Waiter:
        """Send one query and wait for its reply, its end, or a wake (gone, closed)."""
        waiter = _Waiter()
        with self._lock:
            self._waiters.add(waiter)
        try:
            self._session.get(
                self.keys.rpc(op),
                zenoh.handlers.Callback(waiter.reply, waiter.done),
                payload=payload,
                encoding=zenoh.Encoding.APPLICATION_JSON,
                timeout=wait_s + reply_s,
            )
            waiter.wait(wait_s + 2 * reply_s)
        except zenoh.ZError as exc:  # the session closed under us (by close(), or at exit)
            if not self._closed:
                raise self._link.error(f"{op} ({exc})") from None
        finally:
            with self._lock:
                self._waiters.discard(waiter)
        return waiter

    def _answered(self, reply: zenoh.Reply) -> None:
        """The service answered (whatever it said): an outage under way is over, and a reply
        from another Zenoh session than before means the service has restarted."""
        if self._link.is_lost:
            self._link.back("it answered")
        try:
            replier = reply.replier_id
        except Exception:  # an unstable Zenoh API: without it, restarts go unnoticed
            return
        if replier is None:
            return
        instance = str(replier.zid)
        with self._lock:
            if instance == self._instance:
                return
            known, self._instance = self._instance, instance
            if known is not None:
                self.restarts += 1
        if known is not None:
            log.info("BIRIS service %r has restarted (a new Zenoh session answers)", self.name)

    def _raise_error(self, op: str, payload: bytes, reply: zenoh.Reply) -> NoReturn:
        """Raise the exception an error reply stands for. The service's errors are JSON
        objects; anything else is Zenoh's own reply (``Timeout``: the service did not answer
        in time), so the service is lost, not refusing."""
        try:
            body = json.loads(payload)
        except (ValueError, UnicodeDecodeError):
            body = None
        if not isinstance(body, dict) or "error" not in body:
            text = payload[:80].decode("utf-8", "replace") or "an empty error"
            self._link.lost(f"{op}: Zenoh replied {text!r}")
            raise self._link.error(op)
        self._answered(reply)
        if body["error"] == "ConnectionClosed":
            message = str(body.get("message", ""))
            kind = str(body.get("class", "ConnectionClosed"))
            if message in _CLOSING or kind == "ServiceClosing":
                self._link.lost("the service is closing")
                raise self._link.error(op)
            if kind in ("ConnectionClosed", "UnknownConnection"):
                # closed by the service, not by us: unknown to it, released with our token,
                # or closed under a request as the service stops. A refinement (EndOfRecording:
                # a recording played to its end) is final and raised as it is.
                unread = kind == "UnknownConnection" or message in _UNKNOWN
                raise _Released(f"{op}: {message}", unread)
        try:
            raise_error(payload, op)
        except AccessDenied as exc:
            raise self._denied(op, exc) from None
        raise AssertionError("unreachable")  # raise_error always raises

    def _denied(self, op: str, exc: AccessDenied) -> AccessDenied:
        """The service's AccessDenied, saying whose credentials it refused when some were sent:
        its own words for that are the same as for none (``needs a controller's
        credentials``), so the client says what it knows -- that ``user``'s were sent -- and the
        likely reasons; a service that says why keeps its words, in brackets."""
        user = self._credentials.get("user")
        control = op in CONTROL_OPS
        if user is None or not (control or self.reader_credentials):
            return exc
        text = str(exc)
        if any(words in text for words in _DENIED):
            why = "a wrong password or an unknown user"
            if control:
                why += ", or a reader's rather than a controller's"
        else:
            why = text.removeprefix(f"{op}: ").removesuffix("; nothing was done")
        done = "; nothing was done" if control else ""
        return AccessDenied(
            f"{op}: the service refused the credentials of user {user!r} ({why}){done}"
        )

    def _json(
        self,
        op: str,
        body: dict[str, Any],
        wait_s: float = 0.0,
        reply_s: float | None = None,
        pause_s: float | None = None,
    ) -> Any:
        payload, _, _ = self._query(op, body, wait_s, pause_s=pause_s, reply_s=reply_s)
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
            ConnectionLost: the service cannot be reached now.
            ConnectionClosed: this object is closed.
            AccessDenied: the service requires reader credentials and has none from us.
        """
        try:
            kind = ConnectionKind(kind)
            policy = DeliveryPolicy(policy)
        except ValueError:
            raise RequestError(f"open: no kind {kind!r} or policy {policy!r}") from None
        token, ident, depth_used = self._open_token(kind, policy, depth)
        if kind is ConnectionKind.DATA:  # the codec's first use here, not on the first item
            warm("point" if policy is DeliveryPolicy.EVERY_ACQUISITION else "scan")
        conn: RemoteConnection[Any] = RemoteConnection(self, ident, kind, policy, depth_used, token)
        with self._lock:
            self._connections.append(conn)
        return conn

    def _open_token(
        self, kind: ConnectionKind, policy: DeliveryPolicy, depth: int | None
    ) -> tuple[str, int, int]:
        """``open`` on the service: (token, ident, depth used). An open that met the release
        of this client's earlier connections (the service saw our token go and come back) is
        asked again."""
        body = {"kind": kind.name, "policy": policy.value, "depth": depth}
        for attempt in range(MAX_REOPENS):
            try:
                answer = self._json("open", body)
                break
            except _Released as exc:  # it released this client meanwhile: nothing was done
                if attempt == MAX_REOPENS - 1:
                    raise ConnectionClosed(str(exc)) from None
        try:
            return str(answer["conn"]), int(answer["ident"]), int(answer["depth"])
        except (KeyError, TypeError, ValueError):
            raise RequestError("open: unreadable reply from the service") from None

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
            ConnectionLost: the service cannot be reached (a wait for a newer status raises it
                once the service's token has been gone for :data:`LOST_PAUSE_S`, or its
                ``timeout`` if shorter).
            ConnectionClosed: this object is closed.
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
        give_up: float | None = None  # while the service is gone: when to say it is lost
        with self._news:
            while True:
                if self._closed:
                    raise ConnectionClosed(f"the connection to service {self.name!r} is closed")
                if conn is not None and conn.closed:
                    raise ConnectionClosed(f"connection {conn.ident} is closed")
                now = time.monotonic()
                left = None if deadline is None else deadline - now
                wait = left
                if self._gone.is_set():
                    if not self.reconnect:
                        raise ConnectionClosed(f"service {self.name!r} has gone")
                    if give_up is None:
                        pause = LOST_PAUSE_S if left is None else min(LOST_PAUSE_S, left)
                        give_up = now + max(0.0, pause)
                    if now >= give_up:
                        raise self._link.error("status")
                    wait = give_up - now
                else:
                    give_up = None
                    latest = self._latest
                    if latest is not None and self._changes.change > after:
                        return latest
                    if seconds == POLL or (left is not None and left <= 0):
                        raise TimeoutError(
                            f"the status of {self.name!r} has not changed since {after}"
                        )
                self._news.wait(wait)

    def clock(self) -> float:
        """The newest hardware time the service's sensor has been seen at (in a status reply
        or a datum's stamp); 0.0 before any."""
        with self._news:
            return self._clock_s

    def subscribe(
        self,
        what: Literal["point", "scan", "status", "fault", "odom", "grid", "proximity"],
        callback: Callable[[Any], None],
        *,
        direction: Direction | None = None,
    ) -> Subscription:
        """Call ``callback`` with every publication of ``what``: a Point per acquisition, a Scan
        per completed scan (of ``direction``, or both), a ServerStatus, a HardwareFault; on a
        service of a moving robot (``serve(..., poses=, grid=, proximity=)``) a
        :class:`~biris_hw.io.codec.PoseMessage` per vehicle pose sample (``odom``), a
        :class:`~biris_hw.io.codec.OccupancyGridMessage` per certainty grid (``grid``) and a
        :class:`~biris_hw.io.codec.ProximityMessage` per answer of the proximity alarm
        (``proximity``): a service without them publishes none, and the callback is never
        called.

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
        elif what == "odom":
            key = keys.odom

            def decode(data: bytes) -> codec.PoseMessage:
                return codec.decode_pose(data, codec.ODOMETRY)

        elif what == "grid":
            key, decode = keys.grid, codec.decode_occupancy_grid
        elif what == "proximity":
            key, decode = keys.proximity, codec.decode_proximity
        else:
            raise RequestError(f"subscribe: nothing called {what!r}")
        # the codec's first use costs ~0.1 s of interpreter time: paid here, on the caller's
        # thread, rather than by the first publications, which would queue behind it
        if what == "odom":
            codec.warm(codec.ODOMETRY)
        elif what == "grid":
            codec.warm(codec.OCCUPANCY_GRID)
        elif what == "proximity":
            codec.warm(codec.PROXIMITY)
        else:
            warm(what)
        subscription = Subscription()

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                value = decode(sample.payload.to_bytes())
            except codec.WireError:
                subscription.dropped += 1
            else:
                callback(value)
            finally:
                subscription._count(str(sample.key_expr), sample.attachment)

        subscription._subscriber = self._session.declare_subscriber(key, on_sample)
        subscription._life = self._life  # undeclared with the session, if not before
        self._life.track(subscription._subscriber)
        return subscription

    def close(self) -> None:
        """Close every connection opened here, then leave (idempotent). Bounded: a service that
        cannot be reached is not waited for (it releases what we leave once our token goes),
        and Zenoh's close at most :data:`~biris_hw.io.net.lifetime.CLOSE_WAIT_S`."""
        if self._closed:
            return
        with self._lock:
            connections = list(self._connections)
        for conn in connections:
            if self._gone.is_set() or self._link.is_lost:
                conn._forget()  # nobody to tell
                continue
            with contextlib.suppress(BirisError, TimeoutError, ConnectionLost):
                conn.close()
        self._closed = True
        self._closing.set()
        self._link.stop()
        with self._lock:
            waiters = list(self._waiters)
        for waiter in waiters:
            waiter.wake()
        self._wake()
        self._finalizer.detach()
        self._life.close()  # its subscribers first (their threads end), then the session

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
        self.answer: zenoh.Reply | None = None
        self.finished = False
        """Zenoh said the query is over (its replies, or none: nobody answered)."""
        self._woken = False

    def reply(self, reply: zenoh.Reply) -> None:
        with self._cond:
            if self.answer is None:
                self.answer = reply
            self._cond.notify_all()

    def done(self) -> None:
        with self._cond:
            self.finished = True
            self._cond.notify_all()

    def wake(self) -> None:
        """Stop waiting (the service went, or the client is closing)."""
        with self._cond:
            self._woken = True
            self._cond.notify_all()

    def wait(self, timeout: float) -> None:
        with self._cond:
            self._cond.wait_for(
                lambda: self.answer is not None or self.finished or self._woken, timeout
            )


class RemoteConnection(ConnectionBase[D]):
    """A connection through the service: the methods, results and errors of a local one.

    It outlives the service's side of it: when the service has released it (the client's
    token went during an outage) or no longer knows it (the service restarted), the next call
    reopens it -- same kind, policy and depth -- and goes on; :attr:`ident` is then the new
    connection's, :attr:`reopened` counts the reopens and :attr:`missed` the scans made in
    between that it never got.
    """

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
        self._reopen_lock = threading.Lock()
        self._dropped_before = 0
        """What the connections it replaced had dropped (``dropped`` goes on from there)."""
        self._gaps = Missed()
        self._instance = sensor._instance
        """The service instance its token came from (see :attr:`RemoteSensor.restarts`)."""
        self.reopened = 0
        """Times the service's side of it was opened again (see the class)."""

    @property
    def missed(self) -> int:
        """Scans the sensor made while the service was lost that this connection never got:
        the gaps in ``seq`` across its reopens (a DATA connection of scans; see
        :class:`~biris_hw.io.net.reconnect.Missed`). Besides :attr:`dropped`, which the server
        counts."""
        return self._gaps.count

    def _where(self) -> str:
        return f"{self._sensor.name}:"

    def _request(
        self, op: str, body: dict[str, Any], wait_s: float = 0.0, pause_s: float | None = None
    ) -> tuple[bytes, str, bytes | None]:
        """One request on this connection, reopened first if the service no longer holds it.
        A request it refused unread is sent again on the reopened connection; a read it
        closed the connection under is too (nothing was taken); a control operation it closed
        the connection under is not (whether it was done is unknown): ConnectionLost, and
        the next call reopens."""
        self._check_open()
        for attempt in range(MAX_REOPENS + 1):
            token = self._token
            try:
                return self._sensor._query(op, {"conn": token, **body}, wait_s, pause_s=pause_s)
            except _Released as exc:
                self._check_open()
                if not self._sensor.reconnect or attempt == MAX_REOPENS:
                    raise ConnectionClosed(
                        f"connection {self.ident}: the service no longer holds it ({exc})"
                    ) from None
                if op in CONTROL_OPS and not exc.unread:
                    raise ConnectionLost(
                        f"{op}: service {self._sensor.name!r} closed connection {self.ident} "
                        "under the request (is it stopping?): whether it was done is unknown"
                    ) from None
                self._reopen(token)
        raise AssertionError("unreachable")

    def _reopen(self, old: str) -> None:
        """Open the service's side again in place of ``old`` (once, whoever asks first)."""
        sensor = self._sensor
        with self._reopen_lock:
            if self._token != old:
                return  # another thread has reopened it meanwhile
            try:
                token, ident, _ = sensor._open_token(self.kind, self.policy, self.depth)
            except (ConnectionLost, ConnectionClosed, Busy):
                raise  # Busy: nothing was done, the next call tries again
            except BirisError as exc:  # AccessDenied, RequestError: it will not come back
                raise ConnectionClosed(
                    f"connection {self.ident} was released by service {sensor.name!r} and "
                    f"could not be reopened: {exc}"
                ) from exc
            old_ident = self.ident
            self._token, self.ident = token, ident
            self._dropped_before = self.dropped
            if sensor._instance != self._instance:  # a restarted service numbers afresh
                self._gaps.forget()
                self._instance = sensor._instance
            else:
                self._gaps.mark(self.dropped)
            self.reopened += 1
        sensor._note_reopen(self, old_ident)
        if self._closed:  # closed by its user while it reopened: the new one goes too
            with contextlib.suppress(BirisError, TimeoutError, ConnectionLost):
                sensor._json("close", {"conn": token}, reply_s=CLOSE_REPLY_S, pause_s=0.0)

    def _call(self, op: str, body: dict[str, Any] | None = None, wait_s: float = 0.0) -> Any:
        payload, _, _ = self._request(op, body or {}, wait_s)
        try:
            return json.loads(payload)
        except ValueError:
            raise RequestError(f"{op}: unreadable reply from the service") from None

    def _data(
        self, op: str, body: dict[str, Any], wait_s: float = 0.0, pause_s: float | None = None
    ) -> Any:
        try:
            payload, encoding, attachment = self._request(op, body, wait_s, pause_s)
        except ConnectionLost:
            if op == "ready_for_data":  # its reply, an item taken from the queue, may be lost
                self._gaps.mark(self.dropped)
            raise
        if attachment is not None:
            with contextlib.suppress(ValueError, KeyError, TypeError):
                self.dropped = self._dropped_before + int(json.loads(attachment)["dropped"])
        if encoding.endswith(codec.SCAN):
            scan = codec.decode_scan(payload)
            if scan.n_acq:
                self._sensor._saw(float(scan.t[-1]))
            gap = self._gaps.saw(scan, self.dropped)
            if gap is not None:
                self._sensor._note_missed(self, *gap)
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

        Waits in slices of at most MAX_WAIT_S on the service, so that a service that stops
        answering is noticed whatever ``timeout`` is.

        Raises:
            ConnectionLost: the service cannot be reached (see the module); asking again once
                it is back carries on, on a reopened connection if the service released this
                one (:attr:`missed` counts the scans made in between).
            ConnectionClosed: this connection or its sensor was closed here, or the service
                would not reopen it.
            TimeoutError: nothing within ``timeout``.
        """
        return cast(D, self._blocking("ready_for_data", timeout))

    def _blocking(self, op: str, timeout: RealLike | None) -> Any:
        seconds = checked_timeout(timeout)
        if seconds == POLL:
            return self._data(op, {"timeout": 0}, pause_s=0.0)
        deadline = None if seconds is None else time.monotonic() + seconds
        while True:
            left = MAX_WAIT_S if deadline is None else deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"{op}: nothing within {seconds:g} s")
            wait = min(left, MAX_WAIT_S)
            try:
                return self._data(op, {"timeout": wait}, wait, pause_s=min(LOST_PAUSE_S, left))
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
        whose token goes meanwhile still raises ConnectionLost at once (whether the reset ran
        is then unknown: its status says).
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
            self._sensor._json("close", {"conn": self._token}, reply_s=CLOSE_REPLY_S, pause_s=0.0)
        except (ConnectionClosed, TimeoutError, ConnectionLost):
            pass  # gone already, or the service releases it when our token goes

    def _forget(self) -> None:
        """Closed here without telling the service (it cannot be reached)."""
        self._closed = True


if TYPE_CHECKING:

    def _is_a_sensor(remote: RemoteSensor) -> Sensor:
        return remote  # mypy holds RemoteSensor to biris_hw.sensor.Sensor


def _names(names: Sequence[str]) -> str:
    return ", ".join(repr(n) for n in names)


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
        reconnect: (keyword) expect a service that cannot be reached to come back (default
            True): calls raise ConnectionLost meanwhile and the connections are reopened when
            it is back. False: its going is final, ConnectionClosed.

    Raises:
        ConnectionClosed: no such service answered in time.
    """
    return RemoteSensor(name, endpoints, user, password, **options)
