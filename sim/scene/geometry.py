"""A scene's shapes flattened once, when it is made, into numpy tables for the ray caster.

Two flattenings of the same shapes. The general one (rays in any directions) lists every
vertical face (walls, box sides), cylinder mantle and horizontal cap (tops and bottoms, planes).
The fan one serves the common case in which all rays share one heading seen from above, as the
rays of a BIRIS profile do: footprints (a wall is a box of zero width) as pairs of slabs, the
solids' side heights, and the caps' heights; see :mod:`sim.scene.raycast` for how each is used.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from sim.scene.shapes import Box, Cylinder, FloatArray, Plane, Shape, Wall

__all__ = ["EPS", "Circles", "Faces", "Geometry", "Rects", "Slabs"]

EPS = 1e-9
"""Hits closer than this along a ray are ignored, so a ray never hits the surface it left."""

_FAR = 1e6
"""Stands for infinity (a plane's far end, metres) where the fan path divides by it."""


@dataclass(frozen=True)
class Faces:
    """Vertical rectangles: base point, edge vector, z range."""

    px: FloatArray
    py: FloatArray
    ex: FloatArray
    ey: FloatArray
    zlo: FloatArray
    zhi: FloatArray


@dataclass(frozen=True)
class Circles:
    """Cylinder mantles or discs: centre, squared radius, z range (a disc's zlo = zhi)."""

    cx: FloatArray
    cy: FloatArray
    r2: FloatArray
    zlo: FloatArray
    zhi: FloatArray


@dataclass(frozen=True)
class Rects:
    """Oriented rectangles seen from above: centre, unit axis u, half sizes along u and v, z range.

    Footprints of boxes and walls (zlo..zhi the solid's height) or horizontal caps (zlo = zhi;
    a plane is an infinite cap).
    """

    cx: FloatArray
    cy: FloatArray
    ux: FloatArray
    uy: FloatArray
    hu: FloatArray
    hv: FloatArray
    zlo: FloatArray
    zhi: FloatArray


@dataclass(frozen=True)
class Slabs:
    """Footprints as pairs of slabs for the fan path: unit normal n, offset c . n of the
    footprint's centre, half width; all first slabs, then all second slabs (u, then v)."""

    nx: FloatArray
    ny: FloatArray
    offset: FloatArray
    half: FloatArray

    @staticmethod
    def of(rects: Rects | None) -> Slabs | None:
        if (r := rects) is None:
            return None
        return Slabs(
            nx=np.concatenate((r.ux, -r.uy)),
            ny=np.concatenate((r.uy, r.ux)),
            offset=np.concatenate((r.cx * r.ux + r.cy * r.uy, r.cy * r.ux - r.cx * r.uy)),
            half=np.concatenate((r.hu, r.hv)),
        )


def _arr(values: Iterable[float]) -> FloatArray:
    return np.fromiter(values, dtype=np.float64)


_T = TypeVar("_T", Faces, Circles, Rects)


def _table(kind: type[_T], rows: Sequence[tuple[float, ...]]) -> _T | None:
    """Rows of per-primitive numbers as a table of columns, None when there are none."""
    return kind(*(_arr(c) for c in zip(*rows, strict=True))) if rows else None


def _face(p0: Sequence[float], p1: Sequence[float], z0: float, z1: float) -> tuple[float, ...]:
    return (float(p0[0]), float(p0[1]), p1[0] - p0[0], p1[1] - p0[1], z0, z1)


def _footprint(shape: Wall | Box) -> tuple[float, ...]:
    top = shape.base + shape.height
    if isinstance(shape, Box):
        c, s = math.cos(shape.yaw), math.sin(shape.yaw)
        return (*shape.center, c, s, shape.size[0] / 2, shape.size[1] / 2, shape.base, top)
    (x0, y0), (x1, y1) = shape.start, shape.end
    length = math.hypot(x1 - x0, y1 - y0)
    mid = ((x0 + x1) / 2, (y0 + y1) / 2)
    return (*mid, (x1 - x0) / length, (y1 - y0) / length, length / 2, 0.0, shape.base, top)


@dataclass(frozen=True)
class Geometry:
    # General path; albedo in the order faces, mantles, caps, discs.
    faces: Faces | None
    mantles: Circles | None
    caps: Rects | None
    discs: Circles | None
    albedo: FloatArray
    # Fan path: footprints of walls and boxes, then cylinders: the S "solids".
    footprints: Slabs | None
    circles: Circles | None
    side_zlo: FloatArray
    side_zhi: FloatArray
    cap_z: FloatArray
    """Heights of the caps: every solid's bottom, every solid's top, then the planes."""
    plane_near: FloatArray
    plane_far: FloatArray
    fan_albedo: FloatArray
    """Albedo of the solids' sides, bottoms, tops, then the planes."""

    @property
    def empty(self) -> bool:
        return self.albedo.size == 0

    @staticmethod
    def build(shapes: Sequence[Shape]) -> Geometry:
        walls = [s for s in shapes if isinstance(s, Wall)]
        boxes = [s for s in shapes if isinstance(s, Box)]
        cyls = [s for s in shapes if isinstance(s, Cylinder)]
        planes = [s for s in shapes if isinstance(s, Plane)]
        flat: list[Wall | Box] = [*walls, *boxes]
        solids: list[Wall | Box | Cylinder] = [*flat, *cyls]

        faces = [_face(w.start, w.end, w.base, w.base + w.height) for w in walls]
        for b in boxes:
            k = b.corners()
            faces += [_face(k[i], k[(i + 1) % 4], b.base, b.base + b.height) for i in range(4)]
        box_prints = [_footprint(b) for b in boxes]
        caps = [(*p[:6], z, z) for p in box_prints for z in p[6:]]
        caps += [(0.0, 0.0, 1.0, 0.0, math.inf, math.inf, p.z, p.z) for p in planes]
        mantles = [(*c.center, c.radius**2, c.base, c.base + c.height) for c in cyls]
        discs = [(*m[:3], z, z) for m in mantles for z in m[3:]]
        albedo = (
            [w.albedo for w in walls]
            + [b.albedo for b in boxes for _ in range(4)]
            + [c.albedo for c in cyls]
            + [b.albedo for b in boxes for _ in range(2)]
            + [p.albedo for p in planes]
            + [c.albedo for c in cyls for _ in range(2)]
        )
        bottoms = [s.base for s in solids]
        tops = [s.base + s.height for s in solids]
        return Geometry(
            faces=_table(Faces, faces),
            mantles=_table(Circles, mantles),
            caps=_table(Rects, caps),
            discs=_table(Circles, discs),
            albedo=_arr(albedo),
            footprints=Slabs.of(_table(Rects, [_footprint(s) for s in flat])),
            circles=_table(Circles, mantles),
            side_zlo=_arr(bottoms),
            side_zhi=_arr(tops),
            cap_z=_arr(bottoms + tops + [p.z for p in planes]),
            plane_near=np.full(len(planes), EPS),
            plane_far=np.full(len(planes), _FAR),
            fan_albedo=_arr([s.albedo for s in solids] * 3 + [p.albedo for p in planes]),
        )
