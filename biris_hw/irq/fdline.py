"""The shared waiting machinery of descriptor-backed interrupt lines.

A waiter polls two descriptors at once: the line's own and a private stop eventfd. ``close()``
writes the stop eventfd, so every blocked waiter wakes at once and raises ``LineClosed``; the
descriptors are closed by the last waiter to leave (or by ``close()`` when nobody waits), never
while another thread might still be polling them.
"""

from __future__ import annotations

import os
import select
import threading
import time
from abc import abstractmethod

from biris_hw.errors import LineClosed
from biris_hw.irq.base import InterruptLine

__all__ = ["FdLine"]


class FdLine(InterruptLine):
    """An interrupt line whose pending state is a readable descriptor."""

    def __init__(self) -> None:
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

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            idle = self._waiters == 0
            os.eventfd_write(self._stop_fd, 1)
            self._wake_pollers()
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
