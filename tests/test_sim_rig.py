"""SimulatedBiris as a whole: what it hands a driver, reproducibility, and a clean shutdown."""

from __future__ import annotations

import pytest

import sim
from biris_hw import BirisHardware
from biris_hw.irq.eventfd import EventFdLine
from regs import biexec
from regs.layout import BirisMemoryMap
from regs.tech80 import MOTION_WINDOW_SIZE
from sim import POISON, Scene, SimulatedBiris


def test_the_design_names_are_there() -> None:
    assert POISON == 0x7A7A
    assert sim.Scene is Scene and sim.SimulatedBiris is SimulatedBiris


def test_the_hardware_bundle_describes_the_target(no_leaks: None) -> None:
    with SimulatedBiris(scene=Scene.circle(2.0), samples=128, time_scale=20.0, seed=1) as rig:
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
    with SimulatedBiris(seed=5) as a, SimulatedBiris(seed=5) as b, SimulatedBiris(seed=6) as c:
        assert a.azimuth_counts == pytest.approx(b.azimuth_counts, abs=0.01)
        assert a.azimuth_counts != pytest.approx(c.azimuth_counts, abs=0.01)
        assert -2048 <= a.azimuth_counts < 2048


def test_shutdown_leaves_no_thread_or_descriptor(no_leaks: None) -> None:
    rig = SimulatedBiris(time_scale=30.0)
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
    with SimulatedBiris(biris_buffer=memoryview(buffer), time_scale=20.0) as rig:
        rig.hardware.biris.write16(mm.biexec_offset + biexec.OFF_PARAM, 0x4142)
        assert buffer[mm.biexec_offset + biexec.OFF_PARAM] == 0x41
    with pytest.raises(ValueError):
        SimulatedBiris(biris_buffer=bytearray(16))
