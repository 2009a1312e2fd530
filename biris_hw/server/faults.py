"""The server's lifecycle: initialising, idle, or faulted, and who waits on it.

A fault -- BIRIS_BUS_ERR or BIRIS_PARITY_ERR from their notifiers, a BIRIS timeout, a stalled
motor, a protocol error -- ends everything under way, and every blocked and later call gets the
:class:`HardwareFault` until a reset initialises the server again: the report's server can only
report such failures, and a client must not wait for data that will not come. The initialiser
(:mod:`biris_hw.server.initialiser`) runs in a worker of its own so that the administrator never
waits on it; RESET_REQUEST starts it, INIT_DONE ends it.
"""

from __future__ import annotations

import enum
import logging

from biris_hw.errors import FaultKind, HardwareFault, Initialising, RequestError
from biris_hw.ipc import Envelope

__all__ = ["Lifecycle", "Phase", "fail_quietly", "log"]

log = logging.getLogger("biris_hw.server.admin")
"""The administrator thread's messages, whichever module writes them: one name to configure."""


def fail_quietly(env: Envelope, exc: BaseException) -> None:
    """Fail ``env``; one that was already answered has nobody left to tell."""
    try:
        env.fail(exc)
    except Exception:
        log.debug("envelope already answered", exc_info=True)


class Phase(enum.Enum):
    INITIALISING = "initialising"
    IDLE = "idle"  # initialised: serving requests (the activities say what it does)


class Lifecycle:
    """Phase, fault, and the callers parked on initialisation or on idleness."""

    def __init__(self) -> None:
        self.phase = Phase.INITIALISING
        self.fault: HardwareFault | None = None
        self.init_waiters: list[Envelope] = []
        self.idle_waiters: list[Envelope] = []

    @property
    def initialising(self) -> bool:
        return self.phase is Phase.INITIALISING

    def check_usable(self) -> None:
        """Raise the fault, or Initialising (a RequestError): what every request checks."""
        if self.fault is not None:
            raise self.fault
        if self.phase is Phase.INITIALISING:
            raise Initialising("the server is initialising")

    def begin_reset(self, env: Envelope) -> None:
        """RESET_REQUEST: the fault is forgotten and initialisation (re)starts."""
        if self.phase is Phase.INITIALISING and self.init_waiters:
            raise RequestError("initialisation is already running")
        self.init_waiters.append(env)
        self.phase = Phase.INITIALISING
        self.fault = None

    def initialised(self) -> list[Envelope]:
        """INIT_DONE: idle; returns the reset callers to answer."""
        self.phase = Phase.IDLE
        waiters, self.init_waiters = self.init_waiters, []
        return waiters

    def enter_fault(self, kind: FaultKind, text: str) -> HardwareFault | None:
        """The fault state; None when already in one (the first fault is the one reported)."""
        if self.fault is not None:
            return None
        fault = HardwareFault(kind, text)
        log.error("hardware fault: %s", fault)
        self.fault = fault
        waiters, self.idle_waiters = self.idle_waiters, []
        for env in waiters:
            fail_quietly(env, fault)
        return fault

    def release_idle_waiters(self) -> None:
        waiters, self.idle_waiters = self.idle_waiters, []
        for env in waiters:
            env.reply(None)
