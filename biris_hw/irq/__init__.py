"""Interrupt lines: how notifiers wait for BIRIS, motor and coupler interrupts.

Physical lines (``eventfd``, ``uio``, ``poll``) are made by kind with :func:`open_line`; a
:class:`Demultiplexer` turns a physical line into logical ones. What the BIRIS levels carry, and
how they are decoded, is the server's business (:mod:`biris_hw.server.isr`).
"""

from biris_hw.errors import LineClosed
from biris_hw.irq.base import InterruptLine
from biris_hw.irq.demux import Demultiplexer
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.irq.fdline import FdLine
from biris_hw.irq.poll import PollLine
from biris_hw.irq.registry import LINE_KINDS, open_line, register_line
from biris_hw.irq.uio import UioLine

__all__ = [
    "LINE_KINDS",
    "Demultiplexer",
    "EventFdLine",
    "FdLine",
    "InterruptLine",
    "LineClosed",
    "PollLine",
    "UioLine",
    "open_line",
    "register_line",
]
