"""The fault panel: every hardware failure a driver must survive, on demand and clearable.

Each method breaks one thing the way the real target would; ``clear_*`` (or :meth:`clear_all`)
undoes it. The driver sees only registers and interrupts, exactly as on the VME target.

Host latency is a fault too: the hardware keeps its time while the driver's host is late to take
its interrupts (:meth:`FaultPanel.late_interrupts`) or its bus reads take longer
(:meth:`FaultPanel.slow_reads`), for a while (:meth:`FaultPanel.latency_burst`) or until
cleared. Delays are hardware seconds, like every time in the simulator, and drawn from seeded
generators, so a run that injects them is reproducible.
"""

from __future__ import annotations

import math
import random
import threading
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

from sim.bit3 import Bit3Coupler
from sim.irqgate import InterruptGate
from sim.latency import SlowReads
from sim.supervisor import BirisSupervisor
from sim.tech80 import Model7600

if TYPE_CHECKING:
    from biris_hw.bus.base import BusWindow
    from biris_hw.timebase import HwThread
    from sim.cia402 import SimulatedDrive

__all__ = ["FaultPanel"]


class FaultPanel:
    """``rig.faults``: parity and bus errors, the BIRIS crate's power, a hung supervisor, a
    locked pan shaft, a dead pan amplifier, interrupt troubles (coalesced, spurious, dropped), a
    malformed PARAM answer, and host latency (late interrupts, slow reads).

    ``seed`` (the rig's) seeds the late interrupts' delays unless a call gives its own;
    ``driver_windows`` returns the windows the driver reads through (``rig.hardware``'s), the
    ones :meth:`slow_reads` slows; ``remote_power(on)`` switches the BIRIS crate's power and
    returns the BIRIS that powered up, if one did (the rig's; without it the panel has none).
    """

    def __init__(
        self,
        supervisor: BirisSupervisor,
        board: Model7600,
        coupler: Bit3Coupler,
        level2: InterruptGate,
        level3: InterruptGate,
        pan_drive: SimulatedDrive | None = None,
        *,
        seed: int = 0,
        driver_windows: Callable[[], Iterable[BusWindow]] = tuple,
        remote_power: Callable[[bool], BirisSupervisor | None] | None = None,
    ) -> None:
        self._supervisor = supervisor
        self._remote_power = remote_power
        self._board = board
        self._pan_drive = pan_drive
        """The pan's CiA 402 drive when the axes are on CAN (``axes="canopen"``): the motor
        faults then act on its plant, under its lock."""
        self._coupler = coupler
        self._gates = (level2, level3)
        self._level2 = level2
        self._clock = level2.clock
        self._seed = seed
        self._slow = SlowReads(self._clock, driver_windows)
        self._lock = threading.Lock()
        self._timebase = self._clock.timebase
        self._burst_changed = self._timebase.Condition(self._lock)
        self._burst_generation = 0
        self._burst_until: float | None = None
        self._burst_timers: list[HwThread] = []

    # -- coupler ---------------------------------------------------------------------------------
    def parity_error(self) -> None:
        """A parity error on the coupler: sticky status bit, level-2 interrupt if enabled."""
        self._coupler.parity_error()

    def bus_error(self) -> None:
        """A failed bus cycle on the BIRIS VMEbus: sticky status bit, level-2 interrupt."""
        self._coupler.bus_error()

    def remote_power_off(self) -> None:
        """The BIRIS crate loses power (or the coupler's cable comes out): the coupler reports
        NO_CONNECT, every access across it times out (sticky TIMEOUT, a level-2 interrupt if
        error interrupts are enabled, a BusError to the accessor), and BIRIS stops dead. The
        host's crate (the Model 7600, the coupler's own node, a VM-USB) keeps running."""
        self._power(False)

    def remote_power_on(self) -> None:
        """Power is back: the coupler connects again and BIRIS powers up afresh, not booted
        (``rig.supervisor`` is then a new supervisor). A TIMEOUT the coupler latched stays set
        until the driver writes CLR_ERROR, as its reset does."""
        self._power(True)

    def _power(self, on: bool) -> None:
        if self._remote_power is None:
            raise RuntimeError("this fault panel has no BIRIS crate to power (no rig behind it)")
        powered_up = self._remote_power(on)
        if powered_up is not None:
            self._supervisor = powered_up

    # -- BIRIS -----------------------------------------------------------------------------------
    def hang_supervisor(self) -> None:
        """BIRIS stops answering: COMMAND is never cleared and no acquisition completes."""
        self._supervisor.hang()

    def clear_hang(self) -> None:
        self._supervisor.unhang()

    def garbage_param(self) -> None:
        """The next answer BIRIS leaves in PARAM is malformed."""
        self._supervisor.garbage_param()

    def drop_data_interrupt(self) -> None:
        """The next data interrupt is lost on the way."""
        self._supervisor.drop_data_interrupt()

    # -- motor -----------------------------------------------------------------------------------
    def stall_motor(self) -> None:
        """The pan shaft locks: the head stops dead where it is.

        As on the real HCTL-1000 the chip does not notice: a running profile goes on and ends
        on time, MOTOR_END_OF_SCAN fires, and the encoder stays where the shaft locked, so only
        a driver that compares the encoder with the destination sees the failure.
        """
        self._pan_plant("stalled", True)

    def clear_stall(self) -> None:
        """The shaft turns again; the head then runs to wherever the chip commands it."""
        self._pan_plant("stalled", False)

    def _pan_plant(self, attribute: str, value: bool) -> None:
        """Set one of the pan plant's failure flags, caught up to now under its owner's lock
        (the board's, or the CAN drive's: a CiA 402 drive notices a locked shaft by its
        following error and faults, EMCY 0x8611)."""
        if self._pan_drive is not None:
            self._pan_drive.set_plant(attribute, value)
            return
        with self._board.lock:
            self._board.catch_up()
            setattr(self._board.plants[0], attribute, value)

    def dead_amplifier(self) -> None:
        """The pan amplifier dies: its output stays at 0 V, so no torque reaches the shaft.

        The chip's profile and the end-of-scan interrupt behave normally; a head in motion
        coasts to rest (friction and the back emf brake it) and then stays put. The failure a
        real target shows for a blown fuse or an amplifier left disabled.
        """
        self._pan_plant("amplifier_dead", True)

    def clear_dead_amplifier(self) -> None:
        """The amplifier drives again; the head runs to wherever the chip commands it."""
        self._pan_plant("amplifier_dead", False)

    # -- interrupts ------------------------------------------------------------------------------
    def coalesce_interrupts(self, enabled: bool = True, burst: int = 3) -> None:
        """Deliver interrupts in bursts, so one wait sees a count above 1 (both levels)."""
        for gate in self._gates:
            gate.coalesce(enabled, burst)

    def lose_motor_interrupt(self) -> None:
        """The Model 7600's next end-of-motion interrupt is lost on the way (level 3): the
        board latches the end as usual, but no interrupt reaches the host. A driver that waits
        only for the edge never hears the move end.

        Raises:
            RuntimeError: the axes are CiA 402 drives (their end of motion is a CAN frame).
        """
        if self._pan_drive is not None:
            raise RuntimeError("the axes are CiA 402 drives: there is no level-3 interrupt")
        self._gates[1].drop_next("motor")

    def spurious_interrupt(self) -> None:
        """A level-2 interrupt with no cause behind it."""
        self._level2.spurious()

    # -- host latency ----------------------------------------------------------------------------
    def late_interrupts(self, max_delay_s: float, seed: int | None = None) -> None:
        """The host is late to take its interrupts: every interrupt on levels 2 and 3 reaches
        the driver's line late by a delay drawn uniformly in ``[0, max_delay_s]`` hardware
        seconds, in the order raised (one raised while an earlier one is held leaves with it or
        after it, never before).

        The delays come from ``seed`` (default: the rig's), one generator per level, started
        afresh by each call, so the same calls on the same rig give the same delays. With
        coalescing on as well, a burst is late as a whole.
        """
        if not (math.isfinite(max_delay_s) and max_delay_s >= 0.0):
            raise ValueError(f"max_delay_s must be finite and not negative, not {max_delay_s}")
        base = self._seed if seed is None else seed
        for level, gate in zip((2, 3), self._gates, strict=True):
            gate.late(max_delay_s, random.Random(f"biris-late-interrupts:{base}:{level}"))

    def clear_late_interrupts(self) -> None:
        """Deliver every interrupt held by lateness now (in order) and stop delaying; returns
        once they have reached the lines."""
        for gate in self._gates:
            gate.late(None)

    def slow_reads(self, delay_s: float) -> None:
        """The driver's bus is loaded: every read it makes through ``rig.hardware``'s windows
        (BIRIS memory, the Model 7600, the coupler; the VM-USB windows with
        ``transport="vmusb"``) takes ``delay_s`` hardware seconds longer, slept in the reading
        thread before the access. The simulator's own accesses are not slowed, nor are the
        reads a VM-USB's IRQ stack makes (the bridge makes them, not the host)."""
        self._slow.set(delay_s)

    def clear_slow_reads(self) -> None:
        """Reads take their usual time again."""
        self._slow.clear()

    def latency_burst(self, duration_s: float, max_delay_s: float, read_delay_s: float) -> None:
        """Late interrupts (``max_delay_s``) and slow reads (``read_delay_s``) for
        ``duration_s`` hardware seconds from now, then both cleared by a timer on the
        simulator's clock, whoever set them. A new burst replaces one still running."""
        if not (math.isfinite(duration_s) and duration_s > 0.0):
            raise ValueError(f"duration_s must be finite and positive, not {duration_s}")
        self.late_interrupts(max_delay_s)
        self.slow_reads(read_delay_s)
        with self._lock:
            self._burst_generation += 1
            until = self._burst_until = self._clock.now() + duration_s
            timer = self._timebase.Thread(
                target=self._end_burst,
                args=(self._burst_generation, until),
                name="faults-latency-burst",
                daemon=True,
            )
            self._burst_changed.notify_all()  # a burst still running ends its wait
            self._burst_timers = [t for t in self._burst_timers if not t.finished]
            self._burst_timers.append(timer)
            timer.start()

    def _end_burst(self, generation: int, until: float) -> None:
        """The burst's thread: at ``until`` (hardware time) clear both, unless a later burst
        (or clear_all) took over meanwhile, which ends the wait at once."""
        with self._lock:
            while generation == self._burst_generation:
                left = until - self._clock.now()
                if left <= 0.0:
                    break
                self._burst_changed.wait(self._clock.timeout_until(until), what="burst's end")
            if generation != self._burst_generation:
                return
            self._burst_until = None
        self.clear_late_interrupts()
        self.clear_slow_reads()

    @property
    def latency_burst_active(self) -> bool:
        """A :meth:`latency_burst` is running (its end has not come)."""
        with self._lock:
            return self._burst_until is not None

    @property
    def late_interrupt_bound_s(self) -> float | None:
        """The bound late interrupts' delays are drawn under; None while they are off."""
        return self._gates[0].late_bound

    @property
    def read_delay_s(self) -> float:
        """The delay each driver read takes longer, hardware seconds; 0.0 while off."""
        return self._slow.delay_s

    @property
    def late_interrupts_held(self) -> int:
        """Interrupts held by lateness on both levels, not yet delivered."""
        return sum(gate.late_pending for gate in self._gates)

    @property
    def late_interrupts_delivered(self) -> int:
        """Interrupts delivered late on both levels since the rig was built."""
        return sum(gate.late_delivered for gate in self._gates)

    @property
    def late_delay_max_s(self) -> float:
        """The largest delay drawn for a late interrupt so far, hardware seconds."""
        return max(gate.late_delay_max for gate in self._gates)

    @property
    def slow_reads_made(self) -> int:
        """Driver reads that :meth:`slow_reads` slowed since the rig was built."""
        return self._slow.made

    # -- all -------------------------------------------------------------------------------------
    def clear_all(self) -> None:
        """Undo every fault that persists (the coupler's sticky bits are the driver's to clear);
        a BIRIS crate without power is powered on again."""
        if self._remote_power is not None and not self._coupler.remote_powered:
            self.remote_power_on()
        self.clear_hang()
        self.clear_stall()
        self.clear_dead_amplifier()
        self.coalesce_interrupts(False)
        self._cancel_burst()
        self.clear_late_interrupts()
        self.clear_slow_reads()

    def _cancel_burst(self) -> None:
        with self._lock:
            self._burst_generation += 1
            self._burst_until = None
            self._burst_changed.notify_all()

    def close(self) -> None:
        """Stop a burst's timer and join it, and take the slow-read wrappers off the windows:
        the rig calls it as it closes, so no thread is left behind."""
        self._cancel_burst()
        with self._lock:
            timers, self._burst_timers = self._burst_timers, []
        for timer in timers:
            if timer is not threading.current_thread():
                self._timebase.join_thread(timer)
        self.clear_slow_reads()
