"""What the simulated BIRIS looks at: walls, boxes, cylinders and floors, and a ray caster.

The parts: :mod:`.shapes` (what a scene is made of), :mod:`.geometry` (the shapes flattened into
tables), :mod:`.raycast` (every ray against every surface), :mod:`.plan_view` (seen from above),
:mod:`.furniture` (the ready-made room's obstacles) and :mod:`.scene` (:class:`Scene` itself).
"""

from sim.scene.furniture import DEFAULT_ROOM_ORIGIN
from sim.scene.scene import Scene
from sim.scene.shapes import Box, Cylinder, Plane, Shape, Wall, polygon_walls

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
