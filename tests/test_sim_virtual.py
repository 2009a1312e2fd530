"""The simulator's own threads on virtual time (issue 22): the BIRIS supervisor and the Model 7600.

Built as ``sim.rig`` builds them, on ``SimClock(30, timebase=VirtualTime(nominal_scale=30))``:
hardware time moves only while every thread waits, so a test that sleeps N fields sees exactly N
fields, in far less real time than N fields take at x30, a stop returns and leaves no thread in
the domain, and two runs give the same result to the last bit.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest
from numpy.typing import NDArray

import sim.supervisor.supervisor as supervisor_module
from biris_hw.bus.base import BusWindow
from biris_hw.bus.memory import MemoryWindow
from biris_hw.timebase import VirtualTime
from regs.biexec import (
    OFF_CMD_INT_ENABLE,
    OFF_COMMAND,
    OFF_DATA_INT_ENABLE,
    OFF_MOTOR_ACCESS,
    OFF_PARAM,
    OFF_STATUS,
    BiCommand,
    BiStatus,
    encode_param,
)
from regs.hctl1000 import Flag, ProgramCounter, Reg, flag_write, pos24_lsb_first, pos24_msb_first
from regs.layout import BirisMemoryMap
from regs.tech80 import AXIS_BASE, Axis, AxisBit, BoardReg
from sim.audit import Audit
from sim.clock import FIELD_PERIOD, SimClock
from sim.irqgate import InterruptGate
from sim.ramdisk import BOOT_FILE
from sim.supervisor import BirisSupervisor
from sim.supervisor.state import JITTER_S
from sim.supervisor.supervisor import IDLE_CHECK_FIELDS
from sim.tech80 import Model7600

SCALE = 30.0
"""The nominal scale: a caller's second of patience is 30 hardware seconds."""

SIM_THREADS = frozenset({"biris-supervisor", "model7600", "irqgate-late", "irqgate-hold"})


def _sim_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name in SIM_THREADS and t.is_alive()]


@pytest.fixture
def tb() -> Iterator[VirtualTime]:
    """A virtual time base driven by the test's thread; a broken test stalls, never hangs."""
    timebase = VirtualTime(nominal_scale=SCALE, stall_timeout=10.0)
    yield timebase
    assert timebase.deadlock is None


@dataclass
class Biris:
    """A supervisor, its gate and its memory, as ``sim.rig`` wires them, with stub optics."""

    tb: VirtualTime
    clock: SimClock
    mmap: BirisMemoryMap
    mem: MemoryWindow
    gate: InterruptGate
    sup: BirisSupervisor
    delivered: list[tuple[float, int]] = field(default_factory=list)
    """Every interrupt count that reached the level: (hardware time, count)."""

    def set_reg(self, offset: int, value: int) -> None:
        self.mem.write16(self.mmap.biexec_offset + offset, value & 0xFFFF)

    def reg(self, offset: int) -> int:
        return self.mem.read16(self.mmap.biexec_offset + offset)

    def execute(self, code: int, param: str = "") -> int:
        """PARAM, COMMAND and the write hook, then wait for completion; STATUS."""
        done = self.sup.commands_completed + 1
        self.mem.write(self.mmap.biexec_offset + OFF_PARAM, encode_param(param))
        self.set_reg(OFF_COMMAND, code)
        self.sup.note_command_write(code)
        assert self.sup.wait_for(lambda s: s.commands_completed == done, 5.0)
        return self.reg(OFF_STATUS)

    def close(self) -> None:
        self.sup.stop()
        self.gate.close()
        self.mem.close()


def _biris(tb: VirtualTime) -> Biris:
    clock = SimClock(SCALE, timebase=tb)
    mmap = BirisMemoryMap(samples=64, max_acquisitions=32)
    mem = MemoryWindow(mmap.size)
    delivered: list[tuple[float, int]] = []
    gate = InterruptGate(lambda n: delivered.append((clock.now(), n)), clock)

    def acquire(
        az: float, tilt: float, lut: float | None
    ) -> tuple[NDArray[np.int16], NDArray[np.int16]]:
        frame = (np.arange(mmap.samples + 1) + 1000).astype(np.int16)
        return frame, frame

    sup = BirisSupervisor(
        mem,
        mmap,
        clock,
        gate,
        acquire,
        lambda t: 200.0 * t,
        audit=Audit(clock.now),
        rng=np.random.default_rng(7),
    )
    biris = Biris(tb, clock, mmap, mem, gate, sup, delivered)
    for offset in (OFF_CMD_INT_ENABLE, OFF_DATA_INT_ENABLE, OFF_MOTOR_ACCESS):
        biris.set_reg(offset, 1)
    return biris


def test_the_field_loop_runs_exactly_the_fields_slept(tb: VirtualTime) -> None:
    fields = 1801  # thirty hardware seconds: a second of real time at x30
    biris = _biris(tb)
    try:
        biris.sup.start()  # at t=0: the first field to come is field 1
        assert biris.sup._fields.vsync == 1
        started = time.monotonic()
        tb.sleep((fields + 0.5) * FIELD_PERIOD, what="the test's fields")
        elapsed = time.monotonic() - started
        assert tb.now() == (fields + 0.5) * FIELD_PERIOD  # nothing else moved it
        # idle, the thread woke every IDLE_CHECK_FIELDS fields, not at each
        assert tb.advances <= fields // IDLE_CHECK_FIELDS + 2
        biris.sup.catch_up()  # what a reader of BIRIS memory does first: the fields since
        assert biris.sup._fields.vsync == fields + 1  # fields 1..1801, not one more or less
        assert elapsed < 0.5 * fields * FIELD_PERIOD / SCALE  # about 0.1 s on a quiet host
        assert biris.clock.lateness() == 0.0
    finally:
        biris.close()


def _query_done_at(tb: VirtualTime, idle_fields: float) -> tuple[float, int]:
    """A query written after ``idle_fields`` fields of an idle BIRIS: (the time it completed,
    the field of its acceptance)."""
    biris = _biris(tb)
    try:
        biris.sup.start()
        tb.sleep(idle_fields * FIELD_PERIOD, what="idle fields")
        assert biris.execute(BiCommand.BI_GET_VME_INC_FRAME) == BiStatus.OK
        return tb.now(), biris.sup._fields.vsync
    finally:
        biris.close()


@pytest.mark.parametrize("idle_fields", [0.5, 29.5, 100.25, 1000.0])
def test_a_command_to_an_idle_biris_is_seen_at_the_next_field_as_if_it_polled(
    monkeypatch: pytest.MonkeyPatch, idle_fields: float
) -> None:
    """Sleeping through idle fields changes no time: the command completes exactly when a
    supervisor that woke at every field (IDLE_CHECK_FIELDS = 1) completes it, a field after
    the write at most (plus BIRIS's jitter)."""
    asleep = _query_done_at(VirtualTime(nominal_scale=SCALE), idle_fields)
    monkeypatch.setattr(supervisor_module, "IDLE_CHECK_FIELDS", 1)
    polled = _query_done_at(VirtualTime(nominal_scale=SCALE), idle_fields)
    assert asleep == polled
    accepted = math.floor(idle_fields) + 1
    assert accepted * FIELD_PERIOD < asleep[0] <= accepted * FIELD_PERIOD + JITTER_S[1]


def test_stop_returns_and_leaves_no_thread_in_the_domain(tb: VirtualTime) -> None:
    biris = _biris(tb)
    try:
        biris.sup.start()
        biris.gate.coalesce(True, burst=5, max_hold=0.1)  # a hold thread waits for its burst...
        biris.gate.late(0.05)  # ...and the late-release thread for something to hold
        biris.gate.spurious()
        tb.sleep(3 * FIELD_PERIOD, what="a few fields")  # 0.05 s: the burst is still held
        waiting = {w.thread for w in tb.waiting()}
        assert waiting == {"biris-supervisor", "irqgate-hold", "irqgate-late"}
    finally:
        biris.close()
    biris.sup.stop()  # idempotent
    assert biris.gate.pending == 1  # held, not delivered by the closing
    assert _sim_threads() == []
    assert tb.waiting() == ()
    assert "1 runnable: 'MainThread'" in tb.describe()  # the test's thread, and nobody else


def _a_run(tb: VirtualTime) -> tuple[object, ...]:
    """Boot, one BI_ACQUIRE of four, a coalesced and late query: everything time decides."""
    biris = _biris(tb)
    try:
        biris.sup.start()
        assert biris.execute(BiCommand.BI_BOOT, BOOT_FILE) == BiStatus.OK
        biris.gate.coalesce(True, burst=3, max_hold=0.05)
        biris.gate.late(0.02)
        assert biris.execute(BiCommand.BI_ACQUIRE, "4") == BiStatus.OK
        assert biris.sup.wait_for(lambda s: s.acquisitions_made == 4 and not s.busy, 5.0)
        assert biris.execute(BiCommand.BI_GET_VME_INC_FRAME) == BiStatus.OK
        biris.gate.late(None)
        assert biris.sup.failure is None
        return (
            tb.now(),
            biris.sup.acquisition_times,
            biris.sup.sequence_starts,
            tuple(biris.delivered),
            biris.gate.late_log,
            biris.sup._fields.vsync,
        )
    finally:
        biris.close()


def test_two_runs_give_identical_results() -> None:
    runs = []
    for _ in range(2):
        tb = VirtualTime(nominal_scale=SCALE, stall_timeout=10.0)
        runs.append(_a_run(tb))
        assert tb.deadlock is None
    first, second = runs
    assert first == second
    acquisition_times = first[1]
    assert isinstance(acquisition_times, list) and len(acquisition_times) == 4
    late_log = first[4]
    assert isinstance(late_log, tuple) and len(late_log) >= 2
    # every held interrupt left at the very instant it was due (nothing is late in virtual
    # time), but the last, which late(None) flushed early, at the end of the run
    *due, flushed = late_log
    assert all(d.delivered_s == d.due_s for d in due)
    assert flushed.delivered_s == first[0] < flushed.due_s


# -- the Model 7600's thread -----------------------------------------------------------------------
def _wr(win: BusWindow, axis: Axis, reg: int, value: int) -> None:
    win.write8(AXIS_BASE[axis] + reg, value)


def _move(tb: VirtualTime) -> tuple[float, float, float]:
    """A short profile on a board whose thread runs: (write time, predicted end, raise time)."""
    clock = SimClock(SCALE, timebase=tb)
    irq = tb.Event()
    raised: list[float] = []

    def raise_irq() -> None:
        raised.append(clock.now())
        irq.set()

    board = Model7600(clock, np.random.default_rng(5), raise_irq=raise_irq)
    win = board.window()
    board.start()
    try:
        axis = Axis.AZIMUTH
        for reg, value in (
            (Reg.SAMPLE_TIMER, 0xAF),
            (Reg.FILTER_ZERO, 0x7F),
            (Reg.FILTER_POLE, 0xEF),
            (Reg.FILTER_GAIN, 0x3F),
            (Reg.MAX_VELOCITY, 2),
            (Reg.ACCEL_LSB, 0x22),
            (Reg.ACCEL_MSB, 0x33),
        ):
            _wr(win, axis, reg, value)
        for reg, byte in zip(
            (Reg.CMD_POS_MSB, Reg.CMD_POS_MID, Reg.CMD_POS_LSB), pos24_msb_first(0), strict=True
        ):
            _wr(win, axis, reg, byte)
        _wr(win, axis, Reg.PROGRAM_COUNTER, ProgramCounter.CONTROL)
        win.write8(BoardReg.IRQ_ENABLE, AxisBit.AZIMUTH)
        tb.sleep(0.5, what="the board to settle")  # several of its polls
        for reg, byte in zip(
            (Reg.FINAL_POS_LSB, Reg.FINAL_POS_MID, Reg.FINAL_POS_MSB),
            pos24_lsb_first(40),
            strict=True,
        ):
            _wr(win, axis, reg, byte)
        written = clock.now()
        _wr(win, axis, Reg.FLAG, flag_write(Flag.F0_TRAPEZOID, True))
        with board.lock:
            eta = board.azimuth.profile_end_eta()
        assert eta is not None
        assert irq.wait(tb.timeout_hw(1.0), what="the end of the profile")
        assert len(raised) == 1
        return written, eta, raised[0]
    finally:
        board.stop()
        board.stop()  # idempotent
        win.close()


def test_the_board_raises_the_end_of_profile_at_its_very_sample(tb: VirtualTime) -> None:
    """The write that starts a profile shorter than the thread's poll wakes it: the interrupt
    comes at the sample that ends the profile, not at the next poll."""
    written, eta, raised = _move(tb)
    assert written == 0.5
    assert eta - written < tb.timeout_hw(0.002)  # shorter than one poll of the board's thread
    assert raised == pytest.approx(eta, abs=1e-12)
    assert _sim_threads() == []
    assert _move(VirtualTime(nominal_scale=SCALE, stall_timeout=10.0)) == (written, eta, raised)
