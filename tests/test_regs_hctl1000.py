"""The HCTL-1000 description pinned against reference/hardware.md section 1 (explicit numbers)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from regs.describe import Access
from regs.hctl1000 import (
    COUNTS_PER_REV,
    F_CLK_HZ,
    HCTL_REGISTERS,
    HCTL_SPACE,
    MOTION_LIMIT_COUNTS,
    SAMPLE_TIMER_MIN,
    STATUS_WRITABLE_MASK,
    Flag,
    ProgramCounter,
    Reg,
    Status,
    accel_from_reg,
    accel_to_reg,
    counts_to_deg,
    decode_flag_write,
    flag_write,
    motor_command_from_signed,
    motor_command_to_signed,
    pos24_from_lsb_first,
    pos24_from_msb_first,
    pos24_lsb_first,
    pos24_msb_first,
    sample_period,
    sample_timer_for,
    to_signed24,
)

R, W, RW = Access.R, Access.W, Access.RW

# hardware.md table 1.3: (name, address, host access)
REGISTER_MAP = [
    ("FLAG", 0x00, W),
    ("PROGRAM_COUNTER", 0x05, W),
    ("STATUS", 0x07, RW),
    ("MOTOR_COMMAND", 0x08, RW),
    ("PWM_COMMAND", 0x09, RW),
    ("CMD_POS_MSB", 0x0C, RW),
    ("CMD_POS_MID", 0x0D, RW),
    ("CMD_POS_LSB", 0x0E, RW),
    ("SAMPLE_TIMER", 0x0F, RW),
    ("ACT_POS_MSB", 0x12, R),
    ("ACT_POS_MID", 0x13, RW),  # a write clears the counter
    ("ACT_POS_LSB", 0x14, R),
    ("PRESET_MSB", 0x15, W),
    ("PRESET_MID", 0x16, W),
    ("PRESET_LSB", 0x17, W),
    ("COMMUTATOR_RING", 0x18, RW),
    ("COMMUTATOR_VEL_TIMER", 0x19, RW),
    ("COMMUTATOR_X", 0x1A, RW),
    ("COMMUTATOR_Y", 0x1B, RW),
    ("COMMUTATOR_OFFSET", 0x1C, RW),
    ("COMMUTATOR_MAX_ADVANCE", 0x1F, RW),
    ("FILTER_ZERO", 0x20, RW),
    ("FILTER_POLE", 0x21, RW),
    ("FILTER_GAIN", 0x22, RW),
    ("CMD_VEL_LSB", 0x23, RW),
    ("CMD_VEL_MSB", 0x24, RW),
    ("ACCEL_LSB", 0x26, RW),
    ("ACCEL_MSB", 0x27, RW),
    ("MAX_VELOCITY", 0x28, RW),
    ("FINAL_POS_LSB", 0x29, RW),
    ("FINAL_POS_MID", 0x2A, RW),
    ("FINAL_POS_MSB", 0x2B, RW),
    ("ACT_VEL_LSB", 0x34, R),
    ("ACT_VEL_MSB", 0x35, R),
    ("INT_VELOCITY", 0x3C, RW),
]


def test_register_map_matches_the_datasheet_table() -> None:
    assert [(r.name, r.offset, r.access) for r in HCTL_REGISTERS] == REGISTER_MAP
    assert [(r.name, int(r)) for r in Reg] == [(n, a) for n, a, _ in REGISTER_MAP]
    assert all(r.width == 1 for r in HCTL_REGISTERS)
    assert HCTL_SPACE == 0x40 and HCTL_REGISTERS.size == 0x40


def test_clock_and_counts() -> None:
    assert F_CLK_HZ == 2_000_000
    assert COUNTS_PER_REV == 4096
    assert MOTION_LIMIT_COUNTS == 0x1000
    assert counts_to_deg(0x1000) == 360.0
    assert counts_to_deg(1024) == 90.0
    assert counts_to_deg(-2048) == -180.0


# -- flags, status, program counter ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("flag", "value", "byte"),
    [
        (Flag.F0_TRAPEZOID, True, 0x08),
        (Flag.F0_TRAPEZOID, False, 0x00),
        (Flag.F3_PROPORTIONAL_VELOCITY, True, 0x0B),
        (Flag.F3_PROPORTIONAL_VELOCITY, False, 0x03),
        (Flag.F5_INTEGRAL_VELOCITY, False, 0x05),
        (Flag.F5_INTEGRAL_VELOCITY, True, 0x0D),
        (Flag.F1_INIT_IDLE, True, 0x09),
    ],
)
def test_flag_write_encoding(flag: Flag, value: bool, byte: int) -> None:
    assert flag_write(flag, value) == byte
    assert decode_flag_write(byte) == (int(flag), value)


def test_flag_numbers() -> None:
    assert [int(f) for f in Flag] == [0, 1, 2, 3, 4, 5]


def test_decode_flag_write_ignores_upper_bits() -> None:
    assert decode_flag_write(0xF8) == (0, True)
    assert decode_flag_write(0x73) == (3, False)


def test_flag_write_refuses_bad_numbers() -> None:
    with pytest.raises(ValueError):
        flag_write(8, True)
    with pytest.raises(ValueError):
        flag_write(-1, False)


def test_status_bits() -> None:
    assert Status.PWM_SIGN_INHIBIT == 0x01
    assert Status.COMMUTATOR_4_PHASE == 0x02
    assert Status.COMMUTATOR_FULL_COUNT == 0x04
    assert Status.RESERVED_ZERO == 0x08
    assert Status.PROFILE == 0x10
    assert Status.INIT_IDLE == 0x20
    assert Status.STOP_CLEAR == 0x40
    assert Status.LIMIT_CLEAR == 0x80
    assert STATUS_WRITABLE_MASK == 0x0F


def test_status_decoder_names_the_set_bits() -> None:
    status = HCTL_REGISTERS.by_name("STATUS")
    assert status.decode(0xE0) == "0xE0 [INIT_IDLE STOP_CLEAR LIMIT_CLEAR]"
    assert status.decode(0x00) == "0x00 []"


def test_program_counter_values() -> None:
    assert [(p.name, int(p)) for p in ProgramCounter] == [
        ("RESET", 0x00),
        ("INIT_IDLE", 0x01),
        ("ALIGN", 0x02),
        ("CONTROL", 0x03),
    ]


# -- sample timer ---------------------------------------------------------------------------------


def test_sample_period_of_the_init_record() -> None:
    assert sample_period(0xAF) == pytest.approx(1.408e-3, abs=1e-12)
    assert HCTL_REGISTERS.by_name("SAMPLE_TIMER").decode(0xAF) == "0xAF (1.408 ms)"


def test_sample_period_range_at_2_mhz() -> None:
    assert sample_period(SAMPLE_TIMER_MIN) == pytest.approx(64e-6, abs=1e-12)
    assert sample_period(0xFF) == pytest.approx(2048e-6, abs=1e-12)
    assert sample_period(0xFF, f_clk=1_000_000) == pytest.approx(4096e-6, abs=1e-12)
    with pytest.raises(ValueError):
        sample_period(0x100)


def test_sample_timer_for() -> None:
    assert sample_timer_for(1e-3) == 124 == 0x7C
    assert sample_timer_for(1.408e-3) == 0xAF
    assert sample_timer_for(64e-6) == 7
    assert sample_timer_for(2048e-6) == 255
    for bad in (56e-6, 10e-6, 2.1e-3):
        with pytest.raises(ValueError):
            sample_timer_for(bad)


@given(st.integers(min_value=SAMPLE_TIMER_MIN, max_value=0xFF))
def test_sample_timer_round_trip(timer: int) -> None:
    assert sample_timer_for(sample_period(timer)) == timer


# -- acceleration 8.8 -----------------------------------------------------------------------------


def test_acceleration_fixed_point() -> None:
    assert accel_from_reg(0x3322) == 51.1328125
    assert accel_from_reg(0x2000) == 32.0
    assert accel_to_reg(51.1328125) == 0x3322
    assert accel_to_reg(32.0) == 0x2000
    assert accel_to_reg(0.5) == 0x0080


def test_acceleration_range() -> None:
    assert accel_to_reg(127.99609375) == 0x7FFF
    with pytest.raises(ValueError):
        accel_to_reg(128.0)
    with pytest.raises(ValueError):
        accel_to_reg(-1.0)


@given(st.integers(min_value=0, max_value=0x7FFF))
def test_acceleration_round_trip(raw: int) -> None:
    assert accel_to_reg(accel_from_reg(raw)) == raw


# -- 24-bit positions -----------------------------------------------------------------------------


def test_positions_byte_orders() -> None:
    assert pos24_msb_first(0x123456) == (0x12, 0x34, 0x56)
    assert pos24_lsb_first(0x123456) == (0x56, 0x34, 0x12)
    assert pos24_from_msb_first(0x12, 0x34, 0x56) == 0x123456
    assert pos24_from_lsb_first(0x56, 0x34, 0x12) == 0x123456


def test_positions_sign() -> None:
    assert pos24_msb_first(-1) == (0xFF, 0xFF, 0xFF)
    assert pos24_lsb_first(-2048) == (0x00, 0xF8, 0xFF)
    assert pos24_from_msb_first(0xFF, 0xFF, 0xFF) == -1
    assert pos24_from_msb_first(0x80, 0x00, 0x00) == -0x80_0000
    assert pos24_from_msb_first(0x7F, 0xFF, 0xFF) == 0x7F_FFFF
    assert to_signed24(0xFFF000) == -0x1000


def test_positions_out_of_range() -> None:
    for bad in (0x100_0000, -0x80_0001):
        with pytest.raises(ValueError):
            pos24_msb_first(bad)


@given(st.integers(min_value=-0x80_0000, max_value=0x7F_FFFF))
def test_positions_round_trip(counts: int) -> None:
    assert pos24_from_msb_first(*pos24_msb_first(counts)) == counts
    assert pos24_from_lsb_first(*pos24_lsb_first(counts)) == counts
    assert pos24_lsb_first(counts) == tuple(reversed(pos24_msb_first(counts)))


def test_position_composites() -> None:
    comps = {c.name: c for c in HCTL_REGISTERS.composites}
    actual = comps["actual_position"]
    assert actual.read_order[0] == "ACT_POS_LSB"  # R14H latches the other two
    assert actual.read_order == ("ACT_POS_LSB", "ACT_POS_MID", "ACT_POS_MSB")
    values = {"ACT_POS_MSB": 0xFF, "ACT_POS_MID": 0xFC, "ACT_POS_LSB": 0x00}
    assert actual.combine(values) == -1024
    assert actual.decoder(-1024) == "-1024 counts (-90.00 deg)"
    final = comps["final_position"]
    lsb_first = {"FINAL_POS_LSB": 0x56, "FINAL_POS_MID": 0x34, "FINAL_POS_MSB": 0x12}
    assert final.combine(lsb_first) == 0x123456
    command = comps["command_position"]
    msb_first = {"CMD_POS_MSB": 0x00, "CMD_POS_MID": 0x03, "CMD_POS_LSB": 0xE8}
    assert command.combine(msb_first) == 1000
    accel = comps["acceleration"]
    assert accel.combine({"ACCEL_LSB": 0x22, "ACCEL_MSB": 0x33}) == 0x3322
    assert accel.decoder(0x3322) == "0x3322 (51.1328 counts/sample^2)"
    velocity = comps["command_velocity"]
    assert velocity.combine({"CMD_VEL_LSB": 0xE0, "CMD_VEL_MSB": 0xFF}) == -32
    assert velocity.decoder(-32) == "-2.0000 counts/sample"


# -- motor command --------------------------------------------------------------------------------


def test_motor_command_offset_binary() -> None:
    assert motor_command_to_signed(0x80) == 0
    assert motor_command_to_signed(0xFF) == 127
    assert motor_command_to_signed(0x00) == -128
    assert motor_command_to_signed(0x01) == -127
    assert motor_command_from_signed(0) == 0x80
    assert motor_command_from_signed(127) == 0xFF
    assert motor_command_from_signed(-128) == 0x00
    assert HCTL_REGISTERS.by_name("MOTOR_COMMAND").decode(0x90) == "0x90 (+16)"


def test_motor_command_clamps() -> None:
    assert motor_command_from_signed(1000.0) == 0xFF
    assert motor_command_from_signed(128) == 0xFF
    assert motor_command_from_signed(-129) == 0x00
    assert motor_command_from_signed(-1e9) == 0x00
    assert motor_command_from_signed(12.7) == 0x8C


@given(st.integers(min_value=-128, max_value=127))
def test_motor_command_round_trip(value: int) -> None:
    assert motor_command_to_signed(motor_command_from_signed(value)) == value


def test_integral_velocity_is_signed() -> None:
    assert HCTL_REGISTERS.by_name("INT_VELOCITY").decode(0xFE) == "-2"
