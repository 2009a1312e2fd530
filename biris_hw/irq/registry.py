"""Interrupt-line kinds by name, the counterpart of the bus windows' registry.

A target description names its lines (``kind = "uio"``, ``path = "/dev/uio3"``) the same way it
names its windows, so both are built by one mechanism. Built-in kinds load lazily; third parties
add kinds through the ``biris_hw.lines`` entry-point group.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from biris_hw.errors import UnknownKind
from biris_hw.irq.base import InterruptLine

__all__ = ["LINE_KINDS", "open_line", "register_line"]

LINE_KINDS: dict[str, str] = {
    "eventfd": "biris_hw.irq.eventfd:EventFdLine",
    "uio": "biris_hw.irq.uio:UioLine",
    "poll": "biris_hw.irq.poll:PollLine",
}
"""Kind name -> ``module:Class``."""

_loaded: dict[str, type[InterruptLine]] = {}


def register_line(kind: str, cls: type[InterruptLine]) -> None:
    """Make ``open_line(kind, ...)`` build ``cls``; replaces an earlier entry of that name."""
    _loaded[kind] = cls
    LINE_KINDS[kind] = f"{cls.__module__}:{cls.__qualname__}"


def _resolve(kind: str) -> type[InterruptLine]:
    if kind in _loaded:
        return _loaded[kind]
    target = LINE_KINDS.get(kind)
    if target is None:
        for ep in entry_points(group="biris_hw.lines"):
            if ep.name == kind:
                target = ep.value
                break
    if target is None:
        known = ", ".join(sorted(LINE_KINDS))
        raise UnknownKind(f"no interrupt line kind {kind!r} (known: {known})")
    module_name, _, attr = target.partition(":")
    cls = getattr(importlib.import_module(module_name), attr)
    if not (isinstance(cls, type) and issubclass(cls, InterruptLine)):
        raise UnknownKind(f"{target} is not an InterruptLine")
    _loaded[kind] = cls
    return cls


def open_line(kind: str, **options: Any) -> InterruptLine:
    """Open a line of the named kind: ``open_line("uio", path="/dev/uio3")``."""
    return _resolve(kind)(**options)
