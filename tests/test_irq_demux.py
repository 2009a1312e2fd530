"""The generic demultiplexer (biris_hw.irq), and the server's level-2 and level-3 service
routines (biris_hw.server.isr) against memory windows and an eventfd physical line."""

from __future__ import annotations

import os
import select
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from biris_hw.bus.memory import MemoryWindow
from biris_hw.errors import LineClosed
from biris_hw.irq import Demultiplexer, EventFdLine, InterruptLine
from biris_hw.server.isr import Level2Demux, Level3Demux, Logical
from biris_hw.timebase import HwThread, TimeBase, VirtualTime, VirtualTimeDeadlock
from regs.biexec import OFF_COMMAND, BiCommand
from regs.bit3 import BIT3_SPACE, Bit3Reg, LocalStatus
from regs.tech80 import MOTION_WINDOW_SIZE, AxisBit, BoardReg
from tests.conftest import until

WAIT = 5.0
"""Timeout for things that should happen almost at once; only reached when a test fails."""

RELEASE_BOUND = 0.5
BIEXEC = 0x100
DATA, CMD = Logical.BIRIS_DATA_DEV, Logical.BIRIS_CMD
PERR, BERR = Logical.BIT3_PERR, Logical.BIT3_BERR
MOTOR, ELEVATION = Logical.MOTOR_END_OF_SCAN, Logical.ELEVATION_END_OF_SCAN


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@dataclass
class Level2:
    physical: EventFdLine
    coupler: MemoryWindow
    biris: MemoryWindow
    demux: Level2Demux

    def status(self, bits: int) -> None:
        self.coupler.write8(Bit3Reg.LOCAL_STATUS, bits)

    def command(self, code: int) -> None:
        self.biris.write16(BIEXEC + OFF_COMMAND, code)

    def wait(self, logical: Logical) -> int:
        return self.demux.line(logical).wait(WAIT)

    def pending(self, logical: Logical) -> int:
        return self.demux.line(logical).wait(0)

    def barrier(self) -> None:
        """Let every earlier physical interrupt be serviced: rounds run in order, and a data
        interrupt (COMMAND busy, no new coupler error) is serviced last in its round."""
        self.command(BiCommand.BI_ACQUIRE)
        self.physical.trigger()
        assert self.wait(DATA) == 1


@pytest.fixture
def l2() -> Iterator[Level2]:
    physical = EventFdLine()
    coupler = MemoryWindow(BIT3_SPACE)
    biris = MemoryWindow(0x1000)
    demux = Level2Demux(physical, coupler, biris, BIEXEC)
    demux.start()
    try:
        yield Level2(physical, coupler, biris, demux)
    finally:
        demux.close()
        physical.close()
        coupler.close()
        biris.close()


def counts(**nonzero: int) -> dict[Logical, int]:
    expected = dict.fromkeys((DATA, CMD, PERR, BERR), 0)
    expected.update({Logical[name]: n for name, n in nonzero.items()})
    return expected


# -- level 2: decision order ----------------------------------------------------------------------


def test_command_complete_when_command_is_zero(l2: Level2) -> None:
    l2.physical.trigger()
    assert l2.wait(CMD) == 1
    assert l2.pending(DATA) == 0
    assert l2.demux.counts == counts(BIRIS_CMD=1)


def test_data_when_command_is_busy(l2: Level2) -> None:
    l2.command(BiCommand.BI_ACQUIRE)
    l2.physical.trigger()
    assert l2.wait(DATA) == 1
    assert l2.pending(CMD) == 0
    assert l2.demux.counts == counts(BIRIS_DATA_DEV=1)


def test_coalesced_data_passes_the_count_on(l2: Level2) -> None:
    l2.command(BiCommand.BI_ACQUIRE)
    l2.physical.trigger(3)
    assert l2.wait(DATA) == 3
    assert l2.pending(CMD) == 0


def test_coalesced_with_command_zero_raises_data_and_command(l2: Level2) -> None:
    l2.physical.trigger(2)
    assert l2.wait(CMD) == 1
    assert l2.pending(DATA) == 1
    assert l2.demux.counts == counts(BIRIS_DATA_DEV=1, BIRIS_CMD=1)


def test_parity_error_comes_first_and_ends_a_single_interrupt(l2: Level2) -> None:
    l2.status(LocalStatus.PARITY_ERROR)
    l2.command(BiCommand.BI_ACQUIRE)
    l2.physical.trigger()
    assert l2.wait(PERR) == 1
    l2.barrier()  # the still-set parity bit is not a new interrupt
    assert l2.demux.counts == counts(BIT3_PERR=1, BIRIS_DATA_DEV=1)


def test_remote_bus_error_ends_a_single_interrupt(l2: Level2) -> None:
    l2.status(LocalStatus.REMOTE_BUS_ERROR)
    l2.physical.trigger()  # COMMAND is zero: had it been read, BIRIS_CMD would be raised
    assert l2.wait(BERR) == 1
    l2.barrier()
    assert l2.demux.counts == counts(BIT3_BERR=1, BIRIS_DATA_DEV=1)


def test_both_coupler_errors_at_once(l2: Level2) -> None:
    l2.status(LocalStatus.PARITY_ERROR | LocalStatus.REMOTE_BUS_ERROR | LocalStatus.CARD_READY)
    l2.physical.trigger()
    assert l2.wait(PERR) == 1
    assert l2.wait(BERR) == 1
    l2.barrier()
    assert l2.demux.counts == counts(BIT3_PERR=1, BIT3_BERR=1, BIRIS_DATA_DEV=1)


def test_error_in_a_coalesced_burst_still_reads_command(l2: Level2) -> None:
    l2.status(LocalStatus.PARITY_ERROR)
    l2.command(BiCommand.BI_ACQUIRE)
    l2.physical.trigger(3)
    assert l2.wait(DATA) == 2  # one of the three was the coupler's
    assert l2.demux.counts == counts(BIT3_PERR=1, BIRIS_DATA_DEV=2)


def test_sticky_error_is_signalled_once_and_forgotten_once_cleared(l2: Level2) -> None:
    l2.status(LocalStatus.PARITY_ERROR)
    l2.physical.trigger()
    assert l2.wait(PERR) == 1
    l2.physical.trigger()  # still set: this one is BIRIS's
    assert l2.wait(CMD) == 1
    l2.status(0)  # the driver wrote CLR_ERROR
    l2.physical.trigger()
    assert l2.wait(CMD) == 1
    l2.status(LocalStatus.PARITY_ERROR)  # a new parity error
    l2.physical.trigger()
    assert l2.wait(PERR) == 1
    l2.barrier()
    assert l2.demux.counts == counts(BIT3_PERR=2, BIRIS_CMD=2, BIRIS_DATA_DEV=1)


def test_unreadable_command_is_a_bus_error_and_the_demux_keeps_running() -> None:
    physical = EventFdLine()
    coupler = MemoryWindow(BIT3_SPACE)
    small = MemoryWindow(0x10)  # BIEXEC_COM would lie outside it: every COMMAND read fails
    with physical, coupler, small, Level2Demux(physical, coupler, small, BIEXEC) as demux:
        for expected in (1, 2):
            physical.trigger()
            assert demux.line(BERR).wait(WAIT) == 1
            assert demux.counts[BERR] == expected
        assert demux.running
        assert demux.counts[CMD] == demux.counts[DATA] == 0


def test_unreadable_coupler_is_a_bus_error(l2: Level2) -> None:
    l2.coupler.close()
    l2.command(BiCommand.BI_ACQUIRE)
    l2.physical.trigger()  # a single interrupt: taken as the coupler's
    assert l2.wait(BERR) == 1
    l2.physical.trigger(2)  # a burst: COMMAND is still read
    assert l2.wait(BERR) == 1
    assert l2.wait(DATA) == 1
    assert l2.demux.counts == counts(BIT3_BERR=2, BIRIS_DATA_DEV=1)
    assert l2.demux.running


# -- level 3 ---------------------------------------------------------------------------------------


class Model7600(MemoryWindow):
    """Board memory whose IRQ_STATUS is write-1-to-clear, recording every write to it."""

    def __init__(self) -> None:
        super().__init__(MOTION_WINDOW_SIZE)
        self.acks: list[int] = []
        self.watch: InterruptLine | None = None
        self.raised_before_ack: list[bool] = []

    def write8(self, offset: int, value: int) -> None:
        if offset == BoardReg.IRQ_STATUS:
            self.acks.append(value)
            if self.watch is not None:
                poller = select.poll()
                poller.register(self.watch.fileno(), select.POLLIN)
                self.raised_before_ack.append(bool(poller.poll(0)))
            value = self.read8(offset) & ~value
        super().write8(offset, value)

    def raise_status(self, bits: int) -> None:
        super().write8(BoardReg.IRQ_STATUS, self.read8(BoardReg.IRQ_STATUS) | bits)


@pytest.fixture
def l3() -> Iterator[tuple[EventFdLine, Model7600, Level3Demux]]:
    physical = EventFdLine()
    motion = Model7600()
    with physical, motion, Level3Demux(physical, motion) as demux:
        yield physical, motion, demux


def test_level3_acknowledges_azimuth_before_raising(
    l3: tuple[EventFdLine, Model7600, Level3Demux],
) -> None:
    physical, motion, demux = l3
    motion.watch = demux.line(MOTOR)
    motion.raise_status(AxisBit.AZIMUTH)
    physical.trigger()
    assert demux.line(MOTOR).wait(WAIT) == 1
    assert motion.read8(BoardReg.IRQ_STATUS) == 0
    assert motion.acks == [AxisBit.AZIMUTH]
    assert motion.raised_before_ack == [False]  # acknowledged before the notifier could wake
    assert demux.line(ELEVATION).wait(0) == 0


def test_level3_both_axes(l3: tuple[EventFdLine, Model7600, Level3Demux]) -> None:
    physical, motion, demux = l3
    motion.raise_status(AxisBit.AZIMUTH | AxisBit.ELEVATION)
    physical.trigger()
    assert demux.line(MOTOR).wait(WAIT) == 1
    assert demux.line(ELEVATION).wait(WAIT) == 1
    assert sorted(motion.acks) == [AxisBit.AZIMUTH, AxisBit.ELEVATION]
    assert motion.read8(BoardReg.IRQ_STATUS) == 0
    assert demux.counts == {MOTOR: 1, ELEVATION: 1}


def test_level3_interrupt_without_status_is_spurious(
    l3: tuple[EventFdLine, Model7600, Level3Demux],
) -> None:
    physical, motion, demux = l3
    physical.trigger()
    assert until(lambda: demux.spurious == 1)
    assert motion.acks == []
    assert demux.line(MOTOR).wait(0) == demux.line(ELEVATION).wait(0) == 0
    motion.raise_status(AxisBit.AZIMUTH)  # a real one afterwards is still serviced
    physical.trigger()
    assert demux.line(MOTOR).wait(WAIT) == 1
    assert demux.counts == {MOTOR: 1, ELEVATION: 0}
    assert demux.spurious == 1


# -- lifecycle -------------------------------------------------------------------------------------


def blocked_on(line: InterruptLine) -> tuple[threading.Thread, list[object], threading.Event]:
    result: list[object] = []
    done = threading.Event()

    def run() -> None:
        try:
            result.append(line.wait())
        except Exception as exc:
            result.append(exc)
        result.append(time.monotonic())
        done.set()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert until(lambda: line._waiters == 1), "the notifier never blocked"  # type: ignore[attr-defined]
    return thread, result, done


def test_close_releases_a_notifier_blocked_on_a_logical_line(l2: Level2) -> None:
    thread, result, done = blocked_on(l2.demux.line(CMD))
    started = time.monotonic()
    l2.demux.close()
    assert done.wait(WAIT)
    assert isinstance(result[0], LineClosed)
    assert isinstance(result[1], float) and result[1] - started < RELEASE_BOUND
    thread.join(WAIT)
    assert not l2.demux.running
    assert not l2.physical.closed  # the bundle owns it
    l2.physical.trigger()
    assert l2.physical.wait(WAIT) == 1  # nobody consumes it any more
    l2.demux.close()  # idempotent


def test_physical_line_closed_underneath_closes_the_logical_lines(l2: Level2) -> None:
    thread, result, done = blocked_on(l2.demux.line(DATA))
    started = time.monotonic()
    l2.physical.close()
    assert done.wait(WAIT)
    assert isinstance(result[0], LineClosed)
    assert isinstance(result[1], float) and result[1] - started < RELEASE_BOUND
    thread.join(WAIT)
    assert until(lambda: not l2.demux.running)  # the service thread exits
    for logical in (DATA, CMD, PERR, BERR):
        assert l2.demux.line(logical).closed


def test_physical_line_closed_before_start() -> None:
    physical = EventFdLine()
    physical.close()
    with (
        MemoryWindow(0x10) as motion,
        Level3Demux(physical, motion) as demux,
        pytest.raises(LineClosed),
    ):
        demux.line(MOTOR).wait(WAIT)


def test_start_and_line_misuse(l2: Level2) -> None:
    with pytest.raises(RuntimeError, match="already"):
        l2.demux.start()
    with pytest.raises(ValueError, match="MOTOR_END_OF_SCAN"):
        l2.demux.line(MOTOR)
    l2.demux.close()
    with pytest.raises(RuntimeError, match="closed"):
        l2.demux.start()


def test_close_before_start_closes_the_logical_lines() -> None:
    with EventFdLine() as physical, MemoryWindow(0x100) as motion:
        demux = Level3Demux(physical, motion)
        demux.close()
        assert not demux.running
        with pytest.raises(LineClosed):
            demux.line(MOTOR).wait(0)


def test_demultiplexers_leak_no_descriptor_or_thread() -> None:
    before = open_fds()
    threads = threading.active_count()
    physical2, physical3 = EventFdLine(), EventFdLine()
    coupler, biris, motion = MemoryWindow(BIT3_SPACE), MemoryWindow(0x1000), Model7600()
    with (
        Level2Demux(physical2, coupler, biris, BIEXEC) as demux2,
        Level3Demux(physical3, motion) as demux3,
    ):
        physical2.trigger()
        assert demux2.line(CMD).wait(WAIT) == 1
        motion.raise_status(AxisBit.AZIMUTH)
        physical3.trigger()
        assert demux3.line(MOTOR).wait(WAIT) == 1
    for closable in (physical2, physical3, coupler, biris, motion):
        closable.close()
    assert threading.active_count() == threads
    assert open_fds() == before


# -- the generic base ------------------------------------------------------------------------------


class Doorbell(Demultiplexer[str]):
    """A device-free routine: every physical interrupt rings "bell"; a count of 0 is impossible,
    so a count above 3 is called spurious, to exercise the counters."""

    def __init__(self, line: InterruptLine, *, timebase: TimeBase | None = None) -> None:
        super().__init__(line, ("bell", "spare"), "doorbell_isr", timebase=timebase)

    def _service(self, count: int) -> None:
        if count > 3:
            self._count_spurious(count)
            return
        self._raise("bell", count)


def test_the_base_knows_nothing_of_biris() -> None:
    with EventFdLine() as physical, Doorbell(physical) as bell:
        assert bell.carries == ("bell", "spare")
        physical.trigger(2)
        assert bell.line("bell").wait(WAIT) == 2
        physical.trigger(5)
        assert until(lambda: bell.spurious == 5)
        assert bell.counts == {"bell": 2, "spare": 0}
        with pytest.raises(ValueError, match="doorbell_isr does not carry 'nothing'"):
            bell.line("nothing")
        assert [t.name for t in threading.enumerate()].count("doorbell_isr") == 1


def test_an_owner_may_run_the_routine_in_its_own_thread() -> None:
    with EventFdLine() as physical:
        bell = Doorbell(physical)
        owner = threading.Thread(target=bell.run, name="owners_thread")
        owner.start()
        physical.trigger()
        assert bell.line("bell").wait(WAIT) == 1
        assert bell.running
        with pytest.raises(RuntimeError, match="already running"):
            bell.start()
        bell.close()  # stops and joins the owner's thread
        assert not owner.is_alive()
        assert bell.line("bell").closed


def test_a_routine_closed_before_its_thread_runs_returns_at_once() -> None:
    before = open_fds()
    with EventFdLine() as physical:
        bell = Doorbell(physical)
        bell.close()
        owner = threading.Thread(target=bell.run)
        owner.start()
        owner.join(WAIT)
        assert not owner.is_alive() and not bell.running
    assert open_fds() == before


# -- on virtual time ------------------------------------------------------------------------------
# The test's thread drives the domain (time moves only while it waits in it); a stall_timeout
# makes a wait the domain cannot see (a real poll in the routine) fail instead of hang.


class LookingDoorbell(Doorbell):
    """A doorbell whose devices keep state to look at again: a recheck rings "spare"."""

    def _look(self) -> None:
        self._raise("spare")


def test_a_virtual_routine_wakes_its_notifier_at_the_instant_of_the_interrupt() -> None:
    tb = VirtualTime(stall_timeout=WAIT)
    before = open_fds()
    with EventFdLine(timebase=tb) as physical:
        bell = LookingDoorbell(physical, timebase=tb)
        bell.start()
        assert isinstance(bell._thread, HwThread)  # a participant of the domain

        def simulator() -> None:
            tb.sleep(1.0)
            physical.trigger(2)

        sim = tb.Thread(simulator, name="simulator", daemon=True)
        sim.start()
        assert bell.line("bell").wait(WAIT) == 2
        assert tb.now() == 1.0 and bell.counts == {"bell": 2, "spare": 0}
        assert tb.join_thread(sim)
        bell.recheck()  # the routine looks at once: no time passes
        assert bell.line("spare").wait(WAIT) == 1
        assert tb.now() == 1.0

        ended: list[tuple[str, float]] = []

        def notifier() -> None:
            try:
                bell.line("bell").wait()
            except LineClosed:
                ended.append(("closed", tb.now()))

        waiting = tb.Thread(notifier, name="bell notifier", daemon=True)
        waiting.start()
        tb.sleep(2.0)  # the routine and the notifier wait all the while
        bell.close()  # joins the routine in the domain, then closes the logical lines
        assert not bell.running
        assert tb.join_thread(waiting)
        assert ended == [("closed", 3.0)]
        bell.close()  # idempotent
    assert open_fds() == before and tb.deadlock is None


def test_a_virtual_routine_waits_in_the_domain_so_a_lost_interrupt_is_a_deadlock() -> None:
    tb = VirtualTime(stall_timeout=WAIT)
    with EventFdLine(timebase=tb) as physical, Doorbell(physical, timebase=tb) as bell:
        with pytest.raises(VirtualTimeDeadlock) as info:
            bell.line("bell").wait()  # nobody will ever trigger the physical line
        whats = sorted(wait.what for wait in info.value.waits)
        assert whats == ["doorbell_isr: its physical interrupt line", "interrupt line eventfd"]


def test_a_virtual_routine_closed_by_another_closer_waits_in_the_domain() -> None:
    tb = VirtualTime(stall_timeout=WAIT)
    with EventFdLine(timebase=tb) as physical:
        bell = Doorbell(physical, timebase=tb)
        bell.start()
        closers = [tb.Thread(bell.close, name=f"closer-{i}", daemon=True) for i in range(2)]
        for closer in closers:
            closer.start()
        for closer in closers:
            assert tb.join_thread(closer)
        assert bell.closed and not bell.running and bell.line("bell").closed
