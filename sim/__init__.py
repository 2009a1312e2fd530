"""The BIRIS hardware simulator: it plays the far side of the driver's windows and lines.

``SimulatedBiris`` is the whole target; ``Scene`` is what it looks at; ``Trajectory`` is how the
vehicle carrying it moves, and ``OdometryParams`` how its base reports that.
"""

from regs.layout import FRAME_POISON as POISON
from sim.odometry import OdometryParams
from sim.rig import SimulatedBiris
from sim.scene import Scene
from sim.trajectory import Trajectory

__all__ = ["POISON", "OdometryParams", "Scene", "SimulatedBiris", "Trajectory"]
