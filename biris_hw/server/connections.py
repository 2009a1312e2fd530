"""The BIRIS server's open connections, and every hand-over of data to a client.

OPEN_REQUEST and CLOSE_REQUEST change the set; a complete scan or a new acquisition is offered to
every DATA connection that wants it; REQUEST_POINT and REQUEST_SCAN_DATA are answered here, so
that every hand-over is stamped and counted the same way. A connection whose owning thread has
ended is released the next time data are offered, so a client that died never holds a queue.
Only the administrator thread calls this.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable

from biris_hw.data import ConnectionKind, Point, Scan
from biris_hw.errors import ConnectionClosed
from biris_hw.ipc import Envelope
from biris_hw.server.counters import Counters
from biris_hw.server.delivery import ClientConn, check_policy, stamp
from biris_hw.server.faults import fail_quietly, log
from biris_hw.status import ConnectionStatus

__all__ = ["Connections"]


class Connections:
    """Open connections by ident; ``counters.deliveries`` counts every hand-over."""

    def __init__(self, clock: Callable[[], float], counters: Counters) -> None:
        self._clock = clock
        self._counters = counters
        self._conns: dict[int, ClientConn] = {}
        self._next = 1
        self._closed_drops = 0
        """Deliveries dropped by connections since closed (status() still counts them)."""

    def get(self, ident: int) -> ClientConn | None:
        return self._conns.get(ident)

    def open(
        self, kind: ConnectionKind, policy: object, depth: object, owner: object
    ) -> ClientConn:
        """OPEN_REQUEST: a new connection owned by the thread ``owner``."""
        chosen, checked = check_policy(kind, policy, depth)
        assert isinstance(owner, threading.Thread)
        conn = ClientConn(self._next, kind, weakref.ref(owner), chosen, checked)
        self._next += 1
        self._conns[conn.ident] = conn
        return conn

    def close(self, ident: int) -> None:
        """CLOSE_REQUEST: a connection that is not open is closed already."""
        conn = self._conns.get(ident)
        if conn is not None:
            self._drop(conn, "closed")

    def _drop(self, conn: ClientConn, why: str) -> None:
        self._conns.pop(conn.ident, None)
        self._closed_drops += conn.dropped
        if conn.waiting is not None:
            fail_quietly(conn.waiting, ConnectionClosed(f"connection {conn.ident} {why}"))
            conn.waiting = None
        log.debug("connection %d released: %s", conn.ident, why)

    def _live(self, points: bool = False) -> list[ClientConn]:
        """Open connections whose owners still run; the others are released on the way.

        ``points`` limits the check to connections that take every acquisition: that path runs
        per acquisition, so it asks no other connection whether its owner lives (those are
        released at the next complete scan).
        """
        live = []
        for conn in list(self._conns.values()):
            if points and not conn.wants_points:
                continue
            if not conn.alive:
                self._drop(conn, "its owning thread has ended")
                continue
            live.append(conn)
        return live

    def deliver(self, scan: Scan) -> None:
        """A complete scan, to every DATA connection that takes scans (one stamped copy for
        all: with a hundred clients, this loop is what the last of them waits for)."""
        now = self._clock()
        sent = stamp(scan, now)
        delivered = 0
        for conn in self._live():
            if conn.wants_scans:
                before = conn.delivered
                conn.offer(scan, now, sent)
                delivered += conn.delivered - before
        self._counters.deliveries += delivered

    def deliver_points(self, points: list[Point], lost: int) -> None:
        """New acquisitions (and how many were lost), to every connection that takes each one."""
        now = self._clock()
        for conn in self._live(points=True):
            if lost:
                conn.lost(lost)
            before = conn.delivered
            for point in points:
                conn.offer(point, now)
            self._counters.deliveries += conn.delivered - before

    def ready(self, env: Envelope, conn: ClientConn, poll: bool = False) -> None:
        """READY_FOR_DATA: answered from the connection's queue, or parked until data come.

        ``poll`` (the message's, for ``ready_for_data(timeout=0)``): answered at once either way,
        with the oldest waiting buffer (or point) or, when none waits, a TimeoutError; never
        parked, so the client's poll needs no deadline of its own.
        """
        before = conn.delivered
        conn.ready(env, self._clock(), poll=poll)
        self._counters.deliveries += conn.delivered - before

    def hand_over(self, env: Envelope, conn: ClientConn, item: Scan | Point | None) -> None:
        """Answer REQUEST_POINT / REQUEST_SCAN_DATA: stamped, and its latency recorded."""
        if item is None:
            env.reply(None)
            return
        sent = stamp(item, self._clock())
        if env.reply(sent) is not False:
            conn.record(sent)
            self._counters.deliveries += 1

    def fail_waiting(self, exc: BaseException, *, forget: bool = True) -> None:
        """Every parked READY_FOR_DATA gets ``exc``; ``forget=False`` leaves them parked."""
        for conn in self._conns.values():
            if conn.waiting is not None:
                fail_quietly(conn.waiting, exc)
                if forget:
                    conn.waiting = None

    def dropped(self) -> int:
        """Deliveries dropped so far, by open and closed connections alike."""
        return self._closed_drops + sum(c.dropped for c in self._conns.values())

    def idents(self) -> tuple[int, ...]:
        """The open connections' numbers, in the order ``summaries`` lists them."""
        return tuple(self._conns)

    def summaries(self) -> dict[int, ConnectionStatus]:
        """Each open connection's part of ``server.status()``."""
        return {c.ident: c.summary() for c in self._conns.values()}
