"""``biris regdump``: the registers of a target, decoded for people and for scripts.

A dump reads one :class:`~regs.layout.TargetImage` (coupler, Model 7600 board, BIRIS memory)
through a bus window and decodes it with the register descriptions in :mod:`regs`, so there is
no second table to drift. Reads follow the hardware's rules even though a dump file has none:
HCTL-1000 composites are read in their ``read_order`` (R14H first, since on a live chip that read
latches R13H/R12H), write-only registers and registers whose read has an effect are not read, and
nothing is ever written.

The library half (:func:`snapshot`, :func:`changed_rows`, :func:`format_table`, :func:`to_json`)
works on any window; the CLI half (:func:`add_arguments`, :func:`run`) is what ``biris regdump``
calls. The parts: :mod:`.model` (what a dump is), :mod:`.regions` and :mod:`.registers` (reading
by the register descriptions), :mod:`.frames` (the range array), :mod:`.decode` (whole dumps),
:mod:`.render` (table and JSON), :mod:`.images` and :mod:`.cli` (the command).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from biris_hw.regdump.cli import add_arguments, run
from biris_hw.regdump.decode import snapshot, snapshot_hardware, snapshot_regions
from biris_hw.regdump.frames import FrameSummary, last_complete_frame, summarize_frame
from biris_hw.regdump.model import Dump, DumpError, Row, Section, changed_rows
from biris_hw.regdump.model import Json as Json
from biris_hw.regdump.regions import Reader, Region
from biris_hw.regdump.registers import read_register_set as read_register_set
from biris_hw.regdump.render import format_table, to_json

__all__ = [
    "Dump",
    "DumpError",
    "FrameSummary",
    "Reader",
    "Region",
    "Row",
    "Section",
    "add_arguments",
    "changed_rows",
    "format_table",
    "last_complete_frame",
    "run",
    "snapshot",
    "snapshot_hardware",
    "snapshot_regions",
    "summarize_frame",
    "to_json",
]

_sleep: Callable[[float], None] = time.sleep
"""Pacing between ``--watch`` dumps (a package attribute so tests can replace it)."""
