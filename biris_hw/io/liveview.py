"""The live view: a Foxglove WebSocket server publishing the sensor as ROS 2 messages.

Foxglove and Lichtblick connect to a ``foxglove.websocket.v1`` server and show what it
advertises; :class:`LiveView` is that server (foxglove-sdk), fed through the client API
(:class:`~biris_hw.io.ros2.SensorFeed`), so it works on a local server, a network client's sensor
or a replay alike. It publishes the recorder's standard channels, with the same ros2msg schemas
and CDR bytes (:mod:`biris_hw.io.ros2`): ``/biris/profile`` and ``/tf`` per acquisition,
``/biris/points`` per completed scan, ``/diagnostics`` and ``/tf_static`` at the status period
(static transforms are re-sent because a viewer may connect at any time and the WebSocket does
not latch), and ``/biris/sweep``: the acquisitions that arrived since its previous message, in
``vehicle``, at most one message every ``sweep_period_s`` (what came meanwhile waits for the
next, and the status period sends what is left). Each message holds only the new points, so the
work per message is bounded by the data rate, however long a sweep lasts (a message carrying the
whole sweep so far would make the work grow with the square of its length); a viewer shows the
sweep building up by keeping each message for a while: the 3D panel's *decay time*, which
``docs/foxglove-layout.json`` sets for this topic.

Messages are only built for channels a viewer subscribes to, so a live view nobody watches costs
almost nothing; what is built is built in batches, in the feed's one thread and out of step
with the acquisitions (:class:`~biris_hw.io.ros2.SensorFeed`), so a watched live view adds little
to the moment an acquisition reaches the sensor's other clients. ``docs/foxglove-layout.json``
opens the panels.

A sensor in a fault keeps the view up: the WebSocket stays open, ``/diagnostics`` says ERROR
with the fault's kind and the server's message (at once when the fault is met, then at the
status period), and the data come back by themselves once the sensor has been reset. Meanwhile
the sensor is asked for data only every :data:`FAULT_POLL_S` (each ask would only hear the
fault again), not at the batch rate (twenty times a second on each of its two connections),
which would load a sensor reached over the network for nothing.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping
from types import TracebackType
from typing import Any

from biris_hw.data import ConnectionKind, Point, Scan
from biris_hw.errors import BirisError, ConnectionClosed, HardwareFault
from biris_hw.geometry import Frame, Mount
from biris_hw.io import ros2

__all__ = ["DEFAULT_PORT", "FAULT_POLL_S", "LiveView", "viewer_urls"]

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
"""Foxglove's usual WebSocket port."""

FAULT_POLL_S = 0.5
"""While the sensor is in a fault, the pause between two asks for data (real seconds)."""


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
        source: ros2.SensorSource,
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        frame: Frame = "vehicle",
        name: str = "biris",
        status_period_s: float = 1.0,
        sweep_period_s: float = 0.1,
        batch_s: float = ros2.BATCH_S,
    ) -> None:
        ros2.cloud_frame_id(frame)
        self.source = source
        self.host = host
        self.frame: Frame = frame
        self.name = name
        self._wanted_port = port
        self._sweep_period = sweep_period_s
        self._feed = ros2.SensorFeed(
            source,
            on_points=self._points,
            on_scans=self._scans,
            on_status=self._status,
            on_fault=self._fault_met,
            status_period_s=status_period_s,
            batch_s=batch_s,
            point_depth=1024,
            scan_depth=8,
        )
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self._lock = threading.Lock()
        record = getattr(source, "record", None)
        self._mount: Mount | None = getattr(record, "mount", None)
        self._now = 0.0
        self._sweep: list[Point] = []
        """Acquisitions not yet sent on ``/biris/sweep`` (at most one sweep period's worth)."""
        self._sweep_sent = 0.0
        self.published: dict[str, int] = {}
        """Messages published per topic (to at least one subscriber)."""
        self._closing = threading.Event()
        """Set by :meth:`close`: ends the pause between two asks for data during a fault."""
        self._fault: HardwareFault | None = None
        """The fault the sensor is in, as the feed last met it; None outside a fault."""
        self._fault_asked = -float("inf")
        """When the feed last asked for data and met the fault (monotonic seconds)."""
        self.faults_met = 0
        """Asks for data that met a fault (each pauses the feed: :data:`FAULT_POLL_S`)."""

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> LiveView:
        """Listen and begin publishing (``with`` does this)."""
        import foxglove

        self._context = foxglove.Context()
        self._server = foxglove.start_server(
            name=self.name, host=self.host, port=self._wanted_port, context=self._context
        )
        for topic, msgtype in ros2.TOPICS.items():
            schema = foxglove.Schema(
                name=msgtype, encoding="ros2msg", data=ros2.schema_text(msgtype).encode()
            )
            self._channels[topic] = foxglove.Channel(
                topic, schema=schema, message_encoding="cdr", context=self._context
            )
        try:
            self._feed.start()
        except BaseException:
            self._server.stop()
            raise
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
        return self._feed.error

    @property
    def failed(self) -> threading.Event:
        """Set when publishing stopped on its own (the source failed: a damaged recording, a
        callback's error): :attr:`error` says why."""
        return self._feed.failed

    def close(self) -> None:
        """Stop reading and publishing, close the server. Idempotent."""
        self._closing.set()  # first: the feed may be pausing in a fault
        self._feed.stop()
        if self._server is not None:
            self._send_sweep()  # the last acquisitions the feed handed over
            for channel in self._channels.values():
                channel.close()
            self._server.stop()
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

    # -- publishing --------------------------------------------------------------------------
    def _wanted(self, topic: str) -> bool:
        channel = self._channels.get(topic)
        return channel is not None and bool(channel.has_sinks())

    def _publish(self, message: ros2.Encoded, log_time_ns: int | None = None) -> None:
        t = message.log_time_ns if log_time_ns is None else log_time_ns
        self._channels[message.topic].log(message.data, log_time=t)
        self.published[message.topic] = self.published.get(message.topic, 0) + 1

    def _points(self, points: list[Point]) -> None:
        self._now = max(self._now, points[-1].t)
        self._mount = points[-1].mount
        if self._wanted("/biris/profile"):
            for message in ros2.profile_clouds(points):
                self._publish(message)
        if self._wanted("/tf"):
            for point in points:
                self._publish(ros2.transforms(point))
        if not self._wanted("/biris/sweep"):
            self._sweep = []
            return
        self._sweep += points
        self._send_sweep(when_due=True)

    def _send_sweep(self, when_due: bool = False) -> None:
        """The acquisitions waiting for ``/biris/sweep`` as one cloud (see the module); with
        ``when_due``, only once ``sweep_period_s`` has passed since the last."""
        if when_due and time.monotonic() - self._sweep_sent < self._sweep_period:
            return
        pending, self._sweep = self._sweep, []
        if not pending or not self._wanted("/biris/sweep"):
            return
        self._sweep_sent = time.monotonic()
        self._publish(ros2.sweep_cloud(pending))

    def _scans(self, scans: list[Scan]) -> None:
        for scan in scans:
            if scan.mount is not None:
                self._mount = scan.mount
            if self._wanted("/biris/points"):
                self._publish(ros2.scan_cloud(scan, self.frame))

    def _fault_met(self, exc: BaseException) -> None:
        """The feed asked for data and met a fault (it goes on reading, see SensorFeed).

        The first time, the fault is put on ``/diagnostics`` at once rather than at the next
        status period; every time, the feed's thread pauses until :data:`FAULT_POLL_S` has
        passed since its previous ask, since nothing but the fault will come until a reset.
        """
        self.faults_met += 1
        if isinstance(exc, HardwareFault) and self._learn(exc):
            try:
                self._status(self.source.status(), None)
            except ConnectionClosed:
                pass
            except BirisError as failure:
                self._status(None, str(failure))
        pause = self._fault_asked + FAULT_POLL_S - time.monotonic()
        if pause > 0:
            self._closing.wait(pause)
        self._fault_asked = time.monotonic()

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

    def _status(self, status: Mapping[str, Any] | None, error: str | None) -> None:
        self._send_sweep(when_due=True)  # what waited for the period, if no data came since
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
        t = ros2.sensor_time(self.source, self._now)
        if self._wanted("/tf_static"):
            self._publish(ros2.static_transforms(self._mount, t))
        if self._wanted("/diagnostics"):
            extra = {
                "live view": {
                    "dropped_points": self._feed.dropped_points,
                    "dropped_scans": self._feed.dropped_scans,
                }
            }
            self._publish(ros2.diagnostics(status, t, extra=extra, error=error))
