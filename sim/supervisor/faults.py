"""Faults the simulator can inject into the supervisor, for the driver to survive.

**Faults.** :meth:`~SupervisorFaults.hang` freezes the supervisor: nothing is polled, written or
raised; :meth:`~SupervisorFaults.unhang` resumes where it was, the whole schedule shifted by the
hang rounded up to whole fields. :meth:`~SupervisorFaults.garbage_param` makes the next query
answer (BI_GET_*) malformed. :meth:`~SupervisorFaults.drop_data_interrupt` loses the next data
interrupt.
"""

from __future__ import annotations

from sim.supervisor.state import GarbageKind, SupervisorState

__all__ = ["SupervisorFaults"]


class SupervisorFaults(SupervisorState):
    """hang/unhang, garbage_param, drop_data_interrupt."""

    def hang(self) -> None:
        """Freeze: COMMAND is never completed, acquisitions stop, nothing is cleared or raised."""
        with self._lock:
            if self._hung_since is None:
                self._hung_since = self._clock.now()

    def unhang(self) -> None:
        """Resume; the schedule moves on by the hang's length, rounded up to whole fields."""
        with self._lock:
            if self._hung_since is None:
                return
            self._hung_since = None
            self._shift_schedule()
            self._changed.notify_all()
        self._kick.set()

    def garbage_param(self, kind: GarbageKind | None = None) -> None:
        """Make the next query answer malformed: no NUL terminator, or digits that are not hex.

        With no ``kind`` the seeded generator picks one when the answer is written.
        """
        with self._lock:
            self._garbage_armed = True
            self._garbage = kind

    def drop_data_interrupt(self) -> None:
        """Lose the next data interrupt."""
        self._gate.drop_next("data")
