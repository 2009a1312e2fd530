"""Pictures of BIRIS scans: polar (closest range), top-down and 3-D point clouds.

Headless on purpose: figures are made with :class:`matplotlib.figure.Figure` and saved through
the Agg canvas, never pyplot, so no display, no global figure state and no backend to choose;
the same code runs over SSH on the robot and in CI. matplotlib is imported only here, and only
when a picture is drawn: the driver and the other commands never pay for it.

The points are separate functions from the drawing (:func:`closest_points_xy`,
:func:`profile_points`) so that a test can hold what a picture shows against the truth, and so
is the rule that decides where a line may be drawn (:func:`segments`): a picture must not join
two objects with a line that looks like a wall. Each ``save_*`` builds its figure with a
``*_figure`` function that returns it unsaved, so a test can read the axes, lines and colour
bars instead of pixels.

Every picture takes one :class:`Scan` or a sequence of them and draws every sweep it is given:
a command that made ten sweeps shows ten, not the last of each direction.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np
from numpy.typing import ArrayLike, NDArray

from biris_hw.data import Direction, Scan
from biris_hw.geometry import DEFAULT_MOUNT, Mount, scan_points
from regs.hctl1000 import COUNTS_PER_REV

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "GAP_RATIO",
    "MAX_RANGE_M",
    "closest_points_xy",
    "polar_figure",
    "profile_points",
    "save_3d_view",
    "save_polar",
    "save_top_view",
    "segments",
    "top_view_figure",
    "view_3d_figure",
]

FloatArray = NDArray[np.float64]
Outline = Sequence[NDArray[np.floating]]
Scans: TypeAlias = Scan | Sequence[Scan]
"""What a picture draws: one sweep or several, in the order they were taken."""

MAX_RANGE_M = 3.5
"""The sensor's range as configured on the robot (the report: limited to about 3.5 m)."""

GAP_RATIO = 0.2
"""Largest change in range between neighbouring acquisitions still drawn as one surface, as a
share of the nearer of the two ranges.

Along a flat wall seen at an angle theta from its normal, the range changes by about
r tan(theta) dtheta from one acquisition to the next: with a 90-degree sweep's 3.6 degrees
between acquisitions that stays under 20 % until theta passes 70 degrees, where the wall's
returns are sparse anyway; the closest sample's noise is a few per cent. A box in front of a
wall, a pillar, a doorway differ by far more, and those are the jumps a line must not bridge.
"""

_RAD_PER_COUNT = 2.0 * math.pi / COUNTS_PER_REV
_MARKERS = {Direction.CW: "o", Direction.CCW: "^"}
_LEGEND_SWEEPS = 10
"""Up to this many sweeps each gets a colour of its own and a legend entry; more would bury
the picture under the legend, so beyond it the colour follows the sweep's order on a bar."""
_DPI = 110


# -- points ----------------------------------------------------------------------------------------


def closest_points_xy(scan: Scan) -> FloatArray:
    """(m, 2) x, y in metres of each acquisition's closest sample: the report's 2-D data.

    BIRIS measures depth along its optical axis, which is level, so the closest sample's range is
    the horizontal distance at the acquisition's azimuth: x = r cos(az), y = r sin(az) (x
    forward, y left). Acquisitions with no return (0) are left out.
    """
    r = scan.closest_mm.astype(np.float64) / 1000.0
    az = scan.azimuth.astype(np.float64) * _RAD_PER_COUNT
    keep = r > 0
    return np.column_stack((r[keep] * np.cos(az[keep]), r[keep] * np.sin(az[keep])))


def profile_points(scan: Scan) -> FloatArray:
    """(m, 3) x, y, z in metres of every sample with a return, in the vehicle frame.

    The sensor's geometry (fan, head, mount) is :mod:`biris_hw.geometry`'s; a scan from the
    server carries its mount, a scan read back from a file gets the simulator's head.
    """
    return scan_points(scan, frame="vehicle")


def segments(range_values: ArrayLike, gap_ratio: float = GAP_RATIO) -> list[tuple[int, int]]:
    """The runs of neighbouring acquisitions that may be joined by a line, as ``(start, stop)``.

    ``range_values`` is one sweep's range per acquisition in the order taken (any unit: the rule
    is relative). Each run is half-open, ``range_values[start:stop]``, and holds returns only;
    a run ends where the next acquisition has no return (0, negative or not finite) or where
    the range jumps by more than ``gap_ratio`` times the nearer of the two ranges (see
    :data:`GAP_RATIO`). A line drawn through every point of the returned runs, and through
    nothing else, never crosses a hole in a wall nor joins an object to what stands behind it,
    which a line through all the returns did: it drew walls where there are none. A run of one
    is a return with no neighbour on its surface: a marker, no line.
    """
    if not (math.isfinite(gap_ratio) and gap_ratio > 0):
        raise ValueError(f"gap_ratio must be a positive number, not {gap_ratio!r}")
    r = np.asarray(range_values, dtype=np.float64)
    if r.ndim != 1:
        raise ValueError(f"range_values must be one range per acquisition, not shape {r.shape}")
    valid = np.isfinite(r) & (r > 0)
    clean = np.where(valid, r, 0.0)  # no inf or NaN arithmetic below
    nearer = np.minimum(clean[:-1], clean[1:])
    joined = valid[:-1] & valid[1:] & (np.abs(np.diff(clean)) <= gap_ratio * nearer)
    index = np.flatnonzero(valid)
    before = np.concatenate(([False], joined))  # joined to the previous acquisition
    after = np.concatenate((joined, [False]))  # joined to the next one
    starts = index[~before[index]]
    stops = index[~after[index]] + 1
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def _as_scans(scans: Scans) -> list[Scan]:
    """One scan or several as a list; TypeError for anything else, before anything is drawn."""
    if isinstance(scans, Scan):
        return [scans]
    if not isinstance(scans, Sequence):
        raise TypeError(f"expected a Scan or a sequence of Scans, not {type(scans).__name__}")
    listed = list(scans)
    for i, scan in enumerate(listed):
        if not isinstance(scan, Scan):
            raise TypeError(f"item {i} is a {type(scan).__name__}, not a Scan")
    return listed


def _cloud(data: FloatArray | Scans) -> tuple[FloatArray, list[Scan] | None]:
    """The (m, 3) points to draw, and the scans they came from when they came from scans.

    An array is taken as points already computed (what callers passed before pictures took
    scans); anything else must be scans, whose profiles are projected here.
    """
    if isinstance(data, np.ndarray):
        points = np.asarray(data, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must be an (m, 3) array, not shape {points.shape}")
        return points, None
    scans = _as_scans(data)
    chunks = [profile_points(s) for s in scans]
    return (np.vstack(chunks) if chunks else np.zeros((0, 3))), scans


def _sweep_names(scans: Sequence[Scan]) -> str:
    """``"3 sweeps: CW #1 .. CCW #2"`` for titles: which sweeps a picture holds, briefly."""
    if not scans:
        return "no sweeps"
    first, last = scans[0], scans[-1]
    if len(scans) == 1:
        return f"{first.direction.name} #{first.seq}"
    if len(scans) == 2:
        return f"{first.direction.name} #{first.seq}, {last.direction.name} #{last.seq}"
    return (
        f"{len(scans)} sweeps: {first.direction.name} #{first.seq}"
        f" .. {last.direction.name} #{last.seq}"
    )


# -- drawing ---------------------------------------------------------------------------------------


def _figure(size: tuple[float, float]) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=size, layout="constrained")


def _save(fig: Figure, path: str | PathLike[str]) -> Path:
    target = Path(path)
    fig.savefig(target, dpi=_DPI)
    return target


def _draw_outline(ax: Axes, outline: Outline | None) -> None:
    if not outline:
        return
    for i, line in enumerate(outline):
        xy = np.asarray(line, dtype=np.float64)
        ax.plot(xy[:, 0], xy[:, 1], color="0.2", lw=2.0, label="true walls" if i == 0 else None)


def _draw_sensor(ax: Axes) -> None:
    ring = np.linspace(0.0, 2.0 * math.pi, 181)
    ax.plot(
        MAX_RANGE_M * np.cos(ring),
        MAX_RANGE_M * np.sin(ring),
        color="0.75",
        lw=0.8,
        ls="--",
        label=f"{MAX_RANGE_M:g} m range",
    )
    ax.plot([0.0], [0.0], marker=">", color="crimson", ms=10, ls="none", label="sensor (x ahead)")


def _frame_axes(ax: Axes, outline: Outline | None, *points: FloatArray) -> None:
    """Equal scales, and limits that hold the walls, the points and the sensor they are seen
    from: a return means little without where it was seen from."""
    ax.set_aspect("equal")
    ax.set_xlabel("x, forward (m)")
    ax.set_ylabel("y, left (m)")
    ax.grid(True, color="0.9")
    chunks = [np.zeros((1, 2))]
    chunks += [np.asarray(o, dtype=np.float64)[:, :2] for o in (outline or [])]
    chunks += [p[:, :2] for p in points if p.size]
    every = np.vstack(chunks)
    lo, hi = every.min(axis=0) - 0.3, every.max(axis=0) + 0.3
    ax.set_xlim(float(lo[0]), float(hi[0]))
    ax.set_ylim(float(lo[1]), float(hi[1]))


def _legend(fig: Figure) -> None:
    """Below the axes, where it can never hide a wall or a return."""
    fig.legend(loc="outside lower center", ncols=3, fontsize="small", frameon=False)


def _joined(x: FloatArray, y: FloatArray, runs: Sequence[tuple[int, int]]) -> FloatArray:
    """(k, 2) vertices of one polyline through the runs of two or more, NaN between runs.

    One line per sweep rather than one per run: a sweep in a cluttered room has dozens of runs,
    and matplotlib breaks a line at NaN without drawing across it.
    """
    pieces: list[FloatArray] = []
    for start, stop in runs:
        if stop - start < 2:
            continue
        if pieces:
            pieces.append(np.full((1, 2), np.nan))
        pieces.append(np.column_stack((x[start:stop], y[start:stop])))
    return np.vstack(pieces) if pieces else np.zeros((0, 2))


def polar_figure(
    scans: Scans,
    outline: Outline | None = None,
    title: str | None = None,
    gap_ratio: float = GAP_RATIO,
) -> Figure:
    """The closest range against azimuth, drawn as x, y over the true walls when they are known.

    Every sweep is drawn: its returns as markers (circles CW, triangles CCW) in a colour of its
    own, and a thin line through its neighbouring returns only where :func:`segments` says they
    lie on one surface, so a gap between objects stays a gap. Each sweep's artists carry the
    gids ``"sweep <n> line"`` and ``"sweep <n> returns"`` (n from 1) for a test to find them.
    """
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    sweeps = _as_scans(scans)
    fig = _figure((7.0, 6.5))
    ax = fig.add_subplot()
    _draw_outline(ax, outline)
    _draw_sensor(ax)
    many = len(sweeps) > _LEGEND_SWEEPS
    order = Normalize(vmin=1, vmax=max(len(sweeps), 2))
    palette = colormaps["viridis" if many else "tab10"]
    drawn: list[FloatArray] = []
    for n, scan in enumerate(sweeps, start=1):
        colour = palette(order(n)) if many else palette(n - 1)
        r = scan.closest_mm.astype(np.float64) / 1000.0
        az = scan.azimuth.astype(np.float64) * _RAD_PER_COUNT
        x, y = r * np.cos(az), r * np.sin(az)
        line = _joined(x, y, segments(r, gap_ratio))
        if line.size:
            ax.plot(line[:, 0], line[:, 1], lw=0.7, color=colour, alpha=0.6, gid=f"sweep {n} line")
        keep = r > 0
        label = None if many else f"sweep {n} {scan.direction.name}: {int(keep.sum())} returns"
        ax.plot(
            x[keep],
            y[keep],
            ls="none",
            marker=_MARKERS[scan.direction],
            ms=3.5,
            color=colour,
            label=label,
            gid=f"sweep {n} returns",
        )
        drawn.append(np.column_stack((x[keep], y[keep])))
    if many:
        bar = ScalarMappable(norm=order, cmap=palette)
        fig.colorbar(bar, ax=ax, label="sweep, in the order taken", shrink=0.8)
    _frame_axes(ax, outline, *drawn)
    default = f"BIRIS closest range by azimuth ({_sweep_names(sweeps)})"
    fig.suptitle(title or default, fontsize="medium")  # centred on the figure: never cut
    _legend(fig)
    return fig


def save_polar(
    path: str | PathLike[str],
    scans: Scans,
    outline: Outline | None = None,
    title: str | None = None,
    gap_ratio: float = GAP_RATIO,
) -> Path:
    """Write :func:`polar_figure` as a PNG at ``path``; returns the path."""
    return _save(polar_figure(scans, outline, title, gap_ratio), path)


def top_view_figure(
    points: FloatArray | Scans,
    outline: Outline | None = None,
    title: str | None = None,
) -> Figure:
    """Every sample of the profiles seen from above, coloured by height, over the true walls.

    ``points`` is one scan or several (every sweep's profiles drawn together: the walls they
    share should coincide, and where they do not is worth seeing), or an ``(m, 3)`` array of
    vehicle-frame points already computed. Markers only, no lines: neighbouring samples of a
    profile are one above the other, and lines between them would say nothing.
    """
    cloud, sweeps = _cloud(points)
    fig = _figure((7.5, 6.5))
    ax = fig.add_subplot()
    _draw_outline(ax, outline)
    _draw_sensor(ax)
    if cloud.size:
        dots = ax.scatter(cloud[:, 0], cloud[:, 1], c=cloud[:, 2], s=2.0, cmap="viridis")
        fig.colorbar(dots, ax=ax, label="height, z (m)", shrink=0.8)
    _frame_axes(ax, outline, cloud)
    default = f"BIRIS profiles from above: {cloud.shape[0]} points"
    if sweeps is not None:
        default += f" ({_sweep_names(sweeps)})"
    fig.suptitle(title or default, fontsize="medium")  # centred on the figure: never cut
    _legend(fig)
    return fig


def save_top_view(
    path: str | PathLike[str],
    points: FloatArray | Scans,
    outline: Outline | None = None,
    title: str | None = None,
) -> Path:
    """Write :func:`top_view_figure` as a PNG at ``path``; returns the path."""
    return _save(top_view_figure(points, outline, title), path)


def _mount(sweeps: Sequence[Scan] | None) -> Mount:
    """The head the scans were taken with (the first that says), else the simulator's."""
    for scan in sweeps or ():
        if scan.mount is not None:
            return scan.mount
    return DEFAULT_MOUNT


_WIDTH_3D_IN = 8.5
"""The 3-D picture's width, narrower only for a cloud taller than it is wide."""
_HEIGHT_3D_IN = (4.0, 8.5)
"""Least and most height of the 3-D picture: a flat cloud (a room) makes a short picture
rather than a strip, a tall one (a pillar) a narrow one rather than a tower."""
_MARGIN_IN = 0.1
_TITLE_IN = 0.35
_COLOUR_BAR_IN = 1.1
"""Room on the right for the colour bar, its ticks and its label."""


def view_3d_figure(points: FloatArray | Scans, title: str | None = None) -> Figure:
    """The point cloud in 3-D from behind and above the sensor, coloured by height.

    ``points`` as for :func:`top_view_figure`; every sweep's points are drawn together. The
    colour bar says what the colours are: height, z in metres. The axes' limits are the
    points' (and the sensor's) extent with a thin margin and the box has the same proportions,
    so a metre is as long along every axis; and the figure is fitted to the box
    (:func:`_fit_3d`). matplotlib's own limits and layout gave a box whose proportions were not
    the data's, floating in a square of white a third of which was empty.
    """
    from matplotlib.figure import Figure

    cloud, sweeps = _cloud(points)
    centre = np.asarray(_mount(sweeps).optical_centre_m, dtype=np.float64)
    fig = Figure(figsize=(_WIDTH_3D_IN, _WIDTH_3D_IN))
    ax: Any = fig.add_axes((0.0, 0.0, 1.0, 1.0), projection="3d")
    dots = None
    if cloud.size:
        dots = ax.scatter(
            cloud[:, 0], cloud[:, 1], cloud[:, 2], c=cloud[:, 2], s=1.5, cmap="viridis"
        )
    ax.scatter([centre[0]], [centre[1]], [centre[2]], color="crimson", s=30, marker="^")
    every = np.vstack((cloud, centre[np.newaxis, :]))
    lo, hi = every.min(axis=0), every.max(axis=0)
    margin = max(0.03 * float(np.max(hi - lo)), 0.05)
    lo, hi = lo - margin, hi + margin
    ax.set_xlim(float(lo[0]), float(hi[0]))
    ax.set_ylim(float(lo[1]), float(hi[1]))
    ax.set_zlim(float(lo[2]), float(hi[2]))
    ax.set_box_aspect(tuple(float(s) for s in hi - lo))
    ax.set_xlabel("x, forward (m)")
    ax.set_ylabel("y, left (m)")
    ax.set_zlabel("z (m)")
    ax.view_init(elev=28.0, azim=-150.0)
    _fit_3d(fig, ax)
    width, height = (float(v) for v in fig.get_size_inches())
    default = f"BIRIS point cloud: {cloud.shape[0]} points"
    if sweeps is not None:
        default += f" ({_sweep_names(sweeps)})"
    fig.suptitle(title or default, fontsize="medium", y=1.0 - _MARGIN_IN / height)
    if dots is not None:
        bar_h = 0.8 * (height - _TITLE_IN - 2 * _MARGIN_IN)
        bar = fig.add_axes(
            (
                1.0 - (_COLOUR_BAR_IN - 0.2) / width,
                (_MARGIN_IN + bar_h / 8) / height,
                0.16 / width,
                bar_h / height,
            )
        )
        fig.colorbar(dots, cax=bar, label="height, z (m)")
    return fig


def _extent_3d(ax: Any) -> Any:
    """The box with its ticks and labels on the canvas (a ``Bbox`` in pixels), once drawn.

    The box's eight corners projected as matplotlib projects them, and the three axes' tick
    and axis labels: the ink of the picture, which a 3-D axes' square does not tell.
    """
    from itertools import product

    from matplotlib.transforms import Bbox

    limits = (ax.get_xlim(), ax.get_ylim(), ax.get_zlim())
    corners = np.array([(*c, 1.0) for c in product(*limits)], dtype=np.float64).T
    projected = np.asarray(ax.get_proj(), dtype=np.float64) @ corners  # homogeneous
    flat = (projected[:2] / projected[3]).T
    pixels = ax.transData.transform(flat)
    parts = [Bbox.from_extents(*pixels.min(axis=0), *pixels.max(axis=0))]
    parts += [axis.get_tightbbox() for axis in (ax.xaxis, ax.yaxis, ax.zaxis)]
    return Bbox.union([p for p in parts if p is not None])


def _fit_3d(fig: Figure, ax: Any) -> None:
    """Size the figure and place the axes so that the box fills the figure under the title.

    A 3-D axes is a square whatever its position, and a flat cloud (a room is wider than it is
    tall) projects to a wide box across its middle. So: draw, measure the box
    (:func:`_extent_3d`), give the figure the box's proportions (within :data:`_HEIGHT_3D_IN`)
    and grow the square until the box spans the room the margins, the title and the colour bar
    leave; the square's empty top and bottom fall outside the figure. Twice, because labels
    keep their size while the box grows.
    """
    least_h, most_h = (h - _TITLE_IN - 2 * _MARGIN_IN for h in _HEIGHT_3D_IN)
    most_w = _WIDTH_3D_IN - _COLOUR_BAR_IN - 2 * _MARGIN_IN
    for _ in range(2):
        fig.draw_without_rendering()
        dpi = fig.dpi
        ink = _extent_3d(ax)
        square = ax.get_position().transformed(fig.transFigure)
        ink_w, ink_h = ink.width / dpi, ink.height / dpi
        room_h = min(max(most_w * ink_h / ink_w, least_h), most_h)
        scale = min(most_w / ink_w, room_h / ink_h)
        room_w = max(scale * ink_w, least_h)
        width = room_w + _COLOUR_BAR_IN + 2 * _MARGIN_IN
        height = room_h + _TITLE_IN + 2 * _MARGIN_IN
        # the ink's place in the square grows with it; the ink is centred in its room
        left = _MARGIN_IN + (room_w - scale * ink_w) / 2 - scale * (ink.x0 - square.x0) / dpi
        bottom = _MARGIN_IN + (room_h - scale * ink_h) / 2 - scale * (ink.y0 - square.y0) / dpi
        side = scale * square.width / dpi
        fig.set_size_inches(width, height)
        ax.set_position((left / width, bottom / height, side / width, side / height))


def save_3d_view(
    path: str | PathLike[str],
    points: FloatArray | Scans,
    title: str | None = None,
) -> Path:
    """Write :func:`view_3d_figure` as a PNG at ``path``; returns the path."""
    return _save(view_3d_figure(points, title), path)
