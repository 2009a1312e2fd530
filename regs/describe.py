"""Self-description of register sets, so the register dump and the audit need no second table.

A :class:`Register` names one hardware location (offset, width in bytes, access, meaning and a
decoder that turns its raw value into text for people). A :class:`Composite` names a value that
spans several registers (the HCTL-1000's 24-bit positions) with the order in which they must be
read, because on real chips the first read can latch the others.
"""

from __future__ import annotations

import ctypes
import enum
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

__all__ = [
    "Access",
    "Combine",
    "Composite",
    "Register",
    "RegisterSet",
    "describe_struct",
    "flags_decoder",
    "hex_decoder",
    "signed_decoder",
]


class Access(enum.Enum):
    """Who may touch a register from the host side."""

    R = "R"
    W = "W"
    RW = "RW"

    @property
    def readable(self) -> bool:
        return self is not Access.W

    @property
    def writable(self) -> bool:
        return self is not Access.R


def hex_decoder(width: int) -> Callable[[int], str]:
    """The plain decoder: the raw value in hex, zero-padded to the register's width."""
    digits = 2 * width

    def decode(value: int) -> str:
        return f"0x{value & ((1 << (8 * width)) - 1):0{digits}X}"

    return decode


@dataclass(frozen=True)
class Register:
    """One register: where it is, how wide, who may access it, what it means."""

    name: str
    offset: int
    width: int
    access: Access
    meaning: str
    decoder: Callable[[int], str] | None = None
    signed: bool = False
    read_has_effect: bool = False
    """Reading it does more than latch (an interrupt acknowledge, a read-to-clear), so a
    register dump must leave it alone even though the host may read it."""

    def decode(self, value: int) -> str:
        """Text for people; the hex value when no decoder is given."""
        if self.decoder is not None:
            return self.decoder(value)
        return hex_decoder(self.width)(value)

    def to_signed(self, raw: int) -> int:
        """Interpret a raw unsigned read as this register's value (two's complement if signed)."""
        bits = 8 * self.width
        raw &= (1 << bits) - 1
        if self.signed and raw >> (bits - 1):
            return raw - (1 << bits)
        return raw


Combine = Callable[[Mapping[str, int]], int]
"""Turns the raw bytes of a composite's parts (by register name) into its value."""


@dataclass(frozen=True)
class Composite:
    """A value spread over several registers, with the order in which they must be read."""

    name: str
    parts: tuple[str, ...]
    read_order: tuple[str, ...]
    combine: Combine
    decoder: Callable[[int], str]
    meaning: str = ""


@dataclass(frozen=True)
class RegisterSet:
    """The registers of one device (or one structure), in offset order.

    Register offsets are measured in the window the set is reached through; ``base`` is where
    the set's ``size`` bytes start in that window (non-zero for the second HCTL-1000 on the
    Model 7600, whose registers sit at board offsets 0x40..0x7F).
    """

    name: str
    size: int
    registers: tuple[Register, ...]
    composites: tuple[Composite, ...] = field(default=())
    base: int = 0

    def __iter__(self) -> Iterator[Register]:
        return iter(self.registers)

    def __len__(self) -> int:
        return len(self.registers)

    def by_name(self, name: str) -> Register:
        for reg in self.registers:
            if reg.name == name:
                return reg
        raise KeyError(f"{self.name} has no register {name!r}")

    def at(self, offset: int) -> Register | None:
        """The register that starts at ``offset``, or None for an undocumented location."""
        for reg in self.registers:
            if reg.offset == offset:
                return reg
        return None

    def covering(self, offset: int) -> Register | None:
        """The register whose bytes include ``offset``."""
        for reg in self.registers:
            if reg.offset <= offset < reg.offset + reg.width:
                return reg
        return None


_SIGNED_TYPE_CODES = ("b", "h", "i", "l", "q")
"""ctypes type codes of the signed integer types."""


def describe_struct(
    name: str,
    struct_type: type[ctypes.Structure],
    meanings: Mapping[str, str],
    decoders: Mapping[str, Callable[[int], str]] | None = None,
    access: Mapping[str, Access] | None = None,
) -> RegisterSet:
    """Describe a ctypes structure's scalar fields as registers (array fields are skipped).

    Offsets and sizes come from ctypes itself, so the description cannot drift from the layout.
    """
    decoders = decoders or {}
    access = access or {}
    regs: list[Register] = []
    for fname, ftype, *_ in struct_type._fields_:
        desc = getattr(struct_type, fname)
        if issubclass(ftype, ctypes.Array):
            continue
        # By type code, not identity: a BigEndianStructure on a little-endian host stores
        # byte-swapped copies of the field types, which are not ctypes.c_int16 and friends.
        signed = getattr(ftype, "_type_", "") in _SIGNED_TYPE_CODES
        regs.append(
            Register(
                name=fname,
                offset=desc.offset,
                width=desc.size,
                access=access.get(fname, Access.RW),
                meaning=meanings.get(fname, ""),
                decoder=decoders.get(fname),
                signed=signed,
            )
        )
    return RegisterSet(name=name, size=ctypes.sizeof(struct_type), registers=tuple(regs))


def signed_decoder(bits: int) -> Callable[[int], str]:
    """Decimal, read as two's complement of ``bits`` bits."""

    def decode(value: int) -> str:
        value &= (1 << bits) - 1
        if value >> (bits - 1):
            value -= 1 << bits
        return str(value)

    return decode


def flags_decoder(names: Sequence[tuple[int, str]]) -> Callable[[int], str]:
    """``0x31 [PROFILE INIT_IDLE ...]``: the raw value and the names of the set bits."""

    def decode(value: int) -> str:
        set_names = [n for mask, n in names if value & mask]
        return f"0x{value:02X} [{' '.join(set_names)}]" if set_names else f"0x{value:02X} []"

    return decode
