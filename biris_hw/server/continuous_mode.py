"""Appendix D's continuous acquisition: BIRIS acquiring into its ring without a command per sweep.

In continuous acquisition BIRIS is started once (BI_START_CONTINUOUS) and keeps acquiring into
its ring, so the 240 ms start-up is paid once, not per sweep. It is stopped (BI_STOP_CONTINUOUS)
for a tilt, since no acquisition may run while tilting, and restarted after. The ring is *live*
once its first acquisition has begun (CONTINUOUS_LIVE); only then may a sweep start, so a
sweep's first acquisitions are never the start-up's.

**The mode.** ``BirisInitRecord.continuous_acquisition`` chooses it when the server is built
(and the ring then starts after initialisation); a client switches it at run time with the
report's START_CONTINUOUS and STOP_CONTINUOUS messages:

* START_CONTINUOUS starts the ring at once, as Appendix D says the message "would produce a
  continuous sequence of acquisitions" -- unless a scan runs (or waits to start, or continuous
  scanning is on). Then it is *pending*, as BIRIS_HOME is, and takes effect once scanning has
  ended: a sweep is acquired in one mode from start to end, and continuous scanning keeps the
  mode it started in until BIRIS_STOP_SCAN_RQST ends it.
* STOP_CONTINUOUS "would cease all acquisitions immediately": the mode is single at once, a
  start still pending is withdrawn, and BI_STOP_CONTINUOUS is issued at once if the ring runs,
  even under a sweep (what becomes of that sweep is the administrator's to say).
* Both are idempotent; a reset returns to the init record's choice (what the server was built
  with), as it returns to the init record's motor parameters.

A scan in single acquisition needs the ring *off*, not merely the mode switched: BIRIS refuses
BI_ACQUIRE while it acquires continuously, so a scan asked for while BI_STOP_CONTINUOUS is on
its way waits for it (:meth:`Ring.ready`).

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
    """The continuous-acquisition ring: whether it is used, a switch asked for, and its state."""

    def __init__(self, mode: bool) -> None:
        self.default = mode
        """The init record's ``continuous_acquisition``: the mode after a reset."""
        self.mode = mode
        """Appendix D's acquisition is selected: scans are sweeps over the ring."""
        self.pending_start = False
        """START_CONTINUOUS came while scanning: the mode switches once scanning ends."""
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

    @property
    def name(self) -> str:
        """The mode in force, as status and the data say it: "continuous" or "single"."""
        return "continuous" if self.mode else "single"

    @property
    def pending_name(self) -> str | None:
        """The mode asked for and not in force yet (status's ``acquisition_pending``)."""
        return "continuous" if self.pending_start else None

    def ready(self) -> bool:
        """BIRIS may acquire for a scan: the ring is live (continuous acquisition), or it is off
        (single acquisition: BIRIS refuses BI_ACQUIRE while a ring runs, so a scan waits for a
        BI_STOP_CONTINUOUS on its way)."""
        return self.state is (RingState.LIVE if self.mode else RingState.OFF)

    # -- the client's switch (START_CONTINUOUS / STOP_CONTINUOUS) ------------------------------
    def ask_start(self, *, scanning: bool) -> bool:
        """START_CONTINUOUS; True when the mode has switched now (the ring is then to start).

        While ``scanning`` the start is only noted (:attr:`pending_start`), and
        :meth:`take_pending` makes it so once scanning has ended. Already continuous: nothing.
        """
        if self.mode:
            return False
        if scanning:
            self.pending_start = True
            return False
        self.mode = True
        return True

    def take_pending(self) -> bool:
        """Scanning has ended: a pending START_CONTINUOUS switches the mode now; True if it did
        (the ring is then to start)."""
        if not self.pending_start:
            return False
        self.pending_start = False
        self.mode = True
        return True

    def ask_stop(self) -> bool:
        """STOP_CONTINUOUS: single acquisition from now on, and a pending start withdrawn; True
        when the ring runs (starting or live) and BI_STOP_CONTINUOUS is to be issued now. A ring
        already stopping, or off, needs nothing more."""
        self.pending_start = False
        self.mode = False
        return self.state in (RingState.STARTING, RingState.LIVE)

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

    def reset(self) -> None:
        """A reset: the ring forgotten (:meth:`forget`), and the mode back to the init record's,
        a pending switch dropped. The server is initialised from its init record again, as it
        is for the motor parameters: a client that wants the other mode asks again."""
        self.forget()
        self.mode = self.default
        self.pending_start = False
