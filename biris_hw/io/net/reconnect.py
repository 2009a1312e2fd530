"""Riding out the network: when a remote client has lost its service, for how long, and what it
missed.

A remote client (:class:`~biris_hw.io.net.RemoteSensor`) loses its service in three ways that
look alike from its side: the service's liveliness token is withdrawn (the service stopped, a
router in between restarted, a partition outlasted Zenoh's lease), a request is answered by
Zenoh itself rather than by the service (its ``Timeout`` reply: a partition shorter than the
lease), or a request reaches no service at all. None of them says the service refused
anything, and each may end by itself -- Zenoh reconnects to its endpoints and the token comes
back -- so each is a :class:`~biris_hw.errors.ConnectionLost`, never a RequestError, and never
the final :class:`~biris_hw.errors.ConnectionClosed`.

:class:`LinkWatch` keeps that state for one client: lost since when, back when, the
:class:`Outage` records, and the log lines that say so. :class:`Missed` counts, for one
connection of scans the service had to reopen, what the sensor made while it was away: a gap
in the scans' per-direction ``seq``.

:data:`RIDE_OUT_S` is how long the project's long-running consumers (``biris watch
--connect``, the feed of ``biris record --connect``) wait for a lost service before they give up
and say what they missed.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time

from biris_hw.data import Direction, Scan
from biris_hw.errors import RIDE_OUT_S, ConnectionLost

__all__ = [
    "LOST_PAUSE_S",
    "RIDE_OUT_S",
    "LinkWatch",
    "Missed",
    "Outage",
]

log = logging.getLogger("biris_hw.io.net.remote")


LOST_PAUSE_S = 1.0
"""How long a call made while the service is lost waits for it to come back (never longer
than the call's own timeout) before it raises ConnectionLost: a loop that retries on
ConnectionLost is paced by it, rather than spinning."""

MAX_OUTAGES = 100
"""Outages kept in :attr:`LinkWatch.outages` (the oldest are forgotten, counted in
:attr:`LinkWatch.lost_count`)."""


@dataclasses.dataclass(frozen=True)
class Outage:
    """One span during which the service could not be reached."""

    lost_at: float
    """When the first sign came (``time.time()``, seconds since the epoch)."""
    back_at: float | None
    """When the service answered again (``time.time()``), or None while it is still lost."""
    why: str
    """The first sign, in words."""

    @property
    def seconds(self) -> float:
        """How long it lasted (so far, while it goes on)."""
        end = time.time() if self.back_at is None else self.back_at
        return max(0.0, end - self.lost_at)

    def describe(self) -> str:
        """``"12:01:02.250-12:01:05.500 (3.2 s)"``: the span, for a message."""
        start = _clock(self.lost_at)
        end = "now" if self.back_at is None else _clock(self.back_at)
        return f"{start}-{end} ({self.seconds:.1f} s)"


def _clock(t: float) -> str:
    stamp = time.localtime(t)
    return time.strftime("%H:%M:%S", stamp) + f".{int((t % 1) * 1000):03d}"


class LinkWatch:
    """Whether one remote client can reach its service now, and its outages so far.

    Thread-safe; :meth:`lost` and :meth:`back` may come from Zenoh's threads (the service's
    token) or from callers (a request Zenoh answered, or that reached nobody).
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._cond = threading.Condition()
        self._since: float | None = None
        """time.monotonic() of the first sign of the outage under way, else None."""
        self._outages: list[Outage] = []
        self._stopped = False
        self._back: float | None = None
        """time.monotonic() of the last return, else None."""
        self.lost_count = 0
        """Outages since the client connected."""

    @property
    def is_lost(self) -> bool:
        return self._since is not None

    def lost_for(self) -> float:
        """Seconds since the outage under way began (0.0 when the service is reachable)."""
        since = self._since
        return 0.0 if since is None else max(0.0, time.monotonic() - since)

    def back_within(self, seconds: float) -> bool:
        """The service came back from an outage less than ``seconds`` ago."""
        back = self._back
        return back is not None and time.monotonic() - back < seconds

    @property
    def outages(self) -> tuple[Outage, ...]:
        with self._cond:
            return tuple(self._outages)

    def lost(self, why: str) -> None:
        """A sign that the service cannot be reached; the first one opens an outage."""
        with self._cond:
            if self._since is not None:
                return
            self._since = time.monotonic()
            self.lost_count += 1
            self._outages.append(Outage(time.time(), None, why))
            del self._outages[:-MAX_OUTAGES]
        log.info("BIRIS service %r lost: %s", self.name, why)

    def back(self, how: str) -> None:
        """The service answered (or its token returned): the outage under way, if any, ends."""
        with self._cond:
            if self._since is None:
                return
            self._since = None
            self._back = time.monotonic()
            ended = dataclasses.replace(self._outages[-1], back_at=time.time())
            self._outages[-1] = ended
            self._cond.notify_all()
        log.info("BIRIS service %r back (%s) after %.1f s", self.name, how, ended.seconds)

    def wait_back(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for the service to be reachable (or :meth:`stop`);
        True if it is."""
        with self._cond:
            self._cond.wait_for(lambda: self._since is None or self._stopped, max(0.0, timeout))
            return self._since is None

    def stop(self) -> None:
        """The client is closing: every :meth:`wait_back` ends now, and any later one at once."""
        with self._cond:
            self._stopped = True
            self._cond.notify_all()

    def error(self, what: str) -> ConnectionLost:
        """The ConnectionLost to raise for ``what``, saying since when the service is lost."""
        with self._cond:
            current = self._outages[-1] if self._since is not None and self._outages else None
        if current is None:
            return ConnectionLost(f"{what}: BIRIS service {self.name!r} cannot be reached")
        return ConnectionLost(
            f"{what}: BIRIS service {self.name!r} cannot be reached since "
            f"{_clock(current.lost_at)} ({current.seconds:.1f} s; {current.why})"
        )


class Missed:
    """What one connection of scans missed while the service was lost: gaps in ``seq`` that
    span an outage.

    Gaps between the scans of one connection are the server's to count (``dropped``). A gap
    that spans an outage is counted here, less what the server dropped meanwhile: the scans the
    sensor made while the old connection was released and the new one did not exist yet (a
    reopen), and those whose reply was lost in the partition (a request Zenoh gave up on).
    Scans are numbered per direction (``seq``), so the count is exact. A restarted service
    numbers its scans afresh: :meth:`forget` (and a number that goes backwards) starts the
    comparison again, and what it made meanwhile is unknown and not counted. Acquisitions are
    not counted here: their ``acq`` restarts with every scan and does not say its direction (a
    subscription to the service's point publications counts those exactly, from their
    counters).
    """

    def __init__(self) -> None:
        self.count = 0
        self._last_seq: dict[Direction, int] = {}
        self._pending: set[Direction] = set()
        self._dropped_at = 0
        """The connection's ``dropped`` when the outage began: what it drops later is the
        server's count, not ours."""

    def mark(self, dropped: int) -> None:
        """An outage: the next scan of each direction is compared across it (``dropped``: the
        connection's count so far)."""
        if not self._pending:
            self._dropped_at = dropped
        self._pending = set(Direction)

    def forget(self) -> None:
        """The scans come from a new series (a restarted service): nothing to compare with."""
        self._last_seq.clear()
        self._pending.clear()

    def saw(self, item: object, dropped: int) -> tuple[int, str] | None:
        """Note a delivered item (``dropped``: the connection's count as of it); (how many
        scans were missed before it, in words) when it closes a gap across an outage."""
        if not isinstance(item, Scan):
            return None
        direction = item.direction
        last = self._last_seq.get(direction)
        self._last_seq[direction] = item.seq
        if direction not in self._pending:
            return None
        self._pending.discard(direction)
        if last is None or item.seq <= last + 1:
            return None  # nothing before the outage, no gap, or a sensor that started again
        gap = item.seq - last - 1
        theirs = min(gap, max(0, dropped - self._dropped_at))  # the server counted those
        self._dropped_at += theirs
        gap -= theirs
        if gap <= 0:
            return None
        self.count += gap
        first, end = last + 1, item.seq - 1
        span = f"seq {first}" if first == end else f"within seq {first}-{end}"
        return gap, f"{gap} {direction.name.lower()} scan{'s' if gap != 1 else ''} ({span})"
