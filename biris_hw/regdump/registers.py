"""A register set read by its own description, once per register, and decoded into rows.

The descriptions in :mod:`regs` are the only table: what may be read (readable, and reading has
no effect), in which order (composites' parts first), at which width, and how a value decodes.
"""

from __future__ import annotations

from typing import Any

from biris_hw.regdump.model import Json, Row
from biris_hw.regdump.regions import Reader
from regs.describe import Register, RegisterSet
from regs.hctl1000 import counts_to_deg

__all__ = ["composite_rows", "read_register_set", "register_rows"]


def _dumpable(reg: Register) -> bool:
    return reg.access.readable and not reg.read_has_effect


def _read_width(reader: Reader, offset: int, width: int) -> int:
    if width == 1:
        return reader.read8(offset)
    if width == 2:
        return reader.read16(offset)
    if width == 4:
        return reader.read32(offset)
    return int.from_bytes(reader.read(offset, width), "big")


def read_register_set(reader: Reader, regset: RegisterSet) -> dict[str, int]:
    """Raw values by name, each register read once, composites' parts first in read order.

    On a live HCTL-1000 reading R14H latches R13H/R12H, so the parts of a composite are read as
    one group in the order its description gives, before anything else can disturb the latch.
    """
    values: dict[str, int] = {}

    def read(reg: Register) -> None:
        if reg.name not in values and _dumpable(reg):
            values[reg.name] = _read_width(reader, reg.offset, reg.width)

    for composite in regset.composites:
        for name in composite.read_order:
            read(regset.by_name(name))
    for reg in regset:
        read(reg)
    return values


def register_rows(regset: RegisterSet, values: dict[str, int]) -> list[Row]:
    rows = []
    for reg in regset:
        common: dict[str, Any] = {
            "offset": reg.offset,
            "width": reg.width,
            "access": reg.access.value,
            "register": True,
        }
        if reg.name in values:
            raw = values[reg.name]
            rows.append(Row(reg.name, reg.decode(raw), raw=raw, value=reg.to_signed(raw), **common))
        elif not reg.access.readable:
            rows.append(Row(reg.name, "(write-only)", **common))
        else:
            rows.append(Row(reg.name, "(not read: reading it has side effects)", **common))
    return rows


def composite_rows(regset: RegisterSet, values: dict[str, int]) -> list[Row]:
    rows = []
    for composite in regset.composites:
        if not all(part in values for part in composite.parts):
            continue
        combined = composite.combine(values)
        value: Json = {"value": combined}
        if composite.name.endswith("_position"):
            value = {"counts": combined, "deg": counts_to_deg(combined)}
        rows.append(Row(composite.name, composite.decoder(combined), value=value))
    return rows
