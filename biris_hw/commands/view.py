"""``biris view``: the sensor live in Foxglove or Lichtblick (a Foxglove WebSocket server).

``biris view --sim --cw -45 --ccw 45`` starts a simulator and a server, sweeps between the
limits and serves the live view (:class:`~biris_hw.io.liveview.LiveView`) on ``--port`` (8765)
until ``--duration`` is over or Ctrl-C; without limits nothing is commanded and whatever the
sensor does is shown. ``biris view --replay run.mcap`` shows a recording instead (a file damaged
part way is shown up to the damage, then the command stops with a one-line error, exit status
1). The command prints the WebSocket URL, and the one URL that opens it with the project's
layout in Lichtblick (``--viewer``: where its web app is), and Foxglove's (README: "Live view").

Every flag is checked before the sensor is touched (exit status 2, nothing started): the port
(0 to 65535, and free: another program listening there is named as the cause), the host (it must
be an address of this machine), the sweep's limits, the replay's file, the viewer's URL.
``--host`` beyond loopback warns: the live view has no authentication, and foxglove-sdk checks
no ``Origin`` (:mod:`biris_hw.io.liveview`), so anyone who reaches the port can watch.

``--stamp wall`` logs the messages at the host's wall clock (a viewer's timeline then reads
today's date and time), ``--stamp hardware`` at the hardware clock's seconds; the messages keep
their hardware stamps either way. The default is ``wall`` on a real sensor (``--target``, or a
service with ``--connect``) and ``hardware`` on the simulator and a replay, whose clocks are not
the host's (a time-scaled simulator's seconds are not real ones; a replay plays the recorded
times).

On a moving robot (docs/moving.md), as for ``biris record``: ``--drive`` (with ``--sim``) puts
the simulated vehicle on its default drive, and the view publishes its odometry (``/odom``,
``odom -> vehicle`` on ``/tf``) and ``/biris/points`` in ``odom``; ``--grid`` adds the certainty
grid on ``/biris/grid`` and ``--proximity`` the proximity alarm on ``/biris/proximity``. A replay
of a recording that holds the vehicle's poses (``odom -> vehicle`` on ``/tf``, else ``/odom``) is
shown the same way, the poses handed on at the pace of the data; ``--grid`` and ``--proximity``
build the grid and the alarm from them.

A fault of the sensor does not end the view: the WebSocket stays up, ``/diagnostics`` says
ERROR with the fault, the command says once on stderr what the fault is and how to recover
(:class:`~biris_hw.commands.faults.FaultNotice`), and once the sensor has been reset the data
come back (a sweep the fault ended is started again once the server is idle). Meanwhile the
command looks at the status every :data:`POLL_S`. Exit status: 0, or 1 when the sensor was
still in a fault as the view ended, 130 after Ctrl-C, 143 after SIGTERM (which the dispatcher,
:mod:`biris_hw.cli`, turns into Ctrl-C's interruption: the view closes the same way).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import socket
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from biris_hw.commands import options
from biris_hw.commands.argtypes import degrees, path, positive_float
from biris_hw.commands.console import prog_of
from biris_hw.commands.failures import EXIT_FAULT, EXIT_INTERRUPTED, UsageError, report_error
from biris_hw.commands.faults import FaultNotice
from biris_hw.commands.options import (
    add_continuous_argument,
    add_stamp_argument,
    add_target_arguments,
    add_timeout_argument,
    add_yes_argument,
    check_target_arguments,
    stamp_of,
    sweep_chosen,
)
from biris_hw.commands.record import (
    add_moving_arguments,
    check_moving_arguments,
    grid_params,
    moving_session,
    proximity_zone,
)
from biris_hw.commands.session import confirm_moves, open_session, quiet_collector
from biris_hw.errors import HardwareFault
from biris_hw.status import ServerState

if TYPE_CHECKING:
    from collections.abc import Iterator

    from biris_hw.io.liveview import LiveView
    from biris_hw.io.moving_sink import PoseFeed
    from biris_hw.sensor import Sensor

__all__ = ["add_arguments", "run"]


def tcp_port(text: str) -> int:
    """A TCP port to listen on: 0 (any free one) to 65535."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a port is a whole number, not {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0 (any free one) to 65535, not {value}")
    return value


def viewer_url(text: str) -> str:
    """A web app's address: http:// or https://."""
    if not text.startswith(("http://", "https://")) or any(c.isspace() for c in text):
        raise argparse.ArgumentTypeError(f"an http:// or https:// address, not {text!r}")
    return text


DEFAULT_PORT = 8765
""":data:`biris_hw.io.liveview.DEFAULT_PORT`, named here for the same reason."""

DEFAULT_VIEWER = "http://localhost:8080/"
""":data:`biris_hw.io.liveview.DEFAULT_VIEWER`, named here for the same reason."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    view = parser.add_argument_group("live view")
    view.add_argument(
        "--port",
        type=tcp_port,
        default=DEFAULT_PORT,
        help=f"WebSocket port (default {DEFAULT_PORT}; 0: any free one)",
    )
    view.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; the protocol has no authentication: "
        "beyond loopback anyone who reaches the port can watch)",
    )
    add_stamp_argument(view)
    view.add_argument(
        "--viewer",
        type=viewer_url,
        default=DEFAULT_VIEWER,
        metavar="URL",
        help=f"where Lichtblick's web app is, for the URL printed (default {DEFAULT_VIEWER})",
    )
    view.add_argument(
        "--duration",
        type=positive_float,
        metavar="S",
        help="stop after S seconds (default: Ctrl-C)",
    )
    view.add_argument(
        "--frame", choices=("vehicle", "sensor"), default="vehicle", help="frame of /biris/points"
    )
    view.add_argument("--replay", type=path, metavar="FILE", help="show a recording instead")
    view.add_argument(
        "--speed", type=positive_float, default=1.0, metavar="X", help="--replay's pace (1)"
    )
    add_moving_arguments(parser)
    how = parser.add_argument_group("what to scan meanwhile (optional)")
    how.add_argument("--cw", type=degrees, metavar="DEG", help="sweep: clockwise limit")
    how.add_argument("--ccw", type=degrees, metavar="DEG", help="sweep: counter-clockwise limit")
    add_continuous_argument(parser)
    add_yes_argument(parser)
    add_timeout_argument(parser)
    add_target_arguments(parser)


POLL_S = 0.5
"""How often the command looks at the sensor's status (to say when a fault comes and goes, and
to sweep again after a reset), in real seconds."""


def _wait(duration: float | None, stop: threading.Event) -> None:
    stop.wait(duration)


def run(
    args: argparse.Namespace,
    out: TextIO | None = None,
    ready: Any = None,
    stop: threading.Event | None = None,
) -> int:
    """Serve the live view; 0 after ``--duration`` (1 if the sensor was then in a fault), 130
    after Ctrl-C. ``ready`` (tests), if given, is called with the :class:`LiveView` once it
    listens; ``stop`` (tests, an embedding program), if given, ends a sensor's view when set,
    as the end of ``--duration`` would."""
    from biris_hw.io.liveview import LiveView

    stream = out or sys.stdout
    sweep = sweep_chosen(args)
    stop = stop or threading.Event()
    _check_flags(args, sweep)  # all of them, before the sensor is touched
    options: dict[str, Any] = {
        "host": args.host,
        "port": args.port,
        "frame": args.frame,
        "stamp": stamp_of(args),
        "viewer": args.viewer,
    }
    try:
        if args.replay is not None:
            from biris_hw.io.record.replay import ReplayError
            from biris_hw.opening import open_sensor

            poses = _recorded_poses(args)
            if poses is not None:
                options["poses"] = poses
                options["grid"] = grid_params() if args.grid else None
                options["proximity"] = proximity_zone(args)
            with (
                open_sensor(replay=args.replay, speed=args.speed, autostart=False) as replay,
                _listening(LiveView(replay, **options), args) as view,
            ):
                replay.start()
                _announce(view, stream, ready)
                _wait(args.duration, view.failed)  # a damaged file ends the view
            if isinstance(view.error, ReplayError):  # shown up to the damage
                report_error(prog_of(args), view.error, debug=getattr(args, "debug", False))
                return EXIT_FAULT
            if view.error is not None:
                raise view.error
            return 0
        with moving_session(args, open_session) as (session, poses):
            options["poses"] = poses
            options["grid"] = grid_params() if args.grid else None
            options["proximity"] = proximity_zone(args)
            with _listening(LiveView(session.server, **options), args) as view:
                quiet_collector()
                _announce(view, stream, ready)
                if sweep:
                    confirm_moves(session, args, _limits(args))
                notice = _serve(session.server, args, sweep, stop)
        return notice.exit_status()
    except KeyboardInterrupt:
        print(f"{prog_of(args)}: stopped", file=sys.stderr)
        return EXIT_INTERRUPTED


def _serve(
    server: Sensor, args: argparse.Namespace, sweep: bool, stop: threading.Event
) -> FaultNotice:
    """Keep the sensor going while the view serves, until ``--duration`` is over or ``stop``
    is set: sweep between ``--cw`` and ``--ccw`` if asked, and look at the status every
    :data:`POLL_S` meanwhile. A fault ends the sweep (abandoned: the fault has stopped the
    head) but not the view; once the server is idle after a reset, a new sweep begins.

    Returns the notice that followed the faults (its ``exit_status`` is the command's).
    """
    from biris_hw.io.sweeps import sweeping

    notice = FaultNotice(server, args, "the live view serves on and shows it on /diagnostics")
    end: float | None = None if args.duration is None else time.monotonic() + args.duration

    def pause() -> float:
        """Until the next look: POLL_S, or what is left of --duration."""
        if end is None:
            return POLL_S
        return max(0.0, min(POLL_S, end - time.monotonic()))

    def over() -> bool:
        return stop.is_set() or (end is not None and time.monotonic() >= end)

    sweeps_begun = 0
    status = server.status()
    notice.observe(status)
    while not over():
        if sweep and not notice.faulted and (sweeps_begun == 0 or status.state is ServerState.IDLE):
            if sweeps_begun:
                print(f"{prog_of(args)}: sweeping again", file=sys.stderr, flush=True)
            sweeps_begun += 1
            try:
                with sweeping(server, args.cw, args.ccw, timeout=args.timeout) as sweeps:
                    while not over():
                        sweeps.next(timeout=pause())  # returns at each sweep, or None
            except HardwareFault as exc:  # said first-hand, then the status says what is left
                notice.met(exc)
                status = server.status()
                if not notice.observe(status):  # reset meanwhile: the next sweep waits a turn
                    stop.wait(pause())
                continue
        else:
            stop.wait(pause())
        status = server.status()
        notice.observe(status)
    return notice


def _limits(args: argparse.Namespace) -> list[tuple[str, int]]:
    """The sweep's limits in counts, by flag (clamped to +-360 degrees, as the server does)."""
    from biris_hw.angles import destination_counts

    return [
        ("--cw", destination_counts(args.cw, "--cw")),
        ("--ccw", destination_counts(args.ccw, "--ccw")),
    ]


def _check_flags(args: argparse.Namespace, sweep: bool) -> None:
    """Every flag of the command, before anything starts: UsageError (exit 2) for the first
    that is wrong; a warning for a host beyond loopback."""
    from biris_hw.io.liveview import is_loopback

    if args.replay is not None:
        if sweep:
            raise UsageError("a replay cannot be commanded: --cw/--ccw go with a sensor")
        if not Path(args.replay).is_file():
            raise UsageError(f"--replay {args.replay}: no such file")
        check_moving_arguments(args, replay=True)
    else:
        check_target_arguments(args)
        check_moving_arguments(args)
        if sweep:
            _limits(args)
    if not is_loopback(args.host):
        print(
            f"{prog_of(args)}: warning: --host {args.host} listens beyond this machine: anyone "
            f"who reaches port {args.port} (a web page in a browser that does included) can "
            "watch the sensor; the live view has no authentication and checks no Origin",
            file=sys.stderr,
            flush=True,
        )
    check_listening(args.host, args.port)


def check_listening(host: str, port: int) -> None:
    """Whether a server can listen on ``host:port`` now (bound and released at once, as the
    WebSocket server will bind it, address reuse on): UsageError naming why not."""
    try:
        found = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        raise UsageError(f"--host {host}: not an address of this machine ({exc})") from None
    family, kind, proto, _name, address = found[0]
    try:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(address)
            probe.listen()
    except OSError as exc:
        if exc.errno == errno.EADDRINUSE:
            raise UsageError(
                f"--port {port}: another program listens on {host}:{port} already "
                "(another biris view?): choose another --port, or --port 0 for any free one"
            ) from None
        raise UsageError(
            f"--host {host} --port {port}: cannot listen there ({exc.strerror})"
        ) from None


STAMPS = options.STAMPS
"""``--stamp``'s choices (:data:`biris_hw.commands.options.STAMPS`, where the flag is defined)."""

_stamp = stamp_of
"""``--stamp`` or its default (:func:`biris_hw.commands.options.stamp_of`; the old name)."""


def _recorded_poses(args: argparse.Namespace) -> PoseFeed | None:
    """The vehicle's poses a recording holds (``odom -> vehicle`` on ``/tf``, else ``/odom``),
    to show it in ``odom``; None for a recording without any. ``--grid`` or ``--proximity``
    without them is a UsageError; a file whose poses cannot be read is said on stderr and
    shown without."""
    from biris_hw.io.moving_sink import RecordedPoses
    from biris_hw.io.pose import PoseFileError, read_poses

    for topic in ("/tf", "/odom"):
        try:
            samples = read_poses(args.replay, topic)
        except PoseFileError as exc:
            if "has no channel" not in str(exc):
                print(f"{prog_of(args)}: warning: {exc}", file=sys.stderr, flush=True)
            continue
        if samples:
            return RecordedPoses(samples)
    for flag, wanted in (("--grid", args.grid), ("--proximity", proximity_zone(args))):
        if wanted:
            raise UsageError(
                f"{flag}: {args.replay} holds no vehicle poses (odom -> vehicle on /tf, or /odom)"
            )
    return None


@contextlib.contextmanager
def _listening(view: LiveView, args: argparse.Namespace) -> Iterator[LiveView]:
    """``view`` started; a port taken between the check and now is a UsageError too."""
    try:
        view.start()
    except RuntimeError as exc:
        raise UsageError(
            f"--host {args.host} --port {args.port}: cannot listen there ({exc})"
        ) from None
    try:
        yield view
    finally:
        view.close()


def _announce(view: LiveView, stream: TextIO, ready: Any) -> None:
    urls = view.urls
    print(
        f"live view on {urls['websocket']} (Lichtblick 1.22.1 or later, or Foxglove)\n"
        f"  open in Lichtblick, with the layout: {urls['open']}\n"
        f"  or in Foxglove: {urls['foxglove']} (then Import layout: {urls['layout']})",
        file=stream,
        flush=True,
    )
    if ready is not None:
        ready(view)
