"""One reader per sensor and process, fanned out to every sink: each acquisition encoded once.

The service publishes every acquisition and scan, the recorder writes them, the live view shows
them; each used to open its own connections to the sensor and encode what it read, so a sensor
served and recorded in one process was read twice and every acquisition encoded twice. Here a
:class:`SharedFeed` reads a sensor for everyone in the process (:func:`shared_feed` finds or
starts it), encodes each batch once (:mod:`biris_hw.io.codec`) into :class:`Message` objects --
topic, type, CDR bytes, log time -- on the topics some sink wants, and hands *the same bytes* to
every sink, the model of foxglove-sdk's context: a message is logged once and every sink gets
it.

**Sinks** attach (:meth:`SharedFeed.attach`, or :func:`attach`) and detach (:meth:`Sink.detach`)
independently; each names the topics it wants (``wants`` may narrow them batch by batch: the
live view only builds a topic a viewer subscribed to). Each sink has its own bounded queue and
its own thread, which calls its ``on_batch`` with a :class:`Batch`: the items (points, scans)
and the messages made from them, a status reading, the faults the feed met. A slow sink loses
what does not fit its queue and counts it (:attr:`Sink.dropped_points`, :attr:`Sink.dropped_scans`,
which include what the sensor dropped for the feed since the sink attached); it never holds up
the reader nor another sink. A sink whose ``on_batch`` raises fails alone (:attr:`Sink.error`).
Detaching hands the sink what the sensor had queued until then, then its last batch
(``final``), and returns once its thread has handled everything; the last sink to go stops the
feed.

**Reading.** One thread holds two DATA connections, EVERY_ACQUISITION and EVERY_BUFFER, each
:data:`POINT_DEPTH` / :data:`SCAN_DEPTH` deep (the feed only encodes and enqueues, so what it
needs of the sensor's queue does not depend on its sinks). While no sink is ``prompt`` it wakes
every ``batch_s`` (the smallest its sinks asked for), out of step with the acquisitions, and
polls both: a reader blocked in ``ready_for_data`` is woken at the very moment an acquisition
reaches every other client, and whatever it then does (the encoding, a file) holds the
interpreter lock just when those clients should run; in batches the encoding runs once per
batch, vectorised, mostly between acquisitions. A ``prompt`` sink (the network service, whose
publications *are* deliveries to clients) makes the reader wait in ``ready_for_data`` on the
acquisitions instead, so that each goes out as soon as it is read, and is handed its batches in
the reader's thread (no queue, no thread of its own: its ``on_batch`` must not block), before
anything else is asked of the sensor; scans are asked for at most once a ``batch_s`` while
acquisitions flow (each ask is a round trip), so a scan goes out within one or two
``batch_s``. A fault met on the data pauses the asks for :data:`FAULT_POLL_S` (each would only
hear the fault again); while a reset initialises the sensor, reading goes on at the batch rate,
on the same connections.

**A lost network** (a remote sensor's :class:`~biris_hw.errors.ConnectionLost`: a partition, a
router restarting; the remote client reconnects by itself) is ridden out: the asks go on with a
back-off (:data:`LOST_RETRY_S` doubling up to :data:`LOST_RETRY_MAX_S`), and when they succeed
again reading carries on on the same connections. The span without the network is kept
(:class:`LostSpan`: from when, to when, the hardware time of the last data before it) in every
sink's :attr:`Sink.lost_spans`, and logged as a warning when it begins and when it ends. A sink
whose ``lost_limit_s`` (:data:`LOST_LIMIT_S`, 30 real seconds, by default) passes without the
network fails with a ConnectionLost that names the span; the others go on waiting.

**Detaching within a bound.** :meth:`Sink.detach` with a ``timeout`` returns by then whatever
the sink's backlog. For the first half of it the reader goes on taking what the sensor queued
while a drain comes back full, and the sink's thread goes on handling its queue; what still
waits in the queue then is dropped and counted (:attr:`Sink.unhandled_points`, in
:attr:`Sink.dropped_points`), and what the sensor still held is left to it (the sensor counts
what it drops). If ``on_batch`` is still running at the timeout (a write that blocks) detach
returns all the same: the sink's thread goes on to its last batch by itself and sets
:attr:`Sink.done`. Without a timeout detach hands over one drain more, then the last batch, and
waits for ``on_batch`` however long it takes.

**Status.** A second thread reads the status for sinks that want it periodically
(``status_period_s``) or on every change (``status_changes``). When the sensor pushes (its
``status`` takes ``newer_than``: a parked request answered on change) the thread waits on a
connection of its own for the next change, asking nothing while nothing changes; otherwise it
polls every :data:`STATUS_POLL_S` while a sink watches changes. A sink gets a first status as it
attaches. Each reading is stamped with the sensor's hardware time (:func:`sensor_time`) and
encoded once; a sink that wants :data:`~biris_hw.io.codec.RAW_FAULT_TOPIC` also gets a
``biris_msgs/Fault`` when the sensor enters a fault.

Messages a sink makes for itself are not an acquisition's: the recorder's and the live view's
diagnostics carry their own drop counts, and the static transforms are one per recording or
status period.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeAlias

from biris_hw.data import ConnectionKind, DeliveryPolicy, Point, Scan
from biris_hw.errors import (
    RIDE_OUT_S,
    BirisError,
    ConnectionClosed,
    ConnectionLost,
    HardwareFault,
    Initialising,
)
from biris_hw.geometry import Frame
from biris_hw.io import codec
from biris_hw.sensor import Sensor
from biris_hw.status import ServerStatus

__all__ = [
    "BATCH_S",
    "DRAIN_MAX",
    "FAULT_POLL_S",
    "FEED_TOPICS",
    "LOST_LIMIT_S",
    "LOST_RETRY_MAX_S",
    "LOST_RETRY_S",
    "POINT_DEPTH",
    "SCAN_DEPTH",
    "STATUS_POLL_S",
    "Batch",
    "FeedStopped",
    "LostSpan",
    "Message",
    "SensorFeed",
    "SensorSource",
    "SharedFeed",
    "Sink",
    "StatusReading",
    "attach",
    "sensor_time",
    "shared_feed",
]

log = logging.getLogger(__name__)

BATCH_S = 0.05
"""How often a feed collects what the sensor queued for it (real seconds), unless a sink asks
for less."""

DRAIN_MAX = 256
"""At most this many items are taken from one connection before they are handed over, so a
fast sensor's data go out in bounded batches while the rest waits in the sensor's queue."""

POINT_DEPTH = 4096
"""The feed's every-acquisition queue in the sensor (two minutes at 30 Hz)."""

SCAN_DEPTH = 256
"""The feed's every-buffer queue in the sensor."""

FAULT_POLL_S = 0.5
"""While the sensor is in a fault, the pause between two asks for data (real seconds)."""

LOST_LIMIT_S = RIDE_OUT_S
"""How long (real seconds) a sink waits for a lost network to come back before it fails (the
project's one bound, :data:`biris_hw.errors.RIDE_OUT_S`)."""

LOST_RETRY_S = 0.1
"""The first pause (real seconds) between two asks of a sensor whose network is lost..."""

LOST_RETRY_MAX_S = 2.0
"""...doubled at each ask up to this: a network that comes back is heard within it."""

STATUS_POLL_S = 0.05
"""How often the status is read while a sink watches for changes and the sensor cannot push."""

STATUS_DEPTH = 16
"""Status readings that may wait for one sink; more are dropped (and counted)."""

FEED_TOPICS: Mapping[str, str] = {
    codec.RAW_POINT_TOPIC: codec.POINT,
    codec.PROFILE_TOPIC: codec.POINT_CLOUD2,
    codec.TF_TOPIC: codec.TF_MESSAGE,
    codec.SWEEP_TOPIC: codec.POINT_CLOUD2,
    codec.RAW_SCAN_TOPIC: codec.SCAN,
    codec.POINTS_TOPIC: codec.POINT_CLOUD2,
    codec.RAW_STATUS_TOPIC: codec.STATUS,
    codec.RAW_FAULT_TOPIC: codec.FAULT,
}
"""The topics a feed encodes, and their types: per acquisition (the lossless point, the profile
cloud, the pan/tilt transforms, the sweep), per scan (the lossless scan, the scan cloud in the
sink's ``frame``), per status reading (the lossless status, the fault)."""

_POINT_TOPICS = (codec.PROFILE_TOPIC, codec.TF_TOPIC, codec.RAW_POINT_TOPIC)
"""Per-acquisition topics, in the order a sink gets each acquisition's messages."""


SensorSource: TypeAlias = Sensor
"""What a feed reads: any sensor (a BirisServer, a network client's sensor, a ReplayServer)."""


def sensor_time(source: Sensor, last_seen: float) -> float:
    """The time to stamp a status with: the sensor's clock (hardware time now for a local
    server, the newest time seen for a network client or a replay), and never before
    ``last_seen``, the newest time the data carried."""
    return max(float(source.clock()), last_seen)


@dataclass(frozen=True)
class Message(codec.Encoded):
    """One message a feed encoded, and the item it was made from (a Point, a Scan, a status, a
    HardwareFault; None for a sweep, made from many)."""

    item: object = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class StatusReading:
    """The status as read (None when it could not be: ``error`` says why), and the hardware
    time it is stamped with."""

    status: ServerStatus | None
    error: str | None
    t: float


def _clock_text(wall: float) -> str:
    """A wall-clock time for a person: ``14:02:11.3`` (local time)."""
    return time.strftime("%H:%M:%S", time.localtime(wall)) + f".{int(wall % 1 * 10)}"


@dataclass(frozen=True)
class LostSpan:
    """A span of real time without the network to a remote sensor: nothing was received from
    ``began`` to ``ended`` (wall-clock seconds, ``time.time()``; ``ended`` None while it
    lasts); ``after_t`` is the hardware time of the last data before it (0.0: none came
    before), ``gave_up`` True when the sink failed at ``ended`` instead of the network coming
    back."""

    began: float
    ended: float | None
    after_t: float
    gave_up: bool = False

    @property
    def seconds(self) -> float:
        """How long it lasted (so far, while it lasts)."""
        return (time.time() if self.ended is None else self.ended) - self.began

    def __str__(self) -> str:
        end = "still lost" if self.ended is None else f"to {_clock_text(self.ended)}"
        how = ", gave up" if self.gave_up else ""
        return f"from {_clock_text(self.began)} {end} ({self.seconds:.1f} s{how}{self.after()})"

    def after(self) -> str:
        """``; after hardware time 12.345 s``: where the data stop, if any came before."""
        return f"; after hardware time {self.after_t:.3f} s" if self.after_t > 0 else ""


@dataclass(frozen=True)
class Batch:
    """What one sink is handed at a time: items, the messages made from them on its topics (in
    order: each acquisition's profile, transforms and lossless point, then the sweep, then each
    scan's cloud and lossless scan, then the status and the fault), a status reading, the faults
    met on the data, and whether this is its last batch."""

    points: tuple[Point, ...] = ()
    scans: tuple[Scan, ...] = ()
    messages: tuple[Message, ...] = ()
    status: StatusReading | None = None
    faults: tuple[HardwareFault, ...] = ()
    final: bool = False


def _signature(status: ServerStatus) -> tuple[Any, ...]:
    """What makes a status worth handing to a change-watching sink at once (not the
    ever-changing counters): :meth:`~biris_hw.status.ServerStatus.signature`."""
    return tuple(status.signature())


def _fault_state(status: Any) -> str | None:
    """``"fault:<kind>"`` while the status says the sensor is in a fault, else None."""
    state = str(status["state"])
    return state if state.startswith("fault") else None


class Sink:
    """One sink attached to a :class:`SharedFeed`: its queue, its thread, what it lost.

    Made by :meth:`SharedFeed.attach`; see the module for what it is handed and when.
    """

    def __init__(
        self,
        feed: SharedFeed,
        on_batch: Callable[[Batch], None],
        *,
        name: str,
        topics: frozenset[str],
        frame: Frame,
        wants: Callable[[str], bool] | None,
        status_period_s: float | None,
        status_changes: bool,
        batch_s: float,
        prompt: bool,
        sweep_period_s: float,
        point_depth: int,
        scan_depth: int,
        lost_limit_s: float,
    ) -> None:
        self.feed = feed
        self.name = name
        self.topics = topics
        self.frame: Frame = frame
        self.status_period_s = status_period_s
        self.status_changes = status_changes
        self.batch_s = batch_s
        self.prompt = prompt
        self.sweep_period_s = sweep_period_s
        self.point_depth = point_depth
        self.scan_depth = scan_depth
        self.lost_limit_s = lost_limit_s
        self._on_batch = on_batch
        self._wants = wants
        self._cond = threading.Condition()
        self._inline = threading.Lock()
        """A prompt sink is handed its batches in the thread that made them (the reader, or
        the status thread): one at a time."""
        self._queue: collections.deque[Batch] = collections.deque()
        self._pending = [0, 0, 0]  # points, scans, statuses waiting in the queue
        self._sealed = False  # the final batch is queued: nothing more
        self._closing = False
        self._thread: threading.Thread | None = None
        self._base_points = 0
        self._base_scans = 0
        self.lost_points = 0
        """Acquisitions this sink's queue had no room for."""
        self.lost_scans = 0
        self.lost_statuses = 0
        self.unhandled_points = 0
        """Acquisitions still in its queue when its detach's time for them had passed."""
        self.unhandled_scans = 0
        self._drop_after = math.inf
        """Past this (monotonic), what waits in the queue is dropped and counted (detach)."""
        self._spans: list[LostSpan] = []
        """The spans without the network while it was attached (closed ones)."""
        self._attached_at = time.time()
        self.done = threading.Event()
        """Set once its last batch has been handled (or skipped: a failed sink)."""
        self.points = 0
        """Acquisitions handed to ``on_batch``."""
        self.scans = 0
        self.messages = 0
        """Messages handed to ``on_batch``."""
        self.error: BaseException | None = None
        self.failed = threading.Event()
        """Set when ``on_batch`` raised, or the sensor failed: :attr:`error` says how."""
        # the status thread's account of this sink
        self._next_status = -math.inf
        self._last_signature: tuple[Any, ...] | None = None
        self._in_fault: str | None = None
        """The fault state (``fault:<kind>``) of its last status reading, None outside one."""
        self._greeted = False
        """Its first status has been handed over (by attach): the status thread may serve it."""

    def __repr__(self) -> str:
        return f"<Sink {self.name} of {self.feed!r}>"

    @property
    def dropped_points(self) -> int:
        """Acquisitions this sink missed: dropped by the sensor on the feed's connection since
        the sink attached (too slow a feed, or lost by the sensor), by its own queue, and left
        in it at a bounded detach. What a sensor made while the network was lost is not here
        unless the sensor counted it: see :attr:`lost_spans`."""
        return (
            max(0, self.feed.dropped_points - self._base_points)
            + self.lost_points
            + self.unhandled_points
        )

    @property
    def dropped_scans(self) -> int:
        """Scans this sink missed, counted as :attr:`dropped_points` are."""
        return (
            max(0, self.feed.dropped_scans - self._base_scans)
            + self.lost_scans
            + self.unhandled_scans
        )

    @property
    def lost_spans(self) -> tuple[LostSpan, ...]:
        """Every span without the network to the sensor while this sink was attached, the one
        under way included (``ended`` None)."""
        spans = list(self._spans)
        ongoing = self.feed.lost_span
        if ongoing is not None and not (spans and spans[-1].gave_up):
            spans.append(ongoing)
        return tuple(spans)

    def active(self) -> frozenset[str]:
        """The topics to make for this sink now (``wants`` asked once per batch); none once
        it has failed."""
        if self.error is not None:
            return frozenset()
        if self._wants is None:
            return self.topics
        return frozenset(t for t in self.topics if self._wants(t))

    def detach(self, timeout: float | None = None) -> None:
        """Take what the sensor queued until now, then stop; returns once ``on_batch`` has
        been handed the last batch (idempotent). From ``on_batch`` itself it does not wait.

        With ``timeout`` (real seconds) it returns by then whatever waits: what is still in the
        queue once half of it has passed is dropped and counted (:attr:`unhandled_points`), and
        an ``on_batch`` still running then is left to finish in the sink's thread (which sets
        :attr:`done` after the last batch)."""
        self.feed._detach(self, timeout)

    # -- the queue ---------------------------------------------------------------------------
    def _start(self) -> None:
        if self.prompt:  # handed over inline (_offer): no queue, no thread
            return
        self._thread = threading.Thread(
            target=self._run, name=f"biris-sink-{self.name}", daemon=True
        )
        self._thread.start()

    def _offer(self, batch: Batch) -> None:
        """Queue ``batch``, less what does not fit (counted); never blocks on the sink -- but
        a prompt sink's: that one is handed the batch at once, in this thread."""
        if self.prompt:
            self._hand_now(batch)
            return
        with self._cond:
            if self._sealed:  # a bounded detach sealed it first: counted, not lost silently
                self.unhandled_points += len(batch.points)
                self.unhandled_scans += len(batch.scans)
                return
            points, scans, status = batch.points, batch.scans, batch.status
            lost_points = bool(points) and self._pending[0] + len(points) > self.point_depth
            lost_scans = bool(scans) and self._pending[1] + len(scans) > self.scan_depth
            lost_status = status is not None and self._pending[2] >= STATUS_DEPTH
            if lost_points or lost_scans or lost_status:
                gone: set[int] = set()
                if lost_points:
                    self.lost_points += len(points)
                    gone.update(map(id, points))
                    points = ()
                if lost_scans:
                    self.lost_scans += len(scans)
                    gone.update(map(id, scans))
                    scans = ()
                if status is not None and lost_status:
                    self.lost_statuses += 1
                    gone.add(id(status.status))
                    status = None
                messages = tuple(
                    m for m in batch.messages if m.item is None or id(m.item) not in gone
                )
                if lost_points:  # a sweep is made of the acquisitions lost with it
                    messages = tuple(m for m in messages if m.topic != codec.SWEEP_TOPIC)
                batch = Batch(points, scans, messages, status, batch.faults, batch.final)
            if not (batch.points or batch.scans or batch.messages or batch.status) and not (
                batch.faults or batch.final
            ):
                return
            self._pending[0] += len(batch.points)
            self._pending[1] += len(batch.scans)
            self._pending[2] += batch.status is not None
            self._sealed = batch.final
            self._queue.append(batch)
            self._cond.notify_all()  # the sink's thread, and a detach waiting for the seal

    def _hand_now(self, batch: Batch) -> None:
        """A prompt sink's batch, handed over in the thread that made it: a publication is a
        delivery to the service's clients, and a hop through a queue and a thread of its own
        cost every remote reader a thread wake-up per acquisition. Such a sink's ``on_batch``
        must not block (the service's publications drop what a subscriber cannot take)."""
        with self._inline:
            if self._sealed:  # (a prompt sink's is set only below, under _inline)
                return
            self._deliver(batch)
            if batch.final:
                with self._cond:
                    self._sealed = True
                    self._cond.notify_all()  # a detach waiting for the seal
                self.done.set()

    def _deliver(self, batch: Batch) -> None:
        """Hand ``batch`` to ``on_batch`` and count it; a sink that raises fails alone, and is
        handed nothing more."""
        if self.error is not None:
            return
        try:
            self._on_batch(batch)
            self.points += len(batch.points)
            self.scans += len(batch.scans)
            self.messages += len(batch.messages)
        except BaseException as exc:
            log.exception("sink %s failed", self.name)
            self._fail(exc)

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._queue))
                batch = self._queue.popleft()
                self._pending[0] -= len(batch.points)
                self._pending[1] -= len(batch.scans)
                self._pending[2] -= batch.status is not None
            if time.monotonic() >= self._drop_after:
                batch = self._without_data(batch)
            self._deliver(batch)
            if batch.final:
                self.done.set()
                return

    def _without_data(self, batch: Batch) -> Batch:
        """``batch`` less its acquisitions and scans (and the messages made of them), counted:
        a bounded detach has no more time for them. The status and the faults stay."""
        if not (batch.points or batch.scans):
            return batch
        self.unhandled_points += len(batch.points)
        self.unhandled_scans += len(batch.scans)
        gone = {id(item) for item in (*batch.points, *batch.scans)}
        messages = tuple(m for m in batch.messages if m.item is not None and id(m.item) not in gone)
        return Batch((), (), messages, batch.status, batch.faults, batch.final)

    def _fail(self, exc: BaseException) -> None:
        if self.error is None:
            self.error = exc
        self.failed.set()

    def _join(self, timeout: float | None = None) -> None:
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)


_REGISTRY: dict[int, SharedFeed] = {}
_REGISTRY_LOCK = threading.Lock()


def shared_feed(source: SensorSource) -> SharedFeed:
    """The process's feed of ``source``: the running one, or a new one (started by its first
    sink). One per sensor object, whichever of the service, the recorder or the live view asks."""
    with _REGISTRY_LOCK:
        feed = _REGISTRY.get(id(source))
        if feed is None or feed.source is not source or feed._over or feed._ended.is_set():
            feed = SharedFeed(source)  # (an ended one keeps its sinks until they detach)
            _REGISTRY[id(source)] = feed
        return feed


def attach(source: SensorSource, on_batch: Callable[[Batch], None], **options: Any) -> Sink:
    """:meth:`SharedFeed.attach` on the process's feed of ``source``."""
    while True:
        feed = shared_feed(source)
        try:
            return feed.attach(on_batch, **options)
        except FeedStopped:
            continue  # it stopped between the two: the next look finds a new one


class FeedStopped(RuntimeError):
    """A sink was attached to a feed that has stopped (its last sink left, or the sensor has
    gone): :func:`attach` (or :func:`shared_feed`) finds the process's current one."""


@dataclass(frozen=True)
class _Roster:
    """The reader's view of its sinks at one :attr:`SharedFeed._roster_version`: who they
    are, who is closing, and how long a prompt ask for an acquisition waits (0.0: no sink is
    prompt, the reader polls every batch)."""

    version: int
    sinks: tuple[Sink, ...]
    closing: tuple[Sink, ...]
    prompt_wait: float

    @classmethod
    def of(cls, version: int, sinks: Sequence[Sink]) -> _Roster:
        wait = min(BATCH_S, *(s.batch_s for s in sinks)) if any(s.prompt for s in sinks) else 0.0
        return cls(version, tuple(sinks), tuple(s for s in sinks if s._closing), wait)


class SharedFeed:
    """Every acquisition, scan and status of one sensor, read once and encoded once for every
    sink in the process (see the module). Get it with :func:`shared_feed`."""

    def __init__(self, source: SensorSource) -> None:
        self.source = source
        self._lock = threading.Lock()
        self._sinks: list[Sink] = []
        self._roster_version = 0
        """Bumped (under ``_lock``) whenever a sink comes, goes or starts closing: the reader
        works out what its sinks ask of it (:class:`_Roster`) only when this has moved."""
        self._wake = threading.Event()
        """Ends the reader's pause: a sink attached or is detaching."""
        self._status_wake = threading.Event()
        self._stop = threading.Event()
        self._opened = threading.Event()
        self._open_error: BaseException | None = None
        self._over = False
        """No sink is left (or opening failed): a new sink needs a new feed."""
        self._ended = threading.Event()
        """The sensor has gone (both data connections closed), or the feed failed."""
        self._reader: threading.Thread | None = None
        self._watcher: threading.Thread | None = None
        self._status_conn: Any = None
        self._status_lock = threading.Lock()
        self._last_seen = 0.0
        self._last_fault: HardwareFault | None = None
        self._fault_until = -math.inf
        """No ask for data before this (monotonic): a fault's pause, a lost network's back-off."""
        self._lost_since: float | None = None
        """When (monotonic) the network to the sensor was lost, while it is."""
        self._lost: LostSpan | None = None
        self._lost_retry = LOST_RETRY_S
        self._sweep: list[Point] = []
        self._last_roster: _Roster | None = None
        self._sweep_sent = -math.inf
        self._server_dropped = [0, 0]
        """What the sensor dropped on the feed's two connections (its counts, added up across
        a count that starts again: a remote client's connections reopened after a lost
        network)."""
        self._server_seen = [0, 0]
        """The two connections' counts as last read."""
        self._unencoded = [0, 0]
        """Acquisitions and scans lost because they could not be encoded."""
        self.encoded: collections.Counter[str] = collections.Counter()
        """Messages encoded per topic since the feed started: each once, whatever the sinks."""
        self._encoded_lock = threading.Lock()  # the reader and the status thread both count
        self.error: BaseException | None = None
        """Why reading stopped early (a damaged recording), or None."""

    def __repr__(self) -> str:
        return f"<SharedFeed of {type(self.source).__name__} at {id(self.source):#x}>"

    @property
    def dropped_points(self) -> int:
        """Acquisitions no sink got: dropped by the sensor on the feed's every-acquisition
        connection (the sensor's count: too slow a feed, or lost by the sensor), or that could
        not be encoded."""
        return self._server_dropped[0] + self._unencoded[0]

    @property
    def dropped_scans(self) -> int:
        """Scans no sink got, counted as :attr:`dropped_points` are."""
        return self._server_dropped[1] + self._unencoded[1]

    @property
    def sinks(self) -> tuple[Sink, ...]:
        with self._lock:
            return tuple(self._sinks)

    @property
    def lost_span(self) -> LostSpan | None:
        """The span without the network under way, or None."""
        return self._lost

    # -- attaching and detaching -------------------------------------------------------------
    def attach(
        self,
        on_batch: Callable[[Batch], None],
        *,
        name: str = "sink",
        topics: Iterable[str] = (),
        frame: Frame = "vehicle",
        wants: Callable[[str], bool] | None = None,
        status_period_s: float | None = 1.0,
        status_changes: bool = False,
        batch_s: float = BATCH_S,
        prompt: bool = False,
        sweep_period_s: float = 0.1,
        point_depth: int = POINT_DEPTH,
        scan_depth: int = SCAN_DEPTH,
        lost_limit_s: float | None = None,
    ) -> Sink:
        """Attach a sink; ``on_batch`` is called in the sink's own thread with each
        :class:`Batch`. Nothing the sensor produces after this returns is missed.

        Args:
            name: for its thread's name and the log.
            topics: what to encode for it, of :data:`FEED_TOPICS`.
            frame: the frame of its ``/biris/points`` clouds ("vehicle" or "sensor").
            wants: asked once per batch for each of ``topics``: False leaves it out this time.
            status_period_s: a status at least this often (None: none but on changes).
            status_changes: a status whenever it changes too (its signature).
            batch_s: how often the reader collects, at most (the smallest of all sinks').
            prompt: each acquisition as soon as it is read, handed over in the reader's thread
                (``on_batch`` must not block; see the module).
            sweep_period_s: at most one ``/biris/sweep`` message this often.
            point_depth: acquisitions that may wait in its queue; beyond, dropped and counted.
            scan_depth: likewise for scans.
            lost_limit_s: how long (real seconds) it waits for a lost network to come back
                before it fails with a :class:`~biris_hw.errors.ConnectionLost` naming the span
                (None: :data:`LOST_LIMIT_S`).

        Raises:
            ValueError: a topic the feed does not make, a frame that is neither.
            ConnectionClosed: the sensor has stopped (raised by opening its connections).
            FeedStopped: this feed has stopped; :func:`attach` finds the current one.
        """
        wanted = frozenset(topics)
        unknown = wanted - set(FEED_TOPICS)
        if unknown:
            raise ValueError(
                f"a feed makes none of {sorted(unknown)}; it makes {list(FEED_TOPICS)}"
            )
        codec.cloud_frame_id(frame)  # ValueError for a frame that is neither
        sink = Sink(
            self,
            on_batch,
            name=name,
            topics=wanted,
            frame=frame,
            wants=wants,
            status_period_s=status_period_s,
            status_changes=status_changes,
            batch_s=max(0.0, batch_s),
            prompt=prompt,
            sweep_period_s=sweep_period_s,
            point_depth=point_depth,
            scan_depth=scan_depth,
            lost_limit_s=LOST_LIMIT_S if lost_limit_s is None else lost_limit_s,
        )
        with _REGISTRY_LOCK:
            if self._over or self._ended.is_set():
                raise FeedStopped(f"{self!r} has stopped: attach to feed.shared_feed(source)")
            with self._lock:
                first = not self._sinks and self._reader is None
                sink._base_points, sink._base_scans = self.dropped_points, self.dropped_scans
                self._sinks.append(sink)
                self._roster_version += 1
            if first:
                self._start()
        self._opened.wait()
        if self._open_error is not None:
            with self._lock:
                if sink in self._sinks:
                    self._sinks.remove(sink)
                    self._roster_version += 1
            raise self._open_error
        sink._start()
        if status_period_s is not None or status_changes:
            self._first_status(sink)
        self._wake.set()
        self._status_wake.set()
        return sink

    def _start(self) -> None:
        """Open the connections (in the reader, their owner) before the first sink's attach
        returns; on failure the feed is over, and every attach raises what opening raised."""
        self._reader = threading.Thread(target=self._read, name="biris-feed", daemon=True)
        self._reader.start()
        self._opened.wait()
        if self._open_error is not None:
            self._reader.join()
            self._over = True
            _REGISTRY.pop(id(self.source), None)
            return
        self._watcher = threading.Thread(target=self._watch, name="biris-feed-status", daemon=True)
        self._watcher.start()

    def _detach(self, sink: Sink, timeout: float | None = None) -> None:
        deadline = math.inf if timeout is None else time.monotonic() + max(0.0, timeout)
        if timeout is not None:
            sink._drop_after = min(sink._drop_after, time.monotonic() + max(0.0, timeout) / 2)

        def left() -> float | None:
            return None if timeout is None else max(0.0, deadline - time.monotonic())

        # from a thread of the feed's own (a sink's on_batch, the reader, the status thread:
        # a garbage collection may run a finaliser there) a wait would wait for itself
        mine = (sink._thread, self._reader, self._watcher)
        may_wait = threading.current_thread() not in mine
        with self._lock:
            attached = sink in self._sinks
            if attached:
                sink._closing = True
                self._roster_version += 1
        if attached and not self._ended.is_set():
            self._wake.set()  # the reader hands it what waits, then its final batch
            self._status_wake.set()
            if may_wait:
                with sink._cond:
                    sink._cond.wait_for(lambda: sink._sealed or self._ended.is_set(), left())
        if not sink._sealed:  # the reader has gone, or had no time: nothing more will come
            self._remove([sink])
            sink._offer(Batch(messages=self._flush_sweep([sink]), final=True))
        if may_wait:
            sink._join(left())
            if self._over:
                self._join(left())

    def _remove(self, sinks: Sequence[Sink]) -> None:
        """Take ``sinks`` off; the last one to go stops the feed."""
        with _REGISTRY_LOCK, self._lock:
            for sink in sinks:
                if sink in self._sinks:
                    self._sinks.remove(sink)
                    self._roster_version += 1
            if not self._sinks and not self._over:
                self._over = True
                if _REGISTRY.get(id(self.source)) is self:
                    del _REGISTRY[id(self.source)]
                self._stop.set()
                self._wake.set()
                self._status_wake.set()
                self._interrupt_status()

    def _join(self, timeout: float | None = None) -> None:
        deadline = None if timeout is None else time.monotonic() + timeout
        for thread in (self._reader, self._watcher):
            if thread is not None and thread is not threading.current_thread():
                thread.join(None if deadline is None else max(0.0, deadline - time.monotonic()))

    # -- reading the data --------------------------------------------------------------------
    def _open(self, policy: DeliveryPolicy, depth: int) -> Any:
        return self.source.open(ConnectionKind.DATA, policy=policy, depth=depth)

    def _read(self) -> None:
        conns: list[Any] = []
        try:
            conns.append(self._open(DeliveryPolicy.EVERY_ACQUISITION, POINT_DEPTH))
            conns.append(self._open(DeliveryPolicy.EVERY_BUFFER, SCAN_DEPTH))
        except BaseException as exc:
            self._open_error = exc
            self._opened.set()
            self._close(conns)
            return
        self._opened.set()
        try:
            self._loop(conns[0], conns[1])
        except BaseException as exc:  # a bug here must not leave the sinks waiting for ever
            log.exception("a sensor feed failed")
            self._fail(exc)
        finally:
            self._close(conns)
            self._ended.set()
            self._status_wake.set()
            self._interrupt_status()
            for sink in self.sinks:  # a detach waiting for its final batch: none will come
                with sink._cond:
                    sink._cond.notify_all()

    @staticmethod
    def _close(conns: Iterable[Any]) -> None:
        for conn in conns:
            try:
                conn.close()
            except BirisError:
                pass

    def _fail(self, exc: BaseException) -> None:
        """The sensor cannot go on (a damaged recording): every sink is told, and fails."""
        if self.error is None:
            self.error = exc
        for sink in self.sinks:
            sink._fail(exc)

    def _roster(self) -> _Roster:
        """What the sinks ask of the reader now, worked out again only when one came, went or
        began closing since the last time (a prompt reader asks this once per acquisition)."""
        roster = self._last_roster
        version = self._roster_version
        if roster is None or roster.version != version:
            with self._lock:
                roster = _Roster.of(self._roster_version, self._sinks)
            self._last_roster = roster
        return roster

    def _loop(self, points_conn: Any, scans_conn: Any) -> None:
        ended = [False, False]
        scans_polled = -math.inf
        while not self._stop.is_set():
            if self._wake.is_set():  # (clearing an event that is not set takes its lock)
                self._wake.clear()
            roster = self._roster()
            sinks, closing = roster.sinks, roster.closing
            begun = time.monotonic()
            points: list[Point] = []
            scans: list[Scan] = []
            faults: list[HardwareFault] = []
            waited = False
            if begun >= self._fault_until or closing:
                if not ended[0]:
                    wait = 0.0 if closing else roster.prompt_wait
                    points, ended[0], waited = self._drain(points_conn, wait, faults)
                    self._dropped_count(0, points_conn)
                    if wait > 0 and points and not faults:
                        # prompt: the acquisition goes out now, before anything else is asked
                        # (a poll for more, the scans: round trips a remote reader would wait)
                        for point in points:  # (one: a prompt wait returns with the first)
                            self._hand_out_now(sinks, point)
                        points = []
                        if begun - scans_polled < wait:
                            continue  # the scans at most every batch: a poll is a round trip
                if not ended[1] and not faults and self._lost_since is None:
                    scans_polled = begun
                    scans, ended[1], _ = self._drain(scans_conn, 0.0, faults)
                    self._dropped_count(1, scans_conn)
            more = len(points) >= DRAIN_MAX or len(scans) >= DRAIN_MAX
            going = self.error is not None or all(ended)
            if more and not going:  # a bounded detach takes what waits, until half its time
                now = time.monotonic()
                closing = tuple(s for s in closing if not now < s._drop_after < math.inf)
            if points or scans or faults or closing or self._sweep:
                self._hand_out(sinks, points, scans, faults, closing)
            if closing:
                self._remove(closing)
            if going:
                return  # the sensor has gone (or failed): what came is handed over
            if more:
                continue  # more waits: no pause
            if not waited:
                self._wake.wait(self._pause(sinks, begun))

    def _dropped_count(self, which: int, conn: Any) -> None:
        """Add what the sensor dropped on ``conn`` since last read; a count that went down
        started again (a connection reopened under the feed): all of it is new."""
        count = int(conn.dropped)
        seen = self._server_seen[which]
        self._server_dropped[which] += count - seen if count >= seen else count
        self._server_seen[which] = count

    def _pause(self, sinks: Sequence[Sink], begun: float) -> float:
        """How long the reader rests: until the next batch, the end of a fault's pause, or a
        sweep that falls due."""
        now = time.monotonic()
        if now < self._fault_until:
            return self._fault_until - now
        rest = min([BATCH_S, *(s.batch_s for s in sinks)]) - (now - begun)
        if self._sweep:
            period = min([s.sweep_period_s for s in sinks], default=0.0)
            rest = min(rest, self._sweep_sent + period - now)
        return max(0.0, rest)

    def _drain(
        self, conn: Any, wait: float, faults: list[HardwareFault]
    ) -> tuple[list[Any], bool, bool]:
        """What waits on ``conn`` (at most DRAIN_MAX; the first ask waits up to ``wait`` for
        it), whether the sensor has ended (closed: nothing more will come; the connection is
        closed at once), and whether that wait was taken (then the reader does not pause).

        A fault is kept in ``faults`` and pauses the asks (:data:`FAULT_POLL_S`); while a reset
        initialises the sensor the next batch tries again. Any other error of the sensor (a
        replay's ReplayError) fails the feed: what came before is handed over."""
        got: list[Any] = []
        timeout = wait
        while len(got) < DRAIN_MAX:
            try:
                got.append(conn.ready_for_data(timeout=timeout))
                self._network_back()
                if wait > 0:  # a prompt wait: what came goes out at once, the rest next time
                    return got, False, True
            except TimeoutError:
                self._network_back()
                return got, False, wait > 0
            except ConnectionLost as exc:  # ridden out: asked again after a back-off
                self._network_lost(exc)
                return got, False, False
            except ConnectionClosed:
                self._close([conn])
                return got, True, False  # the sensor stopped (or the replay ended)
            except HardwareFault as exc:
                faults.append(exc)
                self._last_fault = exc
                self._fault_until = time.monotonic() + FAULT_POLL_S
                return got, False, False
            except Initialising:  # a reset under way: its data come back
                self._network_back()  # when it is done, on these same connections
                return got, False, False
            except BirisError as exc:
                log.info("sensor feed stopped: %s", exc)
                self._fail(exc)
                return got, True, False
            timeout = 0.0
        return got, False, True

    # -- a lost network --------------------------------------------------------------------------
    def _network_lost(self, exc: ConnectionLost) -> None:
        """An ask met a lost network: the span begins (or goes on), the next ask waits for the
        back-off, and each sink whose limit has passed fails, naming the span."""
        now = time.monotonic()
        if self._lost_since is None:
            self._lost_since = now
            self._lost = LostSpan(time.time(), None, self._last_seen)
            self._lost_retry = LOST_RETRY_S
            log.warning("the network to the sensor is lost (%s): asking again", exc)
        else:
            self._lost_retry = min(LOST_RETRY_MAX_S, self._lost_retry * 2)
        self._fault_until = now + self._lost_retry
        lost = now - self._lost_since
        span = self._lost
        assert span is not None
        for sink in self.sinks:
            if sink.error is None and lost >= sink.lost_limit_s:
                ended = LostSpan(span.began, time.time(), span.after_t, gave_up=True)
                sink._spans.append(ended)
                assert ended.ended is not None
                log.info("sink %s gives up: no network %s", sink.name, ended)
                sink._fail(
                    ConnectionLost(
                        f"the network to the sensor was lost from {_clock_text(ended.began)} "
                        f"to {_clock_text(ended.ended)} and did not come back within "
                        f"{sink.lost_limit_s:g} s ({exc}): nothing was received in that span"
                        f"{ended.after()}"
                    )
                )

    def _network_back(self) -> None:
        """An ask succeeded: a span without the network under way ends, for every sink that
        still waited for it."""
        if self._lost_since is None:
            return
        span = self._lost
        self._lost_since = None
        self._lost = None
        self._fault_until = -math.inf
        if span is None:
            return
        ended = LostSpan(span.began, time.time(), span.after_t)
        log.warning("the network to the sensor is back: nothing was received %s", ended)
        for sink in self.sinks:
            if not (
                sink._spans and sink._spans[-1].gave_up and sink._spans[-1].began == span.began
            ):
                sink._spans.append(ended)

    # -- encoding and handing out ------------------------------------------------------------
    def _hand_out(
        self,
        sinks: Sequence[Sink],
        points: Sequence[Point],
        scans: Sequence[Scan],
        faults: Sequence[HardwareFault],
        closing: Sequence[Sink],
    ) -> None:
        """Encode what the sinks want of this batch, once, and offer each sink its share.

        A batch that cannot be encoded (a sensor handing out values outside the message
        types) is lost for every sink, counted in their drops and logged: the feed goes on.
        """
        if points:
            self._last_seen = max(self._last_seen, points[-1].t)
        for scan in scans:
            self._last_seen = max(self._last_seen, codec.scan_time(scan))
        active = {id(s): s.active() for s in sinks}
        union = frozenset().union(*active.values())
        try:
            per_point = {t: self._encode_points(t, points) for t in _POINT_TOPICS if t in union}
            frames = {s.frame for s in sinks if codec.POINTS_TOPIC in active[id(s)]}
            per_scan: dict[tuple[str, str], list[Message]] = {
                (codec.POINTS_TOPIC, f): self._scan_clouds(scans, f) for f in frames
            }
            if codec.RAW_SCAN_TOPIC in union:
                per_scan[(codec.RAW_SCAN_TOPIC, "")] = [self._raw_scan(s) for s in scans]
            sweepers = [s for s in sinks if codec.SWEEP_TOPIC in active[id(s)]]
            sweep = self._sweep_message(points, sweepers, any(s in closing for s in sweepers))
        except Exception:
            log.exception("a batch of %d points, %d scans not encoded", len(points), len(scans))
            self._unencoded[0] += len(points)
            self._unencoded[1] += len(scans)
            points, scans, per_point, per_scan, sweep = (), (), {}, {}, None
        for sink in sinks:
            mine = active[id(sink)]
            messages: list[Message] = []
            for i in range(len(points)):
                messages.extend(per_point[t][i] for t in _POINT_TOPICS if t in mine)
            if sweep is not None and codec.SWEEP_TOPIC in mine:
                messages.append(sweep)
            keys = ((codec.POINTS_TOPIC, sink.frame), (codec.RAW_SCAN_TOPIC, ""))
            for i in range(len(scans)):
                messages.extend(per_scan[k][i] for k in keys if k[0] in mine)
            final = sink in closing
            status = None
            if final and sink.status_period_s is not None:  # its last word on the sensor
                status = self._read_status()
                if status is not None:
                    messages.extend(self._status_messages(status, [sink])[sink])
            sink._offer(
                Batch(tuple(points), tuple(scans), tuple(messages), status, tuple(faults), final)
            )

    def _hand_out_now(self, sinks: Sequence[Sink], point: Point) -> None:
        """:meth:`_hand_out` of one acquisition read on a prompt wait, and nothing else: the
        same messages and the same batch for every sink, without the work a batch of scans,
        faults or closing sinks needs. A prompt reader pays this for every acquisition, so
        its cost bounds the service's rate (``net.throughput_128`` in docs/benchmarks.md)."""
        if point.t > self._last_seen:  # (as max(): a NaN time leaves it as it was)
            self._last_seen = point.t
        active = [s.active() for s in sinks]
        union = active[0] if len(active) == 1 else frozenset().union(*active)
        encoded: list[tuple[str, Message]] = []
        sweep = None
        try:
            for topic in _POINT_TOPICS:
                if topic in union:
                    encoded.append((topic, self._encode_point(topic, point)))
            if codec.SWEEP_TOPIC in union:
                sweepers = [
                    s for s, mine in zip(sinks, active, strict=True) if codec.SWEEP_TOPIC in mine
                ]
                sweep = self._sweep_message([point], sweepers, False)
            elif self._sweep:  # nobody wants it now: what came meanwhile is not kept
                self._sweep_message((), (), False)
        except Exception:
            log.exception("a batch of %d points, %d scans not encoded", 1, 0)
            self._unencoded[0] += 1
            for sink in sinks:
                sink._offer(Batch())
            return
        items = (point,)
        for sink, mine in zip(sinks, active, strict=True):
            messages = tuple([m for topic, m in encoded if topic in mine])
            if sweep is not None and codec.SWEEP_TOPIC in mine:
                messages += (sweep,)
            sink._offer(Batch(items, (), messages))

    def _encode_point(self, topic: str, point: Point) -> Message:
        """One acquisition's message on ``topic`` (one of :data:`_POINT_TOPICS`), counted."""
        if topic == codec.RAW_POINT_TOPIC:  # the one the service publishes: without a detour
            data = codec.encode_point(point)
            with self._encoded_lock:
                self.encoded[topic] += 1
            return Message(topic, codec.POINT, data, codec.stamp_ns(point.t), point)
        return self._encode_points(topic, [point])[0]  # (a list, as a batch is)

    def _count(
        self, encoded: codec.Encoded, item: object, log_time_ns: int | None = None
    ) -> Message:
        """``encoded`` as a Message from ``item``, counted; logged at ``log_time_ns`` if given."""
        with self._encoded_lock:
            self.encoded[encoded.topic] += 1
        t = encoded.log_time_ns if log_time_ns is None else log_time_ns
        return Message(encoded.topic, encoded.msgtype, encoded.data, t, item)

    def _encode_points(self, topic: str, points: Sequence[Point]) -> list[Message]:
        if topic == codec.PROFILE_TOPIC:
            clouds = codec.profile_clouds(points) if points else []
            return [self._count(c, p) for c, p in zip(clouds, points, strict=True)]
        if topic == codec.TF_TOPIC:
            return [self._count(codec.transforms(p), p) for p in points]
        return [
            self._count(
                codec.Encoded(topic, codec.POINT, codec.encode_point(p), codec.stamp_ns(p.t)), p
            )
            for p in points
        ]

    def _raw_scan(self, scan: Scan) -> Message:
        t = codec.stamp_ns(codec.scan_time(scan))
        return self._count(
            codec.Encoded(codec.RAW_SCAN_TOPIC, codec.SCAN, codec.encode_scan(scan), t), scan
        )

    def _scan_clouds(self, scans: Sequence[Scan], frame: Frame) -> list[Message]:
        """Each scan's cloud in ``frame``, logged when the scan was complete."""
        return [
            self._count(codec.scan_cloud(s, frame), s, codec.stamp_ns(codec.scan_time(s)))
            for s in scans
        ]

    def _sweep_message(
        self, points: Sequence[Point], sweepers: Sequence[Sink], final: bool
    ) -> Message | None:
        """The acquisitions since the last ``/biris/sweep`` message as one, once the smallest
        ``sweep_period_s`` of the sinks that want it has passed (or one of them is leaving);
        none while no sink wants it (what came meanwhile is not kept)."""
        with self._lock:
            if not sweepers:
                self._sweep = []
                return None
            self._sweep += points
            now = time.monotonic()
            period = min(s.sweep_period_s for s in sweepers)
            if not self._sweep or (now - self._sweep_sent < period and not final):
                return None
            pending, self._sweep = self._sweep, []
            self._sweep_sent = now
        return self._count(codec.sweep_cloud(pending), None)

    def _flush_sweep(self, sinks: Sequence[Sink]) -> tuple[Message, ...]:
        """What waits for ``/biris/sweep``, for a sink leaving after the reader has gone."""
        wanting = [s for s in sinks if codec.SWEEP_TOPIC in s.active()]
        sweep = self._sweep_message((), wanting, final=True) if wanting else None
        return () if sweep is None else (sweep,)

    # -- the status --------------------------------------------------------------------------
    def _read_status(
        self, conn: Any = None, newer_than: int | None = None, wait: float = 0.0
    ) -> StatusReading | None:
        """The status now (or, with ``newer_than``, once it has changed, waiting at most
        ``wait``), stamped; None when the sensor is closed or no change came."""
        try:
            if newer_than is not None:
                status = conn.status(newer_than=newer_than, timeout=wait)
            else:
                status = (conn or self.source).status()
        except (ConnectionClosed, TimeoutError):
            return None
        except BirisError as exc:
            return StatusReading(None, str(exc), sensor_time(self.source, self._last_seen))
        except Exception as exc:  # a bug, or a sensor failing its own way: said, tried again
            log.exception("status not read")
            error = f"{type(exc).__name__}: {exc}"
            return StatusReading(None, error, sensor_time(self.source, self._last_seen))
        t = sensor_time(self.source, self._last_seen)
        self._last_seen = max(self._last_seen, t)
        return StatusReading(status, None, t)

    def _status_messages(
        self, reading: StatusReading, sinks: Sequence[Sink]
    ) -> dict[Sink, list[Message]]:
        """Each sink's status messages for ``reading``: the lossless status, and a fault when
        the sensor has entered one (or one of another kind) since the sink's last reading; each
        encoded once for all."""
        out: dict[Sink, list[Message]] = {s: [] for s in sinks}
        status = reading.status
        if status is None:
            return out
        t = codec.stamp_ns(reading.t)
        raw: Message | None = None
        fault: Message | None = None
        faulted = _fault_state(status)
        for sink in sinks:
            mine = sink.active()
            if codec.RAW_STATUS_TOPIC in mine and isinstance(status, ServerStatus):
                if raw is None:
                    data = codec.encode_status(status, reading.t)
                    raw = self._count(
                        codec.Encoded(codec.RAW_STATUS_TOPIC, codec.STATUS, data, t), status
                    )
                out[sink].append(raw)
            entered = faulted is not None and faulted != sink._in_fault  # or another kind
            sink._in_fault = faulted
            if entered and codec.RAW_FAULT_TOPIC in mine:
                if fault is None:
                    known = self._fault_of(status)
                    data = codec.encode_fault(known, reading.t)
                    fault = self._count(
                        codec.Encoded(codec.RAW_FAULT_TOPIC, codec.FAULT, data, t), known
                    )
                out[sink].append(fault)
        return out

    def _fault_of(self, status: ServerStatus) -> HardwareFault:
        """The fault a status in a fault names: the one last met on the data when it is of the
        same kind (it has the sensor's own words), else one of that kind."""
        kind: str | None = status.fault if isinstance(status, ServerStatus) else None
        if kind is None:
            kind = str(status["state"]).partition(":")[2] or "internal"
        known = self._last_fault
        if known is not None and known.kind == kind:
            return known
        return HardwareFault(kind, "the server is in a fault")  # type: ignore[arg-type]

    def _deliver_status(self, reading: StatusReading, sinks: Sequence[Sink], force: bool) -> None:
        """Offer ``reading`` to the sinks it is due for: their period has come, or it is a change
        they watch, or the sensor entered or left a fault since their last (every one of
        ``sinks`` with ``force``)."""
        now = time.monotonic()
        status = reading.status
        signature = _signature(status) if status is not None else None
        due: list[Sink] = []
        for sink in sinks:
            periodic = sink.status_period_s is not None and now >= sink._next_status
            changed = sink.status_changes and signature not in (None, sink._last_signature)
            flipped = status is not None and _fault_state(status) != sink._in_fault
            if force or periodic or changed or flipped:
                due.append(sink)
                if sink.status_period_s is not None:
                    sink._next_status = now + sink.status_period_s
                if signature is not None:
                    sink._last_signature = signature
        messages = self._status_messages(reading, due)
        for sink in due:
            sink._offer(Batch(messages=tuple(messages[sink]), status=reading))

    def _first_status(self, sink: Sink) -> None:
        """A new sink's first status, at once (not at the end of a wait under way); the status
        thread serves it from then on."""
        reading = self._read_status()
        with self._status_lock:
            if reading is not None:
                self._deliver_status(reading, [sink], force=True)
            sink._greeted = True

    def _interrupt_status(self) -> None:
        """End a wait for a status change (closing the connection it waits on)."""
        conn = self._status_conn
        if conn is not None:
            self._close([conn])

    def _watch(self) -> None:
        """The status thread: readings for the sinks, pushed by the sensor or polled."""
        conn = None
        try:  # every sensor pushes its status to a connection's parked request
            conn = self.source.open(ConnectionKind.NORMAL)
        except BirisError as exc:
            log.info("feed status: no connection of its own (%s): polling", exc)
        self._status_conn = conn
        last: ServerStatus | None = None
        try:
            while not self._stop.is_set() and not self._ended.is_set():
                self._status_wake.clear()
                with self._lock:
                    sinks = [s for s in self._sinks if s._greeted and not s._closing]
                now = time.monotonic()
                due = min(
                    (s._next_status for s in sinks if s.status_period_s is not None),
                    default=math.inf,
                )
                watching = any(s.status_changes for s in sinks)
                change = None if last is None else last.change
                if conn is not None and watching and change is not None:
                    # the push: asks nothing until the status changes or the period is due
                    reading = self._read_status(conn, change, max(0.0, min(due - now, 60.0)))
                    if self._stop.is_set() or self._ended.is_set() or conn.closed:
                        return
                    if reading is None:  # no change before the period came
                        reading = self._read_status(conn)
                else:
                    wait = min(due - now, STATUS_POLL_S if watching else 60.0)
                    if wait > 0 and self._status_wake.wait(wait):
                        continue  # a sink came or went: look again
                    if not sinks:
                        continue
                    reading = self._read_status(conn)
                if reading is None:  # not to be read now (closing, or no answer): a pause,
                    self._status_wake.wait(STATUS_POLL_S)  # never a spin that starves the
                    continue  # reader of the interpreter lock
                if reading.status is not None:
                    last = reading.status
                with self._status_lock:
                    self._deliver_status(reading, sinks, force=False)
                if reading.status is None:  # not read (a lost network): asked again after a
                    pause = STATUS_POLL_S if self._lost_since is None else self._lost_retry
                    self._status_wake.wait(pause)  # pause, as the data are
        finally:
            if conn is not None:
                self._close([conn])


# -- a feed by callbacks ---------------------------------------------------------------------------


class SensorFeed:
    """Every acquisition, every completed scan and the status every ``status_period_s`` of a
    sensor, handed over in batches to callbacks that all run in one thread: a sink of the
    process's :class:`SharedFeed` that takes items, not messages.

    :meth:`start` attaches (nothing the sensor produces after it returns is missed), :meth:`stop`
    detaches once what the sensor queued has been handed over. A callback that raises stops
    this feed alone; the error is kept in :attr:`error`. A hardware fault met on the data is
    handed to ``on_fault`` and reading goes on (a reset may clear it).
    """

    def __init__(
        self,
        source: SensorSource,
        *,
        on_points: Callable[[list[Point]], None] | None = None,
        on_scans: Callable[[list[Scan]], None] | None = None,
        on_status: Callable[[ServerStatus | None, str | None], None] | None = None,
        on_fault: Callable[[BaseException], None] | None = None,
        status_period_s: float = 1.0,
        batch_s: float = BATCH_S,
        point_depth: int = POINT_DEPTH,
        scan_depth: int = SCAN_DEPTH,
    ) -> None:
        self._source = source
        self._on_points = on_points
        self._on_scans = on_scans
        self._on_status = on_status
        self._on_fault = on_fault
        self._options: dict[str, Any] = {
            "status_period_s": status_period_s if on_status is not None else None,
            "batch_s": batch_s,
            "point_depth": point_depth,
            "scan_depth": scan_depth,
        }
        self._sink: Sink | None = None
        self._failed = threading.Event()

    def start(self) -> SensorFeed:
        """Attach; raises what opening the sensor raised (ConnectionClosed for a stopped one)."""
        self._sink = attach(self._source, self._batch, name="feed", **self._options)
        return self

    def stop(self) -> None:
        """Hand over what waits, then detach. Idempotent."""
        if self._sink is not None:
            self._sink.detach()

    def _batch(self, batch: Batch) -> None:
        if batch.points and self._on_points is not None:
            self._on_points(list(batch.points))
        if batch.scans and self._on_scans is not None:
            self._on_scans(list(batch.scans))
        if self._on_fault is not None:
            for fault in batch.faults:
                self._on_fault(fault)
        if batch.status is not None and self._on_status is not None:
            self._on_status(batch.status.status, batch.status.error)

    @property
    def failed(self) -> threading.Event:
        """Set when a callback (or the sensor) failed: :attr:`error` says how."""
        return self._sink.failed if self._sink is not None else self._failed

    @property
    def error(self) -> BaseException | None:
        return self._sink.error if self._sink is not None else None

    @property
    def dropped_points(self) -> int:
        return self._sink.dropped_points if self._sink is not None else 0

    @property
    def dropped_scans(self) -> int:
        return self._sink.dropped_scans if self._sink is not None else 0
