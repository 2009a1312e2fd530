"""A scene seen from above: outlines for pictures, and distances for tests."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from sim.scene.geometry import Geometry
from sim.scene.shapes import Box, Cylinder, FloatArray, Shape, Wall

__all__ = ["distance_to_surface_2d", "outline_2d"]

_POLYGON_SIDES = 64
"""Sides of the polygon that stands for a cylinder in :meth:`Scene.outline_2d`."""

_JOIN_TOL = 1e-9
"""Walls whose end and next start are this close are drawn as one polyline."""


def _chain(walls: Sequence[Wall]) -> list[FloatArray]:
    """Walls in order, consecutive ones that meet joined into one polyline."""
    lines: list[list[tuple[float, float]]] = []
    for wall in walls:
        if lines and math.dist(lines[-1][-1], wall.start) <= _JOIN_TOL:
            lines[-1].append(wall.end)
        else:
            lines.append([wall.start, wall.end])
    return [np.asarray(line, dtype=np.float64) for line in lines]


def _circle_polygon(center: tuple[float, float], radius: float) -> FloatArray:
    a = np.linspace(0.0, 2.0 * math.pi, _POLYGON_SIDES + 1)
    poly = np.column_stack((center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)))
    poly[-1] = poly[0]
    return poly


def outline_2d(shapes: Sequence[Shape]) -> list[FloatArray]:
    """Polylines (k, 2) of everything that stands up (see :meth:`sim.scene.Scene.outline_2d`)."""
    lines = _chain([s for s in shapes if isinstance(s, Wall)])
    for shape in shapes:
        if isinstance(shape, Box):
            corners = shape.corners()
            lines.append(np.vstack((corners, corners[:1])))
        elif isinstance(shape, Cylinder):
            lines.append(_circle_polygon(shape.center, shape.radius))
    return lines


def distance_to_surface_2d(g: Geometry, points: NDArray[np.floating]) -> FloatArray:
    """Horizontal distance from each (x, y) point to the nearest standing surface (see
    :meth:`sim.scene.Scene.distance_to_surface_2d`)."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError("points must be (m, 2)")
    best = np.full(p.shape[0], np.inf)
    px, py = p[:, 0:1], p[:, 1:2]
    if g.faces is not None:
        f = g.faces
        s = ((px - f.px) * f.ex + (py - f.py) * f.ey) / (f.ex**2 + f.ey**2)
        s = np.clip(s, 0.0, 1.0)
        dist = np.hypot(px - (f.px + s * f.ex), py - (f.py + s * f.ey))
        best = np.minimum(best, dist.min(axis=1))
    if g.mantles is not None:
        m = g.mantles
        dist = np.abs(np.hypot(px - m.cx, py - m.cy) - np.sqrt(m.r2))
        best = np.minimum(best, dist.min(axis=1))
    return best
