"""BirisSupervisor driven as a driver would: PARAM then COMMAND through memory, level-2 waits.

Timing checks use generous tolerances: the machine is shared, and a late test thread only ever
sees a *later* state, so every assertion on a sampled value accepts that.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest
from numpy.typing import NDArray

from biris_hw.bus.memory import MemoryWindow
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.timebase import VirtualTime
from regs.biexec import (
    ACQ_LINE_END,
    ACQ_LINE_STARTUP,
    BIEXEC_PARAM_SIZE,
    OFF_ACQ_LINE,
    OFF_CMD_INT_ENABLE,
    OFF_COMMAND,
    OFF_CURRENT_FRAME,
    OFF_DATA_INT_ENABLE,
    OFF_MOTOR_ACCESS,
    OFF_PARAM,
    OFF_STATUS,
    BiCommand,
    BiStatus,
    decode_param,
    encode_param,
)
from regs.layout import AZIMUTH_DTYPE, FRAME_DTYPE, BirisMemoryMap, fields_per_acquisition
from sim import POISON
from sim.audit import Audit, Rule
from sim.clock import FIELD_PERIOD, SimClock
from sim.irqgate import InterruptGate
from sim.ramdisk import BOOT_FILE, BootParameters, RamDisk, boot_file_text
from sim.supervisor import BirisSupervisor, GarbageKind

WAIT = 3.0  # real seconds; reached only when something is broken
LATE = 0.5  # hardware seconds a loaded machine may add to any observed time (50 ms at 10x)
COUNTS_TO_RAD = 2.0 * math.pi / 4096


def _to_counts(rad: float) -> int:
    return round(rad / COUNTS_TO_RAD)


@dataclass
class Rig:
    """A supervisor with the driver's side of memory and level 2, and stubbed optics."""

    clock: SimClock
    mmap: BirisMemoryMap
    mem: MemoryWindow
    line: EventFdLine
    gate: InterruptGate
    audit: Audit
    sup: BirisSupervisor
    calls: list[tuple[float, float, float | None]] = field(default_factory=list)
    """Every acquire() call: (azimuth_rad, tilt_rad, lut_tilt_rad)."""
    azimuths: list[tuple[float, float]] = field(default_factory=list)
    """Every azimuth sample the supervisor took: (clock time, counts)."""
    on_acquire: Callable[[int], None] | None = None
    consumed: int = 0
    cmds_at_issue: int = 0

    # -- what a driver does ------------------------------------------------------------------
    def reg(self, offset: int) -> int:
        raw = self.mem.read16(self.mmap.biexec_offset + offset)
        return raw - 0x10000 if raw & 0x8000 else raw

    def set_reg(self, offset: int, value: int) -> None:
        self.mem.write16(self.mmap.biexec_offset + offset, value & 0xFFFF)

    def param(self) -> bytes:
        return self.mem.read(self.mmap.biexec_offset + OFF_PARAM, BIEXEC_PARAM_SIZE)

    def issue(self, code: int, param: str = "") -> None:
        """PARAM, then COMMAND, then the in-process write hook (as a rig would install it)."""
        self.cmds_at_issue = self.gate.raised_by("cmd")
        self.mem.write(self.mmap.biexec_offset + OFF_PARAM, encode_param(param))
        self.set_reg(OFF_COMMAND, code)
        self.sup.note_command_write(code)

    def wait_irq(self, timeout: float = WAIT) -> int:
        """One wait on level 2, counting what it took."""
        count = self.line.wait(timeout)
        self.consumed += count
        return count

    def settle(self) -> None:
        """Take every interrupt delivered so far, so later waits start from nothing."""
        while self.consumed < self.gate.delivered:
            assert self.wait_irq() > 0, "a delivered interrupt never arrived"

    def wait_command(self) -> None:
        """Wait on level 2 for the command interrupt of the last command issued."""
        while self.gate.raised_by("cmd") <= self.cmds_at_issue:
            assert self.wait_irq() > 0, "no command interrupt"
        self.settle()
        assert self.reg(OFF_COMMAND) == 0

    def execute(self, code: int, param: str = "") -> tuple[int, bytes]:
        """Issue a command and wait for its completion: (STATUS, raw PARAM)."""
        self.issue(code, param)
        self.wait_command()
        return self.reg(OFF_STATUS), self.param()

    def answer(self, code: int, param: str = "") -> str:
        status, raw = self.execute(code, param)
        assert status == BiStatus.OK
        return decode_param(raw)

    def boot(self) -> None:
        assert self.answer(BiCommand.BI_BOOT, BOOT_FILE) == ""

    def frame(self, kind: str, k: int) -> NDArray[np.int16]:
        addr = self.mmap.addressing
        offset = addr.range_frame(k) if kind == "range" else addr.intensity_frame(k)
        raw = self.mem.read(offset, 2 * (self.mmap.samples + 1))
        return np.frombuffer(raw, dtype=FRAME_DTYPE).astype(np.int16)

    def azimuth_entry(self, k: int) -> int:
        raw = self.mem.read(self.mmap.addressing.azimuth_entry(k), 4)
        return int(np.frombuffer(raw, dtype=AZIMUTH_DTYPE)[0])

    def expected_range(self, azimuth_counts: int) -> NDArray[np.int16]:
        return _stub_range(self.mmap.samples, azimuth_counts)


def _stub_range(samples: int, azimuth_counts: int) -> NDArray[np.int16]:
    frame = (np.arange(samples + 1) + 1000).astype(np.int16)
    frame[1] = azimuth_counts  # so a frame says which azimuth it was exposed at
    return frame


RigFactory = Callable[..., Rig]


@pytest.fixture
def make_rig() -> Iterator[RigFactory]:
    rigs: list[Rig] = []

    def make(
        *,
        samples: int = 64,
        time_scale: float = 20.0,
        max_acquisitions: int = 32,
        slope: float = 200.0,
        ramdisk: RamDisk | None = None,
        tilting: Callable[[], bool] | None = None,
        elevation_counts: Callable[[float], float] | None = None,
        enables: bool = True,
        bad_frames: bool = False,
    ) -> Rig:
        # virtual time: what the supervisor does depends on its clock, never on the host's load
        tb = VirtualTime(nominal_scale=time_scale, stall_timeout=30.0)
        clock = SimClock(time_scale=time_scale, timebase=tb)
        mmap = BirisMemoryMap(samples=samples, max_acquisitions=max_acquisitions)
        mem = MemoryWindow(mmap.size)
        line = EventFdLine(timebase=tb)
        gate = InterruptGate(line.trigger, clock)
        audit = Audit(clock)
        holder: list[Rig] = []

        def acquire(
            az: float, tilt: float, lut: float | None
        ) -> tuple[NDArray[np.int16], NDArray[np.int16]]:
            rig = holder[0]
            rig.calls.append((az, tilt, lut))
            if rig.on_acquire is not None:
                rig.on_acquire(len(rig.calls) - 1)
            size = samples if bad_frames else samples + 1
            intensity = (np.arange(size) + 10).astype(np.int16)
            return _stub_range(samples, _to_counts(az))[:size], intensity

        def azimuth(t: float) -> float:
            holder[0].azimuths.append((t, slope * t))
            return slope * t

        sup = BirisSupervisor(
            mem,
            mmap,
            clock,
            gate,
            acquire,
            azimuth,
            audit=audit,
            ramdisk=ramdisk,
            rng=np.random.default_rng(7),
            tilting=tilting,
            elevation_counts=elevation_counts,
        )
        rig = Rig(clock, mmap, mem, line, gate, audit, sup)
        holder.append(rig)
        if enables:
            rig.set_reg(OFF_CMD_INT_ENABLE, 1)
            rig.set_reg(OFF_DATA_INT_ENABLE, 1)
            rig.set_reg(OFF_MOTOR_ACCESS, 1)
        rigs.append(rig)
        sup.start()
        return rig

    yield make
    for rig in rigs:
        rig.sup.stop()
        rig.gate.close()
        rig.line.close()
        rig.mem.close()


def _rules(rig: Rig) -> list[Rule]:
    return [v.rule for v in rig.audit.violations]


def _assert_startup_shown(rig: Rig) -> None:
    """Once the sequence is accepted, ACQ_LINE reads -1 for as long as start-up lasts."""
    assert rig.sup.wait_for(lambda s: s.busy, WAIT)
    value = rig.reg(OFF_ACQ_LINE)
    if rig.clock.now() < rig.sup.sequence_starts[-1] + 0.240:  # a slow test may be too late
        assert value == ACQ_LINE_STARTUP


# -- boot, queries, refusals -------------------------------------------------------------------
def test_power_up_state(make_rig: RigFactory) -> None:
    rig = make_rig()
    assert rig.reg(OFF_COMMAND) == 0
    assert rig.reg(OFF_ACQ_LINE) == ACQ_LINE_END
    assert not rig.sup.booted
    assert not rig.sup.busy


def test_boot_ok(make_rig: RigFactory) -> None:
    rig = make_rig()
    status, raw = rig.execute(BiCommand.BI_BOOT, BOOT_FILE)
    assert status == BiStatus.OK
    assert decode_param(raw) == ""
    assert rig.sup.booted
    assert rig.sup.loaded_lut == 0
    assert rig.gate.raised_by("cmd") == 1
    assert rig.sup.commands_completed == 1
    assert rig.audit.violations == []


def test_boot_wrong_name(make_rig: RigFactory) -> None:
    rig = make_rig()
    status, _ = rig.execute(BiCommand.BI_BOOT, "/dd/users/biris/nosuch.par")
    assert status == BiStatus.NO_BOOT_FILE
    assert not rig.sup.booted


def test_boot_file_for_another_camera_is_refused(make_rig: RigFactory) -> None:
    rig = make_rig(samples=64, ramdisk=RamDisk(samples=128))
    status, raw = rig.execute(BiCommand.BI_BOOT, BOOT_FILE)
    assert status == BiStatus.BAD_PARAM
    assert "128" in decode_param(raw)
    assert not rig.sup.booted


def test_boot_file_parses() -> None:
    for samples in (64, 128):
        params = BootParameters.parse(boot_file_text(samples))
        assert params.samples == samples
        assert params.fields_per_acq == fields_per_acquisition(samples)
        assert params.startup_ms == 240
        assert params.has_calibration(0) and not params.has_calibration(5000)
    assert BOOT_FILE in RamDisk().names()
    with pytest.raises(ValueError):
        BootParameters.parse("samples 64\n")


@pytest.mark.parametrize("code", [BiCommand.BI_ACQUIRE, BiCommand.BI_START_CONTINUOUS])
def test_acquisition_refused_before_boot(make_rig: RigFactory, code: BiCommand) -> None:
    rig = make_rig()
    status, _ = rig.execute(code, "5")
    assert status == BiStatus.NOT_BOOTED
    assert rig.gate.raised_by("data") == 0
    assert rig.sup.acquisitions_made == 0


def test_address_answers(make_rig: RigFactory) -> None:
    rig = make_rig()
    dist = rig.answer(BiCommand.BI_GET_VME_ADDR_DIST)
    azim = rig.answer(BiCommand.BI_GET_VME_ADDR_AZIM)
    for text in (dist, azim):
        assert text.startswith("0x")
        offset = int(text, 16) - rig.mmap.biris_base
        assert 0 <= offset < rig.mmap.size
    assert int(dist, 16) - rig.mmap.biris_base == rig.mmap.range_offset
    assert int(azim, 16) - rig.mmap.biris_base == rig.mmap.azimuth_offset
    assert int(rig.answer(BiCommand.BI_GET_VME_INC_FRAME)) == rig.mmap.frame_size


def test_command_completion_delay_is_field_synchronised(make_rig: RigFactory) -> None:
    rig = make_rig(time_scale=10.0)
    delays = []
    for _ in range(5):
        start = rig.clock.now()
        rig.execute(BiCommand.BI_GET_VME_INC_FRAME)
        delays.append(rig.clock.now() - start)
    # up to one field to the next vsync plus at most 2 ms of jitter, plus scheduling slack
    assert all(20e-6 <= d < FIELD_PERIOD + 0.002 + LATE for d in delays), delays
    assert sorted(delays)[2] < FIELD_PERIOD + 0.002 + LATE / 5


def test_unknown_command(make_rig: RigFactory) -> None:
    rig = make_rig()
    status, _ = rig.execute(99)
    assert status == BiStatus.UNKNOWN_COMMAND
    status, _ = rig.execute(-3)
    assert status == BiStatus.UNKNOWN_COMMAND


@pytest.mark.parametrize("param", ["0", "-2", "abc", "1.5", " 3", "33", ""])
def test_bad_acquisition_count(make_rig: RigFactory, param: str) -> None:
    rig = make_rig(max_acquisitions=32)
    rig.boot()
    status, _ = rig.execute(BiCommand.BI_ACQUIRE, param)
    assert status == BiStatus.BAD_PARAM
    assert rig.sup.acquisitions_made == 0


def test_no_interrupts_when_enables_are_clear(make_rig: RigFactory) -> None:
    rig = make_rig(enables=False)
    rig.issue(BiCommand.BI_BOOT, BOOT_FILE)
    assert rig.sup.wait_for(lambda s: s.commands_completed == 1, WAIT)
    assert rig.reg(OFF_STATUS) == BiStatus.OK
    rig.set_reg(OFF_MOTOR_ACCESS, 1)
    rig.issue(BiCommand.BI_ACQUIRE, "3")
    assert rig.sup.wait_for(lambda s: s.commands_completed == 2, WAIT)
    assert rig.reg(OFF_COMMAND) == 0
    assert rig.sup.acquisitions_made == 3
    assert rig.line.wait(0.0) == 0
    assert rig.gate.raised == 0


# -- single acquisition sequences -------------------------------------------------------------
@pytest.mark.parametrize("samples", [64, 128])
def test_acquisition_sequence(make_rig: RigFactory, samples: int) -> None:
    n = 5
    rig = make_rig(samples=samples, time_scale=10.0)
    rig.boot()
    fpa = fields_per_acquisition(samples)
    t_write = rig.clock.now()
    rig.issue(BiCommand.BI_ACQUIRE, str(n))
    _assert_startup_shown(rig)

    lines: list[int] = []
    arrivals: list[float] = []
    total = 0
    while total < n + 2:
        count = rig.wait_irq()
        assert count > 0, f"interrupts stopped after {total}"
        total += count
        arrivals.append(rig.clock.now())
        lines.append(rig.reg(OFF_ACQ_LINE))
    assert rig.wait_irq(0.0) == 0

    # ACQ_LINE walks 0..n-1 then -128; a late sample can only skip ahead, never back
    order = [*range(n), ACQ_LINE_END]
    positions = [order.index(v) for v in lines]
    assert positions == sorted(positions), lines
    assert lines[-1] == ACQ_LINE_END
    assert rig.gate.raised_by("data") == n + 1
    assert rig.gate.raised_by("cmd") == rig.cmds_at_issue + 1  # once, after the boot's
    assert rig.reg(OFF_COMMAND) == 0
    assert rig.reg(OFF_STATUS) == BiStatus.OK
    assert decode_param(rig.param()) == str(n)
    assert rig.reg(OFF_CURRENT_FRAME) == n - 1
    assert rig.sup.acquisitions_made == n
    assert rig.audit.violations == []

    # the schedule: 240 ms start-up rounded up to fields, then one acquisition every fpa fields
    times = rig.sup.acquisition_times
    start = rig.sup.sequence_starts[-1]
    half = fpa * FIELD_PERIOD / 2.0
    startup = times[0] - half - start
    assert 0.240 <= startup < 0.240 + FIELD_PERIOD
    assert np.allclose(np.diff(times), fpa * FIELD_PERIOD, rtol=0, atol=1e-9)
    grid = (np.array(times) - half) / FIELD_PERIOD
    assert np.allclose(grid, np.round(grid), atol=1e-6)
    # what the driver saw: never ahead of the schedule, behind it only by its own lateness
    assert 0.240 <= arrivals[0] - t_write < 0.240 + 2 * FIELD_PERIOD + LATE
    for seen, t_seen in zip(lines, arrivals, strict=True):
        if seen != ACQ_LINE_END:
            exposure_start = times[seen] - half
            assert exposure_start - 1e-9 <= t_seen < exposure_start + LATE  # to a rounding

    # every frame written, none poisoned; the optics were asked once per acquisition
    for k in range(n):
        assert np.array_equal(
            rig.frame("range", k), rig.expected_range(_to_counts(rig.calls[k][0]))
        )
        assert not np.any(rig.frame("intensity", k) == POISON)
    assert len(rig.calls) == n


def test_current_frame_is_poison_previous_is_real(make_rig: RigFactory) -> None:
    n = 6
    rig = make_rig(time_scale=10.0)
    rig.boot()
    rig.issue(BiCommand.BI_ACQUIRE, str(n))
    checked = 0
    while True:
        assert rig.wait_irq() > 0
        rig.sup.hang()  # freeze the supervisor, then look at memory at leisure
        line = rig.reg(OFF_ACQ_LINE)
        if line == ACQ_LINE_END:
            rig.sup.unhang()
            break
        current = rig.reg(OFF_CURRENT_FRAME)
        assert line == current == rig.sup.exposing
        assert np.all(rig.frame("range", current) == POISON)
        assert np.all(rig.frame("intensity", current) == POISON)
        if current > 0:
            previous = rig.frame("range", current - 1)
            assert not np.any(previous == POISON)
            assert np.array_equal(
                previous, rig.expected_range(_to_counts(rig.calls[current - 1][0]))
            )
        checked += 1
        rig.sup.unhang()
    rig.wait_command()
    assert checked >= 1
    assert rig.sup.acquisitions_made == n
    times = rig.sup.acquisition_times  # hangs shift the schedule by whole fields only
    grid = (np.array(times) - FIELD_PERIOD) / FIELD_PERIOD
    assert np.allclose(grid, np.round(grid), atol=1e-6)


def test_azimuth_table_holds_mid_exposure_azimuth(make_rig: RigFactory) -> None:
    slope = 300.0  # counts per hardware second: the head turns during each exposure
    n = 6
    rig = make_rig(time_scale=10.0, slope=slope)
    rig.boot()
    rig.execute(BiCommand.BI_ACQUIRE, str(n))
    mids = rig.sup.acquisition_times  # start of exposure + 1 field (checked elsewhere)
    assert len(rig.azimuths) == n  # the head is sampled once per acquisition
    for k, (t_sample, counts) in enumerate(rig.azimuths):
        # asked for the reading of mid-exposure itself, however late the thread got there
        assert t_sample == pytest.approx(mids[k], abs=1e-9)
        assert rig.azimuth_entry(k) == round(counts)
        assert _to_counts(rig.calls[k][0]) == round(counts)  # the optics saw the same azimuth
        assert rig.frame("range", k)[1] == round(counts)


def test_without_motor_access_entries_are_left_alone(make_rig: RigFactory) -> None:
    n = 3
    rig = make_rig()
    rig.boot()
    rig.set_reg(OFF_MOTOR_ACCESS, 0)
    table = rig.mmap.addressing.azimuth_entry(0)
    rig.mem.write(table, np.full(n, -7, dtype=AZIMUTH_DTYPE).tobytes())
    status, _ = rig.execute(BiCommand.BI_ACQUIRE, str(n))
    assert status == BiStatus.OK
    assert [rig.azimuth_entry(k) for k in range(n)] == [-7] * n
    assert rig.sup.acquisitions_made == n
    assert _rules(rig) == [Rule.ACQUIRE_WITHOUT_MOTOR_ACCESS]


def test_dropped_data_interrupt(make_rig: RigFactory) -> None:
    n = 4
    rig = make_rig()
    rig.boot()
    rig.sup.drop_data_interrupt()
    rig.execute(BiCommand.BI_ACQUIRE, str(n))
    assert rig.gate.raised_by("data") == n + 1
    assert rig.gate.dropped == 1
    assert rig.gate.delivered == rig.gate.raised - 1


# -- the driver breaking the rules, and faults -------------------------------------------------
def test_command_rewritten_during_acquisition_is_recorded(make_rig: RigFactory) -> None:
    rig = make_rig()
    rig.boot()
    rig.issue(BiCommand.BI_ACQUIRE, "20")
    assert rig.wait_irq() > 0  # a data interrupt: busy
    rig.sup.hang()  # hold the sequence while the test writes, however slow it is
    assert rig.sup.busy
    rig.set_reg(OFF_COMMAND, BiCommand.BI_GET_VME_INC_FRAME)  # no hook: vsync polling sees it
    rig.sup.unhang()
    assert rig.sup.wait_for(lambda _: Rule.CMD_WHILE_BUSY in _rules(rig), WAIT)
    violation = rig.audit.violations[0]
    assert violation.registers == {
        "COMMAND": BiCommand.BI_GET_VME_INC_FRAME,
        "EXECUTING": BiCommand.BI_ACQUIRE,
    }
    rig.wait_command()
    assert rig.sup.acquisitions_made == 20  # the acquisition ran on; the query was lost
    assert rig.sup.commands_completed == 2
    assert _rules(rig) == [Rule.CMD_WHILE_BUSY]


def test_same_value_rewrite_is_caught_by_the_write_hook(make_rig: RigFactory) -> None:
    rig = make_rig()
    rig.boot()
    rig.issue(BiCommand.BI_ACQUIRE, "4")
    assert rig.wait_irq() > 0
    rig.sup.hang()
    assert rig.sup.busy
    rig.issue(BiCommand.BI_ACQUIRE, "4")  # same code: invisible to polling, seen by the hook
    rig.sup.unhang()
    rig.wait_command()
    assert _rules(rig) == [Rule.CMD_WHILE_BUSY]


def test_second_write_before_acceptance_is_caught_by_the_hook(make_rig: RigFactory) -> None:
    rig = make_rig()
    rig.sup.hang()  # nothing is accepted meanwhile
    rig.issue(BiCommand.BI_GET_VME_INC_FRAME)
    rig.issue(BiCommand.BI_GET_VME_ADDR_DIST)
    assert _rules(rig) == [Rule.CMD_WHILE_BUSY]
    rig.sup.unhang()
    rig.wait_command()


def test_hang_and_unhang(make_rig: RigFactory) -> None:
    rig = make_rig()
    rig.sup.hang()
    rig.issue(BiCommand.BI_GET_VME_INC_FRAME)
    assert rig.wait_irq(0.2) == 0  # 4 s of hardware time: the BIRIS timeout would fire
    assert rig.reg(OFF_COMMAND) == BiCommand.BI_GET_VME_INC_FRAME
    assert rig.sup.hung
    rig.sup.unhang()
    rig.wait_command()
    assert rig.reg(OFF_STATUS) == BiStatus.OK
    assert decode_param(rig.param()) == str(rig.mmap.frame_size)


def test_hang_during_acquisition_stops_it_and_unhang_resumes(make_rig: RigFactory) -> None:
    n = 8
    rig = make_rig()
    rig.boot()
    rig.issue(BiCommand.BI_ACQUIRE, str(n))
    assert rig.wait_irq() > 0
    rig.sup.hang()
    made = rig.sup.acquisitions_made
    rig.settle()
    assert rig.wait_irq(0.1) == 0
    assert rig.sup.acquisitions_made == made
    assert rig.reg(OFF_COMMAND) == BiCommand.BI_ACQUIRE
    rig.sup.unhang()
    rig.wait_command()
    assert rig.sup.acquisitions_made == n
    assert rig.gate.raised_by("data") == n + 1


@pytest.mark.parametrize("kind", ["unterminated", "bad_digits", None])
def test_garbage_param(make_rig: RigFactory, kind: GarbageKind | None) -> None:
    rig = make_rig()
    rig.sup.garbage_param(kind)
    status, raw = rig.execute(BiCommand.BI_GET_VME_ADDR_DIST)
    assert status == BiStatus.OK
    with pytest.raises(ValueError):
        int(decode_param(raw), 16)
    if kind == "unterminated":
        assert b"\0" not in raw
    good = rig.answer(BiCommand.BI_GET_VME_ADDR_DIST)  # only the next answer was spoilt
    assert int(good, 16) == rig.mmap.address(rig.mmap.range_offset)


def test_a_broken_optics_model_stops_the_supervisor_visibly(make_rig: RigFactory) -> None:
    rig = make_rig(bad_frames=True)
    rig.boot()
    rig.issue(BiCommand.BI_ACQUIRE, "2")
    assert rig.sup.wait_for(lambda s: s.failure is not None, WAIT)
    assert isinstance(rig.sup.failure, ValueError)


def test_start_and_stop_are_idempotent(make_rig: RigFactory) -> None:
    rig = make_rig()
    rig.sup.start()
    rig.sup.stop()
    rig.sup.stop()
    rig.sup.start()
    assert rig.answer(BiCommand.BI_GET_VME_INC_FRAME) == str(rig.mmap.frame_size)


# -- continuous mode ----------------------------------------------------------------------------
def test_continuous_ring_wraps_and_stop_leaves_it_consistent(make_rig: RigFactory) -> None:
    ring, stop_at = 4, 9
    rig = make_rig(samples=128, time_scale=10.0, max_acquisitions=ring)
    rig.boot()

    def stop_mid_exposure(call: int) -> None:
        # runs in the supervisor at mid-exposure: a driver writing STOP at that instant
        if call == stop_at:
            rig.mem.write(rig.mmap.biexec_offset + OFF_PARAM, encode_param(""))
            rig.set_reg(OFF_COMMAND, BiCommand.BI_STOP_CONTINUOUS)

    rig.on_acquire = stop_mid_exposure
    t_write = rig.clock.now()
    status, _ = rig.execute(BiCommand.BI_START_CONTINUOUS)
    assert status == BiStatus.OK
    assert rig.clock.now() - t_write < 2 * FIELD_PERIOD + LATE  # completes at once
    acq_line = rig.reg(OFF_ACQ_LINE)
    if rig.clock.now() < rig.sup.sequence_starts[-1] + 0.240:  # still in start-up
        assert acq_line == ACQ_LINE_STARTUP
    assert rig.sup.continuous

    # the host may issue commands meanwhile
    assert rig.answer(BiCommand.BI_GET_VME_INC_FRAME) == str(rig.mmap.frame_size)
    status, _ = rig.execute(BiCommand.BI_ACQUIRE, "3")
    assert status == BiStatus.BAD_PARAM

    lines: list[int] = []
    rig.cmds_at_issue = rig.gate.raised_by("cmd")  # the STOP comes from on_acquire
    while rig.gate.raised_by("cmd") == rig.cmds_at_issue or rig.consumed < rig.gate.delivered:
        assert rig.wait_irq() > 0
        lines.append(rig.reg(OFF_ACQ_LINE))
    assert rig.wait_irq(0.05) == 0  # stopped: no more data interrupts
    assert rig.sup.wait_for(lambda s: not s.continuous, 0.0)
    assert all(v in range(ring) for v in lines if v != ACQ_LINE_END), lines

    assert rig.reg(OFF_ACQ_LINE) == ACQ_LINE_END
    assert rig.sup.acquisitions_made == stop_at
    assert rig.sup.acquisitions_abandoned == 1
    assert rig.gate.raised_by("data") == stop_at + 1
    assert rig.reg(OFF_CURRENT_FRAME) == (stop_at - 1) % ring
    for slot in range(ring):
        frame = rig.frame("range", slot)
        assert not np.any(frame == POISON), slot
        assert not np.any(rig.frame("intensity", slot) == POISON), slot
        assert frame[1] == rig.azimuth_entry(slot), slot  # frame and azimuth from one lap
    # the ring wrapped: each slot holds its latest complete acquisition, and the abandoned
    # slot the one from the lap before
    for slot in range(ring):
        latest = max(k for k in range(stop_at) if k % ring == slot)
        assert rig.frame("range", slot)[1] == _to_counts(rig.calls[latest][0]), slot
    times = rig.sup.acquisition_times
    assert np.allclose(np.diff(times), 3 * FIELD_PERIOD, atol=1e-9)


def test_stop_when_not_continuous_just_completes(make_rig: RigFactory) -> None:
    rig = make_rig()
    rig.boot()
    before = rig.reg(OFF_ACQ_LINE)
    status, _ = rig.execute(BiCommand.BI_STOP_CONTINUOUS)
    assert status == BiStatus.OK
    assert rig.reg(OFF_ACQ_LINE) == before


# -- calibration tables -------------------------------------------------------------------------
def test_lut_loading_and_calibration_audits(make_rig: RigFactory) -> None:
    elevation = [100.0]
    tilting = [False]
    rig = make_rig(elevation_counts=lambda t: elevation[0], tilting=lambda: tilting[0])
    status, _ = rig.execute(BiCommand.BI_LOAD_LUT, "100")
    assert status == BiStatus.NOT_BOOTED
    rig.boot()
    assert rig.sup.loaded_lut == 0
    assert rig.answer(BiCommand.BI_LOAD_LUT, "100") == ""
    assert rig.sup.loaded_lut == 100
    for bad, expected in (("5000", BiStatus.NO_CALIBRATION), ("1.5", BiStatus.BAD_PARAM)):
        status, _ = rig.execute(BiCommand.BI_LOAD_LUT, bad)
        assert status == expected
    assert rig.sup.loaded_lut == 100

    rig.execute(BiCommand.BI_ACQUIRE, "2")
    assert rig.audit.violations == []
    _, tilt, lut = rig.calls[-1]
    assert lut is not None
    assert _to_counts(lut) == 100 and _to_counts(tilt) == 100

    elevation[0] = 101.0  # within a count: fine
    rig.execute(BiCommand.BI_ACQUIRE, "2")
    assert rig.audit.violations == []

    elevation[0] = 50.0
    rig.execute(BiCommand.BI_ACQUIRE, "3")
    assert _rules(rig) == [Rule.WRONG_CALIBRATION]  # once per episode, not per acquisition
    assert rig.audit.violations[0].registers == {"LUT": 100, "ELEVATION": 50}

    assert rig.answer(BiCommand.BI_LOAD_LUT, "-50") == ""
    elevation[0] = -50.0
    tilting[0] = True
    rig.execute(BiCommand.BI_ACQUIRE, "3")
    assert _rules(rig) == [Rule.WRONG_CALIBRATION, Rule.ACQUIRE_WHILE_TILTING]
