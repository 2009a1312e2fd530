"""Window kinds by name (see :mod:`biris_hw.kinds`); ``biris_hw.windows`` entry points add more."""

from __future__ import annotations

from typing import Any

from biris_hw.bus.base import BusWindow
from biris_hw.kinds import KindRegistry

__all__ = ["WINDOW_KINDS", "open_window", "register_window"]

_REGISTRY: KindRegistry[BusWindow] = KindRegistry(
    "bus window",
    BusWindow,
    {
        "memory": "biris_hw.bus.memory:MemoryWindow",
        "shm": "biris_hw.bus.shm:SharedMemoryWindow",
        "mmap": "biris_hw.bus.mmapwin:MmapWindow",
        "remote": "biris_hw.bus.remote:RemoteWindow",
    },
    "biris_hw.windows",
)

WINDOW_KINDS = _REGISTRY.kinds
"""Kind name -> ``module:Class``."""


def register_window(kind: str, cls: type[BusWindow]) -> None:
    """Make ``open_window(kind, ...)`` build ``cls``; replaces an earlier entry of that name."""
    _REGISTRY.register(kind, cls)


def open_window(kind: str, **options: Any) -> BusWindow:
    """Open a window of the named kind: ``open_window("memory", size=0x1000)``."""
    return _REGISTRY.open(kind, **options)
