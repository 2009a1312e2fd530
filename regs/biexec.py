"""BIEXEC_COM: the control block the BIRIS 68020 supervisor shares over the bus (report Fig. 2).

To issue a command the host copies a NUL-terminated parameter string into PARAM, then writes a
:class:`BiCommand` code to COMMAND. BIRIS clears COMMAND when it is done (and raises BIRIS_CMD if
``_Biris_cmd_int_enable`` is set), leaving STATUS (0 = success) and any answer in PARAM.
"""

from __future__ import annotations

import ctypes
import enum

from regs.describe import Access, RegisterSet, describe_struct, signed_decoder

__all__ = [
    "ACQ_LINE_END",
    "ACQ_LINE_STARTUP",
    "BIEXEC_COM_SIZE",
    "BIEXEC_PARAM_SIZE",
    "BIEXEC_REGISTERS",
    "BiCommand",
    "BiStatus",
    "BiexecCom",
    "decode_param",
    "encode_param",
]

BIEXEC_PARAM_SIZE = 64
"""Bytes in PARAM[]; the report does not give BIEXEC_PARAM_SIZE, 64 is our interpretation."""

ACQ_LINE_STARTUP = -1
"""ACQ_LINE while the sequence starts up; that acquisition is discarded."""

ACQ_LINE_END = -128
"""ACQ_LINE once the acquisition sequence has ended."""


class BiexecCom(ctypes.BigEndianStructure):
    """The report's ``struct BIEXEC_COM`` (the subset the server uses), 80 bytes."""

    _pack_ = 2
    _layout_ = "ms"
    _fields_ = [
        ("COMMAND", ctypes.c_int16),
        ("STATUS", ctypes.c_int16),
        ("ACQ_LINE", ctypes.c_int16),
        ("PARAM", ctypes.c_char * BIEXEC_PARAM_SIZE),
        ("CURRENT_FRAME", ctypes.c_int16),
        ("CURRENT_PROJ", ctypes.c_int16),
        ("_Biris_cmd_int_enable", ctypes.c_int16),
        ("_Biris_data_int_enable", ctypes.c_int16),
        ("_Biris_motor_access", ctypes.c_int16),
    ]


BIEXEC_COM_SIZE = ctypes.sizeof(BiexecCom)

# Field offsets, for width-explicit accesses (COMMAND must never be written as part of a struct).
OFF_COMMAND: int = BiexecCom.COMMAND.offset
OFF_STATUS: int = BiexecCom.STATUS.offset
OFF_ACQ_LINE: int = BiexecCom.ACQ_LINE.offset
OFF_PARAM: int = BiexecCom.PARAM.offset
OFF_CURRENT_FRAME: int = BiexecCom.CURRENT_FRAME.offset
OFF_CURRENT_PROJ: int = BiexecCom.CURRENT_PROJ.offset
OFF_CMD_INT_ENABLE: int = BiexecCom._Biris_cmd_int_enable.offset
OFF_DATA_INT_ENABLE: int = BiexecCom._Biris_data_int_enable.offset
OFF_MOTOR_ACCESS: int = BiexecCom._Biris_motor_access.offset


class BiCommand(enum.IntEnum):
    """Codes written to COMMAND (our code table; the report names the commands, not the codes)."""

    BI_BOOT = 1
    """PARAM = boot file on the BIRIS RAMdisk."""
    BI_GET_VME_ADDR_DIST = 2
    """Answer in PARAM: BIRIS-side VME address of the range array (Biris_range_ptr), hex."""
    BI_GET_VME_ADDR_AZIM = 3
    """Answer in PARAM: BIRIS-side VME address of the azimuth table, hex."""
    BI_GET_VME_INC_FRAME = 4
    """Answer in PARAM: Biris_frame_size in bytes, decimal."""
    BI_ACQUIRE = 5
    """PARAM = number of acquisitions, decimal."""
    BI_START_CONTINUOUS = 6
    """Appendix D: acquire until BI_STOP_CONTINUOUS."""
    BI_STOP_CONTINUOUS = 7
    """Appendix D: cease acquisitions immediately."""
    BI_LOAD_LUT = 8
    """PARAM = elevation (counts, decimal) whose calibration table BIRIS loads."""


class BiStatus(enum.IntEnum):
    """Values BIRIS leaves in STATUS when it clears COMMAND; anything non-zero is an error."""

    OK = 0
    UNKNOWN_COMMAND = 1
    BAD_PARAM = 2
    NOT_BOOTED = 3
    NO_BOOT_FILE = 4
    NO_CALIBRATION = 5


def encode_param(text: str) -> bytes:
    """PARAM bytes for ``text``: ASCII, NUL-terminated, NUL-padded to BIEXEC_PARAM_SIZE."""
    raw = text.encode("ascii")
    if len(raw) >= BIEXEC_PARAM_SIZE:
        raise ValueError(f"parameter of {len(raw)} bytes does not fit PARAM[{BIEXEC_PARAM_SIZE}]")
    return raw.ljust(BIEXEC_PARAM_SIZE, b"\0")


def decode_param(raw: bytes) -> str:
    """The text up to the first NUL; raises ValueError when there is no NUL or non-ASCII."""
    end = raw.find(b"\0")
    if end < 0:
        raise ValueError("PARAM is not NUL-terminated")
    return raw[:end].decode("ascii")


def _signed16(value: int) -> int:
    """Accept the raw unsigned read and the signed ctypes field value alike."""
    value &= 0xFFFF
    return value - 0x10000 if value & 0x8000 else value


def _status_text(value: int) -> str:
    value = _signed16(value)
    try:
        return f"{value} ({BiStatus(value).name})"
    except ValueError:
        return f"{value} (error)"


def _command_text(value: int) -> str:
    value &= 0xFFFF
    if value == 0:
        return "0 (idle)"
    try:
        return f"{value} ({BiCommand(value).name})"
    except ValueError:
        return f"{value} (unknown code)"


def _acq_line_text(value: int) -> str:
    value = _signed16(value)
    if value == ACQ_LINE_STARTUP:
        return "-1 (start-up)"
    if value == ACQ_LINE_END:
        return "-128 (end of sequence)"
    return str(value)


def _flag_text(value: int) -> str:
    return "set" if value else "clear"


BIEXEC_REGISTERS: RegisterSet = describe_struct(
    "BIEXEC_COM",
    BiexecCom,
    meanings={
        "COMMAND": "command register; cleared by BIRIS on completion",
        "STATUS": "status of the last command, 0 = success",
        "ACQ_LINE": "acquisition number in the current sequence",
        "CURRENT_FRAME": "current frame in this sequence",
        "CURRENT_PROJ": "current projection line in this acquisition",
        "_Biris_cmd_int_enable": "command interrupt enable flag",
        "_Biris_data_int_enable": "data interrupt enable flag",
        "_Biris_motor_access": "enables BIRIS access to the motor (azimuth tagging)",
    },
    decoders={
        "COMMAND": _command_text,
        "STATUS": _status_text,
        "ACQ_LINE": _acq_line_text,
        "CURRENT_FRAME": signed_decoder(16),
        "CURRENT_PROJ": signed_decoder(16),
        "_Biris_cmd_int_enable": _flag_text,
        "_Biris_data_int_enable": _flag_text,
        "_Biris_motor_access": _flag_text,
    },
    access={
        "STATUS": Access.R,
        "ACQ_LINE": Access.R,
        "CURRENT_FRAME": Access.R,
        "CURRENT_PROJ": Access.R,
    },
)
