"""The certainty grid: a 2-D occupancy grid in ``odom``, built from every acquisition as it comes.

What the report built BIRIS for: "the integration of BIRIS range data directly into the certainty
grid which is used for reactive collision avoidance". The grid covers a fixed rectangle of the
``odom`` plane (:attr:`GridParams.extent_m`) in square cells (:attr:`GridParams.resolution_m`);
each cell holds the log-odds of "something stands here", 0 (p = 0.5) until evidence arrives.

**One acquisition, one ray.** BIRIS's laser sheet is vertical and lies in the plane of the head's
azimuth, so every sample of a profile, seen from above, lies on one ray from the optical centre.
An acquisition placed with the vehicle's pose at its own time (a
:class:`~biris_hw.data.PoseLookup`: :class:`~biris_hw.io.pose.PoseBuffer`) is therefore a ray in
``odom`` with the horizontal distances of its returns along it:

* ``source="profile"``: the returns whose height (z in the vehicle frame) lies within
  :attr:`GridParams.band_m`, grouped along the ray into surfaces (sorted by distance, a new
  surface wherever the next return is farther by more than :attr:`GridParams.split_ratio` of its
  distance, and at least a cell). Each surface is one return at its mean distance: the 64 rows
  that see one wall measure one distance, so their mean is far sharper than any of them (the
  range noise is centimetres at 3 m), and a surface a cell wide is not smeared over three.
* ``source="closest"``: the report's 2-D data, the closest sample of the profile
  (``closest_mm``, or a :class:`~biris_hw.data.Point`'s ``range_mm``), taken as lying on the
  optical axis; no height band applies (the closest sample may be the floor's).

**The update** (log-odds, as in Elfes's and Moravec's certainty grids): every cell the ray
crosses from the optical centre up to its nearest surface gets :attr:`GridParams.miss` (free
space), the cell of each surface gets :attr:`GridParams.hit` (occupied), and each cell is
clamped into :attr:`GridParams.clamp`. An acquisition whose profile has no return in the band
clears nothing: BIRIS's "no return" cannot tell open space beyond its range from a dark surface.
The cells a ray crosses are found exactly (:func:`crossed_cells`: the parameters at which the
segment crosses the grid's lines, for all rays at once), with array operations for a whole batch
of acquisitions: a scan (:meth:`CertaintyGrid.add_scan`) or one acquisition as it is read
(:meth:`CertaintyGrid.add_point`). Within a batch a cell's evidence is summed, then clamped.

**Decay** (:attr:`GridParams.half_life_s`): without new evidence a cell's log-odds halves every
half-life, so what a moving robot saw long ago fades back towards unknown. It is applied lazily,
per cell, when the cell is next updated or read, so an update costs the same whatever the
grid's size.

**Out.** :meth:`CertaintyGrid.values` is the grid in ROS's terms (``nav_msgs/msg/OccupancyGrid``:
-1 unknown, else the probability in percent, row-major from the cell at the lower-left corner,
x along a row); :meth:`CertaintyGrid.message` encodes it (:mod:`biris_hw.io.codec`, on
``/biris/grid``, frame ``odom``). :func:`grid_figure` draws it, over the true walls when known.

An acquisition without a pose within the lookup's bounds is never placed: it is counted in
:attr:`CertaintyGrid.unplaced`. docs/moving.md, "The certainty grid", says more.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING, Literal, NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from biris_hw.data import Point, PoseLookup, Scan, VehiclePoses
from biris_hw.geometry import DEFAULT_MOUNT, Mount, sample_elevations
from biris_hw.io import codec

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "DEFAULT_PARAMS",
    "GRID_SOURCES",
    "CertaintyGrid",
    "GridFeeder",
    "GridParams",
    "GridSource",
    "Placed",
    "PoseWait",
    "Rays",
    "StandingPoses",
    "crossed_cells",
    "grid_figure",
    "profile_rays",
    "save_grid",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

GridSource = Literal["profile", "closest"]
GRID_SOURCES: tuple[GridSource, ...] = ("profile", "closest")
"""What an acquisition gives the grid: its profile's returns within the height band, or the
closest sample alone (the report's 2-D data)."""

_RAD_PER_COUNT = 2.0 * math.pi / 4096.0


def _log_odds(p: float) -> float:
    return math.log(p / (1.0 - p))


def _probability(name: str, value: float) -> float:
    number = float(value)
    if not (math.isfinite(number) and 0.0 < number < 1.0):
        raise ValueError(f"{name} must be a probability strictly between 0 and 1, not {value!r}")
    return number


@dataclass(frozen=True)
class GridParams:
    """What a :class:`CertaintyGrid` covers and how it weighs evidence; the defaults suit the
    simulated room and a small indoor robot (docs/moving.md)."""

    resolution_m: float = 0.05
    """Side of a square cell, metres."""
    extent_m: tuple[float, float, float, float] = (-10.0, -10.0, 10.0, 10.0)
    """(x_min, y_min, x_max, y_max) in ``odom``, metres: the lower-left corner is the grid's
    origin; x_max and y_max are rounded up to whole cells."""
    band_m: tuple[float, float] = (0.1, 2.0)
    """Heights (z in the vehicle frame, metres; the floor is z = 0 when the vehicle frame's
    origin is on it) of the profile's returns that count: above what the robot rolls over and
    the floor's own returns, below a door's lintel."""
    hit: float = 0.7
    """Probability that a cell holding a surface's return is occupied (log-odds added)."""
    miss: float = 0.4
    """Probability that a cell a ray crossed before its first surface is occupied."""
    clamp: tuple[float, float] = (0.12, 0.97)
    """Probabilities a cell's belief is held within, so that it can change its mind (a door
    that opens) after a bounded number of contrary updates."""
    occupied: float = 0.65
    """A cell at or above this probability is occupied (:meth:`CertaintyGrid.occupied`)."""
    half_life_s: float | None = None
    """Hardware seconds over which a cell's log-odds halves without new evidence; None: never."""
    split_ratio: float = 0.05
    """A profile's returns farther apart along the ray than this share of their distance (and
    than a cell) are two surfaces (``source="profile"``)."""
    max_range_m: float | None = None
    """Surfaces farther than this from the optical centre are left out (None: all)."""
    join_m: float | None = 0.3
    """The nearest surfaces of two consecutive acquisitions (at most :attr:`join_s` apart) that
    lie within this distance of each other are taken for one surface, and the cells between
    them are occupied too (None: never): a sweep's acquisitions are degrees apart, tens of
    centimetres on a wall 3 m away, and a wall is not a dotted line. A doorway or the gap
    between two objects wider than this stays open."""
    join_s: float = 0.1
    """Longest time between two acquisitions joined: consecutive ones of a sweep (33 ms apart
    at 30 Hz, 50 ms at 20 Hz), not the end of one sweep and the start of the next."""

    def __post_init__(self) -> None:
        res = float(self.resolution_m)
        if not (math.isfinite(res) and res > 0.0):
            raise ValueError(f"resolution_m must be a positive number, not {self.resolution_m!r}")
        extent = tuple(float(v) for v in self.extent_m)
        if len(extent) != 4 or not all(math.isfinite(v) for v in extent):
            raise ValueError(f"extent_m must be four finite numbers, not {self.extent_m!r}")
        if not (extent[2] > extent[0] and extent[3] > extent[1]):
            raise ValueError(f"extent_m must be (x_min, y_min, x_max, y_max), not {extent!r}")
        cells = math.ceil((extent[2] - extent[0]) / res - 1e-9) * math.ceil(
            (extent[3] - extent[1]) / res - 1e-9
        )
        if cells > 64_000_000:
            raise ValueError(f"extent_m / resolution_m makes {cells} cells: at most 64 million")
        band = tuple(float(v) for v in self.band_m)
        if len(band) != 2 or not all(math.isfinite(v) for v in band) or not band[1] > band[0]:
            raise ValueError(f"band_m must be (low, high) with high > low, not {self.band_m!r}")
        hit = _probability("hit", self.hit)
        miss = _probability("miss", self.miss)
        if not (hit > 0.5 > miss):
            raise ValueError(f"hit must be above 0.5 and miss below it, not {hit!r}, {miss!r}")
        clamp = tuple(_probability("clamp", v) for v in self.clamp)
        if len(clamp) != 2 or not (clamp[0] < 0.5 < clamp[1]):
            raise ValueError(f"clamp must be (low < 0.5, high > 0.5), not {self.clamp!r}")
        occupied = _probability("occupied", self.occupied)
        if self.half_life_s is not None:
            half = float(self.half_life_s)
            if not (math.isfinite(half) and half > 0.0):
                raise ValueError(f"half_life_s must be positive or None, not {self.half_life_s!r}")
            object.__setattr__(self, "half_life_s", half)
        split = float(self.split_ratio)
        if not (math.isfinite(split) and split > 0.0):
            raise ValueError(f"split_ratio must be a positive number, not {self.split_ratio!r}")
        if self.join_m is not None:
            join = float(self.join_m)
            if not (math.isfinite(join) and join > 0.0):
                raise ValueError(f"join_m must be positive or None, not {self.join_m!r}")
            object.__setattr__(self, "join_m", join)
        join_s = float(self.join_s)
        if not (math.isfinite(join_s) and join_s > 0.0):
            raise ValueError(f"join_s must be a positive number of seconds, not {self.join_s!r}")
        object.__setattr__(self, "join_s", join_s)
        if self.max_range_m is not None:
            reach = float(self.max_range_m)
            if not (math.isfinite(reach) and reach > 0.0):
                raise ValueError(f"max_range_m must be positive or None, not {self.max_range_m!r}")
            object.__setattr__(self, "max_range_m", reach)
        for name, value in (
            ("resolution_m", res),
            ("extent_m", extent),
            ("band_m", band),
            ("hit", hit),
            ("miss", miss),
            ("clamp", clamp),
            ("occupied", occupied),
            ("split_ratio", split),
        ):
            object.__setattr__(self, name, value)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns): (cells along y, cells along x)."""
        x0, y0, x1, y1 = self.extent_m
        res = self.resolution_m
        return (math.ceil((y1 - y0) / res - 1e-9), math.ceil((x1 - x0) / res - 1e-9))

    @property
    def origin_m(self) -> tuple[float, float]:
        """The lower-left corner of cell (0, 0) in ``odom``."""
        return (self.extent_m[0], self.extent_m[1])


DEFAULT_PARAMS = GridParams()


class Rays(NamedTuple):
    """Acquisitions as rays in ``odom``: where each starts, which way it points, and the
    distances of its surfaces along it (what :meth:`CertaintyGrid.integrate` takes)."""

    t: FloatArray
    """(n,) the acquisitions' hardware times."""
    origin: FloatArray
    """(n, 2) the optical centre in ``odom``, metres."""
    heading: FloatArray
    """(n,) the ray's direction in ``odom``, radians counter-clockwise from x."""
    distance: FloatArray
    """(n, k) each surface's horizontal distance from the origin, metres, nearest first; NaN
    pads a ray with fewer surfaces (a ray with none clears nothing)."""


class Placed(NamedTuple):
    """What one update did."""

    placed: int
    """Acquisitions put in the grid."""
    unplaced: int
    """Acquisitions left out: no vehicle pose within the lookup's bounds at their time."""


class StandingPoses:
    """A :class:`~biris_hw.data.PoseLookup` for a vehicle that never moves: at the ``odom``
    origin facing x at every time (so ``odom`` is the vehicle frame). For a sensor on a fixed
    stand, or a recording made on one, which carries no poses."""

    def poses_at(self, times: ArrayLike) -> VehiclePoses:
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        zero = np.zeros(t.shape[0])
        return VehiclePoses(t.copy(), zero, zero.copy(), zero.copy(), np.ones(t.shape[0], bool))


def _surfaces(distance: FloatArray, split_ratio: float, min_gap: float) -> FloatArray:
    """Per row of ``distance`` (n, s; NaN for none), the mean distance of each surface: the
    sorted values split wherever the next is farther by more than ``split_ratio`` of it (and
    ``min_gap``). (n, k) nearest first, NaN-padded; all rows at once."""
    n = distance.shape[0]
    d = np.sort(distance, axis=1)  # NaN sorts last
    valid = np.isfinite(d)
    if not valid.any():
        return np.full((n, 0), np.nan)
    gap = np.diff(d, axis=1)
    with np.errstate(invalid="ignore"):
        new = np.concatenate(
            (valid[:, :1], valid[:, 1:] & ~(gap <= np.maximum(split_ratio * d[:, 1:], min_gap))),
            axis=1,
        )
    surface = np.cumsum(new, axis=1) - 1  # index of each return's surface within its row
    k = int(surface.max()) + 1
    rows = np.broadcast_to(np.arange(n)[:, np.newaxis], d.shape)
    label = rows[valid] * k + surface[valid]
    counts = np.bincount(label, minlength=n * k)
    sums = np.bincount(label, weights=d[valid], minlength=n * k)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return means.reshape(n, k)


def _per_acquisition(name: str, value: ArrayLike, n: int) -> FloatArray:
    """``value`` as (n,) float64: one per acquisition, or one for all."""
    array = np.asarray(value, dtype=np.float64).reshape(-1)
    if array.shape[0] == n:
        return array
    if array.shape[0] == 1:
        return np.full(n, array[0])
    raise ValueError(f"{name} must be one value or one per acquisition ({n}), not {array.shape[0]}")


@functools.cache
def _row_slopes(samples: int) -> FloatArray:
    """tan of each row's angle to the optical axis (geometry.sample_elevations), cached."""
    slopes: FloatArray = np.tan(sample_elevations(samples))
    slopes.flags.writeable = False
    return slopes


def profile_rays(
    range_mm: ArrayLike,
    azimuth_counts: ArrayLike,
    elevation_counts: ArrayLike,
    closest_mm: ArrayLike,
    poses: VehiclePoses,
    mount: Mount | None = None,
    *,
    source: GridSource = "profile",
    params: GridParams = DEFAULT_PARAMS,
) -> Rays:
    """Acquisitions (``range_mm`` (n, samples), azimuths and elevations in counts, one per
    acquisition or one for all, ``closest_mm`` (n,)) as :class:`Rays` in ``odom``, each placed
    with its pose in ``poses`` (all valid: the caller leaves out those without one). See the
    module for the two sources.

    The geometry is :func:`biris_hw.geometry.project_profiles`'s, restricted to the vertical
    plane of the ray: sample k at depth r (along the optical axis, tilted by the elevation e)
    lies ``r (cos e - tan a_k sin e)`` from the optical centre along the azimuth and ``r (sin e
    + tan a_k cos e)`` above it, a_k being its row's angle (``tests/test_grid.py`` holds the two
    to each other)."""
    m = DEFAULT_MOUNT if mount is None else mount
    r = np.asarray(range_mm)
    n = r.shape[0]
    az = _per_acquisition("azimuth_counts", azimuth_counts, n) * _RAD_PER_COUNT
    el = _per_acquisition("elevation_counts", elevation_counts, n) * _RAD_PER_COUNT
    ca, sa = np.cos(az), np.sin(az)
    # the optical centre in the vehicle frame: the pan axis's foot, out along the azimuth
    cx = m.offset_m[0] + m.head_offset_m * ca
    cy = m.offset_m[1] + m.head_offset_m * sa
    if source == "profile":
        if r.ndim != 2:
            raise ValueError(f"range_mm must be (n, samples), not shape {r.shape}")
        depth = np.where(r > 0, r * 0.001, np.nan)
        slope = _row_slopes(r.shape[1])[np.newaxis, :]
        ce, se = np.cos(el)[:, np.newaxis], np.sin(el)[:, np.newaxis]
        z = depth * (se + slope * ce) + (m.offset_m[2] + m.head_height_m)
        low, high = params.band_m
        with np.errstate(invalid="ignore"):
            inside = (z >= low) & (z <= high)
        along = np.where(inside, depth * (ce - slope * se), np.nan)
        distance = _surfaces(along, params.split_ratio, params.resolution_m)
    elif source == "closest":
        near = np.asarray(closest_mm, dtype=np.float64).reshape(n, 1) * 0.001
        distance = np.where(near > 0.0, near * np.cos(el)[:, np.newaxis], np.nan)
    else:
        raise ValueError(f"source must be one of {GRID_SOURCES}, not {source!r}")
    if params.max_range_m is not None:
        with np.errstate(invalid="ignore"):
            distance = np.where(distance <= params.max_range_m, distance, np.nan)
    yaw = np.asarray(poses.yaw_rad, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    origin = np.empty((n, 2))
    origin[:, 0] = poses.x_m + c * cx - s * cy
    origin[:, 1] = poses.y_m + s * cx + c * cy
    return Rays(np.asarray(poses.t, dtype=np.float64), origin, az + yaw, distance)


def crossed_cells(
    u0: ArrayLike, v0: ArrayLike, u1: ArrayLike, v1: ArrayLike
) -> tuple[IntArray, IntArray, IntArray]:
    """Every cell each segment (u0, v0) -> (u1, v1) crosses, in cell units (cell (i, j) is
    [i, i+1) x [j, j+1)), in order from the start, each once: (segment index, i, j).

    Exact, not sampled: a segment enters a new cell wherever it crosses a grid line, so the
    parameters of those crossings (for every segment at once: one flat array, sorted per
    segment, with its two ends) cut it into pieces, one per cell, and each piece's midpoint
    names its cell. A piece of zero length (a crossing exactly through a grid corner) names
    none; a segment of zero length is one piece: the cell it sits in.
    """
    ends = np.array((u0, u1, v0, v1), dtype=np.float64).reshape(4, -1)
    a0, a1, b0, b1 = ends
    k = a0.shape[0]
    du, dv = a1 - a0, b1 - b0
    # both axes at once: entry e < k is segment e's x lines, entry k + e its y lines
    first = np.floor(np.concatenate((a0, b0)))
    last = np.floor(np.concatenate((a1, b1)))
    start = np.concatenate((a0, b0))
    step = np.concatenate((du, dv))
    count = np.abs(last - first).astype(np.intp)  # grid lines crossed: min+1 .. max
    entry = np.repeat(np.arange(2 * k), count)
    line = np.arange(entry.shape[0]) - np.repeat(np.cumsum(count) - count - 1, count)
    line = line + np.minimum(first, last)[entry]
    with np.errstate(invalid="ignore", divide="ignore"):
        # within [0, 1]: a segment that starts on a line must not cross it a rounding error
        # before its start
        crossing = np.clip((line - start[entry]) / step[entry], 0.0, 1.0)
    every = np.arange(k)
    seg = np.concatenate((every, every, entry % k if k else entry))  # its ends at 0 and 1
    param = np.concatenate((np.zeros(k), np.ones(k), crossing))
    order = np.argsort(2.0 * seg + param, kind="stable")  # by segment, then along it
    seg, param = seg[order], param[order]
    # the pieces between consecutive parameters; one shorter than a billionth of a cell is a
    # rounding error at a grid corner (its midpoint would name a cell the segment only grazes)
    length = np.hypot(du, dv)
    piece = param[1:] - param[:-1]
    same = seg[1:] == seg[:-1]
    reach = length[seg[:-1]]
    keep = same & (piece > 0.0) & ((piece * reach > 1e-9) | (reach == 0.0))
    mid = 0.5 * (param[1:] + param[:-1])[keep]
    which = seg[:-1][keep]
    ci = np.floor(a0[which] + mid * du[which]).astype(np.intp)
    cj = np.floor(b0[which] + mid * dv[which]).astype(np.intp)
    return which, ci, cj


class CertaintyGrid:
    """A log-odds occupancy grid of the ``odom`` plane (see the module).

    Thread-safe: a feed's thread may update it while another reads :meth:`values`.
    """

    def __init__(self, params: GridParams = DEFAULT_PARAMS) -> None:
        if not isinstance(params, GridParams):
            raise TypeError(f"params must be a GridParams, not {type(params).__name__}")
        self.params = params
        rows, cols = params.shape
        self._rows, self._cols = rows, cols
        self._res = params.resolution_m
        self._x0, self._y0 = params.origin_m
        self._hit = _log_odds(params.hit)
        self._miss = _log_odds(params.miss)
        self._low = _log_odds(params.clamp[0])
        self._high = _log_odds(params.clamp[1])
        self._threshold = _log_odds(params.occupied)
        self._rate = None if params.half_life_s is None else math.log(2.0) / params.half_life_s
        self._lo = np.zeros(rows * cols, dtype=np.float64)
        self._seen = np.zeros(rows * cols, dtype=bool)
        self._stamp = np.zeros(rows * cols, dtype=np.float64) if self._rate else None
        self._lock = threading.Lock()
        self._last = (-math.inf, math.nan, math.nan)  # the last acquisition's nearest surface
        self.acquisitions = 0
        """Acquisitions placed in the grid."""
        self.unplaced = 0
        """Acquisitions left out: no vehicle pose at their time (never placed by a guess)."""
        self.outside = 0
        """Surfaces that fell outside the grid's extent (their rays still clear what is in)."""
        self.t = -math.inf
        """The newest acquisition's hardware time (-inf before the first)."""

    # -- geometry ------------------------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns): row r covers y from ``y_min + r res``, column c x from ``x_min + c
        res`` (ROS's layout: row-major from the lower-left cell)."""
        return (self._rows, self._cols)

    @property
    def resolution_m(self) -> float:
        return self._res

    @property
    def origin_m(self) -> tuple[float, float]:
        """The lower-left corner of cell (0, 0) in ``odom``."""
        return (self._x0, self._y0)

    def cell_of(self, xy: ArrayLike) -> tuple[IntArray, IntArray]:
        """(row, column) of the cell holding each (x, y) of ``xy`` (m, 2) in ``odom``; cells
        outside the grid are outside ``shape``."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        col = np.floor((p[:, 0] - self._x0) / self._res).astype(np.intp)
        row = np.floor((p[:, 1] - self._y0) / self._res).astype(np.intp)
        return row, col

    def centres(self, rows: ArrayLike, cols: ArrayLike) -> FloatArray:
        """(m, 2) ``odom`` x, y of the centres of the cells (rows[i], cols[i])."""
        r = np.asarray(rows, dtype=np.float64)
        c = np.asarray(cols, dtype=np.float64)
        return np.column_stack((self._x0 + (c + 0.5) * self._res, self._y0 + (r + 0.5) * self._res))

    # -- feeding it ----------------------------------------------------------------------------

    def add_scan(self, scan: Scan, poses: PoseLookup, *, source: GridSource = "profile") -> Placed:
        """Every acquisition of ``scan``, each placed with the vehicle's pose at its own time
        ``scan.t[k]`` (one batch)."""
        return self.add_acquisitions(
            scan.range_mm, scan.azimuth, scan.elevation, scan.closest_mm, scan.t, poses,
            scan.mount, source=source,
        )  # fmt: skip

    def add_point(self, point: Point, poses: PoseLookup, *, source: GridSource = "profile") -> bool:
        """One acquisition as it is read (a :class:`~biris_hw.data.Point`); False (and counted
        in :attr:`unplaced`) if the vehicle's pose at its time is not known."""
        done = self.add_points((point,), poses, source=source)
        return done.placed == 1

    def add_points(
        self, points: Sequence[Point], poses: PoseLookup, *, source: GridSource = "profile"
    ) -> Placed:
        """Acquisitions as read, in one batch (what a feed hands a sink at a time). Points
        of one batch must share one profile length; their mounts are the first's."""
        if not points:
            return Placed(0, 0)
        samples = points[0].profile.shape[0]
        if any(p.profile.shape[0] != samples for p in points):
            raise ValueError("points of one batch must have profiles of one length")
        fields = np.array(
            [(p.azimuth, p.elevation, p.range_mm, p.t) for p in points], dtype=np.float64
        )
        profiles = points[0].profile[np.newaxis, :] if len(points) == 1 else None
        return self.add_acquisitions(
            np.stack([p.profile for p in points]) if profiles is None else profiles,
            fields[:, 0],
            fields[:, 1],
            fields[:, 2],
            fields[:, 3],
            poses,
            points[0].mount,
            source=source,
        )

    def add_acquisitions(
        self,
        range_mm: ArrayLike,
        azimuth_counts: ArrayLike,
        elevation_counts: ArrayLike,
        closest_mm: ArrayLike,
        t: ArrayLike,
        poses: PoseLookup,
        mount: Mount | None = None,
        *,
        source: GridSource = "profile",
    ) -> Placed:
        """The common path of :meth:`add_scan` and :meth:`add_points`: acquisitions as arrays
        (``range_mm`` (n, samples), the rest (n,)), placed with ``poses.poses_at(t)``."""
        if source not in GRID_SOURCES:
            raise ValueError(f"source must be one of {GRID_SOURCES}, not {source!r}")
        r = np.asarray(range_mm)
        times = np.asarray(t, dtype=np.float64).reshape(-1)
        if r.ndim != 2 or r.shape[0] != times.shape[0]:
            raise ValueError(f"range_mm must be (n, samples) for {times.shape[0]} times")
        at = poses.poses_at(times)
        ok = np.asarray(at.valid, dtype=bool)
        n = ok.shape[0]
        az = _per_acquisition("azimuth_counts", azimuth_counts, n)
        el = _per_acquisition("elevation_counts", elevation_counts, n)
        near = _per_acquisition("closest_mm", closest_mm, n)
        missing = int(n - np.count_nonzero(ok))
        if missing:
            keep = np.flatnonzero(ok)
            at = VehiclePoses(at.t[keep], at.x_m[keep], at.y_m[keep], at.yaw_rad[keep], ok[keep])
            r, az, el, near = r[keep], az[keep], el[keep], near[keep]
        rays = profile_rays(r, az, el, near, at, mount, source=source, params=self.params)
        with self._lock:
            self.unplaced += missing
        self.integrate(rays)
        return Placed(int(at.t.shape[0]), missing)

    def integrate(self, rays: Rays) -> None:
        """Put :class:`Rays` in the grid (one batch, in time order): free space along each ray
        up to its nearest surface, a return at every surface and along the joins between
        neighbouring acquisitions' nearest surfaces (the module's update)."""
        t = np.asarray(rays.t, dtype=np.float64).reshape(-1)
        n = t.shape[0]
        if n == 0:
            return
        origin = np.asarray(rays.origin, dtype=np.float64).reshape(n, 2)
        heading = np.asarray(rays.heading, dtype=np.float64).reshape(n)
        dist = np.asarray(rays.distance, dtype=np.float64).reshape(n, -1)
        res = self._res
        cols, ncell = self._cols, self._rows * self._cols
        du, dv = np.cos(heading) / res, np.sin(heading) / res
        u0 = (origin[:, 0] - self._x0) / res
        v0 = (origin[:, 1] - self._y0) / res
        # the surfaces, in cell units: (acquisition, u, v)
        has = np.isfinite(dist)
        ray_of = np.nonzero(has)[0]
        d = dist[has]
        hu = u0[ray_of] + d * du[ray_of]
        hv = v0[ray_of] + d * dv[ray_of]
        # segments: each ray up to its nearest surface (free), and each join (occupied)
        nearest = dist[:, 0] if dist.shape[1] else np.full(n, np.nan)
        end_u, end_v = u0 + nearest * du, v0 + nearest * dv
        free = np.flatnonzero(np.isfinite(nearest))
        pair, ju0, jv0 = self._joins(t, end_u, end_v)
        seg, ci, cj = crossed_cells(
            np.concatenate((u0[free], ju0)),
            np.concatenate((v0[free], jv0)),
            np.concatenate((end_u[free], end_u[pair])),
            np.concatenate((end_v[free], end_v[pair])),
        )
        nfree = free.shape[0]
        # a free ray's last cell holds its nearest surface: not free
        last = np.ones(seg.shape[0], dtype=bool)
        last[:-1] = seg[1:] != seg[:-1]
        is_free = seg < nfree
        take = ~(is_free & last)
        owner = np.concatenate((free, pair))  # the acquisition each segment belongs to
        acq = np.concatenate((ray_of, owner[seg[take]]))
        col = np.concatenate((np.floor(hu).astype(np.intp), ci[take]))
        row = np.concatenate((np.floor(hv).astype(np.intp), cj[take]))
        kind = np.concatenate((np.zeros(ray_of.shape[0], np.intp), is_free[take].astype(np.intp)))
        ok = (col >= 0) & (col < cols) & (row >= 0) & (row < self._rows)
        # one word per acquisition and cell: a return outranks free space (kind 0 sorts first)
        key = np.unique(((acq * ncell + row * cols + col) * 2 + kind)[ok])
        first = np.ones(key.shape[0], dtype=bool)
        first[1:] = (key[1:] >> 1) != (key[:-1] >> 1)
        key = key[first]
        cells = (key >> 1) % ncell
        delta = np.where(key & 1, self._miss, self._hit)
        outside = int(np.count_nonzero(~ok[: ray_of.shape[0]]))
        with self._lock:
            newest = max(self.t, float(t.max()))
            if self._rate is not None:  # each entry's evidence faded to the batch's newest time
                which = (key >> 1) // ncell
                delta = delta * np.exp(-self._rate * np.maximum(newest - t[which], 0.0))
            if n == 1:  # one acquisition says one thing per cell: nothing to sum
                touched, total = cells, delta
            else:
                touched, slot = np.unique(cells, return_inverse=True)
                total = np.bincount(slot, weights=delta, minlength=touched.shape[0])
            lo = self._lo[touched]
            if self._stamp is not None and self._rate is not None:
                age = np.maximum(newest - self._stamp[touched], 0.0)
                lo = lo * np.exp(-self._rate * age)
                self._stamp[touched] = newest
            self._lo[touched] = np.clip(lo + total, self._low, self._high)
            self._seen[touched] = True
            self.acquisitions += n
            self.outside += outside
            self.t = newest

    def _joins(
        self, t: FloatArray, end_u: FloatArray, end_v: FloatArray
    ) -> tuple[IntArray, FloatArray, FloatArray]:
        """The joins of this batch (:attr:`GridParams.join_m`): for each, the acquisition it
        ends at and where it starts (the previous acquisition's nearest surface, in cell
        units); the batch's last acquisition is remembered for the next batch's first."""
        join = self.params.join_m
        with self._lock:
            last = self._last
            self._last = (float(t[-1]), float(end_u[-1]), float(end_v[-1]))
        if join is None:
            return np.zeros(0, np.intp), np.zeros(0), np.zeros(0)
        tt = np.concatenate(([last[0]], t))
        uu = np.concatenate(([last[1]], end_u))
        vv = np.concatenate(([last[2]], end_v))
        dt = tt[1:] - tt[:-1]
        gap = np.hypot(uu[1:] - uu[:-1], vv[1:] - vv[:-1]) * self._res
        with np.errstate(invalid="ignore"):
            pair = np.flatnonzero((dt > 0.0) & (dt <= self.params.join_s) & (gap <= join))
        return pair, uu[pair], vv[pair]

    # -- reading it ----------------------------------------------------------------------------

    def log_odds(self, t: float | None = None) -> FloatArray:
        """(rows, columns) log-odds, decayed to hardware time ``t`` (None: the newest
        acquisition's); 0 where nothing is known."""
        with self._lock:
            lo = self._lo.copy()
            stamp = None if self._stamp is None else self._stamp.copy()
            newest = self.t
        if self._rate is not None and stamp is not None:
            when = newest if t is None else float(t)
            if math.isfinite(when):
                lo *= np.exp(-self._rate * np.maximum(when - stamp, 0.0))
        out: FloatArray = lo.reshape(self._rows, self._cols)
        return out

    def probabilities(self, t: float | None = None) -> FloatArray:
        """(rows, columns) probability that each cell is occupied (0.5: nothing known)."""
        return 1.0 / (1.0 + np.exp(-self.log_odds(t)))

    def known(self) -> NDArray[np.bool_]:
        """(rows, columns): True where some acquisition has said something."""
        with self._lock:
            known: NDArray[np.bool_] = self._seen.reshape(self._rows, self._cols).copy()
        return known

    def occupied(self, t: float | None = None) -> NDArray[np.bool_]:
        """(rows, columns): True where the cell's probability is at least
        :attr:`GridParams.occupied`."""
        occupied: NDArray[np.bool_] = self.log_odds(t) >= self._threshold
        return occupied

    def occupied_xy(self, t: float | None = None) -> FloatArray:
        """(m, 2) ``odom`` centres of the occupied cells."""
        rows, cols = np.nonzero(self.occupied(t))
        return self.centres(rows, cols)

    def values(self, t: float | None = None) -> NDArray[np.int8]:
        """(rows, columns) int8 in ``nav_msgs/msg/OccupancyGrid``'s terms: -1 where nothing
        is known (never observed, or decayed to under 1 % of the clamp), else the
        probability of occupancy in percent, 0..100."""
        lo = self.log_odds(t)
        out = np.rint(100.0 / (1.0 + np.exp(-lo))).astype(np.int8)
        unknown = ~self.known()
        if self._rate is not None:
            unknown |= np.abs(lo) < 0.01 * min(-self._low, self._high)
        out[unknown] = -1
        return out

    def message(self, t: float | None = None, topic: str = codec.GRID_TOPIC) -> codec.Encoded:
        """The grid as a ``nav_msgs/msg/OccupancyGrid`` in ``odom``, stamped ``t`` (None: the
        newest acquisition's time), ready to publish or record (:mod:`biris_hw.io.codec`)."""
        when = self.t if t is None else float(t)
        stamp = when if math.isfinite(when) else 0.0
        return codec.occupancy_grid_message(
            self.values(t), self._res, self.origin_m, stamp, topic=topic
        )


class _PoseSpan(Protocol):
    """A pose lookup that also says which times it holds: :class:`~biris_hw.io.pose.PoseBuffer`."""

    def poses_at(self, times: ArrayLike) -> VehiclePoses: ...

    def span(self) -> tuple[float, float] | None: ...


class PoseWait:
    """Live acquisitions waiting for the vehicle's pose at their time: the rule of every feeder
    (:class:`GridFeeder`, :class:`~biris_hw.io.proximity.ProximityFeeder`).

    A live acquisition often arrives before the pose of its time (a base publishes at 50 Hz,
    BIRIS at 30 Hz): it waits, up to ``wait_s`` hardware seconds behind the newest
    acquisition, until ``poses`` holds a sample at or after its time. Then it is ready: placed
    with its pose, or, if the pose is still unknown (a gap in the stream), left to the feeder to
    count as unplaced.
    """

    def __init__(self, poses: _PoseSpan, wait_s: float = 0.5) -> None:
        if not (math.isfinite(wait_s) and wait_s >= 0.0):
            raise ValueError(f"wait_s must be a number of seconds >= 0, not {wait_s!r}")
        self.poses = poses
        self.wait_s = float(wait_s)
        self._pending: list[Point] = []

    @property
    def pending(self) -> int:
        """Acquisitions waiting for the pose of their time."""
        return len(self._pending)

    def take(self, points: Iterable[Point], *, flush: bool = False) -> tuple[list[Point], float]:
        """Take ``points`` in; the waiting acquisitions that are ready now (all of them with
        ``flush``: the end of a stream), oldest first as they came, and the newest pose time
        held (-inf: none), by which the caller tells a placed one from an unplaced one."""
        self._pending.extend(points)
        span = self.poses.span() if self._pending else None
        newest_pose = -math.inf if span is None else span[1]
        if flush:
            ready, self._pending = self._pending, []
            return ready, newest_pose
        if not self._pending:
            return [], newest_pose
        given_up = max(p.t for p in self._pending) - self.wait_s
        done = [p.t <= newest_pose or p.t < given_up for p in self._pending]
        ready = [p for p, d in zip(self._pending, done, strict=True) if d]
        if ready:
            self._pending = [p for p, d in zip(self._pending, done, strict=True) if not d]
        return ready, newest_pose


class GridFeeder:
    """Feeds a :class:`CertaintyGrid` the acquisitions of a live stream, as a feed's sink does.

    A live acquisition often arrives before the pose of its time (a base publishes at 50 Hz,
    BIRIS at 30 Hz): it waits, up to ``wait_s`` hardware seconds behind the newest
    acquisition, until ``poses`` holds a sample at or after its time; then it is placed, or, if
    the pose is still unknown (a gap in the stream), counted as unplaced. Acquisitions are put
    in the grid in batches (:meth:`add`); :meth:`due` says when the next message is owed at
    ``rate_hz`` (a few Hz: a grid is tens of kilobytes).
    """

    def __init__(
        self,
        grid: CertaintyGrid,
        poses: _PoseSpan,
        *,
        source: GridSource = "profile",
        wait_s: float = 0.5,
        rate_hz: float = 2.0,
    ) -> None:
        waiting = PoseWait(poses, wait_s)
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate_hz must be positive, not {rate_hz!r}")
        if source not in GRID_SOURCES:
            raise ValueError(f"source must be one of {GRID_SOURCES}, not {source!r}")
        self.grid = grid
        self.poses = poses
        self.source: GridSource = source
        self.wait_s = waiting.wait_s
        self.period_s = 1.0 / float(rate_hz)
        self._waiting = waiting
        self._next = -math.inf

    @property
    def pending(self) -> int:
        """Acquisitions waiting for the pose of their time."""
        return self._waiting.pending

    def add(self, points: Iterable[Point]) -> Placed:
        """Take acquisitions in; place every waiting one whose pose can be known now."""
        ready, _ = self._waiting.take(points)
        if not ready:
            return Placed(0, 0)
        return self.grid.add_points(ready, self.poses, source=self.source)

    def flush(self) -> Placed:
        """Place whatever waits, as it stands (at the end of a stream)."""
        ready, _ = self._waiting.take((), flush=True)
        return self.grid.add_points(ready, self.poses, source=self.source)

    def due(self, t: float) -> bool:
        """True (once per period) when a message is owed at hardware time ``t``."""
        if t < self._next:
            return False
        self._next = t + self.period_s
        return True


# -- drawing ---------------------------------------------------------------------------------------

_UNKNOWN_COLOUR = "#d4e1f0"
"""Unknown cells: a pale blue, so that they are not read as the grey of a half-certain cell."""


def grid_figure(
    grid: CertaintyGrid,
    outline: Sequence[NDArray[np.floating]] | None = None,
    *,
    path_xy: NDArray[np.floating] | None = None,
    title: str | None = None,
    margin_m: float = 0.5,
) -> Figure:
    """The grid (white free, black occupied, pale blue unknown), over the true walls (``outline``:
    polylines, e.g. a simulated scene's ``outline_2d()``) and the vehicle's path (``path_xy``,
    (m, 2)) when given, cropped to what is known (and the walls) plus ``margin_m``. Made with
    matplotlib's object API (no pyplot, no display), unsaved (:func:`save_grid` saves)."""
    from matplotlib.figure import Figure

    values = grid.values()
    shown = np.where(values < 0, np.nan, values.astype(np.float64))
    fig = Figure(figsize=(7.0, 6.5), layout="constrained")
    ax = fig.add_subplot()
    x0, y0 = grid.origin_m
    res = grid.resolution_m
    rows, cols = grid.shape
    from matplotlib import colormaps

    cmap = colormaps["gray_r"].with_extremes(bad=_UNKNOWN_COLOUR)
    image = ax.imshow(
        shown, origin="lower", cmap=cmap, vmin=0.0, vmax=100.0, interpolation="nearest",
        extent=(x0, x0 + cols * res, y0, y0 + rows * res),
    )  # fmt: skip
    fig.colorbar(image, ax=ax, shrink=0.8, label="occupancy (%); pale blue: unknown")
    chunks: list[FloatArray] = []
    for i, line in enumerate(outline or []):
        xy = np.asarray(line, dtype=np.float64)
        chunks.append(xy[:, :2])
        ax.plot(
            xy[:, 0], xy[:, 1], color="tab:red", lw=1.0, alpha=0.8,
            label="true walls" if i == 0 else None,
        )  # fmt: skip
    if path_xy is not None and len(path_xy):
        p = np.asarray(path_xy, dtype=np.float64)
        chunks.append(p[:, :2])
        ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=1.0, ls="--", label="vehicle path")
    known_rows, known_cols = np.nonzero(values >= 0)
    if known_rows.size:
        chunks.append(grid.centres(known_rows, known_cols))
    if chunks:
        every = np.vstack(chunks)
        lo, hi = every.min(axis=0) - margin_m, every.max(axis=0) + margin_m
        ax.set_xlim(float(lo[0]), float(hi[0]))
        ax.set_ylim(float(lo[1]), float(hi[1]))
    ax.set_aspect("equal")
    ax.set_xlabel("x in odom (m)")
    ax.set_ylabel("y in odom (m)")
    ax.set_title(
        title or f"certainty grid, {100 * res:g} cm cells: {grid.acquisitions} acquisitions"
    )
    if outline or path_xy is not None:
        ax.legend(loc="upper right", fontsize="small")
    return fig


def save_grid(
    path: str | PathLike[str],
    grid: CertaintyGrid,
    outline: Sequence[NDArray[np.floating]] | None = None,
    *,
    path_xy: NDArray[np.floating] | None = None,
    title: str | None = None,
) -> Path:
    """:func:`grid_figure` saved to ``path`` (its suffix picks the format: .png, .svg, .pdf)."""
    target = Path(path)
    grid_figure(grid, outline, path_xy=path_xy, title=title).savefig(target, dpi=110)
    return target
