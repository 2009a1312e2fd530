"""The ``remote`` window: registers of a simulator in another process, one socket round trip per
access; plus the wire protocol both sides of that socket speak.

Shared memory carries BIRIS memory between processes, but it cannot carry register *semantics*:
reading the HCTL-1000's R14H latches R13H/R12H, writing R0EH commits a position, the coupler's
status clears on a write of 1. Those boards are therefore reached by asking the simulator to do
each access on its device models, so every side effect happens exactly once, in order, where the
model lives. The driver accesses these boards a byte at a time and rarely, so a round trip
(tens of microseconds on a Unix socket) per access is affordable.

The socket is ``SOCK_SEQPACKET``: one packet is one message, so neither side frames anything.

* On connect the simulator sends a :class:`Handshake` (JSON) with the level-2 and level-3
  eventfds attached (``SCM_RIGHTS``), or ``{"protocol": ..., "error": "..."}`` and closes when it
  refuses the connection (one driver at a time).
* Then the driver sends requests, each answered by one response:
  request  ``>IBBHI``: seq u32, op u8 (1 read, 2 write), region u8 (1 motion, 2 coupler),
  length u16, offset u32; a write carries its ``length`` data bytes after the header.
  response ``>IBH``: seq u32, status u8 (:class:`Status`), length u16, then ``length`` bytes:
  the data read, or a UTF-8 message when status is not OK.

:class:`SliceWindow` (kind ``slice``) lives here too: the driver's BIRIS window is the BIRIS
region of the simulator's shared-memory image, a window onto part of another window.
"""

from __future__ import annotations

import ctypes
import enum
import errno
import json
import socket
import struct
import threading
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

from biris_hw.bus.base import BusWindow, S, StructView
from biris_hw.errors import BusError

__all__ = [
    "LINE_NAMES",
    "MAX_PACKET",
    "MAX_TRANSFER",
    "PROTOCOL",
    "REQUEST",
    "RESPONSE",
    "Handshake",
    "Op",
    "Region",
    "RemoteLink",
    "RemoteWindow",
    "SliceWindow",
    "Status",
    "default_socket_path",
    "refusal",
    "serve_request",
]

PROTOCOL = "biris-sim/1"
"""Names this wire format; a peer speaking anything else is refused, not misread."""

REQUEST = struct.Struct(">IBBHI")
"""seq, op, region, length, offset; write data follows."""

RESPONSE = struct.Struct(">IBH")
"""seq, status, length; data (or an error message) follows."""

MAX_TRANSFER = 4096
"""Bytes one request may move; longer accesses are split (the boards are far smaller)."""

MAX_PACKET = 65536
"""Receive buffer for one packet: the handshake, or a header plus ``MAX_TRANSFER`` bytes."""

LINE_NAMES = ("level2", "level3")
"""The interrupt lines the handshake passes, in the order of its descriptors."""


class Op(enum.IntEnum):
    READ = 1
    WRITE = 2


class Region(enum.IntEnum):
    """The register areas served over the socket (BIRIS memory is shared memory instead)."""

    MOTION = 1
    COUPLER = 2


class Status(enum.IntEnum):
    OK = 0
    BUS_ERROR = 1
    """The device refused the access (out of range, bad value): nothing was done."""
    BAD_REQUEST = 2
    """The request was malformed: a peer speaking another protocol."""
    NO_REGION = 3


_STATUS_ERRNO: dict[int, int] = {
    Status.BUS_ERROR: errno.EIO,
    Status.BAD_REQUEST: errno.EPROTO,
    Status.NO_REGION: errno.ENXIO,
}


def default_socket_path(name: str) -> str:
    """Where ``biris sim --shm NAME`` listens unless told otherwise."""
    return f"/tmp/biris-{name.lstrip('/')}.sock"


# -- the handshake ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Handshake:
    """What a driver must know to reach the simulator as it would a target.

    ``t0`` is the ``time.monotonic()`` (CLOCK_MONOTONIC, system-wide on Linux) at which hardware
    time was 0, so ``(monotonic() - t0) * time_scale`` is the simulator's own clock. The memory
    map fields and the image layout let the driver place BIRIS memory in the segment and check
    that both sides agree on register sizes.
    """

    shm: str
    pid: int
    time_scale: float
    t0: float
    samples: int
    biris_base: int
    biexec_offset: int
    range_offset: int
    max_acquisitions: int
    image_size: int
    coupler_offset: int
    coupler_size: int
    motion_offset: int
    motion_size: int
    biris_offset: int
    biris_size: int
    lines: tuple[str, ...] = LINE_NAMES
    clock: str = "CLOCK_MONOTONIC"
    protocol: str = PROTOCOL

    def encode(self) -> bytes:
        return json.dumps(asdict(self), separators=(",", ":")).encode()

    @classmethod
    def decode(cls, raw: bytes) -> Handshake:
        """Parse a handshake; a refusal or anything malformed raises :class:`BusError`."""
        try:
            data = json.loads(raw.decode())
        except (UnicodeDecodeError, ValueError):
            raise BusError("handshake mismatch: the peer did not send JSON", errno.EPROTO) from None
        if not isinstance(data, dict):
            raise BusError("handshake mismatch: not a JSON object", errno.EPROTO)
        if data.get("protocol") != PROTOCOL:
            raise BusError(
                f"handshake mismatch: the peer speaks {data.get('protocol')!r}, not {PROTOCOL!r}",
                errno.EPROTO,
            )
        if "error" in data:
            raise BusError(f"refused: {data['error']}", errno.EBUSY)
        values: dict[str, Any] = {}
        for f in fields(cls):
            if f.name not in data:
                raise BusError(f"handshake mismatch: no {f.name!r}", errno.EPROTO)
            value = data[f.name]
            if f.name == "lines":
                ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
                value = tuple(value) if ok else value
            elif f.type in ("int", int):
                ok = isinstance(value, int) and not isinstance(value, bool)
            elif f.type in ("float", float):
                ok = isinstance(value, (int, float)) and not isinstance(value, bool)
                value = float(value) if ok else value
            else:
                ok = isinstance(value, str)
            if not ok:
                raise BusError(
                    f"handshake mismatch: {f.name!r} has the wrong type ({value!r})", errno.EPROTO
                )
            values[f.name] = value
        return cls(**values)


def refusal(message: str) -> bytes:
    """The packet a simulator sends instead of a handshake when it turns a driver away."""
    return json.dumps({"protocol": PROTOCOL, "error": message}).encode()


# -- the serving side ------------------------------------------------------------------------------


def _response(seq: int, status: Status, payload: bytes = b"") -> bytes:
    return RESPONSE.pack(seq, status, len(payload)) + payload


def serve_request(packet: bytes, windows: Mapping[Region, BusWindow]) -> bytes:
    """Do one request on the window of its region and return the response packet.

    The window is the device's own (a simulator's ``DeviceWindow``), so its side effects happen
    here, once. Errors become a status with a message: the serving loop never dies of a request.
    """
    if len(packet) < REQUEST.size:
        return _response(0, Status.BAD_REQUEST, b"request shorter than its header")
    seq, op, region_code, length, offset = REQUEST.unpack_from(packet)
    data = packet[REQUEST.size :]
    try:
        region = Region(region_code)
        window = windows[region]
    except (ValueError, KeyError):
        return _response(seq, Status.NO_REGION, f"no region {region_code}".encode())
    if length > MAX_TRANSFER:
        return _response(seq, Status.BAD_REQUEST, f"{length} bytes is over the limit".encode())
    try:
        if op == Op.READ and not data:
            return _response(seq, Status.OK, window.read(offset, length))
        if op == Op.WRITE and len(data) == length:
            window.write(offset, data)
            return _response(seq, Status.OK)
    except (BusError, ValueError) as exc:
        return _response(seq, Status.BUS_ERROR, f"{region.name.lower()}: {exc}".encode())
    return _response(seq, Status.BAD_REQUEST, f"malformed op {op} of {length} bytes".encode())


# -- the driver's side -----------------------------------------------------------------------------


class RemoteLink:
    """One connection to a simulator, shared by the remote windows over it.

    Each access is a strict round trip under a lock, each of its send and receive bounded by
    ``timeout``. Any failure of the socket (peer gone, reply overdue, reply out of sequence)
    breaks the link: after a timeout a late reply could be taken for the next request's, so
    every later access raises :class:`BusError` until the owner either closes the link or
    gives it a new connection (:meth:`reconnect`, once the simulator is back).
    """

    def __init__(self, sock: socket.socket, *, timeout: float = 10.0, label: str = "simulator"):
        sock.settimeout(timeout)
        self._sock = sock
        self._label = label
        self._timeout = timeout
        self._lock = threading.Lock()
        self._close_lock = threading.Lock()
        self._seq = 0
        self._closed = False
        self._broken: str | None = None

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def broken(self) -> str | None:
        """Why the link is unusable (the peer went away, a reply was overdue), or None."""
        return self._broken

    @property
    def label(self) -> str:
        return self._label

    def reconnect(self, sock: socket.socket) -> socket.socket:
        """Carry on over ``sock``, a new connection to the same simulator (restarted): the next
        request goes out on it, sequence numbers afresh. Returns the old socket, which the
        caller closes (a thread blocked on it still wakes with :class:`BusError`)."""
        sock.settimeout(self._timeout)
        with self._lock:
            if self._closed:
                raise BusError(f"{self._label}: the link is closed", errno.ENOTCONN)
            old, self._sock = self._sock, sock
            self._seq = 0
            self._broken = None
        return old

    def drop_connection(self, why: str = "the connection was dropped") -> None:
        """Shut the connection down (the peer sees this driver go) and leave the link broken
        until :meth:`reconnect`; nothing once the link is closed."""
        with self._close_lock:
            if self._closed:
                return
            self._broken = self._broken or why
            try:
                self._sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass  # already disconnected

    def request(self, op: Op, region: Region, offset: int, length: int, data: bytes = b"") -> bytes:
        """One round trip; returns the data read (empty for a write)."""
        with self._lock:
            if self._closed or self._broken is not None:
                why = self._broken or "the link is closed"
                raise BusError(f"{self._label}: {why}", errno.ENOTCONN)
            self._seq = (self._seq + 1) & 0xFFFF_FFFF
            seq = self._seq
            packet = REQUEST.pack(seq, op, region, length, offset) + data
            reply = self._round_trip(packet)
        if len(reply) < RESPONSE.size:
            raise self._break("a reply shorter than its header", errno.EPROTO)
        got_seq, status, n = RESPONSE.unpack_from(reply)
        payload = reply[RESPONSE.size :]
        if got_seq != seq or len(payload) != n:
            raise self._break("a reply out of sequence", errno.EPROTO)
        if status != Status.OK:
            code = _STATUS_ERRNO.get(status, errno.EIO)
            raise BusError(f"{self._label}: {payload.decode(errors='replace')}", code)
        if op == Op.READ and n != length:
            raise self._break(f"{n} bytes for a {length}-byte read", errno.EPROTO)
        return payload

    def _round_trip(self, packet: bytes) -> bytes:
        try:
            self._sock.send(packet)
            reply = self._sock.recv(MAX_PACKET)
        except TimeoutError:
            raise self._break(
                f"no reply within {self._timeout:g} s", errno.ETIMEDOUT, locked=True
            ) from None
        except OSError as exc:
            raise self._break(
                f"connection lost ({exc.strerror or exc})", errno.ECONNRESET, locked=True
            ) from None
        if not reply:
            raise self._break(
                "connection lost (the simulator went away)", errno.ECONNRESET, locked=True
            )
        return reply

    def _break(self, why: str, code: int, locked: bool = False) -> BusError:
        """Mark the link unusable; the caller raises what this returns."""
        if self._closed:
            return BusError(f"{self._label}: the link was closed", errno.ENOTCONN)
        if locked:
            self._broken = why
        else:
            with self._lock:
                self._broken = why
        return BusError(f"{self._label}: {why}", code)

    def close(self) -> None:
        """Close the socket; a thread blocked in a round trip wakes and gets ``BusError``."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass  # already disconnected
        with self._lock:
            self._sock.close()


class RemoteWindow(BusWindow):
    """A board's registers in a simulator process: every access is a request over ``link``.

    Accesses keep their order and their grouping: a 16-bit read is one request for 2 bytes,
    which the simulator performs byte by byte in ascending order, as the D8 board sees it. The
    window does not own the link (both boards share one); whoever made the link closes it.
    """

    kind = "remote"

    def __init__(self, link: RemoteLink, region: Region | str, size: int) -> None:
        super().__init__(size)
        self._link = link
        self._region = Region[region.upper()] if isinstance(region, str) else Region(region)

    @property
    def region(self) -> Region:
        return self._region

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        name = self._region.name.lower()
        return f"<{type(self).__name__} region={name} size=0x{self.size:X} {state}>"

    def _read(self, offset: int, n: int) -> bytes:
        chunks = []
        for at in range(offset, offset + n, MAX_TRANSFER):
            length = min(MAX_TRANSFER, offset + n - at)
            chunks.append(self._link.request(Op.READ, self._region, at, length))
        return b"".join(chunks)

    def _write(self, offset: int, data: bytes) -> None:
        for at in range(0, len(data), MAX_TRANSFER):
            chunk = data[at : at + MAX_TRANSFER]
            self._link.request(Op.WRITE, self._region, offset + at, len(chunk), chunk)

    def _close(self) -> None:
        pass  # the link is shared and closed by its owner


class SliceWindow(BusWindow):
    """``size`` bytes of ``parent`` from ``base``, addressed from 0; closing it closes ``parent``
    when it owns it.

    Accesses are forwarded at their own width (a ``read16`` stays one 16-bit access), and views
    are the parent's, so a slice of shared memory is as fast as the segment itself. ``base`` must
    be a multiple of 4 so that alignment means the same thing in both windows.
    """

    kind = "slice"

    def __init__(self, parent: BusWindow, base: int, size: int, *, owns_parent: bool = True):
        if base < 0 or base % 4 or base + size > parent.size:
            raise BusError(
                f"a slice of 0x{size:X} bytes at 0x{base:X} does not fit a {parent.kind} window "
                f"of 0x{parent.size:X} bytes (or is not 4-byte aligned)"
            )
        super().__init__(size)
        self._parent = parent
        self._base = base
        self._owns = owns_parent

    @property
    def parent(self) -> BusWindow:
        return self._parent

    def replace_parent(self, parent: BusWindow) -> BusWindow:
        """Carry on over ``parent`` (the same region of a target that came back: a restarted
        simulator's new segment), which must be large enough; returns the old parent, which the
        caller closes. The slice object, which the driver holds, stays the same."""
        if self.closed:
            raise BusError(f"{self.kind} window is closed")
        if self._base + self.size > parent.size:
            raise BusError(
                f"a slice of 0x{self.size:X} bytes at 0x{self._base:X} does not fit the new "
                f"{parent.kind} window of 0x{parent.size:X} bytes"
            )
        old, self._parent = self._parent, parent
        return old

    @property
    def base(self) -> int:
        return self._base

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        return (
            f"<{type(self).__name__} of {self._parent!r} base=0x{self._base:X} "
            f"size=0x{self.size:X} {state}>"
        )

    def _read(self, offset: int, n: int) -> bytes:
        return self._parent.read(self._base + offset, n)

    def _write(self, offset: int, data: bytes) -> None:
        self._parent.write(self._base + offset, data)

    def read8(self, offset: int) -> int:
        self._check(offset, 1, 1)
        return self._parent.read8(self._base + offset)

    def read16(self, offset: int) -> int:
        self._check(offset, 2, 2)
        return self._parent.read16(self._base + offset)

    def read32(self, offset: int) -> int:
        self._check(offset, 4, 4)
        return self._parent.read32(self._base + offset)

    def write8(self, offset: int, value: int) -> None:
        self._check(offset, 1, 1)
        self._parent.write8(self._base + offset, value)

    def write16(self, offset: int, value: int) -> None:
        self._check(offset, 2, 2)
        self._parent.write16(self._base + offset, value)

    def write32(self, offset: int, value: int) -> None:
        self._check(offset, 4, 4)
        self._parent.write32(self._base + offset, value)

    def view(self, struct_type: type[S], offset: int = 0) -> StructView[S]:
        self._check(offset, ctypes.sizeof(struct_type), 2)
        return self._parent.view(struct_type, self._base + offset)

    def _close(self) -> None:
        if self._owns:
            self._parent.close()
