"""Interrupt lines: how notifiers wait for BIRIS, motor and coupler interrupts."""

from biris_hw.errors import LineClosed
from biris_hw.irq.base import InterruptLine

__all__ = ["InterruptLine", "LineClosed"]
