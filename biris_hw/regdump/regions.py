"""What a dump reads through: any window's width-explicit reads, one area of it at a time."""

from __future__ import annotations

from typing import Protocol

from biris_hw.errors import BusError

__all__ = ["Reader", "Region"]


class Reader(Protocol):
    """What a dump needs of a window: its size and width-explicit reads."""

    @property
    def size(self) -> int: ...

    def read(self, offset: int, n: int) -> bytes: ...

    def read8(self, offset: int) -> int: ...

    def read16(self, offset: int) -> int: ...

    def read32(self, offset: int) -> int: ...


class Region:
    """One area of a window, addressed from its own start, reads forwarded at their own width.

    Forwarding ``read16`` as ``read16`` (not as two bytes) keeps a one-access register a
    one-access register on a live target.
    """

    def __init__(self, window: Reader, base: int, size: int) -> None:
        self.window = window
        self.base = base
        self._size = size

    @property
    def size(self) -> int:
        return self._size

    def _at(self, offset: int, n: int) -> int:
        if offset < 0 or offset + n > self._size:
            raise BusError(
                f"{n}-byte read at 0x{offset:X} is outside an area of 0x{self._size:X} bytes"
            )
        return self.base + offset

    def read(self, offset: int, n: int) -> bytes:
        return self.window.read(self._at(offset, n), n)

    def read8(self, offset: int) -> int:
        return self.window.read8(self._at(offset, 1))

    def read16(self, offset: int) -> int:
        return self.window.read16(self._at(offset, 2))

    def read32(self, offset: int) -> int:
        return self.window.read32(self._at(offset, 4))
