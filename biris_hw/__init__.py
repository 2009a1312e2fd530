"""biris-hw: driver, server and client API for the NRC BIRIS laser range camera."""

from biris_hw.angles import counts_to_deg, deg_to_counts
from biris_hw.errors import BirisError, ConnectionClosed, HardwareFault, RequestError
from biris_hw.hardware import BirisHardware

__all__ = [
    "BirisError",
    "BirisHardware",
    "ConnectionClosed",
    "HardwareFault",
    "RequestError",
    "counts_to_deg",
    "deg_to_counts",
]

__version__ = "0.1.0"
