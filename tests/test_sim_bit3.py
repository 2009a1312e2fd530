"""Bit3Coupler: the local node registers as the driver sees them through a DeviceWindow."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from biris_hw.bus.base import BusWindow
from biris_hw.irq.eventfd import EventFdLine
from regs.bit3 import BIT3_SPACE, Bit3Reg, LocalCommand, LocalIntControl, LocalStatus
from sim.audit import Audit, Rule
from sim.bit3 import CINT2, REMOTE_CARD_ID_VALUE, Bit3Coupler
from sim.clock import SimClock
from sim.irqgate import InterruptGate

WAIT = 2.0


@dataclass
class Node:
    coupler: Bit3Coupler
    window: BusWindow
    line: EventFdLine
    gate: InterruptGate
    audit: Audit


@pytest.fixture
def node() -> Iterator[Node]:
    clock = SimClock(time_scale=20.0)
    line = EventFdLine()
    gate = InterruptGate(line.trigger, clock)
    audit = Audit(clock)
    coupler = Bit3Coupler(gate, audit=audit)
    window = coupler.window()
    yield Node(coupler, window, line, gate, audit)
    window.close()
    gate.close()
    line.close()


def test_power_up_values(node: Node) -> None:
    w = node.window
    assert w.size == BIT3_SPACE
    assert w.read8(Bit3Reg.LOCAL_STATUS) == LocalStatus.CARD_READY
    assert w.read8(Bit3Reg.LOCAL_INT_CONTROL) == 0  # error interrupts off until the driver asks
    assert w.read8(Bit3Reg.LEVEL2_VECTOR) == 0
    assert w.read8(Bit3Reg.LOCAL_INT_STATUS) == 0
    assert w.read8(Bit3Reg.REMOTE_CARD_ID) == REMOTE_CARD_ID_VALUE


def test_errors_are_sticky_until_clr_error(node: Node) -> None:
    w = node.window
    node.coupler.parity_error()
    node.coupler.bus_error()
    both = LocalStatus.PARITY_ERROR | LocalStatus.REMOTE_BUS_ERROR | LocalStatus.CARD_READY
    assert w.read8(Bit3Reg.LOCAL_STATUS) == both
    assert w.read8(Bit3Reg.LOCAL_STATUS) == both  # reading clears nothing
    w.write8(Bit3Reg.LOCAL_COMMAND, LocalCommand.CLR_PR_INT)  # other one-shots: no effect
    assert w.read8(Bit3Reg.LOCAL_STATUS) == both
    w.write8(Bit3Reg.LOCAL_COMMAND, LocalCommand.CLR_ERROR)
    assert w.read8(Bit3Reg.LOCAL_STATUS) == LocalStatus.CARD_READY
    assert w.read8(Bit3Reg.LOCAL_COMMAND) == 0  # one-shot bits read back as 0


def test_no_error_interrupt_unless_enabled(node: Node) -> None:
    node.coupler.parity_error()
    node.coupler.bus_error()
    assert node.line.wait(0.0) == 0
    assert node.gate.raised == 0
    assert node.coupler.error_interrupts == 0


def test_error_interrupts_on_level_2_when_enabled(node: Node) -> None:
    w = node.window
    w.write8(Bit3Reg.LOCAL_INT_CONTROL, LocalIntControl.ERROR_INT_ENABLE)
    assert w.read8(Bit3Reg.LOCAL_INT_CONTROL) == LocalIntControl.ERROR_INT_ENABLE
    node.coupler.parity_error()
    assert node.line.wait(WAIT) == 1
    assert node.gate.last_source == "perr"
    node.coupler.bus_error()
    assert node.line.wait(WAIT) == 1
    assert node.gate.last_source == "berr"
    assert node.coupler.error_interrupts == 2
    assert w.read8(Bit3Reg.LOCAL_STATUS) & LocalStatus.REMOTE_BUS_ERROR


def test_int_pending_bit_is_not_writable(node: Node) -> None:
    node.window.write8(Bit3Reg.LOCAL_INT_CONTROL, 0xFF)
    assert node.window.read8(Bit3Reg.LOCAL_INT_CONTROL) == 0x7F


def test_writes_to_read_only_registers_are_ignored_and_recorded(node: Node) -> None:
    w = node.window
    w.write8(Bit3Reg.LOCAL_STATUS, 0x00)
    w.write8(Bit3Reg.REMOTE_CARD_ID, 0x99)
    assert w.read8(Bit3Reg.LOCAL_STATUS) == LocalStatus.CARD_READY
    assert w.read8(Bit3Reg.REMOTE_CARD_ID) == REMOTE_CARD_ID_VALUE
    violations = node.audit.violations
    assert [v.rule for v in violations] == [Rule.WRITE_TO_READ_ONLY] * 2
    assert violations[0].registers == {"offset": Bit3Reg.LOCAL_STATUS, "value": 0}
    assert "LOCAL_STATUS" in violations[0].detail


def test_read_write_registers_do_not_audit(node: Node) -> None:
    w = node.window
    w.write8(Bit3Reg.LEVEL2_VECTOR, 0x42)
    w.write8(Bit3Reg.REMOTE_PAGE_LO, 0x12)
    w.write8(Bit3Reg.REMOTE_COMMAND_1, 0x02)
    assert w.read8(Bit3Reg.LEVEL2_VECTOR) == 0x42
    assert w.read8(Bit3Reg.REMOTE_PAGE_LO) == 0x12
    assert w.read16(Bit3Reg.REMOTE_IACK) == 0x42  # the vector of every BIRIS interrupt
    assert node.audit.violations == []


def test_cint2_shows_when_the_last_level_2_interrupt_was_biris(node: Node) -> None:
    w = node.window
    node.gate.raise_irq("data")
    assert w.read8(Bit3Reg.LOCAL_INT_STATUS) == CINT2
    w.write8(Bit3Reg.LOCAL_INT_CONTROL, LocalIntControl.ERROR_INT_ENABLE)
    node.coupler.parity_error()
    assert w.read8(Bit3Reg.LOCAL_INT_STATUS) == 0
    node.gate.raise_irq("cmd")
    assert w.read8(Bit3Reg.LOCAL_INT_STATUS) == CINT2


def test_snapshot_matches_reads_and_changes_nothing(node: Node) -> None:
    node.window.write8(Bit3Reg.LEVEL2_VECTOR, 0x40)
    node.coupler.bus_error()
    snap = node.coupler.snapshot()
    assert len(snap) == BIT3_SPACE
    assert snap == node.coupler.snapshot()
    assert snap == node.window.read(0, BIT3_SPACE)
    assert snap[Bit3Reg.LOCAL_STATUS] & LocalStatus.REMOTE_BUS_ERROR
    assert node.coupler.status == snap[Bit3Reg.LOCAL_STATUS]
