"""The fault state: what a hardware fault stops, and who is told.

A fault -- BIRIS_BUS_ERR or BIRIS_PARITY_ERR from their notifiers, a BIRIS timeout, a stalled
motor, a protocol error -- ends everything under way, and every blocked and later call gets the
:class:`HardwareFault` until a reset initialises the server again: the report's server can only
report such failures, and a client must not wait for data that will not come.
"""

from __future__ import annotations

from biris_hw.errors import ConnectionClosed, FaultKind, HardwareFault
from biris_hw.ipc import Envelope
from biris_hw.server.admin_state import AdminState, fail_quietly, log

__all__ = ["Faults"]


class Faults(AdminState):
    """BIRIS_BUS_ERR, BIRIS_PARITY_ERR, and every fault found elsewhere."""

    def _task_fault(self, env: Envelope, kind: FaultKind, text: str) -> None:
        """A notifier's report of a fault: released at once, then the fault state."""
        env.reply(None)
        self._fault(kind, text)

    def _fault(self, kind: FaultKind, text: str) -> None:
        if self.fault is not None:
            return
        fault = HardwareFault(kind, text)
        log.error("hardware fault: %s", fault)
        self.fault = fault
        self.counters["faults"] += 1
        self.biris_timeout.disarm()
        for axis in (self.az, self.el):
            axis.fail_all(fault)  # before forgetting them: the initialiser may wait on one
        self._clear_activity()
        for cmd in list(self.cmd_queue):
            cmd.on_fail(fault)
        self.cmd_queue.clear()
        if self.current_cmd is not None and self.current_cmd in self.init_commands:
            self.current_cmd.on_fail(fault)
        waiters, self.idle_waiters = self.idle_waiters, []
        for env in waiters:
            fail_quietly(env, fault)
        self.clients.fail_waiting(fault)

    def shutdown(self) -> None:
        """Called by the server after this thread has ended: nobody may stay blocked."""
        stopped = ConnectionClosed("the BIRIS server has stopped")
        for env in self.idle_waiters + self.init_waiters:
            fail_quietly(env, stopped)
        self.clients.fail_waiting(stopped, forget=False)
