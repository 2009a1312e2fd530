"""Command transfers from the server to BIRIS, and the BIRIS timeout that watches them.

The report's rule: a new BIRIS command only after BIRIS_CMD of the previous one was serviced
(``Biris_ready``). Commands therefore wait in a queue; one is issued when BIRIS is ready *and*
_Biris_cmd_transfer is parked on CMD_TRANSFER_RDY, and just before it is issued the parked
_Biris_cmd_notifier is replied, so that it is blocked on its interrupt again before BIRIS can
raise it. Each transfer carries a token, so a BIRIS_CMD_COMPLETE that belongs to a transfer
abandoned by a reset is recognised and ignored.

_Biris_timeout is armed whenever BIRIS owes the server an answer (a completion, a continuous-mode
sweep's data, its ring's start) and the client enabled it; BIRIS_TIMEOUT_ERR is a fault only if it
is the latest arming and BIRIS still owes that answer, since a timer message may cross the answer
in the inbox.
"""

from __future__ import annotations

from biris_hw.ipc import Envelope
from biris_hw.server import messages as m
from biris_hw.server.admin_state import AdminState, BirisCommand

__all__ = ["BirisCommands"]


class BirisCommands(AdminState):
    """CMD_TRANSFER_RDY, BIRIS_CMD_COMPLETE, BIRIS_TIMEOUT_ENABLE/DISABLE, BIRIS_TIMEOUT_ERR."""

    def _submit_command(self, cmd: BirisCommand) -> None:
        self.cmd_queue.append(cmd)
        self._pump_commands()

    def _pump_commands(self) -> None:
        if self.fault is not None or not self.biris_ready or self.transfer_env is None:
            return
        if not self.cmd_queue:
            return
        cmd = self.cmd_queue.popleft()
        self.current_cmd = cmd
        self.biris_ready = False
        if self.cmd_notifier_env is not None:  # put the notifier back on its interrupt first
            self.cmd_notifier_env.reply(None)
            self.cmd_notifier_env = None
        env, self.transfer_env = self.transfer_env, None
        self.cmd_token += 1
        cmd.token = self.cmd_token
        env.reply(m.TransferOrder(cmd.code, cmd.param, cmd.seq_id, cmd.n, cmd.token))
        self._rearm_timeout()

    def _on_cmd_transfer_rdy(self, env: Envelope, msg: m.CmdTransferRdy) -> None:
        self.transfer_env = env
        self._pump_commands()

    def _on_cmd_complete(self, env: Envelope, msg: m.BirisCmdComplete) -> None:
        self.cmd_notifier_env = env  # replied just before the next command is issued
        if self.current_cmd is None or msg.token != self.current_cmd.token:
            self.counters["stale_completions"] += 1
            return
        cmd, self.current_cmd = self.current_cmd, None
        self.biris_ready = True
        self._rearm_timeout()
        cmd.on_done(msg.status, msg.param)
        self._pump_commands()
        self._check_idle_waiters()

    # -- _Biris_timeout ----------------------------------------------------------------------
    def _biris_expected(self) -> bool:
        """BIRIS owes a completion, a continuous-mode sweep's data, or its ring's start."""
        scan = self.scan
        return (
            self.current_cmd is not None
            or (scan is not None and scan.ring and not scan.cmd_done)
            or self.ring == "starting"
        )

    def _note_biris_alive(self) -> None:
        """BIRIS has shown life (an acquisition): the timeout starts over if it runs."""
        if self.timeout_enabled and self._biris_expected():
            self.timeout_gen = self.biris_timeout.arm(self.record.timeout_s)

    def _rearm_timeout(self) -> None:
        if self.timeout_enabled and self._biris_expected():
            self.timeout_gen = self.biris_timeout.arm(self.record.timeout_s)
        else:
            self.biris_timeout.disarm()

    def _on_timeout_err(self, env: Envelope, msg: m.BirisTimeoutErr) -> None:
        env.reply(None)
        if msg.generation == self.timeout_gen and self._biris_expected():
            self._fault(
                "timeout", f"BIRIS did not respond for {self.record.timeout_s:g} s of hardware time"
            )

    def _on_timeout_enable(self, env: Envelope, msg: m.TimeoutEnable) -> None:
        self._usable_conn(msg.conn)
        self.timeout_enabled = True
        self._rearm_timeout()
        env.reply(None)

    def _on_timeout_disable(self, env: Envelope, msg: m.TimeoutDisable) -> None:
        self._usable_conn(msg.conn)
        self.timeout_enabled = False
        self.biris_timeout.disarm()
        env.reply(None)
