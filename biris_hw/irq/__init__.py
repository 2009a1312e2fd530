"""Interrupt lines: how notifiers wait for BIRIS, motor and coupler interrupts.

Physical lines (``eventfd``, ``uio``, ``poll``) are made by kind with :func:`open_line`; the
level-2 and level-3 demultiplexers turn a physical line into the report's logical interrupts.
"""

from biris_hw.errors import LineClosed
from biris_hw.irq.base import InterruptLine
from biris_hw.irq.demux import LEVEL2_LOGICALS, LEVEL3_LOGICALS, Level2Demux, Level3Demux, Logical
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.irq.fdline import FdLine
from biris_hw.irq.poll import PollLine
from biris_hw.irq.registry import LINE_KINDS, open_line, register_line
from biris_hw.irq.uio import UioLine

__all__ = [
    "LEVEL2_LOGICALS",
    "LEVEL3_LOGICALS",
    "LINE_KINDS",
    "EventFdLine",
    "FdLine",
    "InterruptLine",
    "Level2Demux",
    "Level3Demux",
    "LineClosed",
    "Logical",
    "PollLine",
    "UioLine",
    "open_line",
    "register_line",
]
