"""``biris demo``: the BIRIS server at work on a simulated robot, then pictures of what it saw.

What ``make demo`` runs. It starts the simulator (a furnished room by default) and the server on
it, sweeps the head continuously between two limits for a bounded time, and receives every
completed sweep on a DATA connection, the way a navigation client would. While it runs the
terminal shows progress live (with rich when a person is watching, plain lines otherwise). Then
it writes three pictures and the data behind them to ``--out``:

* ``demo-polar.png``: the latest CW and CCW sweeps as the report's 2-D data (closest range by
  azimuth, as x/y metres) over the scene's true walls: the check a person can make at a glance;
* ``demo-top.png`` and ``demo-3d.png``: every sample of those sweeps' full profiles, from above
  and in 3-D;
* ``latest-scans.npz`` / ``.csv``: those two sweeps (see ``biris scan --save``).

With ``--drive`` the vehicle drives the simulator's default path through the room
(:func:`sim.drives.default_drive`) while the head sweeps, and every sweep is placed in ``odom``
with the vehicle's pose at each acquisition's own time (:func:`biris_hw.io.deskew.deskewed`, the
poses from the simulated base's odometry) and fed to the certainty grid
(:class:`biris_hw.io.grid.CertaintyGrid`). The pictures are then ``demo-grid.png`` (the grid over
the true walls and the vehicle's path), and ``demo-top.png`` / ``demo-3d.png`` of every sweep's
deskewed profiles; the polar picture is left out, since the report's 2-D data are drawn from a
head standing at the origin.

The run ends with a summary line; the exit status is 1 if the server reported a hardware fault or
the simulator's audit caught the driver breaking a hardware rule, since a demo that shows either
has found a bug.

``--out`` is checked before the simulator starts. Ctrl-C ends the sweeping early but keeps what
was acquired: the pictures and data of the sweeps completed so far are written as at the end of
a full run, the command says so, and the exit status is 130.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from biris_hw.angles import counts_to_deg
from biris_hw.commands.argtypes import (
    DEFAULT_TIME_SCALE,
    add_simulator_arguments,
    degrees,
    path,
    seconds,
)
from biris_hw.commands.console import is_terminal
from biris_hw.commands.failures import EXIT_INTERRUPTED, SetupError
from biris_hw.commands.options import (
    add_continuous_argument,
    add_debug_argument,
    add_quiet_argument,
    check_output_folder,
)
from biris_hw.commands.session import LagWatch, make_scene, quiet_collector
from biris_hw.data import Direction, Scan

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from biris_hw.io.pose import PoseBuffer
    from biris_hw.sensor import Sensor
    from sim import SimulatedBiris

__all__ = ["DemoConfig", "DemoResult", "DemoStatus", "add_arguments", "run", "run_demo"]

DEFAULT_DURATION_S = 25.0
DEFAULT_OUT = "build/demo"
_POLL_S = 0.25
"""Longest the loop waits for a sweep before refreshing the display anyway."""
_PLAIN_EVERY_S = 2.5
"""Seconds between progress lines when nobody watches a live display."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--duration",
        type=seconds,
        default=DEFAULT_DURATION_S,
        metavar="S",
        help=f"real seconds of sweeping (default {DEFAULT_DURATION_S:g})",
    )
    parser.add_argument(
        "--cw", type=degrees, default=-90.0, metavar="DEG", help="clockwise limit (default -90)"
    )
    parser.add_argument(
        "--ccw", type=degrees, default=90.0, metavar="DEG", help="counter-clockwise limit (90)"
    )
    parser.add_argument(
        "--out",
        type=path,
        default=Path(DEFAULT_OUT),
        metavar="DIR",
        help=f"pictures go here ({DEFAULT_OUT})",
    )
    add_continuous_argument(parser)
    parser.add_argument(
        "--drive",
        action="store_true",
        help="the vehicle drives its default path through the room meanwhile: the sweeps are "
        "deskewed with its odometry and build the certainty grid (demo-grid.png)",
    )
    sim = parser.add_argument_group("simulator")
    add_simulator_arguments(sim, default_time_scale=DEFAULT_TIME_SCALE)
    add_quiet_argument(parser)
    add_debug_argument(parser)


@dataclass(frozen=True)
class DemoConfig:
    duration_s: float = DEFAULT_DURATION_S
    cw_deg: float = -90.0
    ccw_deg: float = 90.0
    out: Path = Path(DEFAULT_OUT)
    scene: str = "room"
    samples: int = 64
    time_scale: float = DEFAULT_TIME_SCALE
    seed: int = 0
    continuous: bool = False
    drive: bool = False


@dataclass
class DemoStatus:
    """What the display shows; updated by the loop, read by the views."""

    config: DemoConfig
    elapsed_s: float = 0.0
    hardware_s: float = 0.0
    state: str = "initialising"
    azimuth_deg: float = 0.0
    """The server's destination for the pan."""
    encoder_azimuth_deg: float | None = None
    """The pan encoder as the server reads it now (None until homed)."""
    true_azimuth_deg: float = 0.0
    sweeps: dict[Direction, int] = field(default_factory=lambda: dict.fromkeys(Direction, 0))
    acquisitions: int = 0
    dropped_acquisitions: int = 0
    dropped_buffers: int = 0
    faults: int = 0
    violations: int = 0
    interrupts: dict[str, int] = field(default_factory=dict)
    latest: Scan | None = None
    partial: list[str] = field(default_factory=list)
    """Each partial sweep received, named with its reason (the first sweep, from where the head
    stood, always is one): listed after the summary so that a short sweep is never silent."""
    data_age_s: float | None = None
    """Hardware seconds since the newest delivered sweep's last acquisition."""
    interrupted: bool = False
    """Ctrl-C ended the sweeping before ``duration_s``."""

    @property
    def total_sweeps(self) -> int:
        return sum(self.sweeps.values())


@dataclass
class DemoResult:
    status: DemoStatus
    latest: dict[Direction, Scan]
    pictures: list[Path]
    data_files: tuple[Path, Path] | None
    drive: _Drive | None = None

    @property
    def ok(self) -> bool:
        return self.status.faults == 0 and self.status.violations == 0


# -- the run -------------------------------------------------------------------------------------


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    config = DemoConfig(
        duration_s=args.duration,
        cw_deg=args.cw,
        ccw_deg=args.ccw,
        out=Path(args.out),
        scene=args.scene,
        samples=args.samples,
        time_scale=args.time_scale,
        seed=args.seed,
        continuous=args.continuous,
        drive=args.drive,
    )
    stream = out or sys.stdout
    result = run_demo(config, stream)
    _print_summary(result, stream)
    if result.status.interrupted:
        print(f"biris demo: {_interrupted(result, config)}", file=sys.stderr, flush=True)
        return EXIT_INTERRUPTED
    return 0 if result.ok else 1


def _interrupted(result: DemoResult, config: DemoConfig) -> str:
    """What Ctrl-C left: which sweeps the files hold, of how many completed, and where."""
    made = result.status.total_sweeps
    if not result.latest:
        return "interrupted before the first sweep completed: nothing written"
    kept = len(result.latest)
    return f"interrupted: wrote the latest {kept} of {made} sweeps to {config.out}"


def run_demo(config: DemoConfig, out: TextIO) -> DemoResult:
    """Sweep, show, draw. Raises what the hardware raises; pictures are written only at the end."""
    if config.cw_deg >= config.ccw_deg:
        raise SetupError(f"--cw ({config.cw_deg:g}) must lie below --ccw ({config.ccw_deg:g})")
    import matplotlib  # noqa: F401  (fail before a minute of sweeping, not after)

    check_output_folder("--out", config.out)
    _make_folder(config.out)
    from biris_hw.io import scanfile
    from biris_hw.opening import open_sensor
    from sim import SimulatedBiris

    scene = make_scene(config.scene)
    trajectory = _trajectory(scene) if config.drive else None
    status = DemoStatus(config)
    latest: dict[Direction, Scan] = {}
    view = _make_view(out, status)
    drive: _Drive | None = None
    with (
        view,
        SimulatedBiris(
            scene=scene,
            samples=config.samples,
            time_scale=config.time_scale,
            seed=config.seed,
            trajectory=trajectory,
        ) as rig,
    ):
        watch = LagWatch(rig, "biris demo").start()
        try:
            # homes and boots first
            with (
                open_sensor(sim=rig, continuous=config.continuous) as server,
                _poses(rig, config.drive) as poses,
            ):
                quiet_collector()
                drive = None if poses is None else _Drive(poses)
                started = time.monotonic()
                _sweep(server, rig, status, latest, view, started, drive)
        finally:
            watch.stop()
        _refresh(status, None, rig, started)
        view.update(final=True)
    pictures: list[Path] = []
    data_files = None
    if drive is not None and trajectory is not None:
        pictures = drive.draw(config, scene.outline_2d(), trajectory)
    elif latest:
        pictures = _draw(config, latest, scene.outline_2d())
    if latest:
        ordered = [latest[d] for d in Direction if d in latest]
        data_files = (
            scanfile.save_scans(config.out / "latest-scans.npz", ordered),
            scanfile.export_csv(config.out / "latest-scans.csv", ordered),
        )
    return DemoResult(status, latest, pictures, data_files, drive)


def _trajectory(scene: Any) -> Any:
    """The simulator's default drive through ``scene``, or a SetupError saying why not."""
    from sim.drives import default_drive

    try:
        return default_drive(scene)
    except ValueError as exc:
        raise SetupError(f"--drive: {exc}") from exc


@contextlib.contextmanager
def _poses(rig: SimulatedBiris, drive: bool) -> Iterator[PoseBuffer | None]:
    """The simulated base's odometry in a pose buffer while the block runs (``--drive``)."""
    if not drive:
        yield None
        return
    from biris_hw.opening import open_poses

    with open_poses(sim=rig) as poses:
        yield poses


class _Drive:
    """``--drive``: each completed sweep deskewed with the vehicle's poses and fed to the grid."""

    POSE_WAIT_HW_S = 1.0
    """Longest wait (hardware seconds) for the odometry to reach a sweep's last acquisition."""

    def __init__(self, poses: PoseBuffer) -> None:
        from biris_hw.io.grid import CertaintyGrid

        self.poses = poses
        self.grid = CertaintyGrid()
        self.points: list[NDArray[np.float64]] = []
        self.sweeps = 0
        self.unplaced = 0
        """Acquisitions left out for want of a pose (said in the summary, never placed)."""

    def take(self, scan: Scan) -> None:
        from biris_hw.io.deskew import deskewed

        if scan.n_acq == 0:
            return
        self.poses.wait_for(float(scan.t[-1]), timeout_hw=self.POSE_WAIT_HW_S)
        placed = deskewed(scan, self.poses)
        self.points.append(placed.points())
        self.unplaced += len(placed.unplaced)
        self.grid.add_scan(scan, self.poses)
        self.sweeps += 1

    def draw(self, config: DemoConfig, outline: list[Any], trajectory: Any) -> list[Path]:
        import numpy as np

        from biris_hw.io.grid import save_grid
        from biris_hw.io.plots import save_3d_view, save_top_view

        t = np.linspace(0.0, trajectory.end_s, 2000)
        x, y, _ = trajectory.poses(t)
        pictures = [
            save_grid(
                config.out / "demo-grid.png",
                self.grid,
                outline,
                path_xy=np.column_stack((x, y)),
                title=f"Certainty grid after {self.sweeps} sweeps on the drive ({config.scene})",
            )
        ]
        if self.points:
            points = np.vstack(self.points)
            pictures += [
                save_top_view(
                    config.out / "demo-top.png",
                    points,
                    outline,
                    title=f"Every sweep deskewed into odom: {points.shape[0]} points",
                ),
                save_3d_view(
                    config.out / "demo-3d.png",
                    points,
                    title=f"Every sweep deskewed into odom, in 3-D: {points.shape[0]} points",
                ),
            ]
        return pictures


def _make_folder(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SetupError(f"cannot create {folder}: {exc.strerror or exc}") from exc


def _sweep(
    server: Sensor,
    rig: SimulatedBiris,
    status: DemoStatus,
    latest: dict[Direction, Scan],
    view: _View,
    started: float,
    drive: _Drive | None = None,
) -> None:
    """Sweep until the deadline, or until Ctrl-C (``status.interrupted``): caught outside
    :func:`sweeping`, so the sweep under way is abandoned, not waited for, and what completed
    stays in ``latest`` for the pictures."""
    from biris_hw.io.sweeps import sweeping

    config = status.config
    deadline = started + config.duration_s
    wait_s = max(30.0, 60.0 / config.time_scale)

    try:
        with sweeping(server, config.cw_deg, config.ccw_deg, timeout=wait_s) as sweeps:

            def take(scan: Scan) -> None:
                latest[scan.direction] = scan
                status.latest = scan
                status.sweeps[scan.direction] += 1
                status.dropped_buffers = sweeps.dropped
                if drive is not None:
                    drive.take(scan)
                if scan.partial:
                    why = f": {scan.partial_reason}" if scan.partial_reason else ""
                    status.partial.append(f"{scan.direction.name} #{scan.seq}{why}")

            while (remaining := deadline - time.monotonic()) > 0:
                scan = sweeps.next(timeout=min(_POLL_S, remaining))
                if scan is not None:
                    take(scan)
                _refresh(status, server, rig, started)
                view.update()
            # STOP: the sweep under way completes; the head comes to rest. Keep the sweeps that
            # completed meanwhile, so the pictures show the newest data.
            for scan in sweeps.stop():
                take(scan)
    except KeyboardInterrupt:
        status.interrupted = True
    _refresh(status, server, rig, started)


def _refresh(
    status: DemoStatus, server: Sensor | None, rig: SimulatedBiris, started: float
) -> None:
    status.elapsed_s = time.monotonic() - started
    status.hardware_s = rig.clock.now()
    status.true_azimuth_deg = counts_to_deg(rig.azimuth_counts)
    status.violations = len(rig.audit.violations)
    if status.latest is not None and status.latest.n_acq:
        status.data_age_s = status.hardware_s - float(status.latest.t[-1])
    if server is None:  # closed: keep a fault in view, otherwise say it has stopped
        if not status.state.startswith("fault"):
            status.state = "stopped"
        return
    report: Mapping[str, Any] = server.status()
    counters = report["counters"]
    status.state = str(report["state"])
    status.azimuth_deg = counts_to_deg(float(report["azimuth"]))
    live = report.get("azimuth_live")
    status.encoder_azimuth_deg = None if live is None else counts_to_deg(float(live))
    status.acquisitions = int(counters["acquisitions"])
    status.dropped_acquisitions = int(counters["dropped_acquisitions"])
    status.faults = int(counters["faults"])
    status.interrupts = dict(report["interrupts"])


def _draw(
    config: DemoConfig,
    latest: dict[Direction, Scan],
    outline: list[Any],
) -> list[Path]:
    import numpy as np

    from biris_hw.io.plots import profile_points, save_3d_view, save_polar, save_top_view

    scans = [latest[d] for d in Direction if d in latest]
    sweeps = ", ".join(f"{s.direction.name} #{s.seq}" for s in scans)
    points = np.vstack([profile_points(s) for s in scans])
    where = f"{config.scene}, {config.samples} samples"
    return [
        save_polar(
            config.out / "demo-polar.png",
            scans,
            outline,
            title=f"BIRIS closest range over the true walls ({where}; {sweeps})",
        ),
        save_top_view(
            config.out / "demo-top.png",
            points,
            outline,
            title=f"Full profiles from above: {points.shape[0]} points ({sweeps})",
        ),
        save_3d_view(
            config.out / "demo-3d.png",
            points,
            title=f"Full profiles in 3-D: {points.shape[0]} points ({sweeps})",
        ),
    ]


def _print_summary(result: DemoResult, out: TextIO) -> None:
    s = result.status
    print(f"biris demo: {summary_line(s)}", file=out)
    for sweep in s.partial:
        print(f"  partial: {sweep}", file=out)
    if result.drive is not None:
        d = result.drive
        occupied = int(d.grid.occupied().sum())
        unplaced = f"; {d.unplaced} acquisitions left out without a pose" if d.unplaced else ""
        print(
            f"  drive:   {d.sweeps} sweeps deskewed into odom and in the grid"
            f" ({occupied} occupied cells of {d.grid.resolution_m * 100:g} cm){unplaced}",
            file=out,
        )
    for picture in result.pictures:
        print(f"  picture: {picture}", file=out)
    if result.data_files is not None:
        print(f"  data:    {result.data_files[0]} (and .csv)", file=out)
    if not result.latest:
        print("  no sweep completed: no pictures (try a longer --duration)", file=out)
    out.flush()


def summary_line(s: DemoStatus) -> str:
    """The run in one line: what a person (or a CI log) needs to know it worked."""
    cw, ccw = s.sweeps[Direction.CW], s.sweeps[Direction.CCW]
    return (
        f"{s.total_sweeps} sweeps (CW {cw}, CCW {ccw}), {s.acquisitions} acquisitions, "
        f"{s.dropped_acquisitions} dropped, {s.faults} faults, {s.violations} audit violations "
        f"in {s.elapsed_s:.1f} s of sweeping ({s.hardware_s:.1f} s of hardware time, "
        f"x{s.config.time_scale:g})"
    )


# -- views ---------------------------------------------------------------------------------------


class _View:
    """Shows a :class:`DemoStatus`; ``update(final=True)`` is the last call."""

    def __init__(self, out: TextIO, status: DemoStatus) -> None:
        self.out = out
        self.status = status

    def update(self, *, final: bool = False) -> None:
        raise NotImplementedError

    def __enter__(self) -> _View:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


class _PlainView(_View):
    """A line now and then: for logs, pipes and CI, where a redrawn screen would be noise."""

    def __init__(self, out: TextIO, status: DemoStatus) -> None:
        super().__init__(out, status)
        self._next = 0.0

    def __enter__(self) -> _View:
        c = self.status.config
        print(
            f"biris demo: simulated {c.scene}, {c.samples} samples, x{c.time_scale:g}, "
            f"sweeping {c.cw_deg:+g}..{c.ccw_deg:+g} deg for {c.duration_s:g} s"
            + (", continuous acquisition" if c.continuous else ""),
            file=self.out,
            flush=True,
        )
        return self

    def update(self, *, final: bool = False) -> None:
        s = self.status
        if not final and s.elapsed_s < self._next:
            return
        self._next = s.elapsed_s + _PLAIN_EVERY_S
        age = "-" if s.data_age_s is None else f"{s.data_age_s:.2f} s"
        print(
            f"  {s.elapsed_s:5.1f} s  {s.state:<12} head {s.true_azimuth_deg:+6.1f} deg  "
            f"sweeps {s.total_sweeps:3d}  acquisitions {s.acquisitions:5d}  "
            f"dropped {s.dropped_acquisitions}  data age {age}  faults {s.faults}  "
            f"audit {s.violations}",
            file=self.out,
            flush=True,
        )


class _RichView(_View):
    """A live panel redrawn in place, for a person at a terminal."""

    def __init__(self, out: TextIO, status: DemoStatus) -> None:
        super().__init__(out, status)
        from rich.console import Console
        from rich.live import Live

        self._console = Console(file=out)
        self._live = Live(
            self._render(), console=self._console, refresh_per_second=8, transient=False
        )

    def __enter__(self) -> _View:
        self._live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._live.__exit__(None, None, None)

    def update(self, *, final: bool = False) -> None:
        self._live.update(self._render(), refresh=final)

    def _render(self) -> Any:
        from rich.panel import Panel
        from rich.progress_bar import ProgressBar
        from rich.table import Table

        s, c = self.status, self.status.config
        grid = Table.grid(padding=(0, 2))
        grid.add_column(style="bold cyan", justify="right")
        grid.add_column()
        bar = ProgressBar(total=c.duration_s, completed=min(s.elapsed_s, c.duration_s), width=40)
        time_row = Table.grid(padding=(0, 1))
        time_row.add_row(
            bar, f"{s.elapsed_s:4.1f} / {c.duration_s:g} s   hardware {s.hardware_s:6.1f} s"
        )
        grid.add_row("time", time_row)
        state_style = "red" if s.state.startswith("fault") else "green"
        grid.add_row(
            "state", f"[{state_style}]{s.state}[/]   sweeping {c.cw_deg:+g}..{c.ccw_deg:+g} deg"
        )
        encoder = "-" if s.encoder_azimuth_deg is None else f"{s.encoder_azimuth_deg:+.1f} deg"
        grid.add_row(
            "azimuth",
            f"{s.true_azimuth_deg:+7.1f} deg   (the server's encoder reading: {encoder}, "
            f"destination: {s.azimuth_deg:+.1f} deg)",
        )
        grid.add_row(
            "sweeps",
            f"{s.total_sweeps}   (CW {s.sweeps[Direction.CW]}, CCW {s.sweeps[Direction.CCW]})",
        )
        grid.add_row("acquisitions", str(s.acquisitions))
        dropped_style = "red" if s.dropped_acquisitions or s.dropped_buffers else "green"
        grid.add_row(
            "dropped",
            f"[{dropped_style}]{s.dropped_acquisitions} acquisitions, "
            f"{s.dropped_buffers} sweeps[/]",
        )
        grid.add_row("data age", _age_text(s))
        grid.add_row("faults", f"[{'red' if s.faults else 'green'}]{s.faults}[/]")
        grid.add_row("audit", f"[{'red' if s.violations else 'green'}]{s.violations} violations[/]")
        irq = s.interrupts
        grid.add_row(
            "interrupts",
            f"data {irq.get('BIRIS_DATA_DEV', 0)}  cmd {irq.get('BIRIS_CMD', 0)}  "
            f"end of scan {irq.get('MOTOR_END_OF_SCAN', 0)}",
        )
        title = f"BIRIS demo: simulated {c.scene}, {c.samples} samples, x{c.time_scale:g}"
        return Panel(grid, title=title, expand=False)


def _age_text(s: DemoStatus) -> str:
    if s.data_age_s is None or s.latest is None:
        return "no sweep yet"
    scan = s.latest
    return (
        f"{s.data_age_s:5.2f} s since the last acquisition of "
        f"{scan.direction.name} #{scan.seq} ({scan.n_acq} acquisitions)"
    )


def _make_view(out: TextIO, status: DemoStatus) -> _View:
    if is_terminal(out):
        try:
            return _RichView(out, status)
        except ImportError:
            pass
    return _PlainView(out, status)
