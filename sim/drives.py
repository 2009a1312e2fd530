"""The simulator's default drive through its scene, and how a map made on it is judged.

**The drive.** :func:`default_drive` is the one path ``--drive`` means (``biris grid --sim
--drive``, ``biris record --sim --drive``, the ``grid`` benchmark): a loop of waypoints
(:data:`DRIVE_LOOP`) through ``Scene.room()`` at :data:`DRIVE_SPEED_MPS`, from the origin back to
it, past every wall at 0.7 to 1.2 m and round the furniture, keeping :data:`DRIVE_CLEARANCE_M`
from every surface. It starts at :data:`DRIVE_START_S`, once the server is up. In another scene
the loop is shrunk about the origin until it keeps that clearance (a ``Scene.circle(3)`` gets it
at 0.8 times); a scene too tight for any is refused.

**The truth a map is judged by.** A grid cannot be asked to know walls its sensor never
looked at, so its recall is counted over the stretches of true surface the head *swept*
(:func:`swept_surface`): every true surface standing up (walls, box sides, cylinder mantles)
sampled every :data:`SAMPLE_SPACING_M` along its outline, and a sample counted as swept when
some acquisition's ray passed over it, that is, for some acquisition k:

* it lies within acquisition k's share of its sweep: its bearing from the head's true optical
  centre at ``t[k]`` is within half the angle to the neighbouring acquisitions of the sweep
  (``odom`` bearings: azimuth plus the vehicle's yaw), so the acquisitions of a sweep tile the
  angle it covered;
* its horizontal distance from the optical centre is within the optics' range
  (``min_range_m`` to ``max_range_m``: 0.3 to 3.5 m);
* the height on its surface nearest the optical centre's, within the grid's height band, is
  inside the fan (+-11 degrees, level head), and the line of sight to that point is clear
  (``Scene.cast_general`` reaches it).

:func:`score_occupied` then counts **precision**, the share of the grid's occupied cells whose
centre lies within ``tolerance_m`` of a true surface (``Scene.distance_to_surface_2d``, anywhere
in the scene: a cell marked where nothing stands is wrong wherever it is) or inside the
footprint of a box or a cylinder (:func:`inside_solid`: the fan sees a low crate's top from
close up, and the ground under it is occupied), and **recall**, the
share of swept surface samples with an occupied cell's centre within ``tolerance_m``. The
tolerance is one cell by default: the cell a surface passes through or its neighbour.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sim.optics import DEFAULT_PARAMS, OpticsParams
from sim.scene import Scene
from sim.scene.shapes import Box, Cylinder, Wall
from sim.trajectory import Trajectory

__all__ = [
    "DRIVE_CLEARANCE_M",
    "DRIVE_LOOP",
    "DRIVE_SPEED_MPS",
    "DRIVE_START_S",
    "SAMPLE_SPACING_M",
    "GridScore",
    "SurfaceSamples",
    "default_drive",
    "inside_solid",
    "path_clearance",
    "score_occupied",
    "surface_samples",
    "swept_surface",
]

FloatArray = NDArray[np.float64]

DRIVE_LOOP: tuple[tuple[float, float], ...] = (
    (0.7, 0.0),
    (0.7, 2.3),
    (-1.2, 2.3),
    (-1.2, -0.6),
    (0.3, -0.6),
    (0.3, -2.1),
    (2.1, -2.1),
    (2.1, 0.0),
    (0.0, 0.0),
)
"""The loop's waypoints (x, y in the scene, metres) in the default ``Scene.room()``: left past the
cabinet, along the left and back walls, round the low crate, along the right wall past the bin,
up the front wall and home. 16.8 m; with the turns on the spot, 42 s at 0.5 m/s."""

DRIVE_SPEED_MPS = 0.5
"""The issue's speed: fast enough that an undeskewed sweep smears by tens of centimetres."""

DRIVE_START_S = 8.0
"""Hardware time the vehicle sets off: once the server is up (initialising takes about 7.8 s
with the default init record, homing included), so the whole drive is scanned."""

DRIVE_CLEARANCE_M = 0.4
"""Least distance the path keeps from every surface: a small robot's half-width and a margin."""

SAMPLE_SPACING_M = 0.025
"""Spacing of the samples along the true surfaces: half a 5 cm cell."""

_SHRINK = (1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3)


def path_clearance(scene: Scene, waypoints: Sequence[tuple[float, float]]) -> float:
    """Least horizontal distance (m) from the polyline origin -> waypoints to any surface
    of ``scene``, sampled every 2 cm (a path through a box crosses its side: 0 there)."""
    corners = np.vstack(([(0.0, 0.0)], np.asarray(waypoints, dtype=np.float64)))
    pieces = []
    for a, b in itertools.pairwise(corners):
        n = max(2, math.ceil(float(np.hypot(*(b - a))) / 0.02) + 1)
        pieces.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    return float(scene.distance_to_surface_2d(np.vstack(pieces)).min())


def default_drive(
    scene: Scene | None = None,
    *,
    speed_mps: float = DRIVE_SPEED_MPS,
    start_s: float = DRIVE_START_S,
    clearance_m: float = DRIVE_CLEARANCE_M,
) -> Trajectory:
    """The simulator's default drive through ``scene`` (None: ``Scene.room()``): the loop of
    :data:`DRIVE_LOOP`, shrunk about the origin as little as keeps ``clearance_m`` from every
    surface (see the module), at ``speed_mps`` from ``start_s``.

    Raises:
        ValueError: no shrunk loop (down to 0.3 times) keeps the clearance in ``scene``.
    """
    where = Scene.room() if scene is None else scene
    loop = np.asarray(DRIVE_LOOP, dtype=np.float64)
    for factor in _SHRINK:
        points = [(float(x), float(y)) for x, y in factor * loop]
        if path_clearance(where, points) >= clearance_m:
            return Trajectory.waypoints(
                [(x, y, speed_mps) for x, y in points[:-1]] + [(0.0, 0.0, speed_mps)],
                start_s=start_s,
            )
    raise ValueError(
        f"the default drive does not fit this scene: no loop keeps {clearance_m:g} m from every "
        "surface; pass a Trajectory of your own"
    )


# -- the truth ------------------------------------------------------------------------------------


class SurfaceSamples(NamedTuple):
    """Points along the true surfaces that stand up, with the height span of their shape."""

    xy: FloatArray
    """(m, 2) scene x, y."""
    base: FloatArray
    """(m,) the shape's bottom, metres."""
    top: FloatArray
    """(m,) the shape's top."""


def _along(a: ArrayLike, b: ArrayLike, spacing: float) -> FloatArray:
    p, q = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    n = max(1, math.ceil(float(np.hypot(*(q - p))) / spacing))
    return p + ((np.arange(n) + 0.5) / n)[:, None] * (q - p)


def surface_samples(scene: Scene, spacing_m: float = SAMPLE_SPACING_M) -> SurfaceSamples:
    """Every wall, box side and cylinder mantle of ``scene`` sampled every ``spacing_m`` (at the
    middle of equal pieces); planes have none."""
    xy: list[FloatArray] = []
    base: list[float] = []
    top: list[float] = []

    def add(points: FloatArray, shape: Wall | Box | Cylinder) -> None:
        xy.append(points)
        base.extend([shape.base] * points.shape[0])
        top.extend([shape.base + shape.height] * points.shape[0])

    for shape in scene.shapes:
        if isinstance(shape, Wall):
            add(_along(shape.start, shape.end, spacing_m), shape)
        elif isinstance(shape, Box):
            corners = shape.corners()
            for i in range(4):
                add(_along(corners[i], corners[(i + 1) % 4], spacing_m), shape)
        elif isinstance(shape, Cylinder):
            n = max(8, math.ceil(2.0 * math.pi * shape.radius / spacing_m))
            angle = 2.0 * math.pi * (np.arange(n) + 0.5) / n
            ring = np.column_stack((np.cos(angle), np.sin(angle))) * shape.radius
            add(ring + np.asarray(shape.center, dtype=np.float64), shape)
    if not xy:
        return SurfaceSamples(np.zeros((0, 2)), np.zeros(0), np.zeros(0))
    return SurfaceSamples(np.vstack(xy), np.asarray(base), np.asarray(top))


def inside_solid(scene: Scene, xy: ArrayLike) -> NDArray[np.bool_]:
    """(m,) True where a point (x, y) lies within the footprint of a box or a cylinder of
    ``scene``: ground something stands on, occupied though no side passes near it (the fan
    sees a low box's top from close up)."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    inside = np.zeros(p.shape[0], dtype=bool)
    for shape in scene.shapes:
        if isinstance(shape, Box):
            c, s = math.cos(shape.yaw), math.sin(shape.yaw)
            dx, dy = p[:, 0] - shape.center[0], p[:, 1] - shape.center[1]
            along, across = c * dx + s * dy, -s * dx + c * dy
            inside |= (np.abs(along) <= shape.size[0] / 2) & (np.abs(across) <= shape.size[1] / 2)
        elif isinstance(shape, Cylinder):
            dx, dy = p[:, 0] - shape.center[0], p[:, 1] - shape.center[1]
            inside |= np.hypot(dx, dy) <= shape.radius
    return inside


def _wrap(angle: FloatArray) -> FloatArray:
    wrapped: FloatArray = (angle + math.pi) % (2.0 * math.pi) - math.pi
    return wrapped


def swept_surface(
    scene: Scene,
    trajectory: Trajectory,
    sweeps: Sequence[tuple[ArrayLike, ArrayLike]],
    *,
    band_m: tuple[float, float] = (0.1, 2.0),
    optics: OpticsParams = DEFAULT_PARAMS,
    spacing_m: float = SAMPLE_SPACING_M,
) -> FloatArray:
    """(m, 2) the surface samples the head swept (the module's rule): ``sweeps`` holds, for
    each sweep in the order taken, its acquisitions' hardware times and azimuths (radians,
    relative to the vehicle; a scan's ``t`` and ``azimuth`` times 2 pi / 4096), the vehicle
    following ``trajectory``, the head level, its optics ``optics``; heights within
    ``band_m``."""
    samples = surface_samples(scene, spacing_m)
    low = np.maximum(samples.base, band_m[0])
    high = np.minimum(samples.top, band_m[1])
    usable = low <= high
    xy, low, high = samples.xy[usable], low[usable], high[usable]
    swept = np.zeros(xy.shape[0], dtype=bool)
    h = optics.head_height_m
    half_fan = math.radians(optics.fan_deg) / 2.0
    mx, my = optics.mount_xy_m
    for times, azimuths in sweeps:
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        az = np.asarray(azimuths, dtype=np.float64).reshape(-1)
        if t.size == 0:
            continue
        vx, vy, yaw = trajectory.poses(t, unwrapped=True)
        ox = mx + optics.pan_offset_m * np.cos(az)
        oy = my + optics.pan_offset_m * np.sin(az)
        cx = vx + np.cos(yaw) * ox - np.sin(yaw) * oy
        cy = vy + np.sin(yaw) * ox + np.cos(yaw) * oy
        bearing = az + yaw
        gaps = np.abs(np.diff(bearing))
        if gaps.size == 0:
            share = np.zeros(1)
        else:
            left = np.concatenate((gaps[:1], gaps))
            right = np.concatenate((gaps, gaps[-1:]))
            share = 0.25 * (left + right)  # half the mean gap to the neighbours
        for k in range(t.shape[0]):
            dx, dy = xy[:, 0] - cx[k], xy[:, 1] - cy[k]
            d = np.hypot(dx, dy)
            off = np.abs(_wrap(np.arctan2(dy, dx) - bearing[k]))
            near = (~swept) & (off <= share[k]) & (d >= optics.min_range_m)
            near &= d <= optics.max_range_m
            z = np.clip(h, low, high)
            near &= np.abs(np.arctan2(z - h, d)) <= half_fan
            idx = np.flatnonzero(near)
            if idx.size == 0:
                continue
            target = np.column_stack((dx[idx], dy[idx], z[idx] - h))
            length = np.linalg.norm(target, axis=1)
            reach, _ = scene.cast_general(
                np.array([cx[k], cy[k], h]), target / length[:, np.newaxis]
            )
            swept[idx[reach >= length - 0.02]] = True
    out: FloatArray = xy[swept]
    return out


class GridScore(NamedTuple):
    """How a grid's occupied cells match the truth (:func:`score_occupied`)."""

    precision: float
    """Share of occupied cells within the tolerance of a true surface or inside a solid
    obstacle's footprint (NaN: none occupied)."""
    recall: float
    """Share of swept surface samples with an occupied cell within the tolerance (NaN: none
    swept)."""
    occupied: int
    correct: int
    swept: int
    found: int
    tolerance_m: float


def score_occupied(
    scene: Scene, occupied_xy: ArrayLike, swept_xy: ArrayLike, tolerance_m: float
) -> GridScore:
    """Precision and recall of the occupied cells (their centres, ``occupied_xy`` (m, 2), in
    the scene's frame) against the true surfaces and the swept samples ``swept_xy`` (see the
    module)."""
    occ = np.asarray(occupied_xy, dtype=np.float64).reshape(-1, 2)
    truth = np.asarray(swept_xy, dtype=np.float64).reshape(-1, 2)
    right = scene.distance_to_surface_2d(occ) <= tolerance_m
    correct = int(np.count_nonzero(right | inside_solid(scene, occ)))
    found = 0
    if occ.shape[0]:
        for chunk in np.array_split(truth, max(1, truth.shape[0] // 512)):
            if chunk.shape[0] == 0:
                continue
            gap = np.hypot(chunk[:, None, 0] - occ[None, :, 0], chunk[:, None, 1] - occ[None, :, 1])
            found += int(np.count_nonzero(gap.min(axis=1) <= tolerance_m))
    return GridScore(
        correct / occ.shape[0] if occ.shape[0] else math.nan,
        found / truth.shape[0] if truth.shape[0] else math.nan,
        int(occ.shape[0]),
        correct,
        int(truth.shape[0]),
        found,
        float(tolerance_m),
    )
