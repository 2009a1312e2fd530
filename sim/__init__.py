"""The BIRIS hardware simulator: it plays the far side of the driver's windows and lines.

``SimulatedBiris`` is the whole target; ``Scene`` is what it looks at.
"""

from regs.layout import FRAME_POISON as POISON
from sim.rig import SimulatedBiris
from sim.scene import Scene

__all__ = ["POISON", "Scene", "SimulatedBiris"]
