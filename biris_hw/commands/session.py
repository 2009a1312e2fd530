"""The sensor a ``biris`` command works on: opened from its flags, and what comes with it.

:func:`open_session` is :func:`~biris_hw.opening.open_sensor` with what only a command does:
it resolves the flags (:func:`~biris_hw.commands.options.check_target_arguments`, including
``$BIRIS_TARGET``), starts the simulator for ``--sim`` itself (so that it can say when the host
cannot keep up with the time scale, :class:`LagWatch`), and reads the simulator's audit last: a
rule the driver broke fails the command (:class:`~biris_hw.commands.failures.AuditFailure`)
even if it got its data, because such a run would have misused real hardware.

A command respects the head it turns: it asks before turning a real one more than half a turn
(:func:`confirm_moves`). The long-running commands take what they have built out of the garbage
collector's reach once the sensor is open (:func:`quiet_collector`).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import sys
import threading
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, TextIO

from biris_hw.commands.argtypes import time_scale_warning
from biris_hw.commands.console import prog_of
from biris_hw.commands.failures import AuditFailure, SetupError, UsageError
from biris_hw.commands.options import check_target_arguments, connect_options, profile_hint
from biris_hw.errors import AccessDenied, ConnectionClosed
from biris_hw.opening import load_init_record, open_sensor
from regs.hctl1000 import COUNTS_PER_REV

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

    from biris_hw.hardware import BirisHardware
    from biris_hw.records import BirisInitRecord
    from biris_hw.sensor import Sensor
    from biris_hw.server import BirisServer
    from sim import Scene, SimulatedBiris

__all__ = [
    "HALF_TURN_COUNTS",
    "LAG_CHECK_S",
    "LagWatch",
    "Lagging",
    "Session",
    "check_reachable",
    "confirm_moves",
    "make_scene",
    "open_session",
    "quiet_collector",
]

HALF_TURN_COUNTS = COUNTS_PER_REV // 2
"""A move longer than this (180 degrees) on a real head asks for ``--yes``."""

LAG_CHECK_S = 0.25
"""Real seconds between two looks at whether the simulator keeps up (:class:`LagWatch`)."""


@dataclass
class Session:
    """A running server on a sensor, as a command sees it."""

    server: Sensor
    """The sensor: a server of this command's own, or a running service (--connect)."""
    hardware: BirisHardware | None
    """The hardware under a server of our own; None through a service."""
    record: BirisInitRecord
    rig: SimulatedBiris | None = None
    """The simulator, with --sim: its scene, true azimuth and audit."""
    simulated: bool = True
    """A simulator (--sim, or a ``biris sim`` process with --attach), not a real head: nothing
    breaks if it turns a long way, so it is never asked for --yes."""
    prog: str = "biris"
    """``biris <command>``: what the command's own lines on stderr start with."""
    remote: bool = False
    """Through a running service (--connect): the record is the default one, not the
    service's, and the server is not ours to home or stop."""


def make_scene(spec: str) -> Scene:
    """The simulator's scene for a ``--scene`` value (:meth:`sim.Scene.from_spec`)."""
    from sim import Scene

    return Scene.from_spec(spec)


def _start_rig(args: argparse.Namespace) -> SimulatedBiris:
    """The simulator ``--sim`` and its flags describe, started (tests wrap this to break it).
    With ``--drive`` its vehicle follows the scene's :func:`sim.drives.default_drive` (a scene
    too tight for it is a UsageError, before the simulator starts)."""
    from sim import SimulatedBiris

    scene = make_scene(args.scene)
    trajectory = None
    if getattr(args, "drive", False):
        from sim.drives import default_drive

        try:
            trajectory = default_drive(scene)
        except ValueError as exc:
            raise UsageError(f"--drive in --scene {args.scene}: {exc}") from exc
    return SimulatedBiris(
        scene=scene,
        samples=args.samples,
        time_scale=args.time_scale,
        seed=args.seed,
        clock=getattr(args, "clock", None) or "scaled",
        trajectory=trajectory,
    ).start()


@contextlib.contextmanager
def open_session(args: argparse.Namespace) -> Iterator[Session]:
    """Open the sensor the flags name; take it down on the way out, server first.

    ``--connect NAME`` (or the client's profile: ``$BIRIS_CONNECT``...) opens the service, its
    files checked and its endpoints probed first, so that a missing CA file or a refused
    connection is said at once (:mod:`biris_hw.io.net.probe`).

    ``--continuous`` builds the server with Appendix D's continuous acquisition
    (``BirisInitRecord.continuous_acquisition``) on top of whatever ``--init`` says, so it works
    the same on every sensor; the init record is read before anything starts. With --sim a
    :class:`LagWatch` says if the host cannot keep up with the time scale, and the audit is
    read after the simulator has stopped (:class:`AuditFailure`).
    """
    check_target_arguments(args)
    prog = prog_of(args)
    if getattr(args, "connect", None) is not None:
        options = connect_options(args)  # files named, credentials read: before any network
        check_reachable(args.connect, options)
        try:
            with open_sensor(connect=args.connect, **options) as remote:
                from biris_hw.records import BirisInitRecord

                yield Session(remote, None, BirisInitRecord(), None, False, prog, remote=True)
        except AccessDenied as exc:
            hint = profile_hint(args)  # the profile's user, but no $BIRIS_PASSWORD
            if not hint:
                raise
            raise AccessDenied(f"{exc}{hint}") from exc
        return
    continuous = True if getattr(args, "continuous", False) else None
    record = load_init_record(args.init, continuous=continuous)
    rig: SimulatedBiris | None = None
    with contextlib.ExitStack() as stack:
        opening: AbstractContextManager[BirisServer]
        if args.target is not None:
            opening = open_sensor(target=args.target, init=record)
        elif getattr(args, "attach", None) is not None:
            opening = open_sensor(attach=args.attach, init=record)
        else:
            rig = _start_rig(args)
            stack.callback(rig.close)
            stack.callback(LagWatch(rig, prog).start().stop)
            opening = open_sensor(sim=rig, init=record)
        server = stack.enter_context(opening)
        yield Session(server, server.hardware, server.record, rig, args.target is None, prog)
    if rig is not None and rig.audit.violations:
        found = rig.audit.violations
        raise AuditFailure(
            f"the simulator's audit recorded {len(found)} driver rule violation(s); "
            f"first: {found[0]}"
        )


def check_reachable(name: str, options: Mapping[str, Any]) -> None:
    """Probe the endpoints ``connect_options`` gave (:func:`~biris_hw.io.net.probe.reachable`)
    and raise, at once, why none can be used: a connection refused, a host that cannot be
    reached, a certificate refused, a ``tls/`` endpoint on a port without TLS. A command starts
    no service, so waiting for one to listen would only delay the answer. No endpoints
    (multicast scouting) and the ``net`` extra missing are left to opening the service.

    Raises:
        SetupError: no endpoint can be used (each one's reason said).
        RequestError: a malformed endpoint, TLS files that cannot be used.
    """
    endpoints = options.get("endpoints") or []
    if not endpoints:
        return
    try:
        from biris_hw.io.net.probe import reachable
        from biris_hw.io.net.zconfig import tls_options
    except ImportError:
        return
    zenoh = dict(options.get("zenoh_options") or {})
    if options.get("tls_ca") is not None:
        zenoh.update(tls_options(root_ca=options["tls_ca"]))
    try:
        reachable(endpoints, zenoh, f"no BIRIS service {name!r}")
    except ConnectionClosed as exc:
        raise SetupError(str(exc)) from exc


def quiet_collector() -> None:
    """Take what a command has built to run (modules, the server, a simulator's scene) out of
    the cyclic garbage collector's reach: a full collection over it stalled the data path for
    40-75 ms on a quiet machine and 100-180 ms on a busy one (``make bench``'s streaming p99),
    and after ``gc.freeze()`` it costs under a millisecond. Done by the long-running commands
    (serve, view, watch, record, demo) once their sensor is open: one process, one sensor; a
    one-shot command would pay the collection for nothing, and a library user decides this for
    their own program."""
    gc.collect()
    gc.freeze()


# -- what a person is told and asked -----------------------------------------------------------


class Lagging(Protocol):
    """What :class:`LagWatch` reads of a simulator (:class:`sim.SimulatedBiris` has it)."""

    @property
    def time_scale(self) -> float: ...

    @property
    def lag_bound_s(self) -> float: ...

    def lag_s(self) -> float: ...

    def behind(self) -> bool: ...


class LagWatch:
    """Says once, on stderr, that the simulator cannot keep up with its time scale.

    A time scale is a promise that a hardware second takes ``1/scale`` real seconds; past what
    the host can compute, the simulator runs late (:meth:`sim.SimulatedBiris.lag_s`) and the
    driver's hardware-time deadlines stop meaning what they mean on the robot. The run goes
    on (it may still be what the person wanted) but they are told, once. A thread of its own
    looks every :data:`LAG_CHECK_S` and needs two looks in a row beyond the bound, so that one
    stall of a busy host is not called falling behind.
    """

    def __init__(
        self,
        rig: Lagging,
        prog: str,
        *,
        every_s: float | None = None,
        err: TextIO | None = None,
    ) -> None:
        self._rig = rig
        self._prog = prog
        self._every = LAG_CHECK_S if every_s is None else every_s
        self._err = err
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.warned = False

    def start(self) -> LagWatch:
        self._thread = threading.Thread(target=self._run, name="biris-lag-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _run(self) -> None:
        behind_before = False
        while not self._stop.wait(self._every):
            behind = self._rig.behind()
            if behind and behind_before:
                self.warn()
                return
            behind_before = behind

    def warn(self) -> None:
        """Say it now (once)."""
        if self.warned:
            return
        self.warned = True
        stream = self._err or sys.stderr
        rig = self._rig
        text = time_scale_warning(rig.lag_s(), rig.lag_bound_s, rig.time_scale)
        print(f"{self._prog}: {text}", file=stream, flush=True)


def confirm_moves(
    session: Session, args: argparse.Namespace, moves: Sequence[tuple[str, int]]
) -> None:
    """Refuse (:class:`UsageError`, exit 2) a move of more than half a turn on a real head
    unless ``--yes`` was given.

    ``moves`` are (what the person asked, destination in counts after clamping); each is
    measured from where the head stands now (``status().azimuth``) and, in order, from the
    previous destination, so a sweep's limits count as the sweep they make. A real head carries
    a cable and turns among real things; a long turn nobody expected is worth one flag. The
    simulator never asks.
    """
    if session.simulated or getattr(args, "yes", False) or not moves:
        return
    from biris_hw.angles import counts_to_deg

    here = int(session.server.status()["azimuth"])
    start = here
    for what, dest in moves:
        for origin in dict.fromkeys((here, start)):
            if abs(dest - origin) > HALF_TURN_COUNTS:
                raise UsageError(
                    f"{what} turns the head {counts_to_deg(abs(dest - origin)):.0f}\N{DEGREE SIGN} "
                    f"(from {counts_to_deg(origin):+.1f}\N{DEGREE SIGN} to "
                    f"{counts_to_deg(dest):+.1f}\N{DEGREE SIGN}), more than half a turn: make "
                    f"sure the cable and the space around the head allow it, then add --yes"
                )
        start = dest
