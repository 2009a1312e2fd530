"""Continuous sweeps as a ``with`` block: every completed sweep, then the head left standing still.

The report's recipe for a client that wants every sweep is always the same: open a NORMAL
connection to command and a DATA connection to receive, send BIRIS_CONT_SCAN_RQST, answer each
delivered buffer with READY_FOR_DATA, and at the end send BIRIS_STOP_SCAN_RQST, wait until the
sweep under way has finished and the head stands still, and close both connections.
:func:`sweeping` is that recipe, once::

    from biris_hw.io.sweeps import sweeping

    with sweeping(server, cw_deg=-45.0, ccw_deg=45.0, timeout=10.0) as sweeps:
        for scan in sweeps:                      # READY_FOR_DATA, one complete sweep each
            print(scan.direction.name, scan.seq, scan.n_acq)
            if scan.seq >= 3:
                break
    # here the scan is stopped, the head idle and both connections closed

It uses nothing but the sensor interface (:class:`biris_hw.sensor.Sensor`: ``open``,
``status`` and the :class:`~biris_hw.sensor.Connection` methods), so it works on a local
server, a remote one and a replay alike.

If the block ends with an exception, the scan is still asked to stop and both connections are
closed, but nothing is waited for: the exception (a fault, a timeout, Ctrl-C) is what matters,
and the server, closed next, stops the head in any case.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from typing import TypeAlias

from biris_hw.data import ConnectionKind, Scan
from biris_hw.errors import RIDE_OUT_S, BirisError, ConnectionLost, Initialising
from biris_hw.sensor import Connection, Sensor

__all__ = ["DEFAULT_TIMEOUT_S", "SweepSource", "Sweeps", "sweeping"]

DEFAULT_TIMEOUT_S = 60.0
"""Longest wait, in real seconds, for one sweep or for the head to come to rest."""


SweepSource: TypeAlias = Sensor
"""What :func:`sweeping` needs: any sensor (a local server, a remote one, a replay)."""


class Sweeps:
    """The sweeps of one :func:`sweeping` block: iterate for each completed sweep, in order.

    ``limits`` are the CW and CCW limits the server used (counts, after clamping);
    ``received`` counts the sweeps handed out so far and :attr:`dropped` those the DATA
    connection missed (a LATEST connection keeps only the newest complete sweep for a client
    that is late), so ``received + dropped`` is every sweep completed since the block began.
    """

    def __init__(
        self,
        server: SweepSource,
        conn: Connection[Scan],
        data: Connection[Scan],
        limits: tuple[int, int],
        timeout: float,
        scans_before: int,
    ) -> None:
        self._server = server
        self.conn = conn
        """The NORMAL connection, for other requests while sweeping (points, status...)."""
        self.data = data
        """The DATA connection the sweeps arrive on."""
        self.limits = limits
        self.timeout = timeout
        self.received = 0
        self._scans_before = scans_before
        self._stopped = False
        self._lost_since: float | None = None
        """When the network to a remote sensor was lost (monotonic), while it is."""

    @property
    def dropped(self) -> int:
        """Sweeps the DATA connection missed, as of the latest one received."""
        return self.data.dropped

    @property
    def stopped(self) -> bool:
        return self._stopped

    def __iter__(self) -> Iterator[Scan]:
        """Every completed sweep, waiting up to :attr:`timeout` for each (TimeoutError if none
        comes), until the block ends or :meth:`stop`."""
        while not self._stopped:
            yield self._take(self.timeout)

    def next(self, timeout: float | None = None) -> Scan | None:
        """The next completed sweep, or None if none completes within ``timeout`` seconds
        (default :attr:`timeout`): for a loop that has other things to do meanwhile.

        What passes is None too: a reset under way (:class:`~biris_hw.errors.Initialising`),
        and a lost network to a remote sensor (:class:`~biris_hw.errors.ConnectionLost`; the
        service sweeps on meanwhile, and the connection reopens itself) for up to
        :data:`~biris_hw.errors.RIDE_OUT_S`, after which the ConnectionLost is raised, naming
        how long it lasted. A loop around ``next`` thus rides out what a long-running consumer
        should, and hears of what it should not."""
        try:
            scan = self._take(self.timeout if timeout is None else timeout)
        except (TimeoutError, Initialising):
            return None
        except ConnectionLost as exc:
            now = time.monotonic()
            if self._lost_since is None:
                self._lost_since = now
            if now - self._lost_since > RIDE_OUT_S:
                raise ConnectionLost(
                    f"{exc} (no sweep for {now - self._lost_since:.1f} s, more than the"
                    f" {RIDE_OUT_S:g} s ridden out)"
                ) from exc
            return None
        self._lost_since = None
        return scan

    def stop(self) -> list[Scan]:
        """BIRIS_STOP_SCAN_RQST, then wait until the sweep under way has completed and the head
        is idle; returns the sweeps that completed since the last one received (the last of
        them is the newest data there is). Raises the server's fault if it is in one, and
        TimeoutError if the head does not come to rest in :attr:`timeout`. Once only: the
        block's end does it if it has not been done."""
        if self._stopped:
            return []
        self._stopped = True
        self.conn.stop_scan()
        self.conn.wait_idle(timeout=self.timeout)
        rest: list[Scan] = []
        while self.received + self.dropped < self._completed():
            rest.append(self._take(self.timeout))
        return rest

    def _completed(self) -> int:
        """Sweeps completed since the block began, by the server's own count."""
        return int(self._server.status()["counters"]["scans"]) - self._scans_before

    def _take(self, timeout: float) -> Scan:
        scan = self.data.ready_for_data(timeout=timeout)
        self.received += 1
        return scan

    def _abandon(self) -> None:
        """The block failed: ask for a stop, wait for nothing, let the caller's error through."""
        if self._stopped:
            return
        self._stopped = True
        with contextlib.suppress(BirisError):
            self.conn.stop_scan()


@contextlib.contextmanager
def sweeping(
    server: SweepSource,
    cw_deg: float,
    ccw_deg: float,
    *,
    timeout: float = DEFAULT_TIMEOUT_S,
) -> Iterator[Sweeps]:
    """Sweep continuously between ``cw_deg`` and ``ccw_deg`` for the length of a ``with`` block.

    Opens a NORMAL and a DATA connection, sends BIRIS_CONT_SCAN_RQST (a bad request raises
    RequestError and nothing moves) and yields a :class:`Sweeps`; on leaving the block it stops
    the scan, waits for the head to come to rest (see :meth:`Sweeps.stop`) and closes both
    connections. The first sweep runs from wherever the head stands to the CW limit.
    """
    with server.open() as conn, server.open(ConnectionKind.DATA) as data:
        before = int(server.status()["counters"]["scans"])  # after DATA opened: none missed
        limits = conn.continuous_scan(cw_deg, ccw_deg)
        sweeps = Sweeps(server, conn, data, limits, timeout, before)
        try:
            yield sweeps
        except BaseException:
            sweeps._abandon()
            raise
        sweeps.stop()
