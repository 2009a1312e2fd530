"""The live view: a Foxglove WebSocket server publishing the sensor as ROS 2 messages.

Foxglove and Lichtblick connect to a ``foxglove.websocket.v1`` server and show what it
advertises; :class:`LiveView` is that server (foxglove-sdk), a sink of the sensor's feed
(:mod:`biris_hw.io.feed`), so it works on a local server, a network client's sensor or a replay
alike, and shares the reading and the encoding of every acquisition with whatever else serves or
records the same sensor in the process. It publishes the recorder's standard channels, the very
bytes the feed encoded once (:mod:`biris_hw.io.codec`): ``/biris/profile`` and ``/tf`` per
acquisition, ``/biris/points`` per completed scan, ``/diagnostics`` and ``/tf_static`` at the
status period (static transforms are re-sent because a viewer may connect at any time and the
WebSocket does not latch), and ``/biris/sweep``: the acquisitions that arrived since its
previous message, in ``vehicle``, at most one message every ``sweep_period_s`` (what came
meanwhile waits for the next). Each message holds only the new points, so the work per message
is bounded by the data rate, however long a sweep lasts (a message carrying the whole sweep so
far would make the work grow with the square of its length); a viewer shows the sweep building
up by keeping each message for a while: the 3D panel's *decay time*, which
``docs/foxglove-layout.json`` sets for this topic.

Messages are only built for channels a viewer subscribes to (the feed asks, batch by batch), so
a live view nobody watches costs almost nothing; what is built is built in batches, out of step
with the acquisitions, and published from the view's own thread, so a watched live view adds
little to the moment an acquisition reaches the sensor's other clients.
``docs/foxglove-layout.json`` opens the panels.

A sensor in a fault keeps the view up: the WebSocket stays open, ``/diagnostics`` says ERROR
with the fault's kind and the server's message (at once when the fault is met, then at the
status period), and the data come back by themselves once the sensor has been reset. Meanwhile
the feed asks the sensor for data only every :data:`FAULT_POLL_S` (each ask would only hear the
fault again), not at the batch rate, which would load a sensor reached over the network for
nothing.

A view its owner forgets to close is closed when the garbage collector takes it, or at the
interpreter's exit at the latest, as a file is: the feed holds it only weakly, so a script that
ends without ``close()`` ends (its WebSocket closed, its sink detached) rather than serve on.
"""

from __future__ import annotations

import logging
import threading
import weakref
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any, TypeVar

from biris_hw.data import ConnectionKind
from biris_hw.errors import BirisError, ConnectionClosed, HardwareFault
from biris_hw.geometry import Frame, Mount
from biris_hw.io import codec, feed
from biris_hw.sensor import Sensor
from biris_hw.status import ServerStatus

__all__ = ["DEFAULT_PORT", "FAULT_POLL_S", "LiveView", "viewer_urls"]

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
"""Foxglove's usual WebSocket port."""

FAULT_POLL_S = feed.FAULT_POLL_S
"""While the sensor is in a fault, the pause between two asks for data (real seconds): the
feed's."""

_TOPICS = frozenset({codec.PROFILE_TOPIC, codec.TF_TOPIC, codec.SWEEP_TOPIC, codec.POINTS_TOPIC})
"""What the view takes from the feed; it makes ``/tf_static`` and ``/diagnostics`` itself."""


_T = TypeVar("_T")
_R = TypeVar("_R")


def _weakly(method: Callable[[_T], _R], default: _R) -> Callable[[_T], _R]:
    """``method`` (a bound method) called through a weak reference to its object: what the
    feed holds of a view must not keep the view alive. ``default`` once the view has gone."""
    ref = weakref.WeakMethod(method)

    def call(arg: _T) -> _R:
        bound = ref()
        return default if bound is None else bound(arg)

    return call


class _Parts:
    """What a started view must close, apart from the view itself (its finaliser holds this,
    never the view)."""

    def __init__(self, sink: feed.Sink, server: Any, channels: Sequence[Any], url: str) -> None:
        self.sink = sink
        self.server = server
        self.channels = list(channels)
        self.url = url
        self.by_owner = False
        """close() was called (else the collector or the interpreter's exit closes it)."""


def _shut(parts: _Parts) -> None:
    """Detach the view's sink, close its channels and stop its WebSocket server (once)."""
    if not parts.by_owner:
        log.debug("live view on %s closed: its owner had not closed it", parts.url)
    parts.sink.detach()
    for channel in parts.channels:
        channel.close()
    parts.server.stop()


def viewer_urls(host: str, port: int) -> dict[str, str]:
    """Where to point a viewer: the WebSocket URL, and Foxglove's web app opening it."""
    ws = f"ws://{host}:{port}"
    return {
        "websocket": ws,
        "foxglove": f"https://app.foxglove.dev/view?ds=foxglove-websocket&ds.url={ws}",
    }


class LiveView:
    """A Foxglove WebSocket server showing ``source`` live, while the ``with`` block runs.

    ``port`` 0 picks a free one (:attr:`port` says which); ``host`` is where it listens
    (localhost by default: the protocol has no authentication). ``frame`` is the frame of the
    completed scans' clouds, as for the recorder.

    Raises:
        RuntimeError: the server cannot listen there (the port is taken).
        ConnectionClosed: the source has stopped.
    """

    def __init__(
        self,
        source: Sensor,
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        frame: Frame = "vehicle",
        name: str = "biris",
        status_period_s: float = 1.0,
        sweep_period_s: float = 0.1,
        batch_s: float = feed.BATCH_S,
    ) -> None:
        codec.cloud_frame_id(frame)
        self.source = source
        self.host = host
        self.frame: Frame = frame
        self.name = name
        self._wanted_port = port
        self._options: dict[str, Any] = {
            "name": "liveview",
            "topics": _TOPICS,
            "frame": frame,
            "status_period_s": status_period_s,
            "batch_s": batch_s,
            "sweep_period_s": sweep_period_s,
            "point_depth": 1024,
            "scan_depth": 8,
        }
        self._sink: feed.Sink | None = None
        self._failed = threading.Event()
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        record = source.record
        self._mount: Mount | None = None if record is None else record.mount
        self.published: dict[str, int] = {}
        """Messages published per topic (to at least one subscriber)."""
        self._fault: HardwareFault | None = None
        """The fault the sensor is in, as the feed last met it; None outside a fault."""
        self.faults_met = 0
        """Asks for data that met a fault (the feed pauses after each: :data:`FAULT_POLL_S`)."""
        self._parts: _Parts | None = None
        self._closer: weakref.finalize[[_Parts], LiveView] | None = None
        """Closes the view's parts once: :meth:`close`, the garbage collector or the exit."""

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> LiveView:
        """Listen and begin publishing (``with`` does this)."""
        import foxglove

        self._context = foxglove.Context()
        self._server = foxglove.start_server(
            name=self.name, host=self.host, port=self._wanted_port, context=self._context
        )
        for topic, msgtype in codec.TOPICS.items():
            schema = foxglove.Schema(
                name=msgtype, encoding="ros2msg", data=codec.schema_text(msgtype).encode()
            )
            self._channels[topic] = foxglove.Channel(
                topic, schema=schema, message_encoding="cdr", context=self._context
            )
        try:
            self._sink = feed.attach(
                self.source,
                _weakly(self._batch, None),
                wants=_weakly(self._wanted, False),
                **self._options,
            )
        except BaseException:
            self._server.stop()
            raise
        self._parts = _Parts(
            self._sink, self._server, tuple(self._channels.values()), self.urls["websocket"]
        )
        self._closer = weakref.finalize(self, _shut, self._parts)
        return self

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return int(self._server.port) if self._server is not None else self._wanted_port

    @property
    def urls(self) -> dict[str, str]:
        """:func:`viewer_urls` for this server."""
        return viewer_urls(self.host, self.port)

    @property
    def error(self) -> BaseException | None:
        """Why publishing stopped early, or None."""
        return self._sink.error if self._sink is not None else None

    @property
    def failed(self) -> threading.Event:
        """Set when publishing stopped on its own (the source failed: a damaged recording, a
        publication's error): :attr:`error` says why."""
        return self._sink.failed if self._sink is not None else self._failed

    def close(self) -> None:
        """Stop reading (the last acquisitions handed over are published) and publishing,
        close the server. Idempotent."""
        if self._parts is not None:
            self._parts.by_owner = True
        if self._closer is not None:
            self._closer()
        self._server = None

    def __enter__(self) -> LiveView:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- publishing (the view's own thread, in batches) ----------------------------------------
    def _wanted(self, topic: str) -> bool:
        """Whether a viewer subscribes to ``topic`` now (the feed asks before it encodes)."""
        channel = self._channels.get(topic)
        return channel is not None and bool(channel.has_sinks())

    def _publish(self, message: codec.Encoded) -> None:
        self._channels[message.topic].log(message.data, log_time=message.log_time_ns)
        self.published[message.topic] = self.published.get(message.topic, 0) + 1

    def _batch(self, batch: feed.Batch) -> None:
        """Publish what the feed encoded for the view; then a fault met, a status read."""
        if batch.points:
            self._mount = batch.points[-1].mount
        for scan in batch.scans:
            if scan.mount is not None:
                self._mount = scan.mount
        for message in batch.messages:
            if self._wanted(message.topic):
                self._publish(message)
        for fault in batch.faults:
            self._fault_met(fault)
        if batch.status is not None:
            self._status(batch.status)

    def _fault_met(self, exc: HardwareFault) -> None:
        """The feed asked for data and met a fault (it pauses, then goes on reading): the first
        time, the fault is put on ``/diagnostics`` at once rather than at the next status
        period."""
        self.faults_met += 1
        if self._learn(exc):
            t = feed.sensor_time(self.source, 0.0)
            try:
                self._status(feed.StatusReading(self.source.status(), None, t))
            except ConnectionClosed:
                pass
            except BirisError as failure:
                self._status(feed.StatusReading(None, str(failure), t))

    def _learn(self, fault: HardwareFault) -> bool:
        """Keep ``fault`` as the one the sensor is in; True (and logged) if it is news."""
        news = self._fault is None or self._fault.kind != fault.kind
        self._fault = fault
        if news:
            log.warning("live view: the sensor is in a fault (%s): shown on /diagnostics", fault)
        return news

    def _ask_fault(self) -> HardwareFault | None:
        """The fault the sensor is in, with its message, when the status names one the feed
        has not met yet (the status may come first): a poll on a connection of our own raises
        it. None if the sensor cannot say."""
        try:
            with self.source.open(ConnectionKind.NORMAL) as conn:
                conn.wait_idle(timeout=0)
        except HardwareFault as exc:
            return exc
        except (BirisError, TimeoutError):
            pass
        return None

    def _status(self, reading: feed.StatusReading) -> None:
        status: ServerStatus | None = reading.status
        error = reading.error
        if status is not None:
            state = str(status["state"])
            fault = self._fault
            if not state.startswith("fault"):
                self._fault = None  # left (a reset): the next fault is met afresh
            elif error is None:  # the kind alone says little: the server's own words too
                if fault is None or state != f"fault:{fault.kind}":
                    asked = self._ask_fault()
                    if asked is not None:
                        self._learn(asked)
                        fault = asked
                if fault is not None and state == f"fault:{fault.kind}":
                    error = fault.message
        if self._wanted(codec.TF_STATIC_TOPIC):
            self._publish(codec.static_transforms(self._mount, reading.t))
        if self._wanted(codec.DIAGNOSTICS_TOPIC):
            sink = self._sink
            extra = {
                "live view": {
                    "dropped_points": 0 if sink is None else sink.dropped_points,
                    "dropped_scans": 0 if sink is None else sink.dropped_scans,
                }
            }
            self._publish(codec.diagnostics(status, reading.t, extra=extra, error=error))
