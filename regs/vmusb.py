"""The Wiener VM-USB USB-to-VME bridge: identifiers, packet layouts and bit fields.

Both sides of the ``vmusb`` transport use this module: the driver's bus window and interrupt
lines (:mod:`biris_hw.bus.vmusb`, :mod:`biris_hw.irq.vmusb`) and the simulated device behind
pyusb (:mod:`sim.vmusb`). Facts are those of ``reference/transports-and-ecosystem.md`` section
1.1 (Wiener's register map and bit layouts as the NSCLDAQ and mvme sources use them: read, not
copied). Where the facts are open, the line says **Interpretation**: it is what our driver does
and what our simulated device enforces, and the README says so to a user with a real bridge.

**USB.** VID 0x16DC, PID 0x000B; configuration 1, interface 0; bulk OUT 0x02, bulk IN 0x86
(512-byte packets at high speed); the serial number string reads ``VMnnnn``. Every word on the
wire is little-endian.

**Host to device (one bulk OUT transfer each).**

1. *Immediate list*: ``u16 TA_IMMEDIATE_LIST`` (write | immediate), ``u32 n_shorts`` (the stack's
   length in 16-bit units, plus one), then the stack lines as ``u32`` words. The device runs the
   lines in order and answers with one bulk IN transfer: a ``u32`` per single-cycle read (D8 and
   D16 values in the low bits: **Interpretation**, the driver sets GLOBAL_ALIGN32 at bring-up),
   ``count`` ``u32`` per block read, and, for a list without reads, one ``u16`` 0x0000.
   **Interpretation** (the manual's answer to a failed cycle was not read): a cycle that ends in
   VME BERR stops the list, and the whole answer is one ``u16`` ``BERR_ANSWER | line`` (the
   failing line's index, lists are at most ``MAX_LIST_LINES`` lines). An answer of any other
   length than the one the list implies is a protocol error.
2. *Stack load* (a list kept for IRQ-triggered execution): ``u16 ta_load(stack_id)``, ``u16
   n_shorts`` (as above), ``u16 load offset`` (in 32-bit words of stack memory), then the lines.
   No answer.
3. *Register-block write* (the action register, which no list reaches): three ``u16``:
   ``REGISTER_BLOCK``, ``ACTION_REGISTER``, value. No answer.

**Stack lines.** A line is a mode word, an address, and for a write the data:

- single read ``[MODE_NW | am | ds, address]``, write ``[am | ds, address, data]``;
- D32: ``address & ~3``, DS bits clear; D16: ``(address & ~1) | ADDR_NOT_LWORD``, DS bits clear;
  D8: ``(address & ~1) | ADDR_NOT_LWORD`` and one data strobe: ``MODE_DS1`` for the even byte
  (D15..D8 on VME), ``MODE_DS0`` for the odd byte (**Interpretation** of the DS field);
- block read (D32 BLT): ``[MODE_NW | am_blt | (count << BLOCK_COUNT_SHIFT), address & ~3]`` with
  ``1 <= count <= MAX_BLOCK_WORDS``: **Interpretation** of where the transfer count goes;
- internal register: read ``[MODE_NW | MODE_SLF, reg]``, write ``[MODE_SLF, reg, value]``.

VME data values are what the bus carries: a D32 read of big-endian memory at ``a`` is the value
of the four bytes ``a..a+3`` read most significant first, as a 68k sees it.

**Interrupts.** The bridge has no interrupt endpoint. Each of the eight ISV entries (two per
ISV register: vector bits 0-7, level bits 8-10, stack id bits 12-14; the second entry in the
upper half) names the stack to run when a VME IRQ of that level answers its IACK with that
vector. Stacks run only while data taking runs (ACTION_START_DAQ). The result goes out as a
*buffer* on bulk IN: ``u16`` header (``BUF_LAST`` on the buffer that ends data taking, event
count in ``BUF_EVENT_COUNT``), then per event a ``u16`` event header (stack id ``<< 13``, length
in 16-bit units of the data that follows) and the data (each read value a ``u32``), then ``u16``
``BUF_TERMINATOR``. **Interpretation**: one buffer per IRQ event (USB_BULK_SETUP is written so
that a buffer is never held back for more events), and clearing ACTION_START_DAQ makes the
device send one last buffer, ``BUF_LAST`` with no event, after every buffer still owed.

**What the device forbids** (**Interpretation**, enforced by the simulated device's audit): an
immediate list, a stack load or an internal register access while data taking runs (the host
must stop it, read up to the ``BUF_LAST`` buffer, then send the list); a second OUT transfer
before the answer to an immediate list has been read; starting data taking with an ISV entry
whose stack was never loaded. A VME IRQ that arrives while data taking is stopped stays
pending (VME interrupts are level-held until acknowledged) and its stack runs when data taking
starts again.
"""

from __future__ import annotations

import enum

__all__ = [
    "ACTION_REGISTER",
    "ADDR_NOT_LWORD",
    "BERR_ANSWER",
    "BLOCK_COUNT_SHIFT",
    "BUF_EVENT_COUNT",
    "BUF_LAST",
    "BUF_TERMINATOR",
    "CONFIGURATION",
    "EP_IN",
    "EP_OUT",
    "EVENT_LENGTH",
    "EVENT_STACK_SHIFT",
    "INTERFACE",
    "ISV_REGISTERS",
    "MAX_BLOCK_WORDS",
    "MAX_LIST_LINES",
    "MAX_PACKET",
    "MODE_DS0",
    "MODE_DS1",
    "MODE_NW",
    "MODE_SLF",
    "NO_READ_ANSWER",
    "PID",
    "REGISTER_BLOCK",
    "SERIAL_PREFIX",
    "TA_IMMEDIATE_LIST",
    "VID",
    "Action",
    "AddressModifier",
    "InternalReg",
    "isv_entry",
    "ta_load",
]

# -- USB identity ------------------------------------------------------------------------------
VID = 0x16DC
"""Wiener (JTEC)."""
PID = 0x000B
"""VM-USB (the CC-USB, its CAMAC sibling, is 0x0001)."""
SERIAL_PREFIX = "VM"
"""Serial number strings read ``VMnnnn``."""
CONFIGURATION = 1
INTERFACE = 0
EP_OUT = 0x02
EP_IN = 0x86
MAX_PACKET = 512
"""Bulk max packet size at USB 2.0 high speed."""

# -- OUT packet headers ------------------------------------------------------------------------
TA_STACK_ID_BIT0 = 0x0001
TA_LOAD = 0x0002
TA_WRITE = 0x0004
TA_IMMEDIATE = 0x0008
TA_STACK_ID_HIGH_SHIFT = 4
"""Stack id bits 1-2 sit at TA bits 4-5 (0x10, 0x20)."""
TA_IMMEDIATE_LIST = TA_WRITE | TA_IMMEDIATE
"""0x000C: execute the list that follows now."""

REGISTER_BLOCK = 5
"""First ``u16`` of a register-block write."""
ACTION_REGISTER = 10
"""Second ``u16``: the action register, reached only this way."""

MAX_LIST_LINES = 255
"""Lines per immediate list (the BERR answer names the failing line in 8 bits)."""
NO_READ_ANSWER = 0x0000
"""The ``u16`` that answers a list without reads."""
BERR_ANSWER = 0xBE00
"""``BERR_ANSWER | line``: the list stopped at ``line`` on a VME bus error (Interpretation)."""


def ta_load(stack_id: int) -> int:
    """TA word of a stack load for ``stack_id`` (0-7)."""
    if not 0 <= stack_id <= 7:
        raise ValueError(f"stack id {stack_id} is not 0..7")
    return (
        TA_WRITE
        | TA_LOAD
        | (stack_id & 1) * TA_STACK_ID_BIT0
        | ((stack_id >> 1) & 3) << TA_STACK_ID_HIGH_SHIFT
    )


# -- stack line mode word ----------------------------------------------------------------------
MODE_AM_MASK = 0x3F
MODE_DS0 = 0x40
"""Data strobe 0 only: the odd byte, D7..D0 (Interpretation of the DS field for D8)."""
MODE_DS1 = 0x80
"""Data strobe 1 only: the even byte, D15..D8."""
MODE_NW = 0x100
"""No write: the line reads."""
MODE_NA = 0x400
MODE_MB = 0x800
MODE_SLF = 0x1000
"""The line addresses an internal register of the bridge, not the VME bus."""
MODE_MARKER = 0x2000
MODE_DELAY = 0x8000
BLOCK_COUNT_SHIFT = 24
"""Block reads carry their count of 32-bit transfers in mode bits 24-31 (Interpretation)."""
MAX_BLOCK_WORDS = 255
ADDR_NOT_LWORD = 0x1
"""Address bit 0 set: a 16- or 8-bit cycle (LWORD* high)."""


class AddressModifier(enum.IntEnum):
    """VME address modifiers the driver uses (user data and supervisor data, single and BLT)."""

    A16_USER = 0x29
    A16_SUPERVISOR = 0x2D
    A24_USER = 0x39
    A24_SUPERVISOR = 0x3D
    A24_USER_BLT = 0x3B
    A24_SUPERVISOR_BLT = 0x3F
    A32_USER = 0x09
    A32_SUPERVISOR = 0x0D
    A32_USER_BLT = 0x0B
    A32_SUPERVISOR_BLT = 0x0F


ADDRESS_BITS = {
    AddressModifier.A16_USER: 16,
    AddressModifier.A16_SUPERVISOR: 16,
    AddressModifier.A24_USER: 24,
    AddressModifier.A24_SUPERVISOR: 24,
    AddressModifier.A24_USER_BLT: 24,
    AddressModifier.A24_SUPERVISOR_BLT: 24,
    AddressModifier.A32_USER: 32,
    AddressModifier.A32_SUPERVISOR: 32,
    AddressModifier.A32_USER_BLT: 32,
    AddressModifier.A32_SUPERVISOR_BLT: 32,
}
"""Address width of each modifier."""

BLT_OF = {
    AddressModifier.A24_USER: AddressModifier.A24_USER_BLT,
    AddressModifier.A24_SUPERVISOR: AddressModifier.A24_SUPERVISOR_BLT,
    AddressModifier.A32_USER: AddressModifier.A32_USER_BLT,
    AddressModifier.A32_SUPERVISOR: AddressModifier.A32_SUPERVISOR_BLT,
}
"""The block-transfer modifier of a data modifier (A16 has none: single cycles only)."""


# -- internal registers and the action register ------------------------------------------------
class InternalReg(enum.IntEnum):
    """The bridge's own registers (addresses of SLF lines)."""

    FIRMWARE_ID = 0x00
    GLOBAL_MODE = 0x04
    DAQ_SETTINGS = 0x08
    LED_SOURCE = 0x0C
    DEVICE_SOURCE = 0x10
    DGG_A = 0x14
    DGG_B = 0x18
    SCALER_A = 0x1C
    SCALER_B = 0x20
    EXTRACT_MASK = 0x24
    ISV12 = 0x28
    ISV34 = 0x2C
    ISV56 = 0x30
    ISV78 = 0x34
    DGG_EXT = 0x38
    USB_BULK_SETUP = 0x3C


ISV_REGISTERS = (InternalReg.ISV12, InternalReg.ISV34, InternalReg.ISV56, InternalReg.ISV78)
"""Entries 0-1, 2-3, 4-5, 6-7: entry ``2i`` in the low half of ``ISV_REGISTERS[i]``."""

GLOBAL_ALIGN32 = 0x0080
"""GLOBAL_MODE bit: every single-cycle read answers a full ``u32`` (Interpretation)."""

ISV_VECTOR = 0x00FF
ISV_LEVEL_SHIFT = 8
ISV_LEVEL = 0x0700
ISV_STACK_SHIFT = 12
ISV_STACK = 0x7000


def isv_entry(vector: int, level: int, stack_id: int) -> int:
    """One 16-bit ISV entry: run ``stack_id`` on an IRQ of ``level`` with ``vector``."""
    if not 0 <= vector <= 0xFF or not 1 <= level <= 7 or not 0 <= stack_id <= 7:
        raise ValueError(f"ISV entry vector={vector} level={level} stack={stack_id} out of range")
    return vector | level << ISV_LEVEL_SHIFT | stack_id << ISV_STACK_SHIFT


class Action(enum.IntFlag):
    """The action register's bits."""

    START_DAQ = 0x01
    USB_TRIGGER = 0x02
    CLEAR = 0x04
    SYS_RESET = 0x08
    SCALER_DUMP = 0x10


# -- data-taking buffers -----------------------------------------------------------------------
BUF_LAST = 0x8000
"""Header bit: the last buffer of a data-taking run."""
BUF_SCALER = 0x4000
BUF_CONTINUOUS = 0x2000
BUF_MULTI = 0x1000
BUF_EVENT_COUNT = 0x0FFF
EVENT_STACK_SHIFT = 13
EVENT_CONTINUATION = 0x1000
EVENT_LENGTH = 0x0FFF
"""Event header: data length in 16-bit units."""
BUF_TERMINATOR = 0xFFFF
