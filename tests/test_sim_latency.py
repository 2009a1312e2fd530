"""Host latency as a fault: late interrupts, slow reads and bursts of both (``rig.faults``).

The delays are hardware seconds, bounded and seeded; late interrupts keep their order and are
not lost when the fault is cleared; slow reads slow the driver's windows only; a burst ends by
itself on the simulator's clock; and a server on a late host still scans.

The rigs run on virtual time (issue 22), where a delay is exactly the hardware time the rig lets
pass and nothing moves while the test looks, except the one whose VM-USB transport only scaled
time can run.
"""

from __future__ import annotations

import itertools
import random
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from biris_hw import BirisInitRecord, Direction
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.server import BirisServer
from regs.biexec import OFF_ACQ_LINE
from regs.bit3 import Bit3Reg
from regs.tech80 import BoardReg
from sim.clock import SimClock
from sim.irqgate import InterruptGate
from sim.rig import SimulatedBiris
from sim.scene import Scene
from sim.vmusb import VmUsbRule
from tests.conftest import WAIT, RigFactory, until

SCALE = 30.0
"""Hardware seconds per real second in these tests: a 0.3 s read delay is 10 ms real."""


@pytest.fixture
def line() -> Iterator[EventFdLine]:
    with EventFdLine() as line:
        yield line


@pytest.fixture
def gate(line: EventFdLine) -> Iterator[InterruptGate]:
    gate = InterruptGate(line.trigger, SimClock(time_scale=SCALE))
    yield gate
    gate.close()


def _rig(**options: object) -> SimulatedBiris:
    """A rig on virtual time unless ``clock`` says otherwise."""
    options.setdefault("scene", Scene.circle(2.0))
    options.setdefault("time_scale", SCALE)
    options.setdefault("seed", 3)
    options.setdefault("clock", "virtual")
    return SimulatedBiris(**options)  # type: ignore[arg-type]


def _settings(rig: SimulatedBiris) -> tuple[float | None, float]:
    """The late interrupts' bound and the read delay now (None and 0.0 when off)."""
    return rig.faults.late_interrupt_bound_s, rig.faults.read_delay_s


@pytest.fixture
def idle_rig() -> Iterator[SimulatedBiris]:
    """A started rig with no driver on it (so no interrupt but the test's own)."""
    with _rig() as rig:
        yield rig


def _receive(line: EventFdLine, total: int) -> None:
    received = 0
    while received < total:
        count = line.wait(WAIT)
        assert count > 0, f"{received} of {total} interrupts arrived"
        received += count
    assert received == total


# -- late interrupts at the gate -------------------------------------------------------------------


def test_late_interrupts_keep_their_order_within_the_bound(
    gate: InterruptGate, line: EventFdLine
) -> None:
    bound = 0.05  # hardware seconds: 1.7 ms real, so 40 interrupts overlap in the hold
    gate.late(bound, random.Random(1))
    for _ in range(40):
        gate.raise_irq("data")
    _receive(line, 40)
    assert gate.late_delivered == 40 and gate.late_pending == 0
    assert gate.raised == gate.delivered + gate.dropped + gate.lost + gate.pending
    log = gate.late_log
    assert sum(d.interrupts for d in log) == 40
    assert all(0.0 <= d.delay_s <= bound for d in log)
    assert max(d.delay_s for d in log) == gate.late_delay_max > 0.0
    # never sooner than drawn, never later than the bound allows, and in the order raised
    assert all(d.raised_s + d.delay_s <= d.due_s <= d.raised_s + bound for d in log)
    assert all(d.delivered_s >= d.due_s for d in log)
    for earlier, later in itertools.pairwise(log):
        assert later.raised_s >= earlier.raised_s
        assert later.due_s >= earlier.due_s
        assert later.delivered_s >= earlier.delivered_s
    # some interrupt drew a shorter delay than the one ahead of it, and waited for it
    assert any(d.due_s > d.raised_s + d.delay_s for d in log)


def test_nothing_is_early_and_clearing_delivers_what_is_held(
    gate: InterruptGate, line: EventFdLine
) -> None:
    gate.late(300.0, random.Random(2))  # up to 10 s real: held for the whole test
    for _ in range(3):
        gate.raise_irq("cmd")
    assert line.wait(0.0) == 0 and gate.late_pending == 3
    assert gate.delivered == 0
    gate.late(None)  # returns once they have reached the line
    assert line.wait(0.0) == 3
    assert (gate.late_pending, gate.late_delivered, gate.delivered) == (0, 3, 3)
    assert gate.late_bound is None
    gate.raise_irq("cmd")  # no longer late: straight through
    assert line.wait(0.0) == 1
    assert gate.late_delivered == 3
    # late again: the long delays flushed before do not hold the next interrupt
    gate.late(0.03, random.Random(5))
    gate.raise_irq("cmd")
    _receive(line, 1)
    last = gate.late_log[-1]
    assert last.raised_s + last.delay_s <= last.due_s <= last.raised_s + 0.03


def test_a_coalesced_burst_is_late_as_a_whole(gate: InterruptGate, line: EventFdLine) -> None:
    gate.coalesce(True, 4, max_hold=None)
    gate.late(300.0, random.Random(3))
    for _ in range(4):
        gate.raise_irq("data")
    assert gate.pending == 0 and gate.late_pending == 4  # the burst left coalescing...
    assert line.wait(0.0) == 0  # ...and lateness holds it
    gate.late(None)
    assert line.wait(0.0) == 4
    assert [d.interrupts for d in gate.late_log] == [4]
    gate.coalesce(False)


def test_closing_leaves_no_late_thread(line: EventFdLine) -> None:
    gate = InterruptGate(line.trigger, SimClock(time_scale=1.0))
    before = set(threading.enumerate())
    gate.late(100.0, random.Random(4))
    gate.raise_irq("data")
    gate.close()
    assert [t for t in set(threading.enumerate()) - before if t.is_alive()] == []
    assert gate.late_pending == 1  # held, not delivered by the closing


def test_bad_bounds_are_refused(gate: InterruptGate) -> None:
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            gate.late(bad)
    assert gate.late_bound is None


# -- the fault panel -----------------------------------------------------------------------------


def _spurious_delays(
    rig_seed: int, n: int, seed: int | None = None
) -> tuple[list[float], float, int]:
    """The delays drawn for ``n`` late spurious interrupts on a fresh rig of ``rig_seed``, the
    largest the fault panel reports and how many it still holds. One rig at a time: the test
    waits (``until``) in the time base of the one it drives."""
    with _rig(seed=rig_seed) as rig:
        rig.faults.late_interrupts(0.05, seed=seed)
        for _ in range(n):
            rig.faults.spurious_interrupt()
        until(lambda: rig.faults.late_interrupts_delivered == n)
        rig.faults.clear_late_interrupts()
        delays = [d.delay_s for d in rig.level2_gate.late_log]
        return delays, rig.faults.late_delay_max_s, rig.faults.late_interrupts_held


def test_late_interrupt_delays_are_seeded_by_the_rig() -> None:
    (da, max_a, held_a), (db, _, _), (dc, _, _) = (
        _spurious_delays(seed, 12) for seed in (11, 11, 12)
    )
    assert da == db  # same seed, same delays
    assert da != dc
    assert all(0.0 <= d <= 0.05 for d in da + dc)
    assert max_a == max(da)
    assert held_a == 0


def test_an_explicit_seed_overrides_the_rigs() -> None:
    assert _spurious_delays(1, 8, seed=99)[0] == _spurious_delays(2, 8, seed=99)[0]


def test_late_interrupts_hold_both_levels_until_cleared(idle_rig: SimulatedBiris) -> None:
    rig = idle_rig
    rig.faults.late_interrupts(300.0)  # held until cleared (no time passes meanwhile)
    assert rig.faults.late_interrupt_bound_s == 300.0
    rig.faults.spurious_interrupt()  # level 2
    rig.level3_gate.raise_irq("motor")  # level 3, as the board raises it
    assert rig.faults.late_interrupts_held == 2
    assert rig.hardware.level2.wait(0.0) == 0 and rig.hardware.level3.wait(0.0) == 0
    rig.faults.clear_all()
    assert rig.faults.late_interrupts_held == 0 and rig.faults.late_interrupts_delivered == 2
    assert rig.hardware.level2.wait(0.0) == 1 and rig.hardware.level3.wait(0.0) == 1
    assert rig.faults.late_interrupt_bound_s is None


def _timed(rig: SimulatedBiris, read: Callable[[], object]) -> float:
    """Hardware seconds ``read`` took: on virtual time, exactly the time the rig let pass."""
    t0 = rig.clock.now()
    read()
    return rig.clock.now() - t0


def _real_timed(read: Callable[[], object]) -> float:
    t0 = time.monotonic()
    read()
    return time.monotonic() - t0


def test_slow_reads_slow_the_drivers_reads_only(idle_rig: SimulatedBiris) -> None:
    rig = idle_rig
    hw = rig.hardware
    assert hw.motion is not None
    acq_line = hw.biexec_offset + OFF_ACQ_LINE
    one_delay = pytest.approx(0.3, abs=1e-9)
    assert _timed(rig, lambda: hw.biris.read16(acq_line)) == 0.0  # a read takes no time...
    rig.faults.slow_reads(0.3)
    assert rig.faults.read_delay_s == 0.3
    # ...until slowed: every read path of every driver window, each slowed once (read_many
    # reads through read inside, and is still one delay)
    assert _timed(rig, lambda: hw.biris.read16(acq_line)) == one_delay
    assert _timed(rig, lambda: hw.biris.read_many([(acq_line, 2), (0, 4)])) == one_delay
    assert _timed(rig, lambda: hw.motion.read8(BoardReg.IRQ_VECTOR)) == one_delay  # type: ignore[union-attr]
    assert _timed(rig, lambda: hw.coupler.read(Bit3Reg.LOCAL_STATUS, 1)) == one_delay
    assert rig.faults.slow_reads_made == 4
    # the simulator's own accesses are not slowed
    rig.board.snapshot()
    rig.coupler.snapshot()
    _ = rig.azimuth_counts
    rig.supervisor.catch_up()
    assert rig.faults.slow_reads_made == 4
    rig.faults.clear_slow_reads()
    assert rig.faults.read_delay_s == 0.0
    assert "read16" not in vars(hw.biris)  # the window's own method again
    assert _timed(rig, lambda: hw.biris.read16(acq_line)) == 0.0
    assert rig.faults.slow_reads_made == 4


# the VM-USB transport's pyusb reader waits outside the time base: scaled time only
@pytest.mark.realtime
def test_slow_reads_slow_the_vmusb_windows_not_the_bridge() -> None:
    with _rig(transport="vmusb", time_scale=10.0, clock="scaled") as rig:
        hw = rig.hardware
        rig.faults.slow_reads(0.2)  # 20 ms real at x10
        assert _real_timed(lambda: hw.coupler.read8(Bit3Reg.LOCAL_STATUS)) >= 0.02
        assert rig.faults.slow_reads_made == 1
        # an interrupt makes the bridge read the interrupter's vector from the far side of
        # the crate: the simulator's access, not the driver's (with no driver to service it,
        # the bridge records it as unserviced: expected here)
        device = rig.usb_device
        assert device is not None
        rig.faults.spurious_interrupt()
        until(lambda: device.violations, what="the bridge's IRQ")
        assert [v.rule for v in device.violations] == [VmUsbRule.IRQ_UNSERVICED]
        device.clear_violations()
        assert rig.faults.slow_reads_made == 1
        rig.faults.clear_all()
        assert rig.faults.read_delay_s == 0.0


def test_bad_read_delays_are_refused(idle_rig: SimulatedBiris) -> None:
    rig = idle_rig
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            rig.faults.slow_reads(bad)
    with pytest.raises(ValueError):
        rig.faults.latency_burst(0.0, 0.05, 0.1)
    assert _settings(rig) == (None, 0.0)


def test_a_latency_burst_ends_by_itself(idle_rig: SimulatedBiris) -> None:
    rig = idle_rig
    acq_line = rig.hardware.biexec_offset + OFF_ACQ_LINE
    start = rig.clock.now()
    rig.faults.latency_burst(3.0, max_delay_s=300.0, read_delay_s=0.15)
    assert rig.faults.latency_burst_active
    assert _settings(rig) == (300.0, 0.15)
    assert _timed(rig, lambda: rig.hardware.biris.read16(acq_line)) == pytest.approx(0.15)
    rig.faults.spurious_interrupt()  # held past the burst's end (up to 300 s)...
    assert rig.faults.slow_reads_made == 1 and rig.faults.late_interrupts_held == 1
    until(lambda: not rig.faults.latency_burst_active, what="the burst's end")
    assert rig.clock.now() - start >= 3.0
    # ...and delivered when it ended; both faults are off
    assert rig.faults.late_interrupts_held == 0 and rig.faults.late_interrupts_delivered == 1
    assert rig.hardware.level2.wait(0.0) == 1
    assert _settings(rig) == (None, 0.0)
    assert _timed(rig, lambda: rig.hardware.biris.read16(acq_line)) == 0.0
    assert rig.faults.slow_reads_made == 1


def test_clear_all_ends_a_burst(idle_rig: SimulatedBiris) -> None:
    rig = idle_rig
    rig.faults.latency_burst(300.0, max_delay_s=0.05, read_delay_s=0.1)
    rig.faults.clear_all()
    assert not rig.faults.latency_burst_active
    assert _settings(rig) == (None, 0.0)


# -- end to end ------------------------------------------------------------------------------------


def test_a_server_on_a_late_host_still_scans(make_rig: RigFactory) -> None:
    rig = make_rig()
    rig.faults.late_interrupts(0.05)  # from power-up: initialisation is late too
    with BirisServer(rig.hardware, BirisInitRecord()) as server:
        conn = server.open()
        dest = conn.single_scan(45.0)
        conn.wait_idle(timeout=30.0)
        scan = conn.request_scan_data(Direction.CCW)
        assert scan is not None and scan.seq == 1
        assert abs(int(scan.azimuth[-1]) - dest) <= 2
        assert abs(rig.azimuth_counts - dest) <= 3
    assert rig.faults.late_interrupts_delivered > 10  # commands, data, the motor: all late
    assert 0.0 < rig.faults.late_delay_max_s <= 0.05
