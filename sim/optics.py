"""The BIRIS head's optics: one vertical laser profile per acquisition, as BIRIS frames it.

Model (after docs/simulator.md; its numbers are inferred examples,
not history). The laser fan (22 degrees) lies in the vertical plane of the head's azimuth; each
of the N samples is one CCD row, i.e. one ray at a fixed elevation relative to the optical axis.
The bi-iris mask images the lit point twice; with the lens focused at infinity the separation of
the two images is b = D f / (z pitch) pixels, z being the depth along the optical axis, and the
per-row calibration table turns b back into z. So:

* range is depth along the optical axis (slant distance times the cosine of the row's angle to
  the axis), so a round wall around the pan axis reads its radius on every row;
* noise enters where the sensor measures: each row's separation gets Gaussian jitter of
  ``peak_sigma_px``, hence sigma_z = z^2 pitch sigma_px / (D f), 5.7 mm at 1 m, 51 mm at 3 m;
* no return (0) when the measured separation is too large for the peak search window (closer
  than ``min_range_m``) or too small to split the peaks (beyond ``max_range_m``), and when the
  return is weaker than ``min_return``: intensity = ``intensity_scale`` albedo / z^2, clipped to
  32767, which puts a 0.6-albedo wall at 1 m mid-scale (16384). Intensity has no noise of its own;
  a sample with no return reads intensity 0 too.

Calibration mismatch (a synthetic model, chosen to be systematic and visible, not measured): a
calibration table loaded for head elevation ``lut`` folds that elevation into each row's curve,
so used at the actual tilt ``t`` it reads row r (angle e_r to the axis) as
``z cos(t + e_r) / cos(lut + e_r) + lut_offset_m_per_rad (t - lut)``: a scale that differs from
row to row (a flat wall comes out bent) plus an offset. With the table matched, both vanish.

On a moving vehicle (docs/simulator.md, "A moving vehicle") the head rides on it: the pan axis
stands at ``mount_xy_m`` in the vehicle frame (the init record's ``mount_offset_m``, x and y; the
simulator's head sits at the vehicle's origin), and the vehicle is at (x, y, yaw) in the scene.
The vehicle only moves in the plane and the pan axis is vertical, so its yaw simply adds to the
azimuth and the rays' origin moves with it: the fan stays one heading seen from above and the
ray caster's fast path, and an acquisition costs the same whether the vehicle moves or not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sim.scene import Scene

__all__ = ["DEFAULT_PARAMS", "Acquisition", "BirisOptics", "OpticsParams"]

FloatArray = NDArray[np.float64]

I16_MAX = 32767
"""Largest value of a frame element (range in mm, intensity in counts)."""


@dataclass(frozen=True)
class OpticsParams:
    """Optical constants of the simulated head; defaults are the reference's example values."""

    fan_deg: float = 22.0
    max_range_m: float = 3.5
    min_range_m: float = 0.3
    focal_length_m: float = 0.025
    aperture_separation_m: float = 0.012
    pixel_pitch_m: float = 17e-6
    peak_sigma_px: float = 0.1
    """Jitter (1 sigma) of the measured separation of the two peaks, pixels."""
    min_return: float = 200.0
    """Intensity (counts) below which the peaks are lost in the background: no return."""
    intensity_scale: float = 16384.0 / 0.6
    """Intensity (counts) of an albedo-1 surface at 1 m."""
    head_height_m: float = 0.5
    """Height of the optical centre above the floor."""
    pan_offset_m: float = 0.0
    """Horizontal distance from the pan axis to the optical centre, along the azimuth."""
    lut_offset_m_per_rad: float = 0.1
    """Offset a mismatched calibration table adds, per radian of mismatch."""
    mount_xy_m: tuple[float, float] = (0.0, 0.0)
    """Where the pan axis stands in the vehicle frame (x forward, y left), metres."""

    def __post_init__(self) -> None:
        mount = tuple(float(v) for v in self.mount_xy_m)
        if len(mount) != 2 or not all(math.isfinite(v) for v in mount):
            raise ValueError(f"mount_xy_m must be two finite numbers, not {self.mount_xy_m!r}")
        object.__setattr__(self, "mount_xy_m", mount)
        if not 0.0 < self.fan_deg < 180.0:
            raise ValueError(f"fan_deg must be in (0, 180), not {self.fan_deg}")
        if not 0.0 < self.min_range_m < self.max_range_m <= I16_MAX / 1000.0:
            raise ValueError("need 0 < min_range_m < max_range_m <= 32.767 m (i16 millimetres)")
        for name in ("focal_length_m", "aperture_separation_m", "pixel_pitch_m"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be positive")
        if self.peak_sigma_px < 0.0 or self.min_return < 0.0 or not self.intensity_scale > 0.0:
            raise ValueError("peak_sigma_px and min_return must be >= 0, intensity_scale > 0")

    @property
    def disparity_gain(self) -> float:
        """D f / pitch, in pixel metres: the separation in pixels is this over the depth."""
        return self.aperture_separation_m * self.focal_length_m / self.pixel_pitch_m

    def sigma_z_m(self, z_m: float) -> float:
        """Range noise (1 sigma, metres) at depth ``z_m``, to first order."""
        return z_m * z_m * self.peak_sigma_px / self.disparity_gain


DEFAULT_PARAMS = OpticsParams()


@dataclass(frozen=True)
class Acquisition:
    """One acquisition as BIRIS frames it: element 0 the closest valid sample (0 if none),
    elements 1..N the samples top to bottom; range in millimetres, 0 = no return."""

    range_mm: NDArray[np.int16]
    intensity: NDArray[np.int16]

    @property
    def samples(self) -> int:
        return int(self.range_mm.size) - 1

    @property
    def closest_mm(self) -> int:
        return int(self.range_mm[0])


class BirisOptics:
    """Turns (scene, head pose) into acquisitions; owns the noise generator it is given."""

    def __init__(
        self,
        samples: int,
        rng: np.random.Generator,
        params: OpticsParams = DEFAULT_PARAMS,
        noise: bool = True,
    ) -> None:
        if samples < 1:
            raise ValueError(f"samples must be positive, not {samples}")
        self._n = samples
        self._rng = rng
        self._params = params
        self._noise = noise
        # Row centres spread evenly over the fan, top (positive) first.
        half = math.radians(self._params.fan_deg) / 2.0
        elevations = half * (1.0 - (2.0 * np.arange(samples) + 1.0) / samples)
        elevations.flags.writeable = False
        self._elevations = elevations
        self._cos_rows = np.cos(elevations)
        self._tilt: tuple[float, FloatArray, FloatArray] = (0.0, self._cos_rows, np.sin(elevations))

    @property
    def samples(self) -> int:
        return self._n

    @property
    def params(self) -> OpticsParams:
        return self._params

    @property
    def elevations(self) -> FloatArray:
        """Angle (radians) of each sample's ray above the optical axis, top to bottom."""
        return self._elevations

    def rays(
        self,
        azimuth_rad: float,
        tilt_rad: float = 0.0,
        head_height_m: float | None = None,
        vehicle_pose: tuple[float, float, float] | None = None,
    ) -> tuple[FloatArray, FloatArray]:
        """Origin (3,) and unit directions (N, 3) of the rows' rays in the world frame.

        ``vehicle_pose`` is the vehicle's (x_m, y_m, yaw_rad) in the world; None: at the
        origin facing +x, where the vehicle frame is the world frame."""
        p = self._params
        h = p.head_height_m if head_height_m is None else head_height_m
        ca, sa = math.cos(azimuth_rad), math.sin(azimuth_rad)
        mx, my = p.mount_xy_m
        ox, oy = mx + p.pan_offset_m * ca, my + p.pan_offset_m * sa  # in the vehicle frame
        if vehicle_pose is not None:
            vx, vy, vyaw = vehicle_pose
            cy, sy = math.cos(vyaw), math.sin(vyaw)
            ox, oy = vx + cy * ox - sy * oy, vy + sy * ox + cy * oy
            ca, sa = math.cos(azimuth_rad + vyaw), math.sin(azimuth_rad + vyaw)
        if self._tilt[0] != tilt_rad:  # the tilt axis rarely moves: keep its trigonometry
            up = tilt_rad + self._elevations
            self._tilt = (tilt_rad, np.cos(up), np.sin(up))
        _, level, rise = self._tilt
        directions = np.empty((self._n, 3))
        directions[:, 0] = level * ca
        directions[:, 1] = level * sa
        directions[:, 2] = rise
        origin = np.array([ox, oy, h])
        return origin, directions

    def acquire(
        self,
        scene: Scene,
        azimuth_rad: float,
        tilt_rad: float = 0.0,
        head_height_m: float | None = None,
        lut_tilt_rad: float | None = None,
        vehicle_pose: tuple[float, float, float] | None = None,
    ) -> Acquisition:
        """Expose one profile at this pose. ``lut_tilt_rad`` is the elevation the loaded
        calibration table was made for (None: made for this tilt); ``vehicle_pose`` is where the
        vehicle stands (see :meth:`rays`); see the module notes."""
        p = self._params
        origin, directions = self.rays(azimuth_rad, tilt_rad, head_height_m, vehicle_pose)
        slant, albedo = scene.cast(origin, directions)
        depth = slant * self._cos_rows
        with np.errstate(divide="ignore", invalid="ignore"):
            brightness = p.intensity_scale * albedo / (depth * depth)
            separation = p.disparity_gain / depth  # pixels; 0 where nothing was hit
            if self._noise:
                # One draw per row every time, returns or not, so a seed fixes the whole run.
                separation = separation + p.peak_sigma_px * self._rng.standard_normal(self._n)
            measured = p.disparity_gain / separation
        valid = (
            (slant < np.inf)
            & (measured >= p.min_range_m)
            & (measured <= p.max_range_m)
            & (brightness >= p.min_return)
        )
        if lut_tilt_rad is not None and lut_tilt_rad != tilt_rad:
            rows = self._elevations
            scale = np.cos(tilt_rad + rows) / np.cos(lut_tilt_rad + rows)
            measured = measured * scale + p.lut_offset_m_per_rad * (tilt_rad - lut_tilt_rad)
        range_mm = np.zeros(self._n + 1, dtype=np.int16)
        intensity = np.zeros(self._n + 1, dtype=np.int16)
        rows_mm = np.clip(np.rint(measured[valid] * 1000.0), 1, I16_MAX)
        range_mm[1:][valid] = rows_mm
        intensity[1:][valid] = np.clip(np.rint(brightness[valid]), 0, I16_MAX)
        if rows_mm.size:
            closest = int(np.flatnonzero(valid)[rows_mm.argmin()]) + 1
            range_mm[0] = range_mm[closest]
            intensity[0] = intensity[closest]
        range_mm.flags.writeable = False
        intensity.flags.writeable = False
        return Acquisition(range_mm, intensity)
