"""Appendix D's continuous acquisition: BIRIS acquiring into its ring without a command per sweep.

With ``BirisInitRecord.continuous_acquisition`` BIRIS is started once (BI_START_CONTINUOUS)
after initialisation and keeps acquiring into its ring, so the 240 ms start-up is paid once, not
per sweep. It is stopped (BI_STOP_CONTINUOUS) for a tilt, since no acquisition may run while
tilting, and restarted after. The ring is *live* once its first acquisition has begun
(CONTINUOUS_LIVE); only then may a sweep start, so a sweep's first acquisitions are never the
start-up's.

:class:`Ring` owns that state; its transitions are the table :data:`TRANSITIONS`, and every
change goes through it, so an impossible step (live without starting) is an error, not a
silently odd state.
"""

from __future__ import annotations

import enum

__all__ = ["TRANSITIONS", "Ring", "RingState"]


class RingState(enum.Enum):
    """Where BIRIS's continuous acquisition stands, as the administrator knows it."""

    OFF = "off"
    STARTING = "starting"  # BI_START_CONTINUOUS issued, no acquisition yet
    LIVE = "live"  # acquisitions arrive
    STOPPING = "stopping"  # BI_STOP_CONTINUOUS issued


TRANSITIONS: dict[RingState, frozenset[RingState]] = {
    RingState.OFF: frozenset({RingState.STARTING}),
    RingState.STARTING: frozenset({RingState.LIVE, RingState.STOPPING}),
    RingState.LIVE: frozenset({RingState.STOPPING}),
    RingState.STOPPING: frozenset({RingState.OFF}),
}
"""Every step the ring may take (a reset or a fault sets OFF from anywhere: :meth:`Ring.forget`)."""


class Ring:
    """The continuous-acquisition ring: whether it is used, and its state."""

    def __init__(self, mode: bool) -> None:
        self.mode = mode
        """Appendix D's acquisition is selected (the init record's ``continuous_acquisition``)."""
        self.state = RingState.OFF

    def _go(self, new: RingState) -> None:
        if new not in TRANSITIONS[self.state]:
            raise AssertionError(f"ring: {self.state.value} -> {new.value} is not a transition")
        self.state = new

    @property
    def off(self) -> bool:
        return self.state is RingState.OFF

    @property
    def live(self) -> bool:
        return self.state is RingState.LIVE

    @property
    def starting(self) -> bool:
        return self.state is RingState.STARTING

    @property
    def stopping(self) -> bool:
        return self.state is RingState.STOPPING

    def ready(self) -> bool:
        """BIRIS may acquire for a sweep: report mode, or the ring is live."""
        return not self.mode or self.state is RingState.LIVE

    def settled(self) -> bool:
        """Nothing is on its way: off or live (for ``is_idle``)."""
        return self.state in (RingState.OFF, RingState.LIVE)

    def start(self) -> bool:
        """Begin starting if the mode wants a ring and none runs; True if BI_START_CONTINUOUS
        must now be issued."""
        if not self.mode or self.state is not RingState.OFF:
            return False
        self._go(RingState.STARTING)
        return True

    def went_live(self) -> bool:
        """CONTINUOUS_LIVE; False if the ring was stopped again before its first acquisition."""
        if self.state is not RingState.STARTING:
            return False
        self._go(RingState.LIVE)
        return True

    def stop(self) -> bool:
        """Begin stopping; True if BI_STOP_CONTINUOUS must now be issued (none on its way)."""
        if self.state is RingState.STOPPING:
            return False
        if self.state is RingState.OFF:
            raise AssertionError("ring: stop while off")
        self._go(RingState.STOPPING)
        return True

    def stopped(self) -> None:
        """BI_STOP_CONTINUOUS completed."""
        self._go(RingState.OFF)

    def forget(self) -> None:
        """A reset: BIRIS is made to stop acquiring by the initialiser, whatever it did."""
        self.state = RingState.OFF
