"""The bus-window contract: what every way of reaching BIRIS memory or a VME board offers.

A window is a byte-addressed span of a bus, seen from the host. Values are big-endian, as on the
68k side. Every public access checks range and alignment *before* touching anything, so a bad
access raises :class:`~biris_hw.errors.BusError` and changes nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import struct
import threading
from abc import ABC, abstractmethod
from collections.abc import Sequence
from types import TracebackType
from typing import Any, ClassVar, Generic, TypeVar

from biris_hw.errors import BusError

__all__ = ["BufferWindow", "BusWindow", "StructView"]

_Self = TypeVar("_Self", bound="BusWindow")

S = TypeVar("S", bound=ctypes.Structure)

_U8 = struct.Struct(">B")
_U16 = struct.Struct(">H")
_U32 = struct.Struct(">I")


class StructView(Generic[S]):
    """A ctypes structure laid over a window, owned by that window.

    Field reads and writes go straight to the window's memory (a read is a bus read). The view
    holds the only reference to the ctypes object, so when the window closes it can drop the
    object and release the mapping; any later use raises :class:`BusError` instead of touching a
    dead mapping.
    """

    __slots__ = ("_obj", "_owner")

    def __init__(self, obj: S, owner: BusWindow) -> None:
        object.__setattr__(self, "_obj", obj)
        object.__setattr__(self, "_owner", owner)

    def _live(self) -> S:
        obj: S | None = object.__getattribute__(self, "_obj")
        if obj is None:
            raise BusError("view used after its window was closed")
        return obj

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._live(), name)
        if isinstance(value, (ctypes.Array, ctypes.Structure)):
            # A nested ctypes object would share (and pin) the window's memory: hand out a copy.
            return type(value).from_buffer_copy(value)
        return value

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._live(), name, value)

    def snapshot(self) -> S:
        """A detached copy of the structure, safe to keep after the window closes."""
        obj = self._live()
        return type(obj).from_buffer_copy(bytes(obj))

    def _drop(self) -> None:
        object.__setattr__(self, "_obj", None)


class BusWindow(ABC):
    """One span of a bus, reached from the host.

    Subclasses implement :meth:`_read` and :meth:`_write` (already range-checked) and
    :meth:`_close`; buffer-backed windows derive from :class:`BufferWindow` instead, which gives
    fast width-explicit accessors and ctypes views.
    """

    kind: ClassVar[str] = "abstract"

    def __init__(self, size: int) -> None:
        if size <= 0:
            raise BusError(f"window size must be positive, not {size}")
        self._size = size
        self._closed = False
        self._close_lock = threading.Lock()

    # -- identity ----------------------------------------------------------------------------
    @property
    def size(self) -> int:
        """Bytes in the window; valid offsets are ``0 .. size-1``."""
        return self._size

    @property
    def closed(self) -> bool:
        return self._closed

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<{type(self).__name__} kind={self.kind} size=0x{self._size:X} {state}>"

    # -- checks --------------------------------------------------------------------------------
    def _check(self, offset: int, n: int, align: int) -> None:
        if self._closed:
            raise BusError(f"{self.kind} window is closed")
        if n < 0 or offset < 0 or offset + n > self._size:
            raise BusError(
                f"access of {n} byte(s) at 0x{offset:X} is outside the {self.kind} window "
                f"(size 0x{self._size:X})"
            )
        if align > 1 and offset % align:
            raise BusError(f"{align * 8}-bit access at 0x{offset:X} is misaligned")

    # -- bulk ------------------------------------------------------------------------------------
    def read(self, offset: int, n: int) -> bytes:
        """Copy ``n`` bytes out of the window."""
        self._check(offset, n, 1)
        return self._read(offset, n)

    def write(self, offset: int, data: bytes | bytearray | memoryview) -> None:
        """Copy ``data`` into the window."""
        raw = bytes(data)
        self._check(offset, len(raw), 1)
        self._write(offset, raw)

    def read_many(self, spans: Sequence[tuple[int, int]]) -> list[bytes]:
        """Several reads the caller needs together, as ``(offset, n)`` spans, in order.

        A window that can do them in one bus transaction does so (the VM-USB builds one list:
        one USB round trip instead of one per span); this default reads them one by one. Every
        span is checked before anything is read, so a bad one raises and reads nothing.
        """
        checked = list(spans)
        for offset, n in checked:
            self._check(offset, n, 1)
        return [self.read(offset, n) for offset, n in checked]

    # -- width-explicit registers (one access each) ----------------------------------------------
    def read8(self, offset: int) -> int:
        if self._closed or not 0 <= offset < self._size:
            self._check(offset, 1, 1)  # raises
        return self._read(offset, 1)[0]

    def read16(self, offset: int) -> int:
        if self._closed or offset < 0 or offset + 2 > self._size or offset % 2:
            self._check(offset, 2, 2)  # raises
        return int(_U16.unpack(self._read(offset, 2))[0])

    def read32(self, offset: int) -> int:
        self._check(offset, 4, 4)
        return int(_U32.unpack(self._read(offset, 4))[0])

    def write8(self, offset: int, value: int) -> None:
        if self._closed or not 0 <= offset < self._size:
            self._check(offset, 1, 1)  # raises
        self._write(offset, _pack(_U8, value, 8))

    def write16(self, offset: int, value: int) -> None:
        self._check(offset, 2, 2)
        self._write(offset, _pack(_U16, value, 16))

    def write32(self, offset: int, value: int) -> None:
        self._check(offset, 4, 4)
        self._write(offset, _pack(_U32, value, 32))

    def transaction(self) -> contextlib.AbstractContextManager[None]:
        """Several accesses the caller makes together (a move's start, one drain of the data
        path): a window whose every access has a fixed cost of its own pays it once for all of
        them (the VM-USB stops data taking once, not around each list). Nothing is batched or
        delayed: each access still happens when it is made. A no-op by default; nests."""
        return contextlib.nullcontext()

    # -- structures ------------------------------------------------------------------------------
    def view(self, struct_type: type[S], offset: int = 0) -> StructView[S]:
        """A live ctypes view of ``struct_type`` at ``offset``; only memory-mapped windows."""
        raise BusError(f"{self.kind} windows are not memory-mapped; use read/write instead")

    # -- lifecycle -------------------------------------------------------------------------------
    def relink(self) -> None:
        """Reopen what the window reaches its bus through, if that link was lost, so that the
        same window object works again (the server and its drivers hold it).

        A window whose link can be lost and come back overrides this: a ``vmusb`` window finds
        its VM-USB again by serial number once it is plugged back in. It returns at once when
        the link is alive and raises :class:`BusError` naming what is still missing when it
        cannot reopen it. A window over memory of this process has no link to lose: this default
        does nothing. A closed window is not reopened (it raises).
        """
        if self._closed:
            raise BusError(f"{self.kind} window is closed")

    def close(self) -> None:
        """Release the window and every view made of it. Calling it again does nothing."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
            self._close()

    def __enter__(self: _Self) -> _Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- implementation hooks --------------------------------------------------------------------
    @abstractmethod
    def _read(self, offset: int, n: int) -> bytes:
        """Read ``n`` bytes; the range has been checked."""

    @abstractmethod
    def _write(self, offset: int, data: bytes) -> None:
        """Write ``data``; the range has been checked."""

    @abstractmethod
    def _close(self) -> None:
        """Release the resources; called once."""


def _pack(fmt: struct.Struct, value: int, bits: int) -> bytes:
    """Accept both signed and unsigned spellings of a register value, refuse anything wider."""
    if not -(1 << (bits - 1)) <= value < (1 << bits):
        raise BusError(f"value {value} does not fit in {bits} bits")
    return fmt.pack(value & ((1 << bits) - 1))


class BufferWindow(BusWindow):
    """A window over a writable buffer in this process (bytearray, mmap, shared memory).

    Accesses use ``struct`` directly on the buffer, so a 16-bit read is one 16-bit load, and
    ctypes views are laid over the same memory. Subclasses pass the buffer to ``__init__`` and
    release their own resources in :meth:`_release`, which runs after every view is dropped.
    """

    def __init__(self, buffer: Any, size: int) -> None:
        super().__init__(size)
        self._buf: Any = buffer
        self._views: list[StructView[Any]] = []

    def _read(self, offset: int, n: int) -> bytes:
        return bytes(self._buf[offset : offset + n])

    def _write(self, offset: int, data: bytes) -> None:
        self._buf[offset : offset + len(data)] = data

    # Fast paths: the same checks written out (the common, valid access costs one comparison
    # chain; anything doubtful goes through _check, which raises the precise BusError), and no
    # intermediate bytes objects.
    def read(self, offset: int, n: int) -> bytes:
        if self._closed or n < 0 or offset < 0 or offset + n > self._size:
            self._check(offset, n, 1)  # raises
        return self._read(offset, n)

    def read8(self, offset: int) -> int:
        if self._closed or not 0 <= offset < self._size:
            self._check(offset, 1, 1)  # raises
        return int(self._buf[offset])

    def read16(self, offset: int) -> int:
        if self._closed or offset < 0 or offset + 2 > self._size or offset % 2:
            self._check(offset, 2, 2)  # raises
        return int(_U16.unpack_from(self._buf, offset)[0])

    def read32(self, offset: int) -> int:
        if self._closed or offset < 0 or offset + 4 > self._size or offset % 4:
            self._check(offset, 4, 4)  # raises
        return int(_U32.unpack_from(self._buf, offset)[0])

    def write(self, offset: int, data: bytes | bytearray | memoryview) -> None:
        raw = bytes(data)
        n = len(raw)
        if self._closed or offset < 0 or offset + n > self._size:
            self._check(offset, n, 1)  # raises
        self._write(offset, raw)

    def write8(self, offset: int, value: int) -> None:
        if self._closed or not 0 <= offset < self._size:
            self._check(offset, 1, 1)  # raises
        if not -0x80 <= value <= 0xFF:
            raise BusError(f"value {value} does not fit in 8 bits")
        self._buf[offset] = value & 0xFF

    def write16(self, offset: int, value: int) -> None:
        if self._closed or offset < 0 or offset + 2 > self._size or offset % 2:
            self._check(offset, 2, 2)  # raises
        if not -0x8000 <= value <= 0xFFFF:
            raise BusError(f"value {value} does not fit in 16 bits")
        _U16.pack_into(self._buf, offset, value & 0xFFFF)

    def write32(self, offset: int, value: int) -> None:
        if self._closed or offset < 0 or offset + 4 > self._size or offset % 4:
            self._check(offset, 4, 4)  # raises
        if not -0x8000_0000 <= value <= 0xFFFF_FFFF:
            raise BusError(f"value {value} does not fit in 32 bits")
        _U32.pack_into(self._buf, offset, value & 0xFFFF_FFFF)

    def view(self, struct_type: type[S], offset: int = 0) -> StructView[S]:
        self._check(offset, ctypes.sizeof(struct_type), 2)
        view = StructView(struct_type.from_buffer(self._buf, offset), self)
        self._views.append(view)
        return view

    def _close(self) -> None:
        for view in self._views:
            view._drop()
        self._views.clear()
        self._buf = None
        self._release()

    @abstractmethod
    def _release(self) -> None:
        """Unmap or free the buffer; every view has been dropped already."""
