"""A recording served as a sensor: the client API over an MCAP file's lossless channels.

Code written against :class:`~biris_hw.BirisServer` runs unchanged on a recorded run::

    from biris_hw.io.record.replay import ReplayServer
    with ReplayServer("run.mcap", speed=1.0) as replay:
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        while True:
            try:
                scan = data.ready_for_data(timeout=5.0)   # the recorded Scans, equal
            except EndOfRecording:
                break

The player reads ``/biris/raw/scan``, ``/biris/raw/point`` and ``/biris/raw/status`` (written by
:mod:`biris_hw.io.record` with :mod:`biris_hw.io.codec`) in log-time order and hands each item
over as the server did: to every DATA connection by its delivery policy (LATEST keeps the newest,
EVERY_BUFFER and EVERY_ACQUISITION queue up to their depth, the oldest dropped and counted), and
as the answer to REQUEST_POINT / REQUEST_SCAN_DATA. ``speed`` scales the recorded timing (2.0 is
twice as fast); ``speed=None`` plays as fast as the readers take it: the player waits while a
queueing connection (EVERY_BUFFER, EVERY_ACQUISITION) is full, so those lose nothing.

Playback starts when the first DATA connection opens (or at :meth:`ReplayServer.start`; pass
``autostart=False`` to open several connections first). A replay cannot move anything: motion
and configuration requests raise :class:`ReplayRefused` (a :class:`~biris_hw.errors.RequestError`)
and change nothing. When the recording is over, READY_FOR_DATA with nothing left raises
:class:`EndOfRecording` (a :class:`~biris_hw.errors.ConnectionClosed`, so a loop that stops on a
closed server stops here too) and ``wait_idle`` returns. A file damaged part way (a corrupt
chunk) is played up to the damage; then READY_FOR_DATA, once what was read has been
delivered, and ``wait_idle`` raise :class:`ReplayError` from what the reader met, never
EndOfRecording: a damaged recording does not pass for a complete one.

A file without a footer -- its writer was killed, or the machine went down, before it closed
the file -- is played up to its last complete chunk (:mod:`biris_hw.io.record.cutfile`), and
then ends as a complete one does (EndOfRecording); the replay says so:
:attr:`ReplayServer.recovered` holds the sentence, logged as a warning when the replay is made.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import struct
import threading
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, BinaryIO, Literal, overload

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Metadata

from biris_hw.client import POLL
from biris_hw.client import checked_timeout as _seconds
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Point, Scan
from biris_hw.errors import BirisError, ConnectionClosed, RequestError
from biris_hw.io import codec
from biris_hw.io.codec import RAW_POINT_TOPIC, RAW_SCAN_TOPIC, RAW_STATUS_TOPIC
from biris_hw.io.record import cutfile
from biris_hw.protocol import check_policy
from biris_hw.records import BirisInitRecord
from biris_hw.sensor import ConnectionBase, D

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor
from biris_hw.status import (
    ConnectionStatus,
    ServerState,
    ServerStatus,
    StatusChanges,
    check_change,
)

__all__ = ["EndOfRecording", "ReplayConnection", "ReplayError", "ReplayRefused", "ReplayServer"]

log = logging.getLogger(__name__)

_RAW = (RAW_SCAN_TOPIC, RAW_POINT_TOPIC, RAW_STATUS_TOPIC)


class ReplayError(BirisError, OSError):
    """The file cannot be replayed: missing, not MCAP, or without the lossless channels (raised
    by :class:`ReplayServer`); or damaged part way (raised by ``ready_for_data`` and
    ``wait_idle`` once what was read before the damage has been played, from the reader's
    error)."""


class ReplayRefused(RequestError):
    """A request a recording cannot carry out (motion, configuration); nothing changed."""


class EndOfRecording(ConnectionClosed):
    """The recording has been played to its end and nothing more waits for this connection."""


class ReplayConnection(ConnectionBase[D]):
    """A connection to a :class:`ReplayServer`, with the methods of
    :class:`~biris_hw.client.Connection`."""

    def __init__(
        self,
        replay: ReplayServer,
        ident: int,
        kind: ConnectionKind,
        policy: DeliveryPolicy,
        depth: int,
    ) -> None:
        super().__init__(ident, kind, policy, depth)
        self._replay = replay
        self.delivered = 0
        self._queue: deque[Scan | Point] = deque()

    @property
    def _lossless(self) -> bool:
        return self.kind is ConnectionKind.DATA and self.policy is not DeliveryPolicy.LATEST

    def _wants(self, item: Scan | Point) -> bool:
        if self.kind is not ConnectionKind.DATA or self._closed:
            return False
        return isinstance(item, Point) == (self.policy is DeliveryPolicy.EVERY_ACQUISITION)

    def _offer(self, item: Scan | Point) -> None:
        self._queue.append(item)
        while len(self._queue) > self.depth:
            self._queue.popleft()
            self.dropped += 1

    def _check(self) -> None:
        if self._closed:
            raise ConnectionClosed(f"replay connection {self.ident} is closed")
        self._replay._check_open()

    def status(self, *, newer_than: int | None = None, timeout: object = None) -> ServerStatus:
        """The replay's status (:meth:`ReplayServer.status`); a wait for a newer one also ends,
        with ConnectionClosed, when this connection is closed."""
        self._check()
        return self._replay._wait_status(newer_than, timeout, self)

    # -- data --------------------------------------------------------------------------------
    def request_point(self) -> Point | None:
        """The latest acquisition played so far, or None before the first."""
        with self._replay._cond:
            self._check()
            return self._replay._point

    def request_scan_data(self, direction: Direction | int) -> Scan | None:
        """The latest complete scan played so far in that direction, or None.

        Raises:
            RequestError: no such direction.
        """
        d = self._direction(direction)
        with self._replay._cond:
            self._check()
            return self._replay._scans[d]

    def ready_for_data(self, timeout: object = None) -> D:
        """The next item for this DATA connection, as its policy says (see the module).

        Raises:
            RequestError: not a DATA connection, or a bad timeout.
            TimeoutError: nothing within ``timeout`` seconds (at once for 0).
            EndOfRecording: the recording is over and nothing waits.
            ReplayError: the file is damaged; what was read before it has been delivered.
            ConnectionClosed: this connection or the replay is closed.
        """
        if self.kind is not ConnectionKind.DATA:
            raise RequestError("READY_FOR_DATA is for DATA connections")
        seconds = _seconds(timeout)
        replay = self._replay
        deadline = None if seconds is None else time.monotonic() + seconds
        with replay._cond:
            while True:
                self._check()
                if self._queue:
                    item = self._queue.popleft()
                    self.delivered += 1
                    replay._cond.notify_all()  # the player may wait for room
                    return item  # type: ignore[return-value]  # the policy says which
                if replay._done.is_set():
                    replay._check_damage()
                    raise EndOfRecording(f"{replay.path}: the recording has been played to its end")
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise TimeoutError(f"no data for replay connection {self.ident}")
                if not replay._started.is_set() and replay._autostart:
                    replay.start()
                replay._cond.wait(left)

    def wait_idle(self, timeout: object = None) -> None:
        """Until the recording has been played to its end (a replay's head stops there).

        Raises:
            TimeoutError: not over within ``timeout`` seconds.
            ReplayError: playing stopped at a damaged part of the file.
        """
        seconds = _seconds(timeout)
        self._check()
        if not self._replay._done.wait(seconds):
            raise TimeoutError(f"{self._replay.path}: still playing")
        self._replay._check_damage()

    # -- what a replay cannot do -------------------------------------------------------------
    def _refuse(self, what: str) -> Any:
        self._check()
        raise ReplayRefused(
            f"{what}: a replay of {self._replay.path.name} cannot move or configure the sensor"
        )

    def single_scan(self, to_deg: object) -> int:
        return int(self._refuse("single_scan"))

    def continuous_scan(self, cw_deg: object, ccw_deg: object) -> tuple[int, int]:
        return self._refuse("continuous_scan")  # type: ignore[no-any-return]

    def set_elevation(self, deg: object) -> int:
        return int(self._refuse("set_elevation"))

    def stop_scan(self) -> None:
        self._refuse("stop_scan")

    def start_continuous(self) -> None:
        self._refuse("start_continuous")

    def stop_continuous(self) -> None:
        self._refuse("stop_continuous")

    def home(self) -> None:
        self._refuse("home")

    def set_motor_params(self, params: object) -> None:
        self._refuse("set_motor_params")

    def timeout_enable(self) -> None:
        self._refuse("timeout_enable")

    def timeout_disable(self) -> None:
        self._refuse("timeout_disable")

    def reset(self) -> None:
        self._refuse("reset")

    # -- lifecycle ---------------------------------------------------------------------------
    def _close(self) -> None:
        replay = self._replay
        with replay._cond:
            self._closed = True
            self._queue.clear()
            replay._changed()  # one connection fewer
            replay._cond.notify_all()


class ReplayServer:
    """Serve a recording through the client API (see the module).

    Raises:
        ReplayError: the file is missing, not MCAP, or has no lossless channels.
        ValueError: ``speed`` is not None or a positive number.
    """

    def __init__(
        self, path: str | os.PathLike[str], speed: float | None = 1.0, *, autostart: bool = True
    ) -> None:
        if speed is not None and not (
            isinstance(speed, (int, float)) and speed > 0 and math.isfinite(speed)
        ):
            raise ValueError(f"speed must be a positive number or None, not {speed!r}")
        self.path = Path(path)
        self.speed = speed
        self._autostart = autostart
        self.metadata: dict[str, str] = {}
        self._topics, self._cut = self._inspect()
        """The raw topics to play; where a file without a footer is read to (None: a closed
        file, read whole)."""
        self.recovered: str | None = None
        """Why only part of the file is played, or None: a file without a footer (its writer
        was killed) is played up to its last complete chunk, and this sentence says so."""
        if self._cut is not None:
            self.recovered = self._cut.describe(self.path)
            log.warning("%s", self.recovered)
        self.record: BirisInitRecord | None = None
        if "init_record" in self.metadata:
            try:
                self.record = BirisInitRecord.from_dict(json.loads(self.metadata["init_record"]))
            except (ValueError, RequestError):
                self.record = None
        self._cond = threading.Condition()
        self._conns: list[ReplayConnection[Any]] = []
        self._next = 1
        self._scans: dict[Direction, Scan | None] = {Direction.CW: None, Direction.CCW: None}
        self._point: Point | None = None
        self._status: ServerStatus | None = None
        self.played = {"scans": 0, "points": 0, "statuses": 0}
        self._started = threading.Event()
        self._done = threading.Event()
        self._stop = threading.Event()
        self._closed = False
        self.error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._changes = StatusChanges()
        """Numbers the changes of the replay's status (:meth:`status`'s ``newer_than``)."""
        self._clock_s = 0.0
        """The newest hardware time played: that of the newest point or scan handed over."""

    playback = True
    """A recording: motion and configuration are refused here (:class:`ReplayRefused`)."""

    @property
    def paced(self) -> bool:
        """Played at a speed, not as fast as the slowest queueing reader (``speed=None``)."""
        return self.speed is not None

    def clock(self) -> float:
        """The newest hardware time played so far: that of the newest point or scan handed over
        (0.0 before the first)."""
        with self._cond:
            return self._clock_s

    def _inspect(self) -> tuple[list[str], cutfile.Cut | None]:
        """Read the summary and metadata; the raw topics present. A file without a footer is
        read from its start, up to its last complete record (:mod:`~biris_hw.io.record.cutfile`):
        where is returned too."""
        cut = None
        try:
            with open(self.path, "rb") as f:
                if cutfile.ends_with_footer(f):
                    topics = self._inspect_closed(f)
                else:
                    cut = cutfile.cut_of(f)
                    if cut is None:
                        raise ReplayError(
                            f"{self.path} is not a readable MCAP file: it does not begin "
                            "with the MCAP magic"
                        )
                    topics = self._inspect_cut(f, cut)
        except ReplayError:
            raise
        except OSError as exc:
            raise ReplayError(f"cannot read {self.path}: {exc.strerror or exc}") from exc
        except (McapError, ValueError, EOFError) as exc:
            raise ReplayError(f"{self.path} is not a readable MCAP file: {exc}") from exc
        if not topics:
            if cut is not None:
                raise ReplayError(
                    f"{self.path} ends without a footer before any BIRIS data: nothing to play "
                    f"(its writer was stopped {cut.size:,} bytes in)"
                )
            raise ReplayError(
                f"{self.path} has no lossless BIRIS channels ({RAW_SCAN_TOPIC}, "
                f"{RAW_POINT_TOPIC}): not a biris recording"
            )
        return sorted(topics), cut

    def _inspect_closed(self, f: BinaryIO) -> set[str]:
        f.seek(0)
        reader = make_reader(f)
        for record in reader.iter_metadata():
            if record.name == "biris":
                self.metadata = dict(record.metadata)
        summary = reader.get_summary()
        if summary is not None and summary.channels:
            return {c.topic for c in summary.channels.values()} & set(_RAW)
        # a file cut short (a full disk) has no summary: look at the messages
        f.seek(0)
        found = make_reader(f).iter_messages(topics=list(_RAW))
        return {channel.topic for _s, channel, _m in found}

    def _inspect_cut(self, f: BinaryIO, cut: cutfile.Cut) -> set[str]:
        """The metadata and the raw topics of a file without a footer, read up to its cut; a
        damaged part stops the look (playing will stop there too, and say so)."""
        topics: set[str] = set()
        try:
            for record in cutfile.records(f, cut):
                if isinstance(record, Metadata) and record.name == "biris":
                    self.metadata = dict(record.metadata)
                elif isinstance(record, Channel) and record.topic in _RAW:
                    topics.add(record.topic)
        except (McapError, ValueError, EOFError, struct.error) as exc:
            log.debug("%s: looked at up to a damaged part (%s)", self.path, exc)
        return topics

    # -- playing -----------------------------------------------------------------------------
    def start(self) -> ReplayServer:
        """Begin playing (once; the first DATA connection does it unless ``autostart=False``)."""
        with self._cond:
            self._check_open()
            if self._started.is_set():
                return self
            self._started.set()
            self._changed()  # playing: SCANNING
            self._thread = threading.Thread(target=self._play, name="biris-replay", daemon=True)
            self._thread.start()
        return self

    def _messages(self) -> Iterator[tuple[str, int, bytes]]:
        with open(self.path, "rb") as f:
            if self._cut is not None:  # no footer: from the start, up to the cut
                found = cutfile.time_ordered(cutfile.messages(f, self._cut, self._topics))
            else:  # a damaged chunk is an error, not data
                reader = make_reader(f, validate_crcs=True)
                found = reader.iter_messages(topics=self._topics, log_time_order=True)
            for _schema, channel, message in found:
                yield channel.topic, message.log_time, message.data

    def _play(self) -> None:
        try:
            first: int | None = None
            begun = time.monotonic()
            for topic, log_time, data in self._messages():
                if self._stop.is_set():
                    return
                if self.speed is not None:
                    first = log_time if first is None else first
                    due = begun + (log_time - first) / 1e9 / self.speed
                    if self._stop.wait(max(0.0, due - time.monotonic())):
                        return
                self._hand_over(topic, data)
        except BaseException as exc:  # a damaged file: said to every reader, not lost
            self.error = exc
        finally:
            with self._cond:
                self._done.set()
                self._changed()  # played: IDLE
                self._cond.notify_all()

    def _hand_over(self, topic: str, data: bytes) -> None:
        """Hand one recorded item over. The replay's clock is the items' own hardware time (a
        point's ``t``, a scan's :func:`~biris_hw.io.codec.scan_time`), not the log time: a file
        logged on the wall clock (``stamp="wall"``) has log times of today's date, and a client
        placing data with the replay's clock (a pose lookup, a status's stamp) needs the
        hardware's. A status leaves it as it is."""
        item: Scan | Point
        if topic == RAW_STATUS_TOPIC:
            status = codec.decode_status(data)
            with self._cond:
                self._status = status
                self.played["statuses"] += 1
                self._changed()
            return
        item = codec.decode_scan(data) if topic == RAW_SCAN_TOPIC else codec.decode_point(data)
        t = codec.scan_time(item) if isinstance(item, Scan) else item.t
        with self._cond:
            if self.speed is None:  # as fast as the queueing readers go: wait for room
                self._cond.wait_for(lambda: self._stop.is_set() or self._room(item))
            if isinstance(item, Scan):
                self._scans[item.direction] = item
                self.played["scans"] += 1
            else:
                self._point = item
                self.played["points"] += 1
            self._clock_s = max(self._clock_s, t)
            for conn in self._conns:
                if conn._wants(item):
                    conn._offer(item)
            if self._status is None:  # a status made up from the data: it follows them
                self._changed()
            self._cond.notify_all()

    def _room(self, item: Scan | Point) -> bool:
        return all(len(c._queue) < c.depth for c in self._conns if c._lossless and c._wants(item))

    def _check_damage(self) -> None:
        """Raise ReplayError if playing stopped on an error (the file is damaged)."""
        error = self.error
        if error is not None:
            raise ReplayError(
                f"{self.path} is damaged: playing stopped after {self.played['scans']} scans "
                f"and {self.played['points']} acquisitions ({type(error).__name__}: {error})"
            ) from error

    @property
    def finished(self) -> bool:
        """The whole recording has been played (or playing stopped on an error)."""
        return self._done.is_set()

    def wait_done(self, timeout: float | None = None) -> bool:
        """Wait until the recording has been played; True if it has."""
        return self._done.wait(timeout)

    # -- the server's API --------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise ConnectionClosed(f"the replay of {self.path} is closed")

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.EVERY_ACQUISITION],
        depth: int | None = ...,
    ) -> ReplayConnection[Point]: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: Literal[DeliveryPolicy.LATEST, DeliveryPolicy.EVERY_BUFFER] = ...,
        depth: int | None = ...,
    ) -> ReplayConnection[Scan]: ...

    @overload
    def open(
        self,
        kind: ConnectionKind = ...,
        *,
        policy: DeliveryPolicy,
        depth: int | None = ...,
    ) -> ReplayConnection[Scan] | ReplayConnection[Point]: ...

    def open(
        self,
        kind: ConnectionKind = ConnectionKind.NORMAL,
        *,
        policy: DeliveryPolicy = DeliveryPolicy.LATEST,
        depth: int | None = None,
    ) -> ReplayConnection[Scan] | ReplayConnection[Point]:
        """OPEN_REQUEST, as :meth:`BirisServer.open <biris_hw.BirisServer.open>`.

        Raises:
            ConnectionClosed: the replay is closed.
            RequestError: an unknown kind, policy or depth.
        """
        try:
            kind = ConnectionKind(kind)
        except ValueError:
            raise RequestError(
                f"no connection kind {kind!r}; use ConnectionKind.NORMAL or DATA"
            ) from None
        chosen, used = check_policy(kind, policy, depth)
        with self._cond:
            self._check_open()
            conn: ReplayConnection[Any] = ReplayConnection(self, self._next, kind, chosen, used)
            self._next += 1
            self._conns = [c for c in self._conns if not c.closed] + [conn]
            self._changed()  # one connection more
        if kind is ConnectionKind.DATA and self._autostart:
            self.start()
        return conn

    def status(self, *, newer_than: int | None = None, timeout: object = None) -> ServerStatus:
        """The latest recorded status, with the replay's own state and connections: SCANNING
        while playing, IDLE before and after.

        ``newer_than`` (a status's ``change``) waits, up to ``timeout``, until the status has
        changed since: a recorded status that says something new, playing starting or ending,
        a connection opened or closed.

        Raises:
            ConnectionClosed: the replay is closed.
            RequestError: a ``newer_than`` that is not a whole number, or a bad timeout.
            TimeoutError: no newer status within ``timeout``.
        """
        return self._wait_status(newer_than, timeout, None)

    def _wait_status(
        self, newer_than: object, timeout: object, conn: ReplayConnection[Any] | None
    ) -> ServerStatus:
        """:meth:`status`; asked on ``conn``, the wait also ends when ``conn`` closes."""
        seconds = _seconds(timeout)
        after = check_change(newer_than)
        deadline = None if seconds is None else time.monotonic() + seconds
        with self._cond:
            while True:
                self._check_open()
                if conn is not None and conn.closed:
                    raise ConnectionClosed(f"replay connection {conn.ident} is closed")
                if after is None or self._changes.change > after:
                    return self._status_locked()
                left = None if deadline is None else deadline - time.monotonic()
                if seconds == POLL or (left is not None and left <= 0):
                    raise TimeoutError(f"the replay's status has not changed since {after}")
                self._cond.wait(left)

    def _status_locked(self) -> ServerStatus:
        """The status now (the caller holds ``_cond``)."""
        playing = self._started.is_set() and not self._done.is_set()
        conns = {
            c.ident: ConnectionStatus(
                kind=c.kind.name,
                policy=c.policy.name,
                depth=c.depth,
                queued=len(c._queue),
                delivered=c.delivered,
                dropped=c.dropped,
                latency={},
            )
            for c in self._conns
            if not c.closed
        }
        base = self._status
        point = self._point
        state = ServerState.SCANNING if playing else ServerState.IDLE
        if base is None:
            base = ServerStatus(
                state=state,
                fault=None,
                azimuth=point.azimuth if point else 0,
                elevation=point.elevation if point else 0,
                calibration=None,
                continuous=False,
                acquisition=point.acquisition if point else "single",
                ring="off",
                counters={"scans": self.played["scans"]},
                connections={},
            )
        return dataclasses.replace(
            base, state=state, fault=None, connections=conns, change=self._changes.change
        )

    def _changed(self) -> None:
        """Something the status says may have changed (the caller holds ``_cond``): numbered
        if it did, and the waiters woken."""
        if self._changes.see(self._status_locked().signature()):
            self._cond.notify_all()

    def close(self) -> None:
        """Stop playing, close every connection (their waiters get ConnectionClosed)."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._stop.set()
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join()

    def __enter__(self) -> ReplayServer:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


if TYPE_CHECKING:

    def _is_a_sensor(replay: ReplayServer) -> Sensor:
        return replay  # mypy holds ReplayServer to biris_hw.sensor.Sensor
