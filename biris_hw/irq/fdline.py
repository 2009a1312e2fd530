"""The shared waiting machinery of descriptor-backed interrupt lines.

A waiter polls two descriptors at once: the line's own and a private stop eventfd. ``close()``
writes the stop eventfd, so every blocked waiter wakes at once and raises ``LineClosed``; the
descriptors are closed by the last waiter to leave (or by ``close()`` when nobody waits), never
while another thread might still be polling them.

On virtual time (issue 22, :mod:`biris_hw.timebase`) a waiter polls through the time base
instead, so the domain knows it waits on the line (a real ``poll`` would leave it counted as
running, and time would stand still); every write that makes one of the line's descriptors
readable is followed by a :meth:`~biris_hw.timebase.TimeBase.kick` of it, which is what wakes such
a poller. A caller's timeout is read through :meth:`~biris_hw.timebase.TimeBase.timeout_hw`.
Without a virtual time base a waiter polls for real.
"""

from __future__ import annotations

import os
import select
import threading
import time
from abc import abstractmethod

from biris_hw.errors import LineClosed
from biris_hw.irq.base import InterruptLine
from biris_hw.timebase import TimeBase

__all__ = ["FdLine"]


class FdLine(InterruptLine):
    """An interrupt line whose pending state is a readable descriptor.

    ``timebase``: the time base of the rig whose threads wait on the line (see the module notes;
    only a virtual one changes how they wait). Whoever raises the line must kick the same one.
    """

    def __init__(self, *, timebase: TimeBase | None = None) -> None:
        self.timebase = timebase
        """The time base given, if any."""
        self._virtual = timebase if timebase is not None and timebase.virtual else None
        self._stop_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        self._lock = threading.Lock()
        self._waiters = 0
        self._closed = False
        self._released = False
        self._spare_poller: select.poll | None = None  # kept for the next wait (one at a time)

    # -- subclass hooks ---------------------------------------------------------------------------
    @abstractmethod
    def _line_fd(self) -> int:
        """The descriptor that polls readable while an interrupt is pending."""

    @abstractmethod
    def _consume(self) -> int:
        """Take the pending interrupts off the line and return how many; 0 if none after all.

        Must not block: ``wait(0)`` calls it without polling first.
        """

    @abstractmethod
    def _release_line(self) -> None:
        """Close the line's own descriptor(s)."""

    # -- contract ---------------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        return self._closed

    def fileno(self) -> int:
        if self._closed:
            raise LineClosed(f"{self.kind} line is closed")
        return self._line_fd()

    def wait(self, timeout: float | None = None) -> int:
        with self._lock:
            if self._closed:
                raise LineClosed(f"{self.kind} line is closed")
            self._waiters += 1
            line_fd = self._line_fd()
            # a notifier waits on its line over and over: its poll set is made once
            poller, self._spare_poller = self._spare_poller, None
        try:
            if timeout is not None and timeout <= 0.0:
                return self._look()
            if self._virtual is not None:
                return self._wait_virtual(self._virtual, line_fd, timeout)
            if poller is None:
                poller = select.poll()
                poller.register(self._stop_fd, select.POLLIN)
                poller.register(line_fd, select.POLLIN | select.POLLERR)
            return self._wait(poller, line_fd, timeout)
        finally:
            with self._lock:
                self._waiters -= 1
                last_out = self.closed and self._waiters == 0
                if poller is not None and not self._closed:
                    self._spare_poller = poller
            if last_out:
                self._release()

    def _look(self) -> int:
        """``wait(0)``: a look, not a wait (a demultiplexer that has polled ``fileno()`` itself).

        Every kind's _consume is non-blocking and returns 0 when nothing is pending, so no poll
        is needed.
        """
        if self._closed:
            raise LineClosed(f"{self.kind} line was closed while waiting")
        count = self._consume()
        if count and self._closed:  # the wake-up that close() writes, not an interrupt
            raise LineClosed(f"{self.kind} line was closed while waiting")
        return count

    def _wait(self, poller: select.poll, line_fd: int, timeout: float | None) -> int:
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        while True:
            if deadline is None:
                ms = -1
            else:
                remaining = deadline - time.monotonic()
                ms = max(0, int(remaining * 1000.0 + 0.999))
            ready = dict(poller.poll(ms))
            if self._stop_fd in ready or self._closed:
                raise LineClosed(f"{self.kind} line was closed while waiting")
            if line_fd in ready:
                count = self._consume()
                if count:
                    return count
            elif deadline is not None and time.monotonic() >= deadline:
                return 0

    def _wait_virtual(self, timebase: TimeBase, line_fd: int, timeout: float | None) -> int:
        """:meth:`_wait` in the domain of a virtual ``timebase``: the deadline is in its time."""
        # The first poll is given the timeout itself, so it ends at exactly the deadline the
        # time base computes from it, which is the one compared with below.
        left = None if timeout is None else timebase.timeout_hw(timeout)
        deadline = None if left is None else timebase.now() + left
        fds = (self._stop_fd, line_fd)
        what = f"interrupt line {self.kind}"
        while True:
            ready = timebase.poll(fds, left, what=what)
            if self._stop_fd in ready or self._closed:
                raise LineClosed(f"{self.kind} line was closed while waiting")
            if line_fd in ready:
                count = self._consume()
                if count:
                    return count
            elif deadline is not None and timebase.now() >= deadline:
                return 0
            if deadline is not None:
                left = max(0.0, deadline - timebase.now())

    def _kick(self, fd: int) -> None:
        """Tell a virtual time base that ``fd`` was just made readable (module notes); a scaled
        one needs no telling."""
        if self._virtual is not None:
            self._virtual.kick(fd)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            idle = self._waiters == 0
            os.eventfd_write(self._stop_fd, 1)
            self._wake_pollers()
            # Under the lock, before any descriptor can be released: each number is still ours.
            self._kick(self._stop_fd)
            self._kick(self._line_fd())
        if idle:
            self._release()

    def _wake_pollers(self) -> None:
        """Make the line's own descriptor readable at close, where the kind can.

        A thread that multiplexes on ``fileno()`` (a demultiplexer) does not see the private stop
        descriptor; woken this way it calls ``wait()`` and gets ``LineClosed``. Runs under the
        lock after ``_closed`` is set, so no waiter can take the wake for an interrupt.
        """

    def _release(self) -> None:
        with self._lock:
            if self._released:
                return
            self._released = True
            self._spare_poller = None
        self._release_line()
        os.close(self._stop_fd)
