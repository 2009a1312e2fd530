"""BIEXEC_COM pinned: field offsets, size, packing, big-endian bytes, command codes, PARAM text."""

from __future__ import annotations

import ctypes
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from regs import biexec
from regs.biexec import (
    ACQ_LINE_END,
    ACQ_LINE_STARTUP,
    BIEXEC_COM_SIZE,
    BIEXEC_PARAM_SIZE,
    BIEXEC_REGISTERS,
    BiCommand,
    BiexecCom,
    BiStatus,
    decode_param,
    encode_param,
)
from regs.describe import Access

FIELD_OFFSETS = {
    "COMMAND": 0,
    "STATUS": 2,
    "ACQ_LINE": 4,
    "PARAM": 6,
    "CURRENT_FRAME": 70,
    "CURRENT_PROJ": 72,
    "_Biris_cmd_int_enable": 74,
    "_Biris_data_int_enable": 76,
    "_Biris_motor_access": 78,
}


def test_field_offsets_and_sizes() -> None:
    assert [name for name, *_ in BiexecCom._fields_] == list(FIELD_OFFSETS)
    for name, offset in FIELD_OFFSETS.items():
        field = getattr(BiexecCom, name)
        assert field.offset == offset, name
        assert field.size == (64 if name == "PARAM" else 2), name
    assert BiexecCom.PARAM.offset + BiexecCom.PARAM.size == 70


def test_size_and_packing() -> None:
    assert ctypes.sizeof(BiexecCom) == 80
    assert BIEXEC_COM_SIZE == 80
    assert BIEXEC_PARAM_SIZE == 64
    assert BiexecCom._pack_ == 2
    assert BiexecCom._layout_ == "ms"
    assert issubclass(BiexecCom, ctypes.BigEndianStructure)


def test_offset_constants_match_the_structure() -> None:
    assert (
        biexec.OFF_COMMAND,
        biexec.OFF_STATUS,
        biexec.OFF_ACQ_LINE,
        biexec.OFF_PARAM,
        biexec.OFF_CURRENT_FRAME,
        biexec.OFF_CURRENT_PROJ,
        biexec.OFF_CMD_INT_ENABLE,
        biexec.OFF_DATA_INT_ENABLE,
        biexec.OFF_MOTOR_ACCESS,
    ) == (0, 2, 4, 6, 70, 72, 74, 76, 78)


def test_writes_land_big_endian_at_their_offsets() -> None:
    buf = bytearray(80)
    com = BiexecCom.from_buffer(buf)
    com.COMMAND = 0x0102
    com.STATUS = -2
    com.ACQ_LINE = ACQ_LINE_END
    com.PARAM = b"0x00C01000"
    com.CURRENT_FRAME = 0x1234
    com.CURRENT_PROJ = 0x0506
    com._Biris_cmd_int_enable = 1
    com._Biris_data_int_enable = 0x0708
    com._Biris_motor_access = -1
    expected = struct.pack(
        ">hhh64shhhhh", 0x0102, -2, -128, b"0x00C01000", 0x1234, 0x0506, 1, 0x0708, -1
    )
    assert bytes(buf) == expected
    assert buf[0:2] == b"\x01\x02"
    assert buf[4:6] == b"\xff\x80"
    assert buf[6:16] == b"0x00C01000" and buf[16] == 0
    assert buf[78:80] == b"\xff\xff"


def test_reads_see_the_bytes_big_endian() -> None:
    buf = bytearray(80)
    com = BiexecCom.from_buffer(buf)
    buf[0:2] = b"\x00\x05"
    buf[4:6] = b"\xff\xff"
    buf[70:72] = b"\x01\x00"
    buf[6:9] = b"42\x00"
    assert com.COMMAND == 5
    assert com.ACQ_LINE == -1
    assert com.CURRENT_FRAME == 256
    assert com.PARAM == b"42"


def test_command_codes() -> None:
    assert [c.name for c in BiCommand] == [
        "BI_BOOT",
        "BI_GET_VME_ADDR_DIST",
        "BI_GET_VME_ADDR_AZIM",
        "BI_GET_VME_INC_FRAME",
        "BI_ACQUIRE",
        "BI_START_CONTINUOUS",
        "BI_STOP_CONTINUOUS",
        "BI_LOAD_LUT",
    ]
    codes = [int(c) for c in BiCommand]
    assert all(code != 0 for code in codes)  # 0 means "done" in COMMAND
    assert len(set(codes)) == len(codes)
    assert all(-0x8000 <= code <= 0x7FFF for code in codes)


def test_status_values() -> None:
    assert BiStatus.OK == 0
    assert all(s != 0 for s in BiStatus if s is not BiStatus.OK)


def test_acq_line_constants() -> None:
    assert ACQ_LINE_STARTUP == -1
    assert ACQ_LINE_END == -128


# -- PARAM ------------------------------------------------------------------------------------


def test_encode_param_pads_with_nul() -> None:
    raw = encode_param("12")
    assert raw == b"12" + b"\0" * 62
    assert len(raw) == BIEXEC_PARAM_SIZE
    assert encode_param("") == b"\0" * 64


def test_encode_param_leaves_room_for_the_nul() -> None:
    assert encode_param("x" * 63)[63] == 0
    with pytest.raises(ValueError, match="does not fit"):
        encode_param("x" * 64)


def test_encode_param_refuses_non_ascii() -> None:
    with pytest.raises(ValueError):
        encode_param("/dd/users/bïris")


def test_decode_param_stops_at_the_first_nul() -> None:
    assert decode_param(b"0x00C01000\0garbage" + b"\0" * 46) == "0x00C01000"
    assert decode_param(b"\0" * 64) == ""


def test_decode_param_refuses_missing_nul() -> None:
    with pytest.raises(ValueError, match="NUL"):
        decode_param(b"x" * 64)


def test_decode_param_refuses_non_ascii() -> None:
    with pytest.raises(ValueError):
        decode_param(b"\xff\xfe\0" + b"\0" * 61)


@given(st.text(alphabet=st.characters(min_codepoint=1, max_codepoint=127), max_size=63))
def test_param_round_trip(text: str) -> None:
    assert decode_param(encode_param(text)) == text


# -- the register description ---------------------------------------------------------------------


def test_register_set_describes_every_scalar_field() -> None:
    assert BIEXEC_REGISTERS.size == 80
    assert [(r.name, r.offset, r.width) for r in BIEXEC_REGISTERS] == [
        (name, offset, 2) for name, offset in FIELD_OFFSETS.items() if name != "PARAM"
    ]


def test_register_access_and_signedness() -> None:
    read_only = {"STATUS", "ACQ_LINE", "CURRENT_FRAME", "CURRENT_PROJ"}
    for reg in BIEXEC_REGISTERS:
        assert reg.access is (Access.R if reg.name in read_only else Access.RW), reg.name
        assert reg.signed, reg.name  # every field is an Int_16
    acq = BIEXEC_REGISTERS.by_name("ACQ_LINE")
    assert acq.to_signed(0xFF80) == -128
    assert acq.to_signed(0x0005) == 5


@pytest.mark.parametrize(
    ("name", "value", "text"),
    [
        ("COMMAND", 0, "0 (idle)"),
        ("COMMAND", 5, "5 (BI_ACQUIRE)"),
        ("COMMAND", 0x7777, "30583 (unknown code)"),
        ("STATUS", 0, "0 (OK)"),
        ("STATUS", 1, "1 (UNKNOWN_COMMAND)"),
        ("STATUS", 0xFFFF, "-1 (error)"),
        ("STATUS", -1, "-1 (error)"),
        ("ACQ_LINE", 0xFFFF, "-1 (start-up)"),
        ("ACQ_LINE", -1, "-1 (start-up)"),
        ("ACQ_LINE", 0xFF80, "-128 (end of sequence)"),
        ("ACQ_LINE", -128, "-128 (end of sequence)"),
        ("ACQ_LINE", 7, "7"),
        ("CURRENT_FRAME", 0xFFFE, "-2"),
        ("_Biris_cmd_int_enable", 1, "set"),
        ("_Biris_motor_access", 0, "clear"),
    ],
)
def test_decoders(name: str, value: int, text: str) -> None:
    assert BIEXEC_REGISTERS.by_name(name).decode(value) == text
