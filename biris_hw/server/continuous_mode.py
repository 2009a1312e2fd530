"""Appendix D's continuous mode: BIRIS acquiring into its ring without a command per sweep.

With ``BirisInitRecord.continuous_acquisition`` BIRIS is started once (BI_START_CONTINUOUS)
after initialisation and keeps acquiring into its ring, so the 240 ms start-up is paid once, not
per sweep. It is stopped (BI_STOP_CONTINUOUS) for a tilt, since no acquisition may run while
tilting, and restarted after. The ring is *live* once its first acquisition has begun
(CONTINUOUS_LIVE); only then may a sweep start, so a sweep's first acquisitions are never the
start-up's. ``ring`` is off, starting, live or stopping.
"""

from __future__ import annotations

from collections.abc import Callable

from biris_hw.ipc import Envelope
from biris_hw.server import messages as m
from biris_hw.server.admin_state import AdminState, BirisCommand, status_name
from regs.biexec import BiCommand, BiStatus, decode_param

__all__ = ["ContinuousMode"]


def _ring_answer(param: bytes) -> int:
    """BI_START_CONTINUOUS's answer: the ring's length in frames, 0 if unreadable."""
    try:
        return int(decode_param(param).strip(), 10)
    except ValueError:
        return 0


class ContinuousMode(AdminState):
    """BI_START_CONTINUOUS, BI_STOP_CONTINUOUS and CONTINUOUS_LIVE."""

    def _start_ring(self) -> None:
        if not self.ring_mode or self.ring != "off" or self.fault is not None:
            return
        if self.phase != "idle" or self.tilt is not None:
            return
        self.ring = "starting"

        def started(status: int, param: bytes) -> None:
            if status != BiStatus.OK or _ring_answer(param) <= 0:
                self._fault(
                    "protocol",
                    f"BI_START_CONTINUOUS failed: STATUS {status} ({status_name(status)}), "
                    f"answer {param.split(bytes(1))[0]!r}",
                )

        self._submit_command(BirisCommand(int(BiCommand.BI_START_CONTINUOUS), "", started))

    def _on_continuous_live(self, env: Envelope, msg: m.ContinuousLive) -> None:
        env.reply(None)
        if self.ring != "starting":
            return  # stopped again before its first acquisition
        self.ring = "live"
        self.counters["continuous_starts"] += 1
        self._rearm_timeout()
        self._run_deferred()
        self._check_idle_waiters()

    def _stop_ring(self, then: Callable[[], None]) -> None:
        """BI_STOP_CONTINUOUS, then ``then`` (also when a stop is already on its way)."""
        self.ring_stop_waiters.append(then)
        if self.ring == "stopping":
            return
        self.ring = "stopping"

        def stopped(status: int, param: bytes) -> None:
            self.ring = "off"
            waiters, self.ring_stop_waiters = self.ring_stop_waiters, []
            for waiter in waiters:
                waiter()
            self._check_idle_waiters()

        self._submit_command(BirisCommand(int(BiCommand.BI_STOP_CONTINUOUS), "", stopped))
