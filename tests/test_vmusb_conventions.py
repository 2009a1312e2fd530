"""The VM-USB conventions of the public drivers (issue 26), each from both sides.

For each convention :mod:`regs.vmusb` names the source of: the simulated bridge behaves as the
source says a real one does and refuses (records) what a real one would not do, with packets
built here by hand, so a driver that breaks the convention fails; and our driver keeps it.
The sources: NSCLDAQ's ``CVMUSB*.cpp``, mesytec mvme's ``vmusb.cpp`` / ``vmusb_constants.h`` /
``CVMUSBReadoutList.cpp``, Wiener's manual where it was read.
"""

from __future__ import annotations

import errno
import struct
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import usb.core
import usb.util

from biris_hw.bus import BusError
from biris_hw.bus import vmusb as driver
from biris_hw.bus.memory import MemoryWindow
from biris_hw.bus.vmusb import VmeList, VmUsbBridge, VmUsbWindow
from biris_hw.irq.vmusb import VmUsbLine
from regs.vmusb import (
    BLOCK_COUNT_ESCAPE,
    BLOCK_COUNT_SHIFT,
    BLT_BOUNDARY,
    BUF_LAST,
    BUF_TERMINATOR,
    BUFFER_LENGTH_MASK,
    BUFFER_SINGLE_EVENT,
    FID_IRQ_MASK_SHIFT,
    GLOBAL_ALIGN32,
    IRQ_MASK_ALL,
    MODE_NW,
    NO_DTACK,
    WRITE_ACKNOWLEDGED,
    Action,
    AddressModifier,
    InternalReg,
    isv_entry,
    vector_high_slot,
)
from sim.vmusb import SimulatedVmUsb, VmUsbBackend, VmUsbRule
from tests.conftest import WAIT
from tests.test_sim_vmusb import (
    ACK,
    Crate,
    action,
    blt,
    open_device,
    rd32,
    reg_rd,
    reg_wr,
    stack_load,
    wr8,
    wr32,
)

AM16 = int(AddressModifier.A16_USER)
AM32 = int(AddressModifier.A32_USER)
AM32_BLT = int(AddressModifier.A32_USER_BLT)
A16_BASE, A32_BASE = 0x7600, 0x0800_0000
SIZE = 0x1000
LEVEL, VECTOR, STACK = 3, 0x41, 2
"""The IRQ the raw tests arm: ISV entry 0 (stack 2, as the driver numbers them)."""


# -- a bridge at power-on, reached by hand -------------------------------------------------------
@pytest.fixture
def raw(no_leaks: None) -> Iterator[Crate]:
    """A simulated VM-USB as it powers on (nothing written), A16/A24/A32 memory behind it."""
    sim = SimulatedVmUsb(serial="VM0026")
    windows = [MemoryWindow(SIZE) for _ in range(3)]
    for window, base, bits in zip(
        windows, (A16_BASE, 0x20_0000, A32_BASE), (16, 24, 32), strict=True
    ):
        sim.map(f"a{bits}", window, base, bits)
    dev = open_device(sim)
    try:
        yield Crate(sim, dev, *windows)
    finally:
        usb.util.dispose_resources(dev)
        sim.close()
        for window in windows:
            window.close()


def _arm(crate: Crate, *, vector_high: int | None = 0xFF, mask: int | None = 0) -> None:
    """Load a stack reading A32 word 0, point ISV entry 0 at it; the vector high byte and the
    IRQ mask as given (None: left at power-on)."""
    crate.send(stack_load(STACK, 0, *rd32(AM32, A32_BASE)))
    lines = [reg_wr(InternalReg.ISV12, isv_entry(VECTOR, LEVEL, STACK))]
    if vector_high is not None:
        lines.append(reg_wr(InternalReg.VECTOR_HIGH1, vector_high))
    assert crate.xfer(*lines) == ACK
    if mask is not None:
        crate.load_irq_mask(mask)


def _event(value: int) -> bytes:
    return struct.pack("<HI", STACK << 13 | 2, value)


def _buffer(*events: bytes, last: bool = False) -> bytes:
    header = (BUF_LAST if last else 0) | len(events)
    return b"".join([struct.pack("<H", header), *events, struct.pack("<HH", *[BUF_TERMINATOR] * 2)])


# -- our driver on a simulated crate -------------------------------------------------------------
@dataclass
class Bench:
    device: SimulatedVmUsb
    backend: VmUsbBackend
    memory: MemoryWindow

    def window(self) -> VmUsbWindow:
        return VmUsbWindow(SIZE, base=A32_BASE, am=AM32, backend=self.backend)

    def line(self, level: int, vector: int, reads: list[tuple[VmUsbWindow, int, int]]) -> VmUsbLine:
        return VmUsbLine(level=level, vector=vector, reads=reads, backend=self.backend)


@pytest.fixture
def bench(no_leaks: None, monkeypatch: pytest.MonkeyPatch) -> Iterator[Bench]:
    monkeypatch.setattr(VmUsbBridge, "drain_timeout_s", 0.005)  # the simulation answers at once
    device = SimulatedVmUsb(serial="VM0027")
    memory = MemoryWindow(SIZE)
    memory.write(0, bytes((i * 11 + 5) & 0xFF for i in range(SIZE)))
    device.map("memory", memory, A32_BASE, 32)
    try:
        yield Bench(device, VmUsbBackend(device), memory)
    finally:
        device.close()
        memory.close()


# -- 1. the answer to a write list ---------------------------------------------------------------
def test_a_write_list_answers_zero_for_no_dtack_and_not_zero_when_acknowledged(raw: Crate) -> None:
    """mvme ``VMUSB::write16/32``: "No DTACK on write" when the answer is 0; NSCLDAQ
    ``doVMEWrite``: reply 0 is a bus error. A driver taking 0 as success misses every BERR."""
    assert raw.xfer(wr32(AM32, A32_BASE, 5)) == struct.pack("<H", WRITE_ACKNOWLEDGED)
    assert raw.xfer(wr32(AM32, A32_BASE + SIZE, 5)) == struct.pack("<H", NO_DTACK)  # no slave
    assert raw.a32.read32(0) == 5 and raw.sim.violations == []
    # the review's check (H2): as the driver decodes those answers
    lst = VmeList()
    lst.write16(0x09, 0x0800_0100, 5)
    assert lst.payload(struct.pack("<H", 0x0001)) == b""
    with pytest.raises(BusError) as caught:
        lst.payload(struct.pack("<H", 0))
    assert caught.value.errno == errno.EIO


def test_the_driver_reports_an_unacknowledged_write(bench: Bench) -> None:
    with bench.window() as window:
        window.write32(0x10, 0x0102_0304)
        assert bench.memory.read32(0x10) == 0x0102_0304
        bench.device.bus_error_at(A32_BASE + 0x20)
        with pytest.raises(BusError, match=r"no DTACK.*0x08000020") as caught:
            window.write16(0x20, 1)
        assert caught.value.errno == errno.EIO
        bench.device.bus_error_at(None)
        window.write16(0x20, 2)  # the bridge carries on
        assert bench.memory.read16(0x20) == 2
    assert bench.device.violations == []


# -- 2. interrupts not held back ---------------------------------------------------------------
def test_at_power_on_an_idle_bridge_holds_an_interrupt_until_data_taking_stops(raw: Crate) -> None:
    """GLOBAL_MODE 0: 13K-word buffers (NSCLDAQ ``bufferLen13K``); the event waits in the open
    buffer until it fills or data taking stops (mvme: leaving DAQ mode dumps the buffer)."""
    _arm(raw)
    raw.a32.write32(0, 0x1234_5678)
    raw.send(action(Action.START_DAQ))
    raw.sim.irq(LEVEL, VECTOR)
    assert raw.sim.wait_idle(WAIT)
    assert raw.sim.open_events == 1 and raw.sim.queued_in == 0  # held back
    raw.send(action(0))
    assert raw.read() == _buffer(_event(0x1234_5678), last=True)
    assert raw.sim.violations == []


@pytest.mark.parametrize(
    ("mode", "per_buffer", "irqs", "sent", "left"),
    [
        (8, 0, 21, [20], 1),  # 64 words: a header, 20 events of 3 words, two terminators
        (BUFFER_SINGLE_EVENT, 2, 5, [2, 2], 1),  # code 9: a buffer per 2 events
        (BUFFER_SINGLE_EVENT, 0, 3, [], 3),  # code 9, no count: nothing closes it
    ],
)
def test_buffer_length_codes(
    raw: Crate, mode: int, per_buffer: int, irqs: int, sent: list[int], left: int
) -> None:
    _arm(raw)
    raw.xfer(
        reg_wr(InternalReg.GLOBAL_MODE, mode), reg_wr(InternalReg.EVENTS_PER_BUFFER, per_buffer)
    )
    raw.send(action(Action.START_DAQ))
    raw.sim.irq(LEVEL, VECTOR, count=irqs)
    assert raw.sim.wait_idle(WAIT)
    assert raw.sim.queued_in == len(sent) and raw.sim.open_events == left
    for n in sent:
        assert raw.read() == _buffer(*[_event(0)] * n)
    raw.send(action(0))
    assert raw.read() == _buffer(*[_event(0)] * left, last=True)
    assert raw.sim.violations == []


def test_multi_buffer_transfers_wait_for_their_buffers_or_the_timeout(raw: Crate) -> None:
    """USB_BULK_SETUP bits 0-7: buffers per bulk transfer; bits 8-11 a timeout (NSCLDAQ's
    ``TransferSetupRegister``); both public drivers write 0."""
    _arm(raw)
    one = (InternalReg.EVENTS_PER_BUFFER, 1)
    raw.xfer(reg_wr(InternalReg.GLOBAL_MODE, BUFFER_SINGLE_EVENT), reg_wr(*one))
    raw.xfer(reg_wr(InternalReg.USB_BULK_SETUP, 2 | 15 << 8))  # two buffers, 15 s
    raw.send(action(Action.START_DAQ))
    raw.sim.irq(LEVEL, VECTOR)
    assert raw.sim.wait_idle(WAIT)
    assert raw.sim.held_buffers == 1 and raw.sim.queued_in == 0
    raw.sim.irq(LEVEL, VECTOR)
    assert raw.read() == _buffer(_event(0)) * 2  # one transfer, two buffers
    raw.sim.irq(LEVEL, VECTOR)
    assert raw.sim.wait_idle(WAIT) and raw.sim.held_buffers == 1
    raw.send(action(0))  # the last buffer takes what is held with it
    assert raw.read() == _buffer(_event(0)) + _buffer(last=True)
    assert raw.sim.violations == []


def test_a_held_multi_buffer_goes_out_at_its_timeout(no_leaks: None) -> None:
    sim = SimulatedVmUsb(serial="VM0028", time_scale=1000.0)  # 1 s of hardware time: 1 ms
    memory = MemoryWindow(SIZE)
    sim.map("a32", memory, A32_BASE, 32)
    dev = open_device(sim)
    crate = Crate(sim, dev, memory, memory, memory)
    try:
        _arm(crate)
        crate.xfer(
            reg_wr(InternalReg.GLOBAL_MODE, BUFFER_SINGLE_EVENT),
            reg_wr(InternalReg.EVENTS_PER_BUFFER, 1),
            reg_wr(InternalReg.USB_BULK_SETUP, 4 | 1 << 8),
        )
        crate.send(action(Action.START_DAQ))
        sim.irq(LEVEL, VECTOR)
        assert crate.read() == _buffer(_event(0))  # alone, once the timeout passed
        crate.send(action(0))
        assert crate.read() == _buffer(last=True)
        assert sim.violations == []
    finally:
        usb.util.dispose_resources(dev)
        sim.close()
        memory.close()


def test_the_driver_sets_one_event_per_buffer_and_interrupts_arrive_while_idle(
    bench: Bench,
) -> None:
    with bench.window() as window, bench.line(2, 0x42, [(window, 0x10, 32)]) as line:
        device = bench.device
        mode = device.register(InternalReg.GLOBAL_MODE)
        assert mode & BUFFER_LENGTH_MASK == BUFFER_SINGLE_EVENT and not mode & GLOBAL_ALIGN32
        assert device.register(InternalReg.EVENTS_PER_BUFFER) == 1
        assert device.register(InternalReg.USB_BULK_SETUP) == 0
        lists = device.counters.immediate_lists
        for _ in range(3):  # nothing but the interrupt: no list flushes it out
            device.irq(2, 0x42)
            assert line.wait(WAIT) == 1
            assert line.prefetched() == (bench.memory.read32(0x10),)
        assert device.counters.immediate_lists == lists
    assert bench.device.violations == []


def test_a_driver_left_at_13k_buffers_gets_its_interrupt_only_at_its_next_list(
    bench: Bench, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What issue 26 found: GLOBAL_MODE 0x0080 (buffer code 0) held IRQ events while idle."""
    monkeypatch.setattr(driver, "DRIVER_GLOBAL_MODE", GLOBAL_ALIGN32 & 0)  # code 0: 13K words
    with bench.window() as window, bench.line(2, 0x42, [(window, 0x10, 32)]) as line:
        bench.device.irq(2, 0x42)
        assert bench.device.wait_idle(WAIT)
        assert bench.device.open_events == 1 and line.wait(0) == 0  # held in the bridge
        window.read32(0)  # a list: data taking stops, the bridge sends what it holds
        assert line.wait(WAIT) == 1
    assert bench.device.violations == []


# -- 3. the vector high bytes --------------------------------------------------------------------
def test_an_isv_entry_needs_the_upper_vector_byte_of_its_interrupter(raw: Crate) -> None:
    """The bridge compares 16-bit vectors; an 8-bit interrupter presents 0xFF above its vector
    (NSCLDAQ ``vmusbserver`` ``writeVector``: 0xFFFFFFFF "what 8bit interrupters require")."""
    _arm(raw, vector_high=None)  # VECTOR_HIGH1 left at 0
    raw.xfer(
        reg_wr(InternalReg.GLOBAL_MODE, BUFFER_SINGLE_EVENT),
        reg_wr(InternalReg.EVENTS_PER_BUFFER, 1),
    )
    raw.send(action(Action.START_DAQ))
    raw.sim.irq(LEVEL, VECTOR)
    assert raw.sim.wait_idle(WAIT) and raw.sim.queued_in == 0 and raw.sim.open_events == 0
    assert raw.rules() == [VmUsbRule.VECTOR_HIGH_MISMATCH]
    assert raw.sim.violations[0].registers["vector_high"] == 0
    raw.sim.irq(LEVEL, VECTOR, vector_high=0x00)  # a 16-bit interrupter presenting 0x0041
    assert raw.read() == _buffer(_event(0))
    raw.send(action(0))
    assert raw.read() == _buffer(last=True)
    raw.xfer(reg_wr(InternalReg.VECTOR_HIGH1, 0xFF))  # entry 0's byte
    raw.send(action(Action.START_DAQ))
    raw.sim.irq(LEVEL, VECTOR)  # an 8-bit interrupter
    assert raw.read() == _buffer(_event(0))
    raw.send(action(0))
    assert raw.read() == _buffer(last=True)
    assert raw.rules() == [VmUsbRule.VECTOR_HIGH_MISMATCH]


def test_the_driver_writes_the_vector_high_bytes(bench: Bench) -> None:
    assert [vector_high_slot(i) for i in (0, 3, 4, 7)] == [
        (InternalReg.VECTOR_HIGH1, 0),
        (InternalReg.VECTOR_HIGH1, 24),
        (InternalReg.VECTOR_HIGH2, 0),
        (InternalReg.VECTOR_HIGH2, 24),
    ]
    with bench.window():
        for reg in (InternalReg.VECTOR_HIGH1, InternalReg.VECTOR_HIGH2):
            assert bench.device.register(reg) == 0xFFFF_FFFF
    assert bench.device.violations == []


# -- 4. block counts, D8 lanes, bus errors, the IRQ mask -----------------------------------------
def test_block_reads_never_use_255_and_never_cross_256_bytes(bench: Bench) -> None:
    """A count field of 0xFF is mvme's escape (and NSCLDAQ refuses counts above 254); a VME
    block transfer does not cross a 256-byte boundary (NSCLDAQ ``addBlockRead``)."""
    lst = VmeList()
    lst.block_read32(AM32_BLT, A32_BASE + 0x1C, 600)
    words = lst.words()
    modes, addresses = words[0::2], words[1::2]
    counts = [mode >> BLOCK_COUNT_SHIFT for mode in modes]
    assert BLOCK_COUNT_ESCAPE not in counts and sum(counts) == 600
    for count, address in zip(counts, addresses, strict=True):
        assert address // BLT_BOUNDARY == (address + 4 * count - 1) // BLT_BOUNDARY
    with bench.window() as window:
        assert window.read(0x1C, 2400) == bench.memory.read(0x1C, 2400)
    assert bench.device.violations == []


def test_a_bare_count_of_255_is_refused(raw: Crate) -> None:
    raw.send(struct.pack("<HI2I", 0x000C, 5, *blt(AM32_BLT, A32_BASE, 255)))
    assert raw.rules() == [VmUsbRule.MALFORMED_PACKET] and raw.sim.queued_in == 0
    escaped = [MODE_NW | AM32_BLT | BLOCK_COUNT_ESCAPE << BLOCK_COUNT_SHIFT, 255, A32_BASE]
    assert len(raw.xfer(escaped)) == 4 * 255  # mvme's form of the same read


def test_a_d8_write_on_one_lane_writes_the_other_lane(raw: Crate) -> None:
    """NSCLDAQ ``addWrite8`` puts the byte on D7..D0 and D15..D8: which lane the bridge drives
    is undocumented. The byte only in the low bits, at an even address: the strobed lane (D15..D8)
    carries 0."""
    raw.a16.write(0, b"\x11\x22")
    one_lane = [AM16 | 0x80, A16_BASE | 1, 0xAB]  # DS1, even byte, D7..D0 only
    assert raw.xfer(one_lane) == ACK
    assert raw.a16.read(0, 2) == b"\x00\x22"
    assert raw.rules() == [VmUsbRule.D8_ONE_LANE]
    raw.sim.clear_violations()
    assert raw.xfer(wr8(AM16, A16_BASE, 0xAB), wr8(AM16, A16_BASE + 1, 0xCD)) == ACK
    assert raw.a16.read(0, 2) == b"\xab\xcd" and raw.sim.violations == []


def test_the_driver_writes_a_byte_on_both_lanes(bench: Bench) -> None:
    lst = VmeList()
    lst.write8(0x29, 0x7600, 0xAB)
    assert lst.words()[2] == 0xABAB  # the review's check (H4)
    with bench.window() as window:
        window.write8(0x40, 0x5A)
        window.write8(0x41, 0xA5)
        window.write(0x43, b"\x77")
        assert bench.memory.read(0x40, 4) == b"\x5a\xa5" + bench.memory.read(0x42, 1) + b"\x77"
    assert bench.device.violations == []


def test_a_block_read_that_ends_short_is_a_bus_error(bench: Bench) -> None:
    """NSCLDAQ ``vmeBlockRead``: a BERR ends a block transfer with fewer words, no error code
    of its own; the driver, which asked for all of them, names the block."""
    bench.device.bus_error_at(A32_BASE + 0x48)
    with bench.window() as window:
        with pytest.raises(BusError, match=r"bus error at or before the D32 block read") as c:
            window.read(0x40, 0x20)
        assert c.value.errno == errno.EIO
        bench.device.bus_error_at(None)
        assert window.read(0x40, 0x20) == bench.memory.read(0x40, 0x20)
    assert bench.device.violations == []


def test_a_masked_level_is_not_serviced_until_the_mask_is_loaded(raw: Crate) -> None:
    """At power-on every level is ignored here (NSCLDAQ writes 0x7F at open); the mask is
    loaded through GLOBAL_MODE bit 15 and a USB trigger, and shows in FIRMWARE_ID meanwhile
    (``CVMUSB::writeIrqMask``, mvme ``VMUSB::setIrqMask``)."""
    _arm(raw, mask=None)
    assert raw.sim.irq_mask == IRQ_MASK_ALL
    raw.xfer(
        reg_wr(InternalReg.GLOBAL_MODE, BUFFER_SINGLE_EVENT),
        reg_wr(InternalReg.EVENTS_PER_BUFFER, 1),
    )
    raw.send(action(Action.START_DAQ))
    raw.sim.irq(LEVEL, VECTOR)
    assert raw.sim.wait_idle(WAIT) and raw.sim.queued_in == 0
    assert raw.rules() == [VmUsbRule.IRQ_MASKED]
    assert raw.sim.pending_irqs == {(LEVEL, VECTOR): 1}  # still on the bus
    raw.send(action(0))
    assert raw.read() == _buffer(last=True)
    shown = raw.load_irq_mask(IRQ_MASK_ALL & ~(1 << (LEVEL - 1)))
    assert shown >> FID_IRQ_MASK_SHIFT & IRQ_MASK_ALL == 0x7B
    assert raw.xfer(reg_rd(InternalReg.FIRMWARE_ID)) == struct.pack("<I", raw.sim.firmware_id)
    raw.send(action(Action.START_DAQ))  # the pending IRQ is acknowledged now
    assert raw.read() == _buffer(_event(0))
    raw.send(action(0))
    assert raw.read() == _buffer(last=True)
    assert raw.rules() == [VmUsbRule.IRQ_MASKED]


def test_the_driver_masks_every_level_it_does_not_serve(bench: Bench) -> None:
    device = bench.device
    with bench.window() as window:
        assert device.irq_mask == IRQ_MASK_ALL
        two = bench.line(2, 0x42, [(window, 0, 8)])
        assert device.irq_mask == 0x7D
        three = bench.line(3, 0x60, [])
        assert device.irq_mask == 0x79
        two.close()
        assert device.irq_mask == 0x7B
        device.irq(3, 0x60)
        assert three.wait(WAIT) == 1
        three.close()
        assert device.irq_mask == IRQ_MASK_ALL
        device.irq(2, 0x42)  # no entry, masked or not: dropped and recorded
    assert [v.rule for v in device.violations] == [VmUsbRule.IRQ_UNSERVICED]


def test_data_taking_with_align32_is_recorded(raw: Crate) -> None:
    """The manual: with Align32 every buffer header is a 32-bit word, a layout neither public
    driver reads and this simulation does not produce."""
    raw.xfer(reg_wr(InternalReg.GLOBAL_MODE, GLOBAL_ALIGN32))
    raw.send(action(Action.START_DAQ))
    raw.send(action(0))
    assert raw.read() == _buffer(last=True)
    assert raw.rules() == [VmUsbRule.ALIGN32_DATA_TAKING]
