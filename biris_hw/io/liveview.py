"""The live view: a Foxglove WebSocket server publishing the sensor as ROS 2 messages.

Foxglove and Lichtblick show what a Foxglove WebSocket server advertises; :class:`LiveView` is
that server (foxglove-sdk), a sink of the sensor's feed (:mod:`biris_hw.io.feed`), so it works
on a local server, a network client's sensor or a replay alike, and shares the reading and the
encoding of every acquisition with whatever else serves or records the same sensor in the
process. It publishes the recorder's standard channels, the very bytes the feed encoded once
(:mod:`biris_hw.io.codec`): ``/biris/profile`` and ``/tf`` per acquisition, ``/biris/points``
per completed scan, ``/diagnostics`` and ``/tf_static`` at the status period (static transforms
are re-sent because a viewer may connect at any time and the WebSocket does not latch), and
``/biris/sweep``: the acquisitions that arrived since its previous message, in ``vehicle``, at
most one message every ``sweep_period_s`` (what came meanwhile waits for the next). Each message
holds only the new points, so the work per message is bounded by the data rate, however long a
sweep lasts (a message carrying the whole sweep so far would make the work grow with the square
of its length); a viewer shows the sweep building up by keeping each message for a while: the
3D panel's *decay time*, which the project's layout (:data:`LAYOUT_FILE`) sets for this topic.

**Which viewers.** foxglove-sdk (0.30) speaks the WebSocket subprotocols ``foxglove.sdk.v1``
and ``foxglove.sdk.v1.1`` only: the protocol once named ``foxglove.websocket.v1``, under a new
name, and the SDK has no setting to accept the old one (a client that offers only
``foxglove.websocket.v1`` gets HTTP 400). So the viewers that connect are Lichtblick 1.22.1 and
later and the current Foxglove app; the last open-source Foxglove Studio (1.x) and Lichtblick up
to 1.22.0 cannot.

**One URL opens everything.** The view also serves its layout over HTTP (a second port on the
same host, :data:`LAYOUT_PATH`), so that :attr:`LiveView.urls` ``["open"]`` -- a viewer's address
with ``?ds=foxglove-websocket&ds.url=<ws>&layoutUrl=<layout>`` -- opens the connection and the
panels in one go (Lichtblick reads ``layoutUrl``; Foxglove's app loads only layouts saved in its
own account, so ``urls["foxglove"]`` connects and the layout is imported by hand).

**Who can connect.** The protocol has no authentication, and foxglove-sdk checks no ``Origin``
header (it offers no hook to): any web page open in a browser on a host that reaches the port
can read the live view. It can only read: the view advertises no capability (no publishing, no
services, no parameters), so nothing it receives reaches the sensor. Hence the default host,
127.0.0.1; ``biris view --host`` beyond loopback warns.

**Log times** (``stamp``): the hardware clock's seconds by default, or the host's wall clock
(:class:`~biris_hw.io.codec.LogTimes`), which puts the view's timeline at today's date; the
messages' own stamps stay the hardware clock's either way.

Messages are only built for channels a viewer subscribes to (the feed asks, batch by batch), so
a live view nobody watches costs almost nothing; what is built is built in batches, out of step
with the acquisitions, and published from the view's own thread, so a watched live view adds
little to the moment an acquisition reaches the sensor's other clients.

A sensor in a fault keeps the view up: the WebSocket stays open, ``/diagnostics`` says ERROR
with the fault's kind and the server's message (at once when the fault is met, then at the
status period), and the data come back by themselves once the sensor has been reset. Meanwhile
the feed asks the sensor for data only every :data:`FAULT_POLL_S` (each ask would only hear the
fault again), not at the batch rate, which would load a sensor reached over the network for
nothing.

**On a moving robot** (``poses=``, and ``grid=``, ``proximity=``) the view also publishes
``/odom`` and ``odom -> vehicle`` on ``/tf`` (each pose sample once), ``/biris/points`` in
``odom`` (each scan deskewed), with a grid the certainty grid on ``/biris/grid`` at a few Hz,
and with a proximity alarm its answers on ``/biris/proximity``
(:class:`~biris_hw.io.moving_sink.MovingEncoder`, shared with the recorder); a 3D panel whose
display frame is ``odom`` then shows the profiles and sweeps where they were taken too, through
the transforms. Those channels are advertised only then, and the layout the view serves is
the moving robot's (:func:`layout`). The grid and the alarm are fed every
acquisition whether or not a viewer watches them, so a viewer who subscribes late sees the grid
whole and the alarm remembering what the head saw before.

A view its owner forgets to close is closed when the garbage collector takes it, or at the
interpreter's exit at the latest, as a file is: the feed holds it only weakly, so a script that
ends without ``close()`` ends (its WebSocket closed, its sink detached) rather than serve on.
"""

from __future__ import annotations

import contextlib
import http.server
import ipaddress
import json
import logging
import socket
import socketserver
import threading
import weakref
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar
from urllib.parse import urlencode

from biris_hw.data import ConnectionKind
from biris_hw.errors import BirisError, ConnectionClosed, HardwareFault
from biris_hw.geometry import Frame, Mount
from biris_hw.io import codec, feed
from biris_hw.io.moving_sink import (
    GridOption,
    MovingEncoder,
    PoseFeed,
    ProximityOption,
    moving_encoder,
)
from biris_hw.sensor import Sensor
from biris_hw.status import ServerStatus

__all__ = [
    "DEFAULT_PORT",
    "DEFAULT_VIEWER",
    "FAULT_POLL_S",
    "FOXGLOVE_APP",
    "LAYOUT_FILE",
    "LAYOUT_PATH",
    "SUBPROTOCOL",
    "LiveView",
    "is_loopback",
    "viewer_urls",
]

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
"""Foxglove's usual WebSocket port."""

SUBPROTOCOL = "foxglove.sdk.v1"
"""The WebSocket subprotocol the viewers offer and foxglove-sdk accepts (see the module: which
viewers); not ``foxglove.websocket.v1``."""

DEFAULT_VIEWER = "http://localhost:8080/"
"""Where Lichtblick's web app is served by default (its Docker image,
``ghcr.io/lichtblick-suite/lichtblick``, and ``yarn web:serve`` of its source): the base of
:attr:`LiveView.urls` ``["open"]``."""

FOXGLOVE_APP = "https://app.foxglove.dev/~/view"
"""Foxglove's web app: its deep links take ``ds`` and ``ds.url`` (and layouts saved in the
user's account, not a layout file)."""

LAYOUT_FILE = Path(__file__).with_name("foxglove-layout.json")
"""The project's layout for Foxglove and Lichtblick (shipped in the package): a 3-D panel
following ``vehicle`` with the clouds, the diagnostics, a plot of the pan."""

LAYOUT_PATH = "/foxglove-layout.json"
"""Where the view's HTTP server serves its layout (:func:`layout`)."""


def layout(*, moving: bool = False) -> dict[str, Any]:
    """The layout the view serves: :data:`LAYOUT_FILE`, or on a moving robot its variant.

    A view that stands still shows everything in ``vehicle``. On a moving robot the clouds are in
    ``odom`` and the vehicle moves through it: the 3-D panel's camera follows the vehicle's
    position but not its heading (``follow-position``), so the scene keeps the orientation of
    ``odom`` and the deskewed scans of ``/biris/points`` stay 30 s to build up the room around
    the vehicle; the reference grid lies in ``odom``; ``/biris/grid`` (the certainty grid) is
    drawn under the clouds and the proximity alarm's distance and age are plotted where the
    pan's plot was (the pan is in ``/tf`` still)."""
    base: dict[str, Any] = json.loads(LAYOUT_FILE.read_text())
    if not moving:
        return base
    panel = base["configById"]["3D!biris"]
    panel["followTf"] = "vehicle"
    panel["followMode"] = "follow-position"
    panel["layers"]["grid"]["frameId"] = codec.ODOM_FRAME
    panel["topics"][codec.POINTS_TOPIC]["decayTime"] = 30
    panel["topics"][codec.GRID_TOPIC] = {"visible": True}
    base["configById"]["Plot!azimuth"] = {
        "paths": [
            {
                "value": f"{codec.PROXIMITY_TOPIC}.distance_m",
                "enabled": True,
                "timestampMethod": "headerStamp",
                "label": "nearest in the zone (m)",
            },
            {
                "value": f"{codec.PROXIMITY_TOPIC}.age_s",
                "enabled": True,
                "timestampMethod": "headerStamp",
                "label": "its age (s)",
            },
        ],
        "showLegend": True,
    }
    return base


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


class _LayoutHandler(http.server.BaseHTTPRequestHandler):
    """Answers ``GET`` of :data:`LAYOUT_PATH` with the layout, anything else 404.

    The layout is fetched by the viewer's page, from another origin (Lichtblick's own server,
    or Foxglove's site): hence ``Access-Control-Allow-Origin: *`` (the file is public: it is in
    the package), and the answer to a browser's private-network preflight (a public page asking
    a host on loopback or the LAN)."""

    server_version = "biris-liveview"
    layout = b""
    timeout = 5.0
    """A request not sent within this (real seconds) is dropped: closing the view joins the
    threads answering requests, so none may wait for ever on a client that sends nothing."""

    def _headers(self, status: int, length: int) -> None:
        self.send_response(status)
        self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Access-Control-Allow-Private-Network", "true")
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(length))
        self.end_headers()

    def do_GET(self) -> None:
        if self.path.split("?", 1)[0] == LAYOUT_PATH:
            self._headers(200, len(self.layout))
            self.wfile.write(self.layout)
        else:
            self._headers(404, 0)

    def do_OPTIONS(self) -> None:
        self.send_response(204)
        self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Access-Control-Allow-Methods", "GET")
        self.send_header("Access-Control-Allow-Headers", "*")
        self.send_header("Access-Control-Allow-Private-Network", "true")
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("layout server: " + format, *args)


class _LayoutServer:
    """The layout over HTTP on ``host``, on a port of its own (0: a free one), in a thread."""

    def __init__(self, host: str, port: int = 0, *, moving: bool = False) -> None:
        served = json.dumps(layout(moving=moving), indent=1).encode()
        handler = type("_Handler", (_LayoutHandler,), {"layout": served})
        # a plain TCP server, not http.server's: that one looks its host's name up (a DNS
        # query, seconds on a host without DNS) for a header nobody reads
        server_class = type(
            "_Server",
            (socketserver.ThreadingTCPServer,),
            {"address_family": _family(host), "allow_reuse_address": True},
        )
        self.httpd = server_class((host, port), handler)
        self.port = int(self.httpd.server_address[1])
        self._thread = threading.Thread(
            target=self.httpd.serve_forever, name="biris-liveview-layout", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join()


def _family(host: str) -> socket.AddressFamily:
    """IPv6 for an IPv6 literal (``::1``, ``::``), else IPv4."""
    with contextlib.suppress(ValueError):
        if ipaddress.ip_address(host).version == 6:
            return socket.AF_INET6
    return socket.AF_INET


class _Parts:
    """What a started view must close, apart from the view itself (its finaliser holds this,
    never the view)."""

    def __init__(
        self,
        sink: feed.Sink,
        server: Any,
        channels: Sequence[Any],
        url: str,
        layout: _LayoutServer | None,
    ) -> None:
        self.sink = sink
        self.server = server
        self.channels = list(channels)
        self.url = url
        self.layout = layout
        self.by_owner = False
        """close() was called (else the collector or the interpreter's exit closes it)."""


def _shut(parts: _Parts) -> None:
    """Detach the view's sink, close its channels, stop its servers (once)."""
    if not parts.by_owner:
        log.debug("live view on %s closed: its owner had not closed it", parts.url)
    parts.sink.detach()
    for channel in parts.channels:
        channel.close()
    parts.server.stop()
    if parts.layout is not None:
        parts.layout.stop()


def is_loopback(host: str) -> bool:
    """Whether listening on ``host`` keeps the port to this machine: ``localhost`` or an
    address in 127.0.0.0/8 or ``::1``. The wildcards (``0.0.0.0``, ``::``), a host name and
    any other address are reachable from elsewhere (or may be)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _url_host(host: str) -> str:
    """``host`` as it stands in a URL: a wildcard becomes this machine's name (a viewer cannot
    open ``0.0.0.0``), an IPv6 literal goes in brackets."""
    if host in ("0.0.0.0", "::", ""):
        host = socket.gethostname()
    if _family(host) == socket.AF_INET6:
        return f"[{host}]"
    return host


def viewer_urls(
    host: str, port: int, layout_port: int | None = None, viewer: str = DEFAULT_VIEWER
) -> dict[str, str]:
    """Where to point a viewer at a view listening on ``host:port``.

    ``websocket``: the WebSocket URL; ``foxglove``: Foxglove's web app connecting to it; with
    the view's ``layout_port``, ``layout``: the layout's URL, and ``open``: ``viewer`` (a
    Lichtblick web app, :data:`DEFAULT_VIEWER`) connecting and loading the layout in one go."""
    where = _url_host(host)
    ws = f"ws://{where}:{port}"
    source = {"ds": "foxglove-websocket", "ds.url": ws}
    urls = {"websocket": ws, "foxglove": f"{FOXGLOVE_APP}?{urlencode(source, safe=':/')}"}
    if layout_port is not None:
        layout = f"http://{where}:{layout_port}{LAYOUT_PATH}"
        query = urlencode({**source, "layoutUrl": layout}, safe=":/")
        urls["layout"] = layout
        urls["open"] = f"{viewer}{'&' if '?' in viewer else '?'}{query}"
    return urls


class LiveView:
    """A Foxglove WebSocket server showing ``source`` live, while the ``with`` block runs.

    ``port`` 0 picks a free one (:attr:`port` says which); ``host`` is where it listens
    (localhost by default: the protocol has no authentication, see the module). ``frame`` is
    the frame of the completed scans' clouds, as for the recorder. ``stamp`` the log times:
    ``"hardware"`` or ``"wall"`` (:class:`~biris_hw.io.codec.LogTimes`). ``layout_port`` is
    where the layout is served over HTTP on ``host`` (0: a free port; None: not served);
    ``viewer`` the web app :attr:`urls` ``["open"]`` points at.

    ``poses`` (the vehicle's pose: a :class:`~biris_hw.io.pose.PoseBuffer`, or any
    :class:`~biris_hw.io.moving_sink.PoseFeed`, on the sensor's hardware clock) and ``grid`` (a
    :class:`~biris_hw.io.grid.GridParams`, :class:`~biris_hw.io.grid.CertaintyGrid` or
    :class:`~biris_hw.io.grid.GridFeeder`; it needs ``poses``) and ``proximity`` (a
    :class:`~biris_hw.io.proximity.ProximityZone`, :class:`~biris_hw.io.proximity.ProximityAlarm`
    or :class:`~biris_hw.io.proximity.ProximityFeeder`; it needs ``poses``) add the moving
    robot's channels (see the module); ``/biris/points`` is then in ``odom``, whatever
    ``frame`` says.

    Raises:
        RuntimeError: the server cannot listen there (the port is taken).
        OSError: the layout's HTTP server cannot listen on ``layout_port``.
        ValueError: a frame or a stamp that is neither of its two; ``grid`` or ``proximity``
            without ``poses``.
        TypeError: ``poses`` is not a pose buffer, ``grid`` or ``proximity`` none of its
            kinds.
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
        stamp: codec.Stamp = "hardware",
        layout_port: int | None = 0,
        viewer: str = DEFAULT_VIEWER,
        poses: PoseFeed | None = None,
        grid: GridOption | None = None,
        proximity: ProximityOption | None = None,
    ) -> None:
        codec.cloud_frame_id(frame)
        self.moving: MovingEncoder | None = moving_encoder(poses, grid, proximity)
        """What adds the vehicle's poses, the clouds in ``odom``, the grid and the proximity
        alarm (``poses=``)."""
        self.source = source
        self.host = host
        self.frame: Frame = frame
        self.name = name
        self.viewer = viewer
        self.log_times = codec.LogTimes(stamp)
        """How the view's messages are logged (``stamp``), and the wall offset once measured."""
        self._wanted_port = port
        self._layout_port = layout_port
        self._options: dict[str, Any] = {
            "name": "liveview",
            "topics": _TOPICS if self.moving is None else _TOPICS - {codec.POINTS_TOPIC},
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
        self._layout: _LayoutServer | None = None
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

        self.log_times.anchor_to(self.source)
        self._context = foxglove.Context()
        self._server = foxglove.start_server(
            name=self.name, host=self.host, port=self._wanted_port, context=self._context
        )
        try:
            if self._layout_port is not None:
                self._layout = _LayoutServer(
                    self.host, self._layout_port, moving=self.moving is not None
                )
            topics = dict(codec.TOPICS)
            if self.moving is not None:
                self.moving.warm()
                topics.update(self.moving.topics)
            for topic, msgtype in topics.items():
                schema = foxglove.Schema(
                    name=msgtype, encoding="ros2msg", data=codec.schema_text(msgtype).encode()
                )
                self._channels[topic] = foxglove.Channel(
                    topic, schema=schema, message_encoding="cdr", context=self._context
                )
            self._sink = feed.attach(
                self.source,
                _weakly(self._batch, None),
                wants=_weakly(self._wanted, False),
                **self._options,
            )
        except BaseException:
            for channel in self._channels.values():
                channel.close()
            self._server.stop()
            if self._layout is not None:
                self._layout.stop()
            raise
        self._parts = _Parts(
            self._sink,
            self._server,
            tuple(self._channels.values()),
            self.urls["websocket"],
            self._layout,
        )
        self._closer = weakref.finalize(self, _shut, self._parts)
        return self

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return int(self._server.port) if self._server is not None else self._wanted_port

    @property
    def urls(self) -> dict[str, str]:
        """:func:`viewer_urls` for this server (``open`` and ``layout`` while it serves the
        layout)."""
        layout = self._layout.port if self._layout is not None else None
        return viewer_urls(self.host, self.port, layout, self.viewer)

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
        self._layout = None

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
        self._channels[message.topic].log(
            message.data, log_time=self.log_times(message.log_time_ns)
        )
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
        if self.moving is not None:
            for encoded in self.moving.messages(batch, self._wanted):
                self._publish(encoded)
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
            counts: dict[str, object] = {
                "dropped_points": 0 if sink is None else sink.dropped_points,
                "dropped_scans": 0 if sink is None else sink.dropped_scans,
            }
            if self.moving is not None:
                counts.update(self.moving.counts())
            extra = {"live view": counts}
            self._publish(codec.diagnostics(status, reading.t, extra=extra, error=error))
