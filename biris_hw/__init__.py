"""biris-hw: driver, server and client API for the NRC BIRIS laser range camera."""

from biris_hw.angles import counts_to_deg, deg_to_counts
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Point, Scan
from biris_hw.errors import BirisError, ConnectionClosed, HardwareFault, RequestError
from biris_hw.geometry import Mount
from biris_hw.hardware import BirisHardware
from biris_hw.records import BirisInitRecord, MotorParams
from biris_hw.server import BirisServer

__all__ = [
    "BirisError",
    "BirisHardware",
    "BirisInitRecord",
    "BirisServer",
    "ConnectionClosed",
    "ConnectionKind",
    "DeliveryPolicy",
    "Direction",
    "HardwareFault",
    "MotorParams",
    "Mount",
    "Point",
    "RequestError",
    "Scan",
    "counts_to_deg",
    "deg_to_counts",
]

__version__ = "0.1.0"
