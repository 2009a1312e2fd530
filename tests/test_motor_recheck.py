"""A lost end-of-motion interrupt costs a delay, not the move (issue 11 leftover).

The Model 7600 latches the end of a profile in its interrupt status whether or not the level-3
interrupt reaches the host. Before, a lost edge left the move's notifier waiting until the motor
watchdog called the move a motor_stall although the head had arrived. Now the watchdog's first
expiry asks the level-3 routine to read the board (``Demultiplexer.recheck``); the notifier,
woken, verifies the arrival as usual. The routine on its own first, then the whole server.
"""

from __future__ import annotations

import logging
import threading

import pytest

from biris_hw import BirisServer, Direction
from biris_hw.irq import EventFdLine
from biris_hw.irq.demux import Demultiplexer
from biris_hw.server.isr import Logical
from sim import SimulatedBiris
from tests.conftest import WAIT, until


class _Latch(Demultiplexer[str]):
    """A routine over a device that latches "done" (set by the test), read only on asking."""

    def __init__(self, line: EventFdLine) -> None:
        super().__init__(line, ["done"], "latch-isr")
        self.latched = threading.Event()
        self.looks = 0

    def _service(self, count: int) -> None:
        self._raise("done", count)

    def _look(self) -> None:
        self.looks += 1
        if self.latched.is_set():
            self.latched.clear()
            self._raise("done")


def test_recheck_reads_the_device_in_the_routines_thread_and_raises_what_is_latched() -> None:
    with EventFdLine() as line, _Latch(line) as routine:
        done = routine.line("done")
        routine.recheck()  # nothing latched: looked at, nothing raised
        until(lambda: routine.looks == 1)
        assert done.wait(0) == 0 and routine.counts == {"done": 0}
        routine.latched.set()
        routine.recheck()
        assert done.wait(WAIT) == 1
        assert routine.counts == {"done": 1} and routine.looks == 2
    routine.recheck()  # closed: asked of nobody, no error


def test_a_lost_end_of_motion_interrupt_is_found_and_the_scan_completes(
    rig: SimulatedBiris, server: BirisServer, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    conn = server.open()
    before = server.status().interrupts.get(Logical.MOTOR_END_OF_SCAN.name, 0)
    rig.faults.lose_motor_interrupt()
    dest = conn.single_scan(30.0)
    conn.wait_idle(timeout=WAIT)  # beyond the watchdog's bound, and no fault
    status = server.status()
    assert status["state"] == "idle" and status.fault is None
    scan = conn.request_scan_data(Direction.CCW)
    assert scan is not None and abs(int(scan.azimuth[-1]) - dest) <= 2
    assert abs(rig.azimuth_counts - dest) <= 2
    said = [r.getMessage() for r in caplog.records]
    assert any("asking the controller" in text for text in said)
    assert any("MOTOR_END_OF_SCAN was latched" in text for text in said)
    # the end was raised by the look: counted like any other
    assert status.interrupts[Logical.MOTOR_END_OF_SCAN.name] == before + 1
    # the next move is heard as usual and asks nothing
    caplog.clear()
    conn.single_scan(0.0)
    conn.wait_idle(timeout=WAIT)
    assert not any("asking the controller" in r.getMessage() for r in caplog.records)


def test_the_can_drives_have_no_level3_interrupt_to_lose() -> None:
    with SimulatedBiris(axes="canopen", seed=3) as rig, pytest.raises(RuntimeError):
        rig.faults.lose_motor_interrupt()
