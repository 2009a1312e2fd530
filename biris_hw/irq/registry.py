"""Interrupt-line kinds by name (see :mod:`biris_hw.kinds`); ``biris_hw.lines`` entry points add
more. A target description names its lines the same way it names its windows.

``open_line("uio", path="/dev/uio3")`` opens a line of the named kind; ``register_line(kind,
cls)`` adds or replaces a kind; ``LINE_KINDS`` maps every built-in or registered kind to its
``module:Class``.
"""

from __future__ import annotations

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
        "vmusb": "biris_hw.irq.vmusb:VmUsbLine",
    },
    "biris_hw.lines",
)

LINE_KINDS = _REGISTRY.kinds
open_line = _REGISTRY.open
register_line = _REGISTRY.register
