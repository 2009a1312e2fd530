"""The floor under the data path: the bare hand-over chain, with no server logic in it.

An acquisition reaches a client through four threads, whatever the server does besides: the
simulator writes an eventfd (the interrupt), a thread polling it takes the interrupt and hands
the item to the administrator's inbox, the administrator passes it to the client's parked
READY_FOR_DATA, and the client's thread wakes up holding it. :func:`hand_over_floor` runs that
chain and nothing else, with the primitives the real path uses (``os.eventfd``, ``select.poll``,
:class:`biris_hw.ipc.Mailbox` post / receive / reply), at the sensor's cadence, and times it
from the eventfd write to the client thread holding the item.

The server's own cost is then the ratio of a real latency figure to this floor, both measured in
the same run on the same machine (``latency_us.server_over_floor``).

This module registers no benchmark; the ``latency_us`` section calls it.
"""

from __future__ import annotations

import os
import select
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from biris_hw.errors import ConnectionClosed
from biris_hw.ipc import Envelope, Mailbox, Ticket

__all__ = ["FloorRun", "hand_over_floor"]


@dataclass(frozen=True)
class _Ready:
    """The client's READY_FOR_DATA."""


@dataclass(frozen=True)
class _NewItem:
    """The poller's NEW_POINT: the ``seq``-th eventfd write (the newest, if several coalesced)."""

    seq: int


@dataclass
class FloorRun:
    """What one run of the chain measured."""

    latencies_us: list[float] = field(default_factory=list)
    """Eventfd write to the client thread holding the item, one per delivery waited for."""
    written: int = 0
    """Eventfd writes made (items the simulator thread produced)."""
    not_waiting: int = 0
    """Deliveries of an item written before the client was back in READY_FOR_DATA (left out,
    as the every_acquisition figure leaves them out)."""
    timeouts: int = 0
    """READY_FOR_DATA calls that got nothing within their timeout."""


def hand_over_floor(samples: int, period_s: float, *, give_up_s: float | None = None) -> FloorRun:
    """Run the chain until the client has ``samples`` deliveries it was waiting for.

    ``period_s`` is the simulator thread's cadence (one eventfd write per period, on a fixed
    schedule). Stops early after ``give_up_s`` wall seconds (default: twice the time the samples
    need, plus 10 s), with what it has.
    """
    if samples < 1:
        raise ValueError("samples must be at least 1")
    budget = give_up_s if give_up_s is not None else 2.0 * samples * period_s + 10.0
    chain = _Chain(period_s)
    run = FloorRun()
    chain.start()
    try:
        deadline = time.perf_counter() + budget
        while len(run.latencies_us) < samples and time.perf_counter() < deadline:
            called = time.perf_counter_ns()
            try:
                seq = chain.inbox.send(_Ready(), timeout=max(10 * period_s, 1.0))
            except TimeoutError:
                run.timeouts += 1
                continue
            held = time.perf_counter_ns()
            assert isinstance(seq, int)
            raised = chain.written[seq]  # appended before the write that produced ``seq``
            if raised < called:
                run.not_waiting += 1
                continue
            run.latencies_us.append((held - raised) / 1000.0)
    finally:
        chain.stop()
    run.written = len(chain.written)
    return run


class _Chain:
    """The four roles' threads (the client is the caller's): simulator, poller, administrator."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.inbox = Mailbox("floor-administrator")
        self.written: list[int] = []
        """perf_counter_ns of each eventfd write, by sequence number."""
        self._irq_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        self._stop_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        self._stopping = threading.Event()
        self._errors: list[BaseException] = []
        self._threads = [
            threading.Thread(target=self._guard, args=(body,), name=f"floor-{name}", daemon=True)
            for name, body in (
                ("administrator", self._administrator),
                ("poller", self._poller),
                ("simulator", self._simulator),
            )
        ]

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def stop(self) -> None:
        """Stop every thread and close the descriptors; re-raises what a thread raised."""
        self._stopping.set()
        os.eventfd_write(self._stop_fd, 1)
        self.inbox.close()
        for thread in self._threads:
            thread.join(timeout=10.0)
        os.close(self._irq_fd)
        os.close(self._stop_fd)
        if self._errors:
            raise self._errors[0]

    def _guard(self, body: Callable[[], None]) -> None:
        try:
            body()
        except ConnectionClosed:  # the inbox closed under a blocked call: stopping
            pass
        except BaseException as exc:
            self._errors.append(exc)

    def _simulator(self) -> None:
        """One eventfd write per period on a fixed schedule, as BIRIS raises its data line."""
        due = time.perf_counter() + self.period_s
        while not self._stopping.is_set():
            wait = due - time.perf_counter()
            if wait > 0 and self._stopping.wait(wait):
                return
            self.written.append(time.perf_counter_ns())
            os.eventfd_write(self._irq_fd, 1)
            due += self.period_s

    def _poller(self) -> None:
        """Poll the eventfd (and a stop eventfd); hand each interrupt to the administrator.

        Like the data notifier: the message is posted, and the reply to it collected just
        before the next post, so the poller never has more than one message outstanding.
        """
        poller = select.poll()
        poller.register(self._stop_fd, select.POLLIN)
        poller.register(self._irq_fd, select.POLLIN)
        seen = 0
        outstanding: Ticket | None = None
        while True:
            ready = dict(poller.poll())
            if self._stop_fd in ready:
                return
            if self._irq_fd not in ready:
                continue
            try:
                count = os.eventfd_read(self._irq_fd)
            except BlockingIOError:
                continue
            seen += count
            if outstanding is not None:
                outstanding.wait()
            outstanding = self.inbox.post(_NewItem(seen - 1))

    def _administrator(self) -> None:
        """Receive; answer NEW_POINT at once, then hand the item to the parked client."""
        parked: Envelope | None = None
        pending: int | None = None
        while True:
            env = self.inbox.receive()
            msg = env.message
            if isinstance(msg, _NewItem):
                env.reply(None)
                if parked is not None:
                    client, parked = parked, None
                    if client.reply(msg.seq):
                        continue
                pending = msg.seq  # nobody waiting: the newest replaces the older
            elif isinstance(msg, _Ready):
                if pending is not None:
                    env.reply(pending)
                    pending = None
                else:
                    parked = env
            else:
                env.fail(TypeError(f"unexpected message {msg!r}"))
