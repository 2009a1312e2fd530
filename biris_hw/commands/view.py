"""``biris view``: the sensor live in Foxglove or Lichtblick (a Foxglove WebSocket server).

``biris view --sim --cw -45 --ccw 45`` starts a simulator and a server, sweeps between the
limits and serves the live view (:class:`~biris_hw.io.liveview.LiveView`) on ``--port`` (8765)
until ``--duration`` is over or Ctrl-C; without limits nothing is commanded and whatever the
sensor does is shown. ``biris view --replay run.mcap`` shows a recording instead (a file damaged
part way is shown up to the damage, then the command stops with a one-line error, exit status
1). The command prints the WebSocket URL to open in the viewer (README: "Live view").

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
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from biris_hw.commands.argtypes import degrees, path, positive_float
from biris_hw.commands.console import prog_of
from biris_hw.commands.failures import EXIT_FAULT, EXIT_INTERRUPTED, UsageError, report_error
from biris_hw.commands.faults import FaultNotice
from biris_hw.commands.options import (
    add_continuous_argument,
    add_target_arguments,
    add_timeout_argument,
    add_yes_argument,
    sweep_chosen,
)
from biris_hw.commands.session import confirm_moves, open_session, quiet_collector
from biris_hw.errors import HardwareFault
from biris_hw.status import ServerState

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    view = parser.add_argument_group("live view")
    view.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765)")
    view.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; the protocol has no authentication)",
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
    try:
        if args.replay is not None:
            from biris_hw.io.record.replay import ReplayError
            from biris_hw.opening import open_sensor

            if sweep:
                raise UsageError("a replay cannot be commanded: --cw/--ccw go with a sensor")
            if not Path(args.replay).is_file():
                raise UsageError(f"--replay {args.replay}: no such file")
            with (
                open_sensor(replay=args.replay, speed=args.speed, autostart=False) as replay,
                LiveView(replay, host=args.host, port=args.port, frame=args.frame) as view,
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
        with (
            open_session(args) as session,
            LiveView(session.server, host=args.host, port=args.port, frame=args.frame) as view,
        ):
            quiet_collector()
            _announce(view, stream, ready)
            if sweep:
                from biris_hw.angles import destination_counts

                confirm_moves(
                    session,
                    args,
                    [
                        ("--cw", destination_counts(args.cw, "--cw")),
                        ("--ccw", destination_counts(args.ccw, "--ccw")),
                    ],
                )
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


def _announce(view: Any, stream: TextIO, ready: Any) -> None:
    urls = view.urls
    print(
        f"live view on {urls['websocket']} (Foxglove: {urls['foxglove']})", file=stream, flush=True
    )
    if ready is not None:
        ready(view)
