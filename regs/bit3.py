"""Bit 3 Model 412 VME-VME adaptor, local (host-side) node registers.

Interpretation: no Model 412 manual survives; the layout is the Bit 3 adaptor-node family's (as
documented for the Model 617 and matched by 1992 VME-VME code), plus a level-2 interrupt vector
register whose place is ours. PARITY and REMBUS are sticky until CLR_ERROR is written.
"""

from __future__ import annotations

import enum

from regs.describe import Access, Register, RegisterSet, flags_decoder

__all__ = [
    "BIT3_REGISTERS",
    "BIT3_SPACE",
    "ERROR_MASK",
    "Bit3Reg",
    "LocalCommand",
    "LocalIntControl",
    "LocalStatus",
]

BIT3_SPACE = 0x20
"""Bytes of coupler register space in our target description."""


class Bit3Reg(enum.IntEnum):
    """Byte offsets of the local node registers."""

    LOCAL_COMMAND = 0x00
    LOCAL_INT_CONTROL = 0x01
    LOCAL_STATUS = 0x02
    LOCAL_INT_STATUS = 0x03
    REMOTE_COMMAND_1 = 0x08  # write; reading 0x08 gives REMOTE_STATUS
    REMOTE_COMMAND_2 = 0x09
    REMOTE_PAGE_LO = 0x0A
    REMOTE_PAGE_HI = 0x0B
    REMOTE_CARD_ID = 0x0C
    REMOTE_ADDR_MOD = 0x0D
    REMOTE_IACK = 0x0E
    LEVEL2_VECTOR = 0x10


REMOTE_STATUS = 0x08
"""Reading offset 0x08 returns the remote status (writing it is remote command 1)."""


class LocalCommand(enum.IntFlag):
    """LOCAL_COMMAND bits; all one-shot."""

    SND_PT_INT = 0x20
    CLR_PR_INT = 0x40
    CLR_ERROR = 0x80


class LocalIntControl(enum.IntFlag):
    """LOCAL_INT_CONTROL bits."""

    LINE_SELECT = 0x07
    ERROR_INT_ENABLE = 0x20
    NORMAL_INT_ENABLE = 0x40
    INT_PENDING = 0x80


class LocalStatus(enum.IntFlag):
    """LOCAL_STATUS bits (read only)."""

    NO_CONNECT = 0x01
    LRC_ERROR = 0x02
    TIMEOUT = 0x04
    CARD_READY = 0x10
    PR_INT = 0x20
    REMOTE_BUS_ERROR = 0x40
    PARITY_ERROR = 0x80


ERROR_MASK = int(
    LocalStatus.PARITY_ERROR
    | LocalStatus.REMOTE_BUS_ERROR
    | LocalStatus.TIMEOUT
    | LocalStatus.LRC_ERROR
)
"""Status bits that mean an error; cleared together by LocalCommand.CLR_ERROR."""


def _names(flag: type[enum.IntFlag]) -> list[tuple[int, str]]:
    return [(int(bit), bit.name or "") for bit in flag]


def _cint_text(value: int) -> str:
    levels = [str(level) for level in range(7, 0, -1) if value & (1 << level)]
    return f"0x{value:02X} [IRQ {' '.join(levels)}]" if levels else f"0x{value:02X} []"


BIT3_REGISTERS = RegisterSet(
    name="Bit 3 Model 412 (local node)",
    size=BIT3_SPACE,
    registers=(
        Register(
            "LOCAL_COMMAND",
            0x00,
            1,
            Access.RW,
            "bit7 clear errors, bit6 clear PR int, bit5 send PT int (one-shot)",
            flags_decoder(_names(LocalCommand)),
        ),
        Register(
            "LOCAL_INT_CONTROL",
            0x01,
            1,
            Access.RW,
            "bit7 pending (R), bit6 normal enable, bit5 error enable, bits2..0 line",
            flags_decoder(_names(LocalIntControl)),
        ),
        Register(
            "LOCAL_STATUS",
            0x02,
            1,
            Access.R,
            "bit7 parity, bit6 remote bus error, bit2 timeout, bit0 no connection",
            flags_decoder(_names(LocalStatus)),
        ),
        Register("LOCAL_INT_STATUS", 0x03, 1, Access.R, "bits7..1 = remote IRQ7..IRQ1", _cint_text),
        Register("REMOTE_STATUS", 0x08, 1, Access.R, "remote status (read side of 0x08)"),
        Register("REMOTE_COMMAND_1", 0x08, 1, Access.W, "remote command 1 (write side of 0x08)"),
        Register("REMOTE_COMMAND_2", 0x09, 1, Access.RW, "bit4 disables remote interrupt pass"),
        Register("REMOTE_PAGE_LO", 0x0A, 1, Access.RW, "remote page A16..A23"),
        Register("REMOTE_PAGE_HI", 0x0B, 1, Access.RW, "remote page A24..A31"),
        Register("REMOTE_CARD_ID", 0x0C, 1, Access.R, "remote card id"),
        Register("REMOTE_ADDR_MOD", 0x0D, 1, Access.RW, "remote address modifier"),
        Register(
            "REMOTE_IACK",
            0x0E,
            2,
            Access.R,
            "remote IACK read: vector (the read runs an IACK cycle on the remote bus)",
            read_has_effect=True,
        ),
        Register(
            "LEVEL2_VECTOR",
            0x10,
            1,
            Access.RW,
            "vector for every level-2 (BIRIS) interrupt (interpretation)",
        ),
    ),
)
