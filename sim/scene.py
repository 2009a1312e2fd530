"""What the simulated BIRIS looks at: walls, boxes, cylinders and floors, and a ray caster.

Frame: x forward, y left, z up (REP 103); the pan axis is the z axis through the origin. Boxes
and cylinders are solids standing on their ``base`` (the floor, z = 0, by default); walls are
two-sided and thin; planes are unbounded. The optics cast one ray per range sample, once per
acquisition and at up to thousands of acquisitions a second in benchmarks, so a scene flattens its
shapes once, when it is made, into numpy tables, and :meth:`Scene.cast` intersects all rays with
all shapes in a fixed number of array operations, never a Python loop over rays or shapes. The
rays of one profile share a heading seen from above, which a second, shorter path exploits (see
the note at the fan path); the general path is kept for other rays and as the reference.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TypeAlias, TypeVar

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "DEFAULT_ROOM_ORIGIN",
    "Box",
    "Cylinder",
    "Plane",
    "Scene",
    "Shape",
    "Wall",
    "polygon_walls",
]

FloatArray: TypeAlias = NDArray[np.float64]

DEFAULT_ROOM_ORIGIN = (-2.1, -2.8)
"""World (x, y) of the default room's rear-right corner: the sensor sits 2.1 m from the back wall
and 2.8 m from the right one, so the front wall is 2.9 m away and the left 3.2 m (all in range)
while the corners are not, and no two opposite scans are mirror images."""

_EPS = 1e-9
"""Hits closer than this along a ray are ignored, so a ray never hits the surface it left."""

_POLYGON_SIDES = 64
"""Sides of the polygon that stands for a cylinder in :meth:`Scene.outline_2d`."""

_JOIN_TOL = 1e-9
"""Walls whose end and next start are this close are drawn as one polyline."""


def _check_albedo(albedo: float) -> None:
    if not 0.0 < albedo <= 1.0:
        raise ValueError(f"albedo must be in (0, 1], not {albedo}")


def _check_positive(name: str, value: float) -> None:
    if not value > 0.0 or not math.isfinite(value):
        raise ValueError(f"{name} must be positive and finite, not {value}")


@dataclass(frozen=True)
class Wall:
    """A vertical rectangle on the segment ``start`` -> ``end``, from ``base`` up ``height``.

    Both faces reflect, so a wall can bound a room from inside or stand free as a partition.
    """

    start: tuple[float, float]
    end: tuple[float, float]
    height: float = 2.5
    albedo: float = 0.6
    base: float = 0.0

    def __post_init__(self) -> None:
        if math.dist(self.start, self.end) <= 0.0:
            raise ValueError("a wall needs two distinct end points")
        _check_positive("height", self.height)
        _check_albedo(self.albedo)


@dataclass(frozen=True)
class Box:
    """A solid box: ``size`` is (length along its own x, width along its own y), turned by
    ``yaw`` (radians, counter-clockwise) about its centre, from ``base`` up ``height``."""

    center: tuple[float, float]
    size: tuple[float, float]
    height: float
    yaw: float = 0.0
    albedo: float = 0.6
    base: float = 0.0

    def __post_init__(self) -> None:
        _check_positive("box length", self.size[0])
        _check_positive("box width", self.size[1])
        _check_positive("height", self.height)
        _check_albedo(self.albedo)

    def corners(self) -> FloatArray:
        """The four corners seen from above, counter-clockwise, shape (4, 2)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        hl, hw = self.size[0] / 2.0, self.size[1] / 2.0
        local = np.array([[hl, -hw], [hl, hw], [-hl, hw], [-hl, -hw]])
        rot = np.array([[c, -s], [s, c]])
        return np.asarray(local @ rot.T + np.asarray(self.center), dtype=np.float64)


@dataclass(frozen=True)
class Cylinder:
    """A solid upright cylinder, from ``base`` up ``height``.

    From inside (the sensor within the radius) its mantle is a round wall: that is
    :meth:`Scene.circle`.
    """

    center: tuple[float, float]
    radius: float
    height: float
    albedo: float = 0.6
    base: float = 0.0

    def __post_init__(self) -> None:
        _check_positive("radius", self.radius)
        _check_positive("height", self.height)
        _check_albedo(self.albedo)


@dataclass(frozen=True)
class Plane:
    """An unbounded horizontal plane at height ``z``: a floor (z = 0) or a ceiling."""

    z: float = 0.0
    albedo: float = 0.3

    def __post_init__(self) -> None:
        if not math.isfinite(self.z):
            raise ValueError(f"plane height must be finite, not {self.z}")
        _check_albedo(self.albedo)


Shape: TypeAlias = Wall | Box | Cylinder | Plane


def polygon_walls(
    vertices: Sequence[tuple[float, float]], height: float = 2.5, albedo: float = 0.6
) -> tuple[Wall, ...]:
    """Walls along a closed polygon (last vertex joins the first): a room of any shape."""
    if len(vertices) < 3:
        raise ValueError("a closed polygon needs at least three vertices")
    n = len(vertices)
    return tuple(
        Wall(vertices[i], vertices[(i + 1) % n], height=height, albedo=albedo) for i in range(n)
    )


# --- flattened geometry --------------------------------------------------------------------------
#
# Two flattenings of the same shapes. The general one (rays in any directions) intersects every
# ray with every vertical face (walls, box sides), cylinder mantle and horizontal cap (tops and
# bottoms, planes). The fan one serves the common case in which all rays share one heading seen
# from above, as the rays of a BIRIS profile do. The plan-view work is then done once, for the
# heading, on arrays one entry per shape: where the heading enters and leaves each footprint (a
# wall is a box of zero width). Each ray is then placed by its slope k = dz / |d_xy| alone. A
# vertical side met at horizontal distance rho between heights zlo and zhi is hit by the rays
# with (zlo - oz) / rho <= k <= (zhi - oz) / rho; a cap at height z crossing the heading between
# rho_a and rho_b by the rays whose (z - oz) / k lies in that span. Both are slope intervals, so
# one broadcast comparison finds every hit of every ray; numpy's per-call overhead, not the
# arithmetic, is the cost at these sizes, so the path counts its calls.

_FAR = 1e6
"""Stands for infinity (a plane's far end, metres) where the fan path divides by it."""


@dataclass(frozen=True)
class _Faces:
    """Vertical rectangles: base point, edge vector, z range."""

    px: FloatArray
    py: FloatArray
    ex: FloatArray
    ey: FloatArray
    zlo: FloatArray
    zhi: FloatArray


@dataclass(frozen=True)
class _Circles:
    """Cylinder mantles or discs: centre, squared radius, z range (a disc's zlo = zhi)."""

    cx: FloatArray
    cy: FloatArray
    r2: FloatArray
    zlo: FloatArray
    zhi: FloatArray


@dataclass(frozen=True)
class _Rects:
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
class _Slabs:
    """Footprints as pairs of slabs for the fan path: unit normal n, offset c . n of the
    footprint's centre, half width; all first slabs, then all second slabs (u, then v)."""

    nx: FloatArray
    ny: FloatArray
    offset: FloatArray
    half: FloatArray

    @staticmethod
    def of(rects: _Rects | None) -> _Slabs | None:
        if (r := rects) is None:
            return None
        return _Slabs(
            nx=np.concatenate((r.ux, -r.uy)),
            ny=np.concatenate((r.uy, r.ux)),
            offset=np.concatenate((r.cx * r.ux + r.cy * r.uy, r.cy * r.ux - r.cx * r.uy)),
            half=np.concatenate((r.hu, r.hv)),
        )


def _arr(values: Iterable[float]) -> FloatArray:
    return np.fromiter(values, dtype=np.float64)


_T = TypeVar("_T", _Faces, _Circles, _Rects)


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
class _Geometry:
    # General path; albedo in the order faces, mantles, caps, discs.
    faces: _Faces | None
    mantles: _Circles | None
    caps: _Rects | None
    discs: _Circles | None
    albedo: FloatArray
    # Fan path: footprints of walls and boxes, then cylinders: the S "solids".
    footprints: _Slabs | None
    circles: _Circles | None
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
    def build(shapes: Sequence[Shape]) -> _Geometry:
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
        return _Geometry(
            faces=_table(_Faces, faces),
            mantles=_table(_Circles, mantles),
            caps=_table(_Rects, caps),
            discs=_table(_Circles, discs),
            albedo=_arr(albedo),
            footprints=_Slabs.of(_table(_Rects, [_footprint(s) for s in flat])),
            circles=_table(_Circles, mantles),
            side_zlo=_arr(bottoms),
            side_zhi=_arr(tops),
            cap_z=_arr(bottoms + tops + [p.z for p in planes]),
            plane_near=np.full(len(planes), _EPS),
            plane_far=np.full(len(planes), _FAR),
            fan_albedo=_arr([s.albedo for s in solids] * 3 + [p.albedo for p in planes]),
        )


# --- general path ---------------------------------------------------------------------------------
# Each _hit_* returns an (n, m) array of distances along the rays, inf where a ray misses.
# ox, oy, oz: ray origin; dx, dy, dz: (n, 1) direction columns. Called under np.errstate.


def _hit_faces(
    f: _Faces, ox: float, oy: float, oz: float, dx: FloatArray, dy: FloatArray, dz: FloatArray
) -> FloatArray:
    # Solve o + t d = p + s e in plan: t = (w x e) / (d x e), s = (w x d) / (d x e), w = p - o.
    wx = f.px - ox
    wy = f.py - oy
    inv = 1.0 / (dx * f.ey - dy * f.ex)
    t = (wx * f.ey - wy * f.ex) * inv
    s = (wx * dy - wy * dx) * inv
    z = oz + t * dz
    ok = (t > _EPS) & (s >= 0.0) & (s <= 1.0) & (z >= f.zlo) & (z <= f.zhi)
    return np.where(ok, t, np.inf)


def _hit_mantles(
    m: _Circles, ox: float, oy: float, oz: float, dx: FloatArray, dy: FloatArray, dz: FloatArray
) -> FloatArray:
    # |w + t d_xy|^2 = r^2 with w = o - c. The near root is the way in from outside; when it is
    # behind the ray or off the mantle's height, the far root (the inside of a round wall) may
    # still be hit.
    wx = ox - m.cx
    wy = oy - m.cy
    a = dx * dx + dy * dy
    b = dx * wx + dy * wy
    root = np.sqrt(b * b - a * (wx * wx + wy * wy - m.r2))
    t1 = (-b - root) / a
    t2 = (root - b) / a
    z1 = oz + t1 * dz
    z2 = oz + t2 * dz
    ok1 = (t1 > _EPS) & (z1 >= m.zlo) & (z1 <= m.zhi)
    ok2 = (t2 > _EPS) & (z2 >= m.zlo) & (z2 <= m.zhi)
    return np.where(ok1, t1, np.where(ok2, t2, np.inf))


def _hit_caps(
    r: _Rects, ox: float, oy: float, oz: float, dx: FloatArray, dy: FloatArray, dz: FloatArray
) -> FloatArray:
    t = (r.zlo - oz) / dz
    px = (ox - r.cx) + t * dx
    py = (oy - r.cy) + t * dy
    pu = px * r.ux + py * r.uy
    pv = py * r.ux - px * r.uy
    ok = (t > _EPS) & (t < np.inf) & (np.abs(pu) <= r.hu) & (np.abs(pv) <= r.hv)
    return np.where(ok, t, np.inf)


def _hit_discs(
    d: _Circles, ox: float, oy: float, oz: float, dx: FloatArray, dy: FloatArray, dz: FloatArray
) -> FloatArray:
    t = (d.zlo - oz) / dz
    px = (ox - d.cx) + t * dx
    py = (oy - d.cy) + t * dy
    ok = (t > _EPS) & (t < np.inf) & (px * px + py * py <= d.r2)
    return np.where(ok, t, np.inf)


def _cast_general(
    g: _Geometry, o: tuple[float, float, float], d: FloatArray
) -> tuple[FloatArray, FloatArray]:
    ox, oy, oz = o
    dx, dy, dz = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    parts: list[FloatArray] = []
    if g.faces is not None:
        parts.append(_hit_faces(g.faces, ox, oy, oz, dx, dy, dz))
    if g.mantles is not None:
        parts.append(_hit_mantles(g.mantles, ox, oy, oz, dx, dy, dz))
    if g.caps is not None:
        parts.append(_hit_caps(g.caps, ox, oy, oz, dx, dy, dz))
    if g.discs is not None:
        parts.append(_hit_discs(g.discs, ox, oy, oz, dx, dy, dz))
    t = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
    nearest = t.argmin(axis=1)
    dist = t[np.arange(t.shape[0]), nearest]
    return dist, np.where(dist < np.inf, g.albedo[nearest], 0.0)


# --- fan path -------------------------------------------------------------------------------------


def _spans_rects(
    s: _Slabs, ox: float, oy: float, hx: float, hy: float
) -> tuple[FloatArray, FloatArray]:
    """Where the heading enters and leaves each footprint (slab method); NaN where it misses."""
    q = (ox * s.nx + oy * s.ny) - s.offset
    inv = 1.0 / (hx * s.nx + hy * s.ny)
    t1 = (-s.half - q) * inv
    t2 = (s.half - q) * inv
    lo = np.minimum(t1, t2)
    hi = np.maximum(t1, t2)
    f = lo.size // 2
    enter = np.maximum(lo[:f], lo[f:])
    leave = np.minimum(hi[:f], hi[f:])
    return enter, np.where(enter <= leave, leave, np.nan)


def _spans_circles(
    c: _Circles, ox: float, oy: float, hx: float, hy: float
) -> tuple[FloatArray, FloatArray]:
    """Where the heading enters and leaves each circle; NaN where it misses."""
    wx = ox - c.cx
    wy = oy - c.cy
    b = hx * wx + hy * wy
    root = np.sqrt(b * b - (wx * wx + wy * wy - c.r2))
    return -b - root, root - b


def _cast_fan(
    g: _Geometry,
    o: tuple[float, float, float],
    hx: float,
    hy: float,
    d: FloatArray,
    hxy: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Cast rays that all have the plan-view heading (hx, hy), ``hxy`` their plan-view lengths;
    see the note above."""
    ox, oy, oz = o
    spans = []
    if g.footprints is not None:
        spans.append(_spans_rects(g.footprints, ox, oy, hx, hy))
    if g.circles is not None:
        spans.append(_spans_circles(g.circles, ox, oy, hx, hy))
    if len(spans) == 2:
        enter = np.concatenate((spans[0][0], spans[1][0]))
        leave = np.concatenate((spans[0][1], spans[1][1]))
    elif spans:
        enter, leave = spans[0]
    else:
        enter = leave = np.empty(0)
    # Seen from outside, a solid's side is met where the heading enters it, from inside where
    # it leaves (a round wall around the sensor); a span behind the sensor (leave <= 0) is
    # no hit. Its bottom and top are crossed over the part of the span ahead of the sensor.
    side = np.where(leave > _EPS, np.where(enter > _EPS, enter, leave), np.nan)
    start = np.maximum(enter, _EPS)
    near = np.concatenate((start, start, g.plane_near))
    far = np.concatenate((leave, leave, g.plane_far))
    rise = g.cap_z - oz
    near = np.where((near <= far) & (rise != 0.0), near, np.nan)
    slope_near = rise / near
    slope_far = rise / far
    k_lo = np.concatenate(((g.side_zlo - oz) / side, np.minimum(slope_near, slope_far)))
    k_hi = np.concatenate(((g.side_zhi - oz) / side, np.maximum(slope_near, slope_far)))

    # Only surfaces some ray can hit go into the (rays x surfaces) stage; NaNs drop out here.
    slope = d[:, 2] / hxy
    keep = np.flatnonzero((k_hi >= slope.min()) & (k_lo <= slope.max()))
    n = d.shape[0]
    if keep.size == 0:
        return np.full(n, np.inf), np.zeros(n)
    at_rho = np.concatenate((side, np.zeros(rise.size)))[keep]
    per_inv_slope = np.concatenate((np.zeros(side.size), rise))[keep]
    slope_col = slope[:, None]
    # A level ray (slope 0) never falls in a cap's interval, so its 1/slope may be 0: it then
    # only multiplies the sides' zero per_inv_slope.
    inv_slope = 1.0 / np.where(slope_col == 0.0, np.inf, slope_col)
    hit = (slope_col >= k_lo[keep]) & (slope_col <= k_hi[keep])
    rho = np.where(hit, at_rho + per_inv_slope * inv_slope, np.inf)
    nearest = rho.argmin(axis=1)
    rho_hit = rho[np.arange(n), nearest]
    albedo = g.fan_albedo[keep[nearest]]
    return rho_hit / hxy, np.where(rho_hit < np.inf, albedo, 0.0)


def _common_heading(d: FloatArray) -> tuple[float, float, FloatArray] | None:
    """The unit plan-view heading every ray shares and the rays' plan-view lengths, or None."""
    bearing = np.arctan2(d[:, 1], d[:, 0])
    if bearing.max() - bearing.min() > 1e-12:
        return None
    b0 = float(bearing[0])
    hx, hy = math.cos(b0), math.sin(b0)
    along = d[:, 0] * hx + d[:, 1] * hy
    if not along.min() > 1e-9:  # rays (nearly) straight up or down have no heading
        return None
    return hx, hy, along


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


class Scene:
    """An immutable set of shapes, flattened once for fast ray casting."""

    def __init__(self, shapes: Iterable[Shape]) -> None:
        self._shapes = tuple(shapes)
        for shape in self._shapes:
            if not isinstance(shape, (Wall, Box, Cylinder, Plane)):
                raise TypeError(f"not a scene shape: {shape!r}")
        self._geometry = _Geometry.build(self._shapes)

    @property
    def shapes(self) -> tuple[Shape, ...]:
        return self._shapes

    def with_shapes(self, *shapes: Shape) -> Scene:
        """This scene plus ``shapes``: how a test adds one obstacle to a known room."""
        return Scene(self._shapes + shapes)

    def __repr__(self) -> str:
        return f"Scene({list(self._shapes)!r})"

    # --- ready-made scenes -----------------------------------------------------------------------

    @classmethod
    def circle(cls, radius_m: float, albedo: float = 0.6) -> Scene:
        """A round wall of ``radius_m`` centred on the pan axis.

        Every sample then has the same depth along the optical axis at every azimuth, which is
        what end-to-end tests compare against. The wall reaches 100 radii above and below the
        sensor, so even a steeply tilted fan sees nothing but the wall.
        """
        _check_positive("radius_m", radius_m)
        reach = 100.0 * radius_m + 100.0
        return cls([Cylinder((0.0, 0.0), radius_m, 2.0 * reach, albedo=albedo, base=-reach)])

    @classmethod
    def room(
        cls,
        width_m: float = 6.0,
        depth_m: float = 5.0,
        origin: tuple[float, float] = DEFAULT_ROOM_ORIGIN,
        obstacles: Sequence[Box | Cylinder] | None = None,
        height_m: float = 2.5,
        seed: int | None = None,
        *,
        wall_albedo: float = 0.6,
        floor: bool = False,
        ceiling: bool = False,
    ) -> Scene:
        """A rectangular room, ``depth_m`` along x and ``width_m`` along y, whose rear-right
        corner is at ``origin`` (world x, y); the sensor, at the world origin, must be inside.

        ``obstacles=None`` furnishes it: with ``seed=None`` a fixed set (two boxes, one a low
        one that only the fan's lower rows see, and a cylinder, all within 3.5 m of the sensor
        and clear of the x and y axes in the default room); with a seed, a random but
        reproducible set of the same kinds. Pass ``obstacles=[]`` for an empty room. The floor
        and ceiling are off by default because the fan's lowest row meets the floor 2.6 m out,
        which would put a false ring in closest-point (2-D) scans.
        """
        _check_positive("width_m", width_m)
        _check_positive("depth_m", depth_m)
        _check_positive("height_m", height_m)
        x0, y0 = origin
        x1, y1 = x0 + depth_m, y0 + width_m
        if not (x0 < 0.0 < x1 and y0 < 0.0 < y1):
            raise ValueError("the sensor (world origin) must be inside the room")
        corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
        shapes: list[Shape] = list(polygon_walls(corners, height_m, wall_albedo))
        if obstacles is not None:
            if seed is not None:
                raise ValueError("give either obstacles or a seed, not both")
            shapes += obstacles
        elif seed is None:
            shapes += _DEFAULT_OBSTACLES
        else:
            shapes += _random_obstacles((x0, y0, x1, y1), np.random.default_rng(seed))
        if floor:
            shapes.append(Plane(0.0, albedo=0.3))
        if ceiling:
            shapes.append(Plane(height_m, albedo=0.8))
        return cls(shapes)

    # --- ray casting -----------------------------------------------------------------------------

    def cast(
        self, origin: NDArray[np.floating], directions: NDArray[np.floating]
    ) -> tuple[FloatArray, FloatArray]:
        """Distance along each ray to the first surface, and that surface's albedo.

        ``origin`` is (3,), ``directions`` (n, 3), normally unit vectors (a distance is in units
        of its ray's length). A ray that hits nothing gets distance inf and albedo 0. Rays that
        share one heading seen from above (a BIRIS profile) take the fast path.
        """
        return self._cast(origin, directions, fan=True)

    def cast_general(
        self, origin: NDArray[np.floating], directions: NDArray[np.floating]
    ) -> tuple[FloatArray, FloatArray]:
        """:meth:`cast` without the shared-heading shortcut: the reference the tests hold the
        shortcut to, and what rays of mixed headings get anyway."""
        return self._cast(origin, directions, fan=False)

    def _cast(
        self, origin: NDArray[np.floating], directions: NDArray[np.floating], fan: bool
    ) -> tuple[FloatArray, FloatArray]:
        o = np.asarray(origin, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        if o.shape != (3,) or d.ndim != 2 or d.shape[1] != 3:
            raise ValueError("cast wants origin (3,) and directions (n, 3)")
        n = d.shape[0]
        g = self._geometry
        if n == 0 or g.empty:
            return np.full(n, np.inf), np.zeros(n)
        o3 = (float(o[0]), float(o[1]), float(o[2]))
        with np.errstate(divide="ignore", invalid="ignore"):
            heading = _common_heading(d) if fan else None
            if heading is None:
                return _cast_general(g, o3, d)
            hx, hy, hxy = heading
            return _cast_fan(g, o3, hx, hy, d, hxy)

    # --- seen from above -------------------------------------------------------------------------

    def outline_2d(self) -> list[FloatArray]:
        """Polylines (k, 2) of everything that stands up, seen from above, for pictures.

        Boxes and cylinders (as polygons) are closed (last point = first); walls that meet end to
        start in the order given are joined, so a room drawn with :func:`polygon_walls` is one
        closed polyline. Planes have no outline.
        """
        lines = _chain([s for s in self._shapes if isinstance(s, Wall)])
        for shape in self._shapes:
            if isinstance(shape, Box):
                corners = shape.corners()
                lines.append(np.vstack((corners, corners[:1])))
            elif isinstance(shape, Cylinder):
                lines.append(_circle_polygon(shape.center, shape.radius))
        return lines

    def distance_to_surface_2d(self, points: NDArray[np.floating]) -> FloatArray:
        """Horizontal distance from each (x, y) point to the nearest wall, box side or cylinder
        mantle (a true circle, not the drawn polygon); inf when nothing stands up.

        Lets a test check that measured points lie on true surfaces without re-deriving them.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2:
            raise ValueError("points must be (m, 2)")
        best = np.full(p.shape[0], np.inf)
        g = self._geometry
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


_DEFAULT_OBSTACLES: tuple[Box | Cylinder, ...] = (
    Box(center=(1.6, 1.2), size=(0.6, 0.4), height=0.8, yaw=0.3, albedo=0.7),
    Box(center=(-1.2, -1.6), size=(0.8, 0.5), height=0.35, albedo=0.5),
    Cylinder(center=(1.4, -1.3), radius=0.25, height=1.2, albedo=0.4),
)
"""The default room's furniture: a cabinet front-left, a low crate behind-right (below the head,
so only the lower rows see it) and a bin front-right; all clear of the x and y axes."""


def _random_obstacles(
    bounds: tuple[float, float, float, float], rng: np.random.Generator
) -> list[Box | Cylinder]:
    """Two boxes and a cylinder, 0.8-3.0 m from the sensor, inside the room, not overlapping
    (as many as fit: a room too small for one gets fewer).

    Placement is by rejection on bounding circles; the draw order is fixed, so a seed always
    gives the same furniture in the same room.
    """
    x0, y0, x1, y1 = bounds
    placed: list[tuple[float, float, float]] = []  # centre x, centre y, bounding radius
    result: list[Box | Cylinder] = []
    for kind in ("box", "box", "cylinder"):
        for _ in range(1000):
            reach = float(rng.uniform(0.8, 3.0))
            bearing = float(rng.uniform(-math.pi, math.pi))
            cx, cy = reach * math.cos(bearing), reach * math.sin(bearing)
            albedo = float(rng.uniform(0.25, 0.9))
            height = float(rng.uniform(0.3, 1.5))
            shape: Box | Cylinder
            if kind == "box":
                size = (float(rng.uniform(0.3, 0.9)), float(rng.uniform(0.3, 0.9)))
                yaw = float(rng.uniform(-math.pi, math.pi))
                shape = Box((cx, cy), size, height, yaw=yaw, albedo=albedo)
                bound = math.hypot(*size) / 2.0
            else:
                radius = float(rng.uniform(0.1, 0.35))
                shape = Cylinder((cx, cy), radius, height, albedo=albedo)
                bound = radius
            inside = x0 + bound < cx < x1 - bound and y0 + bound < cy < y1 - bound
            clear = reach - bound >= 0.4 and all(
                math.hypot(cx - qx, cy - qy) > bound + qb for qx, qy, qb in placed
            )
            if inside and clear:
                placed.append((cx, cy, bound))
                result.append(shape)
                break
    return result
