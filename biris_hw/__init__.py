"""biris-hw: driver, server and client API for the NRC BIRIS laser range camera.

The names below are loaded on first use (PEP 562), so ``import biris_hw.bus`` -- the lowest
layer -- does not drag in the server, and neither does ``import sim``. ``from biris_hw import
BirisServer`` works as before; type checkers and IDEs see the names through the
``TYPE_CHECKING`` block.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from biris_hw import _moved
from biris_hw._version import __version__ as __version__

if TYPE_CHECKING:
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


_WHERE: dict[str, str] = {
    "BirisError": "biris_hw.errors",
    "BirisHardware": "biris_hw.hardware",
    "BirisInitRecord": "biris_hw.records",
    "BirisServer": "biris_hw.server",
    "ConnectionClosed": "biris_hw.errors",
    "ConnectionKind": "biris_hw.data",
    "DeliveryPolicy": "biris_hw.data",
    "Direction": "biris_hw.data",
    "HardwareFault": "biris_hw.errors",
    "MotorParams": "biris_hw.records",
    "Mount": "biris_hw.geometry",
    "Point": "biris_hw.data",
    "RequestError": "biris_hw.errors",
    "Scan": "biris_hw.data",
    "counts_to_deg": "biris_hw.angles",
    "deg_to_counts": "biris_hw.angles",
}
"""Public name -> the module that defines it (kept equal to ``__all__`` by a test)."""


if not TYPE_CHECKING:  # hidden from type checkers, so a misspelt name is still an error there

    def __getattr__(name: str) -> Any:
        module = _WHERE.get(name)
        if module is None:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        globals()[name] = value  # later look-ups skip this function
        return value


_moved.install()  # the old paths of the modules now in biris_hw.io (one more release)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
