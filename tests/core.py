"""A thread-free harness for the administrator: a message in, replies and orders out.

The administrator only ever answers envelopes; it never blocks. So a test can play every task
of the report itself, in one thread: post a message, let :meth:`Administrator.handle` run its
case, and look at which envelopes were answered and with what. Workers are played by keeping
their READY envelope (the order arrives as its reply), notifiers by posting what they would post,
and timers by :class:`FakeTimer` on a :class:`VirtualClock` that the test advances by hand. No
thread, no sleep, no real time: the report's rules are checked exactly and fast.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from biris_hw import protocol as p
from biris_hw.data import ConnectionKind, DeliveryPolicy
from biris_hw.ipc import Mailbox, Ticket
from biris_hw.records import BirisInitRecord
from biris_hw.server import messages as m
from biris_hw.server.admin import Administrator
from biris_hw.server.initialiser import InitResult
from regs.biexec import BiCommand
from regs.layout import FrameAddressing
from regs.tech80 import Axis

__all__ = ["Core", "FakeTimer", "VirtualClock"]


class VirtualClock:
    """Hardware time that moves only when the test says so."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@dataclass
class FakeTimer:
    """A deadline timer without a thread: :meth:`Core.advance` fires it."""

    clock: VirtualClock
    make: Callable[[int], object]
    deadline: float | None = None
    generation: int = 0
    arms: list[float] = field(default_factory=list)

    def arm(self, hw_seconds: float, real_slack_s: float = 0.0) -> int:
        self.generation += 1
        self.deadline = self.clock() + hw_seconds
        self.arms.append(hw_seconds)
        return self.generation

    def disarm(self) -> None:
        self.generation += 1
        self.deadline = None


class Core:
    """One administrator, its workers parked, driven by hand."""

    PERIOD = 2 / 59.94
    """The acquisition period the initialiser reports (2 fields)."""
    SAMPLES = 64

    def __init__(
        self,
        record: BirisInitRecord | None = None,
        *,
        recheck_biris: bool = False,
        lag: Callable[[], float] | None = None,
    ) -> None:
        self.record = record if record is not None else BirisInitRecord()
        self.task_resets = 0
        """The supervisor's reset count the administrator reads (the tests move it as a
        reset's initialiser would, restarting the failed tasks)."""
        self.clock = VirtualClock()
        self.inbox = Mailbox("core")
        self.biris_timeout = FakeTimer(self.clock, m.BirisTimeoutErr)
        self.az_watchdog = FakeTimer(self.clock, m.MotorWatchdogErr)
        self.el_watchdog = FakeTimer(
            self.clock, lambda generation: m.MotorWatchdogErr(generation, Axis.ELEVATION)
        )
        self.initialiser_starts = 0
        self.rechecks = 0
        """How many times the administrator asked the level-3 routine to look again."""
        self.biris_rechecks = 0
        """How many times it asked the level-2 routine to read BIRIS afresh (``recheck_biris``:
        without, a BIRIS timeout is a fault at once, as with a routine that cannot look)."""
        self.admin = Administrator(
            self.record,
            self.inbox,
            self.clock,
            self.biris_timeout,
            self.az_watchdog,
            self._start_initialiser,
            self.el_watchdog,
            recheck_motion=self._recheck,
            recheck_biris=self._recheck_biris if recheck_biris else None,
            lag=lag,
            task_generation=lambda: self.task_resets,
        )
        self.transfer = self.send(m.CmdTransferRdy())
        self.notifier: Ticket | None = None
        self.workers = {
            Axis.AZIMUTH: self.send(m.AzReady()),
            Axis.ELEVATION: self.send(m.ElReady()),
        }

    def _start_initialiser(self) -> None:
        self.initialiser_starts += 1

    def _recheck(self) -> None:
        self.rechecks += 1

    def _recheck_biris(self) -> None:
        self.biris_rechecks += 1

    # -- the inbox ---------------------------------------------------------------------------
    def send(self, message: object) -> Ticket:
        """Post ``message`` and run its case; the ticket says whether it was answered."""
        ticket = self.inbox.post(message)
        envelope = self.inbox.try_receive()
        assert envelope is not None
        self.admin.handle(envelope)
        return ticket

    def call(self, message: object) -> object:
        """A client's request that must be answered at once; returns the answer (or raises)."""
        ticket = self.send(message)
        assert ticket.done, f"{message!r} was not answered"
        return ticket.wait(0)

    def advance(self, seconds: float) -> None:
        """Move hardware time on; every timer whose deadline passes reports as its task would."""
        self.clock.now += seconds
        for timer in (self.biris_timeout, self.az_watchdog, self.el_watchdog):
            if timer.deadline is not None and timer.deadline <= self.clock.now:
                timer.deadline = None
                self.send(timer.make(timer.generation))

    # -- lifecycle ---------------------------------------------------------------------------
    def initialise(self) -> Ticket:
        """RESET_REQUEST and a successful INIT_DONE, as the server's start does."""
        reset = self.send(p.ResetRequest(0))
        result = self.init_done()
        assert reset.done and reset.wait(0) is result
        return reset

    def init_done(self) -> InitResult:
        """A successful INIT_DONE from the initialiser (after a RESET_REQUEST); its result."""
        addressing = FrameAddressing(range_offset=0x1000, frame_size=130, azimuth_offset=0x8000)
        result = InitResult(addressing, self.SAMPLES, self.PERIOD)
        self.send(m.InitDone(None, result))
        return result

    def open(
        self, kind: ConnectionKind = ConnectionKind.NORMAL, policy: DeliveryPolicy | None = None
    ) -> int:
        chosen = policy if policy is not None else DeliveryPolicy.LATEST
        answer = self.call(p.OpenRequest(kind, threading.current_thread(), chosen))
        assert isinstance(answer, tuple)
        return int(answer[0])

    # -- the command worker and notifier -----------------------------------------------------
    def command(self, *, start: bool = True) -> m.TransferOrder | None:
        """The command biris_cmd_transfer was ordered to write (it then parks again), if any.

        A BI_ACQUIRE's start-up is taken to end at once (``start``): SEQUENCE_STARTED follows,
        as the data notifier sends it at the first acquisition, and the scan's motor starts.
        ``start=False`` leaves that to :meth:`started`.
        """
        if not self.transfer.done:
            return None
        order = self.transfer.wait(0)
        assert isinstance(order, m.TransferOrder)
        self.transfer = self.send(m.CmdTransferRdy())
        if start and order.code == BiCommand.BI_ACQUIRE:
            self.started(order.seq_id)
        return order

    def started(self, seq_id: int) -> None:
        """SEQUENCE_STARTED: BI_ACQUIRE sequence ``seq_id`` has begun its first acquisition."""
        self.send(m.SequenceStarted(seq_id, self.clock.now))

    def complete(self, order: m.TransferOrder, status: int = 0, param: bytes = b"") -> None:
        """BIRIS_CMD_COMPLETE for ``order``, from biris_cmd_notifier (which then parks)."""
        self.notifier = self.send(m.BirisCmdComplete(status, param, order.token))

    # -- the axis workers and notifiers ------------------------------------------------------
    def move(self, axis: Axis = Axis.AZIMUTH) -> m.MoveOrder | m.ParamsOrder | None:
        """The order an axis worker was given (it then reports ready again), if any."""
        worker = self.workers[axis]
        if not worker.done:
            return None
        order = worker.wait(0)
        assert isinstance(order, (m.MoveOrder, m.ParamsOrder)), order
        ready = m.AzReady() if axis is Axis.AZIMUTH else m.ElReady()
        self.workers[axis] = self.send(ready)
        return order

    def arrive(
        self,
        axis: Axis = Axis.AZIMUTH,
        *,
        position: int | None = None,
        settled: bool = True,
        token: int | None = None,
    ) -> None:
        """AZ_SCAN_DONE / EL_SCAN_DONE: the move ended and the head came to rest (at
        ``position`` as the notifier read it; None: not read, so not verified)."""
        done = m.AzScanDone if axis is Axis.AZIMUTH else m.ElScanDone
        self.send(done(position=position, settled=settled, token=token))

    # -- data --------------------------------------------------------------------------------
    def acquisitions(
        self, seq_id: int, indices: range, azimuth: Callable[[int], int] = lambda k: 10 * (k + 1)
    ) -> None:
        """NEW_POINT with acquisitions ``indices`` of sequence ``seq_id`` (by default made on the
        way from 0 and away from it, so that none is taken for one made standing at the start)."""
        profile = np.full(self.SAMPLES, 1000, dtype=np.int16)
        profile.setflags(write=False)
        acqs = tuple(
            m.Acquisition(
                seq_id=seq_id,
                index=k,
                azimuth=azimuth(k),
                closest_mm=1000,
                profile=profile,
                intensity=profile,
                t=self.clock.now + k * 0.0334,
                discarded=0,
            )
            for k in indices
        )
        self.send(m.NewPoint(acqs))
