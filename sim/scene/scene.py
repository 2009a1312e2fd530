"""``Scene``: what the simulated BIRIS looks at, and the ready-made scenes tests use.

A scene is an immutable set of shapes (:mod:`sim.scene.shapes`), flattened once when it is made
(:mod:`sim.scene.geometry`) so that :meth:`Scene.cast` (:mod:`sim.scene.raycast`) takes a fixed
number of array operations however many rays and shapes there are; its plan views are in
:mod:`sim.scene.plan_view`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import NDArray

from sim.scene import plan_view, raycast
from sim.scene.furniture import DEFAULT_OBSTACLES, DEFAULT_ROOM_ORIGIN, random_obstacles
from sim.scene.geometry import Geometry
from sim.scene.shapes import (
    Box,
    Cylinder,
    FloatArray,
    Plane,
    Shape,
    Wall,
    check_positive,
    polygon_walls,
)

__all__ = ["Scene"]


class Scene:
    """An immutable set of shapes, flattened once for fast ray casting."""

    def __init__(self, shapes: Iterable[Shape]) -> None:
        self._shapes = tuple(shapes)
        for shape in self._shapes:
            if not isinstance(shape, (Wall, Box, Cylinder, Plane)):
                raise TypeError(f"not a scene shape: {shape!r}")
        self._geometry = Geometry.build(self._shapes)

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
        check_positive("radius_m", radius_m)
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
        check_positive("width_m", width_m)
        check_positive("depth_m", depth_m)
        check_positive("height_m", height_m)
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
            shapes += DEFAULT_OBSTACLES
        else:
            shapes += random_obstacles((x0, y0, x1, y1), np.random.default_rng(seed))
        if floor:
            shapes.append(Plane(0.0, albedo=0.3))
        if ceiling:
            shapes.append(Plane(height_m, albedo=0.8))
        return cls(shapes)

    @classmethod
    def from_spec(cls, spec: str) -> Scene:
        """The scene a command line names: ``room`` (:meth:`room`, furnished as by default) or
        ``circle:R`` (:meth:`circle` of radius R metres).

        The one rule for R is :meth:`circle`'s own: any finite number above 0. A wall beyond
        BIRIS's reach (BIRIS_MAX_RANGE, 32.767 m by default) is a legitimate scene, the one
        that shows what "no return" looks like; the range limit belongs to the sensor and the
        server's init record, not to what the sensor looks at. Anything else is a ValueError
        whose message is one line fit for a usage error.
        """
        if spec == "room":
            return cls.room()
        kind, colon, radius_text = spec.partition(":")
        if kind != "circle" or not colon:
            raise ValueError(f"a scene is 'room' or 'circle:R' (R in metres), not {spec!r}")
        try:
            radius = float(radius_text)
        except ValueError:
            radius = math.nan
        if not (math.isfinite(radius) and radius > 0.0):
            raise ValueError(
                f"circle:R needs a radius in metres, a finite R > 0, not {radius_text!r}"
            )
        return cls.circle(radius)

    # --- ray casting -----------------------------------------------------------------------------

    def cast(
        self, origin: NDArray[np.floating], directions: NDArray[np.floating]
    ) -> tuple[FloatArray, FloatArray]:
        """Distance along each ray to the first surface, and that surface's albedo.

        ``origin`` is (3,), ``directions`` (n, 3), normally unit vectors (a distance is in units
        of its ray's length). A ray that hits nothing gets distance inf and albedo 0. Rays that
        share one heading seen from above (a BIRIS profile) take the fast path.
        """
        return raycast.cast(self._geometry, origin, directions, fan=True)

    def cast_general(
        self, origin: NDArray[np.floating], directions: NDArray[np.floating]
    ) -> tuple[FloatArray, FloatArray]:
        """:meth:`cast` without the shared-heading shortcut: the reference the tests hold the
        shortcut to, and what rays of mixed headings get anyway."""
        return raycast.cast(self._geometry, origin, directions, fan=False)

    # --- seen from above -------------------------------------------------------------------------

    def outline_2d(self) -> list[FloatArray]:
        """Polylines (k, 2) of everything that stands up, seen from above, for pictures.

        Boxes and cylinders (as polygons) are closed (last point = first); walls that meet end to
        start in the order given are joined, so a room drawn with :func:`polygon_walls` is one
        closed polyline. Planes have no outline.
        """
        return plan_view.outline_2d(self._shapes)

    def distance_to_surface_2d(self, points: NDArray[np.floating]) -> FloatArray:
        """Horizontal distance from each (x, y) point to the nearest wall, box side or cylinder
        mantle (a true circle, not the drawn polygon); inf when nothing stands up.

        Lets a test check that measured points lie on true surfaces without re-deriving them.
        """
        return plan_view.distance_to_surface_2d(self._geometry, points)
