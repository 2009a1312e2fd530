"""How the long-running commands (``biris watch``, ``biris view``) live through a fault.

A server in a fault (``state=fault:<kind>``) stays in it until it is reset, and keeps running:
it still answers ``status()``, and a reset (``conn.reset()``, from this program or from a
controller of the service it is reached through) brings it back. A command that shows the
sensor for as long as a person wants therefore shows the fault too and goes on, rather than
ending: ending would hide the very state a person is watching for, and lose the view of the
sensor coming back. :class:`FaultNotice` says on stderr, once per fault, what the fault is
(the server's own message) and how to recover, and once that the server has left it; at the
end it gives the exit status: 1 (:data:`~biris_hw.commands.failures.EXIT_FAULT`) when the server
was in a fault as the command ended, else 0, so that a script still learns that the sensor
needs attention.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from biris_hw.commands.console import prog_of
from biris_hw.commands.failures import EXIT_FAULT, error_line
from biris_hw.errors import BirisError, HardwareFault
from biris_hw.status import ServerState

if TYPE_CHECKING:
    from biris_hw.sensor import Sensor
    from biris_hw.status import ServerStatus

__all__ = ["FaultNotice", "fault_of", "recovery_hint"]


def recovery_hint(args: argparse.Namespace) -> str:
    """How to bring the server out of a fault, for the server this command uses.

    A served sensor (``--connect NAME``) is reset by one of its controllers, with ``biris
    reset --connect``; a server of the command's own (``--sim``, ``--target``, ``--attach``)
    only by the program holding it, so by restarting the command.
    """
    name = getattr(args, "connect", None)
    if name is not None:
        endpoints = "".join(f" --endpoint {e}" for e in getattr(args, "endpoint", None) or ())
        return f"check the sensor, then a controller runs: biris reset --connect {name}{endpoints}"
    return "check the sensor, then reset the server (conn.reset() or restart the command)"


def fault_of(server: Sensor, status: ServerStatus) -> HardwareFault:
    """The fault the server is in, with its own message: a poll (``wait_idle(timeout=0)``) on a
    connection of our own raises it. The status names only the kind, so that is what is left
    when the poll cannot say more (the fault was cleared meanwhile, the link failed)."""
    kind = status.fault or "internal"
    try:
        with server.open() as conn:
            conn.wait_idle(timeout=0)
    except HardwareFault as exc:
        return exc
    except (BirisError, TimeoutError):
        pass
    return HardwareFault(kind, "reported by the server's status")


class FaultNotice:
    """Follows the server's state through the statuses a command reads, and says on stderr
    when it enters a fault (once per fault: the fault, the server's message and
    :func:`recovery_hint`, then ``going_on``, what the command does meanwhile) and when it has
    left it.

    stderr is looked up at each line, not kept: a live display (rich) that has taken stderr
    over prints the line above itself instead of being scribbled over.
    """

    def __init__(self, server: Sensor, args: argparse.Namespace, going_on: str) -> None:
        self._server = server
        self._prog = prog_of(args)
        self._hint = recovery_hint(args)
        self._going_on = going_on
        self._faults_seen: int | None = None
        self.fault: HardwareFault | None = None
        """The fault the server is in, as of the last status seen; None outside a fault."""

    @property
    def faulted(self) -> bool:
        """Whether the last status seen was a fault."""
        return self.fault is not None

    def met(self, fault: HardwareFault) -> None:
        """A fault the command met first-hand (a request of its own failed with it): said with
        its own message even when a reset elsewhere has already cleared it by the time the
        command reads the status, so a loaded host that looks late still says it."""
        if self.fault is None or self.fault.kind != fault.kind:
            self.fault = fault
            self._say_fault(fault)

    def observe(self, status: ServerStatus) -> bool:
        """Take the latest status into account; returns whether it is a fault."""
        faults = status.counters.get("faults")
        came_and_went = (
            faults is not None
            and self._faults_seen is not None
            and faults > self._faults_seen
            and self.fault is None
        )
        if faults is not None:
            self._faults_seen = faults
        if status.state is ServerState.FAULT:
            if self.fault is None or self.fault.kind != status.fault:
                self.fault = fault_of(self._server, status)
                self._say_fault(self.fault)
            return True
        if self.fault is not None:
            self.fault = None
            self._say(f"the server has left the fault (state {status.state_name})")
        elif came_and_went:
            # between two looks the server met a fault and was reset: never silent
            self._say(
                f"the server met a hardware fault and was reset between two looks (faults "
                f"counted: {faults}); its state is {status.state_name}"
            )
        return False

    def _say_fault(self, fault: HardwareFault) -> None:
        self._say(
            f"{error_line(fault)}; the server stays in this fault until it is "
            f"reset: {self._hint}; {self._going_on}"
        )

    def exit_status(self) -> int:
        """0, or 1 (said on stderr) when the server was in a fault as the command ended."""
        if self.fault is None:
            return 0
        self._say(f"ended with the server still in the fault ({self.fault.kind})")
        return EXIT_FAULT

    def _say(self, text: str) -> None:
        print(f"{self._prog}: {text}", file=sys.stderr, flush=True)
