"""The Wiener VM-USB USB-to-VME bridge: identifiers, packet layouts and bit fields.

Both sides of the ``vmusb`` transport use this module: the driver's bus window and interrupt
lines (:mod:`biris_hw.bus.vmusb`, :mod:`biris_hw.irq.vmusb`) and the simulated device behind
pyusb (:mod:`sim.vmusb`). Every convention names the public source it rests on: NSCLDAQ's
``CVMUSB.cpp`` / ``CVMUSB.h`` / ``CVMUSBusb.cpp`` / ``CVMUSBReadoutList.cpp`` (FRIBDAQ,
``main/usb/vmusb/vmusb/``; ``vmusbserver/CVMUSB.cpp`` for the older server), mesytec mvme's
``vmusb.cpp`` / ``vmusb.h`` / ``vmusb_constants.h`` / ``CVMUSBReadoutList.cpp`` /
``vmusb_readout_worker.cc`` / ``vmusb_buffer_processor.cc``, and Wiener's VM-USB user manual
(rev. 3.4.1, sections 3.4 and 4.6, as far as it was read). Facts were read, no code copied.
A line marked **Interpretation** rests on none of them: it is what our driver does and what our
simulated device enforces, and docs/transports.md lists every one for a user with a real bridge.

**USB.** VID 0x16DC, PID 0x000B; configuration 1, interface 0; bulk OUT 0x02, bulk IN 0x86
(512-byte packets at high speed); the serial number string reads ``VMnnnn`` (NSCLDAQ
``CVMUSB.cpp`` constants, ``enumerateAndIdentify``). Every word on the wire is little-endian
(``addToPacket16/32``).

**Host to device (one bulk OUT transfer each).**

1. *Immediate list*: ``u16 TA_IMMEDIATE_LIST``, ``u32 n_shorts`` (the stack's length in 16-bit
   units, plus one), then the stack lines as ``u32`` words (``listToOutPacket``). The device runs
   the lines in order and answers with one bulk IN transfer holding only the data read (manual
   4.6): with GLOBAL_MODE's Align32 clear, as both public drivers run it, a ``u16`` per D8 or D16
   read (the byte of a D8 read in the low 8 bits: NSCLDAQ's ``vmeRead8`` takes the answer's first
   byte), a ``u32`` per D32 read, per transfer of a block read and per internal register read
   (``readRegister`` reads 4 bytes). A list without reads is answered by one ``u16`` that is
   **not zero when every write was acknowledged** and zero when one was not (no DTACK, a bus
   error): mvme ``VMUSB::write16/write32`` ("No DTACK on write" when it is 0), NSCLDAQ
   ``CVMUSB::doVMEWrite`` (reply 0 is status -3, a bus error). The value of a good answer is
   :data:`WRITE_ACKNOWLEDGED` in Wiener's manual of the VM-DBA, whose FPGA takes the same
   stacks ("for WRITE operations, the returned data = 1"); the driver takes any value but zero.
   A list of internal register writes only is answered the same way, and the driver does not
   judge the value (NSCLDAQ's ``writeRegister`` ignores it).
   A VME bus error ends a block read short (NSCLDAQ ``vmeBlockRead``: "a BERR in the middle of
   the transfer is successful completion", fewer transfers), and the answer is then shorter than
   the list implies. **Interpretation**: a bus error on a single-cycle read or a write stops the
   list there; the block read's ends only that line.
2. *Stack load* (a list kept for IRQ-triggered execution): ``u16 ta_load(stack_id)``, ``u16
   n_shorts`` (as above), ``u16 load offset`` (in 32-bit words of stack memory), then the lines.
   No answer (NSCLDAQ ``loadList``).
3. *Register-block write* (the action register, which no list reaches): three ``u16``:
   ``REGISTER_BLOCK``, ``ACTION_REGISTER``, value. No answer (``writeActionRegister``).

**Stack lines.** A line is a mode word, an address, and for a write the data
(``CVMUSBReadoutList``):

- single read ``[MODE_NW | am | ds, address]``, write ``[am | ds, address, data]``;
- D32: ``address & ~3``, DS bits clear; D16: ``(address & ~1) | ADDR_NOT_LWORD``, DS bits clear;
  D8: ``(address & ~1) | ADDR_NOT_LWORD`` and one data strobe, ``MODE_DS1`` (0x80) for an even
  address, ``MODE_DS0`` (0x40) for an odd one (``dataStrobes``). **A D8 write puts the byte on
  both data lanes**, D7..D0 and D15..D8 (``addWrite8``: "so it does not matter ... whether the
  data has to be in the appropriate data lanes"): which lane the bridge drives is undocumented;
- block read (D32 BLT): ``[MODE_NW | am_blt | count << BLOCK_COUNT_SHIFT, address & ~3]`` with
  ``1 <= count <= MAX_BLOCK_WORDS``; a count field of :data:`BLOCK_COUNT_ESCAPE` (0xFF) means
  the count follows in a word of its own, ``[mode | 0xFF << 24, count, address]`` (mvme's
  "universal" ``addBlockRead``; NSCLDAQ refuses counts above 254 for that reason). The driver
  never needs the escape: like NSCLDAQ's ``addBlockRead`` it cuts a block read at every
  :data:`BLT_BOUNDARY` (a VME block transfer does not cross a 256-byte boundary), so no line
  carries more than 64 transfers;
- internal register: read ``[MODE_NW | MODE_SLF, reg]``, write ``[MODE_SLF, reg, value]``.

VME data values are what the bus carries: a D32 read of big-endian memory at ``a`` is the value
of the four bytes ``a..a+3`` read most significant first, as a 68k sees it.

**Bring-up registers.** GLOBAL_MODE (NSCLDAQ ``GlobalModeRegister``): buffer length code in bits
0-3 (0 = 13K words ... 8 = 64 words, 9 = "single": a buffer closes after EVENTS_PER_BUFFER
events, ``writeEventsPerBuffer``), Align32 in bit 7 (manual 3.4.2: it also turns every buffer
and event header into a 32-bit word, a layout neither public driver reads, so the driver leaves
it clear). USB_BULK_SETUP (``TransferSetupRegister``): buffers per bulk transfer in bits 0-7,
a timeout in bits 8-11; both public drivers write 0 (NSCLDAQ ``CAcquisitionThread::startDaq``:
"don't want multibuffering", mvme's DAQ start). The IRQ mask has no address of its own
(``CVMUSB::writeIrqMask``, mvme ``VMUSB::setIrqMask``): write GLOBAL_MODE with
:data:`IRQ_MASK_LOAD` and the mask in bits 0-6 (a set bit ignores level ``bit + 1``: mvme's
``removeIrqMask``), write the action register :attr:`Action.USB_TRIGGER`, read FIRMWARE_ID
(bits 24-30 show the mask: mvme checks them), write GLOBAL_MODE 0, then its value again.
NSCLDAQ writes the mask 0x7F at every open. Vector high bits: the ISV entries hold 8 bits of a
16-bit vector; registers VECTOR_HIGH1 (0x40, entries 0-3) and VECTOR_HIGH2 (0x44, entries 4-7)
hold the upper byte of each, one byte per entry (NSCLDAQ ``CStack``), and an 8-bit interrupter
needs 0xFF there (NSCLDAQ ``vmusbserver`` ``writeVector`` writes both registers 0xFFFFFFFF
"in keeping with what 8bit interrupters require").

**Interrupts.** The bridge has no interrupt endpoint. Each of the eight ISV entries (two per
ISV register: vector bits 0-7, level bits 8-10, stack id bits 12-14; the second entry in the
upper half) names the stack to run when a VME IRQ of that level answers its IACK with that
vector. Stacks run only while data taking runs (ACTION_START_DAQ). The result goes out in
*buffers* on bulk IN (manual 4.6, mvme ``vmusb_buffer_processor``): ``u16`` header
(``BUF_LAST`` on the buffer that ends data taking, event count in ``BUF_EVENT_COUNT``), then
per event a ``u16`` event header (stack id ``<< 13``, length in 16-bit units of the data that
follows) and the data (each read value as in an immediate answer; writes add nothing), then two
``u16`` ``BUF_TERMINATOR`` words (mvme reads two; a reader takes one or two). A buffer is sent
when it is full (its length code), when it holds EVENTS_PER_BUFFER events (code 9), and when
data taking stops: clearing ACTION_START_DAQ makes the device send what it holds, the last
buffer marked ``BUF_LAST`` (mvme: leaving DAQ mode "forces the controller to dump its buffer";
NSCLDAQ ``executeList``: wait for the last buffer). An idle bridge therefore holds an interrupt's
event until one of those happens: the driver sets code 9 with one event per buffer.

**What the device forbids**: an immediate list, a stack load or an internal register access
while data taking runs (the host must stop it, read up to the ``BUF_LAST`` buffer, then send the
list: NSCLDAQ ``executeList``'s comment, the FRIB manual "the device will only accept read
operations"). **Interpretation** (enforced by the simulated device's audit): a second OUT
transfer before the answer to an immediate list has been read; starting data taking with an ISV
entry whose stack was never loaded. A VME IRQ that arrives while data taking is stopped stays
pending (VME interrupts are level-held until acknowledged) and its stack runs when data taking
starts again.
"""

from __future__ import annotations

import enum

__all__ = [
    "ACTION_REGISTER",
    "ADDR_NOT_LWORD",
    "BLOCK_COUNT_ESCAPE",
    "BLOCK_COUNT_SHIFT",
    "BLT_BOUNDARY",
    "BLT_MAX_COUNT",
    "BUFFER_LENGTH_MASK",
    "BUFFER_LENGTH_WORDS",
    "BUFFER_SINGLE_EVENT",
    "BUF_EVENT_COUNT",
    "BUF_LAST",
    "BUF_TERMINATOR",
    "BULK_MULTI_BUFFER",
    "BULK_TIMEOUT",
    "BULK_TIMEOUT_SHIFT",
    "CONFIGURATION",
    "EP_IN",
    "EP_OUT",
    "EVENT_LENGTH",
    "EVENT_STACK_SHIFT",
    "FID_IRQ_MASK_SHIFT",
    "GLOBAL_ALIGN32",
    "INTERFACE",
    "IRQ_MASK_ALL",
    "IRQ_MASK_LOAD",
    "ISV_REGISTERS",
    "MAX_BLOCK_WORDS",
    "MAX_LIST_LINES",
    "MAX_PACKET",
    "MODE_DS0",
    "MODE_DS1",
    "MODE_NW",
    "MODE_SLF",
    "NO_DTACK",
    "PID",
    "REGISTER_BLOCK",
    "SERIAL_PREFIX",
    "TA_IMMEDIATE_LIST",
    "VECTOR_HIGH_8BIT",
    "VID",
    "WRITE_ACKNOWLEDGED",
    "Action",
    "AddressModifier",
    "InternalReg",
    "irq_mask_bit",
    "isv_entry",
    "read_answer_bytes",
    "ta_load",
    "vector_high_slot",
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
"""Lines per immediate list (Interpretation: the driver's cap, which the simulated device
enforces; the manual's limit was not read)."""
WRITE_ACKNOWLEDGED = 0x0001
"""The ``u16`` answer to a list without reads whose every write was acknowledged: 1 in the
VM-DBA manual; the driver takes any value but :data:`NO_DTACK`."""
NO_DTACK = 0x0000
"""The answer to a list without reads when a write got no DTACK (a bus error): mvme's
``write16/write32``, NSCLDAQ's ``doVMEWrite``."""


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
"""Block reads carry their count of 32-bit transfers in mode bits 24-31 (NSCLDAQ and mvme
``modeBLTShift``)."""
MAX_BLOCK_WORDS = 254
"""The largest count the field holds itself (NSCLDAQ's ``addBlockRead`` refuses more)."""
BLOCK_COUNT_ESCAPE = 0xFF
"""A count field of 0xFF: the transfer count follows the mode word in a word of its own (mvme's
``addBlockRead``)."""
BLT_MAX_COUNT = 1 << 23
"""The largest escaped BLT count (mvme ``vmusb_constants.h``, ``BLTMaxTransferCount``)."""
BLT_BOUNDARY = 256
"""Bytes: a D32 block transfer does not cross a multiple of it (the VME rule NSCLDAQ's
``addBlockRead`` cuts at), so one line moves at most 64 words."""
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
    VECTOR_HIGH1 = 0x40
    """Upper vector bytes of ISV entries 0-3, entry ``i`` in bits ``8i..8i+7``."""
    VECTOR_HIGH2 = 0x44
    """Upper vector bytes of ISV entries 4-7."""
    EVENTS_PER_BUFFER = 0x24
    """mvme's name of 0x24 (NSCLDAQ's ``writeEventsPerBuffer`` writes it): with buffer length
    code :data:`BUFFER_SINGLE_EVENT` a buffer closes after this many events (12 bits)."""


ISV_REGISTERS = (InternalReg.ISV12, InternalReg.ISV34, InternalReg.ISV56, InternalReg.ISV78)
"""Entries 0-1, 2-3, 4-5, 6-7: entry ``2i`` in the low half of ``ISV_REGISTERS[i]``."""

GLOBAL_ALIGN32 = 0x0080
"""GLOBAL_MODE bit: D8/D16 reads answer a ``u32`` and every buffer and event header becomes a
32-bit word (manual 3.4.2). Neither public driver takes data with it; ours leaves it clear."""
BUFFER_LENGTH_MASK = 0x000F
"""GLOBAL_MODE bits 0-3: the buffer length code (NSCLDAQ ``bufferLenMask``)."""
BUFFER_LENGTH_WORDS = {
    0: 13 * 1024,
    1: 8 * 1024,
    2: 4 * 1024,
    3: 2 * 1024,
    4: 1024,
    5: 512,
    6: 256,
    7: 128,
    8: 64,
}
"""16-bit words of a buffer per length code (NSCLDAQ ``bufferLen13K`` ... ``bufferLen64``)."""
BUFFER_SINGLE_EVENT = 9
"""Length code 9 (``bufferLenSingle``): a buffer closes after EVENTS_PER_BUFFER events."""
IRQ_MASK_LOAD = 0x8000
"""GLOBAL_MODE bit 15: the low 7 bits are an IRQ mask, taken at the next USB_TRIGGER action."""
IRQ_MASK_ALL = 0x7F
"""Every level ignored: what NSCLDAQ writes at open."""
FID_IRQ_MASK_SHIFT = 24
"""While :data:`IRQ_MASK_LOAD` is set, FIRMWARE_ID shows the mask in bits 24-30 (mvme)."""
BULK_MULTI_BUFFER = 0x00FF
"""USB_BULK_SETUP bits 0-7: buffers sent together in one bulk transfer (0 or 1: each alone)."""
BULK_TIMEOUT = 0x0F00
BULK_TIMEOUT_SHIFT = 8
"""USB_BULK_SETUP bits 8-11: how long a bulk transfer waits for its buffers (NSCLDAQ:
"1sec timeout is fine" for 0; mvme notes the manual also names bits 16-19)."""
VECTOR_HIGH_8BIT = 0xFF
"""The upper vector byte of an 8-bit (D08(O)) interrupter as the bridge sees it."""

ISV_VECTOR = 0x00FF
ISV_LEVEL_SHIFT = 8
ISV_LEVEL = 0x0700
ISV_STACK_SHIFT = 12
ISV_STACK = 0x7000


def irq_mask_bit(level: int) -> int:
    """The IRQ mask bit that ignores VME IRQ ``level`` (1-7): bit ``level - 1``."""
    if not 1 <= level <= 7:
        raise ValueError(f"IRQ level {level} is not 1..7")
    return 1 << (level - 1)


def vector_high_slot(entry: int) -> tuple[InternalReg, int]:
    """Where ISV entry ``entry`` (0-7) keeps its vector's upper byte: (register, bit shift)."""
    if not 0 <= entry <= 7:
        raise ValueError(f"ISV entry {entry} is not 0..7")
    reg = InternalReg.VECTOR_HIGH1 if entry < 4 else InternalReg.VECTOR_HIGH2
    return reg, 8 * (entry % 4)


def read_answer_bytes(width_bits: int, align32: bool = False) -> int:
    """Bytes a single-cycle VME read of ``width_bits`` adds to an answer or an event."""
    if width_bits not in (8, 16, 32):
        raise ValueError(f"a VME single cycle is 8, 16 or 32 bits wide, not {width_bits}")
    return 4 if width_bits == 32 or align32 else 2


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
"""Ends a buffer, twice (the manual's "Buffer Terminator, Second Buffer Terminator"; mvme reads
two and tolerates one)."""
