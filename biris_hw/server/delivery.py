"""A client connection as the administrator keeps it: its kind, its delivery policy, its queue.

The report's DATA connection is "issued data automatically when a buffer is acquired": the
client sends READY_FOR_DATA and the administrator replies when there is something to give. What
waits for a client that is not ready depends on the connection's :class:`DeliveryPolicy`; what
no longer fits is dropped *and counted*, never lost silently.

Every hand-over -- a parked READY_FOR_DATA replied, or REQUEST_POINT / REQUEST_SCAN_DATA
answered -- stamps the data with ``t_delivered`` (hardware clock) and records its age in the
connection's :class:`LatencyHistogram`. Only the administrator thread touches these objects.
"""

from __future__ import annotations

import threading
import weakref
from collections import deque
from dataclasses import dataclass, field
from typing import TypeVar

from biris_hw.data import ConnectionKind, DeliveryPolicy, Point, Scan
from biris_hw.errors import RequestError
from biris_hw.ipc import Envelope
from biris_hw.protocol import check_policy
from biris_hw.server.latency import LatencyHistogram
from biris_hw.status import ConnectionStatus

__all__ = ["ClientConn", "check_policy", "stamp"]  # check_policy: from biris_hw.protocol

_Data = TypeVar("_Data", bound=Scan | Point)


def stamp(item: _Data, now: float) -> _Data:
    """A copy of ``item`` handed over at ``now`` (arrays are shared: they are read-only).

    What ``dataclasses.replace(item, t_delivered=now)`` gives, without validating again the
    fields ``item`` already holds validated: every delivery to every connection stamps a copy,
    so this is on the administrator's hot path.
    """
    copy = object.__new__(type(item))
    fields = copy.__dict__
    fields.update(item.__dict__)
    fields["t_delivered"] = float(now)
    return copy


_newest: tuple[object, float] = (None, 0.0)
"""The last scan time array whose newest time :func:`_age` looked up, and that time."""


def _age(item: Scan | Point) -> float | None:
    """``item.age``; a buffer handed to many connections is searched for its newest time once
    (its time array is read-only, and shared by every stamped copy)."""
    global _newest
    if isinstance(item, Point):
        return item.age
    delivered, t = item.t_delivered, item.t
    if delivered is None or t.size == 0:
        return None
    seen = _newest  # one read: another server's administrator may replace it meanwhile
    if seen[0] is t:
        return delivered - seen[1]
    newest = float(t.max())
    _newest = (t, newest)
    return delivered - newest


@dataclass
class ClientConn:
    """One open connection: who owns it, what it wants, what waits for it."""

    ident: int
    kind: ConnectionKind
    owner: weakref.ref[threading.Thread]
    policy: DeliveryPolicy = DeliveryPolicy.LATEST
    depth: int = 1
    waiting: Envelope | None = None
    """A READY_FOR_DATA parked until there is something to send."""
    queue: deque[Scan | Point] = field(default_factory=deque)
    dropped: int = 0
    delivered: int = 0
    latency: LatencyHistogram = field(default_factory=LatencyHistogram)

    @property
    def alive(self) -> bool:
        owner = self.owner()
        return owner is not None and owner.is_alive()

    @property
    def wants_scans(self) -> bool:
        return (
            self.kind is ConnectionKind.DATA and self.policy is not DeliveryPolicy.EVERY_ACQUISITION
        )

    @property
    def wants_points(self) -> bool:
        return self.kind is ConnectionKind.DATA and self.policy is DeliveryPolicy.EVERY_ACQUISITION

    def record(self, item: Scan | Point) -> None:
        """Count a hand-over and its latency (``item`` is already stamped)."""
        self.delivered += 1
        age = _age(item)
        if age is not None:
            self.latency.add(age)

    def offer(self, item: Scan | Point, now: float, sent: Scan | Point | None = None) -> None:
        """A new buffer (or acquisition): straight to a waiting client, else into the queue.

        ``sent`` is ``item`` already stamped at ``now``: a buffer handed to many connections at
        once is stamped once and the copy shared (it is immutable, its arrays read-only).
        """
        if self.waiting is not None:
            env, self.waiting = self.waiting, None
            if sent is None:
                sent = stamp(item, now)
            if env.reply((sent, self.dropped)) is not False:
                self.record(sent)
                return
        self.queue.append(item)
        while len(self.queue) > self.depth:  # LATEST: depth 1, so the newer replaces the older
            self.queue.popleft()
            self.dropped += 1

    def lost(self, count: int) -> None:
        """Acquisitions the server never had (a point stream would have carried them)."""
        self.dropped += count

    def ready(self, env: Envelope, now: float, *, poll: bool = False) -> bool:
        """READY_FOR_DATA: reply at once from the queue (True), or park the request (False).

        With ``poll`` (``ready_for_data(timeout=0)``) the request is never parked: an empty
        queue fails it at once with TimeoutError (True). A poll that finds nothing leaves a
        READY_FOR_DATA parked by another thread where it is: it asked for nothing to change.
        """
        if self.queue:
            item = self.queue[0]
            sent = stamp(item, now)
            if env.reply((sent, self.dropped)) is not False:
                self.queue.popleft()
                self.record(sent)
            return True
        if poll:
            env.fail(TimeoutError(f"no data waiting for connection {self.ident}"))
            return True
        if self.waiting is not None:
            self.waiting.fail(RequestError("superseded by a newer READY_FOR_DATA"))
        self.waiting = env
        return False

    def summary(self) -> ConnectionStatus:
        """This connection's part of ``server.status()``."""
        return ConnectionStatus(
            kind=self.kind.name,
            policy=self.policy.name,
            depth=self.depth,
            queued=len(self.queue),
            delivered=self.delivered,
            dropped=self.dropped,
            latency=self.latency.summary(),
        )
