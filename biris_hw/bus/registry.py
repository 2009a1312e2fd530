"""Window kinds by name, in the manner of python-can's interface registry.

Built-in kinds are imported lazily, so a kind whose optional dependency is missing costs nothing
until it is asked for; third parties add kinds through the ``biris_hw.windows`` entry-point group.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from biris_hw.bus.base import BusWindow
from biris_hw.errors import UnknownKind

__all__ = ["WINDOW_KINDS", "open_window", "register_window"]

WINDOW_KINDS: dict[str, str] = {
    "memory": "biris_hw.bus.memory:MemoryWindow",
    "shm": "biris_hw.bus.shm:SharedMemoryWindow",
    "mmap": "biris_hw.bus.mmapwin:MmapWindow",
    "remote": "biris_hw.bus.remote:RemoteWindow",
}
"""Kind name -> ``module:Class``."""

_loaded: dict[str, type[BusWindow]] = {}


def register_window(kind: str, cls: type[BusWindow]) -> None:
    """Make ``open_window(kind, ...)`` build ``cls``; replaces an earlier entry of that name."""
    _loaded[kind] = cls
    WINDOW_KINDS[kind] = f"{cls.__module__}:{cls.__qualname__}"


def _resolve(kind: str) -> type[BusWindow]:
    if kind in _loaded:
        return _loaded[kind]
    target = WINDOW_KINDS.get(kind)
    if target is None:
        for ep in entry_points(group="biris_hw.windows"):
            if ep.name == kind:
                target = ep.value
                break
    if target is None:
        known = ", ".join(sorted(WINDOW_KINDS))
        raise UnknownKind(f"no bus window kind {kind!r} (known: {known})")
    module_name, _, attr = target.partition(":")
    cls = getattr(importlib.import_module(module_name), attr)
    if not (isinstance(cls, type) and issubclass(cls, BusWindow)):
        raise UnknownKind(f"{target} is not a BusWindow")
    _loaded[kind] = cls
    return cls


def open_window(kind: str, **options: Any) -> BusWindow:
    """Open a window of the named kind: ``open_window("memory", size=0x1000)``."""
    return _resolve(kind)(**options)
