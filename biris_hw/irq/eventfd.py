"""``EventFdLine``: an interrupt line on a Linux eventfd, raised by ``trigger()``.

This is how the simulator interrupts the driver, in process or (with the descriptor passed over
a Unix socket) from another process; it is also the shape of a VFIO-bound interrupt.
"""

from __future__ import annotations

import os

from biris_hw.errors import LineClosed
from biris_hw.irq.fdline import FdLine
from biris_hw.timebase import TimeBase

__all__ = ["EventFdLine"]


class EventFdLine(FdLine):
    """An eventfd counter: ``trigger(n)`` adds n, ``wait()`` takes the whole count (coalescing).

    Pass ``fd`` to adopt a descriptor received from elsewhere (the line then owns and closes it).
    ``timebase``: the time base of the rig (:class:`~biris_hw.irq.fdline.FdLine`); ``trigger()``
    kicks it, so a waiter on virtual time is woken by the interrupt.
    """

    kind = "eventfd"

    def __init__(self, fd: int | None = None, *, timebase: TimeBase | None = None) -> None:
        self._fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK) if fd is None else fd
        super().__init__(timebase=timebase)

    def trigger(self, count: int = 1) -> None:
        """Raise ``count`` interrupts; they accumulate until a waiter takes them."""
        if count < 1:
            raise ValueError("an interrupt count must be at least 1")
        # Under the line's lock: close() sets ``_closed`` under it before any descriptor is
        # released, so a write that passed the check can never hit a closed (or reused) number.
        with self._lock:
            if self._closed:
                raise LineClosed("eventfd line is closed")
            os.eventfd_write(self._fd, count)
            if self._virtual is not None:  # under the lock: the number cannot have been reused
                self._virtual.kick(self._fd)

    def _line_fd(self) -> int:
        return self._fd

    def _consume(self) -> int:
        try:
            return int(os.eventfd_read(self._fd))
        except BlockingIOError:
            return 0  # another waiter took it first

    def _wake_pollers(self) -> None:
        os.eventfd_write(self._fd, 1)

    def _release_line(self) -> None:
        os.close(self._fd)
