"""Technology 80 Model 7600 dual-axis VME motion controller (two HCTL-1000s).

Interpretation (no manual survives): axis 0 (azimuth) has HCTL register n at board offset n,
axis 1 (elevation) at 0x40 + n; byte accesses. Board registers from 0x80 carry the
MOTOR_END_OF_SCAN interrupt (vector, per-axis enable, per-axis write-1-to-clear status raised at
the end of a trapezoidal profile), a per-axis chip reset, and a per-axis index-seen latch that
initialisation polls to find the zero index.
"""

from __future__ import annotations

import dataclasses
import enum

from regs.describe import Access, Register, RegisterSet, flags_decoder
from regs.hctl1000 import HCTL_REGISTERS, HCTL_SPACE

__all__ = [
    "AXIS_BASE",
    "BOARD_REGISTERS",
    "MOTION_WINDOW_SIZE",
    "Axis",
    "AxisBit",
    "BoardReg",
    "axis_register",
    "hctl_registers_for",
]


class Axis(enum.IntEnum):
    AZIMUTH = 0
    ELEVATION = 1


AXIS_BASE = {Axis.AZIMUTH: 0x00, Axis.ELEVATION: HCTL_SPACE}
"""Board offset of each axis's HCTL-1000 register file."""


class BoardReg(enum.IntEnum):
    """Board registers above the two register files."""

    IRQ_VECTOR = 0x80
    IRQ_ENABLE = 0x81
    IRQ_STATUS = 0x82
    CHIP_RESET = 0x83
    INDEX_STATUS = 0x84
    IRQ_LEVEL = 0x85


class AxisBit(enum.IntFlag):
    """One bit per axis in IRQ_ENABLE, IRQ_STATUS, CHIP_RESET and INDEX_STATUS."""

    AZIMUTH = 0x01
    ELEVATION = 0x02


MOTION_WINDOW_SIZE = 0x100
"""Bytes of board space in our target description."""

DEFAULT_IRQ_VECTOR = 0x70
"""Vector the server programs for MOTOR_END_OF_SCAN (ours)."""

MOTOR_IRQ_LEVEL = 3


def axis_register(axis: Axis | int, reg: int) -> int:
    """Board offset of HCTL register ``reg`` of ``axis``."""
    if not 0 <= reg < HCTL_SPACE:
        raise ValueError(f"HCTL register 0x{reg:02X} out of range")
    return AXIS_BASE[Axis(axis)] + reg


_AXIS_NAMES = [(int(bit), bit.name or "") for bit in AxisBit]

BOARD_REGISTERS = RegisterSet(
    name="Model 7600 board",
    size=MOTION_WINDOW_SIZE,
    registers=(
        Register("IRQ_VECTOR", 0x80, 1, Access.RW, "MOTOR_END_OF_SCAN interrupt vector"),
        Register(
            "IRQ_ENABLE",
            0x81,
            1,
            Access.RW,
            "end-of-profile interrupt enable per axis",
            flags_decoder(_AXIS_NAMES),
        ),
        Register(
            "IRQ_STATUS",
            0x82,
            1,
            Access.RW,
            "end-of-profile pending per axis; write 1 to acknowledge",
            flags_decoder(_AXIS_NAMES),
        ),
        Register(
            "CHIP_RESET",
            0x83,
            1,
            Access.W,
            "write 1 to reset that axis's HCTL-1000",
            flags_decoder(_AXIS_NAMES),
        ),
        Register(
            "INDEX_STATUS",
            0x84,
            1,
            Access.RW,
            "index pulse seen per axis; write 1 to clear",
            flags_decoder(_AXIS_NAMES),
        ),
        Register("IRQ_LEVEL", 0x85, 1, Access.R, "VME interrupt level (jumpered: 3)"),
    ),
)


def hctl_registers_for(axis: Axis | int) -> RegisterSet:
    """The HCTL-1000 register set of one axis, with board offsets."""
    base = AXIS_BASE[Axis(axis)]
    name = f"HCTL-1000 axis {int(axis)} ({Axis(axis).name.lower()})"
    return RegisterSet(
        name=name,
        size=HCTL_SPACE,
        registers=tuple(dataclasses.replace(r, offset=base + r.offset) for r in HCTL_REGISTERS),
        composites=HCTL_REGISTERS.composites,
        base=base,
    )
