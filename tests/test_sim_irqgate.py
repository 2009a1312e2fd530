"""InterruptGate: coalescing, dropping and spurious interrupts, seen through a real eventfd line."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest

from biris_hw.errors import LineClosed
from biris_hw.irq.eventfd import EventFdLine
from sim.clock import SimClock
from sim.irqgate import InterruptGate

WAIT = 2.0  # real seconds; only reached when something is broken


@pytest.fixture
def line() -> Iterator[EventFdLine]:
    with EventFdLine() as line:
        yield line


@pytest.fixture
def gate(line: EventFdLine) -> Iterator[InterruptGate]:
    gate = InterruptGate(line.trigger, SimClock(time_scale=20.0))
    yield gate
    gate.close()


def test_plain_delivery_one_per_interrupt(gate: InterruptGate, line: EventFdLine) -> None:
    gate.raise_irq("cmd")
    assert line.wait(WAIT) == 1
    gate.raise_irq("data")
    gate.raise_irq("data")
    assert line.wait(WAIT) == 2  # the eventfd itself merges what nobody waited for
    assert (gate.raised, gate.delivered, gate.dropped, gate.pending) == (3, 3, 0, 0)
    assert gate.raised_by("data") == 2
    assert gate.last_source == "data"


def test_coalescing_delivers_a_burst_in_one_wait(gate: InterruptGate, line: EventFdLine) -> None:
    gate.coalesce(True, burst=3, max_hold=None)
    gate.raise_irq("data")
    gate.raise_irq("data")
    assert line.wait(0.0) == 0  # held
    assert gate.pending == 2
    gate.raise_irq("cmd")
    assert line.wait(WAIT) == 3
    assert (gate.delivered, gate.pending) == (3, 0)


def test_switching_coalescing_off_flushes(gate: InterruptGate, line: EventFdLine) -> None:
    gate.coalesce(True, burst=5, max_hold=None)
    gate.raise_irq("data")
    gate.raise_irq("data")
    gate.coalesce(False)
    assert line.wait(WAIT) == 2
    gate.raise_irq("data")
    assert line.wait(WAIT) == 1  # no longer held


def test_flush_delivers_held_interrupts(gate: InterruptGate, line: EventFdLine) -> None:
    gate.coalesce(True, burst=5, max_hold=None)
    gate.raise_irq("data")
    gate.raise_irq("cmd")
    gate.flush()
    assert line.wait(WAIT) == 2
    gate.flush()
    assert line.wait(0.0) == 0


def test_a_held_interrupt_is_late_not_lost(gate: InterruptGate, line: EventFdLine) -> None:
    gate.coalesce(True, burst=10, max_hold=0.05)  # 2.5 ms real at time_scale 20
    gate.raise_irq("cmd")
    assert line.wait(WAIT) == 1
    assert gate.pending == 0


def test_close_leaves_no_timer_thread(line: EventFdLine) -> None:
    gate = InterruptGate(line.trigger, SimClock(time_scale=1.0))
    before = set(threading.enumerate())
    gate.coalesce(True, burst=10, max_hold=100.0)
    gate.raise_irq("data")
    gate.close()
    assert [t for t in set(threading.enumerate()) - before if t.is_alive()] == []
    assert gate.pending == 1  # held, not delivered by the closing


def test_drop_next_drops_exactly_one(gate: InterruptGate, line: EventFdLine) -> None:
    gate.drop_next("data")
    gate.raise_irq("cmd")  # another source is not affected
    assert line.wait(WAIT) == 1
    gate.raise_irq("data")  # this one is lost
    assert line.wait(0.0) == 0
    gate.raise_irq("data")
    assert line.wait(WAIT) == 1
    assert (gate.raised, gate.delivered, gate.dropped) == (3, 2, 1)
    assert gate.raised_by("data") == 2


def test_spurious_interrupt_has_no_source_cause(gate: InterruptGate, line: EventFdLine) -> None:
    gate.spurious()
    assert line.wait(WAIT) == 1
    assert gate.raised_by("spurious") == 1
    assert gate.last_source == "spurious"


def test_closed_line_counts_interrupts_as_lost(gate: InterruptGate, line: EventFdLine) -> None:
    line.close()
    gate.raise_irq("data")
    assert (gate.raised, gate.delivered, gate.lost) == (1, 0, 1)
    with pytest.raises(LineClosed):
        line.wait(0.0)


def test_bad_arguments_are_refused(gate: InterruptGate) -> None:
    with pytest.raises(ValueError):
        gate.coalesce(True, burst=0)
    with pytest.raises(ValueError):
        gate.coalesce(True, max_hold=0.0)


def test_counters_add_up_under_concurrent_raisers(gate: InterruptGate, line: EventFdLine) -> None:
    gate.coalesce(True, burst=7, max_hold=None)
    for _ in range(5):
        gate.drop_next("data")

    def raiser() -> None:
        for _ in range(400):
            gate.raise_irq("data")

    threads = [threading.Thread(target=raiser) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    gate.flush()
    received = 0
    while received < 1600 - 5:
        count = line.wait(WAIT)
        assert count > 0
        received += count
    assert received == gate.delivered == 1595
    assert gate.dropped == 5
    assert gate.raised == 1600
