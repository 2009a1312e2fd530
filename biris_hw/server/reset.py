"""Initialisation and reset: the server's way from nothing (or a fault) to idle.

The initialiser (:mod:`biris_hw.server.initialiser`) runs in a worker of its own so that the
administrator never waits on it; it sends its BIRIS commands and motions here (INIT_COMMAND,
INIT_MOVE) so that they go through the same queues, workers and notifiers as a scan's, and
reports INIT_DONE. RESET_REQUEST forgets everything under way and starts it again.
"""

from __future__ import annotations

from collections import deque

from biris_hw.errors import HardwareFault, RequestError
from biris_hw.ipc import Envelope
from biris_hw.server import messages as m
from biris_hw.server.admin_state import AdminState, BirisCommand, fail_quietly
from biris_hw.server.initialiser import InitResult
from biris_hw.server.motion import Motion

__all__ = ["Reset"]


class Reset(AdminState):
    """RESET_REQUEST, and the initialiser's INIT_COMMAND, INIT_MOVE and INIT_DONE."""

    def _on_reset(self, env: Envelope, msg: m.ResetRequest) -> None:
        if msg.conn:
            self._conn(msg.conn)
        if self.phase == "initialising" and self.init_waiters:
            raise RequestError("initialisation is already running")
        self.init_waiters.append(env)
        self.phase = "initialising"
        self.fault = None
        self._clear_activity()
        self.ring = "off"
        self._start_initialiser()

    def _on_init_command(self, env: Envelope, msg: m.InitCommand) -> None:
        cmd = BirisCommand(
            msg.code,
            msg.param,
            on_done=lambda status, param: env.reply((status, param)),
            on_fail=lambda exc: fail_quietly(env, exc),
        )
        self.init_commands.append(cmd)
        self._submit_command(cmd)

    def _on_init_move(self, env: Envelope, msg: m.InitMove) -> None:
        def done(err: str | None) -> None:
            if err is None:
                env.reply(None)
            else:
                fail_quietly(env, HardwareFault("motor_stall", err))

        self._submit_motion(
            self._axis(msg.axis),
            Motion(
                m.MoveOrder(msg.destination),
                on_done=done,
                on_fail=lambda exc: fail_quietly(env, exc),
            ),
        )

    def _on_init_done(self, env: Envelope, msg: m.InitDone) -> None:
        env.reply(None)
        waiters, self.init_waiters = self.init_waiters, []
        # commands the initialiser gave up on must not be issued later
        stale = {id(c) for c in self.init_commands}
        self.cmd_queue = deque(c for c in self.cmd_queue if id(c) not in stale)
        self.init_commands.clear()
        if msg.error is not None:
            exc = msg.error
            fault = (
                exc
                if isinstance(exc, HardwareFault)
                else HardwareFault("protocol", f"initialisation failed: {exc}")
            )
            self.phase = "idle"
            self._fault(fault.kind, fault.message)
            for w in waiters:
                fail_quietly(w, fault)
            return
        result = msg.addressing
        assert isinstance(result, InitResult)
        self.samples = result.samples
        self.phase = "idle"
        self.az.position = 0
        self.el.position = 0
        self.elevation = 0
        self.lut = 0  # the initialiser loaded the table for the level head
        for w in waiters:
            w.reply(result)
        self._start_ring()
        self._check_idle_waiters()
