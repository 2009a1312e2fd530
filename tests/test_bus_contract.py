"""One contract for every bus-window kind (docs/registers.md).

Each kind is opened the way a user would open it, through ``open_window``:

* ``memory``: a bytearray;
* ``shm``: a segment this process creates;
* ``mmap-file``: a temporary regular file;
* ``mmap-uio``: UIO map 1 of a fake ``uio2``: a temporary sysfs tree says where the map starts
  inside its page, and a regular file stands in for ``/dev/uio2`` (map 1 is its second page);
* ``mmap-physaddr``: the ``/dev/mem`` branch (physical address, ``O_SYNC``, no file-length
  check) forced with ``device=True`` on a regular file standing in for physical memory, at a
  physical address that is not page aligned;
* ``mmap-chardev``: ``/dev/zero``, a real character device, so the branch is also chosen the way
  it is for ``/dev/mem`` (by ``stat``). Its offset stays inside the first page because Linux
  faults on ``/dev/zero`` mappings at a non-zero file offset.

* ``remote``: a board in another process, here a memory window served over a socket pair on a
  thread (the wire protocol of :mod:`biris_hw.bus.remote`); not memory-mapped, so no views;
* ``slice``: part of a larger memory window, at a base that is not zero.

The kinds come from the registry (``WINDOW_KINDS``): every registered kind is held to this
contract, and a kind registered without a factory in ``FACTORIES`` fails
``test_every_registered_kind_has_a_factory``.

Where the kind has a second way in (the bytearray, the shm file, the stand-in file) the tests
read it too, so a window that maps the wrong place fails even when its own reads agree.
"""

from __future__ import annotations

import mmap
import os
import socket
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from biris_hw.bus import WINDOW_KINDS, BusError, BusWindow, open_window, register_window, registry
from biris_hw.bus.memory import MemoryWindow
from biris_hw.bus.remote import MAX_PACKET, Region, RemoteLink, serve_request
from biris_hw.bus.shm import SharedMemoryWindow
from biris_hw.errors import UnknownKind
from regs.biexec import OFF_COMMAND, OFF_PARAM, OFF_STATUS, BiexecCom

SIZE = 0x200
VIEW_AT = 0x40
UIO_MAP_OFFSET = 0x120
PHYS_ADDR = 0x1234
CHARDEV_ADDR = 0x234
SLICE_BASE = 0x84


@dataclass
class Rig:
    """A window plus what the tests need to know about where its bytes live."""

    window: BusWindow
    open_again: Callable[[], BusWindow]
    peek: Callable[[int, int], bytes] | None
    """Reads the target's bytes at a window offset without going through the window."""
    mapped_path: Callable[[BusWindow], str] | None
    """The name ``/proc/self/maps`` shows for a window's mapping, for kinds that map a file."""
    views: bool = True
    """Whether the kind is memory-mapped and so offers ctypes views."""
    cleanup: Callable[[], None] | None = None
    """Releases what the kind needed besides the window (a serving thread and its socket)."""


def _file_peek(path: Path, base: int) -> Callable[[int, int], bytes]:
    def peek(offset: int, n: int) -> bytes:
        with open(path, "rb") as f:
            f.seek(base + offset)
            return f.read(n)

    return peek


def _memory(tmp_path: Path) -> Rig:
    backing = bytearray(SIZE)

    def make() -> BusWindow:
        return open_window("memory", size=SIZE, buffer=backing)

    return Rig(make(), make, lambda off, n: bytes(backing[off : off + n]), None)


def _shm_path(window: BusWindow) -> str:
    assert isinstance(window, SharedMemoryWindow)
    return f"/dev/shm/{window.name}"


def _shm(tmp_path: Path) -> Rig:
    def make() -> BusWindow:
        return open_window("shm", size=SIZE, create=True)

    window = make()
    shm_file = Path(_shm_path(window))
    if not shm_file.exists():
        return Rig(window, make, None, None)
    return Rig(window, make, _file_peek(shm_file, 0), _shm_path)


def _mmap_file(tmp_path: Path) -> Rig:
    path = tmp_path / "bus.bin"
    path.write_bytes(bytes(SIZE))

    def make() -> BusWindow:
        return open_window("mmap", path=str(path), size=SIZE)

    return Rig(make(), make, _file_peek(path, 0), lambda _: str(path))


def make_uio_tree(root: Path, uio: int, index: int, size: int, offset: int) -> None:
    """A sysfs tree the way the kernel lays one out for one UIO map."""
    map_dir = root / f"uio{uio}" / "maps" / f"map{index}"
    map_dir.mkdir(parents=True)
    (map_dir / "size").write_text(f"0x{size:08x}\n")
    (map_dir / "offset").write_text(f"0x{offset:x}\n")
    (map_dir / "addr").write_text(f"0x{0xFE000000 + offset:08x}\n")
    (map_dir / "name").write_text("biris\n")


def _mmap_uio(tmp_path: Path) -> Rig:
    sysfs = tmp_path / "sys"
    make_uio_tree(sysfs, 2, 1, SIZE, UIO_MAP_OFFSET)
    standin = tmp_path / "uio2"
    standin.write_bytes(bytes(3 * mmap.PAGESIZE))

    def make() -> BusWindow:
        return open_window("mmap", uio=2, map_index=1, path=str(standin), sysfs_root=str(sysfs))

    base = 1 * mmap.PAGESIZE + UIO_MAP_OFFSET
    return Rig(make(), make, _file_peek(standin, base), lambda _: str(standin))


def _mmap_physaddr(tmp_path: Path) -> Rig:
    physmem = tmp_path / "physmem"
    physmem.write_bytes(bytes(3 * mmap.PAGESIZE))

    def make() -> BusWindow:
        return open_window("mmap", path=str(physmem), offset=PHYS_ADDR, size=SIZE, device=True)

    return Rig(make(), make, _file_peek(physmem, PHYS_ADDR), lambda _: str(physmem))


def _mmap_chardev(tmp_path: Path) -> Rig:
    try:
        os.close(os.open("/dev/zero", os.O_RDWR))
    except OSError as exc:
        pytest.skip(f"/dev/zero is not usable here: {exc}")

    def make() -> BusWindow:
        return open_window("mmap", path="/dev/zero", offset=CHARDEV_ADDR, size=SIZE)

    return Rig(make(), make, None, lambda _: "/dev/zero")


class _Served:
    """The serving half of the remote protocol for one memory window, on a thread."""

    def __init__(self, backing: bytearray) -> None:
        self.board = MemoryWindow(len(backing), buffer=backing)
        self.client, self._end = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.link = RemoteLink(self.client, timeout=10.0, label="contract")
        self._thread = threading.Thread(target=self._run, name="contract-remote", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            try:
                packet = self._end.recv(MAX_PACKET)
            except OSError:
                return
            if not packet:
                return
            self._end.send(serve_request(packet, {Region.MOTION: self.board}))

    def close(self) -> None:
        self.link.close()  # the peer sees end of file and the thread returns
        self._thread.join(timeout=10.0)
        self._end.close()
        self.board.close()


def _remote(tmp_path: Path) -> Rig:
    backing = bytearray(SIZE)
    served = _Served(backing)

    def make() -> BusWindow:
        return open_window("remote", link=served.link, region="motion", size=SIZE)

    peek = lambda off, n: bytes(backing[off : off + n])  # noqa: E731
    return Rig(make(), make, peek, None, views=False, cleanup=served.close)


def _slice(tmp_path: Path) -> Rig:
    backing = bytearray(SLICE_BASE + SIZE + 0x40)

    def make() -> BusWindow:
        parent = open_window("memory", size=len(backing), buffer=backing)
        return open_window("slice", parent=parent, base=SLICE_BASE, size=SIZE)

    peek = lambda off, n: bytes(backing[SLICE_BASE + off : SLICE_BASE + off + n])  # noqa: E731
    return Rig(make(), make, peek, None)


VMUSB_BASE = 0x30_0000


@pytest.fixture(autouse=True)
def _quick_vmusb_bring_up(monkeypatch: pytest.MonkeyPatch) -> None:
    """The bring-up's silence check on the IN endpoint waits 20 ms for a real bridge's stale
    data; the simulated one owes none, and the suite opens a window per test."""
    from biris_hw.bus.vmusb import VmUsbBridge

    monkeypatch.setattr(VmUsbBridge, "drain_timeout_s", 0.002)


def _vmusb(tmp_path: Path) -> Rig:
    """A24 memory of a board in a simulated VM-USB's crate, reached through real pyusb."""
    from sim.vmusb import SimulatedVmUsb, VmUsbBackend

    backing = bytearray(SIZE)
    device = SimulatedVmUsb(serial="VM0042", transfer_latency_s=0.0)
    device.map("board", MemoryWindow(SIZE, buffer=backing), VMUSB_BASE, 24)
    backend = VmUsbBackend(device)

    def make() -> BusWindow:
        return open_window("vmusb", size=SIZE, base=VMUSB_BASE, am=0x39, backend=backend)

    def cleanup() -> None:
        violations = device.violations
        device.close()
        assert violations == [], violations

    def peek(off: int, n: int) -> bytes:
        return bytes(backing[off : off + n])

    return Rig(make(), make, peek, None, views=False, cleanup=cleanup)


FACTORIES: dict[str, dict[str, Callable[[Path], Rig]]] = {
    "memory": {"memory": _memory},
    "shm": {"shm": _shm},
    "mmap": {
        "mmap-file": _mmap_file,
        "mmap-uio": _mmap_uio,
        "mmap-physaddr": _mmap_physaddr,
        "mmap-chardev": _mmap_chardev,
    },
    "remote": {"remote": _remote},
    "slice": {"slice": _slice},
    "vmusb": {"vmusb": _vmusb},
}
"""Registered kind -> the ways of opening one the suite runs (test id -> factory)."""

CASES = [
    pytest.param((kind, make), id=variant)
    for kind in sorted(WINDOW_KINDS)
    for variant, make in FACTORIES.get(kind, {}).items()
]


def test_every_registered_kind_has_a_factory() -> None:
    missing = sorted(set(WINDOW_KINDS) - set(FACTORIES))
    assert not missing, f"window kinds registered but not held to the contract: {missing}"
    assert set(FACTORIES) <= set(WINDOW_KINDS), "a factory for a kind nobody registers"


@pytest.fixture(params=CASES)
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Rig]:
    kind, make = request.param
    made = make(tmp_path)
    assert made.window.kind == kind
    try:
        yield made
    finally:
        made.window.close()
        if made.cleanup is not None:
            made.cleanup()


@pytest.fixture
def window(rig: Rig) -> BusWindow:
    return rig.window


def fill(window: BusWindow) -> bytes:
    """Give every byte a distinct-ish value, so an access that strays shows up."""
    pattern = bytes((i * 7 + 3) & 0xFF for i in range(window.size))
    window.write(0, pattern)
    return pattern


def mapped_names() -> str:
    return Path("/proc/self/maps").read_text()


# -- identity ------------------------------------------------------------------------------------


def test_window_has_its_size_and_kind(rig: Rig) -> None:
    assert rig.window.size == SIZE
    assert WINDOW_KINDS[rig.window.kind].endswith(f":{type(rig.window).__qualname__}")
    assert not rig.window.closed


def test_target_is_mapped_where_asked(rig: Rig) -> None:
    if rig.peek is None:
        pytest.skip("this kind has no second way in")
    rig.window.write(0, b"\xa1\xb2")
    rig.window.write32(SIZE - 4, 0xC0FFEE11)
    assert rig.peek(0, 2) == b"\xa1\xb2"
    assert rig.peek(SIZE - 4, 4) == b"\xc0\xff\xee\x11"


# -- width-explicit accesses ---------------------------------------------------------------------


@pytest.mark.parametrize("offset", [0, 4, 0x100, SIZE - 4])
def test_round_trips_at_each_width(window: BusWindow, offset: int) -> None:
    window.write8(offset + 1, 0x5A)
    assert window.read8(offset + 1) == 0x5A
    window.write16(offset + 2, 0xBEEF)
    assert window.read16(offset + 2) == 0xBEEF
    window.write32(offset, 0x89ABCDEF)
    assert window.read32(offset) == 0x89ABCDEF


def test_values_are_big_endian(window: BusWindow) -> None:
    window.write16(0x10, 0x1234)
    assert window.read(0x10, 2) == b"\x12\x34"
    window.write32(0x20, 0x12345678)
    assert window.read(0x20, 4) == b"\x12\x34\x56\x78"
    assert window.read16(0x20) == 0x1234
    assert window.read16(0x22) == 0x5678
    assert window.read8(0x23) == 0x78
    window.write(0x30, b"\xab\xcd\xef\x01")
    assert window.read32(0x30) == 0xABCDEF01


@pytest.mark.parametrize(
    ("width", "value", "stored"),
    [
        (1, -1, 0xFF),
        (1, -0x80, 0x80),
        (2, -1, 0xFFFF),
        (2, -0x8000, 0x8000),
        (4, -1, 0xFFFF_FFFF),
        (4, -0x8000_0000, 0x8000_0000),
    ],
)
def test_signed_values_are_accepted(window: BusWindow, width: int, value: int, stored: int) -> None:
    write, read = _accessors(window, width)
    write(8, value)
    assert read(8) == stored


@pytest.mark.parametrize(
    ("width", "value"),
    [(1, 0x100), (1, -0x81), (2, 0x1_0000), (2, -0x8001), (4, 1 << 32), (4, -(1 << 31) - 1)],
)
def test_too_wide_values_are_refused(window: BusWindow, width: int, value: int) -> None:
    before = fill(window)
    write, _ = _accessors(window, width)
    with pytest.raises(BusError):
        write(8, value)
    assert window.read(0, SIZE) == before


def _accessors(
    window: BusWindow, width: int
) -> tuple[Callable[[int, int], None], Callable[[int], int]]:
    return {
        1: (window.write8, window.read8),
        2: (window.write16, window.read16),
        4: (window.write32, window.read32),
    }[width]


BAD_ACCESSES: dict[str, Callable[[BusWindow], Any]] = {
    "read8 at size": lambda w: w.read8(SIZE),
    "write8 at size": lambda w: w.write8(SIZE, 1),
    "read8 at -1": lambda w: w.read8(-1),
    "write8 at -1": lambda w: w.write8(-1, 1),
    "write16 across the end": lambda w: w.write16(SIZE - 1, 0x1111),
    "read16 at size": lambda w: w.read16(SIZE),
    "write32 across the end": lambda w: w.write32(SIZE - 2, 0x11111111),
    "write32 at -4": lambda w: w.write32(-4, 0x11111111),
    "read32 past the end": lambda w: w.read32(SIZE),
    "bulk read past the end": lambda w: w.read(SIZE - 2, 4),
    "bulk read of negative length": lambda w: w.read(0, -1),
    "bulk write past the end": lambda w: w.write(SIZE - 2, b"\x11\x11\x11\x11"),
    "bulk write at -1": lambda w: w.write(-1, b"\x11\x11"),
    "read16 misaligned": lambda w: w.read16(0x11),
    "write16 misaligned": lambda w: w.write16(0x11, 0x1111),
    "read32 at 2 mod 4": lambda w: w.read32(0x12),
    "write32 at 2 mod 4": lambda w: w.write32(0x12, 0x11111111),
    "write32 at 1 mod 4": lambda w: w.write32(0x11, 0x11111111),
    "view misaligned": lambda w: w.view(BiexecCom, 1),
    "view past the end": lambda w: w.view(BiexecCom, SIZE - 2),
}


@pytest.mark.parametrize("access", BAD_ACCESSES.values(), ids=BAD_ACCESSES.keys())
def test_bad_accesses_raise_and_change_nothing(
    window: BusWindow, access: Callable[[BusWindow], Any]
) -> None:
    before = fill(window)
    with pytest.raises(BusError):
        access(window)
    assert window.read(0, SIZE) == before


def test_bus_error_is_an_os_error(window: BusWindow) -> None:
    with pytest.raises(OSError) as caught:
        window.read16(1)
    assert isinstance(caught.value, BusError)
    assert isinstance(caught.value.errno, int)
    assert "misaligned" in str(caught.value)


# -- bulk ----------------------------------------------------------------------------------------


def test_bulk_round_trip(window: BusWindow) -> None:
    data = bytes(range(256)) + bytes(range(255, -1, -1))
    window.write(0, data)
    assert window.read(0, SIZE) == data
    window.write(0x101, bytearray(b"\x01\x02\x03"))
    window.write(0x1F0, memoryview(b"\xee" * 16))
    assert window.read(0x100, 5) == bytes([0xFF, 1, 2, 3, 0xFB])
    assert window.read(0x1F0, 16) == b"\xee" * 16
    assert window.read(0x10, 0) == b""


# -- structure views -----------------------------------------------------------------------------


def _views_only(rig: Rig) -> None:
    """Skip for a kind that is not memory-mapped, after checking it refuses views properly."""
    if not rig.views:
        with pytest.raises(BusError, match="not memory-mapped"):
            rig.window.view(BiexecCom, VIEW_AT)
        pytest.skip("this kind is not memory-mapped")


def test_view_shares_memory_with_width_accesses(rig: Rig) -> None:
    _views_only(rig)
    window = rig.window
    com = window.view(BiexecCom, VIEW_AT)
    window.write16(VIEW_AT + OFF_COMMAND, 5)
    assert com.COMMAND == 5
    com.STATUS = -2
    assert window.read16(VIEW_AT + OFF_STATUS) == 0xFFFE
    com.PARAM = b"0x1000"
    assert window.read(VIEW_AT + OFF_PARAM, 7) == b"0x1000\0"
    snap = com.snapshot()
    window.write16(VIEW_AT + OFF_COMMAND, 0)
    assert com.COMMAND == 0
    assert snap.COMMAND == 5


# -- lifecycle -----------------------------------------------------------------------------------

AFTER_CLOSE: dict[str, Callable[[BusWindow], Any]] = {
    "read": lambda w: w.read(0, 4),
    "write": lambda w: w.write(0, b"\x01"),
    "read8": lambda w: w.read8(0),
    "read16": lambda w: w.read16(0),
    "read32": lambda w: w.read32(0),
    "write8": lambda w: w.write8(0, 1),
    "write16": lambda w: w.write16(0, 1),
    "write32": lambda w: w.write32(0, 1),
    "view": lambda w: w.view(BiexecCom, 0),
}


@pytest.mark.parametrize("name", AFTER_CLOSE)
def test_every_access_after_close_raises(rig: Rig, name: str) -> None:
    window, access = rig.window, AFTER_CLOSE[name]
    if name == "view":
        _views_only(rig)
    access(window)  # fine while open
    window.close()
    assert window.closed
    with pytest.raises(BusError):
        access(window)


def test_views_die_with_their_window(rig: Rig) -> None:
    _views_only(rig)
    window = rig.window
    com = window.view(BiexecCom, VIEW_AT)
    com.COMMAND = 3
    window.close()
    with pytest.raises(BusError):
        _ = com.COMMAND
    with pytest.raises(BusError):
        com.COMMAND = 4
    window.close()  # twice is fine
    assert window.closed


def test_context_manager_closes(rig: Rig) -> None:
    with rig.open_again() as window:
        window.write16(0, 7)
        com = window.view(BiexecCom, 0) if rig.views else None
        assert com is None or com.COMMAND == 7
    assert window.closed
    with pytest.raises(BusError):
        window.read16(0)
    if com is not None:
        with pytest.raises(BusError):
            _ = com.COMMAND


def test_close_unmaps(rig: Rig) -> None:
    if rig.mapped_path is None:
        pytest.skip("this kind maps no file")
    first = rig.mapped_path(rig.window)
    assert first in mapped_names()
    rig.window.close()
    assert first not in mapped_names()
    window = rig.open_again()
    again = rig.mapped_path(window)
    assert again in mapped_names()
    window.close()
    assert again not in mapped_names()


def test_open_and_close_leave_no_descriptor(rig: Rig) -> None:
    before = len(os.listdir("/proc/self/fd"))
    for _ in range(3):
        window = rig.open_again()
        window.write8(0, 1)
        window.close()
    assert len(os.listdir("/proc/self/fd")) == before


# -- properties ----------------------------------------------------------------------------------

_PROPERTY_SETTINGS = settings(
    max_examples=60,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


@_PROPERTY_SETTINGS
@given(data=st.data())
def test_property_width_accesses(window: BusWindow, data: st.DataObject) -> None:
    width = data.draw(st.sampled_from([1, 2, 4]), label="width")
    bits = 8 * width
    offset = data.draw(st.integers(-8, SIZE + 8), label="offset")
    # Twice as wide as the register either way, so too-wide values are drawn as often as not.
    value = data.draw(st.integers(-(1 << bits), (1 << (bits + 1)) - 1), label="value")
    write, read = _accessors(window, width)
    before = window.read(0, SIZE)
    fits = offset >= 0 and offset + width <= SIZE and offset % width == 0
    representable = -(1 << (bits - 1)) <= value < (1 << bits)
    if fits and representable:
        write(offset, value)
        stored = value & ((1 << bits) - 1)
        assert read(offset) == stored
        expected = before[:offset] + stored.to_bytes(width, "big") + before[offset + width :]
        assert window.read(0, SIZE) == expected
        return
    with pytest.raises(BusError):
        write(offset, value)
    if not fits:
        with pytest.raises(BusError):
            read(offset)
    assert window.read(0, SIZE) == before


@_PROPERTY_SETTINGS
@given(offset=st.integers(-4, SIZE + 4), data=st.binary(max_size=24))
def test_property_bulk_accesses(window: BusWindow, offset: int, data: bytes) -> None:
    before = window.read(0, SIZE)
    if offset >= 0 and offset + len(data) <= SIZE:
        window.write(offset, data)
        assert window.read(offset, len(data)) == data
        assert window.read(0, SIZE) == before[:offset] + data + before[offset + len(data) :]
        return
    with pytest.raises(BusError):
        window.write(offset, data)
    with pytest.raises(BusError):
        window.read(offset, len(data))
    assert window.read(0, SIZE) == before


# -- registry ------------------------------------------------------------------------------------


def test_unknown_kind_is_refused() -> None:
    with pytest.raises(UnknownKind) as caught:
        open_window("nope")
    assert isinstance(caught.value, LookupError)
    assert "nope" in str(caught.value)
    assert "mmap" in str(caught.value)  # the message lists what is known


def test_register_window_adds_a_kind() -> None:
    class ScratchWindow(MemoryWindow):
        kind = "scratch"

    with pytest.raises(UnknownKind):
        open_window("scratch", size=16)
    register_window("scratch", ScratchWindow)
    try:
        assert WINDOW_KINDS["scratch"].endswith("ScratchWindow")
        with open_window("scratch", size=16) as window:
            assert isinstance(window, ScratchWindow)
            window.write16(0, 0x4242)
            assert window.read(0, 2) == b"BB"
    finally:
        registry._REGISTRY.unregister("scratch")  # the registry is process-wide
    assert "scratch" not in WINDOW_KINDS
