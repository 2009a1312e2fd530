"""Interrupt-line kinds by name (see :mod:`biris_hw.kinds`); ``biris_hw.lines`` entry points add
more. A target description names its lines the same way it names its windows."""

from __future__ import annotations

from typing import Any

from biris_hw.irq.base import InterruptLine
from biris_hw.kinds import KindRegistry

__all__ = ["LINE_KINDS", "open_line", "register_line"]

_REGISTRY: KindRegistry[InterruptLine] = KindRegistry(
    "interrupt line",
    InterruptLine,
    {
        "eventfd": "biris_hw.irq.eventfd:EventFdLine",
        "uio": "biris_hw.irq.uio:UioLine",
        "poll": "biris_hw.irq.poll:PollLine",
    },
    "biris_hw.lines",
)

LINE_KINDS = _REGISTRY.kinds
"""Kind name -> ``module:Class``."""


def register_line(kind: str, cls: type[InterruptLine]) -> None:
    """Make ``open_line(kind, ...)`` build ``cls``; replaces an earlier entry of that name."""
    _REGISTRY.register(kind, cls)


def open_line(kind: str, **options: Any) -> InterruptLine:
    """Open a line of the named kind: ``open_line("uio", path="/dev/uio3")``."""
    return _REGISTRY.open(kind, **options)
