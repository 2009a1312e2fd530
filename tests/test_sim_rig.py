"""SimulatedBiris as a whole: what it hands a driver, reproducibility, and a clean shutdown.

Every rig here runs on virtual time (issue 22): hardware time moves only while the test waits
through the rig's time base, so what each test sees does not depend on the host's speed.
"""

from __future__ import annotations

import pytest

import sim
from biris_hw import BirisHardware
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.timebase import HwEvent
from regs import biexec
from regs.layout import BirisMemoryMap
from regs.tech80 import MOTION_WINDOW_SIZE
from sim import POISON, Scene, SimulatedBiris
from sim.clock import FIELD_PERIOD, SimClock
from sim.ramdisk import BOOT_FILE
from sim.supervisor.state import JITTER_S
from tests.conftest import until


def test_the_design_names_are_there() -> None:
    assert POISON == 0x7A7A
    assert sim.Scene is Scene and sim.SimulatedBiris is SimulatedBiris


def test_the_hardware_bundle_describes_the_target(no_leaks: None) -> None:
    with SimulatedBiris(
        scene=Scene.circle(2.0), samples=128, time_scale=20.0, seed=1, clock="virtual"
    ) as rig:
        hw = rig.hardware
        assert isinstance(hw, BirisHardware)
        mm = BirisMemoryMap(samples=128)
        assert hw.biris.size == mm.size and hw.motion.size == MOTION_WINDOW_SIZE
        assert hw.biexec_offset == mm.biexec_offset and hw.biris_base == mm.biris_base
        assert isinstance(hw.level2, EventFdLine) and isinstance(hw.level3, EventFdLine)
        assert hw.time_scale == 20.0
        t0 = hw.clock()
        assert hw.clock() >= t0 >= 0.0
        # BIRIS powers up idle, not booted, with nothing to say
        assert hw.biris.read16(hw.biexec_offset + biexec.OFF_COMMAND) == 0
        assert not rig.supervisor.booted
        assert rig.audit.violations == []


def test_a_seed_fixes_where_the_head_wakes_up(no_leaks: None) -> None:
    with (
        SimulatedBiris(seed=5, clock="virtual") as a,
        SimulatedBiris(seed=5, clock="virtual") as b,
        SimulatedBiris(seed=6, clock="virtual") as c,
    ):
        assert a.azimuth_counts == pytest.approx(b.azimuth_counts, abs=0.01)
        assert a.azimuth_counts != pytest.approx(c.azimuth_counts, abs=0.01)
        assert -2048 <= a.azimuth_counts < 2048


def test_shutdown_leaves_no_thread_or_descriptor(no_leaks: None) -> None:
    rig = SimulatedBiris(time_scale=30.0, clock="virtual")
    rig.start()
    rig.faults.coalesce_interrupts(True)  # pending timers must be cancelled too
    rig.faults.spurious_interrupt()
    rig.close()
    rig.close()  # idempotent
    with pytest.raises(RuntimeError):
        rig.start()


def test_a_buffer_of_the_callers_holds_biris_memory(no_leaks: None) -> None:
    mm = BirisMemoryMap()
    buffer = bytearray(mm.size)
    with SimulatedBiris(biris_buffer=memoryview(buffer), time_scale=20.0, clock="virtual") as rig:
        rig.hardware.biris.write16(mm.biexec_offset + biexec.OFF_PARAM, 0x4142)
        assert buffer[mm.biexec_offset + biexec.OFF_PARAM] == 0x41
    with pytest.raises(ValueError):
        SimulatedBiris(biris_buffer=bytearray(16), clock="virtual")


def test_a_command_written_straight_into_a_shared_buffer_is_seen_at_the_next_field(
    no_leaks: None,
) -> None:
    """A driver in another process (``biris sim``) writes COMMAND into the shared segment
    itself, past the tap that wakes an idle supervisor: BIRIS there still looks at every field,
    so a query written after 100.25 idle fields completes within its jitter of field 101."""
    mm = BirisMemoryMap()
    buffer = bytearray(mm.size)
    with SimulatedBiris(biris_buffer=memoryview(buffer), time_scale=30.0, clock="virtual") as rig:
        rig.timebase.sleep(100.25 * FIELD_PERIOD, what="idle fields")
        at = mm.biexec_offset + biexec.OFF_COMMAND
        buffer[at : at + 2] = int(biexec.BiCommand.BI_GET_VME_INC_FRAME).to_bytes(2, "big")
        assert rig.supervisor.wait_for(lambda s: s.commands_completed == 1, 5.0)
        done = rig.clock.now()
    assert 101 * FIELD_PERIOD < done <= 101 * FIELD_PERIOD + JITTER_S[1]


class _StarvingClock:
    """The supervisor's view of the clock, with a thread that never gets to run: every wait
    blocks until the test lets go, as on a host too busy to schedule it. The block is a wait
    through the rig's time base that only the release ends, so hardware time runs on without
    the thread (as a busy host's would) while the test waits."""

    def __init__(self, clock: SimClock) -> None:
        self._clock = clock
        self.release = clock.timebase.Event()
        self.waiting = clock.timebase.Event()

    def now(self) -> float:
        return self._clock.now()

    def wait_until(self, t_hw: float, stop: HwEvent) -> bool:
        self.waiting.set()
        while not self.release.wait(1.0, what="a starved supervisor"):
            if stop.is_set():
                return False
        return self._clock.wait_until(t_hw, stop)


def test_a_starved_supervisor_is_caught_up_by_the_drivers_reads(no_leaks: None) -> None:
    """BIRIS never lags the video fields: a driver read does what the starved thread has not."""
    rig = SimulatedBiris(time_scale=20.0, clock="virtual")
    starving = _StarvingClock(rig.clock)
    rig.supervisor._clock = starving  # type: ignore[assignment]
    try:
        rig.start()
        until(starving.waiting.is_set, what="the supervisor's first wait")  # stuck from here on
        hw = rig.hardware
        command = hw.biexec_offset + biexec.OFF_COMMAND
        hw.biris.write16(command, 99)  # unknown: refused at the next field, after a jitter
        until(  # each read lets the simulator catch up; nothing else can complete it
            lambda: hw.biris.read16(command) == 0, what="a driver read to complete the command"
        )
        assert (
            hw.biris.read16(hw.biexec_offset + biexec.OFF_STATUS) == biexec.BiStatus.UNKNOWN_COMMAND
        )
        assert rig.supervisor.commands_completed == 1
        assert rig.supervisor.failure is None
    finally:
        starving.release.set()
        rig.close()


def test_a_hook_reading_biris_memory_from_inside_an_event_is_not_a_recursion(
    no_leaks: None,
) -> None:
    """An interrupt hook runs inside the supervisor's field; its read must not start it over."""
    with SimulatedBiris(time_scale=20.0, clock="virtual") as rig:
        hw = rig.hardware
        base = hw.biexec_offset

        def execute(code: int, param: str) -> None:
            done = rig.supervisor.commands_completed + 1  # before the write: it may be quick
            hw.biris.write(base + biexec.OFF_PARAM, biexec.encode_param(param))
            hw.biris.write16(base + biexec.OFF_COMMAND, code)
            assert rig.supervisor.wait_for(lambda s: s.commands_completed == done, 5.0)

        execute(biexec.BiCommand.BI_BOOT, BOOT_FILE)
        hw.biris.write16(base + biexec.OFF_DATA_INT_ENABLE, 1)
        hw.biris.write16(base + biexec.OFF_MOTOR_ACCESS, 1)  # as a driver must (audited)
        lines: list[int] = []
        rig.level2_gate.on_raise = lambda source, t_ns: lines.append(
            hw.biris.read16(base + biexec.OFF_ACQ_LINE)
        )
        execute(biexec.BiCommand.BI_ACQUIRE, "3")
        # one data interrupt per acquisition begun, and one after the last: each read once
        assert rig.level2_gate.raised_by("data") == len(lines) == 4
        assert rig.supervisor.failure is None and rig.supervisor.acquisitions_made == 3
