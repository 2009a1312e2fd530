"""Bus windows: how the host reaches BIRIS memory and the VME boards (docs/registers.md)."""

from biris_hw.bus.base import BufferWindow, BusWindow, StructView
from biris_hw.bus.registry import WINDOW_KINDS, open_window, register_window
from biris_hw.errors import BusError

__all__ = [
    "WINDOW_KINDS",
    "BufferWindow",
    "BusError",
    "BusWindow",
    "StructView",
    "open_window",
    "register_window",
]
