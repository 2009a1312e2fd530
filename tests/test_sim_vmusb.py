"""SimulatedVmUsb through real pyusb: descriptors, immediate lists, stacks and IRQ buffers, audit.

Packets are built here from :mod:`regs.vmusb` alone (not from the driver), so these tests pin the
wire format the driver and the simulated device share.
"""

from __future__ import annotations

import errno
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import usb.core
import usb.util

from biris_hw.bus.memory import MemoryWindow
from regs.vmusb import (
    ACTION_REGISTER,
    ADDR_NOT_LWORD,
    BLOCK_COUNT_SHIFT,
    BUF_LAST,
    BUF_TERMINATOR,
    BUFFER_SINGLE_EVENT,
    EP_IN,
    EP_OUT,
    GLOBAL_ALIGN32,
    IRQ_MASK_ALL,
    IRQ_MASK_LOAD,
    MAX_LIST_LINES,
    MODE_DS0,
    MODE_DS1,
    MODE_MB,
    MODE_NW,
    MODE_SLF,
    NO_DTACK,
    PID,
    REGISTER_BLOCK,
    TA_IMMEDIATE_LIST,
    VID,
    WRITE_ACKNOWLEDGED,
    Action,
    AddressModifier,
    InternalReg,
    isv_entry,
    ta_load,
)
from sim.vmusb import SimulatedVmUsb, VmUsbBackend, VmUsbRule

AM16 = AddressModifier.A16_USER
AM24 = AddressModifier.A24_USER
AM32 = AddressModifier.A32_USER
AM32_BLT = AddressModifier.A32_USER_BLT

A16_BASE, A24_BASE, A32_BASE = 0x7600, 0x20_0000, 0x0800_0000
SIZE = 0x1000
FIRMWARE = 0x0A00_0A02
TIMEOUT_MS = 2000
"""Reads that must succeed: only reached when a test fails."""


# -- packets -------------------------------------------------------------------------------------
def immediate(*words: int) -> bytes:
    return struct.pack(f"<HI{len(words)}I", TA_IMMEDIATE_LIST, 2 * len(words) + 1, *words)


def stack_load(stack_id: int, offset: int, *words: int) -> bytes:
    return struct.pack(f"<HHH{len(words)}I", ta_load(stack_id), 2 * len(words) + 1, offset, *words)


def action(value: int) -> bytes:
    return struct.pack("<HHH", REGISTER_BLOCK, ACTION_REGISTER, value)


def rd32(am: int, a: int) -> list[int]:
    return [MODE_NW | am, a & ~3]


def rd16(am: int, a: int) -> list[int]:
    return [MODE_NW | am, (a & ~1) | ADDR_NOT_LWORD]


def rd8(am: int, a: int) -> list[int]:
    return [MODE_NW | am | (MODE_DS0 if a & 1 else MODE_DS1), (a & ~1) | ADDR_NOT_LWORD]


def wr32(am: int, a: int, v: int) -> list[int]:
    return [am, a & ~3, v]


def wr16(am: int, a: int, v: int) -> list[int]:
    return [am, (a & ~1) | ADDR_NOT_LWORD, v]


def wr8(am: int, a: int, v: int) -> list[int]:
    """A D8 write with the byte on both data lanes, as NSCLDAQ writes it."""
    return [am | (MODE_DS0 if a & 1 else MODE_DS1), (a & ~1) | ADDR_NOT_LWORD, v | v << 8]


def blt(am: int, a: int, count: int) -> list[int]:
    return [MODE_NW | am | count << BLOCK_COUNT_SHIFT, a & ~3]


def reg_rd(reg: int) -> list[int]:
    return [MODE_NW | MODE_SLF, reg]


def reg_wr(reg: int, v: int) -> list[int]:
    return [MODE_SLF, reg, v]


def u32s(data: bytes) -> list[int]:
    return list(struct.unpack(f"<{len(data) // 4}I", data))


ACK = struct.pack("<H", WRITE_ACKNOWLEDGED)
"""The answer to a list without reads whose writes were all acknowledged."""
MODE = BUFFER_SINGLE_EVENT
"""GLOBAL_MODE the fixture sets: one event per buffer (with EVENTS_PER_BUFFER 1), Align32 clear."""


# -- a crate behind pyusb ------------------------------------------------------------------------
@dataclass
class Crate:
    sim: SimulatedVmUsb
    dev: usb.core.Device
    a16: MemoryWindow
    a24: MemoryWindow
    a32: MemoryWindow

    def send(self, packet: bytes) -> None:
        assert self.dev.write(EP_OUT, packet, TIMEOUT_MS) == len(packet)

    def read(self, timeout_ms: int = TIMEOUT_MS) -> bytes:
        return bytes(self.dev.read(EP_IN, 8192, timeout_ms))

    def xfer(self, *lines: list[int]) -> bytes:
        self.send(immediate(*[w for line in lines for w in line]))
        return self.read()

    def rules(self) -> list[VmUsbRule]:
        return [v.rule for v in self.sim.violations]

    def load_irq_mask(self, mask: int) -> int:
        """Load the IRQ mask as NSCLDAQ and mvme do; FIRMWARE_ID as read during the load."""
        assert self.xfer(reg_wr(InternalReg.GLOBAL_MODE, IRQ_MASK_LOAD | mask)) == ACK
        self.send(action(Action.USB_TRIGGER))
        answer = self.xfer(
            reg_rd(InternalReg.FIRMWARE_ID),
            reg_wr(InternalReg.GLOBAL_MODE, 0),
            reg_wr(InternalReg.GLOBAL_MODE, MODE),
        )
        (shown,) = u32s(answer)
        return shown


def open_device(sim: SimulatedVmUsb, backend: VmUsbBackend | None = None) -> usb.core.Device:
    dev = usb.core.find(idVendor=VID, idProduct=PID, backend=backend or VmUsbBackend(sim))
    assert dev is not None
    dev.set_configuration(1)
    usb.util.claim_interface(dev, 0)
    return dev


@pytest.fixture
def crate(no_leaks: None) -> Iterator[Crate]:
    sim = SimulatedVmUsb(serial="VM0001", firmware_id=FIRMWARE)
    windows = [MemoryWindow(SIZE) for _ in range(3)]
    for window, base, bits in zip(
        windows, (A16_BASE, A24_BASE, A32_BASE), (16, 24, 32), strict=True
    ):
        sim.map(f"a{bits}", window, base, bits)
    dev = open_device(sim)
    c = Crate(sim, dev, *windows)
    # as the driver sets it up: one event per buffer, 8-bit interrupters, every level heard
    assert (
        c.xfer(
            reg_wr(InternalReg.GLOBAL_MODE, MODE),
            reg_wr(InternalReg.EVENTS_PER_BUFFER, 1),
            reg_wr(InternalReg.VECTOR_HIGH1, 0xFFFF_FFFF),
            reg_wr(InternalReg.VECTOR_HIGH2, 0xFFFF_FFFF),
        )
        == ACK
    )
    assert c.load_irq_mask(0) >> 24 & IRQ_MASK_ALL == 0
    sim.counters = type(sim.counters)()  # the tests count from here
    yield c
    usb.util.dispose_resources(dev)
    sim.close()
    for window in windows:
        window.close()


# -- USB identity ----------------------------------------------------------------------------------
def test_descriptors_strings_configuration_reset(crate: Crate) -> None:
    dev = crate.dev
    assert (dev.bcdUSB, dev.bDeviceClass, dev.idVendor, dev.idProduct) == (0x0200, 0, VID, PID)
    assert dev.speed == usb.util.SPEED_HIGH and dev.bus == 1 and dev.address >= 1
    assert usb.util.get_string(dev, dev.iSerialNumber) == "VM0001"
    assert usb.util.get_string(dev, dev.iManufacturer) == "Wiener/JTEC"
    assert usb.util.get_string(dev, dev.iProduct) == "VM-USB"
    assert dev.langids == (0x0409,)
    assert dev.bNumConfigurations == 1
    cfg = dev.get_active_configuration()
    assert cfg.bConfigurationValue == 1 and cfg.bNumInterfaces == 1
    intf = cfg[(0, 0)]
    assert intf.bInterfaceNumber == 0 and intf.bNumEndpoints == 2
    eps = {ep.bEndpointAddress: ep for ep in intf}
    assert set(eps) == {EP_OUT, EP_IN}
    for ep in eps.values():
        assert usb.util.endpoint_type(ep.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK
        assert ep.wMaxPacketSize == 512
    raw = dev.ctrl_transfer(0x80, 6, 0x0200, 0, 64)  # the configuration descriptor, whole
    assert len(raw) == 32 and raw[2] == 32 and raw[9 + 5] == 0xFF
    assert str(dev).startswith("DEVICE ID 16dc:000b")
    with pytest.raises(usb.core.USBError) as stall:
        dev.ctrl_transfer(0xC0, 0x42, 0, 0, 4)  # no vendor requests
    assert stall.value.errno == errno.EPIPE
    crate.send(action(Action.START_DAQ))
    crate.send(action(0))
    crate.sim.wait_idle()
    assert crate.sim.queued_in == 1  # the BUF_LAST buffer
    dev.reset()  # the endpoint FIFOs are flushed, registers stay
    assert crate.sim.queued_in == 0 and crate.sim.counters.usb_resets == 1
    assert crate.xfer(reg_rd(InternalReg.GLOBAL_MODE)) == struct.pack("<I", MODE)
    assert crate.sim.violations == []


def test_find_all_lists_devices_by_serial(no_leaks: None) -> None:
    first, second, third = (SimulatedVmUsb(serial=f"VM000{i}") for i in (1, 2, 3))
    try:
        backend = VmUsbBackend(first)
        backend.add(second)
        devices = list(usb.core.find(find_all=True, idVendor=VID, idProduct=PID, backend=backend))
        assert sorted(usb.util.get_string(d, d.iSerialNumber) for d in devices) == [
            "VM0001",
            "VM0002",
        ]
        assert len({(d.bus, d.address) for d in devices}) == 2
        backend.add(third)
        second.unplug()
        serials = [
            d.serial_number
            for d in usb.core.find(find_all=True, idVendor=VID, idProduct=PID, backend=backend)
        ]
        assert serials == ["VM0001", "VM0003"]
        for d in devices:
            usb.util.dispose_resources(d)
    finally:
        for sim in (first, second, third):
            sim.close()


# -- immediate lists -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("am", "base", "attr"),
    [(AM16, A16_BASE, "a16"), (AM24, A24_BASE, "a24"), (AM32, A32_BASE, "a32")],
)
def test_single_cycles_big_endian_and_byte_lanes(
    crate: Crate, am: int, base: int, attr: str
) -> None:
    mem: MemoryWindow = getattr(crate, attr)
    mem.write(0x40, bytes([0x12, 0x34, 0x56, 0x78]))
    answer = crate.xfer(
        rd32(am, base + 0x40),
        rd16(am, base + 0x40),
        rd16(am, base + 0x42),
        rd8(am, base + 0x40),
        rd8(am, base + 0x41),
        rd8(am, base + 0x43),
    )
    # 16-bit alignment: a u16 per D16 and D8 read (the byte in the low bits), a u32 per D32
    assert struct.unpack("<I5H", answer) == (0x1234_5678, 0x1234, 0x5678, 0x12, 0x34, 0x78)
    assert (
        crate.xfer(
            wr32(am, base + 0x80, 0xDEAD_BEEF),
            wr16(am, base + 0x86, 0xCAFE),
            wr8(am, base + 0x88, 0xA1),
            wr8(am, base + 0x8B, 0xB2),
        )
        == ACK
    )  # not zero: every write was acknowledged
    assert mem.read(0x80, 12) == bytes.fromhex("DEADBEEF 0000CAFE A10000B2")
    c = crate.sim.counters
    assert (c.immediate_lists, c.list_lines) == (2, 6 + 4)
    # Align32: D8 and D16 reads answer a u32, and so does a write list
    crate.xfer(reg_wr(InternalReg.GLOBAL_MODE, MODE | GLOBAL_ALIGN32))
    assert u32s(crate.xfer(rd16(am, base + 0x40), rd8(am, base + 0x41))) == [0x1234, 0x34]
    assert crate.xfer(wr16(am, base + 0x86, 1)) == struct.pack("<I", WRITE_ACKNOWLEDGED)
    assert crate.sim.violations == []


def test_block_read(crate: Crate) -> None:
    crate.a32.write(0x100, bytes(range(16)))
    answer = crate.xfer(blt(AM32_BLT, A32_BASE + 0x100, 4), rd32(AM32, A32_BASE + 0x104))
    assert u32s(answer) == [0x0001_0203, 0x0405_0607, 0x0809_0A0B, 0x0C0D_0E0F, 0x0405_0607]
    # mvme's escape: a count field of 0xFF, the count in the next word
    crate.a32.write(0, bytes((i * 3) & 0xFF for i in range(SIZE)))
    escaped = [MODE_NW | AM32_BLT | 0xFF << BLOCK_COUNT_SHIFT, 600, A32_BASE]
    words = [crate.a32.read32(4 * i) for i in range(600)]
    assert u32s(crate.xfer(escaped, rd32(AM32, A32_BASE))) == [*words, words[0]]
    assert crate.sim.violations == []


def test_internal_registers(crate: Crate) -> None:
    isv = isv_entry(0x41, 3, 2) | isv_entry(0x42, 2, 3) << 16
    answer = crate.xfer(
        reg_rd(InternalReg.FIRMWARE_ID),
        reg_wr(InternalReg.ISV12, isv),
        reg_rd(InternalReg.ISV12),
        reg_rd(InternalReg.GLOBAL_MODE),
    )
    assert u32s(answer) == [FIRMWARE, isv, MODE]
    assert crate.sim.register(InternalReg.ISV12) == isv


def test_a_bus_error_is_a_zero_acknowledgement_or_a_short_answer(crate: Crate) -> None:
    # a write list: 0 when a write got no DTACK (mvme "No DTACK on write", NSCLDAQ -3), and
    # the list stops there
    answer = crate.xfer(
        wr32(AM32, A32_BASE, 0x1111_1111),
        wr32(AM24, 0x00F0_0000, 5),  # no A24 slave there
        wr32(AM32, A32_BASE + 4, 0x2222_2222),
    )
    assert answer == struct.pack("<H", NO_DTACK)
    assert crate.a32.read32(0) == 0x1111_1111 and crate.a32.read32(4) == 0  # stopped at line 1
    # a read list: the data read before a single cycle's bus error, and no more
    crate.a32.write32(0x10, 0xAABB_CCDD)
    answer = crate.xfer(rd32(AM32, A32_BASE + 0x10), rd16(AM24, 0x00F0_0000), rd32(AM32, A32_BASE))
    assert u32s(answer) == [0xAABB_CCDD]
    # the right address in the wrong address space is no slave either: an empty answer
    assert crate.xfer(rd16(AM16, A24_BASE & 0xFFFF)) == b""
    # a block read that runs off the end of a slave ends short, and the list goes on
    answer = crate.xfer(blt(AM32_BLT, A32_BASE + SIZE - 8, 3), rd32(AM32, A32_BASE + 0x10))
    assert u32s(answer) == [0, 0, 0xAABB_CCDD]
    crate.sim.bus_error_at(A16_BASE + 0x11)
    assert crate.xfer(rd8(AM16, A16_BASE + 0x10), rd8(AM16, A16_BASE + 0x11)) == b"\0\0"
    assert crate.xfer(rd32(AM16, A16_BASE + 0x10)) == b""
    assert crate.xfer(wr8(AM16, A16_BASE + 0x11, 1)) == struct.pack("<H", NO_DTACK)
    crate.sim.bus_error_at(None)
    assert len(crate.xfer(rd32(AM16, A16_BASE + 0x10))) == 4
    assert crate.sim.counters.bus_errors == 7
    assert crate.sim.violations == []  # a bus error is an answer, not misuse


def test_partial_reads_keep_the_rest(crate: Crate) -> None:
    crate.a32.write(0, bytes(range(12)))
    crate.send(immediate(*blt(AM32_BLT, A32_BASE, 3)))
    first = bytes(crate.dev.read(EP_IN, 5, TIMEOUT_MS))
    assert first + crate.read() == bytes([3, 2, 1, 0, 7, 6, 5, 4, 11, 10, 9, 8])
    assert crate.sim.counters.in_transfers == 2


# -- data taking -----------------------------------------------------------------------------------
def _event(stack_id: int, values: list[int]) -> bytes:
    """An event of u32 values: its header (stack id, length in 16-bit units) and the data."""
    return struct.pack(f"<H{len(values)}I", stack_id << 13 | 2 * len(values), *values)


def _buffer(*events: bytes, last: bool = False) -> bytes:
    """A data-taking buffer: header, events, two terminators."""
    header = (BUF_LAST if last else 0) | len(events)
    return b"".join([struct.pack("<H", header), *events, struct.pack("<HH", *[BUF_TERMINATOR] * 2)])


def _event_buffer(stack_id: int, values: list[int]) -> bytes:
    return _buffer(_event(stack_id, values))


LAST = _buffer(last=True)


def _arm(crate: Crate, level: int = 3, vector: int = 0x41, stack_id: int = 2) -> None:
    crate.send(stack_load(stack_id, 0x10, *rd32(AM32, A32_BASE), *blt(AM32_BLT, A32_BASE + 8, 2)))
    assert crate.xfer(reg_wr(InternalReg.ISV12, isv_entry(vector, level, stack_id))) == ACK


def test_irq_runs_the_stack_one_buffer_per_event(crate: Crate) -> None:
    _arm(crate)
    assert crate.sim.stack(2) == (0x10, (*rd32(AM32, A32_BASE), *blt(AM32_BLT, A32_BASE + 8, 2)))
    crate.a32.write32(0, 0xA0A0_0001)
    crate.a32.write(8, bytes.fromhex("0102030405060708"))
    crate.send(action(Action.START_DAQ))
    crate.sim.irq(3, 0x41, count=2)
    expected = _event_buffer(2, [0xA0A0_0001, 0x0102_0304, 0x0506_0708])
    assert crate.read() == expected and crate.read() == expected
    crate.send(action(0))
    assert crate.read() == LAST
    c = crate.sim.counters
    assert (c.irq_events, c.buffers, c.daq_starts, c.daq_stops, c.stack_loads) == (2, 3, 1, 1, 1)
    assert not crate.sim.daq_running
    assert crate.sim.violations == []


def test_irq_while_stopped_is_pending_until_start(crate: Crate) -> None:
    _arm(crate)
    crate.sim.irq(3, 0x41)
    crate.sim.irq(3, 0x41, count=2)
    assert crate.sim.pending_irqs == {(3, 0x41): 3}
    assert crate.sim.queued_in == 0
    crate.a32.write32(0, 7)  # the stack reads the slave when it runs, at START_DAQ
    crate.send(action(Action.START_DAQ))
    for _ in range(3):
        assert crate.read() == _event_buffer(2, [7, 0, 0])
    assert crate.sim.pending_irqs == {}
    crate.send(action(0))
    assert crate.read() == LAST
    assert crate.sim.violations == []


def test_clear_and_sys_reset(crate: Crate) -> None:
    _arm(crate)
    crate.send(action(Action.START_DAQ))
    crate.sim.irq(3, 0x41, count=2)
    assert crate.sim.wait_idle()
    assert crate.sim.queued_in == 2
    crate.send(action(Action.START_DAQ | Action.CLEAR))  # keeps taking data
    assert crate.sim.queued_in == 0 and crate.sim.daq_running
    crate.send(action(0))
    assert crate.read() == LAST  # nothing owed before it any more
    crate.send(action(Action.SYS_RESET))
    assert crate.sim.stack(2) is None
    assert crate.sim.register(InternalReg.ISV12) == 0
    assert crate.sim.register(InternalReg.FIRMWARE_ID) == FIRMWARE
    assert crate.sim.register(InternalReg.GLOBAL_MODE) == 0
    assert crate.sim.irq_mask == IRQ_MASK_ALL  # power-on: every level ignored
    assert crate.sim.violations == []


def test_bus_error_in_a_stack_ends_the_event(crate: Crate) -> None:
    _arm(crate)
    crate.a32.write32(0, 5)
    crate.a32.write32(8, 6)
    crate.sim.bus_error_at(A32_BASE + 12)  # inside the block read, the stack's second line
    crate.send(action(Action.START_DAQ))
    crate.sim.irq(3, 0x41)
    assert crate.read() == _event_buffer(2, [5, 6])  # a short event: the block ended short
    crate.send(action(Action.SYS_RESET))  # stops data taking without a last buffer
    assert not crate.sim.daq_running and crate.sim.queued_in == 0
    assert crate.sim.counters.bus_errors == 1
    assert crate.sim.violations == []


# -- the audit -------------------------------------------------------------------------------------
def test_list_and_load_refused_while_daq_runs(crate: Crate) -> None:
    _arm(crate)
    crate.send(action(Action.START_DAQ))
    crate.send(immediate(*reg_rd(InternalReg.FIRMWARE_ID)))
    crate.send(stack_load(3, 0x40, *rd32(AM32, A32_BASE)))
    assert crate.rules() == [VmUsbRule.LIST_WHILE_DAQ, VmUsbRule.LOAD_WHILE_DAQ]
    assert "internal register" in crate.sim.violations[0].detail
    assert crate.sim.stack(3) is None
    crate.send(action(0))
    assert crate.read() == LAST  # the refused list left no answer
    assert crate.sim.queued_in == 0


def test_unread_answer_is_dropped(crate: Crate) -> None:
    crate.send(immediate(*reg_rd(InternalReg.FIRMWARE_ID)))
    crate.send(immediate(*reg_rd(InternalReg.GLOBAL_MODE)))
    assert crate.read() == struct.pack("<I", MODE)
    assert crate.rules() == [VmUsbRule.ANSWER_NOT_READ]


BAD_PACKETS = {
    "empty": b"",
    "odd length": immediate(*rd32(AM32, A32_BASE)) + b"\0",
    "unknown TA": struct.pack("<HHH", 0x0040, 0, 0),
    "n_shorts mismatch": struct.pack("<HI2I", TA_IMMEDIATE_LIST, 7, *rd32(AM32, A32_BASE)),
    "truncated line": immediate(AM32, A32_BASE),
    "too many lines": immediate(*(rd32(AM32, A32_BASE) * (MAX_LIST_LINES + 1))),
    "block count 0": immediate(*blt(AM32_BLT, A32_BASE, 0)),
    "escaped count 0": immediate(MODE_NW | AM32_BLT | 0xFF << BLOCK_COUNT_SHIFT, 0, A32_BASE),
    "count 255 without its word": immediate(*blt(AM32_BLT, A32_BASE, 255)),
    "multi-block": immediate(MODE_NW | AM32_BLT | MODE_MB | 64 << BLOCK_COUNT_SHIFT, 2, A32_BASE),
    "count on non-BLT AM": immediate(*blt(AM32, A32_BASE, 2)),
    "unknown AM": immediate(*rd32(0x08, A32_BASE)),  # MBLT64 is not supported
    "misaligned D32": immediate(*[MODE_NW | AM32, A32_BASE + 2]),
    "misaligned BLT": immediate(*[MODE_NW | AM32_BLT | 1 << BLOCK_COUNT_SHIFT, A32_BASE + 2]),
    "address beyond A16": immediate(*rd16(AM16, 0x1_0000)),
    "D8 data too wide": immediate(*[AM16 | MODE_DS1, A16_BASE | 1, 0x1_0000]),
    "both strobes": immediate(*[MODE_NW | AM16 | MODE_DS0 | MODE_DS1, A16_BASE | 1]),
    "unknown register": immediate(*reg_rd(0x7C)),
    "register block": struct.pack("<HHH", REGISTER_BLOCK, 3, 0),
    "action bits": action(0x80),
    "load n_shorts": struct.pack("<HHH2I", ta_load(2), 1, 0, *rd32(AM32, A32_BASE)),
}


@pytest.mark.parametrize("packet", BAD_PACKETS.values(), ids=BAD_PACKETS.keys())
def test_malformed_packets_are_ignored(crate: Crate, packet: bytes) -> None:
    crate.send(packet)
    assert crate.rules() == [VmUsbRule.MALFORMED_PACKET]
    assert crate.sim.queued_in == 0  # no answer: the host times out
    assert crate.sim.counters.immediate_lists == 0


def test_start_without_stack_and_unserviced_irqs(crate: Crate) -> None:
    crate.xfer(reg_wr(InternalReg.ISV34, isv_entry(0x10, 5, 6)))
    crate.sim.irq(4, 0x99)  # no entry, while stopped: dropped, not pending
    assert crate.sim.pending_irqs == {}
    crate.send(action(Action.START_DAQ))
    crate.sim.irq(2, 0x10)  # right vector, wrong level
    crate.sim.irq(5, 0x10)  # serviced by a stack never loaded: an empty event
    assert crate.read() == _event_buffer(6, [])
    crate.send(action(0))
    assert crate.read() == LAST
    assert crate.rules() == [
        VmUsbRule.IRQ_UNSERVICED,
        VmUsbRule.START_WITHOUT_STACK,
        VmUsbRule.IRQ_UNSERVICED,
    ]
    assert crate.sim.violations[1].registers == {"entry": 2, "stack": 6}


def test_register_rules(crate: Crate) -> None:
    answer = crate.xfer(reg_wr(InternalReg.FIRMWARE_ID, 0), reg_rd(InternalReg.FIRMWARE_ID))
    assert u32s(answer) == [FIRMWARE]
    crate.send(stack_load(1, 0, *rd32(AM32, A32_BASE), *rd32(AM32, A32_BASE)))
    crate.send(stack_load(2, 3, *rd32(AM32, A32_BASE)))  # words 3..4 over stack 1's 0..3
    assert crate.rules() == [VmUsbRule.WRITE_TO_FIRMWARE_ID, VmUsbRule.STACK_OVERLAP]


def test_wrong_endpoints(crate: Crate) -> None:
    with pytest.raises(usb.core.USBError):
        crate.dev.write(EP_IN, b"\0\0", TIMEOUT_MS)
    with pytest.raises(usb.core.USBError):
        crate.dev.read(EP_OUT, 64, TIMEOUT_MS)
    assert crate.rules() == [VmUsbRule.WRONG_ENDPOINT] * 2
    assert crate.sim.counters.out_transfers == 0


# -- unplug, timeouts, timing ----------------------------------------------------------------------
def test_read_timeout(crate: Crate) -> None:
    with pytest.raises(usb.core.USBTimeoutError) as exc:
        crate.dev.read(EP_IN, 64, 5)
    assert exc.value.errno == errno.ETIMEDOUT and exc.value.backend_error_code == -7


def test_unplug_wakes_a_blocked_read(crate: Crate) -> None:
    errors: list[BaseException] = []

    def reader() -> None:
        try:
            crate.dev.read(EP_IN, 64, 0)  # forever, as libusb
        except usb.core.USBError as exc:
            errors.append(exc)

    thread = threading.Thread(target=reader)
    thread.start()
    crate.sim.unplug()
    thread.join(5.0)
    assert not thread.is_alive()
    with pytest.raises(usb.core.USBError) as exc:
        crate.send(action(0))
    assert exc.value.errno == errno.ENODEV
    assert len(errors) == 1 and isinstance(errors[0], usb.core.USBError)
    assert errors[0].errno == errno.ENODEV
    crate.sim.irq(3, 0x41)  # nothing left to service it, nothing recorded
    assert crate.sim.violations == []


def test_timing_model(no_leaks: None) -> None:
    latency, bandwidth, scale = 1e-3, 1e5, 50.0
    sim = SimulatedVmUsb(
        clock=lambda: 42.0,
        time_scale=scale,
        transfer_latency_s=latency,
        bandwidth_bytes_per_s=bandwidth,
    )
    window = MemoryWindow(SIZE)
    sim.map("a32", window, A32_BASE, 32)
    dev = open_device(sim)
    try:
        packet = immediate(*blt(AM32_BLT, A32_BASE, 250))  # 14 bytes out, 1000 in
        t0 = time.monotonic()
        dev.write(EP_OUT, packet, TIMEOUT_MS)
        assert len(dev.read(EP_IN, 8192, TIMEOUT_MS)) == 1000
        elapsed = time.monotonic() - t0
        modelled = (latency + 14 / bandwidth) + (latency + 1000 / bandwidth)
        assert sim.modelled_busy_s == pytest.approx(modelled, rel=1e-12)
        assert elapsed >= modelled / scale * 0.99
        c = sim.counters
        assert (c.out_transfers, c.in_transfers, c.bytes_out, c.bytes_in) == (1, 1, 14, 1000)
        dev.write(EP_OUT, b"\x01", TIMEOUT_MS)
        assert [(v.time, v.rule) for v in sim.violations] == [(42.0, VmUsbRule.MALFORMED_PACKET)]
        assert sim.modelled_busy_s == pytest.approx(modelled + latency + 1 / bandwidth)
    finally:
        usb.util.dispose_resources(dev)
        sim.close()
        window.close()
