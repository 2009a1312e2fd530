"""The ``vmusb`` window: VME boards reached through a Wiener VM-USB bridge, over pyusb.

The bridge runs *lists* of VME cycles: the host sends a list in one bulk OUT transfer and reads
every value it read in one bulk IN transfer (the wire format is :mod:`regs.vmusb`). A USB round
trip costs far more than the VME cycles in it, so the window turns each access into one list,
and :meth:`VmUsbWindow.read_many` / :meth:`VmUsbWindow.read_regs` put several reads into one.

Three pieces:

* :class:`VmeList` builds a list and decodes its answer: a write list's acknowledgement (zero
  is no DTACK, a VME bus error), a read list's data (an answer that ends short is a bus error),
  either as a :class:`~biris_hw.errors.BusError` naming the VME cycle;
* :class:`VmUsbBridge` is one claimed device, shared (reference-counted) by every window and
  interrupt line of one serial number. It runs immediate lists, loads IRQ stacks, and while any
  IRQ is armed keeps *data taking* running with a reader thread that parses the buffers the
  bridge sends when it has run a stack for a VME interrupt. The bridge forbids an immediate list
  while data taking runs, so :meth:`VmUsbBridge.execute` stops it, runs the list, and starts it
  again; a VME interrupt raised meanwhile stays pending on the bus and is served at the restart.
  Bring-up sets what the public drivers set (:mod:`regs.vmusb` names each source): one event
  per buffer, so an interrupt's buffer leaves the bridge at once however idle it is, no
  multi-buffering, Align32 clear, the IRQ mask (levels nobody armed ignored), the ISV vector
  high bytes an 8-bit interrupter needs;
* :class:`VmUsbWindow` (kind ``vmusb``): offsets of the window are VME addresses from ``base``
  with one address modifier. Interrupt lines are :class:`biris_hw.irq.vmusb.VmUsbLine`.

Every failure is a :class:`~biris_hw.errors.BusError` naming the bridge's serial number; once
the device has gone (unplugged, powered off), every access raises and every armed IRQ is
suspended (its line's ``wait()`` raises the error), until :meth:`VmUsbBridge.relink` (or
:meth:`VmUsbWindow.relink`, which a server's reset calls through its hardware bundle) finds the
serial number again, brings the device up and re-arms the IRQs: the same windows and lines then
work again.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import struct
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import usb.core
import usb.util

from biris_hw.bus.base import BusWindow
from biris_hw.errors import BusError
from regs.vmusb import (
    ACTION_REGISTER,
    ADDR_NOT_LWORD,
    ADDRESS_BITS,
    BLOCK_COUNT_SHIFT,
    BLT_BOUNDARY,
    BLT_OF,
    BUF_EVENT_COUNT,
    BUF_LAST,
    BUF_TERMINATOR,
    BUFFER_SINGLE_EVENT,
    CONFIGURATION,
    EP_IN,
    EP_OUT,
    EVENT_CONTINUATION,
    EVENT_LENGTH,
    EVENT_STACK_SHIFT,
    FID_IRQ_MASK_SHIFT,
    INTERFACE,
    IRQ_MASK_ALL,
    IRQ_MASK_LOAD,
    ISV_REGISTERS,
    MAX_LIST_LINES,
    MAX_PACKET,
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
    Action,
    AddressModifier,
    InternalReg,
    irq_mask_bit,
    isv_entry,
    read_answer_bytes,
    ta_load,
)

__all__ = [
    "DRIVER_GLOBAL_MODE",
    "IRQ_STACK_IDS",
    "IRQ_STACK_WORDS",
    "BridgeStats",
    "IrqSubscription",
    "ReadSlot",
    "VmUsbBridge",
    "VmUsbWindow",
    "VmeList",
]

log = logging.getLogger(__name__)

IRQ_STACK_IDS = range(2, 8)
"""Stacks the driver gives to IRQs (0 and 1 are the bridge's event and scaler stacks)."""
IRQ_STACK_WORDS = 128
"""Stack memory (32-bit words) set aside for each IRQ stack: stack ``i`` loads at offset
``(i - 2) * IRQ_STACK_WORDS``, so arming one IRQ never moves another's stack."""

DRIVER_GLOBAL_MODE = BUFFER_SINGLE_EVENT
"""GLOBAL_MODE as the driver runs the bridge: buffer length code 9 with one event per buffer
(EVENTS_PER_BUFFER 1), so each interrupt's buffer is sent at once; Align32 clear (16-bit
alignment, as NSCLDAQ and mvme take data); no mixed or spanning buffers; bus request level 0."""
EVENTS_PER_BUFFER = 1
"""Events per buffer under :data:`DRIVER_GLOBAL_MODE`."""
BULK_SETUP = 0
"""USB_BULK_SETUP: no multi-buffering (each buffer its own bulk transfer), timeout code 0, as
NSCLDAQ's ``startDaq`` and mvme's DAQ start write it."""

READ_SIZE = 64 * MAX_PACKET
"""Bytes asked for by one bulk IN read of data-taking buffers (several buffers fit)."""
DRAIN_TIMEOUT_S = 0.02
"""Silence on the IN endpoint that counts as drained at bring-up: the last buffer of a run a
previous user left going follows the stop within a few USB microframes."""
DRAIN_LIMIT = 256
"""Reads of stale data before bring-up gives up on a bridge that never falls silent."""
READER_POLL_S = 0.25
"""The reader thread's bulk IN timeout: how soon it notices it should quit. (A timed-out read
can lose a partial transfer with libusb, so it is not made short.)"""

_U16 = struct.Struct("<H")
_LIST_HEADER = struct.Struct("<HI")
_SHORTS3 = struct.Struct("<HHH")

_VANISHED = frozenset({errno.ENODEV, errno.EIO, errno.ENXIO, errno.ESHUTDOWN})
"""USB errors that mean the device is gone, or the exchange is beyond recovery."""

_WIDTH_MASK = {8: 0xFF, 16: 0xFFFF, 32: 0xFFFF_FFFF}
_WRITES_NAMED = 4
"""Writes named one by one in the message of an unacknowledged write list."""


# -- lists -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReadSlot:
    """What one entry of :meth:`VmeList.decode`'s result is.

    ``kind`` ``single`` (a VME single cycle, an ``int`` of ``width`` bits), ``block`` (a D32 block
    read, ``bytes`` of ``4 * count``, big-endian as a 68k sees them) or ``register`` (an internal
    register of the bridge, an ``int``); ``address`` is the VME address (or register) read.
    """

    kind: Literal["single", "block", "register"]
    address: int
    width: int
    count: int

    @property
    def nbytes(self) -> int:
        """Bytes of the answer this entry takes: a ``u16`` for a D8 or D16 single cycle (Align32
        is clear), a ``u32`` per D32 transfer and per register."""
        if self.kind == "single":
            return read_answer_bytes(self.width)
        return 4 * self.count


@dataclass(frozen=True)
class _Line:
    words: tuple[int, ...]
    nbytes: int
    """Bytes this line adds to the answer."""
    what: str
    """The cycle, for messages: ``D16 read at A24 0x001234``."""
    vme: Literal["read", "write", ""] = ""
    """A VME read or write line; "" for an internal register."""


def _modifier(am: int) -> AddressModifier:
    try:
        return AddressModifier(am)
    except ValueError:
        known = ", ".join(f"0x{m:02X}" for m in AddressModifier)
        raise BusError(
            f"address modifier 0x{am:02X} is not one the VM-USB driver knows ({known})",
            errno.EINVAL,
        ) from None


def _space(am: AddressModifier, address: int) -> str:
    return f"A{ADDRESS_BITS[am]} 0x{address:0{ADDRESS_BITS[am] // 4}X} (AM 0x{am:02X})"


class VmeList:
    """A list of VME cycles and bridge register accesses, built line by line.

    Builders append lines (they check address ranges and alignment and raise
    :class:`BusError` for a line the bridge could not run); :meth:`words` is the stack as the
    bridge takes it; :attr:`reads` says what each entry of :meth:`decode`'s result is. A list
    may be longer than :data:`~regs.vmusb.MAX_LIST_LINES`: :meth:`segments` cuts it into the
    lists the bridge runs one after the other.

    A list holds VME reads or VME writes, not both (internal register lines go with either):
    the answer to a list with reads carries their data only, so a write's bus error would not
    show in it.
    """

    def __init__(self) -> None:
        self._lines: list[_Line] = []
        self.reads: list[ReadSlot] = []
        self._vme_kinds: set[str] = set()

    def __len__(self) -> int:
        return len(self._lines)

    def __repr__(self) -> str:
        return f"<VmeList {len(self._lines)} line(s), {len(self.reads)} read(s)>"

    # -- single cycles -----------------------------------------------------------------------------
    def read8(self, am: int, address: int) -> None:
        self._single(am, address, 8, None)

    def read16(self, am: int, address: int) -> None:
        self._single(am, address, 16, None)

    def read32(self, am: int, address: int) -> None:
        self._single(am, address, 32, None)

    def write8(self, am: int, address: int, value: int) -> None:
        self._single(am, address, 8, value)

    def write16(self, am: int, address: int, value: int) -> None:
        self._single(am, address, 16, value)

    def write32(self, am: int, address: int, value: int) -> None:
        self._single(am, address, 32, value)

    def _single(self, am: int, address: int, width: int, value: int | None) -> None:
        mod = _modifier(am)
        nbytes = width // 8
        _check_address(mod, address, nbytes)
        if address % nbytes:
            raise BusError(f"D{width} cycle at {_space(mod, address)} is misaligned", errno.EINVAL)
        if width == 32:
            ds, field = 0, address & ~3
        elif width == 16:
            ds, field = 0, (address & ~1) | ADDR_NOT_LWORD
        else:  # D8: one data strobe picks the byte lane (Interpretation in regs.vmusb)
            ds = MODE_DS0 if address & 1 else MODE_DS1
            field = (address & ~1) | ADDR_NOT_LWORD
        what = f"D{width} {'read' if value is None else 'write'} at {_space(mod, address)}"
        if value is None:
            self._vme("read")
            line = _Line((MODE_NW | mod | ds, field), read_answer_bytes(width), what, "read")
            self._lines.append(line)
            self.reads.append(ReadSlot("single", address, width, 1))
        else:
            self._vme("write")
            data = _fit(value, width)
            if width == 8:  # on both data lanes, D7..D0 and D15..D8 (NSCLDAQ's addWrite8)
                data |= data << 8
            self._lines.append(_Line((mod | ds, field, data), 0, what, "write"))

    def _vme(self, kind: Literal["read", "write"]) -> None:
        """Refuse a VME read in a list of VME writes, and the other way round."""
        other = "write" if kind == "read" else "read"
        if other in self._vme_kinds:
            raise BusError(
                f"a VME {kind} in a list of VME {other}s: the answer to a list with reads "
                "carries their data only, so a write's bus error would not show",
                errno.EINVAL,
            )
        self._vme_kinds.add(kind)

    # -- block reads -------------------------------------------------------------------------------
    def block_read32(self, am: int, address: int, n_words: int) -> None:
        """D32 block transfer of ``n_words`` from ``address``; ``am`` is the BLT modifier or the
        data modifier it belongs to. One result entry (``bytes``), however many lines it takes:
        a line ends at every :data:`~regs.vmusb.BLT_BOUNDARY` (NSCLDAQ's ``addBlockRead``), so
        none carries more than 64 transfers and the count field never needs its escape."""
        mod = _modifier(am)
        blt = BLT_OF.get(mod, mod)
        if blt not in BLT_OF.values():
            raise BusError(f"AM 0x{mod:02X} has no block-transfer modifier", errno.EINVAL)
        if n_words < 1:
            raise BusError(f"a block read needs at least one word, not {n_words}", errno.EINVAL)
        _check_address(blt, address, 4 * n_words)
        if address % 4:
            raise BusError(f"block read at {_space(blt, address)} is misaligned", errno.EINVAL)
        self._vme("read")
        at, left = address, n_words
        while left:
            count = min(left, (BLT_BOUNDARY - at % BLT_BOUNDARY) // 4)
            mode = MODE_NW | blt | count << BLOCK_COUNT_SHIFT
            what = f"D32 block read of {count} word(s) at {_space(blt, at)}"
            self._lines.append(_Line((mode, at), 4 * count, what, "read"))
            at, left = at + 4 * count, left - count
        self.reads.append(ReadSlot("block", address, 32, n_words))

    # -- the bridge's own registers ----------------------------------------------------------------
    def read_register(self, reg: int) -> None:
        self._lines.append(_Line((MODE_NW | MODE_SLF, reg), 4, f"read of register 0x{reg:02X}"))
        self.reads.append(ReadSlot("register", reg, 32, 1))

    def write_register(self, reg: int, value: int) -> None:
        what = f"write of register 0x{reg:02X}"
        self._lines.append(_Line((MODE_SLF, reg, _fit(value, 32)), 0, what))

    # -- the wire ------------------------------------------------------------------------------
    def words(self, lines: range | None = None) -> list[int]:
        """The stack (u32 words) of the whole list, or of ``lines`` of it."""
        chosen = self._lines if lines is None else self._lines[lines.start : lines.stop]
        return [word for line in chosen for word in line.words]

    def segments(self) -> list[range]:
        """The line ranges the bridge runs as separate lists (none for an empty list)."""
        n = len(self._lines)
        return [range(i, min(n, i + MAX_LIST_LINES)) for i in range(0, n, MAX_LIST_LINES)]

    def answer_bytes(self, lines: range | None = None) -> int:
        """Bytes of data the answer to ``lines`` (default: all) carries."""
        chosen = self._lines if lines is None else self._lines[lines.start : lines.stop]
        return sum(line.nbytes for line in chosen)

    def answer_size(self, lines: range | None = None) -> int:
        """Bytes of a good answer to ``lines``: the data, or the ``u16`` of a list without reads."""
        return self.answer_bytes(lines) or 2

    def payload(self, answer: bytes, lines: range | None = None) -> bytes:
        """The data of the answer to ``lines`` (one bulk IN transfer), checked.

        A list without reads is answered by an acknowledgement: zero when a VME write got no
        DTACK (:class:`BusError` EIO naming the writes), anything else when all did; a list of
        register writes only is not judged by it. A list with reads is answered by their data;
        an answer that ends short means a VME bus error ended the list (EIO naming the first
        read whose data is missing: the failing cycle, or one after it when a block read ended
        short and the list went on). Any other answer is EPROTO.
        """
        span = range(len(self._lines)) if lines is None else lines
        chosen = self._lines[span.start : span.stop]
        expected = sum(line.nbytes for line in chosen)
        if not expected:
            if len(answer) not in (2, 4):  # a u16; a u32 under Align32 (mvme's write32)
                raise BusError(
                    f"the VM-USB answered {len(answer)} byte(s) to a list without reads, not "
                    "a 2-byte acknowledgement",
                    errno.EPROTO,
                )
            writes = [line for line in chosen if line.vme == "write"]
            if writes and int.from_bytes(answer, "little") == NO_DTACK:
                raise BusError(f"VME bus error (no DTACK): {_writes(writes)}", errno.EIO)
            return b""
        if len(answer) == expected:
            return answer
        if len(answer) < expected and not len(answer) % 2:
            done = 0
            for line in chosen:
                done += line.nbytes
                if line.nbytes and done > len(answer):
                    raise BusError(
                        f"VME bus error at or before the {line.what} (the answer is "
                        f"{expected - len(answer)} of {expected} byte(s) short)",
                        errno.EIO,
                    )
        raise BusError(
            f"the VM-USB answered {len(answer)} byte(s) to a list whose answer is {expected} "
            "byte(s)",
            errno.EPROTO,
        )

    def values(self, payload: bytes) -> list[int | bytes]:
        """The result entries (one per :attr:`reads` slot) of checked answer data."""
        if len(payload) != self.answer_bytes():
            raise BusError(
                f"{len(payload)} byte(s) of data for a list that reads {self.answer_bytes()}",
                errno.EPROTO,
            )
        out: list[int | bytes] = []
        pos = 0
        for slot in self.reads:
            if slot.kind == "block":
                n = slot.count
                words = struct.unpack_from(f"<{n}I", payload, pos)
                out.append(struct.pack(f">{n}I", *words))
            else:
                value = int.from_bytes(payload[pos : pos + slot.nbytes], "little")
                out.append(value & _WIDTH_MASK[slot.width])
            pos += slot.nbytes
        return out

    def decode(self, answer: bytes) -> list[int | bytes]:
        """The values of a one-transfer answer to the whole list (see :meth:`payload`)."""
        return self.values(self.payload(answer))


def _writes(writes: Sequence[_Line]) -> str:
    """The writes of an unacknowledged list, for its message (which one failed is not said)."""
    if len(writes) == 1:
        return f"the {writes[0].what}"
    named = ", ".join(line.what for line in writes[:_WRITES_NAMED])
    more = f", ... ({len(writes) - _WRITES_NAMED} more)" if len(writes) > _WRITES_NAMED else ""
    return f"one of the list's {len(writes)} writes: {named}{more}"


def _check_address(mod: AddressModifier, address: int, nbytes: int) -> None:
    if address < 0 or address + nbytes > 1 << ADDRESS_BITS[mod]:
        raise BusError(
            f"{nbytes} byte(s) at 0x{address:X} do not fit in A{ADDRESS_BITS[mod]} space",
            errno.EINVAL,
        )


def _fit(value: int, bits: int) -> int:
    if not -(1 << (bits - 1)) <= value < (1 << bits):
        raise BusError(f"value {value} does not fit in {bits} bits", errno.EINVAL)
    return value & ((1 << bits) - 1)


# -- the bridge --------------------------------------------------------------------------------


@dataclass
class BridgeStats:
    """What one bridge has done on the wire (for benchmarks and tests)."""

    lists: int = 0
    """Immediate lists executed (as sent: a long list counts once per segment)."""
    transfers_out: int = 0
    transfers_in: int = 0
    """Bulk IN transfers that brought data (answers, buffers, drained leftovers)."""
    daq_starts: int = 0
    daq_stops: int = 0
    buffers: int = 0
    events: int = 0
    stray_events: int = 0
    """Events of a stack no armed IRQ owns (dropped)."""


class IrqSubscription:
    """One armed VME interrupt: its IRQ stack, and the mailbox its events land in.

    Events are counted on an eventfd (readable while any are pending, so a line can poll it);
    the values the stack read for the newest one are kept under the same lock as the count, so
    :meth:`take` returns a count and the values of the last event it counted, never those of an
    event it did not count.

    **A lost device suspends the IRQ, it does not end it.** When the bridge's device goes away
    the subscription stays registered with its stack and vector; its eventfd is made readable
    and :meth:`take` raises the bridge's :class:`BusError` (so a thread polling the line wakes
    and its ``wait()`` raises: the target is gone) until :meth:`VmUsbBridge.relink` has found
    the device again and re-armed the stack; then it counts events as before. ``on_close`` is
    not called for a lost device (the line stays usable across the loss); the parameter is kept
    for callers that pass one.
    """

    def __init__(
        self,
        bridge: VmUsbBridge,
        level: int,
        vector: int,
        stack_id: int,
        reads: VmeList,
        on_close: Callable[[BusError], None] | None,
    ) -> None:
        self.bridge = bridge
        self.level = level
        self.vector = vector
        self.stack_id = stack_id
        self.reads = reads
        self.error: BusError | None = None
        """Why the IRQ is suspended (the device went away), or None while it is armed."""
        self._on_close = on_close
        self._lock = threading.Lock()
        self._fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        self._fd_open = True
        self._latest: tuple[int, ...] | None = None
        self._armed = True

    @property
    def armed(self) -> bool:
        return self._armed

    def fileno(self) -> int:
        return self._fd

    def take(self) -> tuple[int, tuple[int, ...] | None]:
        """Events since the last take, and the values read for the newest of them; raises the
        bridge's :class:`BusError` while the device is lost (see the class notes)."""
        with self._lock:
            if not self._fd_open:
                return 0, None
            loss = self.error
            if loss is not None:
                raise BusError(str(loss), loss.errno or errno.ENODEV)
            try:
                count = int(os.eventfd_read(self._fd))
            except BlockingIOError:
                return 0, None
            return count, self._latest

    def wake(self) -> None:
        """Make the descriptor readable (a closing line wakes whoever polls it)."""
        with self._lock:
            if self._fd_open:
                os.eventfd_write(self._fd, 1)

    def disarm(self) -> None:
        """Clear the ISV entry (data taking stops if no IRQ is left), close the mailbox; once."""
        with self._lock:
            armed, self._armed = self._armed, False
        try:
            if armed:
                self.bridge._disarm(self)
        finally:
            with self._lock:
                if self._fd_open:
                    self._fd_open = False
                    os.close(self._fd)

    # -- the bridge's side -------------------------------------------------------------------------
    def _post(self, values: tuple[int, ...] | None) -> None:
        with self._lock:
            if not self._fd_open:
                return
            self._latest = values
            os.eventfd_write(self._fd, 1)

    def _lost(self, error: BusError) -> None:
        """The device went away: suspended, and pollers woken to find out (:meth:`take`)."""
        with self._lock:
            if not self._armed or not self._fd_open:
                return
            self.error = error
            os.eventfd_write(self._fd, 1)

    def _restored(self) -> None:
        """The bridge re-armed the stack on a device found again: events count afresh (what
        was pending from before the loss is dropped with the loss's wake-up)."""
        with self._lock:
            self.error = None
            self._latest = None
            if self._fd_open:
                with contextlib.suppress(BlockingIOError):
                    os.eventfd_read(self._fd)


_TABLE_LOCK = threading.RLock()
_TABLE: dict[tuple[str, int], VmUsbBridge] = {}
"""Open bridges by (serial, id(backend)); the bridge keeps its backend, so the id stays its."""


class VmUsbBridge:
    """One claimed VM-USB, shared by the windows and lines of its serial number.

    Get one with :meth:`acquire` and give it back with :meth:`release`; the last release stops
    data taking and frees the device. One lock covers every exchange (the bridge answers one
    list at a time, and a list must not run while data taking does).

    **Lost and found.** A device that goes away (unplugged, the crate powered off) makes the
    bridge *lost*: every access raises, every armed IRQ is suspended (its line's waiters get the
    :class:`BusError`), and nothing else changes -- the windows and lines keep this bridge.
    :meth:`relink` looks for the serial number again on the same backend and, once the device
    is back, brings it up as at the first open and re-arms every suspended IRQ, so the same
    windows and lines work again. :meth:`acquire` of a lost bridge's serial tries the same.
    """

    drain_timeout_s = DRAIN_TIMEOUT_S

    # -- sharing -----------------------------------------------------------------------------------
    @classmethod
    def acquire(
        cls, serial: str | None = None, backend: Any = None, timeout_s: float = 2.0
    ) -> VmUsbBridge:
        """The bridge of ``serial`` (or of the only VM-USB connected), opened if need be.

        ``backend`` is a pyusb backend (None: libusb as pyusb finds it). ``timeout_s`` bounds
        each USB transfer; the first user of a bridge sets it.
        """
        if not (isinstance(timeout_s, (int, float)) and 0 < timeout_s < 3600):
            raise BusError(
                f"timeout_s must be a positive number of seconds, not {timeout_s!r}", errno.EINVAL
            )
        with _TABLE_LOCK:
            if serial is not None:
                known = _TABLE.get((serial, id(backend)))
                if known is not None and known._dead is None:
                    known._refs += 1
                    return known
                if known is not None and known.lost:  # its windows keep it: find it again
                    known.relink()
                    known._refs += 1
                    return known
            device, found_serial = _find(serial, backend)
            key = (found_serial, id(backend))
            known = _TABLE.get(key)
            if known is not None and known._dead is None:
                usb.util.dispose_resources(device)
                known._refs += 1
                return known
            if known is not None and known.lost:
                usb.util.dispose_resources(device)
                known.relink()
                known._refs += 1
                return known
            bridge = cls(device, found_serial, backend, float(timeout_s))
            _TABLE[key] = bridge
            return bridge

    def release(self) -> None:
        """Give back one reference; the last one stops data taking and frees the device."""
        with _TABLE_LOCK:
            if self._refs <= 0:
                return
            self._refs -= 1
            if self._refs:
                return
            if _TABLE.get(self._key) is self:
                del _TABLE[self._key]
            self._shutdown()

    def _retain(self) -> None:
        with _TABLE_LOCK:
            self._refs += 1

    # -- bring-up ----------------------------------------------------------------------------------
    def __init__(self, device: Any, serial: str, backend: Any, timeout_s: float) -> None:
        self.serial = serial
        self.backend = backend
        self.timeout_s = timeout_s
        self.firmware_id: int | None = None
        self.stats = BridgeStats()
        self._dev = device
        self._key = (serial, id(backend))
        self._timeout_ms = max(1, round(timeout_s * 1000))
        self._refs = 1
        self._io = threading.RLock()
        self._cond = threading.Condition(threading.Lock())
        self._dead: BusError | None = None
        self._released = False
        """The last reference was given back: the bridge is gone for good (never re-linked)."""
        self._generation = 0
        """Bumped by every :meth:`relink`: a reader thread of an earlier device ends."""
        self.relinks = 0
        """How many times :meth:`relink` found the device again (for status and tests)."""
        self._subs: dict[int, IrqSubscription] = {}
        self._isv = [0] * 8
        self._irq_mask = IRQ_MASK_ALL
        """The IRQ mask the bridge holds (bring-up ignores every level)."""
        self._daq = False
        self._hold = 0
        self._owed_start = False
        self._reading = False
        self._quit = False
        self._resync = False
        self._reader: threading.Thread | None = None
        self._inbuf = bytearray()
        try:
            with self._io:
                self._bring_up()
        except BaseException:
            self._dead = self._dead or BusError(f"VM-USB {serial}: bring-up failed")
            self._released = True  # never shared: nothing holds it to re-link
            self._free_device()
            raise

    def _bring_up(self) -> None:
        """Claim the device and leave it idle, in a known mode, with nothing owed on EP 0x86.

        As NSCLDAQ's ``openVMUsb`` and mvme's ``openUsbDevice``: clear, stop data taking, drain,
        every IRQ level masked (NSCLDAQ ``writeIrqMask(0x7f)``). Then the registers data taking
        depends on (:mod:`regs.vmusb`, "Bring-up registers"), in the list that ends the mask's
        load: one event per buffer, no multi-buffering, the vector high bytes of 8-bit
        interrupters; and the firmware id. Stale ISV entries are cleared before the mask is
        loaded.
        """
        try:
            self._dev.set_configuration(CONFIGURATION)
            usb.util.claim_interface(self._dev, INTERFACE)
        except usb.core.USBError as exc:
            hint = " (is another program using it?)" if exc.errno == errno.EBUSY else ""
            raise self._usb_failure(f"claiming interface {INTERFACE}{hint}", exc) from exc
        self._action(Action.CLEAR)
        self._action(0)  # data taking stopped, whatever a previous user left running
        self._drain()
        stale = VmeList()
        for reg in ISV_REGISTERS:  # no stale ISV entry may name a stack we never loaded
            stale.write_register(reg, 0)
        setup = self._load_irq_mask(IRQ_MASK_ALL, stale)
        setup.write_register(InternalReg.EVENTS_PER_BUFFER, EVENTS_PER_BUFFER)
        setup.write_register(InternalReg.USB_BULK_SETUP, BULK_SETUP)
        every_entry = int.from_bytes(bytes([VECTOR_HIGH_8BIT]) * 4, "little")
        setup.write_register(InternalReg.VECTOR_HIGH1, every_entry)
        setup.write_register(InternalReg.VECTOR_HIGH2, every_entry)
        setup.read_register(InternalReg.FIRMWARE_ID)
        shown, fid = self._run(setup)
        assert isinstance(shown, int) and isinstance(fid, int)
        self._irq_mask_taken(IRQ_MASK_ALL, shown)
        self.firmware_id = fid
        log.info("VM-USB %s: firmware 0x%08X", self.serial, fid)

    def _load_irq_mask(self, mask: int, before: VmeList | None = None) -> VmeList:
        """Load IRQ ``mask`` into the bridge (lock held, data taking stopped): GLOBAL_MODE with
        IRQ_MASK_LOAD (after the register writes of ``before``, in the same list), a USB
        trigger; the returned list, which the caller runs (and may extend), reads FIRMWARE_ID
        first (the mask shows in its bits 24-30) and puts GLOBAL_MODE back to 0 and then to
        :data:`DRIVER_GLOBAL_MODE` (NSCLDAQ's and mvme's sequence)."""
        load = VmeList() if before is None else before
        load.write_register(InternalReg.GLOBAL_MODE, IRQ_MASK_LOAD | mask)
        self._run(load)
        self._action(Action.USB_TRIGGER)
        back = VmeList()
        back.read_register(InternalReg.FIRMWARE_ID)
        back.write_register(InternalReg.GLOBAL_MODE, 0)
        back.write_register(InternalReg.GLOBAL_MODE, DRIVER_GLOBAL_MODE)
        return back

    def _irq_mask_taken(self, mask: int, shown: int) -> None:
        """Note the mask the bridge now holds; warn when FIRMWARE_ID did not show it (mvme takes
        that as an error, NSCLDAQ does not look; which firmware shows it is not documented)."""
        self._irq_mask = mask
        if (shown >> FID_IRQ_MASK_SHIFT) & IRQ_MASK_ALL != mask:
            log.warning(
                "VM-USB %s: IRQ mask 0x%02X loaded, but FIRMWARE_ID read 0x%08X during the load",
                self.serial,
                mask,
                shown,
            )

    def _set_irq_mask(self, mask: int) -> None:
        """Make the bridge ignore exactly the levels of ``mask`` (lock held, data taking
        stopped); nothing to do when it already does."""
        if mask == self._irq_mask:
            return
        (shown,) = self._run(self._load_irq_mask(mask))
        assert isinstance(shown, int)
        self._irq_mask_taken(mask, shown)

    def _wanted_irq_mask(self, *extra_levels: int) -> int:
        """Every level ignored but those of the armed IRQs (and ``extra_levels``), as mvme's
        ``removeIrqMask`` does per IRQ stack."""
        with self._cond:
            levels = {sub.level for sub in self._subs.values()} | set(extra_levels)
        mask = IRQ_MASK_ALL
        for level in levels:
            mask &= ~irq_mask_bit(level)
        return mask

    def _drain(self) -> None:
        timeout_ms = max(1, round(self.drain_timeout_s * 1000))
        for _ in range(DRAIN_LIMIT):
            try:
                data = self._dev.read(EP_IN, READ_SIZE, timeout_ms)
            except usb.core.USBTimeoutError:
                return
            except usb.core.USBError as exc:
                raise self._usb_failure("draining the IN endpoint", exc) from exc
            self.stats.transfers_in += 1
            log.debug("VM-USB %s: drained %d stale byte(s)", self.serial, len(data))
        raise BusError(f"VM-USB {self.serial} keeps sending data; it cannot be made idle")

    # -- immediate lists -------------------------------------------------------------------------
    def execute(self, lst: VmeList) -> list[int | bytes]:
        """Run ``lst`` now and return its values (see :meth:`VmeList.decode`).

        With IRQs armed, data taking is stopped around the list (the bridge runs no list while
        it takes data) and started again after it, also when the list fails.
        """
        if not len(lst):
            return []
        with self._io:
            self._check_alive()
            restart = self._stop_daq()
            if self._hold:  # a transaction: started again when it ends
                self._owed_start = self._owed_start or restart
                return self._run(lst)
            try:
                values = self._run(lst)
            except BusError:
                if restart and self._dead is None:
                    try:
                        self._start_daq()
                    except BusError:
                        log.exception("VM-USB %s: restarting data taking", self.serial)
                raise
            if restart:
                self._start_daq()
            return values

    @contextlib.contextmanager
    def held(self) -> Iterator[None]:
        """Keep data taking stopped across the lists run inside (one stop and one start for
        all of them, instead of one pair each), and other threads' lists out: the caller's
        accesses belong together. IRQs that come meanwhile stay pending in the bridge and are
        serviced when data taking starts again, at the end. Nests."""
        with self._io:
            self._hold += 1
            try:
                yield
            finally:
                self._hold -= 1
                if not self._hold and self._owed_start:
                    self._owed_start = False
                    if self._dead is None:
                        self._start_daq()

    def _run(self, lst: VmeList) -> list[int | bytes]:
        """Run ``lst`` segment by segment; data taking is stopped and the lock held."""
        payload = bytearray()
        for lines in lst.segments():
            words = lst.words(lines)
            packet = _LIST_HEADER.pack(TA_IMMEDIATE_LIST, 2 * len(words) + 1)
            packet += struct.pack(f"<{len(words)}I", *words)
            if self._resync:  # an answer we gave up on may still arrive: not as this one's
                self._drain()
                self._resync = False
            self._send(packet, "sending a list")
            self.stats.lists += 1
            expected = lst.answer_size(lines)
            asked = -(-expected // MAX_PACKET) * MAX_PACKET
            try:
                answer = self._receive(asked, "reading a list's answer")
            except BusError as exc:
                if exc.errno == errno.ETIMEDOUT:
                    self._resync = True
                raise
            payload += lst.payload(answer, lines)
        return lst.values(bytes(payload))

    # -- interrupts ------------------------------------------------------------------------------
    def arm_irq(
        self,
        level: int,
        vector: int,
        reads: VmeList,
        *,
        on_close: Callable[[BusError], None] | None = None,
    ) -> IrqSubscription:
        """Run ``reads`` whenever VME IRQ ``level`` answers its IACK with ``vector``.

        Loads the stack, writes its ISV entry and (re)starts data taking; the events land in
        the returned subscription. ``on_close`` is called (from the reader thread) if the device
        goes away while the IRQ is armed. :meth:`IrqSubscription.disarm` undoes it all.
        """
        if not (1 <= level <= 7 and 0 <= vector <= 0xFF):
            raise ValueError(f"VME IRQ level {level} / vector {vector} out of range (1-7, 0-255)")
        words = reads.words()
        if len(words) > IRQ_STACK_WORDS:
            raise BusError(
                f"an IRQ stack of {len(words)} words does not fit in {IRQ_STACK_WORDS}",
                errno.EINVAL,
            )
        self._retain()  # the subscription's reference, given back when it ends
        retained = True
        try:
            with self._io:
                self._check_alive()
                with self._cond:
                    taken = self._subs.values()
                    if any(s.level == level and s.vector == vector for s in taken):
                        raise BusError(
                            f"VM-USB {self.serial}: IRQ {level} vector 0x{vector:02X} is armed",
                            errno.EBUSY,
                        )
                    free = [i for i in IRQ_STACK_IDS if i not in self._subs]
                if not free:
                    raise BusError(
                        f"VM-USB {self.serial}: all {len(IRQ_STACK_IDS)} IRQ stacks are in use",
                        errno.EBUSY,
                    )
                stack_id = free[0]
                restart = self._stop_daq()
                sub = IrqSubscription(self, level, vector, stack_id, reads, on_close)
                try:
                    self._set_irq_mask(self._wanted_irq_mask(level))  # before the ISV entry
                    self._load_stack(stack_id, words)
                    self._set_isv(
                        stack_id - IRQ_STACK_IDS.start, isv_entry(vector, level, stack_id)
                    )
                    with self._cond:
                        self._subs[stack_id] = sub
                    self._start_daq()
                except BaseException:
                    with self._cond:
                        self._subs.pop(stack_id, None)
                    with sub._lock:
                        retained = sub._armed
                        sub._armed = False
                    sub.disarm()  # closes the mailbox only
                    if restart and self._dead is None and self._subs:
                        try:
                            self._start_daq()
                        except BusError:
                            log.exception("VM-USB %s: restarting data taking", self.serial)
                    raise
        except BaseException:
            if retained:
                self.release()
            raise
        return sub

    def _disarm(self, sub: IrqSubscription) -> None:
        try:
            with self._io:
                with self._cond:
                    if self._subs.get(sub.stack_id) is not sub:
                        return
                    if self._dead is not None:  # nothing to clear on a device that has gone
                        del self._subs[sub.stack_id]
                        return
                self._stop_daq()
                with self._cond:
                    del self._subs[sub.stack_id]
                try:
                    self._set_isv(sub.stack_id - IRQ_STACK_IDS.start, 0)
                    self._set_irq_mask(self._wanted_irq_mask())
                finally:
                    if self._subs and self._dead is None:
                        self._start_daq()
        finally:
            self.release()

    def _load_stack(self, stack_id: int, words: list[int]) -> None:
        offset = (stack_id - IRQ_STACK_IDS.start) * IRQ_STACK_WORDS
        packet = _SHORTS3.pack(ta_load(stack_id), 2 * len(words) + 1, offset)
        packet += struct.pack(f"<{len(words)}I", *words)
        self._send(packet, f"loading stack {stack_id}")

    def _set_isv(self, index: int, entry: int) -> None:
        self._isv[index] = entry
        pair = index & ~1
        lst = VmeList()
        lst.write_register(ISV_REGISTERS[index // 2], self._isv[pair] | self._isv[pair + 1] << 16)
        self._run(lst)

    # -- data taking -----------------------------------------------------------------------------
    def _stop_daq(self) -> bool:
        """Stop data taking if it runs, once the reader has had the last buffer; the lock is
        held. True if it was running (the caller starts it again)."""
        if not self._daq:
            return False
        self._daq = False
        try:
            self._action(0)
        except BusError as exc:
            self._fail(exc)  # whether the bridge still takes data is unknown: no list is safe
            raise
        self.stats.daq_stops += 1
        with self._cond:
            done = self._cond.wait_for(
                lambda: not self._reading or self._dead is not None, self.timeout_s
            )
        self._check_alive()
        if not done:
            error = BusError(
                f"VM-USB {self.serial} sent no last buffer within {self.timeout_s:g} s of the "
                "end of data taking",
                errno.ETIMEDOUT,
            )
            self._fail(error)
            raise error
        return True

    def _start_daq(self) -> None:
        """Start data taking (and the reader) for the armed IRQs; the lock is held."""
        with self._cond:
            if not self._subs:
                return
            self._reading = True
            self._cond.notify_all()
        if self._reader is None:
            self._reader = threading.Thread(
                target=self._read_buffers,
                args=(self._generation, self._dev),
                name=f"vmusb-{self.serial}",
                daemon=True,
            )
            self._reader.start()
        try:
            self._action(Action.START_DAQ)
        except BusError as exc:
            self._fail(exc)  # whether the bridge took data is unknown: no list is safe
            raise
        self._daq = True
        self.stats.daq_starts += 1

    def _read_buffers(self, generation: int, device: Any) -> None:
        """The reader thread of ``device``: reads buffers while data taking runs, parks between
        runs; ends when the bridge is released or loses the device (a re-linked bridge starts
        a reader of its own for the device it found)."""
        timeout_ms = max(1, round(READER_POLL_S * 1000))

        def over() -> bool:
            return self._quit or self._dead is not None or self._generation != generation

        while True:
            with self._cond:
                while not self._reading and not over():
                    self._cond.wait()
                if over():
                    return
            try:
                data = device.read(EP_IN, READ_SIZE, timeout_ms)
            except usb.core.USBTimeoutError:
                continue
            except usb.core.USBError as exc:
                if self._generation == generation:
                    self._fail(self._usb_failure("reading a data buffer", exc, fatal=True))
                return
            except Exception as exc:
                if self._generation == generation:
                    self._fail(BusError(f"VM-USB {self.serial}: reading a data buffer: {exc!r}"))
                return
            self.stats.transfers_in += 1
            try:
                last = self._take_buffers(bytes(data))
            except BusError as exc:
                self._fail(exc)
                return
            if last:
                with self._cond:
                    self._reading = False
                    self._cond.notify_all()

    def _take_buffers(self, data: bytes) -> bool:
        """Parse complete buffers out of what has arrived; True if the last one was among them."""
        self._inbuf += data
        last = False
        while True:
            _skip_terminators(self._inbuf)  # a buffer's second one, if it came on its own
            parsed = _parse_buffer(self._inbuf, self.serial)
            if parsed is None:
                return last
            used, header, events = parsed
            del self._inbuf[:used]
            self.stats.buffers += 1
            for stack_id, payload in events:
                self._deliver(stack_id, payload)
            if header & BUF_LAST:
                if self._inbuf:
                    extra = len(self._inbuf)
                    log.warning("VM-USB %s: %d byte(s) after the last buffer", self.serial, extra)
                    self._inbuf.clear()
                return True

    def _deliver(self, stack_id: int, payload: bytes) -> None:
        with self._cond:
            sub = self._subs.get(stack_id)
        if sub is None:
            self.stats.stray_events += 1
            log.warning("VM-USB %s: event of stack %d, which no IRQ owns", self.serial, stack_id)
            return
        self.stats.events += 1
        values: tuple[int, ...] | None = None
        if len(payload) == sub.reads.answer_bytes():
            values = tuple(int(v) for v in sub.reads.values(payload) if isinstance(v, int))
        else:
            log.warning(
                "VM-USB %s: IRQ %d event of %d byte(s), its stack reads %d",
                self.serial,
                sub.level,
                len(payload),
                sub.reads.answer_bytes(),
            )
        sub._post(values)

    # -- the wire --------------------------------------------------------------------------------
    def _action(self, value: int) -> None:
        self._send(_SHORTS3.pack(REGISTER_BLOCK, ACTION_REGISTER, int(value)), "writing the action")

    def _send(self, packet: bytes, doing: str) -> None:
        try:
            sent = self._dev.write(EP_OUT, packet, self._timeout_ms)
        except usb.core.USBError as exc:
            raise self._usb_failure(doing, exc) from exc
        self.stats.transfers_out += 1
        if sent != len(packet):
            raise BusError(f"VM-USB {self.serial}: {doing}: sent {sent} of {len(packet)} bytes")

    def _receive(self, size: int, doing: str) -> bytes:
        try:
            data = self._dev.read(EP_IN, size, self._timeout_ms)
        except usb.core.USBError as exc:
            raise self._usb_failure(doing, exc) from exc
        self.stats.transfers_in += 1
        return bytes(data)

    def _usb_failure(self, doing: str, exc: usb.core.USBError, fatal: bool = False) -> BusError:
        """The BusError for a pyusb error; a vanished device also kills the bridge."""
        if isinstance(exc, usb.core.USBTimeoutError):
            error = BusError(
                f"VM-USB {self.serial}: {doing}: no answer within {self.timeout_s:g} s",
                errno.ETIMEDOUT,
            )
            if fatal:
                self._fail(error)
            return error
        err = exc.errno or errno.EIO
        if err in _VANISHED or fatal:
            error = BusError(
                f"VM-USB {self.serial} is gone ({doing}: {exc.strerror or exc}); check its "
                "cable and the crate's power: once it is back, a reset finds it again by its "
                "serial number",
                err,
            )
            self._fail(error)
            return error
        return BusError(f"VM-USB {self.serial}: {doing}: {exc.strerror or exc}", err)

    def _check_alive(self) -> None:
        dead = self._dead
        if dead is not None:
            raise BusError(str(dead), dead.errno or errno.ENODEV)

    @property
    def alive(self) -> bool:
        """False once the device has gone (every access then raises) or the bridge was
        released; True again after a successful :meth:`relink`."""
        return self._dead is None

    @property
    def lost(self) -> bool:
        """The device has gone while the bridge is still in use: :meth:`relink` may find it."""
        return self._dead is not None and not self._released

    # -- lost and found --------------------------------------------------------------------------
    def relink(self) -> None:
        """Find the device again after it was lost, and carry on with it; at once if alive.

        Looks for this serial number on the same backend; once found, brings the device up as
        the first open did (claim, stop whatever runs, drain, clear the ISV registers) and
        re-arms every suspended IRQ: its stack loaded again, its ISV entry written, data taking
        started. The windows and lines of this bridge then work as before the loss.

        Raises:
            BusError: ``ENODEV`` when the device is still gone (the message says what to
                check), ``EBUSY`` when another bridge of this process has opened it meanwhile,
                or the bring-up's own error; the bridge stays lost and may be re-linked later.
                ``EBADF`` for a bridge that was released.
        """
        with _TABLE_LOCK, self._io:  # the table's lock first, as acquire() and release() take it
            if self._released:
                raise BusError(f"VM-USB {self.serial} was released", errno.EBADF)
            if self._dead is None:
                return
            self._retire_device()
            try:
                device, _ = _find(self.serial, self.backend)
            except BusError as exc:
                raise BusError(
                    f"VM-USB {self.serial} is still gone: {exc}; once it is back, reset again",
                    exc.errno or errno.ENODEV,
                ) from None
            other = _TABLE.get(self._key)
            if other is not None and other is not self and other._dead is None:
                usb.util.dispose_resources(device)
                raise BusError(
                    f"VM-USB {self.serial} is open again through another bridge of this "
                    "process; close what opened it, or start a new driver process",
                    errno.EBUSY,
                )
            _TABLE[self._key] = self
            self._bring_up_again(device)
        log.warning("VM-USB %s: found again; %d IRQ(s) re-armed", self.serial, len(self._subs))

    def _retire_device(self) -> None:
        """Let go of the lost device: its reader thread ends (the generation moves on), and
        its resources are freed."""
        with self._cond:
            self._generation += 1
            self._reading = False
            self._cond.notify_all()
        reader, self._reader = self._reader, None
        if reader is not None and reader is not threading.current_thread():
            reader.join(READER_POLL_S + self.timeout_s)
        self._free_device()

    def _bring_up_again(self, device: Any) -> None:
        """The lost bridge on ``device``: bring-up, stacks and ISV entries of every suspended
        IRQ, then data taking (the lock and the table's are held)."""
        self._dev = device
        self._daq = False
        self._owed_start = False
        self._resync = False
        self._inbuf.clear()
        self._isv = [0] * 8
        lost = self._dead
        self._dead = None
        try:
            self._bring_up()
            with self._cond:
                subs = list(self._subs.values())
            self._set_irq_mask(self._wanted_irq_mask())  # before the ISV entries
            for sub in subs:
                self._load_stack(sub.stack_id, sub.reads.words())
                index = sub.stack_id - IRQ_STACK_IDS.start
                self._set_isv(index, isv_entry(sub.vector, sub.level, sub.stack_id))
            for sub in subs:  # before data taking: no event of the new device is drained
                sub._restored()
            self._start_daq()
        except BusError as exc:
            self._fail(exc)  # the subscriptions are suspended again
            self._free_device()
            raise BusError(
                f"VM-USB {self.serial} was found again but could not be brought up ({exc}); "
                f"it was lost with: {lost}",
                exc.errno or errno.EIO,
            ) from exc
        self.relinks += 1

    @property
    def daq_running(self) -> bool:
        """Whether data taking runs (some IRQ is armed and no list is in progress)."""
        return self._daq

    # -- endings ---------------------------------------------------------------------------------
    def _fail(self, error: BusError) -> None:
        """The device is gone or out of step: refuse every access and suspend every armed IRQ
        (their lines' waiters get the error) until :meth:`relink`."""
        with self._cond:
            if self._dead is not None:
                return
            self._dead = error
            self._reading = False
            subs = list(self._subs.values())
            self._cond.notify_all()
        log.error("%s", error)
        for sub in subs:
            sub._lost(error)

    def _shutdown(self) -> None:
        # Bounded: a thread still in an exchange (a window closed under another thread's access)
        # may be failing, and wanting the table lock this caller holds; then free it regardless.
        locked = self._io.acquire(timeout=self.timeout_s + READER_POLL_S)
        try:
            if self._dead is None and locked:
                try:
                    self._stop_daq()
                except BusError:
                    log.exception("VM-USB %s: stopping data taking", self.serial)
            with self._cond:
                self._quit = True
                self._cond.notify_all()
            reader = self._reader
            if reader is not None and reader is not threading.current_thread():
                reader.join(READER_POLL_S + self.timeout_s)
            self._released = True
            if self._dead is None:
                self._dead = BusError(f"VM-USB {self.serial} was released", errno.EBADF)
            self._free_device()
        finally:
            if locked:
                self._io.release()

    def _free_device(self) -> None:
        try:
            usb.util.release_interface(self._dev, INTERFACE)
        except (usb.core.USBError, ValueError, NotImplementedError):
            pass  # a device that has gone cannot be told
        try:
            usb.util.dispose_resources(self._dev)
        except (usb.core.USBError, NotImplementedError):
            pass

    def __repr__(self) -> str:
        state = "alive" if self._dead is None else "released" if self._released else "lost"
        return f"<VmUsbBridge {self.serial} {state} refs={self._refs}>"


_TERMINATOR_BYTES = _U16.pack(BUF_TERMINATOR)


def _skip_terminators(buf: bytearray) -> None:
    """Drop buffer terminators at the start of ``buf``: no buffer header is 0xFFFF."""
    while buf[:2] == _TERMINATOR_BYTES:
        del buf[:2]


def _parse_buffer(buf: bytearray, serial: str) -> tuple[int, int, list[tuple[int, bytes]]] | None:
    """(bytes used, header, [(stack id, event data)]) of the first buffer, or None if it has not
    all arrived. Continuation segments are joined to the event they continue; the buffer ends
    with one terminator or two (the second, when it has arrived, is used up too)."""
    if len(buf) < 2:
        return None
    (header,) = _U16.unpack_from(buf, 0)
    pos = 2
    events: list[tuple[int, bytes]] = []
    pending = b""
    for _ in range(header & BUF_EVENT_COUNT):
        if len(buf) < pos + 2:
            return None
        (event,) = _U16.unpack_from(buf, pos)
        n = 2 * (event & EVENT_LENGTH)
        if len(buf) < pos + 2 + n:
            return None
        pending += bytes(buf[pos + 2 : pos + 2 + n])
        pos += 2 + n
        if not event & EVENT_CONTINUATION:
            events.append((event >> EVENT_STACK_SHIFT & 7, pending))
            pending = b""
    if len(buf) < pos + 2:
        return None
    (end,) = _U16.unpack_from(buf, pos)
    if end != BUF_TERMINATOR or pending:
        raise BusError(
            f"VM-USB {serial}: malformed data buffer (header 0x{header:04X}, ends 0x{end:04X})",
            errno.EPROTO,
        )
    pos += 2
    if buf[pos : pos + 2] == _TERMINATOR_BYTES:
        pos += 2
    return pos, header, events


def _find(serial: str | None, backend: Any) -> tuple[Any, str]:
    """The device of ``serial`` (or the only VM-USB) and its serial number."""
    try:
        found = list(usb.core.find(find_all=True, idVendor=VID, idProduct=PID, backend=backend))
    except usb.core.NoBackendError as exc:
        raise BusError(
            "pyusb finds no USB backend: install libusb-1.0 to reach a VM-USB", errno.ENODEV
        ) from exc
    except usb.core.USBError as exc:
        raise BusError(f"listing USB devices: {exc}", exc.errno or errno.EIO) from exc
    if not found:
        raise BusError(
            f"no VM-USB (USB {VID:04x}:{PID:04x}) found: check its USB cable, that the VME "
            "crate is powered, and that a udev rule gives you access to the device",
            errno.ENODEV,
        )
    if serial is None and len(found) == 1:
        return found[0], _serial_of(found[0])
    serials = [_serial_of(device) for device in found]
    chosen = None
    for device, number in zip(found, serials, strict=True):
        if serial is not None and number == serial and chosen is None:
            chosen = device
        else:
            usb.util.dispose_resources(device)
    listed = ", ".join(serials)
    if serial is None:
        raise BusError(
            f"{len(found)} VM-USBs are connected ({listed}): say which one with serial=",
            errno.EINVAL,
        )
    if chosen is None:
        raise BusError(f"no VM-USB with serial {serial} (connected: {listed})", errno.ENODEV)
    return chosen, serial


def _serial_of(device: Any) -> str:
    try:
        number = device.serial_number
    except (usb.core.USBError, ValueError, NotImplementedError) as exc:
        # pyusb raises ValueError when it may not read string descriptors (no access rights)
        raise BusError(
            f"reading the serial number of the VM-USB at bus {device.bus} address "
            f"{device.address}: {exc} (does a udev rule give you access?)",
            errno.EACCES,
        ) from exc
    return str(number)


# -- the window ------------------------------------------------------------------------------------


class VmUsbWindow(BusWindow):
    """VME addresses ``base .. base+size-1`` with modifier ``am``, reached through a VM-USB.

    Every access is one list, so one USB round trip: width accessors are one single cycle;
    :meth:`read` is D32 block transfers (single cycles for an unaligned head or tail, and D16
    single cycles in A16 space, which has no block transfer); :meth:`write` is D32 (A16: D16)
    single cycles with D16/D8 at the ends. Values are big-endian, as the 68k sees the bus.
    ``serial`` picks the bridge (None: the only one connected); ``backend`` is a pyusb backend.
    The window is not memory-mapped: no views.
    """

    kind = "vmusb"

    def __init__(
        self,
        size: int,
        *,
        base: int,
        am: int = AddressModifier.A24_USER,
        serial: str | None = None,
        backend: Any = None,
        timeout_s: float = 2.0,
    ) -> None:
        super().__init__(size)
        mod = _modifier(am)
        if mod in BLT_OF.values():
            raise BusError(
                f"AM 0x{mod:02X} is a block-transfer modifier: give the data modifier (block "
                "reads use its BLT modifier)",
                errno.EINVAL,
            )
        bits = ADDRESS_BITS[mod]
        if base < 0 or base + size > 1 << bits:
            raise BusError(
                f"a window of 0x{size:X} bytes at 0x{base:X} does not fit in A{bits} space",
                errno.EINVAL,
            )
        self.base = base
        self.am = mod
        self._blt = BLT_OF.get(mod)
        self.bridge = VmUsbBridge.acquire(serial, backend, timeout_s)

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return (
            f"<VmUsbWindow {self.bridge.serial} {_space(self.am, self.base)} "
            f"size=0x{self._size:X} {state}>"
        )

    # -- width-explicit: one single cycle each ---------------------------------------------------
    def read8(self, offset: int) -> int:
        if self._closed or not 0 <= offset < self._size:
            self._check(offset, 1, 1)  # raises
        lst = VmeList()
        lst.read8(self.am, self.base + offset)
        return self._one(lst)

    def read16(self, offset: int) -> int:
        if self._closed or offset < 0 or offset + 2 > self._size or offset % 2:
            self._check(offset, 2, 2)  # raises
        lst = VmeList()
        lst.read16(self.am, self.base + offset)
        return self._one(lst)

    def read32(self, offset: int) -> int:
        if self._closed or offset < 0 or offset + 4 > self._size or offset % 4:
            self._check(offset, 4, 4)  # raises
        lst = VmeList()
        lst.read32(self.am, self.base + offset)
        return self._one(lst)

    def write8(self, offset: int, value: int) -> None:
        if self._closed or not 0 <= offset < self._size:
            self._check(offset, 1, 1)  # raises
        lst = VmeList()
        lst.write8(self.am, self.base + offset, _fit(value, 8))
        self.bridge.execute(lst)

    def write16(self, offset: int, value: int) -> None:
        if self._closed or offset < 0 or offset + 2 > self._size or offset % 2:
            self._check(offset, 2, 2)  # raises
        lst = VmeList()
        lst.write16(self.am, self.base + offset, _fit(value, 16))
        self.bridge.execute(lst)

    def write32(self, offset: int, value: int) -> None:
        if self._closed or offset < 0 or offset + 4 > self._size or offset % 4:
            self._check(offset, 4, 4)  # raises
        lst = VmeList()
        lst.write32(self.am, self.base + offset, _fit(value, 32))
        self.bridge.execute(lst)

    # -- batches -----------------------------------------------------------------------------------
    def transaction(self) -> contextlib.AbstractContextManager[None]:
        """The bridge's :meth:`VmUsbBridge.held`: one stop and start of data taking for every
        list inside, not one pair per list."""
        if self._closed:
            self._check(0, 0, 1)  # raises
        return self.bridge.held()

    def read_many(self, spans: Sequence[tuple[int, int]]) -> list[bytes]:
        """Every span read by one list (one USB round trip, however many spans)."""
        checked = list(spans)
        for offset, n in checked:
            self._check(offset, n, 1)
        lst = VmeList()
        bounds = []
        for offset, n in checked:
            start = len(lst.reads)
            self._add_span(lst, offset, n)
            bounds.append((start, len(lst.reads)))
        values = self.bridge.execute(lst)
        return [_join(values[a:b], lst.reads[a:b]) for a, b in bounds]

    def read_regs(self, items: Sequence[tuple[int, int]]) -> list[int]:
        """Single cycles of ``(offset, width_bits)``, in order, by one list: e.g. a latched
        24-bit position as three D8 reads, least significant byte first."""
        lst = VmeList()
        for offset, width in items:
            self.add_read(lst, offset, width)
        return [int(v) for v in self.bridge.execute(lst) if isinstance(v, int)]

    def add_read(self, lst: VmeList, offset: int, width_bits: int) -> None:
        """Append a checked single-cycle read of ``offset`` to ``lst`` (IRQ stacks use it)."""
        if width_bits not in _WIDTH_MASK:
            raise BusError(f"a register is 8, 16 or 32 bits wide, not {width_bits}", errno.EINVAL)
        nbytes = width_bits // 8
        self._check(offset, nbytes, nbytes)
        lst._single(self.am, self.base + offset, width_bits, None)

    # -- hooks -----------------------------------------------------------------------------------
    def _read(self, offset: int, n: int) -> bytes:
        if n == 0:
            return b""
        lst = VmeList()
        self._add_span(lst, offset, n)
        return _join(self.bridge.execute(lst), lst.reads)

    def _write(self, offset: int, data: bytes) -> None:
        lst = VmeList()
        am, address, end = self.am, self.base + offset, self.base + offset + len(data)
        i = 0
        if address & 1 and address < end:
            lst.write8(am, address, data[i])
            address, i = address + 1, i + 1
        if self._blt is not None:
            if address & 2 and end - address >= 2:
                lst.write16(am, address, int.from_bytes(data[i : i + 2], "big"))
                address, i = address + 2, i + 2
            while end - address >= 4:
                lst.write32(am, address, int.from_bytes(data[i : i + 4], "big"))
                address, i = address + 4, i + 4
        while end - address >= 2:
            lst.write16(am, address, int.from_bytes(data[i : i + 2], "big"))
            address, i = address + 2, i + 2
        if address < end:
            lst.write8(am, address, data[i])
        self.bridge.execute(lst)

    def _add_span(self, lst: VmeList, offset: int, n: int) -> None:
        """Lines reading ``n`` bytes at ``offset`` (checked): D8/D16 at unaligned ends, D32
        block transfers between (A16: D16 single cycles)."""
        am, address, end = self.am, self.base + offset, self.base + offset + n
        if address & 1 and address < end:
            lst.read8(am, address)
            address += 1
        if self._blt is not None:
            if address & 2 and end - address >= 2:
                lst.read16(am, address)
                address += 2
            words = (end - address) // 4
            if words:
                lst.block_read32(self._blt, address, words)
                address += 4 * words
        while end - address >= 2:
            lst.read16(am, address)
            address += 2
        if address < end:
            lst.read8(am, address)

    def _one(self, lst: VmeList) -> int:
        (value,) = self.bridge.execute(lst)
        assert isinstance(value, int)
        return value

    # -- lost and found --------------------------------------------------------------------------
    def relink(self) -> None:
        """The bridge's :meth:`VmUsbBridge.relink`: the VM-USB found again by its serial number
        once it is plugged back in; at once while it is there. Every window and line of the
        bridge works again after it."""
        super().relink()  # a closed window is not reopened
        self.bridge.relink()

    def _close(self) -> None:
        self.bridge.release()


def _join(values: Sequence[int | bytes], slots: Sequence[ReadSlot]) -> bytes:
    """The bytes of consecutive reads, in address order, big-endian."""
    return b"".join(
        v if isinstance(v, bytes) else v.to_bytes(s.width // 8, "big")
        for v, s in zip(values, slots, strict=True)
    )
