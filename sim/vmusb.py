"""A simulated Wiener VM-USB (USB-to-VME bridge) that the driver reaches through real pyusb.

The driver's ``vmusb`` transport talks pyusb; this module is the far side of that cable, so the
driver's own code runs unchanged against a crate of simulated VME slaves:
``usb.core.find(idVendor=0x16DC, idProduct=0x000B, backend=VmUsbBackend(sim))``.

- :class:`SimulatedVmUsb` is the bridge: the slaves mapped in its crate (any
  :class:`~biris_hw.bus.base.BusWindow`, reached at a base address for every address modifier of
  one width), its internal registers, its stack memory and its bulk IN queue. The wire format,
  every constant and every interpretation are those of :mod:`regs.vmusb`; this module adds none
  of its own except where the spec is silent, and says so (``Interpretation`` below).
- :class:`VmUsbBackend` is a pyusb ``IBackend``: the descriptor tree, string descriptors through
  GET_DESCRIPTOR, handles, configuration, interface claims, bulk transfers and reset, the way the
  libusb1 backend reports them (the same exception classes and libusb error codes).

Why a sequencer thread: a VME IRQ makes the bridge run a stack *on its own*, and the slave that
asserts the IRQ typically does so from its own thread with its own lock held. Running the stack
inside :meth:`SimulatedVmUsb.irq` would read that slave's window from the slave's thread while a
host list may hold the VME bus and wait for the same slave: a lock-order deadlock. So ``irq()``
only queues work (it never calls a window) and the device's sequencer thread, like the real
bridge's FPGA, runs the stacks a moment later. All VME cycles, of lists and of stacks, hold one
bus lock (the crate has one bus); device state has its own lock, always taken after the bus
lock.

What the device does as the public sources say a real one does (:mod:`regs.vmusb` names each
source), and refuses or records when a driver breaks the convention:

- *Answers.* Only the data read, 16-bit aligned unless GLOBAL_MODE has Align32 (then D8/D16
  reads answer a ``u32``); a list without reads is answered ``WRITE_ACKNOWLEDGED`` when every
  write got DTACK and ``NO_DTACK`` (0) when one did not. A bus error ends a block read short
  (the list goes on) and stops the list at a single-cycle read or a write (Interpretation), so a
  read list's answer comes back short, empty (a zero-length transfer) if nothing was read.
- *D8 writes* drive the byte the data strobe selects: D15..D8 of the data word for an even
  address, D7..D0 for an odd one. A D8 write whose two lanes differ is carried out that way and
  recorded (``D8_ONE_LANE``): which lane a real bridge takes is undocumented, so a driver puts
  the byte on both, as NSCLDAQ does.
- *Block reads*: a count field of 0xFF is the escape (the count follows in its own word, up to
  ``BLT_MAX_COUNT``); a count of 0 is malformed.
- *Buffers.* Events collect in an open buffer that is sent when the next event would not fit its
  length code (GLOBAL_MODE bits 0-3), when it holds EVENTS_PER_BUFFER events (code 9; with 0
  there it never closes by count), and when data taking stops (then marked ``BUF_LAST``, an
  empty one if no event is open). Each buffer ends with two terminators. With USB_BULK_SETUP
  asking for ``n > 1`` buffers per transfer, closed buffers wait in the bridge until ``n`` are
  there, until the timeout of bits 8-11 (Interpretation: ``t`` seconds of hardware time for a
  code ``t``, 1 s for 0) or until data taking stops. So a bridge left at power-on settings (13K
  words) holds an idle interrupt's event until the host next stops data taking. Data taking
  with Align32 set is recorded (``ALIGN32_DATA_TAKING``): the manual makes every header 32 bits
  then, a layout this device does not produce (it sends the 16-bit one).
- *The IRQ mask* is loaded as the public drivers load it (GLOBAL_MODE with IRQ_MASK_LOAD, then
  the USB_TRIGGER action; FIRMWARE_ID shows it in bits 24-30 while IRQ_MASK_LOAD is set). At
  power-on every level is ignored (Interpretation: the real default is not documented; NSCLDAQ
  writes it at every open). An IRQ whose ISV entry matches on a masked level is not
  acknowledged: it stays pending on the bus and is recorded (``IRQ_MASKED``).
- *Vectors* are 16 bits: an 8-bit interrupter presents ``VECTOR_HIGH_8BIT`` above its vector,
  and an ISV entry matches only when the entry's byte in VECTOR_HIGH1/2 agrees (``irq(...,
  vector_high=)`` for another interrupter). An IRQ that matches an entry's level and low byte
  but not its high byte runs nothing (``VECTOR_HIGH_MISMATCH``); one that matches no entry is
  dropped (``IRQ_UNSERVICED``), masked or not (Interpretation: a real bridge leaves a masked one
  on the bus).

Interpretations where the sources are silent (the simulated device's choices):

- A malformed OUT packet is ignored whole (nothing runs, no answer: the host times out) and is
  recorded as ``MALFORMED_PACKET``. Write data of D8/D16 lines sits in the low 16 bits of the
  data word and must fit. Address bits beyond the modifier's width are malformed.
- A block read needs a BLT modifier and a BLT modifier needs a count. MARKER, DELAY, NA, MB
  (NSCLDAQ's multi-block form) and the other mode bits are not modelled: malformed.
- A VME bus error inside an IRQ stack follows the same rules: the event carries the values read
  before it (the host sees a short event), counted in ``counters.bus_errors``.
- An ISV entry is used when its level is not 0. A stack that an ISV entry names but that was
  never loaded runs as an empty stack (an event of length 0), after ``START_WITHOUT_STACK``.
- SYS_RESET resets the registers (the IRQ mask too), forgets the stacks, stops data taking
  without a BUF_LAST buffer and drops every buffer, open, held or queued; IRQs held pending stay
  pending (they are the slaves' state, and a VME SYSRESET is not modelled). CLEAR drops the
  buffers. Writing START_DAQ clear while data taking is off sends nothing. USB_TRIGGER does
  nothing but load the IRQ mask; SCALER_DUMP does nothing.
- A USB reset (``dev.reset()``) drops what is queued on bulk IN, as a flushed endpoint FIFO;
  registers, stacks and data taking are the crate's and stay.
- Data taking "runs" from START_DAQ until the BUF_LAST buffer is queued: an immediate list or a
  stack load in between is refused.
"""

from __future__ import annotations

import array
import enum
import errno
import itertools
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import usb.backend
import usb.core

from biris_hw.bus.base import BusWindow
from biris_hw.errors import BusError
from regs.vmusb import (
    ACTION_REGISTER,
    ADDR_NOT_LWORD,
    ADDRESS_BITS,
    BLOCK_COUNT_ESCAPE,
    BLOCK_COUNT_SHIFT,
    BLT_MAX_COUNT,
    BLT_OF,
    BUF_EVENT_COUNT,
    BUF_LAST,
    BUF_TERMINATOR,
    BUFFER_LENGTH_MASK,
    BUFFER_LENGTH_WORDS,
    BUFFER_SINGLE_EVENT,
    BULK_MULTI_BUFFER,
    BULK_TIMEOUT,
    BULK_TIMEOUT_SHIFT,
    CONFIGURATION,
    EP_IN,
    EP_OUT,
    EVENT_LENGTH,
    EVENT_STACK_SHIFT,
    FID_IRQ_MASK_SHIFT,
    GLOBAL_ALIGN32,
    INTERFACE,
    IRQ_MASK_ALL,
    IRQ_MASK_LOAD,
    ISV_LEVEL,
    ISV_LEVEL_SHIFT,
    ISV_REGISTERS,
    ISV_STACK,
    ISV_STACK_SHIFT,
    ISV_VECTOR,
    MAX_LIST_LINES,
    MAX_PACKET,
    MODE_AM_MASK,
    MODE_DS0,
    MODE_DS1,
    MODE_NW,
    MODE_SLF,
    NO_DTACK,
    PID,
    REGISTER_BLOCK,
    TA_IMMEDIATE_LIST,
    VECTOR_HIGH_8BIT,
    VID,
    WRITE_ACKNOWLEDGED,
    Action,
    AddressModifier,
    InternalReg,
    irq_mask_bit,
    read_answer_bytes,
    ta_load,
    vector_high_slot,
)
from sim.audit import Audit, Violation
from sim.clock import SimClock

__all__ = [
    "SimulatedVmUsb",
    "VmUsbBackend",
    "VmUsbCounters",
    "VmUsbRule",
]

# -- what libusb would say ---------------------------------------------------------------------
_LIBUSB_ERROR_INVALID_PARAM = -2
_LIBUSB_ERROR_NO_DEVICE = -4
_LIBUSB_ERROR_NOT_FOUND = -5
_LIBUSB_ERROR_TIMEOUT = -7
_LIBUSB_ERROR_PIPE = -9

_SPEED_HIGH = 3
"""``usb.util.SPEED_HIGH`` (libusb's LIBUSB_SPEED_HIGH)."""

_LANGID_EN_US = 0x0409
_MANUFACTURER = "Wiener/JTEC"
_PRODUCT = "VM-USB"
_BCD_DEVICE = 0x0100
"""Device release (Interpretation: the real value was not read)."""

_STRING_MANUFACTURER = 1
_STRING_PRODUCT = 2
_STRING_SERIAL = 3

_DESC_DEVICE = 1
_DESC_CONFIG = 2
_DESC_STRING = 3
_REQ_GET_STATUS = 0x00
_REQ_CLEAR_FEATURE = 0x01
_REQ_GET_DESCRIPTOR = 0x06
_REQ_GET_CONFIGURATION = 0x08
_REQ_SET_CONFIGURATION = 0x09
_REQ_SET_INTERFACE = 0x0B
_CTRL_IN = 0x80
_CTRL_TYPE_MASK = 0x60

_ACTION_BITS = int(
    Action.START_DAQ | Action.USB_TRIGGER | Action.CLEAR | Action.SYS_RESET | Action.SCALER_DUMP
)
_LOAD_TAS = {ta_load(i): i for i in range(8)}
_BLT_MODIFIERS = frozenset(int(am) for am in BLT_OF.values())
_KNOWN_MODIFIERS = frozenset(int(am) for am in AddressModifier)
_INTERNAL_REGS = frozenset(int(reg) for reg in InternalReg)
_VME_MODE_BITS = MODE_AM_MASK | MODE_DS0 | MODE_DS1 | MODE_NW | (0xFF << BLOCK_COUNT_SHIFT)

_address_counter = itertools.count(1)
"""USB addresses of simulated devices: each device gets its own, as on a real bus."""


# -- audit ---------------------------------------------------------------------------------------
class VmUsbRule(str, enum.Enum):
    """Protocol misuse the simulated bridge records; the value is the name used in reports."""

    LIST_WHILE_DAQ = "VMUSB_LIST_WHILE_DAQ"
    """An immediate list (internal register accesses included) while data taking runs: ignored,
    no answer."""
    LOAD_WHILE_DAQ = "VMUSB_LOAD_WHILE_DAQ"
    """A stack load while data taking runs: ignored."""
    ANSWER_NOT_READ = "VMUSB_ANSWER_NOT_READ"
    """An OUT transfer before the answer to the previous immediate list was read: the old answer
    is dropped."""
    MALFORMED_PACKET = "VMUSB_MALFORMED_PACKET"
    """An OUT packet the bridge cannot parse (length, TA, n_shorts, lines, modifier, alignment,
    block count): ignored whole."""
    START_WITHOUT_STACK = "VMUSB_START_WITHOUT_STACK"
    """START_DAQ while an ISV entry names a stack that was never loaded."""
    IRQ_UNSERVICED = "VMUSB_IRQ_UNSERVICED"
    """A VME IRQ no ISV entry services (level and vector): dropped."""
    WRITE_TO_FIRMWARE_ID = "VMUSB_WRITE_TO_FIRMWARE_ID"
    """A write to the read-only FIRMWARE_ID register: ignored."""
    WRONG_ENDPOINT = "VMUSB_WRONG_ENDPOINT"
    """A transfer on an endpoint other than bulk OUT 0x02 / bulk IN 0x86."""
    STACK_OVERLAP = "VMUSB_STACK_OVERLAP"
    """A stack loaded over part of another stack's memory."""
    D8_ONE_LANE = "VMUSB_D8_ONE_LANE"
    """A D8 write whose data lanes D7..D0 and D15..D8 differ: the byte the strobe selects is
    written, which need not be the one meant (NSCLDAQ puts it on both)."""
    IRQ_MASKED = "VMUSB_IRQ_MASKED"
    """A VME IRQ an ISV entry would service, on a level the IRQ mask ignores: left pending."""
    VECTOR_HIGH_MISMATCH = "VMUSB_VECTOR_HIGH_MISMATCH"
    """A VME IRQ matching an ISV entry's level and vector byte, but not the entry's upper vector
    byte (VECTOR_HIGH1/2): no stack runs."""
    ALIGN32_DATA_TAKING = "VMUSB_ALIGN32_DATA_TAKING"
    """START_DAQ with GLOBAL_MODE's Align32 set (32-bit buffer headers, not modelled)."""


@dataclass
class VmUsbCounters:
    """What crossed the cable and what the bridge did; read freely, written under the lock."""

    out_transfers: int = 0
    """Bulk OUT transfers taken (to EP 0x02), whatever they held."""
    in_transfers: int = 0
    """Bulk IN transfers that returned data (timeouts are not transfers)."""
    immediate_lists: int = 0
    """Immediate lists run (refused and malformed ones are not)."""
    list_lines: int = 0
    """Lines of immediate lists run (a list stopped by BERR counts up to the failing line)."""
    stack_loads: int = 0
    action_writes: int = 0
    buffers: int = 0
    """Data-taking buffers closed (each BUF_LAST buffer too)."""
    irq_events: int = 0
    """IRQ events serviced: stack runs."""
    bytes_out: int = 0
    bytes_in: int = 0
    daq_starts: int = 0
    daq_stops: int = 0
    bus_errors: int = 0
    """VME cycles that ended in BERR (lists and stacks)."""
    usb_resets: int = 0


# -- parsed packets ------------------------------------------------------------------------------
class _Malformed(Exception):
    """An OUT packet or stack line the bridge cannot parse; the message is the audit detail."""


class _Op(enum.Enum):
    READ = "read"
    WRITE = "write"
    BLOCK = "block"
    REG_READ = "reg_read"
    REG_WRITE = "reg_write"


@dataclass(frozen=True)
class _Line:
    """One stack line: ``address`` is the first byte's VME address, or an internal register."""

    op: _Op
    address: int
    width: int = 4
    """Bytes per cycle: 1, 2 or 4."""
    bits: int = 0
    """Address width of the modifier (16, 24, 32); 0 for an internal register."""
    count: int = 1
    data: int = 0
    """Write data as it came: a D8 write's both lanes, D15..D8 and D7..D0."""

    @property
    def reads(self) -> bool:
        """Whether this line puts data in an answer or an event."""
        return self.op in (_Op.READ, _Op.BLOCK, _Op.REG_READ)

    def answer_bytes(self, align32: bool = False) -> int:
        """Bytes this line puts in an answer or an event when every cycle succeeds."""
        if self.op is _Op.READ:
            return read_answer_bytes(8 * self.width, align32)
        if self.op is _Op.BLOCK:
            return 4 * self.count
        return 4 if self.op is _Op.REG_READ else 0


@dataclass(frozen=True)
class _ImmediateList:
    lines: tuple[_Line, ...]


@dataclass(frozen=True)
class _StackLoad:
    stack_id: int
    offset: int
    words: tuple[int, ...]
    lines: tuple[_Line, ...]


@dataclass(frozen=True)
class _ActionWrite:
    value: int


@dataclass(frozen=True)
class _Run:
    """What running lines gave: the data read, the lines run (up to one that stopped the list),
    and whether a write got no DTACK."""

    data: bytes
    executed: int
    write_failed: bool


_TERMINATORS = struct.pack("<HH", BUF_TERMINATOR, BUF_TERMINATOR)
"""What ends a buffer: the terminator, twice."""


def _words32(payload: bytes) -> list[int]:
    return list(struct.unpack(f"<{len(payload) // 4}I", payload))


def _parse_packet(packet: bytes) -> _ImmediateList | _StackLoad | _ActionWrite:
    """Decode one OUT transfer (regs/vmusb.py, "Host to device"); raise _Malformed."""
    if len(packet) < 2:
        raise _Malformed(f"packet of {len(packet)} byte(s) has no TA word")
    (ta,) = struct.unpack_from("<H", packet)
    if ta == TA_IMMEDIATE_LIST:
        if len(packet) < 6 or (len(packet) - 6) % 4:
            raise _Malformed(f"immediate list of {len(packet)} bytes: not 6 + 4*n")
        (n_shorts,) = struct.unpack_from("<I", packet, 2)
        words = _words32(packet[6:])
        if n_shorts != 2 * len(words) + 1:
            raise _Malformed(
                f"immediate list n_shorts={n_shorts} but {len(words)} words follow "
                f"(expected {2 * len(words) + 1})"
            )
        return _ImmediateList(_parse_lines(words))
    if ta in _LOAD_TAS:
        if len(packet) < 6 or (len(packet) - 6) % 4:
            raise _Malformed(f"stack load of {len(packet)} bytes: not 6 + 4*n")
        n_shorts, offset = struct.unpack_from("<HH", packet, 2)
        words = _words32(packet[6:])
        if n_shorts != 2 * len(words) + 1:
            raise _Malformed(
                f"stack load n_shorts={n_shorts} but {len(words)} words follow "
                f"(expected {2 * len(words) + 1})"
            )
        lines = _parse_lines(words)
        shorts = sum(line.answer_bytes() for line in lines) // 2
        if shorts > EVENT_LENGTH:
            raise _Malformed(
                f"stack {_LOAD_TAS[ta]} reads {shorts} 16-bit units, more than an event holds "
                f"({EVENT_LENGTH})"
            )
        return _StackLoad(_LOAD_TAS[ta], offset, tuple(words), lines)
    if ta == REGISTER_BLOCK:
        if len(packet) != 6:
            raise _Malformed(f"register-block write of {len(packet)} bytes, not 6")
        _, register, value = struct.unpack("<HHH", packet)
        if register != ACTION_REGISTER:
            raise _Malformed(
                f"register-block write to register {register}: only the action "
                f"register ({ACTION_REGISTER}) is reached this way"
            )
        if value & ~_ACTION_BITS:
            raise _Malformed(f"action value 0x{value:04X} has unknown bits")
        return _ActionWrite(value)
    raise _Malformed(f"unknown TA 0x{ta:04X}")


def _parse_lines(words: list[int]) -> tuple[_Line, ...]:
    """Decode stack lines (regs/vmusb.py, "Stack lines"); raise _Malformed."""
    lines: list[_Line] = []
    i = 0
    while i < len(words):
        index = len(lines)
        if index >= MAX_LIST_LINES:
            raise _Malformed(f"list longer than {MAX_LIST_LINES} lines")
        mode = words[i]
        read = bool(mode & MODE_NW)
        escaped = (
            read
            and not mode & MODE_SLF
            and mode & MODE_AM_MASK in _BLT_MODIFIERS
            and mode >> BLOCK_COUNT_SHIFT == BLOCK_COUNT_ESCAPE
        )
        need = 3 if escaped or not read else 2
        if i + need > len(words):
            raise _Malformed(f"line {index} (mode 0x{mode:08X}) is truncated")
        if escaped:  # [mode | 0xFF << 24, count, address] (mvme's "universal" block read)
            count, address, data = words[i + 1], words[i + 2], 0
            if not 1 <= count <= BLT_MAX_COUNT:
                raise _Malformed(
                    f"line {index}: escaped block count {count} is not 1..{BLT_MAX_COUNT}"
                )
        else:
            address = words[i + 1]
            data = 0 if read else words[i + 2]
            count = mode >> BLOCK_COUNT_SHIFT
        i += need
        if mode & MODE_SLF:
            lines.append(_internal_line(index, mode, address, data, read))
        else:
            lines.append(_vme_line(index, mode, address, data, read, count))
    return tuple(lines)


def _internal_line(index: int, mode: int, reg: int, data: int, read: bool) -> _Line:
    if mode & ~(MODE_SLF | MODE_NW):
        raise _Malformed(f"line {index}: internal register line with mode bits 0x{mode:08X}")
    if reg not in _INTERNAL_REGS:
        raise _Malformed(f"line {index}: unknown internal register 0x{reg:X}")
    return _Line(_Op.REG_READ if read else _Op.REG_WRITE, reg, data=data)


def _vme_line(index: int, mode: int, address: int, data: int, read: bool, count: int) -> _Line:
    if mode & ~_VME_MODE_BITS:
        raise _Malformed(f"line {index}: unsupported mode bits 0x{mode & ~_VME_MODE_BITS:08X}")
    am = mode & MODE_AM_MASK
    ds = mode & (MODE_DS0 | MODE_DS1)
    if am not in _KNOWN_MODIFIERS:
        raise _Malformed(f"line {index}: unknown address modifier 0x{am:02X}")
    bits = ADDRESS_BITS[AddressModifier(am)]
    if address >> bits:
        raise _Malformed(f"line {index}: address 0x{address:X} is beyond A{bits}")
    if am in _BLT_MODIFIERS:
        if not read:
            raise _Malformed(f"line {index}: block writes are not supported")
        if count == 0:
            raise _Malformed(f"line {index}: block read with count 0")
        if ds or address & 3:
            raise _Malformed(f"line {index}: misaligned D32 block read at 0x{address:X}")
        return _Line(_Op.BLOCK, address, 4, bits, count)
    if count:
        raise _Malformed(f"line {index}: block count {count} with non-BLT modifier 0x{am:02X}")
    op = _Op.READ if read else _Op.WRITE
    if address & ADDR_NOT_LWORD:
        base = address & ~1
        if ds == 0:
            width, first = 2, base
        elif ds == MODE_DS1:
            width, first = 1, base
        elif ds == MODE_DS0:
            width, first = 1, base + 1
        else:
            raise _Malformed(f"line {index}: both data strobes set (D16 has them clear)")
        if not read and data >> 16:  # D8 data may use both lanes of the low 16 bits
            raise _Malformed(f"line {index}: D{8 * width} write data 0x{data:X} does not fit")
        return _Line(op, first, width, bits, data=data)
    if ds:
        raise _Malformed(f"line {index}: D32 line with data strobe bits 0x{ds:02X}")
    if address & 3:
        raise _Malformed(f"line {index}: misaligned D32 at 0x{address:X}")
    return _Line(op, address, 4, bits, data=data)


# -- the device ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Slave:
    name: str
    window: BusWindow
    base: int
    bits: int


@dataclass(frozen=True)
class _Stack:
    offset: int
    words: tuple[int, ...]
    lines: tuple[_Line, ...]


@dataclass
class _InItem:
    """One bulk IN transfer waiting for the host; ``sent`` bytes of it were read already."""

    data: bytes
    answer: bool
    sent: int = 0


@dataclass(frozen=True)
class _IrqWork:
    stack_id: int
    count: int


_LAST = "last"
"""Sequencer work item: the BUF_LAST buffer that ends a run, after every buffer owed."""


class _Descriptor:
    """A USB descriptor as pyusb reads it: the USB field names as attributes (``bLength``...),
    plus the layout to send it in a GET_DESCRIPTOR answer."""

    def __init__(self, layout: str, fields: dict[str, Any]) -> None:
        self._layout = layout
        self._order = [name for name in fields if name not in _NOT_ON_WIRE]
        self.__dict__.update(fields)

    def __getattr__(self, name: str) -> Any:  # only reached for a missing field
        raise AttributeError(name)

    def pack(self) -> bytes:
        return struct.pack(self._layout, *(self.__dict__[name] for name in self._order))


_NOT_ON_WIRE = frozenset(
    {"bus", "address", "port_number", "port_numbers", "speed", "extra_descriptors", "bRefresh"}
    | {"bSynchAddress"}
)
"""Attributes pyusb reads that are not bytes of the descriptor (libusb's additions, the audio
endpoint extension); the others are packed in the order each descriptor's dict lists them."""


def _device_descriptor(address: int) -> _Descriptor:
    """The device descriptor, plus what libusb adds (bus, address, ports, speed)."""
    port = address % 256
    return _Descriptor(
        "<BBHBBBBHHHBBBB",
        {
            "bLength": 18,
            "bDescriptorType": _DESC_DEVICE,
            "bcdUSB": 0x0200,
            "bDeviceClass": 0,  # per interface
            "bDeviceSubClass": 0,
            "bDeviceProtocol": 0,
            "bMaxPacketSize0": 64,
            "idVendor": VID,
            "idProduct": PID,
            "bcdDevice": _BCD_DEVICE,
            "iManufacturer": _STRING_MANUFACTURER,
            "iProduct": _STRING_PRODUCT,
            "iSerialNumber": _STRING_SERIAL,
            "bNumConfigurations": 1,
            "bus": 1,
            "address": (address - 1) % 127 + 1,
            "port_number": port,
            "port_numbers": (port,),
            "speed": _SPEED_HIGH,
        },
    )


_CONFIG = _Descriptor(
    "<BBHBBBBB",
    {
        "bLength": 9,
        "bDescriptorType": _DESC_CONFIG,
        "wTotalLength": 9 + 9 + 7 + 7,
        "bNumInterfaces": 1,
        "bConfigurationValue": CONFIGURATION,
        "iConfiguration": 0,
        "bmAttributes": 0xC0,  # self-powered: the crate powers the bridge
        "bMaxPower": 0,
        "extra_descriptors": [],
    },
)
_INTERFACE = _Descriptor(
    "<BBBBBBBBB",
    {
        "bLength": 9,
        "bDescriptorType": 4,
        "bInterfaceNumber": INTERFACE,
        "bAlternateSetting": 0,
        "bNumEndpoints": 2,
        "bInterfaceClass": 0xFF,  # vendor specific
        "bInterfaceSubClass": 0,
        "bInterfaceProtocol": 0,
        "iInterface": 0,
        "extra_descriptors": [],
    },
)


def _endpoint(address: int) -> _Descriptor:
    return _Descriptor(
        "<BBBBHB",
        {
            "bLength": 7,
            "bDescriptorType": 5,
            "bEndpointAddress": address,
            "bmAttributes": 2,  # bulk
            "wMaxPacketSize": MAX_PACKET,
            "bInterval": 0,
            "bRefresh": 0,
            "bSynchAddress": 0,
            "extra_descriptors": [],
        },
    )


_ENDPOINTS = (_endpoint(EP_OUT), _endpoint(EP_IN))


def _no_device() -> usb.core.USBError:
    return usb.core.USBError(
        "No such device (it may have been disconnected)", _LIBUSB_ERROR_NO_DEVICE, errno.ENODEV
    )


def _stall() -> usb.core.USBError:
    return usb.core.USBError("Pipe error", _LIBUSB_ERROR_PIPE, errno.EPIPE)


class SimulatedVmUsb:
    """The bridge and the crate behind it; every public method is thread-safe.

    ``clock`` stamps violations (hardware seconds; a :class:`~sim.clock.SimClock` at
    ``time_scale`` when None). Every USB transfer costs ``transfer_latency_s + nbytes /
    bandwidth_bytes_per_s`` of hardware time, summed in :attr:`modelled_busy_s` and waited for
    in real time (divided by ``time_scale``) before the transfer returns.
    """

    def __init__(
        self,
        *,
        serial: str = "VM0001",
        clock: Callable[[], float] | None = None,
        time_scale: float = 1.0,
        transfer_latency_s: float = 125e-6,
        bandwidth_bytes_per_s: float = 40e6,
        firmware_id: int = 0x0A00_0A02,
    ) -> None:
        if not time_scale > 0.0:
            raise ValueError(f"time_scale must be positive, not {time_scale}")
        if not bandwidth_bytes_per_s > 0.0 or transfer_latency_s < 0.0:
            raise ValueError("bandwidth must be positive and latency not negative")
        self.serial = serial
        self.time_scale = float(time_scale)
        self.transfer_latency_s = float(transfer_latency_s)
        self.bandwidth_bytes_per_s = float(bandwidth_bytes_per_s)
        self.firmware_id = firmware_id & 0xFFFF_FFFF
        self._clock = clock if clock is not None else SimClock(time_scale).now
        self.descriptor = _device_descriptor(next(_address_counter))
        self.counters = VmUsbCounters()
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._bus_lock = threading.Lock()
        self._abort = threading.Event()
        """Set on unplug/close: modelled transfer waits end at once."""
        self._audit = Audit(self._clock)
        self._slaves: tuple[_Slave, ...] = ()
        self._berr_address: int | None = None
        self._present = True
        self._closed = False
        self._configuration = CONFIGURATION
        """Linux configures a vendor-class device at enumeration, so a new device is configured."""
        self._busy_s = 0.0
        self._regs: dict[int, int] = {}
        self._stacks: dict[int, _Stack] = {}
        self._in: deque[_InItem] = deque()
        self._work: deque[_IrqWork | str] = deque()
        self._working = False
        self._daq_on = False
        self._lasts_owed = 0
        self._pending: dict[tuple[int, int, int], int] = {}
        """IRQs held on the bus: ``{(level, vector, vector_high): count}``."""
        self._irq_mask = IRQ_MASK_ALL
        self._open: list[bytes] = []
        """Events of the buffer being filled (each its header and data)."""
        self._held: list[bytes] = []
        """Closed buffers waiting for the rest of a multi-buffer bulk transfer."""
        self._held_deadline: float | None = None
        """Monotonic real time at which the held buffers go out regardless."""
        self._reset_registers()
        self._sequencer = threading.Thread(
            target=self._run_sequencer, name=f"vmusb-{serial}", daemon=True
        )
        self._sequencer.start()

    # -- the crate ---------------------------------------------------------------------------------
    def map(self, name: str, window: BusWindow, base: int, address_bits: int) -> None:
        """Put a slave in the crate: ``window`` answers at ``base`` for every address modifier of
        ``address_bits`` (16, 24 or 32)."""
        if address_bits not in (16, 24, 32):
            raise ValueError(f"address_bits must be 16, 24 or 32, not {address_bits}")
        if base < 0 or base % 4 or base + window.size > 1 << address_bits:
            raise ValueError(
                f"slave {name!r} at 0x{base:X} (size 0x{window.size:X}) is misaligned or "
                f"outside A{address_bits}"
            )
        with self._lock:
            for slave in self._slaves:
                if slave.name == name:
                    raise ValueError(f"a slave named {name!r} is mapped already")
                if slave.bits == address_bits and (
                    base < slave.base + slave.window.size and slave.base < base + window.size
                ):
                    raise ValueError(f"slave {name!r} overlaps {slave.name!r} in A{address_bits}")
            self._slaves = (*self._slaves, _Slave(name, window, base, address_bits))

    def unmap(self, name: str) -> None:
        """Take a slave out of the crate; its addresses answer BERR from now on."""
        with self._lock:
            self._slaves = tuple(s for s in self._slaves if s.name != name)

    def bus_error_at(self, address: int | None) -> None:
        """Fault injection: every VME cycle that touches ``address`` ends in BERR (None clears)."""
        with self._lock:
            self._berr_address = address

    def irq(
        self, level: int, vector: int, count: int = 1, *, vector_high: int = VECTOR_HIGH_8BIT
    ) -> None:
        """A VME IRQ at ``level`` answering its IACK with ``vector``, asserted ``count`` times.

        ``vector_high`` is the byte above the vector the bridge sees: the default, 0xFF, is an
        8-bit interrupter's. Never calls a window, so a slave may call it with its own lock held;
        the stack runs in the sequencer thread. While data taking is off, or while the IRQ mask
        ignores ``level``, the IRQ stays pending (level-held).
        """
        if not (1 <= level <= 7 and 0 <= vector <= 0xFF and 0 <= vector_high <= 0xFF) or count < 1:
            raise ValueError(
                f"IRQ level={level} vector={vector} vector_high={vector_high} count={count} out "
                "of range"
            )
        with self._cond:
            if not self._present:
                return
            stack_id = self._service(level, vector, vector_high, count)
            if stack_id is None:
                return
            if self._irq_mask & irq_mask_bit(level):
                self._violate(
                    VmUsbRule.IRQ_MASKED,
                    f"IRQ level {level} vector 0x{vector:02X} while the IRQ mask 0x"
                    f"{self._irq_mask:02X} ignores level {level}: left pending on the bus",
                    level=level,
                    vector=vector,
                    mask=self._irq_mask,
                )
            elif self._daq_on:
                self._work.append(_IrqWork(stack_id, count))
                self._cond.notify_all()
                return
            key = (level, vector, vector_high)
            self._pending[key] = self._pending.get(key, 0) + count

    def unplug(self) -> None:
        """The device vanishes: transfers raise ENODEV from now on, blocked reads wake and raise."""
        with self._cond:
            self._present = False
            self._work.clear()
            self._cond.notify_all()
        self._abort.set()

    def close(self) -> None:
        """Unplug and stop the sequencer thread (joined). Calling it again does nothing."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._present = False
            self._cond.notify_all()
        self._abort.set()
        if self._sequencer is not threading.current_thread():
            self._sequencer.join()

    def __enter__(self) -> SimulatedVmUsb:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- observation (the simulator's backdoor) ----------------------------------------------------
    @property
    def violations(self) -> list[Violation]:
        """A copy of the protocol misuse recorded so far, oldest first (rules: VmUsbRule)."""
        return self._audit.violations

    def clear_violations(self) -> None:
        self._audit.clear()

    @property
    def modelled_busy_s(self) -> float:
        """Hardware seconds the USB transfers cost so far (the timing model's total)."""
        with self._lock:
            return self._busy_s

    @property
    def present(self) -> bool:
        with self._lock:
            return self._present

    @property
    def daq_running(self) -> bool:
        """True from START_DAQ until the BUF_LAST buffer is queued."""
        with self._lock:
            return self._daq_on or self._lasts_owed > 0

    @property
    def pending_irqs(self) -> dict[tuple[int, int], int]:
        """IRQs held while data taking is off or their level masked: ``{(level, vector):
        count}``."""
        with self._lock:
            out: dict[tuple[int, int], int] = {}
            for (level, vector, _), count in self._pending.items():
                out[level, vector] = out.get((level, vector), 0) + count
            return out

    @property
    def irq_mask(self) -> int:
        """The IRQ mask: bit ``level - 1`` set when the bridge ignores that level."""
        with self._lock:
            return self._irq_mask

    @property
    def open_events(self) -> int:
        """Events in the buffer being filled, not yet sent (held back by the buffer mode)."""
        with self._lock:
            return len(self._open)

    @property
    def held_buffers(self) -> int:
        """Closed buffers waiting for a multi-buffer bulk transfer (USB_BULK_SETUP)."""
        with self._lock:
            return len(self._held)

    @property
    def queued_in(self) -> int:
        """Bulk IN transfers (answers and buffers) waiting for the host."""
        with self._lock:
            return len(self._in)

    def register(self, reg: int) -> int:
        """An internal register's value, without side effects."""
        with self._lock:
            return self._regs[int(reg)]

    def stack(self, stack_id: int) -> tuple[int, tuple[int, ...]] | None:
        """A loaded stack's ``(offset, words)``, or None."""
        with self._lock:
            stack = self._stacks.get(stack_id)
            return None if stack is None else (stack.offset, stack.words)

    def wait_idle(self, timeout: float = 5.0) -> bool:
        """Wait until the sequencer has run every stack it owes (event-driven, for tests)."""
        with self._cond:
            return self._cond.wait_for(
                lambda: (not self._work and not self._working) or self._closed, timeout
            )

    # -- the USB side (called by VmUsbBackend) -----------------------------------------------------
    def host_out(self, packet: bytes) -> int:
        """One bulk OUT transfer to EP 0x02: wait its modelled cost, then act on it."""
        cost = self._cost(len(packet))
        with self._lock:
            if not self._present:
                raise _no_device()
            self._busy_s += cost
            self.counters.out_transfers += 1
            self.counters.bytes_out += len(packet)
        self._model_wait(cost)
        with self._bus_lock:
            with self._cond:
                if not self._present:
                    raise _no_device()
                self._drop_unread_answer()
                try:
                    request = _parse_packet(packet)
                except _Malformed as exc:
                    self._violate(VmUsbRule.MALFORMED_PACKET, str(exc), length=len(packet))
                    return len(packet)
                if isinstance(request, _ActionWrite):
                    self._action(request.value)
                    return len(packet)
                if self._daq_on or self._lasts_owed:
                    if isinstance(request, _StackLoad):
                        self._violate(
                            VmUsbRule.LOAD_WHILE_DAQ,
                            f"stack {request.stack_id} load while data taking runs: ignored",
                        )
                    else:
                        slf = any(ln.op in (_Op.REG_READ, _Op.REG_WRITE) for ln in request.lines)
                        what = " with internal register access" if slf else ""
                        self._violate(
                            VmUsbRule.LIST_WHILE_DAQ,
                            f"immediate list{what} while data taking runs: ignored, no answer",
                        )
                    return len(packet)
                if isinstance(request, _StackLoad):
                    self._load(request)
                    return len(packet)
                self.counters.immediate_lists += 1
            run = self._run_lines(request.lines)
            with self._cond:
                self.counters.list_lines += run.executed
                if any(line.reads for line in request.lines):
                    answer = run.data  # short, or empty, after a bus error
                else:
                    ack = NO_DTACK if run.write_failed else WRITE_ACKNOWLEDGED
                    answer = struct.pack("<I" if self._align32() else "<H", ack)
                self._queue_in(answer, answer=True)
        return len(packet)

    def host_in(self, size: int, timeout_ms: int) -> bytes:
        """One bulk IN transfer from EP 0x86: the next queued item (or what fits of it), waiting
        up to ``timeout_ms`` real milliseconds (0: forever, as libusb) for one to be queued."""
        timeout = timeout_ms / 1000.0 if timeout_ms > 0 else None
        with self._cond:
            if not self._present:
                raise _no_device()
            if not self._cond.wait_for(lambda: bool(self._in) or not self._present, timeout):
                raise usb.core.USBTimeoutError(
                    "Operation timed out", _LIBUSB_ERROR_TIMEOUT, errno.ETIMEDOUT
                )
            if not self._present:
                raise _no_device()
            item = self._in[0]
            chunk = item.data[item.sent : item.sent + size]
            item.sent += len(chunk)
            if item.sent >= len(item.data):
                self._in.popleft()
            cost = self._cost(len(chunk))
            self._busy_s += cost
            self.counters.in_transfers += 1
            self.counters.bytes_in += len(chunk)
        self._model_wait(cost)
        return chunk

    def usb_reset(self) -> None:
        """A USB port reset: the endpoint FIFOs are flushed; the crate side keeps its state."""
        with self._cond:
            if not self._present:
                raise _no_device()
            self._in.clear()
            self.counters.usb_resets += 1

    def wrong_endpoint(self, ep: int, direction: str) -> usb.core.USBError:
        """Record a transfer on an endpoint the bridge does not use; the error to raise."""
        with self._lock:
            self._violate(
                VmUsbRule.WRONG_ENDPOINT,
                f"bulk {direction} on endpoint 0x{ep:02X} (the bridge uses OUT 0x{EP_OUT:02X}, "
                f"IN 0x{EP_IN:02X})",
                endpoint=ep,
            )
        return usb.core.USBError("Invalid parameter", _LIBUSB_ERROR_INVALID_PARAM, errno.EINVAL)

    def string(self, index: int) -> str | None:
        return {
            _STRING_MANUFACTURER: _MANUFACTURER,
            _STRING_PRODUCT: _PRODUCT,
            _STRING_SERIAL: self.serial,
        }.get(index)

    @property
    def configuration(self) -> int:
        with self._lock:
            return self._configuration

    def set_configuration(self, value: int) -> None:
        if value not in (0, CONFIGURATION):
            raise usb.core.USBError("Entity not found", _LIBUSB_ERROR_NOT_FOUND, errno.ENOENT)
        with self._lock:
            if not self._present:
                raise _no_device()
            self._configuration = value

    def check_present(self) -> None:
        with self._lock:
            if not self._present:
                raise _no_device()

    # -- internals (each docstring says which lock its caller holds) -------------------------------
    def _cost(self, nbytes: int) -> float:
        return self.transfer_latency_s + nbytes / self.bandwidth_bytes_per_s

    def _model_wait(self, cost: float) -> None:
        """The transfer's modelled time in real time: the model, not test synchronisation."""
        self._abort.wait(cost / self.time_scale)

    def _violate(self, rule: VmUsbRule, detail: str, **registers: int) -> None:
        """Record (lock held)."""
        self._audit.record(rule, detail, **registers)

    def _queue_in(self, data: bytes, *, answer: bool) -> None:
        """Queue one bulk IN transfer (lock held)."""
        self._in.append(_InItem(data, answer))
        self._cond.notify_all()

    def _drop_unread_answer(self) -> None:
        """An OUT transfer arrived: an immediate answer still queued is overwritten (lock held)."""
        if not any(item.answer for item in self._in):
            return
        dropped = [item for item in self._in if item.answer]
        self._in = deque(item for item in self._in if not item.answer)
        self._violate(
            VmUsbRule.ANSWER_NOT_READ,
            f"OUT transfer before the answer to the previous immediate list was read: "
            f"{sum(len(i.data) - i.sent for i in dropped)} unread byte(s) dropped",
        )

    def _reset_registers(self) -> None:
        self._regs = {int(reg): 0 for reg in InternalReg}
        self._regs[int(InternalReg.FIRMWARE_ID)] = self.firmware_id
        self._irq_mask = IRQ_MASK_ALL

    def _align32(self) -> bool:
        """GLOBAL_MODE's Align32 (lock held)."""
        return bool(self._regs[int(InternalReg.GLOBAL_MODE)] & GLOBAL_ALIGN32)

    def _isv_entries(self) -> Iterator[tuple[int, int, int, int]]:
        """Used ISV entries ``(index, level, vector, stack_id)`` (lock held); ``vector`` has 16
        bits, its upper byte from VECTOR_HIGH1/2."""
        for i, reg in enumerate(ISV_REGISTERS):
            value = self._regs[int(reg)]
            for half in (0, 1):
                entry = (value >> (16 * half)) & 0xFFFF
                level = (entry & ISV_LEVEL) >> ISV_LEVEL_SHIFT
                if level:
                    index = 2 * i + half
                    high_reg, shift = vector_high_slot(index)
                    high = (self._regs[int(high_reg)] >> shift) & 0xFF
                    yield (
                        index,
                        level,
                        high << 8 | entry & ISV_VECTOR,
                        (entry & ISV_STACK) >> ISV_STACK_SHIFT,
                    )

    def _isv_stack(self, level: int, vector: int, vector_high: int) -> int | None:
        full = vector_high << 8 | vector
        for _, lv, vec, stack_id in self._isv_entries():
            if lv == level and vec == full:
                return stack_id
        return None

    def _service(self, level: int, vector: int, vector_high: int, count: int) -> int | None:
        """The stack an IRQ runs; None, recorded, when no ISV entry takes it (lock held)."""
        stack_id = self._isv_stack(level, vector, vector_high)
        if stack_id is not None:
            return stack_id
        near = [
            (index, vec >> 8)
            for index, lv, vec, _ in self._isv_entries()
            if lv == level and vec & 0xFF == vector
        ]
        if near:
            index, high = near[0]
            self._violate(
                VmUsbRule.VECTOR_HIGH_MISMATCH,
                f"IRQ level {level} vector 0x{vector:02X} matches ISV entry {index} but its "
                f"upper vector byte is 0x{high:02X} where the interrupter presents "
                f"0x{vector_high:02X} (VECTOR_HIGH1/2): no stack runs",
                level=level,
                vector=vector,
                entry=index,
                vector_high=high,
            )
        else:
            self._violate(
                VmUsbRule.IRQ_UNSERVICED,
                f"IRQ level {level} vector 0x{vector:02X} matches no ISV entry: dropped",
                level=level,
                vector=vector,
                count=count,
            )
        return None

    def _load(self, load: _StackLoad) -> None:
        """Keep a stack (lock held)."""
        self.counters.stack_loads += 1
        end = load.offset + len(load.words)
        for other_id, other in self._stacks.items():
            if (
                other_id != load.stack_id
                and load.words
                and other.words
                and (load.offset < other.offset + len(other.words) and other.offset < end)
            ):
                self._violate(
                    VmUsbRule.STACK_OVERLAP,
                    f"stack {load.stack_id} at words {load.offset}..{end - 1} overlaps stack "
                    f"{other_id} at {other.offset}..{other.offset + len(other.words) - 1}",
                )
        self._stacks[load.stack_id] = _Stack(load.offset, load.words, load.lines)

    def _action(self, value: int) -> None:
        """The action register (lock held)."""
        self.counters.action_writes += 1
        if value & Action.SYS_RESET:
            self._reset_registers()
            self._stacks.clear()
            self._daq_on = False
            self._lasts_owed = 0
            self._work.clear()
            self._in.clear()
            self._drop_buffers()
        if value & Action.CLEAR:
            self._in = deque(item for item in self._in if item.answer)
            self._drop_buffers()
        mode = self._regs[int(InternalReg.GLOBAL_MODE)]
        if value & Action.USB_TRIGGER and mode & IRQ_MASK_LOAD:
            self._irq_mask = mode & IRQ_MASK_ALL  # CVMUSB::writeIrqMask, VMUSB::setIrqMask
        start = bool(value & Action.START_DAQ)
        if start and not self._daq_on:
            self._start_daq()
        elif not start and self._daq_on:
            self._daq_on = False
            self._lasts_owed += 1
            self.counters.daq_stops += 1
            self._work.append(_LAST)
            self._cond.notify_all()

    def _start_daq(self) -> None:
        self._daq_on = True
        self.counters.daq_starts += 1
        if self._align32():
            self._violate(
                VmUsbRule.ALIGN32_DATA_TAKING,
                "START_DAQ with Align32 set: the manual makes every buffer and event header a "
                "32-bit word then; this device sends the 16-bit layout",
                global_mode=self._regs[int(InternalReg.GLOBAL_MODE)],
            )
        for index, level, vector, named in self._isv_entries():
            if named not in self._stacks:
                self._violate(
                    VmUsbRule.START_WITHOUT_STACK,
                    f"START_DAQ: ISV entry {index} (level {level}, vector 0x{vector:04X}) names "
                    f"stack {named}, which was never loaded",
                    entry=index,
                    stack=named,
                )
        pending, self._pending = self._pending, {}
        for (level, vector, high), count in pending.items():
            if self._irq_mask & irq_mask_bit(level):
                self._pending[level, vector, high] = count  # still ignored: still on the bus
                continue
            stack_id = self._service(level, vector, high, count)
            if stack_id is not None:
                self._work.append(_IrqWork(stack_id, count))
        self._cond.notify_all()

    # -- VME cycles (the bus lock is held, the state lock is not) ----------------------------------
    def _run_lines(self, lines: tuple[_Line, ...]) -> _Run:
        """Run ``lines`` as the bridge does (regs/vmusb.py; module notes): the data read, in the
        alignment GLOBAL_MODE sets."""
        with self._lock:
            align32 = self._align32()
        data = bytearray()
        for index, line in enumerate(lines):
            if line.op is _Op.REG_READ:
                with self._lock:
                    data += struct.pack("<I", self._register_read(line.address))
                continue
            if line.op is _Op.REG_WRITE:
                with self._lock:
                    if line.address == InternalReg.FIRMWARE_ID:
                        self._violate(
                            VmUsbRule.WRITE_TO_FIRMWARE_ID,
                            "write to the read-only FIRMWARE_ID: ignored",
                            value=line.data,
                        )
                    else:
                        self._regs[line.address] = line.data & 0xFFFF_FFFF
                continue
            if line.op is _Op.BLOCK:
                words = self._block(line)
                data += struct.pack(f"<{len(words)}I", *words)
                if len(words) < line.count:  # ended short by BERR; the list goes on
                    self._bus_error()
                continue
            if line.op is _Op.WRITE and line.width == 1:
                self._check_lanes(line)
            value = self._single(line)
            if value is None:
                self._bus_error()
                return _Run(bytes(data), index + 1, line.op is _Op.WRITE)
            if line.op is _Op.READ:
                size = read_answer_bytes(8 * line.width, align32)
                data += value.to_bytes(size, "little")
        return _Run(bytes(data), len(lines), False)

    def _register_read(self, reg: int) -> int:
        """An internal register as a read sees it (lock held): FIRMWARE_ID shows the IRQ mask in
        bits 24-30 while GLOBAL_MODE has IRQ_MASK_LOAD (mvme's check of the mask)."""
        value = self._regs[reg]
        mode = self._regs[int(InternalReg.GLOBAL_MODE)]
        if reg == InternalReg.FIRMWARE_ID and mode & IRQ_MASK_LOAD:
            shown = IRQ_MASK_ALL << FID_IRQ_MASK_SHIFT
            value = value & ~shown | self._irq_mask << FID_IRQ_MASK_SHIFT
        return value

    def _bus_error(self) -> None:
        with self._lock:
            self.counters.bus_errors += 1

    def _check_lanes(self, line: _Line) -> None:
        """A D8 write whose two lanes differ (lock not held)."""
        high, low = line.data >> 8 & 0xFF, line.data & 0xFF
        if high != low:
            lane = "D7..D0" if line.address & 1 else "D15..D8"
            with self._lock:
                self._violate(
                    VmUsbRule.D8_ONE_LANE,
                    f"D8 write at 0x{line.address:X} with data 0x{line.data:04X}: the lanes "
                    f"differ, the strobe selects {lane} (0x{low if line.address & 1 else high:02X})"
                    "; NSCLDAQ puts the byte on both",
                    address=line.address,
                    data=line.data,
                )

    def _target(self, address: int, nbytes: int, bits: int) -> tuple[BusWindow, int] | None:
        """The slave that answers ``nbytes`` at ``address`` and its offset; None is BERR."""
        berr = self._berr_address
        if berr is not None and address <= berr < address + nbytes:
            return None
        for slave in self._slaves:
            if (
                slave.bits == bits
                and slave.base <= address
                and address + nbytes <= slave.base + slave.window.size
            ):
                return slave.window, address - slave.base
        return None

    def _block(self, line: _Line) -> list[int]:
        """A D32 block read's words, up to the first transfer that ends in BERR."""
        words: list[int] = []
        for k in range(line.count):
            target = self._target(line.address + 4 * k, 4, line.bits)
            if target is None:
                break
            window, offset = target
            try:
                words.append(window.read32(offset))
            except BusError:
                break
        return words

    def _single(self, line: _Line) -> int | None:
        """One single cycle: the value read (0 for a write), or None on BERR."""
        target = self._target(line.address, line.width, line.bits)
        if target is None:
            return None
        window, offset = target
        try:
            if line.op is _Op.READ:
                if line.width == 4:
                    return window.read32(offset)
                if line.width == 2:
                    return window.read16(offset)
                return window.read8(offset)
            if line.width == 4:
                window.write32(offset, line.data)
            elif line.width == 2:
                window.write16(offset, line.data)
            else:  # the lane the data strobe selects: D7..D0 odd, D15..D8 even
                window.write8(offset, line.data & 0xFF if line.address & 1 else line.data >> 8)
            return 0
        except BusError:
            return None

    # -- the sequencer: stacks run by IRQs ---------------------------------------------------------
    def _run_sequencer(self) -> None:
        while True:
            with self._cond:
                if not self._wait_for_work():
                    return
            with self._bus_lock:
                with self._cond:
                    if not self._work:  # a SYS_RESET took it meanwhile
                        continue
                    work = self._work.popleft()
                    self._working = True
                    if isinstance(work, str):  # _LAST
                        self._lasts_owed -= 1
                        self._close_buffer(last=True)
                        self._working = False
                        self._cond.notify_all()
                        continue
                    stack = self._stacks.get(work.stack_id)
                    lines = stack.lines if stack is not None else ()
                for _ in range(work.count):
                    run = self._run_lines(lines)
                    with self._cond:
                        if not self._present:
                            break
                        self.counters.irq_events += 1
                        self._add_event(work.stack_id, run.data)
                with self._cond:
                    self._working = False
                    self._cond.notify_all()

    def _wait_for_work(self) -> bool:
        """Wait for stack runs or a last buffer to do; send held buffers whose timeout passes
        meanwhile. False once the device is closed (lock held)."""
        while not self._closed:
            if self._work:
                return True
            deadline = self._held_deadline
            if deadline is None:
                self._cond.wait()
                continue
            left = deadline - time.monotonic()
            if left <= 0:
                self._send_held()
            else:
                self._cond.wait(left)
        return False

    # -- buffers (lock held) -----------------------------------------------------------------------
    def _add_event(self, stack_id: int, data: bytes) -> None:
        """Put an event in the open buffer; close it as its length code says."""
        event = struct.pack("<H", stack_id << EVENT_STACK_SHIFT | len(data) // 2) + data
        mode = self._regs[int(InternalReg.GLOBAL_MODE)]
        code = mode & BUFFER_LENGTH_MASK
        room = BUFFER_LENGTH_WORDS.get(code, BUFFER_LENGTH_WORDS[0])
        used = sum(len(e) for e in self._open) // 2 + 3  # the header and two terminators
        if self._open and used + len(event) // 2 > room:
            self._close_buffer()
        self._open.append(event)
        per_buffer = self._regs[int(InternalReg.EVENTS_PER_BUFFER)] & BUF_EVENT_COUNT
        if (
            (code == BUFFER_SINGLE_EVENT and per_buffer and len(self._open) >= per_buffer)
            or len(event) // 2 + 3 > room
            or len(self._open) == BUF_EVENT_COUNT
        ):
            self._close_buffer()

    def _close_buffer(self, *, last: bool = False) -> None:
        """Close the open buffer (an empty one only as the last) and send it, or hold it for a
        multi-buffer transfer; the last buffer sends everything held."""
        if not self._open and not last:
            return
        header = (BUF_LAST if last else 0) | len(self._open)
        buffer = b"".join([struct.pack("<H", header), *self._open, _TERMINATORS])
        self._open = []
        self.counters.buffers += 1
        self._held.append(buffer)
        setup = self._regs[int(InternalReg.USB_BULK_SETUP)]
        if last or len(self._held) >= max(1, setup & BULK_MULTI_BUFFER):
            self._send_held()
        elif self._held_deadline is None:
            code = (setup & BULK_TIMEOUT) >> BULK_TIMEOUT_SHIFT
            self._held_deadline = time.monotonic() + (code or 1) / self.time_scale
            self._cond.notify_all()

    def _send_held(self) -> None:
        """The held buffers, in one bulk IN transfer."""
        if self._held:
            self._queue_in(b"".join(self._held), answer=False)
        self._held = []
        self._held_deadline = None

    def _drop_buffers(self) -> None:
        self._open = []
        self._held = []
        self._held_deadline = None


# -- pyusb -----------------------------------------------------------------------------------------
class _Handle:
    """What ``open_device`` returns: the device and the interfaces this handle claimed."""

    def __init__(self, device: SimulatedVmUsb) -> None:
        self.device = device
        self.claimed: set[int] = set()


class VmUsbBackend(usb.backend.IBackend):  # type: ignore[misc]  # pyusb is untyped
    """A pyusb backend whose bus holds simulated VM-USBs (unplugged ones are not enumerated)."""

    def __init__(self, *devices: SimulatedVmUsb) -> None:
        super().__init__()
        self._lock = threading.Lock()
        self._devices: list[SimulatedVmUsb] = list(devices)

    def add(self, device: SimulatedVmUsb) -> None:
        """Plug another device in."""
        with self._lock:
            self._devices.append(device)

    # -- enumeration and descriptors ---------------------------------------------------------------
    def enumerate_devices(self) -> Iterator[SimulatedVmUsb]:
        with self._lock:
            devices = list(self._devices)
        for device in devices:
            if device.present:
                yield device

    def get_parent(self, dev: SimulatedVmUsb) -> None:
        return None

    def get_device_descriptor(self, dev: SimulatedVmUsb) -> _Descriptor:
        return dev.descriptor

    def get_configuration_descriptor(self, dev: SimulatedVmUsb, config: int) -> _Descriptor:
        if config != 0:
            raise IndexError(f"configuration index {config}: the VM-USB has one")
        return _CONFIG

    def get_interface_descriptor(
        self, dev: SimulatedVmUsb, intf: int, alt: int, config: int
    ) -> _Descriptor:
        if config != 0 or intf != 0 or alt != 0:
            raise IndexError(f"interface {intf} alternate setting {alt} does not exist")
        return _INTERFACE

    def get_endpoint_descriptor(
        self, dev: SimulatedVmUsb, ep: int, intf: int, alt: int, config: int
    ) -> _Descriptor:
        if config != 0 or intf != 0 or alt != 0 or not 0 <= ep < len(_ENDPOINTS):
            raise IndexError(f"endpoint index {ep} does not exist")
        return _ENDPOINTS[ep]

    # -- handles, configuration, interfaces --------------------------------------------------------
    def open_device(self, dev: SimulatedVmUsb) -> _Handle:
        dev.check_present()
        return _Handle(dev)

    def close_device(self, dev_handle: _Handle) -> None:
        dev_handle.claimed.clear()

    def set_configuration(self, dev_handle: _Handle, config_value: int) -> None:
        dev_handle.device.set_configuration(config_value)

    def get_configuration(self, dev_handle: _Handle) -> int:
        dev_handle.device.check_present()
        return dev_handle.device.configuration

    def set_interface_altsetting(self, dev_handle: _Handle, intf: int, altsetting: int) -> None:
        dev_handle.device.check_present()
        if intf != INTERFACE or altsetting != 0:
            raise usb.core.USBError("Entity not found", _LIBUSB_ERROR_NOT_FOUND, errno.ENOENT)

    def claim_interface(self, dev_handle: _Handle, intf: int) -> None:
        dev_handle.device.check_present()
        if intf != INTERFACE:
            raise usb.core.USBError("Entity not found", _LIBUSB_ERROR_NOT_FOUND, errno.ENOENT)
        dev_handle.claimed.add(intf)

    def release_interface(self, dev_handle: _Handle, intf: int) -> None:
        dev_handle.claimed.discard(intf)
        dev_handle.device.check_present()

    def is_kernel_driver_active(self, dev_handle: _Handle, intf: int) -> bool:
        return False

    def detach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        return None

    def attach_kernel_driver(self, dev_handle: _Handle, intf: int) -> None:
        return None

    def reset_device(self, dev_handle: _Handle) -> None:
        dev_handle.device.usb_reset()

    def clear_halt(self, dev_handle: _Handle, ep: int) -> None:
        dev_handle.device.check_present()
        if ep not in (EP_OUT, EP_IN):
            raise usb.core.USBError("Entity not found", _LIBUSB_ERROR_NOT_FOUND, errno.ENOENT)

    # -- transfers ---------------------------------------------------------------------------------
    def bulk_write(
        self, dev_handle: _Handle, ep: int, intf: int, data: array.array[Any], timeout: int
    ) -> int:
        device = dev_handle.device
        if ep != EP_OUT:
            device.check_present()
            raise device.wrong_endpoint(ep, "write")
        return device.host_out(data.tobytes())

    def bulk_read(
        self, dev_handle: _Handle, ep: int, intf: int, buff: array.array[Any], timeout: int
    ) -> int:
        device = dev_handle.device
        if ep != EP_IN:
            device.check_present()
            raise device.wrong_endpoint(ep, "read")
        view = memoryview(buff).cast("B")
        chunk = device.host_in(len(view), timeout)
        view[: len(chunk)] = chunk
        return len(chunk)

    def ctrl_transfer(
        self,
        dev_handle: _Handle,
        request_type: int,
        request: int,
        value: int,
        index: int,
        data: array.array[Any],
        timeout: int,
    ) -> int:
        """Standard requests only: GET_DESCRIPTOR (device, configuration, strings), GET_STATUS,
        GET/SET_CONFIGURATION, SET_INTERFACE, CLEAR_FEATURE; anything else stalls."""
        device = dev_handle.device
        device.check_present()
        if request_type & _CTRL_TYPE_MASK:
            raise _stall()  # no class or vendor requests
        view = memoryview(data).cast("B")
        if request_type & _CTRL_IN:
            if request == _REQ_GET_DESCRIPTOR:
                reply = self._descriptor(device, value >> 8, value & 0xFF)
            elif request == _REQ_GET_STATUS:
                reply = b"\x01\x00" if request_type & 3 == 0 else b"\x00\x00"  # self-powered
            elif request == _REQ_GET_CONFIGURATION:
                reply = bytes([device.configuration])
            else:
                raise _stall()
            n = min(len(reply), len(view))
            view[:n] = reply[:n]
            return n
        if request == _REQ_SET_CONFIGURATION:
            device.set_configuration(value)
        elif request == _REQ_SET_INTERFACE:
            self.set_interface_altsetting(dev_handle, index, value)
        elif request != _REQ_CLEAR_FEATURE:
            raise _stall()
        return len(view)

    @staticmethod
    def _descriptor(device: SimulatedVmUsb, kind: int, index: int) -> bytes:
        if kind == _DESC_DEVICE and index == 0:
            return device.descriptor.pack()
        if kind == _DESC_CONFIG and index == 0:
            return _CONFIG.pack() + _INTERFACE.pack() + b"".join(ep.pack() for ep in _ENDPOINTS)
        if kind == _DESC_STRING:
            if index == 0:
                return struct.pack("<BBH", 4, _DESC_STRING, _LANGID_EN_US)
            text = device.string(index)
            if text is not None:
                encoded = text.encode("utf-16-le")
                return bytes([2 + len(encoded), _DESC_STRING]) + encoded
        raise _stall()
