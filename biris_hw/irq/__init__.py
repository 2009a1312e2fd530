"""Interrupt lines: how notifiers wait for BIRIS, motor and coupler interrupts."""

from biris_hw.errors import LineClosed
from biris_hw.irq.base import InterruptLine
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.irq.fdline import FdLine

__all__ = ["EventFdLine", "FdLine", "InterruptLine", "LineClosed"]
