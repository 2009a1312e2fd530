"""``biris record``: record a sensor to MCAP (ROS 2 message types) while it scans.

``biris record --sim --out run.mcap --duration 10 --cw -45 --ccw 45`` starts a server (or uses
the sensor named by the session flags), opens a :class:`~biris_hw.io.record.Recorder` on it, sweeps
between the limits (``--to DEG``: one scan; neither: nothing is commanded, whatever the sensor
does is recorded) and stops after ``--duration`` seconds or at Ctrl-C. The file is checked
before the sensor is touched, and an existing file is refused (exit 2, the file untouched)
unless ``--force`` is given. The file is closed with its summary however the run ends, within
:data:`~biris_hw.io.record.recorder.CLOSE_TIMEOUT_S` (what the recorder then had no time to write
is dropped and counted), and the command prints what it holds and what was dropped however the
run ends too: after Ctrl-C or SIGTERM (exit 130 or 143, the file complete: :mod:`biris_hw.cli`
turns SIGTERM into the same KeyboardInterrupt), and before the error's line when a
fault, a timeout, a full disk or a network to the service lost for longer than
:data:`~biris_hw.io.feed.LOST_LIMIT_S` stops the run (exit 1, or 2 for a full disk, with a
valid, shorter file). A shorter loss of the network is ridden out: the summary names the span.
On a terminal (and not with ``--quiet``) one line at the bottom says how the recording is doing
while it runs: seconds elapsed, scans recorded, megabytes written, items dropped.

On a moving robot (docs/moving.md): ``--drive`` (with ``--sim``) puts the simulated vehicle on
the simulator's default drive through its scene (:func:`sim.drives.default_drive`, setting off
at 8 s of hardware time), and the recording carries its odometry (``/odom``, ``odom ->
vehicle`` on ``/tf``) and ``/biris/points`` in ``odom``, each scan deskewed; ``--grid`` adds the
certainty grid on ``/biris/grid`` (a few Hz), built from every acquisition, and
``--proximity`` the proximity alarm's answers on ``/biris/proximity`` (five a second; the zone
:data:`~biris_hw.io.proximity.DEFAULT_ZONE`, or ``--proximity-zone FRONT,WIDTH,LENGTH`` in
metres). On ``--sim`` alone the vehicle stands at the origin, and its odometry is recorded the
same way. A real robot's poses come in through the API (``Recorder(poses=...)``,
docs/moving.md).

``--stamp wall|hardware`` is what the messages are logged at, as for ``biris view``: ``wall``
on a real sensor, ``hardware`` on the simulator (:func:`~biris_hw.commands.options.stamp_of`).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from biris_hw.commands.argtypes import degrees, path, positive_float
from biris_hw.commands.console import StatusLine, note_clamped, prog_of, wants_progress
from biris_hw.commands.failures import EXIT_INTERRUPTED, UsageError
from biris_hw.commands.options import (
    add_continuous_argument,
    add_stamp_argument,
    add_target_arguments,
    add_timeout_argument,
    add_yes_argument,
    check_output_file,
    stamp_of,
    sweep_chosen,
)
from biris_hw.commands.session import (
    Session,
    confirm_moves,
    open_session,
    quiet_collector,
)

if TYPE_CHECKING:
    from biris_hw.io.grid import GridParams
    from biris_hw.io.moving_sink import PoseFeed
    from biris_hw.io.proximity import ProximityZone
    from biris_hw.io.record import Recorder

__all__ = [
    "add_arguments",
    "add_moving_arguments",
    "check_moving_arguments",
    "grid_params",
    "moving_session",
    "progress_text",
    "proximity_zone",
    "recording_metadata",
    "run",
]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    out = parser.add_argument_group("recording")
    out.add_argument(
        "--out",
        type=path,
        required=True,
        metavar="FILE",
        help="the .mcap file (an existing one is refused without --force)",
    )
    out.add_argument(
        "--force", action="store_true", help="overwrite FILE if it exists (default: refuse)"
    )
    out.add_argument(
        "--duration",
        type=positive_float,
        default=None,
        metavar="S",
        help="stop after S real seconds (default: after --to's scan, else at Ctrl-C)",
    )
    out.add_argument(
        "--frame",
        choices=("vehicle", "sensor"),
        default="vehicle",
        help="frame of the scan clouds on /biris/points (default vehicle)",
    )
    out.add_argument(
        "--no-profiles",
        action="store_true",
        help="leave out the per-acquisition profile clouds (the lossless data stay)",
    )
    add_stamp_argument(out)
    add_moving_arguments(parser)
    how = parser.add_argument_group("what to scan meanwhile (optional)")
    how.add_argument("--to", type=degrees, metavar="DEG", help="one scan to DEG degrees")
    how.add_argument("--cw", type=degrees, metavar="DEG", help="sweep: clockwise limit")
    how.add_argument("--ccw", type=degrees, metavar="DEG", help="sweep: counter-clockwise limit")
    add_continuous_argument(parser)
    add_yes_argument(parser)
    add_timeout_argument(parser)
    add_target_arguments(parser)


def add_moving_arguments(parser: argparse.ArgumentParser) -> None:
    """``--drive``, ``--grid`` and ``--proximity``: the simulated vehicle on its default drive,
    the certainty grid, the proximity alarm (``biris record``, ``biris view``, ``biris
    serve``)."""
    moving = parser.add_argument_group("on a moving robot (docs/moving.md)")
    moving.add_argument(
        "--drive",
        action="store_true",
        help="with --sim: the vehicle follows the simulator's default drive through its scene "
        "(from 8 s of hardware time); its odometry goes on /odom and /tf, and /biris/points "
        "is in odom, each scan deskewed",
    )
    moving.add_argument(
        "--grid",
        action="store_true",
        help="the certainty grid on /biris/grid (nav_msgs/OccupancyGrid in odom, 5 cm cells "
        "over 20 m x 20 m, a few Hz), built from every acquisition placed with the vehicle's "
        "pose (on --sim; with --replay, a recording that holds poses)",
    )
    moving.add_argument(
        "--proximity",
        action="store_true",
        help="the proximity alarm on /biris/proximity (biris_msgs/Proximity, five a second): "
        "the nearest return in a zone ahead of the vehicle, with its age (needs the poses, "
        "as --grid)",
    )
    moving.add_argument(
        "--proximity-zone",
        type=_zone_size,
        metavar="FRONT,WIDTH,LENGTH",
        help="the alarm's zone in metres: where it starts ahead of the vehicle frame's origin, "
        "its width, its length standing still (default 0,0.6,0.5); implies --proximity",
    )


def _zone_size(text: str) -> tuple[float, float, float]:
    """``--proximity-zone``: three numbers in metres, the front finite, the width and the
    length positive."""
    words = text.split(",")
    try:
        values = [float(word) for word in words]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(
            f"not three numbers FRONT,WIDTH,LENGTH in metres: {text!r}"
        )
    front, width, length = values
    if width <= 0 or length <= 0:
        raise argparse.ArgumentTypeError(f"the width and the length must be positive: {text!r}")
    return front, width, length


def check_moving_arguments(args: argparse.Namespace, *, replay: bool = False) -> None:
    """``--drive``, ``--grid`` and ``--proximity`` where the command has the vehicle's poses:
    the simulator (``--sim``), or a replay (``replay``: its own poses, for ``--grid`` and
    ``--proximity``); UsageError else."""
    if getattr(args, "drive", False) and not args.sim:
        what = "a replay drives nothing" if replay else "a real vehicle drives itself"
        raise UsageError(f"--drive goes with --sim ({what})")
    for flag, wanted in (("--grid", getattr(args, "grid", False)), ("--proximity", _alarm(args))):
        if wanted and not (args.sim or replay):
            raise UsageError(
                f"{flag} needs the vehicle's poses, which this command has on the simulator "
                "(--sim, and --drive for a moving vehicle) or in a recording (biris view "
                "--replay); a real robot's poses come in through the API: Recorder(poses=...), "
                "LiveView(poses=...) (docs/moving.md)"
            )


def _alarm(args: argparse.Namespace) -> bool:
    """``--proximity`` or ``--proximity-zone`` was given."""
    return (
        bool(getattr(args, "proximity", False)) or getattr(args, "proximity_zone", None) is not None
    )


def proximity_zone(args: argparse.Namespace) -> ProximityZone | None:
    """The proximity alarm's zone ``--proximity`` or ``--proximity-zone`` asks for (the default
    zone, docs/moving.md, or the one given); None when neither is given."""
    if not _alarm(args):
        return None
    from biris_hw.io.proximity import DEFAULT_ZONE, ProximityZone

    size = getattr(args, "proximity_zone", None)
    if size is None:
        return DEFAULT_ZONE
    front, width, length = size
    return ProximityZone(front_m=front, width_m=width, length_m=length)


def grid_params() -> GridParams:
    """The certainty grid ``--grid`` builds: the defaults (5 cm cells over 20 m x 20 m round
    the odom origin, docs/moving.md)."""
    from biris_hw.io.grid import GridParams

    return GridParams()


@contextlib.contextmanager
def moving_session(
    args: argparse.Namespace,
    opener: Callable[[argparse.Namespace], AbstractContextManager[Session]] | None = None,
) -> Iterator[tuple[Session, PoseFeed | None]]:
    """:func:`~biris_hw.commands.session.open_session`, and the vehicle's poses when
    ``--drive``, ``--grid`` or ``--proximity`` asks for them (None otherwise): the simulated
    odometry, pumped into a :class:`~biris_hw.io.pose.PoseBuffer` on the rig's time base while
    the block runs. With ``--drive`` the simulator's vehicle follows
    :func:`sim.drives.default_drive` (the session's simulator is built so: a scene too tight
    for it is a UsageError, before anything starts). ``opener`` opens the session (the calling
    command's ``open_session``)."""
    from biris_hw.opening import open_poses

    drive = getattr(args, "drive", False)
    wants_poses = drive or getattr(args, "grid", False) or _alarm(args)
    with (opener or open_session)(args) as session:
        if not wants_poses:
            yield session, None
            return
        if session.rig is None:  # check_moving_arguments refuses this first
            raise UsageError("--drive, --grid and --proximity go with --sim")
        with open_poses(sim=session.rig) as poses:
            yield session, poses


def _check(args: argparse.Namespace) -> None:
    sweep_chosen(args)
    check_moving_arguments(args)
    if args.to is None and args.duration is None:
        raise UsageError("say how long to record: --duration S (or --to DEG for one scan)")
    out = check_output_file("--out", Path(args.out), suffixes={".mcap"})
    if (out.exists() or out.is_symlink()) and not getattr(args, "force", False):
        raise UsageError(
            f"--out {out}: the file exists; give another name, or --force to overwrite it"
        )


def recording_metadata(session: Session, args: argparse.Namespace) -> dict[str, object]:
    """What the file's ``biris`` metadata says about the sensor: the simulator's scene and
    settings, or the target description's text."""
    meta: dict[str, object] = {"command": " ".join(sys.argv[1:]) or "biris record"}
    if session.rig is not None:
        rig = session.rig
        meta["scene"] = repr(rig.scene)
        simulator: dict[str, object] = {
            "scene": getattr(args, "scene", None),
            "samples": rig.samples,
            "time_scale": rig.time_scale,
            "seed": rig.seed,
        }
        if getattr(args, "drive", False):
            simulator["drive"] = "sim.drives.default_drive"
        meta["simulator"] = simulator
    target = getattr(args, "target", None)
    if target is not None:
        try:
            meta["target_description"] = Path(target).read_text()
        except OSError as exc:
            meta["target_description"] = f"unreadable: {exc}"
    return meta


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Record; 0 when done, 130 after Ctrl-C (the file complete either way)."""
    from biris_hw.io.record import Recorder

    stream = out or sys.stdout
    _check(args)
    interrupted = False
    recorder: Recorder | None = None
    try:
        with moving_session(args) as (session, poses):
            quiet_collector()
            recorder = Recorder(
                session.server,
                args.out,
                frame=args.frame,
                profiles=not args.no_profiles,
                metadata=recording_metadata(session, args),
                overwrite=getattr(args, "force", False),
                stamp=stamp_of(args),
                poses=poses,
                grid=grid_params() if getattr(args, "grid", False) else None,
                proximity=proximity_zone(args),
            )
            try:
                with recorder, _progress(args, recorder):
                    _scan(session, args, recorder)
            except KeyboardInterrupt:  # Ctrl-C (or SIGTERM), even a second one during close
                interrupted = True
    finally:  # however the run ended (a fault, a full disk): what the file holds, then the error
        summary = None
        if recorder is not None:
            summary = recorder.summary
            if summary is None:  # close() was interrupted (a second Ctrl-C): once more
                summary = recorder.close()
        if summary is not None:
            print(f"recorded {summary}", file=stream, flush=True)
    if interrupted:
        print(f"{prog_of(args)}: interrupted: {args.out} is complete up to then", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


@contextlib.contextmanager
def _progress(args: argparse.Namespace, recorder: Recorder) -> Iterator[None]:
    """While the recording runs, on a terminal (not with --quiet): one line rewritten in place,
    ``biris record: 12 s, 37 scans, 1.2 MB, dropped 0``."""
    if not wants_progress(args):
        yield
        return
    started = time.monotonic()
    out = Path(args.out)

    def text() -> str:
        return progress_text(
            time.monotonic() - started,
            recorder.scans,
            _size(out),
            recorder.dropped_points + recorder.dropped_scans,
        )

    with StatusLine(prog_of(args), text):
        yield


def progress_text(elapsed_s: float, scans: int, size: int, dropped: int) -> str:
    """The recording's progress line: elapsed time, scans, megabytes written, items dropped."""
    return f"{elapsed_s:.0f} s, {scans} scans, {size / 1e6:.1f} MB, dropped {dropped}"


def _size(file: Path) -> int:
    try:
        return file.stat().st_size
    except OSError:
        return 0


def _scan(session: Session, args: argparse.Namespace, recorder: Recorder) -> None:
    """Command the head as asked while ``recorder`` runs, until the duration is over."""
    from biris_hw.angles import destination_counts
    from biris_hw.io.sweeps import sweeping

    end = None if args.duration is None else time.monotonic() + args.duration

    def left() -> float | None:
        return None if end is None else max(0.0, end - time.monotonic())

    if args.cw is not None:
        limits = [
            (f"--cw {args.cw:g}", destination_counts(args.cw, "--cw")),
            (f"--ccw {args.ccw:g}", destination_counts(args.ccw, "--ccw")),
        ]
        confirm_moves(session, args, limits)
        with sweeping(session.server, args.cw, args.ccw, timeout=args.timeout) as sweeps:
            note_clamped(session.prog, "--cw", args.cw, sweeps.limits[0])
            note_clamped(session.prog, "--ccw", args.ccw, sweeps.limits[1])
            while not recorder.failed.is_set() and (left() or 0.0) > 0.0:
                sweeps.next(timeout=min(left() or 0.0, args.timeout))
    elif args.to is not None:
        with session.server.open() as conn:
            confirm_moves(
                session, args, [(f"--to {args.to:g}", destination_counts(args.to, "--to"))]
            )
            dest = conn.single_scan(args.to)
            note_clamped(session.prog, "--to", args.to, dest)
            conn.wait_idle(timeout=args.timeout)
        if args.duration is not None:
            recorder.failed.wait(left())
    else:
        recorder.failed.wait(left())
