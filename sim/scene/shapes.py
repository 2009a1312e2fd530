"""The shapes a scene is made of: walls, boxes, cylinders and planes.

Frame: x forward, y left, z up (REP 103); the pan axis is the z axis through the origin. Boxes
and cylinders are solids standing on their ``base`` (the floor, z = 0, by default); walls are
two-sided and thin; planes are unbounded. Shapes check themselves when made, so a scene never
holds one that the ray caster would have to guard against.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "Box",
    "Cylinder",
    "FloatArray",
    "Plane",
    "Shape",
    "Wall",
    "check_albedo",
    "check_positive",
    "polygon_walls",
]

FloatArray: TypeAlias = NDArray[np.float64]


def check_albedo(albedo: float) -> None:
    """The optics scale a return by albedo: 0 would be no surface, above 1 light from nowhere."""
    if not 0.0 < albedo <= 1.0:
        raise ValueError(f"albedo must be in (0, 1], not {albedo}")


def check_positive(name: str, value: float) -> None:
    """A zero or NaN size would not fail later: the shape would silently vanish from every cast."""
    if not value > 0.0 or not math.isfinite(value):
        raise ValueError(f"{name} must be positive and finite, not {value}")


def _check_standing(height: float, albedo: float) -> None:
    """What every shape that stands up checks (a plane has no height)."""
    check_positive("height", height)
    check_albedo(albedo)


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
        _check_standing(self.height, self.albedo)


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
        check_positive("box length", self.size[0])
        check_positive("box width", self.size[1])
        _check_standing(self.height, self.albedo)

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
        check_positive("radius", self.radius)
        _check_standing(self.height, self.albedo)


@dataclass(frozen=True)
class Plane:
    """An unbounded horizontal plane at height ``z``: a floor (z = 0) or a ceiling."""

    z: float = 0.0
    albedo: float = 0.3

    def __post_init__(self) -> None:
        if not math.isfinite(self.z):
            raise ValueError(f"plane height must be finite, not {self.z}")
        check_albedo(self.albedo)


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
