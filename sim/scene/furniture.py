"""What the ready-made room holds: a fixed set of furniture, or a seeded random one."""

from __future__ import annotations

import math

import numpy as np

from sim.scene.shapes import Box, Cylinder

__all__ = ["DEFAULT_OBSTACLES", "DEFAULT_ROOM_ORIGIN", "random_obstacles"]

DEFAULT_ROOM_ORIGIN = (-2.1, -2.8)
"""World (x, y) of the default room's rear-right corner: the sensor sits 2.1 m from the back wall
and 2.8 m from the right one, so the front wall is 2.9 m away and the left 3.2 m (all in range)
while the corners are not, and no two opposite scans are mirror images."""


DEFAULT_OBSTACLES: tuple[Box | Cylinder, ...] = (
    Box(center=(1.6, 1.2), size=(0.6, 0.4), height=0.8, yaw=0.3, albedo=0.7),
    Box(center=(-1.2, -1.6), size=(0.8, 0.5), height=0.35, albedo=0.5),
    Cylinder(center=(1.4, -1.3), radius=0.25, height=1.2, albedo=0.4),
)
"""The default room's furniture: a cabinet front-left, a low crate behind-right (below the head,
so only the lower rows see it) and a bin front-right; all clear of the x and y axes."""


def random_obstacles(
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
