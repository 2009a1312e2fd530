"""Model 7600 and Bit 3 Model 412 descriptions pinned, and the invariants of every register set."""

from __future__ import annotations

import itertools

import pytest

from regs.biexec import BIEXEC_REGISTERS
from regs.bit3 import (
    BIT3_REGISTERS,
    BIT3_SPACE,
    ERROR_MASK,
    REMOTE_STATUS,
    Bit3Reg,
    LocalCommand,
    LocalIntControl,
    LocalStatus,
)
from regs.describe import Access, Register, RegisterSet, flags_decoder, hex_decoder, signed_decoder
from regs.hctl1000 import HCTL_REGISTERS, HCTL_SPACE, Reg
from regs.tech80 import (
    AXIS_BASE,
    BOARD_REGISTERS,
    DEFAULT_IRQ_VECTOR,
    MOTION_WINDOW_SIZE,
    MOTOR_IRQ_LEVEL,
    Axis,
    AxisBit,
    BoardReg,
    axis_register,
    hctl_registers_for,
)

R, W, RW = Access.R, Access.W, Access.RW

# -- Technology 80 Model 7600 ---------------------------------------------------------------------


def test_axis_offsets() -> None:
    assert AXIS_BASE == {Axis.AZIMUTH: 0x00, Axis.ELEVATION: 0x40}
    assert (int(Axis.AZIMUTH), int(Axis.ELEVATION)) == (0, 1)
    for reg in Reg:
        assert axis_register(Axis.AZIMUTH, reg) == int(reg)
        assert axis_register(Axis.ELEVATION, reg) == 0x40 + int(reg)
    assert axis_register(1, 0x14) == 0x54
    for bad in (-1, 0x40):
        with pytest.raises(ValueError):
            axis_register(Axis.AZIMUTH, bad)


def test_board_register_offsets() -> None:
    assert [(b.name, int(b)) for b in BoardReg] == [
        ("IRQ_VECTOR", 0x80),
        ("IRQ_ENABLE", 0x81),
        ("IRQ_STATUS", 0x82),
        ("CHIP_RESET", 0x83),
        ("INDEX_STATUS", 0x84),
        ("IRQ_LEVEL", 0x85),
    ]
    assert [(r.name, r.offset, r.width, r.access) for r in BOARD_REGISTERS] == [
        ("IRQ_VECTOR", 0x80, 1, RW),
        ("IRQ_ENABLE", 0x81, 1, RW),
        ("IRQ_STATUS", 0x82, 1, RW),
        ("CHIP_RESET", 0x83, 1, W),
        ("INDEX_STATUS", 0x84, 1, RW),
        ("IRQ_LEVEL", 0x85, 1, R),
    ]
    assert MOTION_WINDOW_SIZE == 0x100 and BOARD_REGISTERS.size == 0x100
    assert (int(AxisBit.AZIMUTH), int(AxisBit.ELEVATION)) == (0x01, 0x02)
    assert DEFAULT_IRQ_VECTOR == 0x70 and MOTOR_IRQ_LEVEL == 3
    assert BOARD_REGISTERS.by_name("IRQ_STATUS").decode(0x03) == "0x03 [AZIMUTH ELEVATION]"


@pytest.mark.parametrize("axis", list(Axis))
def test_hctl_registers_for_each_axis(axis: Axis) -> None:
    regset = hctl_registers_for(axis)
    base = 0x40 * int(axis)
    assert regset.base == base and regset.size == HCTL_SPACE
    assert regset.name == f"HCTL-1000 axis {int(axis)} ({axis.name.lower()})"
    assert len(regset) == len(HCTL_REGISTERS)
    for mine, chip in zip(regset, HCTL_REGISTERS, strict=True):
        assert mine.offset == base + chip.offset
        assert (mine.name, mine.width, mine.access, mine.decoder) == (
            chip.name,
            chip.width,
            chip.access,
            chip.decoder,
        )
    assert regset.composites == HCTL_REGISTERS.composites
    assert regset.by_name("ACT_POS_LSB").offset == base + 0x14
    assert regset.at(base + 0x07) is regset.by_name("STATUS")


# -- Bit 3 Model 412 ------------------------------------------------------------------------------


def test_bit3_offsets() -> None:
    assert [(b.name, int(b)) for b in Bit3Reg] == [
        ("LOCAL_COMMAND", 0x00),
        ("LOCAL_INT_CONTROL", 0x01),
        ("LOCAL_STATUS", 0x02),
        ("LOCAL_INT_STATUS", 0x03),
        ("REMOTE_COMMAND_1", 0x08),
        ("REMOTE_COMMAND_2", 0x09),
        ("REMOTE_PAGE_LO", 0x0A),
        ("REMOTE_PAGE_HI", 0x0B),
        ("REMOTE_CARD_ID", 0x0C),
        ("REMOTE_ADDR_MOD", 0x0D),
        ("REMOTE_IACK", 0x0E),
        ("LEVEL2_VECTOR", 0x10),
    ]
    assert REMOTE_STATUS == 0x08
    assert BIT3_SPACE == 0x20 and BIT3_REGISTERS.size == 0x20
    assert [(r.name, r.offset, r.width, r.access) for r in BIT3_REGISTERS] == [
        ("LOCAL_COMMAND", 0x00, 1, RW),
        ("LOCAL_INT_CONTROL", 0x01, 1, RW),
        ("LOCAL_STATUS", 0x02, 1, R),
        ("LOCAL_INT_STATUS", 0x03, 1, R),
        ("REMOTE_STATUS", 0x08, 1, R),
        ("REMOTE_COMMAND_1", 0x08, 1, W),
        ("REMOTE_COMMAND_2", 0x09, 1, RW),
        ("REMOTE_PAGE_LO", 0x0A, 1, RW),
        ("REMOTE_PAGE_HI", 0x0B, 1, RW),
        ("REMOTE_CARD_ID", 0x0C, 1, R),
        ("REMOTE_ADDR_MOD", 0x0D, 1, RW),
        ("REMOTE_IACK", 0x0E, 2, R),
        ("LEVEL2_VECTOR", 0x10, 1, RW),
    ]


def test_bit3_bits() -> None:
    assert (LocalCommand.CLR_ERROR, LocalCommand.CLR_PR_INT, LocalCommand.SND_PT_INT) == (
        0x80,
        0x40,
        0x20,
    )
    assert LocalIntControl.INT_PENDING == 0x80
    assert LocalIntControl.NORMAL_INT_ENABLE == 0x40
    assert LocalIntControl.ERROR_INT_ENABLE == 0x20
    assert LocalIntControl.LINE_SELECT == 0x07
    assert LocalStatus.PARITY_ERROR == 0x80
    assert LocalStatus.REMOTE_BUS_ERROR == 0x40
    assert LocalStatus.PR_INT == 0x20
    assert LocalStatus.CARD_READY == 0x10
    assert LocalStatus.TIMEOUT == 0x04
    assert LocalStatus.LRC_ERROR == 0x02
    assert LocalStatus.NO_CONNECT == 0x01
    assert ERROR_MASK == 0xC6


def test_bit3_decoders() -> None:
    status = BIT3_REGISTERS.by_name("LOCAL_STATUS")
    assert status.decode(0xC0) == "0xC0 [REMOTE_BUS_ERROR PARITY_ERROR]"
    cint = BIT3_REGISTERS.by_name("LOCAL_INT_STATUS")
    assert cint.decode(0x0C) == "0x0C [IRQ 3 2]"
    assert cint.decode(0x00) == "0x00 []"


def test_iack_read_is_marked_as_having_an_effect() -> None:
    effects = [r.name for r in BIT3_REGISTERS if r.read_has_effect]
    assert effects == ["REMOTE_IACK"]


# -- every register set ---------------------------------------------------------------------------

ALL_SETS = [
    BIEXEC_REGISTERS,
    HCTL_REGISTERS,
    hctl_registers_for(Axis.AZIMUTH),
    hctl_registers_for(Axis.ELEVATION),
    BOARD_REGISTERS,
    BIT3_REGISTERS,
]


@pytest.mark.parametrize("regset", ALL_SETS, ids=lambda s: s.name)
def test_names_are_unique(regset: RegisterSet) -> None:
    names = [r.name for r in regset]
    assert len(names) == len(set(names))
    assert len({c.name for c in regset.composites}) == len(regset.composites)


@pytest.mark.parametrize("regset", ALL_SETS, ids=lambda s: s.name)
def test_registers_lie_inside_the_set(regset: RegisterSet) -> None:
    for reg in regset:
        assert regset.base <= reg.offset, reg.name
        assert reg.offset + reg.width <= regset.base + regset.size, reg.name
        assert reg.width in (1, 2, 4)
        assert reg.offset % reg.width == 0, reg.name  # one aligned access each


@pytest.mark.parametrize("regset", ALL_SETS, ids=lambda s: s.name)
def test_registers_are_in_offset_order(regset: RegisterSet) -> None:
    offsets = [r.offset for r in regset]
    assert offsets == sorted(offsets)


@pytest.mark.parametrize("regset", ALL_SETS, ids=lambda s: s.name)
def test_only_read_write_pairs_share_bytes(regset: RegisterSet) -> None:
    for a, b in itertools.combinations(regset, 2):
        if a.offset < b.offset + b.width and b.offset < a.offset + a.width:
            assert {a.access, b.access} == {R, W}, (a.name, b.name)


@pytest.mark.parametrize("regset", ALL_SETS, ids=lambda s: s.name)
def test_composites_name_readable_registers(regset: RegisterSet) -> None:
    for comp in regset.composites:
        assert sorted(comp.read_order) == sorted(comp.parts)
        for name in comp.parts:
            assert regset.by_name(name).access.readable


# -- describe.py helpers --------------------------------------------------------------------------


def test_register_set_lookups() -> None:
    assert BIT3_REGISTERS.at(0x08) is BIT3_REGISTERS.by_name("REMOTE_STATUS")
    assert BIT3_REGISTERS.at(0x05) is None
    assert BIT3_REGISTERS.covering(0x0F) is BIT3_REGISTERS.by_name("REMOTE_IACK")
    assert BIT3_REGISTERS.covering(0x11) is None
    with pytest.raises(KeyError):
        BIT3_REGISTERS.by_name("NOPE")


def test_access_flags() -> None:
    assert (R.readable, R.writable) == (True, False)
    assert (W.readable, W.writable) == (False, True)
    assert (RW.readable, RW.writable) == (True, True)


def test_decoder_helpers() -> None:
    assert hex_decoder(2)(0x1F) == "0x001F"
    assert hex_decoder(1)(-1) == "0xFF"
    assert signed_decoder(8)(0x80) == "-128"
    assert signed_decoder(16)(0x7FFF) == "32767"
    assert flags_decoder([(0x01, "A"), (0x80, "H")])(0x81) == "0x81 [A H]"


def test_register_default_decoder_and_sign() -> None:
    reg = Register("X", 0, 2, RW, "")
    assert reg.decode(0xAB) == "0x00AB"
    assert reg.to_signed(0xFFFF) == 0xFFFF
    signed = Register("Y", 0, 2, RW, "", signed=True)
    assert signed.to_signed(0xFFFF) == -1
    assert signed.to_signed(-1) == -1
