"""``biris grid``: the certainty grid from a recording or a simulated drive; a summary, a picture.

``biris grid run.mcap --plot grid.png`` reads every scan of a recording (as ``biris replay``
does) and the vehicle's poses it holds (``odom -> vehicle`` on ``/tf``, else ``/odom``:
:func:`biris_hw.io.pose.read_poses`), places each acquisition with the pose at its own time and
builds a :class:`~biris_hw.io.grid.CertaintyGrid`. A recording without poses is refused unless
``--standing`` says the sensor stood still (every scan then at the ``odom`` origin).

``biris grid --sim --drive --plot grid.png`` runs the simulator (on virtual time unless
``--clock scaled`` says otherwise: a drive of most of a minute then takes seconds) with the
vehicle on the simulator's default drive (:func:`sim.drives.default_drive`), the head sweeping
between ``-SWEEP`` and ``+SWEEP`` degrees the whole way, each scan placed with the simulated
odometry's poses; it then holds the grid against the scene's truth (precision and recall of the
occupied cells, as the ``grid`` benchmark counts them) and draws it over the true walls. Without
``--drive`` the vehicle stands at the origin for ``--sweeps`` sweeps. The simulator's flags are
every command's (``--scene``, ``--samples``, ``--time-scale``, ``--seed``, ``--clock``).

Either way it prints what went in (scans, acquisitions placed and left without a pose) and what
came out (occupied, free and unknown cells), and ``--plot PATH`` draws the grid.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import numpy as np

from biris_hw.commands.argtypes import (
    DEFAULT_TIME_SCALE,
    SIM_DEFAULTS,
    add_simulator_arguments,
    path,
    positive_float,
    positive_int,
)
from biris_hw.commands.failures import AuditFailure, UsageError
from biris_hw.commands.options import add_debug_argument, check_output_file
from biris_hw.data import ConnectionKind, DeliveryPolicy, PoseLookup, Scan

if TYPE_CHECKING:
    from biris_hw.io.grid import CertaintyGrid, GridParams
    from biris_hw.sensor import Sensor
    from sim import Scene, Trajectory

__all__ = ["add_arguments", "run"]

DEFAULT_SWEEP_DEG = 90.0
"""``--sweep``'s default: the head sweeps from -90 to +90 degrees, ahead and to both sides."""

DEFAULT_SWEEPS = 4
"""``--sweeps``' default for a simulated vehicle standing still."""

_SIM_ONLY = ("drive", "sweeps", "scene", "samples", "time_scale", "seed", "clock")
"""The flags that go with --sim only."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file", type=path, nargs="?", metavar="FILE", help="a recording (.mcap); or --sim"
    )
    parser.add_argument(
        "--plot", type=path, metavar="PATH", help="draw the grid at PATH (.png, .svg, .pdf...)"
    )
    built = parser.add_argument_group("the grid")
    built.add_argument(
        "--source",
        choices=("profile", "closest"),
        default="profile",
        help="what each acquisition gives: its profile's returns within the height band "
        "(default) or the closest sample alone (the report's 2-D data)",
    )
    built.add_argument(
        "--resolution",
        type=positive_float,
        default=0.05,
        metavar="M",
        help="cell side in metres (default 0.05)",
    )
    built.add_argument(
        "--size",
        type=positive_float,
        default=20.0,
        metavar="M",
        help="the grid covers M x M metres centred on the odom origin (default 20)",
    )
    built.add_argument(
        "--band",
        type=float,
        nargs=2,
        default=(0.1, 2.0),
        metavar=("LOW", "HIGH"),
        help="heights (m, vehicle frame) of the returns that count (default 0.1 2.0)",
    )
    built.add_argument(
        "--half-life",
        type=positive_float,
        default=None,
        metavar="S",
        help="evidence halves every S hardware seconds without news (default: never)",
    )
    recorded = parser.add_argument_group("a recording")
    recorded.add_argument(
        "--standing",
        action="store_true",
        help="the sensor stood still: place every scan at the odom origin (a recording "
        "without poses)",
    )
    sim = parser.add_argument_group("the simulator")
    sim.add_argument("--sim", action="store_true", help="build the grid on the simulator")
    sim.add_argument(
        "--drive",
        action="store_true",
        help="the vehicle follows the simulator's default drive through its scene",
    )
    add_simulator_arguments(sim, default_time_scale=DEFAULT_TIME_SCALE, deferred=True, clocks=True)
    for action in sim._group_actions:  # this command's clock is virtual unless told otherwise
        if action.dest == "clock":
            action.help = (
                "the simulator's time: virtual (default: the drive runs as fast as it is "
                "computed, whatever the host's load) or scaled real time, --time-scale times "
                "faster"
            )
    sim.add_argument(
        "--sweep",
        type=positive_float,
        default=DEFAULT_SWEEP_DEG,
        metavar="DEG",
        help=f"the head sweeps from -DEG to +DEG (default {DEFAULT_SWEEP_DEG:g})",
    )
    sim.add_argument(
        "--sweeps",
        type=positive_int,
        default=None,
        metavar="N",
        help=f"sweeps to make (default: until the drive ends; standing, {DEFAULT_SWEEPS})",
    )
    add_debug_argument(parser)


def _params(args: argparse.Namespace) -> GridParams:
    from biris_hw.io.grid import GridParams

    low, high = (float(v) for v in args.band)
    half = float(args.size) / 2.0
    try:
        return GridParams(
            resolution_m=float(args.resolution),
            extent_m=(-half, -half, half, half),
            band_m=(low, high),
            half_life_s=args.half_life,
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from exc


def _check(args: argparse.Namespace) -> None:
    """Refuse contradictory flags before anything starts."""
    if args.sim == (args.file is not None):
        raise UsageError("give a recording FILE or --sim, one of the two")
    if not args.sim:
        for flag in _SIM_ONLY:
            if getattr(args, flag) not in (None, False):
                raise UsageError(f"--{flag.replace('_', '-')} goes with --sim")
    else:
        if args.standing:
            raise UsageError(
                "--standing is for a recording; a simulated vehicle stands unless --drive"
            )
        defaults = {**SIM_DEFAULTS, "clock": "virtual", "time_scale": DEFAULT_TIME_SCALE}
        for key, value in defaults.items():
            if getattr(args, key) is None:
                setattr(args, key, value)
    if args.sweep > 180.0:
        raise UsageError(f"--sweep {args.sweep:g}: at most 180 degrees either side")
    if args.plot is not None:
        from biris_hw.commands.scan import picture_suffixes

        check_output_file("--plot", args.plot, suffixes=picture_suffixes())


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Build the grid, print what went in and came out, draw it; 0 when done."""
    stream = out or sys.stdout
    _check(args)
    params = _params(args)
    if args.sim:
        return _simulated(args, params, stream)
    return _recorded(args, params, stream)


# -- from a recording ------------------------------------------------------------------------------


def _every_scan(sensor: Sensor) -> Iterator[Scan]:
    """Every scan of a replayed recording, in the order recorded (none dropped)."""
    from biris_hw.io.record.replay import EndOfRecording

    data = sensor.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=64)
    while True:
        try:
            yield data.ready_for_data(timeout=None)
        except EndOfRecording:
            return


def _recorded_poses(file: Path, standing: bool) -> tuple[PoseLookup, np.ndarray | None, str]:
    """The recording's poses as a lookup, their path (x, y) for the picture, and where they
    came from; UsageError when it holds none and ``--standing`` was not given."""
    from biris_hw.io.grid import StandingPoses
    from biris_hw.io.pose import PoseBuffer, PoseFileError, read_poses

    if standing:
        return StandingPoses(), None, "standing at the odom origin (--standing)"
    for topic in ("/tf", "/odom"):
        try:
            samples = read_poses(file, topic)
        except PoseFileError as exc:
            if "has no channel" in str(exc):
                continue
            raise UsageError(str(exc)) from exc
        if samples:
            buffer = PoseBuffer(capacity=max(2, len(samples)))
            buffer.extend(samples)
            path_xy = np.array([(s.x_m, s.y_m) for s in samples], dtype=np.float64)
            return buffer, path_xy, f"{len(samples)} poses from {topic}"
    raise UsageError(
        f"{file} holds no vehicle poses (odom -> vehicle on /tf, or /odom); if the sensor "
        "stood still, say --standing"
    )


def _recorded(args: argparse.Namespace, params: GridParams, stream: TextIO) -> int:
    from biris_hw.io.grid import CertaintyGrid
    from biris_hw.opening import open_sensor

    if not Path(args.file).is_file():
        raise UsageError(f"{args.file}: no such file")
    poses, path_xy, said = _recorded_poses(args.file, args.standing)
    grid = CertaintyGrid(params)
    scans = 0
    with open_sensor(replay=args.file, speed=None) as replay:  # as fast as it reads
        for scan in _every_scan(replay):
            grid.add_scan(scan, poses, source=args.source)
            scans += 1
    print(f"{args.file}: {scans} scans; vehicle {said}", file=stream)
    _summary(grid, stream)
    if args.plot is not None:
        from biris_hw.io.grid import save_grid

        args.plot.parent.mkdir(parents=True, exist_ok=True)
        title = f"certainty grid of {Path(args.file).name}, {100 * grid.resolution_m:g} cm cells"
        print(f"picture: {save_grid(args.plot, grid, path_xy=path_xy, title=title)}", file=stream)
    return 0


# -- from the simulator ----------------------------------------------------------------------------


def _simulated(args: argparse.Namespace, params: GridParams, stream: TextIO) -> int:
    from biris_hw.data import Direction
    from biris_hw.io.grid import CertaintyGrid
    from biris_hw.opening import open_poses, open_sensor
    from sim import Scene, SimulatedBiris
    from sim.drives import default_drive

    scene = Scene.from_spec(args.scene)
    try:
        trajectory = default_drive(scene) if args.drive else None
    except ValueError as exc:
        raise UsageError(f"--drive in --scene {args.scene}: {exc}") from exc
    sweeps = args.sweeps if args.sweeps is not None else None if args.drive else DEFAULT_SWEEPS
    end = trajectory.end_s if trajectory is not None else math.inf
    grid = CertaintyGrid(params)
    taken: list[Scan] = []
    rig = SimulatedBiris(
        scene=scene,
        samples=args.samples,
        seed=args.seed,
        clock=args.clock,
        time_scale=args.time_scale,
        trajectory=trajectory,
    )
    with rig, open_sensor(sim=rig) as server, open_poses(sim=rig) as poses:
        conn = server.open()
        conn.wait_idle()
        ends = (float(args.sweep), -float(args.sweep))
        conn.single_scan(ends[1])
        conn.wait_idle()
        while (sweeps is None and server.clock() < end) or (
            sweeps is not None and len(taken) < sweeps
        ):
            to = ends[len(taken) % 2]
            conn.single_scan(to)
            conn.wait_idle()
            scan = conn.request_scan_data(Direction.CCW if to > 0 else Direction.CW)
            if scan is None or scan.n_acq == 0:
                raise RuntimeError(f"the sweep to {to:g} deg delivered no scan")
            poses.wait_for(float(scan.t[-1]), timeout_hw=1.0)
            grid.add_scan(scan, poses, source=args.source)
            taken.append(scan)
    if rig.audit.violations:
        found = rig.audit.violations
        raise AuditFailure(
            f"the simulator's audit recorded {len(found)} driver rule violation(s); "
            f"first: {found[0]}"
        )
    moving = "on the default drive" if trajectory is not None else "standing at the origin"
    print(f"simulated {args.scene}, vehicle {moving}: {len(taken)} scans", file=stream)
    _summary(grid, stream)
    _score(scene, trajectory, taken, grid, stream)
    if args.plot is not None:
        from biris_hw.io.grid import save_grid

        path_xy = None
        if trajectory is not None:
            t = np.linspace(0.0, trajectory.end_s, 2000)
            x, y, _ = trajectory.poses(t)
            path_xy = np.column_stack((x, y))
        args.plot.parent.mkdir(parents=True, exist_ok=True)
        saved = save_grid(args.plot, grid, scene.outline_2d(), path_xy=path_xy)
        print(f"picture: {saved}", file=stream)
    return 0


def _score(
    scene: Scene,
    trajectory: Trajectory | None,
    scans: list[Scan],
    grid: CertaintyGrid,
    stream: TextIO,
) -> None:
    """Precision and recall of the occupied cells against the scene's truth (sim.drives)."""
    from sim import Trajectory
    from sim.drives import score_occupied, swept_surface

    path = trajectory if trajectory is not None else Trajectory.standing()
    per_count = 2.0 * math.pi / 4096.0
    sweeps = [(s.t, s.azimuth.astype(np.float64) * per_count) for s in scans]
    swept = swept_surface(scene, path, sweeps, band_m=grid.params.band_m)
    score = score_occupied(scene, grid.occupied_xy(), swept, grid.resolution_m)
    cm = 100.0 * grid.resolution_m
    print(
        f"against the scene's truth: precision {score.precision:.3f} ({score.correct} of "
        f"{score.occupied} occupied cells within {cm:g} cm of a true surface or on an "
        f"obstacle's ground), recall "
        f"{score.recall:.3f} ({score.found} of {score.swept} samples of the surfaces the head "
        f"swept with an occupied cell within {cm:g} cm)",
        file=stream,
    )


def _summary(grid: CertaintyGrid, stream: TextIO) -> None:
    known = grid.known()
    occupied = int(np.count_nonzero(grid.occupied()))
    free = int(np.count_nonzero(known & (grid.log_odds() < 0.0)))
    area = grid.resolution_m**2
    print(
        f"grid: {grid.acquisitions} acquisitions placed, {grid.unplaced} without a pose; "
        f"{grid.shape[1]} x {grid.shape[0]} cells of {100 * grid.resolution_m:g} cm: "
        f"{occupied} occupied, {free} free ({free * area:.1f} m2), "
        f"{known.size - int(np.count_nonzero(known))} unknown",
        file=stream,
    )
