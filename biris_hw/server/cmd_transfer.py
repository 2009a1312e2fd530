"""The command channel: BIRIS commands one at a time, and the BIRIS timeout that watches them.

The report's rule: a new BIRIS command only after BIRIS_CMD of the previous one was serviced
(``Biris_ready``). Commands therefore wait in a queue; one is issued when BIRIS is ready *and*
_Biris_cmd_transfer is parked on CMD_TRANSFER_RDY, and just before it is issued the parked
_Biris_cmd_notifier is replied, so that it is blocked on its interrupt again before BIRIS can
raise it. Each transfer carries a token, so a BIRIS_CMD_COMPLETE that belongs to a transfer
abandoned by a reset is recognised and ignored.

_Biris_timeout is armed whenever BIRIS owes the server an answer and the client enabled it. What
BIRIS owes is the administrator's to say (a completion, a continuous-mode sweep's data, its
ring's start), so it passes ``owed`` in; BIRIS_TIMEOUT_ERR counts only if it is the latest arming
and BIRIS still owes that answer, since a timer message may cross the answer in the inbox.

A command carries its *purpose* (why it was issued) and what it was issued for (the scan, the
tilt, the initialiser's envelope); the administrator maps the purpose to the named method that
handles the completion, so what follows a command can be found by reading, not by tracing a
stored closure.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from biris_hw.ipc import Envelope
from biris_hw.server.messages import TransferOrder
from regs.biexec import BiCommand, BiStatus

if TYPE_CHECKING:
    from biris_hw.server.elevation import Tilt
    from biris_hw.server.scan_assembly import ActiveScan
    from biris_hw.server.start_schedule import StartSchedule

__all__ = [
    "BirisCommand",
    "CommandChannel",
    "CommandPurpose",
    "Timer",
    "command_name",
    "status_name",
]


TIMEOUT_REAL_SLACK_S = 0.1
"""Real seconds the BIRIS timeout allows on top of its hardware seconds.

The countdown is the report's 4 s per command on the hardware clock, restarted by every
acquisition, so a sequence longer than 4 s never times out while data arrive. But the evidence
of life reaches the administrator through threads the host schedules: on a simulator clock 30
times fast, 100 ms of starvation is 3 hardware seconds. The slack keeps a busy host from
faking a hang; at x1 it adds 0.1 s to the 4 s bound."""


class Timer(Protocol):
    """What the administrator needs of a deadline timer (the real one is a task; tests fake it)."""

    def arm(self, hw_seconds: float, real_slack_s: float = 0.0) -> int: ...

    def disarm(self) -> None: ...


class CommandPurpose(enum.Enum):
    """Why a BIRIS command was issued: names the administrator's case for its completion."""

    ACQUIRE = "acquire"  # BI_ACQUIRE of a report-mode scan
    LOAD_LUT = "load_lut"  # BI_LOAD_LUT of a tilt
    START_CONTINUOUS = "start_continuous"  # Appendix D's ring
    STOP_CONTINUOUS = "stop_continuous"
    INIT = "init"  # the initialiser's (replied to its envelope)


@dataclass(eq=False)
class BirisCommand:
    """One BIEXEC_COM command on its way to BIRIS, and what it was issued for."""

    code: int
    param: str
    purpose: CommandPurpose
    n: int = 0
    """Acquisitions a BI_ACQUIRE asks for (0 for any other command)."""
    seq_id: int = 0
    scan: ActiveScan | None = None
    tilt: Tilt | None = None
    requester: Envelope | None = None
    """The initialiser's INIT_COMMAND, replied with (STATUS, PARAM)."""
    token: int = 0
    """Which transfer this is, so a late completion of an abandoned one is recognised."""
    schedule: StartSchedule | None = None
    """BI_ACQUIRE of a report-mode scan: the schedule its trapezoid starts by."""


def command_name(code: int) -> str:
    """A BIEXEC_COM COMMAND's name (BI_STOP_CONTINUOUS, not 9), for a fault's message: the
    operator holding the report finds it there."""
    try:
        return BiCommand(code).name
    except ValueError:
        return f"command {code}"


def status_name(status: int) -> str:
    """A BIEXEC_COM STATUS's name, for a fault's message."""
    try:
        return BiStatus(status).name
    except ValueError:
        return "error"


class CommandChannel:
    """The queue of BIRIS commands, the one in flight, the parked workers and the timeout."""

    def __init__(self, timer: Timer, timeout_s: float, timeout_enabled: bool = True) -> None:
        self._timer = timer
        self._timeout_s = timeout_s
        self._queue: deque[BirisCommand] = deque()
        self.current: BirisCommand | None = None
        """The command BIRIS is executing (issued, not yet completed)."""
        self._transfer_env: Envelope | None = None
        """_Biris_cmd_transfer, parked on CMD_TRANSFER_RDY."""
        self._notifier_env: Envelope | None = None
        """_Biris_cmd_notifier, parked on its last BIRIS_CMD_COMPLETE."""
        self._token = 0
        self.timeout_enabled = timeout_enabled
        """On unless the init record turns it off; BIRIS_TIMEOUT_ENABLE/DISABLE toggle it."""
        self._timeout_gen = -1
        self._rechecking = False
        self._alive = False
        """BIRIS has shown life since the recheck was asked (an acquisition, a completion)."""

    @property
    def timeout_s(self) -> float:
        return self._timeout_s

    def busy(self) -> bool:
        """A command runs or waits."""
        return self.current is not None or bool(self._queue)

    # -- the command flow --------------------------------------------------------------------
    def submit(self, cmd: BirisCommand) -> None:
        """Queue ``cmd``; :meth:`pump` issues it once BIRIS and the worker are ready."""
        self._queue.append(cmd)

    def pump(self) -> BirisCommand | None:
        """Issue the next command if BIRIS is ready and the worker parked; returns it."""
        if self.current is not None or self._transfer_env is None or not self._queue:
            return None
        cmd = self._queue.popleft()
        self.current = cmd
        self.release_notifier()  # put the notifier back on its interrupt first
        env, self._transfer_env = self._transfer_env, None
        self._token += 1
        cmd.token = self._token
        env.reply(TransferOrder(cmd.code, cmd.param, cmd.seq_id, cmd.n, cmd.token, cmd.schedule))
        return cmd

    def worker_ready(self, env: Envelope) -> None:
        """CMD_TRANSFER_RDY: the worker is parked until the next command."""
        self._transfer_env = env

    @property
    def worker_parked(self) -> bool:
        """The worker waits for an order: nothing handed to it is still unwritten."""
        return self._transfer_env is not None

    def complete(self, env: Envelope, token: int) -> BirisCommand | None:
        """BIRIS_CMD_COMPLETE: the command it completes, or None when it is stale.

        The notifier stays parked (replied just before the next command is issued).
        """
        if self.current is None or token != self.current.token:
            env.reply(None)  # stale: nothing will follow it, so the notifier goes straight back
            return None
        self._notifier_env = env
        cmd, self.current = self.current, None
        return cmd

    def release_notifier(self) -> None:
        """Reply to the parked notifier, if it still waits (a case that failed after parking
        it has answered it already, with the error)."""
        env, self._notifier_env = self._notifier_env, None
        if env is not None and env.waiting:
            env.reply(None)

    def discard(self, keep: Callable[[BirisCommand], bool] | None = None) -> list[BirisCommand]:
        """Take waiting commands out of the queue (those ``keep`` refuses, or all); returns them.

        The command in flight stays: BIRIS is executing it, and its completion must still be
        recognised (as stale, or for whoever waits on it).
        """
        if keep is None:
            dropped, self._queue = list(self._queue), deque()
            return dropped
        dropped = [c for c in self._queue if not keep(c)]
        self._queue = deque(c for c in self._queue if keep(c))
        return dropped

    def abandon(self) -> list[BirisCommand]:
        """A reset: every command, waiting or in flight, is given up; returns them.

        BIRIS may still be executing the one in flight: its completion arrives with a token
        nobody waits for and is counted stale; whoever issues the next command (the
        initialiser) first waits until BIRIS has finished it.
        """
        dropped = [*([self.current] if self.current is not None else []), *self._queue]
        self._queue.clear()
        self.current = None
        return dropped

    def waiting(self) -> Iterable[BirisCommand]:
        return tuple(self._queue)

    # -- _Biris_timeout ----------------------------------------------------------------------
    def rearm_timeout(self, owed: bool) -> None:
        """Arm the timeout afresh if enabled and BIRIS owes an answer, else disarm it.

        Also how life from BIRIS (an acquisition) restarts the countdown.
        """
        self._alive = True
        if self.timeout_enabled and owed:
            self._timeout_gen = self._timer.arm(self._timeout_s, TIMEOUT_REAL_SLACK_S)
        else:
            self._rechecking = False
            self._timer.disarm()

    def note_alive(self, owed: bool) -> None:
        """BIRIS has shown life: the countdown starts over if it runs (never disarms)."""
        self._alive = True
        if self.timeout_enabled and owed:
            self._timeout_gen = self._timer.arm(self._timeout_s, TIMEOUT_REAL_SLACK_S)

    # -- the recheck: hardware time in which BIRIS did not progress, not a host that did not look
    @property
    def rechecking(self) -> bool:
        """The timeout ran out and BIRIS is being read afresh; its answer decides."""
        return self._rechecking

    def begin_recheck(self) -> None:
        """The timeout ran out: BIRIS is to be read afresh. The countdown runs again meanwhile
        (only to ask again if the answer is slow in coming: a routine that cannot answer at all
        is a failed task, which the supervisor reports)."""
        self._rechecking = True
        self._alive = False
        self._timeout_gen = self._timer.arm(self._timeout_s, TIMEOUT_REAL_SLACK_S)

    def end_recheck(self, progressed: bool) -> bool:
        """The answer to the recheck; True when it proves a hang: BIRIS made no acquisition and
        completed nothing in the timeout's hardware seconds, however late the host looked."""
        if not self._rechecking:
            return False
        self._rechecking = False
        return not (progressed or self._alive)

    def timed_out(self, generation: int, owed: bool) -> bool:
        """BIRIS_TIMEOUT_ERR: True if it is the latest arming and BIRIS still owes."""
        return generation == self._timeout_gen and owed

    def enable_timeout(self, owed: bool) -> None:
        self.timeout_enabled = True
        self.rearm_timeout(owed)

    def disable_timeout(self) -> None:
        self.timeout_enabled = False
        self._rechecking = False
        self._timer.disarm()

    def stop_timer(self) -> None:
        """Disarm without changing whether the timeout is enabled (a fault, a reset)."""
        self._rechecking = False
        self._timer.disarm()
