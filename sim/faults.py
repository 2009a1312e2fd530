"""The fault panel: every hardware failure a driver must survive, on demand and clearable.

Each method breaks one thing the way the real target would; ``clear_*`` (or :meth:`clear_all`)
undoes it. The driver sees only registers and interrupts, exactly as on the VME target.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sim.bit3 import Bit3Coupler
from sim.irqgate import InterruptGate
from sim.supervisor import BirisSupervisor
from sim.tech80 import Model7600

if TYPE_CHECKING:
    from sim.cia402 import SimulatedDrive

__all__ = ["FaultPanel"]


class FaultPanel:
    """``rig.faults``: parity and bus errors, a hung supervisor, a locked pan shaft, a dead pan
    amplifier, and interrupt troubles (coalesced, spurious, dropped), plus a malformed PARAM
    answer."""

    def __init__(
        self,
        supervisor: BirisSupervisor,
        board: Model7600,
        coupler: Bit3Coupler,
        level2: InterruptGate,
        level3: InterruptGate,
        pan_drive: SimulatedDrive | None = None,
    ) -> None:
        self._supervisor = supervisor
        self._board = board
        self._pan_drive = pan_drive
        """The pan's CiA 402 drive when the axes are on CAN (``axes="canopen"``): the motor
        faults then act on its plant, under its lock."""
        self._coupler = coupler
        self._gates = (level2, level3)
        self._level2 = level2

    # -- coupler ---------------------------------------------------------------------------------
    def parity_error(self) -> None:
        """A parity error on the coupler: sticky status bit, level-2 interrupt if enabled."""
        self._coupler.parity_error()

    def bus_error(self) -> None:
        """A failed bus cycle on the BIRIS VMEbus: sticky status bit, level-2 interrupt."""
        self._coupler.bus_error()

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

    # -- all -------------------------------------------------------------------------------------
    def clear_all(self) -> None:
        """Undo every fault that persists (the coupler's sticky bits are the driver's to clear)."""
        self.clear_hang()
        self.clear_stall()
        self.clear_dead_amplifier()
        self.coalesce_interrupts(False)
