"""Pictures of BIRIS scans: polar (closest range), top-down and 3-D point clouds.

Headless on purpose: figures are made with :class:`matplotlib.figure.Figure` and saved through
the Agg canvas, never pyplot, so no display, no global figure state and no backend to choose;
the same code runs over SSH on the robot and in CI. matplotlib is imported only here, and only
when a picture is drawn: the driver and the other commands never pay for it.

The points are separate functions from the drawing (:func:`closest_points_xy`,
:func:`profile_points`) so that a test can hold what a picture shows against the truth.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from biris_hw.data import Direction, Scan
from biris_hw.geometry import Mount, scan_points
from regs.hctl1000 import COUNTS_PER_REV

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "MAX_RANGE_M",
    "closest_points_xy",
    "profile_points",
    "save_3d_view",
    "save_polar",
    "save_top_view",
]

FloatArray = NDArray[np.float64]
Outline = Sequence[NDArray[np.floating]]

MAX_RANGE_M = 3.5
"""The sensor's range as configured on the robot (the report: limited to about 3.5 m)."""

_RAD_PER_COUNT = 2.0 * math.pi / COUNTS_PER_REV
_COLOURS = {Direction.CW: "#1f77b4", Direction.CCW: "#ff7f0e"}
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
    ax.set_aspect("equal")
    ax.set_xlabel("x, forward (m)")
    ax.set_ylabel("y, left (m)")
    ax.grid(True, color="0.9")
    chunks = [np.asarray(o, dtype=np.float64)[:, :2] for o in (outline or [])]
    chunks += [p[:, :2] for p in points if p.size]
    if chunks:
        every = np.vstack(chunks)
        lo, hi = every.min(axis=0) - 0.3, every.max(axis=0) + 0.3
        ax.set_xlim(float(lo[0]), float(hi[0]))
        ax.set_ylim(float(lo[1]), float(hi[1]))


def _legend(fig: Figure) -> None:
    """Below the axes, where it can never hide a wall or a return."""
    fig.legend(loc="outside lower center", ncols=3, fontsize="small", frameon=False)


def save_polar(
    path: str | PathLike[str],
    scans: Sequence[Scan],
    outline: Outline | None = None,
    title: str | None = None,
) -> Path:
    """Closest range against azimuth, drawn as x, y over the true walls when they are known."""
    fig = _figure((7.0, 6.5))
    ax = fig.add_subplot()
    _draw_outline(ax, outline)
    _draw_sensor(ax)
    drawn: list[FloatArray] = []
    for scan in scans:
        xy = closest_points_xy(scan)
        drawn.append(xy)
        colour = _COLOURS[scan.direction]
        ax.plot(xy[:, 0], xy[:, 1], lw=0.5, color=colour, alpha=0.5)
        ax.plot(
            xy[:, 0],
            xy[:, 1],
            ls="none",
            marker="o",
            ms=3.5,
            color=colour,
            label=f"{scan.direction.name} #{scan.seq}: {xy.shape[0]} returns",
        )
    _frame_axes(ax, outline, *drawn)
    ax.set_title(title or "BIRIS closest range by azimuth", fontsize="medium")
    _legend(fig)
    return _save(fig, path)


def save_top_view(
    path: str | PathLike[str],
    points: FloatArray,
    outline: Outline | None = None,
    title: str | None = None,
) -> Path:
    """Every sample of the profiles seen from above, coloured by height."""
    fig = _figure((7.5, 6.5))
    ax = fig.add_subplot()
    _draw_outline(ax, outline)
    _draw_sensor(ax)
    if points.size:
        dots = ax.scatter(points[:, 0], points[:, 1], c=points[:, 2], s=2.0, cmap="viridis")
        fig.colorbar(dots, ax=ax, label="height above the floor (m)", shrink=0.8)
    _frame_axes(ax, outline, points)
    ax.set_title(title or f"BIRIS profiles from above: {points.shape[0]} points", fontsize="medium")
    _legend(fig)
    return _save(fig, path)


def save_3d_view(
    path: str | PathLike[str],
    points: FloatArray,
    title: str | None = None,
) -> Path:
    """The point cloud in 3-D, coloured by height, from behind and above the sensor."""
    fig = _figure((8.0, 6.5))
    ax: Any = fig.add_subplot(projection="3d")
    if points.size:
        ax.scatter(points[:, 0], points[:, 1], points[:, 2], c=points[:, 2], s=1.5, cmap="viridis")
        span = np.ptp(points, axis=0)
        ax.set_box_aspect(tuple(float(max(s, 0.1)) for s in span))
    centre = Mount().optical_centre_m
    ax.scatter([centre[0]], [centre[1]], [centre[2]], color="crimson", s=30, marker="^")
    ax.set_xlabel("x, forward (m)")
    ax.set_ylabel("y, left (m)")
    ax.set_zlabel("z (m)")
    ax.view_init(elev=28.0, azim=-150.0)
    ax.set_title(title or f"BIRIS point cloud: {points.shape[0]} points", fontsize="medium")
    return _save(fig, path)
