"""The driver side of the ``vmusb`` transport, against a simulated VM-USB behind real pyusb.

Slaves in the simulated crate are :class:`MemoryWindow`\\ s, so every value read through the
bridge is compared with what the same memory gives directly. Every test ends with the device's
protocol audit clean (the ``crate`` fixture) and nothing left open or running (``no_leaks``).
"""

from __future__ import annotations

import errno
import select
import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import usb.core
import usb.util

from biris_hw.bus import BusError, open_window
from biris_hw.bus import vmusb as driver
from biris_hw.bus.memory import MemoryWindow
from biris_hw.bus.vmusb import VmeList, VmUsbBridge, VmUsbWindow
from biris_hw.errors import LineClosed
from biris_hw.irq import open_line
from biris_hw.irq.vmusb import VmUsbLine
from regs.vmusb import (
    ACTION_REGISTER,
    BUFFER_LENGTH_MASK,
    BUFFER_SINGLE_EVENT,
    EP_OUT,
    GLOBAL_ALIGN32,
    IRQ_MASK_ALL,
    MAX_LIST_LINES,
    PID,
    REGISTER_BLOCK,
    VID,
    Action,
    AddressModifier,
    InternalReg,
)
from sim.vmusb import SimulatedVmUsb, VmUsbBackend

A24 = int(AddressModifier.A24_USER)
A16 = int(AddressModifier.A16_SUPERVISOR)
MEM_BASE = 0x20_0000
MEM_SIZE = 0x2000
REG_BASE = 0x4000
REG_SIZE = 0x100
WAIT = 5.0
"""Timeout for what should happen at once; only reached when a test fails."""


@dataclass
class Crate:
    device: SimulatedVmUsb
    backend: VmUsbBackend
    memory: MemoryWindow
    """A24 memory at MEM_BASE."""
    regs: MemoryWindow
    """A16 registers at REG_BASE."""

    def window(self, **options: object) -> VmUsbWindow:
        options.setdefault("size", MEM_SIZE)
        options.setdefault("base", MEM_BASE)
        options.setdefault("am", A24)
        window = open_window("vmusb", backend=self.backend, **options)
        assert isinstance(window, VmUsbWindow)
        return window

    def reg_window(self) -> VmUsbWindow:
        return self.window(size=REG_SIZE, base=REG_BASE, am=A16)

    def line(self, level: int, vector: int, **options: object) -> VmUsbLine:
        line = open_line("vmusb", level=level, vector=vector, backend=self.backend, **options)
        assert isinstance(line, VmUsbLine)
        return line


def _crate(serial: str) -> tuple[SimulatedVmUsb, MemoryWindow, MemoryWindow]:
    device = SimulatedVmUsb(serial=serial)
    memory = MemoryWindow(MEM_SIZE)
    memory.write(0, bytes((i * 7 + 3) & 0xFF for i in range(MEM_SIZE)))
    regs = MemoryWindow(REG_SIZE)
    device.map("memory", memory, MEM_BASE, 24)
    device.map("regs", regs, REG_BASE, 16)
    return device, memory, regs


def _no_bridge_left(backend: VmUsbBackend) -> bool:
    with driver._TABLE_LOCK:
        return not any(key[1] == id(backend) for key in driver._TABLE)


@pytest.fixture
def crate(no_leaks: None, monkeypatch: pytest.MonkeyPatch) -> Iterator[Crate]:
    # the simulated bridge answers at once: a short bring-up drain keeps the file fast
    monkeypatch.setattr(VmUsbBridge, "drain_timeout_s", 0.005)
    device, memory, regs = _crate("VM0001")
    backend = VmUsbBackend(device)
    try:
        yield Crate(device, backend, memory, regs)
        assert _no_bridge_left(backend), "a window or line was left open"
        assert device.violations == []
    finally:
        device.close()


def transfers(device: SimulatedVmUsb) -> tuple[int, int]:
    return device.counters.out_transfers, device.counters.in_transfers


# -- lists ---------------------------------------------------------------------------------------


def test_list_lines_are_encoded_as_the_spec_says() -> None:
    lst = VmeList()
    lst.read8(A24, 0x123456)  # even byte: DS1, LWORD* high
    lst.read8(A24, 0x123457)  # odd byte: DS0
    lst.read16(A24, 0x123458)
    lst.read32(A24, 0x12345C)
    lst.block_read32(A24, 0x100000, 300)  # cut at every 256 bytes: 4 x 64 + 44, one result
    lst.read_register(InternalReg.FIRMWARE_ID)
    blocks = [0x100 | 0x3B | n << 24 for n in (64, 64, 64, 64, 44)]
    assert lst.words() == [
        0x100 | 0x80 | A24,
        0x123457,
        0x100 | 0x40 | A24,
        0x123457,
        0x100 | A24,
        0x123459,
        0x100 | A24,
        0x12345C,
        *(w for i, mode in enumerate(blocks) for w in (mode, 0x100000 + 256 * i)),
        0x100 | 0x1000,
        0x00,
    ]
    assert [slot.kind for slot in lst.reads] == ["single"] * 4 + ["block", "register"]
    # 16-bit alignment: D8 and D16 reads answer a u16, D32, blocks and registers u32s
    answer = struct.pack("<HHHI", 0x12, 0x34, 0xBEEF, 0x89ABCDEF)
    answer += struct.pack("<I", 0x01020304) + struct.pack("<I", 7) * 299
    values = lst.decode(answer + struct.pack("<I", 0x0A000A02))
    assert values[:4] == [0x12, 0x34, 0xBEEF, 0x89ABCDEF]
    assert values[4] == b"\x01\x02\x03\x04" + b"\x00\x00\x00\x07" * 299
    assert values[5] == 0x0A000A02
    writes = VmeList()
    writes.write8(A24, 0x123456, 0xAB)  # the byte on both data lanes
    writes.write16(A24, 0x123458, 0xBEEF)
    assert writes.words() == [0x80 | A24, 0x123457, 0xABAB, A24, 0x123459, 0xBEEF]


def test_answers_are_checked() -> None:
    writes = VmeList()
    writes.write8(A16, 0x10, 1)
    writes.write16(A16, 0x20, 2)
    assert writes.decode(b"\x01\x00") == []  # not zero: every write acknowledged
    assert writes.decode(b"\x01\x00\x00\x00") == []  # a u32 under Align32
    with pytest.raises(BusError, match=r"no DTACK.*D8 write at A16 0x0010.*0x0020") as berr:
        writes.decode(b"\x00\x00")
    assert berr.value.errno == errno.EIO
    with pytest.raises(BusError) as odd:
        writes.decode(b"\x01")
    assert odd.value.errno == errno.EPROTO
    registers = VmeList()
    registers.write_register(InternalReg.ISV12, 0)
    assert registers.decode(b"\x00\x00") == []  # not judged (NSCLDAQ's writeRegister)
    reads = VmeList()
    reads.read8(A16, 0x10)
    reads.read16(A16, 0x20)
    assert reads.decode(b"\x05\x00\x06\x07") == [5, 0x0706]
    with pytest.raises(
        BusError, match=r"bus error at or before the D16 read at A16 0x0020"
    ) as short:
        reads.decode(b"\x05\x00")  # ended short: the list stopped at a bus error
    assert short.value.errno == errno.EIO
    with pytest.raises(BusError, match=r"D8 read at A16 0x0010"):
        reads.decode(b"")
    for bad in (b"\x05\x00\x06", b"\x05\x00\x06\x07\x08\x09"):
        with pytest.raises(BusError) as proto:
            reads.decode(bad)
        assert proto.value.errno == errno.EPROTO
    with pytest.raises(BusError, match=r"in a list of VME reads") as mixed:
        reads.write8(A16, 0x30, 1)
    assert mixed.value.errno == errno.EINVAL
    with pytest.raises(BusError, match="in a list of VME writes"):
        writes.block_read32(A24, 0x100, 2)
    with pytest.raises(BusError):
        VmeList().block_read32(A16, 0x100, 1)  # A16 has no block transfer
    with pytest.raises(BusError):
        VmeList().read16(A24, 0x101)


# -- bring-up and finding ----------------------------------------------------------------------


def test_bring_up_leaves_the_bridge_idle_and_aligned(crate: Crate) -> None:
    # a previous user left data taking running, with a buffer owed: bring-up stops and drains it
    raw = usb.core.find(idVendor=VID, idProduct=PID, backend=crate.backend)
    raw.write(EP_OUT, struct.pack("<HHH", REGISTER_BLOCK, ACTION_REGISTER, Action.START_DAQ))
    usb.util.dispose_resources(raw)
    assert crate.device.daq_running
    with crate.window() as window:
        bridge = window.bridge
        assert bridge.serial == "VM0001"
        assert bridge.firmware_id == crate.device.firmware_id
        mode = crate.device.register(InternalReg.GLOBAL_MODE)
        assert mode & BUFFER_LENGTH_MASK == BUFFER_SINGLE_EVENT and not mode & GLOBAL_ALIGN32
        assert crate.device.register(InternalReg.EVENTS_PER_BUFFER) == 1
        assert crate.device.register(InternalReg.USB_BULK_SETUP) == 0
        assert crate.device.irq_mask == IRQ_MASK_ALL  # no IRQ armed: every level ignored
        assert not crate.device.daq_running
        assert crate.device.queued_in == 0
        assert crate.device.configuration == 1
        for reg in (InternalReg.ISV12, InternalReg.ISV34, InternalReg.ISV56, InternalReg.ISV78):
            assert crate.device.register(reg) == 0
        with crate.reg_window() as other:
            assert other.bridge is bridge  # one claimed device per serial
        assert bridge.stats.lists == 2  # the IRQ mask's load, then the registers and the id


def test_devices_are_told_apart_by_serial(no_leaks: None) -> None:
    first, mem1, _ = _crate("VM0001")
    second, mem2, _ = _crate("VM0002")
    mem2.write32(0, 0x22222222)
    mem1.write32(0, 0x11111111)
    backend = VmUsbBackend(first, second)
    try:
        with pytest.raises(BusError, match="VM0001, VM0002") as caught:
            VmUsbWindow(16, base=MEM_BASE, backend=backend)
        assert caught.value.errno == errno.EINVAL
        with pytest.raises(BusError, match="VM0003") as missing:
            VmUsbWindow(16, base=MEM_BASE, serial="VM0003", backend=backend)
        assert missing.value.errno == errno.ENODEV
        with (
            VmUsbWindow(16, base=MEM_BASE, serial="VM0002", backend=backend) as two,
            VmUsbWindow(16, base=MEM_BASE, serial="VM0001", backend=backend) as one,
        ):
            assert two.read32(0) == 0x22222222
            assert one.read32(0) == 0x11111111
            assert one.bridge is not two.bridge
        assert _no_bridge_left(backend)
        assert first.violations == second.violations == []
    finally:
        first.close()
        second.close()


def test_no_device_says_what_to_check() -> None:
    with pytest.raises(BusError, match=r"cable.*power.*udev") as caught:
        VmUsbWindow(16, base=0, backend=VmUsbBackend())
    assert caught.value.errno == errno.ENODEV


@pytest.mark.parametrize(
    "options",
    [
        {"am": 0x3E},  # not a modifier the driver knows
        {"am": 0x3B},  # a BLT modifier is not a window's modifier
        {"size": 0x100, "base": 0xFFF0, "am": A16},  # past the end of A16
        {"size": 0x100, "base": 0xFFFFF0},  # past the end of A24
    ],
)
def test_bad_windows_are_refused(crate: Crate, options: dict[str, int]) -> None:
    with pytest.raises(BusError) as caught:
        crate.window(**options)
    assert caught.value.errno == errno.EINVAL


# -- accesses ------------------------------------------------------------------------------------


@pytest.mark.parametrize("space", ["A24", "A16"])
def test_reads_equal_the_memory_and_writes_land(crate: Crate, space: str) -> None:
    if space == "A24":
        window, memory = crate.window(), crate.memory
    else:
        crate.regs.write(0, bytes((0x80 + i) & 0xFF for i in range(REG_SIZE)))
        window, memory = crate.reg_window(), crate.regs
    with window:
        for offset in (0, 4, 0x12, 0x40):
            assert window.read8(offset + 1) == memory.read8(offset + 1)
            assert window.read8(offset) == memory.read8(offset)
            assert window.read16(offset) == memory.read16(offset)
            assert window.read16(offset + 2) == memory.read16(offset + 2)
        assert window.read32(0x20) == memory.read32(0x20)
        for offset, n in [(0, 0), (1, 1), (1, 2), (1, 5), (2, 3), (3, 9), (5, 0x33), (0, 0x80)]:
            assert window.read(offset, n) == memory.read(offset, n), (offset, n)
        window.write8(0x31, 0xA5)
        window.write16(0x32, 0xBEEF)
        window.write32(0x34, 0x01234567)
        assert memory.read(0x31, 7) == b"\xa5\xbe\xef\x01\x23\x45\x67"
        window.write8(0x30, -1)
        assert memory.read8(0x30) == 0xFF
        for offset, data in [(0x41, b"\x01"), (0x43, b"\x02\x03\x04\x05\x06\x07\x08"), (0x52, b"")]:
            window.write(offset, data)
            assert memory.read(offset, len(data)) == data
        data = bytes(range(0x60))
        window.write(0x61, data)
        assert window.read(0x61, len(data)) == data == memory.read(0x61, len(data))


def test_width_accesses_are_one_round_trip(crate: Crate) -> None:
    with crate.window() as window:
        before = transfers(crate.device)
        window.read8(3)
        window.read16(6)
        window.read32(8)
        window.write8(3, 1)
        window.write16(6, 2)
        window.write32(8, 3)
        window.read(1, 0x101)  # unaligned head and tail, a block in between: still one list
        assert transfers(crate.device) == (before[0] + 7, before[1] + 7)


def test_long_accesses_are_split_into_lists(crate: Crate) -> None:
    data = bytes((i * 5) & 0xFF for i in range(0x400))
    with crate.reg_window() as regs, crate.window() as window:
        lists = crate.device.counters.immediate_lists
        window.write(0x101, data)  # D8 + 255 D32 + D16 + D8 = 258 lines: two lists
        assert crate.device.counters.immediate_lists == lists + 2
        assert crate.memory.read(0x101, len(data)) == data
        lists = crate.device.counters.immediate_lists
        assert window.read(0x100, 0x1400) == crate.memory.read(0x100, 0x1400)
        assert crate.device.counters.immediate_lists == lists + 1  # 20 block lines, one list
        lists = crate.device.counters.immediate_lists
        assert regs.read(0, REG_SIZE) == crate.regs.read(0, REG_SIZE)  # A16: 128 D16 cycles
        assert crate.device.counters.immediate_lists == lists + 1
        assert REG_SIZE // 2 < MAX_LIST_LINES


def test_read_many_is_one_list(crate: Crate) -> None:
    spans = [(0, 4), (0x11, 3), (0x100, 0x40), (0x7, 0), (0x1FF, 1)]
    with crate.window() as window:
        lists = crate.device.counters.immediate_lists
        got = window.read_many(spans)
        assert crate.device.counters.immediate_lists == lists + 1
        assert got == [crate.memory.read(offset, n) for offset, n in spans]


def test_default_read_many_reads_in_order() -> None:
    with MemoryWindow(16) as memory:
        memory.write(0, bytes(range(16)))
        assert memory.read_many([(1, 2), (8, 3)]) == [b"\x01\x02", b"\x08\x09\x0a"]
        with pytest.raises(BusError):
            memory.read_many([(0, 1), (15, 2)])


def test_a_latched_position_is_three_byte_reads_in_one_list(crate: Crate) -> None:
    crate.regs.write(0x10, b"\x12\x34\x56")  # MSB..LSB at 0x10..0x12
    with crate.reg_window() as regs:
        lists = crate.device.counters.immediate_lists
        low, mid, high = regs.read_regs([(0x12, 8), (0x11, 8), (0x10, 8)])
        assert crate.device.counters.immediate_lists == lists + 1
        assert high << 16 | mid << 8 | low == 0x123456
        assert regs.read_regs([(0x10, 16), (0x10, 32)]) == [0x1234, 0x12345600]


BAD = {
    "read8 at size": lambda w: w.read8(MEM_SIZE),
    "read16 misaligned": lambda w: w.read16(1),
    "read32 at 2 mod 4": lambda w: w.read32(2),
    "write16 misaligned": lambda w: w.write16(3, 1),
    "write32 past the end": lambda w: w.write32(MEM_SIZE, 1),
    "write8 too wide": lambda w: w.write8(0, 0x100),
    "read past the end": lambda w: w.read(MEM_SIZE - 2, 4),
    "write at -1": lambda w: w.write(-1, b"\x01"),
    "read_many with one bad span": lambda w: w.read_many([(0, 4), (MEM_SIZE, 1)]),
    "read_regs misaligned": lambda w: w.read_regs([(0, 8), (1, 16)]),
    "read_regs of 24 bits": lambda w: w.read_regs([(0, 24)]),
    "view": lambda w: w.view(type("S", (), {}), 0),
}


@pytest.mark.parametrize("access", BAD.values(), ids=BAD.keys())
def test_bad_accesses_raise_before_any_transfer(crate: Crate, access: object) -> None:
    with crate.window() as window:
        before = transfers(crate.device)
        with pytest.raises(BusError):
            access(window)  # type: ignore[operator]
        assert transfers(crate.device) == before


def test_a_vme_bus_error_names_the_address(crate: Crate) -> None:
    crate.device.bus_error_at(MEM_BASE + 0x22)
    with crate.window() as window:
        with pytest.raises(BusError, match=r"0x200022") as caught:
            window.read16(0x22)
        assert caught.value.errno == errno.EIO
        with pytest.raises(BusError, match=r"block read .* at A24 0x200020"):
            window.read(0x20, 0x10)
        with pytest.raises(BusError, match=r"0x200022"):
            window.write(0x21, b"\x01\x02\x03")
        assert window.read16(0x24) == crate.memory.read16(0x24)  # the bridge carries on
        crate.device.bus_error_at(None)


def test_after_closing_every_access_raises(crate: Crate) -> None:
    window = crate.window()
    window.close()
    with pytest.raises(BusError):
        window.read8(0)
    window.close()


# -- interrupts ----------------------------------------------------------------------------------


def test_an_irq_brings_the_registers_its_stack_read(crate: Crate) -> None:
    crate.regs.write8(0x01, 0x5A)
    crate.memory.write16(0x10, 0x1234)
    with crate.reg_window() as regs, crate.window() as memory:
        line = crate.line(2, 0x42, reads=[(regs, 0x01, 8), (memory, 0x10, 16)])
        with line:
            assert line.prefetched() is None
            assert line.wait(0) == 0
            assert crate.device.daq_running
            crate.device.irq(2, 0x42)
            assert line.wait(WAIT) == 1
            assert line.prefetched() == (0x5A, 0x1234)
            crate.regs.write8(0x01, 0x07)
            crate.device.irq(2, 0x42)
            ready, _, _ = select.select([line.fileno()], [], [], WAIT)
            assert ready == [line.fileno()]  # readable while pending
            assert line.wait(WAIT) == 1
            assert line.prefetched() == (0x07, 0x1234)
            crate.memory.write16(0x10, 0x4321)
            crate.device.irq(2, 0x42, count=3)
            seen = 0
            while seen < 3:
                got = line.wait(WAIT)
                assert got
                seen += got
            assert seen == 3
            assert line.prefetched() == (0x07, 0x4321)
        assert not crate.device.daq_running
        assert crate.device.register(InternalReg.ISV12) == 0


def test_accesses_while_armed_pause_data_taking(crate: Crate) -> None:
    with crate.reg_window() as regs:
        with crate.line(3, 0x60, reads=[(regs, 0x03, 8)]) as line:
            before = transfers(crate.device)
            stops = crate.device.counters.daq_stops
            regs.read8(0)
            # stop (action), the last buffer, the list, its answer, start again (action)
            assert transfers(crate.device) == (before[0] + 3, before[1] + 2)
            assert crate.device.counters.daq_stops == stops + 1
            assert crate.device.daq_running
            assert regs.bridge.stats.daq_starts == regs.bridge.stats.daq_stops + 1
            crate.device.irq(3, 0x60)
            assert line.wait(WAIT) == 1
        assert not crate.device.daq_running


class _Doorbell(MemoryWindow):
    """A slave that raises a VME IRQ when its register 0 is read (mid-list: data taking off)."""

    def __init__(self, device: SimulatedVmUsb) -> None:
        super().__init__(0x10)
        self.device = device

    def read8(self, offset: int) -> int:
        if offset == 0:
            self.device.irq(2, 0x42)
        return super().read8(offset)


def test_an_irq_raised_while_data_taking_is_paused_is_delivered(crate: Crate) -> None:
    crate.device.map("doorbell", _Doorbell(crate.device), 0x8000, 16)
    with (
        crate.window(size=0x10, base=0x8000, am=A16) as bell,
        crate.line(2, 0x42, reads=[(bell, 0x04, 8)]) as line,
    ):
        bell.write8(0x04, 0x99)
        assert bell.read8(0) == 0  # the IRQ is raised during this list
        assert line.wait(WAIT) == 1
        assert line.prefetched() == (0x99,)
        assert crate.device.pending_irqs == {}


def test_two_lines_share_data_taking(crate: Crate) -> None:
    with crate.reg_window() as regs:
        two = crate.line(2, 0x42, reads=[(regs, 0, 8)])
        three = crate.line(3, 0x60)  # no reads: found by backend alone
        assert three._bridge is regs.bridge
        crate.device.irq(3, 0x60)
        assert three.wait(WAIT) == 1
        assert three.prefetched() == ()
        waiter = _Waiter(two)
        two.close()
        assert waiter.ended(LineClosed)
        assert crate.device.daq_running  # level 3 is still armed
        crate.device.irq(3, 0x60)
        assert three.wait(WAIT) == 1
        three.close()
        assert not crate.device.daq_running
        with pytest.raises(BusError, match="is armed"), crate.line(2, 0x42), crate.line(2, 0x42):
            pass


def test_line_refuses_windows_of_two_bridges(crate: Crate) -> None:
    other, _, _ = _crate("VM0002")
    crate.backend.add(other)
    try:
        with (
            crate.window(serial="VM0001") as one,
            crate.window(serial="VM0002", size=REG_SIZE, base=REG_BASE, am=A16) as two,
        ):
            with pytest.raises(ValueError, match="one VM-USB"):
                crate.line(2, 0x42, reads=[(one, 0, 8), (two, 0, 8)])
            with pytest.raises(ValueError, match="vmusb windows only"):
                crate.line(2, 0x42, reads=[(crate.memory, 0, 8)])
            with pytest.raises(BusError):
                crate.line(2, 0x42, reads=[(one, 1, 16)])  # misaligned: refused before arming
            with pytest.raises(ValueError):
                crate.line(8, 0x42)
        assert other.violations == []
    finally:
        other.close()


class _Waiter:
    """A thread blocked in ``line.wait()``; records what ended it."""

    def __init__(self, line: VmUsbLine) -> None:
        self.line = line
        self.outcome: object = None
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            # an interrupt raised before the test acted may reach a late thread first: what
            # ends the waiting is what the test judges
            while (count := self.line.wait(WAIT)) > 0:
                self.outcome = count
            self.outcome = count
        except Exception as exc:
            self.outcome = exc
        self._done.set()

    def ended(self, kind: type[BaseException]) -> bool:
        assert self._done.wait(WAIT), "the waiter is still blocked"
        self._thread.join(WAIT)
        assert isinstance(self.outcome, kind), f"the wait ended with {self.outcome!r}"
        return True


def test_unplugging_fails_accesses_and_suspends_lines(crate: Crate) -> None:
    with crate.reg_window() as regs:
        line = crate.line(2, 0x42, reads=[(regs, 0, 8)])
        waiter = _Waiter(line)
        crate.device.unplug()
        assert waiter.ended(BusError)  # told the target is gone; the line stays for a re-link
        assert not line.closed
        with pytest.raises(BusError, match="VM0001") as caught:
            regs.read8(0)
        assert caught.value.errno == errno.ENODEV
        with pytest.raises(BusError, match="VM0001 is gone"):
            line.wait(0)
        line.close()
        assert not regs.bridge.alive and regs.bridge.lost
    with pytest.raises(BusError):  # gone from the bus: nothing to find
        crate.window()


def test_a_bus_error_inside_the_irq_stack_brings_no_values(crate: Crate) -> None:
    with (
        crate.reg_window() as regs,
        crate.line(2, 0x42, reads=[(regs, 0, 8), (regs, 2, 16)]) as line,
    ):
        crate.device.bus_error_at(REG_BASE + 2)
        crate.device.irq(2, 0x42)
        assert line.wait(WAIT) == 1
        assert line.prefetched() is None  # a short event: the routine reads the registers itself
        crate.device.bus_error_at(None)
        crate.regs.write16(2, 0x0102)
        crate.device.irq(2, 0x42)
        assert line.wait(WAIT) == 1
        assert line.prefetched() == (crate.regs.read8(0), 0x0102)
        assert regs.bridge.stats.events == 2
