"""What a register dump is: sections of rows, and how two dumps differ.

A dump is plain frozen data, made once per pass and never changed, so ``--watch`` can keep the
previous one to mark what changed and a script can hold dumps side by side.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from biris_hw.errors import BirisError

__all__ = ["Dump", "DumpError", "Json", "Row", "Section", "changed_rows", "hex_offset"]


Json = Any
"""A value ``json.dumps`` accepts (numbers, strings, None, lists and dicts of them)."""


class DumpError(BirisError, ValueError):
    """The dump cannot be made as asked: a missing or short source, a layout that does not fit."""


@dataclass(frozen=True)
class Row:
    """One line of a dump: a register (``register=True``, ``raw`` read or None) or a derived value.

    ``offset`` is relative to the section's base; ``value`` is what ``--json`` shows.
    """

    name: str
    decoded: str
    offset: int | None = None
    width: int = 0
    access: str = ""
    raw: int | None = None
    value: Json = None
    register: bool = False

    @property
    def raw_text(self) -> str:
        return "" if self.raw is None else f"0x{self.raw:0{2 * self.width}X}"


@dataclass(frozen=True)
class Section:
    """The rows of one register area; ``base`` is its offset in the source it was read from."""

    key: str
    title: str
    where: str
    base: int
    rows: tuple[Row, ...]

    def row(self, name: str) -> Row:
        for row in self.rows:
            if row.name == name:
                return row
        raise KeyError(f"{self.key} has no row {name!r}")


@dataclass(frozen=True)
class Dump:
    """Everything one pass read, in display order, plus where it came from."""

    source: str
    layout: dict[str, int]
    sections: tuple[Section, ...]

    def section(self, key: str) -> Section:
        for section in self.sections:
            if section.key == key:
                return section
        raise KeyError(f"no section {key!r}")


def changed_rows(previous: Dump | None, current: Dump) -> frozenset[tuple[str, str]]:
    """(section key, row name) of every row whose raw value or decoding differs from before."""
    if previous is None:
        return frozenset()
    before = {(s.key, r.name): (r.raw, r.decoded) for s in previous.sections for r in s.rows}
    return frozenset(
        (s.key, r.name)
        for s in current.sections
        for r in s.rows
        if before.get((s.key, r.name)) != (r.raw, r.decoded)
    )


def hex_offset(offset: int) -> str:
    """An offset as the dump shows it everywhere."""
    return f"0x{offset:04X}"
