"""From BIRIS range profiles to 3-D points: the sensor's fan, the pan/tilt head and its mount.

The report's server handed out polar data only (range against azimuth) and promised "full 3-D
data" for the next version; this module is that step, kept apart from the server so that a
client can turn any :class:`~biris_hw.data.Scan` or :class:`~biris_hw.data.Point` into points
without talking to a server (reference notes, section 4.1).

**The fan.** BIRIS projects a vertical laser sheet with a 22 degree dispersion (the report's
introduction); each of the N samples of a profile is one CCD row, row k (top first) looking at
``e_k = (FAN_DEG/2) (1 - (2k+1)/N)`` above the optical axis, the centre of its row. BIRIS ranges
are *depth along the optical axis*, not slant distance (README.md, "Python API"), so sample k at
range r lies at ``(r, 0, r tan e_k)`` in the head's own frame: x along the optical axis, z up.

**The head.** The tilt axis (elevation) is horizontal and passes through the optical centre;
positive elevation looks up. The pan axis (azimuth) is vertical; positive azimuth turns
counter-clockwise seen from above (REP 103) and 0 is dead ahead. The optical centre sits
``head_height_m`` up the pan axis from the point where the pan axis meets the mount, and
``head_offset_m`` out from the pan axis along the azimuth (0 on the simulated head).

**Frames** (x forward, y left, z up in both):

* ``"sensor"`` -- centred on the pan axis at the height of the optical centre, not turning with
  the head: the point after the tilt and pan rotations (and the optical centre's offset from the
  pan axis, which turns with the azimuth), before the mount. With ``head_offset_m`` = 0 its
  origin is the optical centre.
* ``"vehicle"`` -- the sensor frame moved by the mount: ``mount_offset_m`` is where the pan
  axis's foot sits in the vehicle frame, and the optical centre is ``head_height_m`` above it.
  On the simulator (mount offset 0) the vehicle frame is the scene's world frame: the pan axis
  is the world's z axis and the floor is z = 0.

Samples with no return (range 0) are left out of point lists; the grid form keeps them as NaN
rows so that row k of acquisition i stays addressable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from biris_hw.data import Point, Scan

__all__ = [
    "FAN_DEG",
    "Frame",
    "Mount",
    "point_points",
    "project_profiles",
    "sample_elevations",
    "scan_points",
]

FAN_DEG = 22.0
"""Vertical dispersion of the BIRIS laser sheet, degrees (report, introduction)."""

Frame = Literal["sensor", "vehicle"]

_RAD_PER_COUNT = 2.0 * math.pi / 4096.0  # binary degrees: 4096 counts per revolution


@dataclass(frozen=True)
class Mount:
    """Where the head sits on the vehicle: what a scan needs to become vehicle-frame points.

    ``offset_m`` is the pan axis's foot in the vehicle frame (the init record's
    ``mount_offset_m``), ``head_height_m`` the optical centre's height above that foot along the
    pan axis, ``head_offset_m`` its horizontal distance from the pan axis along the azimuth. The
    defaults are the simulator's head: optical centre on the pan axis, 0.5 m up.

    A value, not a handle: scans carry one so that they stay plain data (picklable, shareable)
    and still know how to place themselves.
    """

    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    head_height_m: float = 0.5
    head_offset_m: float = 0.0

    def __post_init__(self) -> None:
        offset = tuple(float(v) for v in self.offset_m)
        if len(offset) != 3 or not all(math.isfinite(v) for v in offset):
            raise ValueError(f"offset_m must be three finite numbers, not {self.offset_m!r}")
        object.__setattr__(self, "offset_m", offset)
        for name in ("head_height_m", "head_offset_m"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, not {value}")
            object.__setattr__(self, name, value)

    @property
    def optical_centre_m(self) -> tuple[float, float, float]:
        """The sensor frame's origin in the vehicle frame."""
        x, y, z = self.offset_m
        return (x, y, z + self.head_height_m)


DEFAULT_MOUNT = Mount()


def sample_elevations(samples: int) -> NDArray[np.float64]:
    """Angle (radians) of each sample's ray above the optical axis, top row first.

    Row k of N looks through the centre of its row: ``(FAN_DEG/2) (1 - (2k+1)/N)``; so the rows
    are symmetric about the axis and none looks exactly along it when N is even.
    """
    if isinstance(samples, bool) or int(samples) != samples or samples < 1:
        raise ValueError(f"samples must be a positive whole number, not {samples!r}")
    n = int(samples)
    half = math.radians(FAN_DEG) / 2.0
    return half * (1.0 - (2.0 * np.arange(n, dtype=np.float64) + 1.0) / n)


def project_profiles(
    range_mm: ArrayLike,
    azimuth_counts: ArrayLike,
    elevation_counts: ArrayLike = 0,
    frame: Frame = "vehicle",
    mount: Mount | None = None,
) -> NDArray[np.float64]:
    """Every sample of every profile as a point: shape ``(n_acq, samples, 3)``, metres.

    ``range_mm`` is ``(n_acq, samples)`` (0 = no return: that row is NaN), ``azimuth_counts``
    ``(n_acq,)`` and ``elevation_counts`` a scalar or ``(n_acq,)``, both in binary-degree
    counts. The grid keeps each sample at its (acquisition, row) place, which plots and
    per-row statistics want; :func:`scan_points` is the flat list without the gaps.
    """
    if frame not in ("sensor", "vehicle"):
        raise ValueError(f"frame must be 'sensor' or 'vehicle', not {frame!r}")
    m = DEFAULT_MOUNT if mount is None else mount
    r = np.asarray(range_mm, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"range_mm must be (n_acq, samples), not shape {r.shape}")
    n_acq, samples = r.shape
    az = np.broadcast_to(np.asarray(azimuth_counts, dtype=np.float64), (n_acq,))
    el = np.broadcast_to(np.asarray(elevation_counts, dtype=np.float64), (n_acq,))
    depth = np.where(r > 0.0, r / 1000.0, np.nan)  # metres along the optical axis
    rows = sample_elevations(samples) if samples else np.zeros(0)
    # head frame: x along the optical axis, z up the sheet
    hx = depth
    hz = depth * np.tan(rows)[np.newaxis, :]
    # tilt: rotate about the (horizontal) tilt axis, positive looks up
    tilt = (el * _RAD_PER_COUNT)[:, np.newaxis]
    ct, st = np.cos(tilt), np.sin(tilt)
    fx = hx * ct - hz * st + m.head_offset_m  # forward of the pan axis
    fz = hx * st + hz * ct
    # pan: rotate about the vertical pan axis, positive counter-clockwise seen from above
    pan = (az * _RAD_PER_COUNT)[:, np.newaxis]
    out = np.empty((n_acq, samples, 3), dtype=np.float64)
    out[..., 0] = fx * np.cos(pan)
    out[..., 1] = fx * np.sin(pan)
    out[..., 2] = fz
    if frame == "vehicle":
        out += np.asarray(m.optical_centre_m, dtype=np.float64)
    return out


def _valid(grid: NDArray[np.float64], range_mm: NDArray[np.int16]) -> NDArray[np.float64]:
    return np.ascontiguousarray(grid[np.asarray(range_mm) > 0])


def scan_points(
    scan: Scan, frame: Frame = "vehicle", mount: Mount | None = None
) -> NDArray[np.float64]:
    """A scan's returns as an ``(m, 3)`` array of points in metres, no-return samples left out.

    Ordered acquisition by acquisition, top row first within each. ``mount`` defaults to the
    one the server attached to the scan (from its init record), else the simulator's head.
    """
    use = mount if mount is not None else (scan.mount or DEFAULT_MOUNT)
    grid = project_profiles(scan.range_mm, scan.azimuth, scan.elevation, frame, use)
    return _valid(grid, scan.range_mm)


def point_points(
    point: Point, frame: Frame = "vehicle", mount: Mount | None = None
) -> NDArray[np.float64]:
    """One acquisition's profile as an ``(m, 3)`` array of points, no-return samples left out."""
    use = mount if mount is not None else (point.mount or DEFAULT_MOUNT)
    profile = point.profile[np.newaxis, :]
    grid = project_profiles(profile, [point.azimuth], point.elevation, frame, use)
    return _valid(grid, profile)
