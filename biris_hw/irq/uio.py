"""``UioLine``: an interrupt line on a Linux UIO device (``/dev/uioN``), for the real VME host.

The kernel's UIO read takes exactly 4 bytes and answers with the *total* number of interrupts
since the device was registered, so the line keeps the last total and reports differences: a
jump of more than one is interrupts that arrived while nobody was reading, which is exactly the
coalescing the rest of the driver already expects from ``wait()``. ``uio_pdrv_genirq`` masks the
interrupt in its handler; writing a 4-byte 1 unmasks it, and we do that after every read so the
next interrupt is not lost.
"""

from __future__ import annotations

import errno
import os
import struct
import threading

from biris_hw.errors import BusError
from biris_hw.irq.fdline import FdLine

__all__ = ["UioLine"]

_TOTAL = struct.Struct("=i")
"""The UIO read and write format: one native-endian s32 (read: total count; write: irq on/off)."""

_REENABLE = _TOTAL.pack(1)


class UioLine(FdLine):
    """The interrupt of one UIO device.

    ``wait()`` returns the interrupts since the previous wait, from the difference of the totals
    the kernel reports (modulo 2**32, so the s32 wrapping at 2**31 costs nothing). The first read
    after opening counts as **one** interrupt: the kernel only lets that read return once the
    total has changed since ``open()``, so at least one arrived, but the total at open time is
    not observable and earlier interrupts (from before we listened) must not be reported.

    Pass ``fd`` to adopt an open descriptor instead of opening ``path`` (tests use one end of a
    socket pair); the line then owns it, closes it, and switches it to non-blocking, because a
    waiter that loses the race for a pending interrupt must not block in ``read``. With
    ``reenable=False`` the line never writes (for a driver whose interrupt needs no unmasking,
    such as one that does not implement ``irqcontrol``).
    """

    kind = "uio"

    def __init__(
        self, path: str = "/dev/uio0", *, fd: int | None = None, reenable: bool = True
    ) -> None:
        self._path = path if fd is None else f"fd {fd}"
        self._reenable = reenable
        self._last_total: int | None = None
        self._read_lock = threading.Lock()
        opened = fd is None
        if fd is None:
            try:
                fd = os.open(path, os.O_RDWR | os.O_CLOEXEC | os.O_NONBLOCK)
            except OSError as exc:
                raise BusError(
                    f"cannot open UIO device {path}: {exc.strerror or exc}",
                    exc.errno or errno.EIO,
                ) from exc
        self._fd = fd
        try:
            os.set_blocking(fd, False)
            super().__init__()
        except OSError as exc:
            if opened:
                os.close(fd)
            raise BusError(
                f"cannot use UIO device {self._path}: {exc}", exc.errno or errno.EIO
            ) from exc

    @property
    def path(self) -> str:
        """The device this line reads (or ``fd N`` for an adopted descriptor), for messages."""
        return self._path

    def _line_fd(self) -> int:
        return self._fd

    def _consume(self) -> int:
        # One lock around read and bookkeeping: two waiters must not compute their deltas from
        # the same previous total.
        with self._read_lock:
            try:
                raw = os.read(self._fd, _TOTAL.size)
            except BlockingIOError:
                return 0  # another waiter took it first
            except OSError as exc:
                raise BusError(
                    f"reading UIO device {self._path} failed: {exc.strerror or exc}",
                    exc.errno or errno.EIO,
                ) from exc
            if len(raw) != _TOTAL.size:
                # Zero bytes is end of file (the device or its stand-in went away); the kernel
                # never returns a partial count, so anything else is not a UIO device.
                raise BusError(f"UIO device {self._path} returned {len(raw)} byte(s) instead of 4")
            total = int(_TOTAL.unpack(raw)[0])
            previous, self._last_total = self._last_total, total
            count = 1 if previous is None else (total - previous) & 0xFFFF_FFFF
            if self._reenable:
                self._unmask()
        return count

    def _unmask(self) -> None:
        try:
            os.write(self._fd, _REENABLE)
        except OSError as exc:
            raise BusError(
                f"re-enabling the interrupt of {self._path} failed: {exc.strerror or exc}",
                exc.errno or errno.EIO,
            ) from exc

    def _release_line(self) -> None:
        os.close(self._fd)
