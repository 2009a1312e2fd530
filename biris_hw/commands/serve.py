"""``biris serve``: run the sensor as a long-running service on Zenoh (:mod:`biris_hw.io.net`).

Every other command starts a server of its own, and so homes the head each time (some 12 s of
hardware time); on a robot the sensor runs once, as a service, several programs read it and one
commands it. This command starts the server on ``--sim``/``--target``/``--attach`` as the others
do, serves it as ``--name`` on the ``--listen`` endpoints until Ctrl-C or SIGTERM (or
``--duration``), and takes everything down in order.

Credentials never go on the command line (``ps`` shows it to every user): ``--credentials FILE``
is TOML with a ``[controllers]`` table (user = "password": those who may move and configure) and
optionally ``[readers]`` (then reading needs credentials too). Without it the service is
read-only. A service with credentials does no multicast scouting unless ``--multicast`` asks
(clients give ``--endpoint``): it is not announced to whoever listens on the network. TLS:
``--listen tls/host:port --tls-cert FILE --tls-key FILE``; anything else Zenoh offers
(user/password on the link, access control) through ``--zenoh-option KEY=JSON``.
``--dead-man`` stops the head (stop_scan) when the last controller's client has gone, so that a
continuous scan nobody controls any more does not sweep for ever.

The service listens on loopback (:data:`~biris_hw.commands.serve_setup.DEFAULT_LISTEN`) unless
``--listen`` says otherwise, and every flag is checked before the sensor is touched
(:mod:`biris_hw.commands.serve_setup`: a name, an endpoint or a port in use, a TLS file, a
credentials file other users may read): a mistake costs no homing. What leaves it open -- an
endpoint beyond loopback in the clear or open to anyone, a certificate expired or about to, a
live view on the network -- is warned about in its log as it starts.

A fault of the sensor does not end the service: the server stays up in its fault, the service
goes on answering (the status says ``fault:<kind>``) and publishes the fault, and once the
sensor has been reset it publishes the sensor's data again (:class:`~biris_hw.io.net.Service`);
the ``--foxglove`` view shows the fault on ``/diagnostics``. A controller resets it over the
network (``biris reset --connect NAME``), or the service does, with ``--auto-reset N``
(:class:`~biris_hw.commands.reset.AutoReset`: at most N tries, the pause between them doubling
from ``--reset-delay``); a sensor still in a fault after the last try ends the service with
status 1, so that its supervisor starts a new one (a lost link may need a new process).

The service logs to stderr, from INFO up (``--debug``: DEBUG), one line per event, in the
journal's form under systemd (:class:`~biris_hw.commands.console.ServiceLines`): its start (name,
endpoints, sensor), clients connecting and leaving, access refused, faults with their kind,
resets and recoveries, what could not be published. SIGTERM ends it as Ctrl-C does (the
dispatcher, :mod:`biris_hw.cli`): clients' connections closed, the head stopped, ``stopping
NAME``; exit status 0 after ``--duration``, 1 when ``--auto-reset`` gave up, 2 for a usage or
set-up error, 130 after Ctrl-C, 143 after SIGTERM.

``--foxglove PORT`` also shows the served sensor live in Foxglove or Lichtblick
(:class:`~biris_hw.io.liveview.LiveView`) for as long as the service runs: one process, one server,
both views. ``--replay FILE`` serves a recording instead of a sensor
(:class:`~biris_hw.io.record.ReplayServer`), at the recorded pace times ``--speed``: clients
``--connect`` to it as to a live sensor, and get the recorded Scans, equal; motion and
configuration are refused with the replay's own error (a RequestError on the client). Playing
begins when the first client opens a DATA connection, so that it sees the recording from its
start (``--replay-now``: at once, as a live sensor would).

``--sim --drive`` sets the simulated vehicle on its default drive, ``--grid`` adds the
certainty grid and ``--proximity`` the proximity alarm (the flags and rules of ``biris
record``: :mod:`biris_hw.commands.record`): the service then also publishes the vehicle's
odometry, ``odom -> vehicle``, each scan deskewed, the grid and the alarm's answers on keys of
their own (``serve(..., poses=, grid=, proximity=)``, docs/wire-format.md), and ``--foxglove``
shows the same (``/odom``, ``/tf``, ``/biris/points`` in ``odom``, ``/biris/grid``,
``/biris/proximity``).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

from biris_hw.commands.argtypes import path, positive_float, seconds
from biris_hw.commands.failures import EXIT_INTERRUPTED, SetupError, UsageError
from biris_hw.commands.options import add_target_arguments
from biris_hw.commands.record import (
    add_moving_arguments,
    check_moving_arguments,
    grid_params,
    moving_session,
    proximity_zone,
)
from biris_hw.commands.reset import AutoReset, add_auto_reset_arguments, check_auto_reset
from biris_hw.commands.serve_setup import DEFAULT_LISTEN, check_service_flags, warn_about_exposure
from biris_hw.commands.session import open_session, quiet_collector
from biris_hw.errors import BirisError, HardwareFault

__all__ = ["add_arguments", "run"]

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    service = parser.add_argument_group("service")
    service.add_argument(
        "--name",
        default="biris0",
        help="the service's name, which clients give to --connect (default biris0)",
    )
    service.add_argument(
        "--listen",
        nargs="+",
        action="extend",
        metavar="ENDPOINT",
        help=f"Zenoh endpoints to listen on (default {DEFAULT_LISTEN}: this machine only; "
        "tcp/0.0.0.0:7447 for the network); tls/HOST:PORT with --tls-cert and --tls-key",
    )
    service.add_argument(
        "--credentials",
        type=path,
        metavar="FILE",
        help='TOML of mode 600: [controllers] user = "password" (may move and configure), '
        "optionally [readers] (then reading needs credentials too); default: read-only for "
        "everyone",
    )
    service.add_argument("--tls-cert", type=path, metavar="FILE", help="TLS certificate (PEM)")
    service.add_argument(
        "--tls-key", type=path, metavar="FILE", help="TLS private key (PEM, mode 600)"
    )
    service.add_argument(
        "--zenoh-option",
        action="append",
        default=[],
        metavar="KEY=JSON",
        help="any Zenoh setting, e.g. access_control/enabled=true (repeatable)",
    )
    scouting = service.add_mutually_exclusive_group()
    scouting.add_argument(
        "--no-multicast",
        action="store_true",
        help="no multicast scouting: clients must give --endpoint (the default with --credentials)",
    )
    scouting.add_argument(
        "--multicast",
        action="store_true",
        help="multicast scouting even with --credentials (the default without)",
    )
    service.add_argument(
        "--dead-man",
        action="store_true",
        help="when the last controller has gone (its client closed, crashed or lost the "
        "link), stop the scan rather than let the head sweep on",
    )
    service.add_argument(
        "--duration",
        type=seconds,
        metavar="S",
        help="stop after S real seconds (default: at Ctrl-C or SIGTERM)",
    )
    add_auto_reset_arguments(parser)
    view = parser.add_argument_group("live view")
    view.add_argument(
        "--foxglove",
        type=int,
        metavar="PORT",
        help="also serve a Foxglove WebSocket live view on PORT (8765 is Foxglove's usual; 0 "
        "picks a free one) for as long as the service runs",
    )
    view.add_argument(
        "--foxglove-host",
        default="127.0.0.1",
        metavar="HOST",
        help="where the live view listens (default 127.0.0.1: its protocol has no "
        "authentication, so reach it through an SSH tunnel rather than opening it)",
    )
    replay = parser.add_argument_group("replay (instead of --sim/--target/--attach)")
    replay.add_argument(
        "--replay",
        type=path,
        metavar="FILE",
        help="serve a recording (.mcap from biris record) as if it were the sensor",
    )
    replay.add_argument(
        "--speed",
        type=positive_float,
        default=1.0,
        metavar="X",
        help="with --replay: X times the recorded pace (default 1)",
    )
    replay.add_argument(
        "--replay-now",
        action="store_true",
        help="with --replay: play at once (default: when the first client opens a DATA "
        "connection, so that it sees the recording from its start)",
    )
    add_moving_arguments(parser)
    add_target_arguments(parser, remote=False)


_SENSOR_FLAGS = ("sim", "target", "attach", "init", "scene", "samples", "time_scale", "seed")


def _check_replay_arguments(args: argparse.Namespace) -> None:
    """--replay replaces the sensor: no sensor flags beside it; --speed goes with it."""
    if getattr(args, "replay", None) is None:
        if getattr(args, "replay_now", False) or getattr(args, "speed", 1.0) != 1.0:
            raise UsageError("--speed and --replay-now go with --replay FILE")
        return
    for key in _SENSOR_FLAGS:
        value = getattr(args, key, None)
        if value not in (None, False):
            raise UsageError(f"--{key.replace('_', '-')} does not go with --replay (a recording)")
    if not Path(args.replay).is_file():
        raise UsageError(f"--replay {args.replay}: no such file")


@contextlib.contextmanager
def _sensor(args: argparse.Namespace) -> Iterator[tuple[Any, Any]]:
    """The sensor to serve -- a server of our own on --sim/--target/--attach, or a replay --
    and the vehicle's poses with ``--drive``/``--grid``/``--proximity`` (the simulator's
    odometry; else None)."""
    if args.replay is None:
        with moving_session(args, open_session) as (session, poses):
            quiet_collector()
            yield session.server, poses
        return
    from biris_hw.opening import open_sensor

    # autostart off: the service's own feeds open DATA connections at once, and would start it
    # before any client is there; _start_playing decides when
    with open_sensor(replay=args.replay, speed=args.speed, autostart=False) as replay:
        yield replay, None


def _start_playing(replay: Any, service: Any, now: bool, stop: threading.Event) -> None:
    """Start the replay at once, or when a client first opens a DATA connection."""

    def wait_for_client() -> None:
        while not stop.is_set():
            if service.data_opened.wait(0.25):
                with contextlib.suppress(BirisError):  # closed meanwhile: nothing to play
                    replay.start()
                return

    if now:
        replay.start()
    else:
        threading.Thread(target=wait_for_client, name="biris-replay-start", daemon=True).start()


@contextlib.contextmanager
def _live_view(
    args: argparse.Namespace, sensor: Any, stream: TextIO, moving: dict[str, Any]
) -> Iterator[None]:
    """``--foxglove PORT``: the sensor shown live for as long as the block runs (with the
    vehicle's poses, the grid and the alarm as the service has them: ``moving``)."""
    if args.foxglove is None:
        yield
        return
    try:
        from biris_hw.io.liveview import LiveView
    except ImportError as exc:
        raise SetupError(
            f"--foxglove needs the record extra (pip install 'biris-hw[record]'): {exc}"
        ) from exc
    # log times on the host's wall clock for a real sensor (a timeline shows the date), on the
    # hardware clock for the simulator and a recording, as `biris view` does
    real = args.replay is None and not args.sim and getattr(args, "attach", None) is None
    view = LiveView(
        sensor,
        host=args.foxglove_host,
        port=args.foxglove,
        stamp="wall" if real else "hardware",
        **moving,
    )
    try:
        view.start()
    except RuntimeError as exc:  # the port is taken
        raise SetupError(f"--foxglove {args.foxglove}: {exc}") from exc
    try:
        print(f"live view: {view.urls['websocket']} (opens with its layout: {view.urls['open']})",
              file=stream)  # fmt: skip
        yield
    finally:
        view.close()


def _describe(args: argparse.Namespace) -> str:
    """What is served, for the log (the flags resolved by then: $BIRIS_TARGET, the
    simulator's defaults)."""
    if args.replay is not None:
        return f"the recording {args.replay} at x{args.speed:g}"
    if getattr(args, "attach", None) is not None:
        return f"the simulator process {args.attach!r}"
    if args.sim:
        return f"the simulator (scene {args.scene}, x{args.time_scale:g}, seed {args.seed})"
    return f"the target {args.target}"


def run(
    args: argparse.Namespace, out: TextIO | None = None, stop: threading.Event | None = None
) -> int:
    """Serve until ``--duration`` is over (0), Ctrl-C or SIGTERM (130: the dispatcher makes it
    143 for SIGTERM), or ``--auto-reset`` gives up (the fault is raised: status 1). ``stop``
    (tests, an embedding program), if given, ends the service when set, as the end of
    ``--duration`` would."""
    stream = out or sys.stdout
    try:
        from biris_hw.io.net import serve
    except ImportError as exc:
        raise SetupError(
            f"biris serve needs the net extra (pip install 'biris-hw[net]'): {exc}"
        ) from exc
    _check_replay_arguments(args)
    check_moving_arguments(args)
    check_auto_reset(args, playback=args.replay is not None)
    setup = check_service_flags(args)  # all of them, before the sensor is touched
    warn_about_exposure(setup, args)
    controllers, listen = setup.controllers, setup.listen
    stop = stop or threading.Event()
    gave_up: list[HardwareFault] = []
    interrupted = False

    def give_up(fault: HardwareFault) -> None:
        gave_up.append(fault)
        stop.set()

    try:
        with contextlib.ExitStack() as stack:
            watches: list[AutoReset] = []

            def join_watches() -> None:
                for each in watches:
                    each.join()

            # joined last, once the sensor is closed: a reset under way ends with it
            stack.callback(join_watches)
            sensor, poses = stack.enter_context(_sensor(args))
            moving: dict[str, Any] = {}
            if poses is not None:
                moving["poses"] = poses
                if getattr(args, "grid", False):
                    moving["grid"] = grid_params()
                zone = proximity_zone(args)
                if zone is not None:
                    moving["proximity"] = zone
            service = stack.enter_context(
                serve(
                    sensor,
                    name=args.name,
                    listen=listen,
                    controllers=controllers,
                    readers=setup.readers,
                    multicast=setup.multicast,
                    options=setup.options,
                    stop_when_controllers_leave=args.dead_man,
                    **moving,
                )
            )
            try:  # from here the service is up: Ctrl-C or SIGTERM closes it in order
                stack.enter_context(_live_view(args, sensor, stream, moving))
                if args.replay is not None:
                    who = f"replay of {args.replay} at x{args.speed:g}, read-only"
                    _start_playing(sensor, service, args.replay_now, stop)
                    log.info("serving %s", _describe(args))
                else:
                    who = f"{len(controllers)} controller(s)" if controllers else "read-only"
                    watch = AutoReset(
                        sensor, tries=args.auto_reset, delay_s=args.reset_delay, on_give_up=give_up
                    )
                    watches.append(watch.start())
                    stack.callback(watch.stop)
                    if args.auto_reset:
                        after = (
                            f"reset at most {args.auto_reset} time(s), {args.reset_delay:g} s "
                            "after it, then twice as long before each further try"
                        )
                    else:
                        after = "wait for a controller's reset"
                    log.info("serving %s; after a fault: %s", _describe(args), after)
                print(
                    f"serving {service.name} on {' '.join(listen)} ({who}); Ctrl-C to stop",
                    file=stream,
                    flush=True,
                )
                stop.wait(args.duration)
            except KeyboardInterrupt:  # Ctrl-C, or SIGTERM (the dispatcher's)
                interrupted = True
            print(f"stopping {service.name}", file=stream, flush=True)
            log.info("stopping %s", service.name)
    finally:
        stop.set()  # ends the thread waiting to start a replay, if any
    if gave_up:
        raise gave_up[0]
    return EXIT_INTERRUPTED if interrupted else 0
