"""The HP HCTL-1000 motion-control IC, as the host sees it: 64 byte-wide registers.

Facts are from the HCTL-1100/1101 datasheets (register compatible as far as is known; see
``docs/design.md``). Multi-byte quantities are spread over byte registers and some reads
and writes have side effects: reading R14H latches the actual position for R13H/R12H, writing R0EH
commits the command position. Always access them one byte at a time, in the documented order.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping

from regs.describe import (
    Access,
    Combine,
    Composite,
    Register,
    RegisterSet,
    flags_decoder,
    signed_decoder,
)

__all__ = [
    "COUNTS_PER_REV",
    "F_CLK_HZ",
    "HCTL_REGISTERS",
    "HCTL_SPACE",
    "MOTION_LIMIT_COUNTS",
    "SAMPLE_TIMER_MIN",
    "Flag",
    "ProgramCounter",
    "Reg",
    "Status",
    "accel_from_reg",
    "accel_to_reg",
    "counts_to_deg",
    "decode_flag_write",
    "flag_write",
    "motor_command_from_signed",
    "motor_command_to_signed",
    "pos24_from_lsb_first",
    "pos24_from_msb_first",
    "pos24_lsb_first",
    "pos24_msb_first",
    "sample_period",
    "sample_timer_for",
    "to_signed24",
]

F_CLK_HZ = 2_000_000
"""The chip clock on our board (interpretation)."""

COUNTS_PER_REV = 4096
"""Encoder counts per revolution of the head: binary degrees, 0x1000 = 360 degrees."""

MOTION_LIMIT_COUNTS = 0x1000
"""_Scan_limit: no destination may lie outside +-0x1000 counts (+-360 degrees)."""

HCTL_SPACE = 0x40
"""Bytes of register space per chip (R00H..R3FH)."""


class Reg(enum.IntEnum):
    """Register numbers (the HP ``RxxH`` address)."""

    FLAG = 0x00
    PROGRAM_COUNTER = 0x05
    STATUS = 0x07
    MOTOR_COMMAND = 0x08
    PWM_COMMAND = 0x09
    CMD_POS_MSB = 0x0C
    CMD_POS_MID = 0x0D
    CMD_POS_LSB = 0x0E
    SAMPLE_TIMER = 0x0F
    ACT_POS_MSB = 0x12
    ACT_POS_MID = 0x13
    ACT_POS_LSB = 0x14
    PRESET_MSB = 0x15
    PRESET_MID = 0x16
    PRESET_LSB = 0x17
    COMMUTATOR_RING = 0x18
    COMMUTATOR_VEL_TIMER = 0x19
    COMMUTATOR_X = 0x1A
    COMMUTATOR_Y = 0x1B
    COMMUTATOR_OFFSET = 0x1C
    COMMUTATOR_MAX_ADVANCE = 0x1F
    FILTER_ZERO = 0x20
    FILTER_POLE = 0x21
    FILTER_GAIN = 0x22
    CMD_VEL_LSB = 0x23
    CMD_VEL_MSB = 0x24
    ACCEL_LSB = 0x26
    ACCEL_MSB = 0x27
    MAX_VELOCITY = 0x28
    FINAL_POS_LSB = 0x29
    FINAL_POS_MID = 0x2A
    FINAL_POS_MSB = 0x2B
    ACT_VEL_LSB = 0x34
    ACT_VEL_MSB = 0x35
    INT_VELOCITY = 0x3C


class Flag(enum.IntEnum):
    """Flag numbers in R00H; F0, F3 and F5 select the control mode (one at a time)."""

    F0_TRAPEZOID = 0
    F1_INIT_IDLE = 1
    F2_UNIPOLAR = 2
    F3_PROPORTIONAL_VELOCITY = 3
    F4_HOLD_COMMUTATOR = 4
    F5_INTEGRAL_VELOCITY = 5


def flag_write(flag: Flag | int, value: bool) -> int:
    """The R00H byte that sets (``value``) or clears one flag: bit 3 = value, bits 2..0 = flag."""
    if not 0 <= int(flag) <= 7:
        raise ValueError(f"flag number {flag} out of range 0..7")
    return (0x08 if value else 0x00) | int(flag)


def decode_flag_write(byte: int) -> tuple[int, bool]:
    """(flag number, value) carried by a byte written to R00H; upper bits are ignored."""
    return byte & 0x07, bool(byte & 0x08)


class Status(enum.IntFlag):
    """Status register R07H. STOP_CLEAR and LIMIT_CLEAR are active low: 0 means triggered."""

    PWM_SIGN_INHIBIT = 0x01
    COMMUTATOR_4_PHASE = 0x02
    COMMUTATOR_FULL_COUNT = 0x04
    RESERVED_ZERO = 0x08
    PROFILE = 0x10
    INIT_IDLE = 0x20
    STOP_CLEAR = 0x40
    LIMIT_CLEAR = 0x80


STATUS_WRITABLE_MASK = 0x0F
"""Only the low four status bits can be written (bit 3 must be written 0)."""


SAMPLE_TIMER_MIN = 0x07
"""Smallest R0FH the datasheet's range allows: 64 us at 2 MHz (the range is 64 us..2048 us)."""


class ProgramCounter(enum.IntEnum):
    """Values written to R05H."""

    RESET = 0x00
    INIT_IDLE = 0x01
    ALIGN = 0x02
    CONTROL = 0x03


def sample_period(timer: int, f_clk: float = F_CLK_HZ) -> float:
    """Seconds per sample: t = 16 (T + 1) / f_clk."""
    if not 0 <= timer <= 0xFF:
        raise ValueError(f"sample timer {timer} out of range 0..255")
    return 16.0 * (timer + 1) / f_clk


def sample_timer_for(period_s: float, f_clk: float = F_CLK_HZ) -> int:
    """R0FH value whose period is closest to ``period_s``: T = f_clk t / 16 - 1."""
    timer = round(f_clk * period_s / 16.0 - 1.0)
    if not SAMPLE_TIMER_MIN <= timer <= 0xFF:
        raise ValueError(f"a {period_s * 1e3:.3f} ms sample period is out of the chip's range")
    return timer


def accel_to_reg(counts_per_sample2: float) -> int:
    """8.8 fixed point for R27H (integer, 00H..7FH) and R26H (fraction)."""
    raw = round(counts_per_sample2 * 256.0)
    if not 0 <= raw <= 0x7FFF:
        raise ValueError(f"acceleration {counts_per_sample2} out of range 0..127.996")
    return raw


def accel_from_reg(raw: int) -> float:
    """Counts per sample squared from the 16-bit 8.8 register pair."""
    return (raw & 0x7FFF) / 256.0


def to_signed24(raw: int) -> int:
    """Two's complement reading of a 24-bit quantity."""
    raw &= 0xFF_FFFF
    return raw - 0x100_0000 if raw & 0x80_0000 else raw


def _check24(value: int) -> int:
    if not -0x80_0000 <= value <= 0xFF_FFFF:
        raise ValueError(f"position {value} does not fit 24 bits")
    return value & 0xFF_FFFF


def pos24_msb_first(value: int) -> tuple[int, int, int]:
    """(MSB, mid, LSB) bytes: the order of R0CH..R0EH and R12H..R14H."""
    raw = _check24(value)
    return (raw >> 16) & 0xFF, (raw >> 8) & 0xFF, raw & 0xFF


def pos24_lsb_first(value: int) -> tuple[int, int, int]:
    """(LSB, mid, MSB) bytes: the order of the final position R29H..R2BH."""
    msb, mid, lsb = pos24_msb_first(value)
    return lsb, mid, msb


def pos24_from_msb_first(msb: int, mid: int, lsb: int) -> int:
    """Signed counts from three bytes in MSB-first order."""
    return to_signed24(((msb & 0xFF) << 16) | ((mid & 0xFF) << 8) | (lsb & 0xFF))


def pos24_from_lsb_first(lsb: int, mid: int, msb: int) -> int:
    """Signed counts from three bytes in LSB-first order."""
    return pos24_from_msb_first(msb, mid, lsb)


def motor_command_to_signed(byte: int) -> int:
    """R08H is offset binary: 80H = 0, FFH = +127, 00H = -128."""
    return (byte & 0xFF) - 0x80


def motor_command_from_signed(value: float) -> int:
    """The clamped offset-binary byte the chip writes to R08H for a filter output."""
    clamped = max(-128, min(127, int(value)))
    return clamped + 0x80


def counts_to_deg(counts: float) -> float:
    """Binary degrees to degrees (4096 counts per revolution)."""
    return counts * 360.0 / COUNTS_PER_REV


def _deg_text(value: int) -> str:
    return f"{value} counts ({counts_to_deg(value):+.2f} deg)"


def _accel_text(value: int) -> str:
    return f"0x{value:04X} ({accel_from_reg(value):.4f} counts/sample^2)"


_STATUS_NAMES = [(int(bit), bit.name or "") for bit in Status]
_FLAG_NAMES = [(1 << int(f), f.name) for f in Flag]


def _mc_text(value: int) -> str:
    return f"0x{value:02X} ({motor_command_to_signed(value):+d})"


def _timer_text(value: int) -> str:
    return f"0x{value:02X} ({sample_period(value) * 1e3:.3f} ms)"


def _pc_text(value: int) -> str:
    try:
        return f"0x{value:02X} ({ProgramCounter(value).name})"
    except ValueError:
        return f"0x{value:02X}"


_R, _W, _RW = Access.R, Access.W, Access.RW

_TABLE: list[tuple[Reg, Access, str]] = [
    (Reg.FLAG, _W, "flag register: write bit3 = set/clear, bits2..0 = flag number"),
    (Reg.PROGRAM_COUNTER, _W, "program counter: 00 reset, 01 init/idle, 02 align, 03 control"),
    (Reg.STATUS, _RW, "status; only bits 3..0 writable"),
    (Reg.MOTOR_COMMAND, _RW, "motor command port, offset binary (80H = 0)"),
    (Reg.PWM_COMMAND, _RW, "PWM motor command"),
    (Reg.CMD_POS_MSB, _RW, "command position MSB"),
    (Reg.CMD_POS_MID, _RW, "command position mid"),
    (Reg.CMD_POS_LSB, _RW, "command position LSB; writing it commits all 24 bits"),
    (Reg.SAMPLE_TIMER, _RW, "sample timer T: t = 16(T+1)/f_clk"),
    (Reg.ACT_POS_MSB, _R, "actual position MSB (latched by reading R14H)"),
    (Reg.ACT_POS_MID, _RW, "actual position mid (latched); any write clears the counter"),
    (Reg.ACT_POS_LSB, _R, "actual position LSB; reading it latches all 24 bits"),
    (Reg.PRESET_MSB, _W, "actual position preset MSB (HCTL-1100 only)"),
    (Reg.PRESET_MID, _W, "actual position preset mid (HCTL-1100 only)"),
    (Reg.PRESET_LSB, _W, "actual position preset LSB; loads all 24 bits (HCTL-1100 only)"),
    (Reg.COMMUTATOR_RING, _RW, "commutator ring"),
    (Reg.COMMUTATOR_VEL_TIMER, _RW, "commutator velocity timer"),
    (Reg.COMMUTATOR_X, _RW, "commutator X"),
    (Reg.COMMUTATOR_Y, _RW, "commutator Y (phase overlap)"),
    (Reg.COMMUTATOR_OFFSET, _RW, "commutator offset"),
    (Reg.COMMUTATOR_MAX_ADVANCE, _RW, "commutator maximum phase advance"),
    (Reg.FILTER_ZERO, _RW, "filter zero A (A/256)"),
    (Reg.FILTER_POLE, _RW, "filter pole B (B/256)"),
    (Reg.FILTER_GAIN, _RW, "filter gain K"),
    (Reg.CMD_VEL_LSB, _RW, "command velocity LSB (12.4, proportional velocity mode)"),
    (Reg.CMD_VEL_MSB, _RW, "command velocity MSB (12.4, proportional velocity mode)"),
    (Reg.ACCEL_LSB, _RW, "command acceleration fraction (8.8)"),
    (Reg.ACCEL_MSB, _RW, "command acceleration integer (8.8, 00H..7FH)"),
    (Reg.MAX_VELOCITY, _RW, "maximum velocity for the trapezoid, counts/sample (00H..7FH)"),
    (Reg.FINAL_POS_LSB, _RW, "trapezoid final position LSB"),
    (Reg.FINAL_POS_MID, _RW, "trapezoid final position mid"),
    (Reg.FINAL_POS_MSB, _RW, "trapezoid final position MSB"),
    (Reg.ACT_VEL_LSB, _R, "actual velocity LSB (proportional velocity mode)"),
    (Reg.ACT_VEL_MSB, _R, "actual velocity MSB (proportional velocity mode)"),
    (Reg.INT_VELOCITY, _RW, "command velocity, integral velocity mode (signed counts/sample)"),
]

_DECODERS = {
    Reg.STATUS: flags_decoder(_STATUS_NAMES),
    Reg.MOTOR_COMMAND: _mc_text,
    Reg.SAMPLE_TIMER: _timer_text,
    Reg.PROGRAM_COUNTER: _pc_text,
    Reg.INT_VELOCITY: signed_decoder(8),
}


def _combine_msb(msb: str, mid: str, lsb: str) -> Combine:
    def combine(values: Mapping[str, int]) -> int:
        return pos24_from_msb_first(values[msb], values[mid], values[lsb])

    return combine


def _combine16(lsb: str, msb: str, signed: bool) -> Combine:
    def combine(values: Mapping[str, int]) -> int:
        raw = (values[msb] << 8) | values[lsb]
        return raw - 0x10000 if signed and raw & 0x8000 else raw

    return combine


HCTL_REGISTERS = RegisterSet(
    name="HCTL-1000",
    size=HCTL_SPACE,
    registers=tuple(
        Register(
            name=reg.name,
            offset=int(reg),
            width=1,
            access=acc,
            meaning=text,
            decoder=_DECODERS.get(reg),
        )
        for reg, acc, text in _TABLE
    ),
    composites=(
        Composite(
            "actual_position",
            ("ACT_POS_MSB", "ACT_POS_MID", "ACT_POS_LSB"),
            ("ACT_POS_LSB", "ACT_POS_MID", "ACT_POS_MSB"),
            _combine_msb("ACT_POS_MSB", "ACT_POS_MID", "ACT_POS_LSB"),
            _deg_text,
            "R12H..R14H, read R14H first (it latches)",
        ),
        Composite(
            "command_position",
            ("CMD_POS_MSB", "CMD_POS_MID", "CMD_POS_LSB"),
            ("CMD_POS_MSB", "CMD_POS_MID", "CMD_POS_LSB"),
            _combine_msb("CMD_POS_MSB", "CMD_POS_MID", "CMD_POS_LSB"),
            _deg_text,
            "R0CH..R0EH",
        ),
        Composite(
            "final_position",
            ("FINAL_POS_LSB", "FINAL_POS_MID", "FINAL_POS_MSB"),
            ("FINAL_POS_LSB", "FINAL_POS_MID", "FINAL_POS_MSB"),
            _combine_msb("FINAL_POS_MSB", "FINAL_POS_MID", "FINAL_POS_LSB"),
            _deg_text,
            "R29H..R2BH, LSB first",
        ),
        Composite(
            "acceleration",
            ("ACCEL_LSB", "ACCEL_MSB"),
            ("ACCEL_LSB", "ACCEL_MSB"),
            _combine16("ACCEL_LSB", "ACCEL_MSB", signed=False),
            _accel_text,
            "R26H/R27H, 8.8 counts/sample^2",
        ),
        Composite(
            "command_velocity",
            ("CMD_VEL_LSB", "CMD_VEL_MSB"),
            ("CMD_VEL_LSB", "CMD_VEL_MSB"),
            _combine16("CMD_VEL_LSB", "CMD_VEL_MSB", signed=True),
            lambda v: f"{v / 16.0:+.4f} counts/sample",
            "R23H/R24H, 12.4 fixed point",
        ),
        Composite(
            "actual_velocity",
            ("ACT_VEL_LSB", "ACT_VEL_MSB"),
            ("ACT_VEL_LSB", "ACT_VEL_MSB"),
            _combine16("ACT_VEL_LSB", "ACT_VEL_MSB", signed=True),
            lambda v: f"{v:+d} counts/sample",
            "R34H/R35H",
        ),
    ),
)
