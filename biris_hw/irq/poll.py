"""``PollLine``: an interrupt line made by polling a register, for targets with no interrupt path.

Some bridges (a USB or CAN adaptor, a VME host whose kernel gives user space no VME interrupts)
can read the status registers but cannot deliver the interrupt itself. A background thread then
plays the interrupt controller: it evaluates a predicate at a fixed period and, when it holds,
raises an internal eventfd, so notifiers wait on this line exactly as on any other.

Given a time base (``timebase=``, issue 22), the line keeps that rig's time: the period is in its
hardware seconds, the thread is the time base's (:meth:`~biris_hw.timebase.TimeBase.Thread`) and
waits between checks through :meth:`~biris_hw.timebase.TimeBase.poll`, and every write to the
line's descriptors is followed by a :meth:`~biris_hw.timebase.TimeBase.kick`. On virtual time
each check then comes one period of hardware time after the one before (a check takes no time
there, so none overruns), and waiters are woken through the domain.
"""

from __future__ import annotations

import logging
import math
import os
import select
import threading
import time
from collections.abc import Callable

from biris_hw.errors import BusError
from biris_hw.irq.fdline import FdLine
from biris_hw.timebase import HwThread, TimeBase

__all__ = ["PollLine"]

log = logging.getLogger(__name__)


class PollLine(FdLine):
    """An interrupt raised whenever ``predicate()`` is true at one of the periodic checks.

    When the predicate holds, ``acknowledge()`` (if given) runs before the interrupt is raised,
    just as an interrupt service routine clears the source before it wakes anyone. Without an
    acknowledgement a condition that stays true fires once per period; give one to turn a level
    (a sticky status bit) into one interrupt.

    The predicate is checked every ``period`` seconds on the monotonic clock; a check that
    overruns skips the missed slots rather than firing a burst. Between checks the thread waits
    with ``poll()`` on a private stop eventfd, so ``close()`` stops it at once.

    Failure is never silent: if the predicate or the acknowledgement raises, polling stops, the
    exception is kept (see :attr:`error`), interrupts raised before it are still delivered by the
    next ``wait()``, and every ``wait()`` after that raises :class:`BusError` chained to it (the
    descriptor stays readable, so a thread multiplexing on ``fileno()`` finds out too). Only
    ``close()`` ends that state.

    ``timebase``: the time base whose hardware seconds the period is in, and whose domain the
    thread and the waiters belong to (module notes); None for the monotonic clock and real waits.
    """

    kind = "poll"

    def __init__(
        self,
        predicate: Callable[[], bool],
        period: float,
        *,
        acknowledge: Callable[[], None] | None = None,
        timebase: TimeBase | None = None,
    ) -> None:
        if not (isinstance(period, (int, float)) and math.isfinite(period) and period > 0):
            raise ValueError(
                f"a polling period must be a positive number of seconds, not {period!r}"
            )
        self._predicate = predicate
        self._acknowledge = acknowledge
        self._period = float(period)
        self._state = threading.Lock()
        self._pending = 0
        self._error: Exception | None = None
        self._halting = False
        self._closed_by_thread = False
        self._event_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        self._halt_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        try:
            super().__init__(timebase=timebase)
        except BaseException:
            os.close(self._event_fd)
            os.close(self._halt_fd)
            raise
        self._thread: threading.Thread
        if timebase is not None:
            self._thread = timebase.Thread(self._run, name="biris-poll-line", daemon=True)
        else:
            self._thread = threading.Thread(target=self._run, name="biris-poll-line", daemon=True)
        self._thread.start()

    @property
    def period(self) -> float:
        """Seconds between two evaluations of the predicate."""
        return self._period

    @property
    def error(self) -> Exception | None:
        """The exception that stopped polling, or None while the line works."""
        with self._state:
            return self._error

    # -- the polling thread ----------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._poll_loop()
        finally:
            if self._closed_by_thread:
                super().close()

    def _poll_loop(self) -> None:
        """Check the predicate every period until halted: on the monotonic clock with a real
        poll, or in a time base's hardware seconds, waiting through it."""
        timebase = self.timebase
        now: Callable[[], float]
        halted: Callable[[float], bool]
        if timebase is not None:
            halt = (self._halt_fd,)
            now = timebase.now
            halted = lambda s: bool(timebase.poll(halt, s, what="poll line period"))  # noqa: E731
        else:
            poller = select.poll()
            poller.register(self._halt_fd, select.POLLIN)
            now = time.monotonic
            halted = lambda s: bool(poller.poll(max(1, math.ceil(s * 1000.0))))  # noqa: E731
        due = now()
        while True:
            try:
                fired = self._predicate()
                if fired and self._acknowledge is not None:
                    self._acknowledge()
            except Exception as exc:
                log.error("poll line stopped: its predicate or acknowledgement raised %r", exc)
                self._raise_pending(error=exc)
                return
            if fired and not self._raise_pending():
                return
            t = now()
            due += self._period
            if due <= t:  # overran: skip the missed checks instead of catching up in a burst
                due = t + self._period
            if halted(due - t):
                return

    def _raise_pending(self, error: Exception | None = None) -> bool:
        """Count one interrupt (or record the failure) and make the descriptor readable.

        Returns False once the line is halting: a callback may have closed it, and then the
        descriptors are no longer ours to write.
        """
        with self._state:
            if self._halting:
                return False
            if error is None:
                self._pending += 1
            else:
                self._error = error
            os.eventfd_write(self._event_fd, 1)
            self._kick(self._event_fd)
            return True

    # -- FdLine hooks ----------------------------------------------------------------------------
    def _line_fd(self) -> int:
        return self._event_fd

    def _consume(self) -> int:
        with self._state:
            if self._error is None:
                try:
                    os.eventfd_read(self._event_fd)
                except BlockingIOError:
                    pass  # another waiter drained it; _pending says what is left
            # After a failure the descriptor is left readable on purpose: the line is broken.
            count, self._pending = self._pending, 0
            error = self._error
        if count:
            return count
        if error is not None:
            raise BusError(f"poll line stopped: {error!r}") from error
        return 0

    def _wake_pollers(self) -> None:
        os.eventfd_write(self._event_fd, 1)  # the polling thread is joined: nobody races this

    def _release_line(self) -> None:
        os.close(self._event_fd)
        os.close(self._halt_fd)

    # -- lifecycle -------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop and join the polling thread, then close the line (waking every waiter).

        Called from the predicate or acknowledgement itself, it cannot join its own thread; the
        thread then finishes the close as it leaves.
        """
        with self._state:
            if not self._halting:
                self._halting = True
                # Written under the lock that set the flag, so no other closer can have released
                # the descriptor yet (it would first have to see the flag).
                os.eventfd_write(self._halt_fd, 1)
                self._kick(self._halt_fd)
            if threading.current_thread() is self._thread:
                self._closed_by_thread = True
                return
        thread = self._thread
        if isinstance(thread, HwThread):
            thread.timebase.join_thread(thread)  # a wait in the domain: a participant may close
        else:
            thread.join()
        super().close()
