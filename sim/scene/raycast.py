"""The ray caster: every ray against every surface in a fixed number of array operations.

The optics cast one ray per range sample, once per acquisition and at up to thousands of
acquisitions a second in benchmarks, so :func:`cast` never loops in Python over rays or shapes.
The general path intersects each ray with each surface. The rays of one profile share a heading
seen from above, which the fan path exploits: the plan-view work is then done once, for the
heading, on arrays one entry per shape: where the heading enters and leaves each footprint. Each
ray is then placed by its slope k = dz / |d_xy| alone. A vertical side met at horizontal
distance rho between heights zlo and zhi is hit by the rays with (zlo - oz) / rho <= k <=
(zhi - oz) / rho; a cap at height z crossing the heading between rho_a and rho_b by the rays
whose (z - oz) / k lies in that span. Both are slope intervals, so one broadcast comparison finds
every hit of every ray; numpy's per-call overhead, not the arithmetic, is the cost at these
sizes, so the path counts its calls. The general path is kept for other rays and as the
reference the tests hold the fan path to.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from sim.scene.geometry import EPS, Circles, Faces, Geometry, Rects, Slabs
from sim.scene.shapes import FloatArray

__all__ = ["cast"]


# --- general path ---------------------------------------------------------------------------------
# Each _hit_* returns an (n, m) array of distances along the rays, inf where a ray misses.
# ox, oy, oz: ray origin; dx, dy, dz: (n, 1) direction columns. Called under np.errstate.


def _hit_faces(
    f: Faces, ox: float, oy: float, oz: float, dx: FloatArray, dy: FloatArray, dz: FloatArray
) -> FloatArray:
    # Solve o + t d = p + s e in plan: t = (w x e) / (d x e), s = (w x d) / (d x e), w = p - o.
    wx = f.px - ox
    wy = f.py - oy
    inv = 1.0 / (dx * f.ey - dy * f.ex)
    t = (wx * f.ey - wy * f.ex) * inv
    s = (wx * dy - wy * dx) * inv
    z = oz + t * dz
    ok = (t > EPS) & (s >= 0.0) & (s <= 1.0) & (z >= f.zlo) & (z <= f.zhi)
    return np.where(ok, t, np.inf)


def _hit_mantles(
    m: Circles, ox: float, oy: float, oz: float, dx: FloatArray, dy: FloatArray, dz: FloatArray
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
    ok1 = (t1 > EPS) & (z1 >= m.zlo) & (z1 <= m.zhi)
    ok2 = (t2 > EPS) & (z2 >= m.zlo) & (z2 <= m.zhi)
    return np.where(ok1, t1, np.where(ok2, t2, np.inf))


def _level_crossing(
    z: FloatArray,
    cx: FloatArray,
    cy: FloatArray,
    ox: float,
    oy: float,
    oz: float,
    dx: FloatArray,
    dy: FloatArray,
    dz: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Where each ray crosses height ``z``: its distance, and the point relative to (cx, cy)."""
    t = (z - oz) / dz
    return t, (ox - cx) + t * dx, (oy - cy) + t * dy


def _hit_caps(
    r: Rects, ox: float, oy: float, oz: float, dx: FloatArray, dy: FloatArray, dz: FloatArray
) -> FloatArray:
    t, px, py = _level_crossing(r.zlo, r.cx, r.cy, ox, oy, oz, dx, dy, dz)
    pu = px * r.ux + py * r.uy
    pv = py * r.ux - px * r.uy
    ok = (t > EPS) & (t < np.inf) & (np.abs(pu) <= r.hu) & (np.abs(pv) <= r.hv)
    return np.where(ok, t, np.inf)


def _hit_discs(
    d: Circles, ox: float, oy: float, oz: float, dx: FloatArray, dy: FloatArray, dz: FloatArray
) -> FloatArray:
    t, px, py = _level_crossing(d.zlo, d.cx, d.cy, ox, oy, oz, dx, dy, dz)
    ok = (t > EPS) & (t < np.inf) & (px * px + py * py <= d.r2)
    return np.where(ok, t, np.inf)


def _cast_general(
    g: Geometry, o: tuple[float, float, float], d: FloatArray
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
    s: Slabs, ox: float, oy: float, hx: float, hy: float
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
    c: Circles, ox: float, oy: float, hx: float, hy: float
) -> tuple[FloatArray, FloatArray]:
    """Where the heading enters and leaves each circle; NaN where it misses."""
    wx = ox - c.cx
    wy = oy - c.cy
    b = hx * wx + hy * wy
    root = np.sqrt(b * b - (wx * wx + wy * wy - c.r2))
    return -b - root, root - b


def _cast_fan(
    g: Geometry,
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
    side = np.where(leave > EPS, np.where(enter > EPS, enter, leave), np.nan)
    start = np.maximum(enter, EPS)
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


def cast(
    g: Geometry, origin: NDArray[np.floating], directions: NDArray[np.floating], *, fan: bool
) -> tuple[FloatArray, FloatArray]:
    """Distance along each ray to the first surface, and that surface's albedo (see
    :meth:`sim.scene.Scene.cast`); ``fan`` lets rays that share a heading take the fan path."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.shape != (3,) or d.ndim != 2 or d.shape[1] != 3:
        raise ValueError("cast wants origin (3,) and directions (n, 3)")
    n = d.shape[0]
    if n == 0 or g.empty:
        return np.full(n, np.inf), np.zeros(n)
    o3 = (float(o[0]), float(o[1]), float(o[2]))
    with np.errstate(divide="ignore", invalid="ignore"):
        heading = _common_heading(d) if fan else None
        if heading is None:
            return _cast_general(g, o3, d)
        hx, hy, hxy = heading
        return _cast_fan(g, o3, hx, hy, d, hxy)
