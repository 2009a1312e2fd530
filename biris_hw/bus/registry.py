"""Window kinds by name (see :mod:`biris_hw.kinds`); ``biris_hw.windows`` entry points add more.

``open_window("memory", size=0x1000)`` opens a window of the named kind; ``register_window(kind,
cls)`` adds or replaces a kind; ``WINDOW_KINDS`` maps every built-in or registered kind to its
``module:Class``.
"""

from __future__ import annotations

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
        "slice": "biris_hw.bus.remote:SliceWindow",
        "vmusb": "biris_hw.bus.vmusb:VmUsbWindow",
    },
    "biris_hw.windows",
)

WINDOW_KINDS = _REGISTRY.kinds
open_window = _REGISTRY.open
register_window = _REGISTRY.register
