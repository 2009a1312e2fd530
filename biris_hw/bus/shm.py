"""The ``shm`` window: a named shared-memory segment, so the simulator can run in another process.

One side creates the segment and owns it (it unlinks the name on close); every other side
attaches by name and never unlinks. Attaching must not hand the segment to Python's
``resource_tracker``: before Python 3.13 the tracker of the attaching process would otherwise
unlink the owner's segment (with a "leaked shared_memory" warning) when that process exits
(CPython gh-82300). Python 3.13 has ``track=False`` for this; older versions register on attach,
so the attacher unregisters straight away.

Limitation before 3.13: the tracker keeps a *set* of names, so an attacher whose tracker is also
the owner's (a ``multiprocessing`` child of the owner, or an owner in this process that is not a
:class:`SharedMemoryWindow`) cancels the owner's crash protection, and the tracker prints a
``KeyError`` when the owner unlinks. Owners made by this class in this process are known and
handled; the rest is fixed only by Python 3.13.
"""

from __future__ import annotations

import errno
import os
import sys
import threading
from collections import Counter
from multiprocessing import resource_tracker
from multiprocessing.shared_memory import SharedMemory

from biris_hw.bus.base import BufferWindow
from biris_hw.errors import BusError

__all__ = ["SharedMemoryWindow"]

_TRACKED = os.name == "posix"
"""Only POSIX segments go through the resource tracker (Windows frees them with the last handle)."""

_tracker_lock = threading.Lock()
"""Makes "open a segment, then fix up the tracker" one step, as seen by other windows here."""

_owned: Counter[str] = Counter()
"""Names of the segments that owner windows in this process hold, registered with the tracker."""

_stranded: list[SharedMemory] = []
"""Segments whose close failed because a caller still holds memory taken from a view.

Kept here rather than dropped: dropping them would let ``SharedMemory.__del__`` fail noisily and
leak the descriptor. Every later open or close of a window tries them again.
"""


def _sweep_stranded() -> None:
    """Finish closing the segments whose stray exports have gone since; call under the lock."""
    for shm in list(_stranded):
        try:
            shm.close()
        except BufferError:
            continue
        _stranded.remove(shm)


def _open_segment(name: str | None, size: int | None, create: bool) -> SharedMemory:
    """Create or attach, leaving the tracker with exactly the owners' registrations."""
    what = "creating" if create else "attaching to"
    label = "a new segment" if name is None else repr(name)
    with _tracker_lock:
        _sweep_stranded()
        try:
            if create:
                shm = SharedMemory(name=name, create=True, size=size or 0)
            elif sys.version_info >= (3, 13):
                shm = SharedMemory(name=name, track=False)
            else:
                shm = SharedMemory(name=name)
        except FileNotFoundError as exc:
            raise BusError(
                f"{what} shared memory {label}: no segment of that name (has its owner created "
                f"it?)",
                errno.ENOENT,
            ) from exc
        except OSError as exc:
            raise BusError(
                f"{what} shared memory {label}: {exc.strerror}", exc.errno or errno.EIO
            ) from exc
        except ValueError as exc:  # an empty segment, or a size SharedMemory refuses
            raise BusError(f"{what} shared memory {label}: {exc}", errno.EINVAL) from exc
        if create:
            _owned[shm.name] += 1
        elif sys.version_info < (3, 13) and _TRACKED and not _owned[shm.name]:
            # The attach just registered the name; an owner here would have registered it
            # already, and then the set already held it and unregistering would drop the
            # owner's entry instead.
            resource_tracker.unregister("/" + shm.name, "shared_memory")
    return shm


def _unlink_segment(shm: SharedMemory) -> None:
    """Remove the name (an owner's last act) and forget the tracker registration with it."""
    with _tracker_lock:
        try:
            shm.unlink()
        except FileNotFoundError:
            # Someone unlinked it for us; SharedMemory.unlink then skips the unregister, and the
            # tracker would try again (and warn) at exit.
            if _TRACKED:
                resource_tracker.unregister("/" + shm.name, "shared_memory")
        finally:
            _owned[shm.name] -= 1
            if _owned[shm.name] <= 0:
                del _owned[shm.name]


class SharedMemoryWindow(BufferWindow):
    """A window over a ``multiprocessing.shared_memory`` segment.

    ``create=True`` makes a zero-filled segment of ``size`` bytes (``name=None`` picks a free
    name) and unlinks it on close. ``create=False`` attaches to ``name``; ``size`` may be left out
    to use the whole segment and may not exceed it.

    Raises:
        BusError: ``ENOENT`` when the segment to attach does not exist, ``EEXIST`` when the
            name to create is taken, ``EINVAL`` for a missing name or size, a size that is not
            positive or one larger than the segment.
    """

    kind = "shm"

    def __init__(
        self, name: str | None = None, size: int | None = None, create: bool = False
    ) -> None:
        if create and size is None:
            raise BusError("creating shared memory: size is required", errno.EINVAL)
        if not create and name is None:
            raise BusError("attaching to shared memory: a name is required", errno.EINVAL)
        if size is not None and size <= 0:
            raise BusError(
                f"opening shared memory: size must be positive, not {size}", errno.EINVAL
            )
        shm = _open_segment(name, size, create)
        window_size = shm.size if size is None else size
        buf = shm.buf
        if window_size > shm.size or buf is None:
            shm.close()
            if create:
                _unlink_segment(shm)
            raise BusError(
                f"attaching to shared memory {shm.name!r}: size 0x{window_size:X} is larger "
                f"than the segment (0x{shm.size:X})",
                errno.EINVAL,
            )
        self._shm = shm
        self._owner = create
        # The segment's own memoryview, not a slice: a window the caller forgets to close then
        # holds no second view, so SharedMemory.__del__ can still close the mapping quietly.
        # The window's range checks keep accesses inside ``window_size``.
        super().__init__(buf, window_size)

    @property
    def name(self) -> str:
        """The segment's name, as another process passes it to attach."""
        return self._shm.name

    @property
    def owner(self) -> bool:
        """Whether this window created the segment (and so unlinks it on close)."""
        return self._owner

    def __repr__(self) -> str:
        role = "owner" if self._owner else "attached"
        state = "closed" if self.closed else "open"
        return (
            f"<{type(self).__name__} name={self._shm.name!r} size=0x{self.size:X} {role} {state}>"
        )

    def _release(self) -> None:
        # BufferWindow has dropped every view; what may still pin the mapping is a ctypes
        # object a caller pulled out of a view (an array field), which we cannot drop for them.
        # SharedMemory.close releases the memoryview first, then unmaps.
        try:
            self._shm.close()
        except BufferError as exc:
            with _tracker_lock:
                _stranded.append(self._shm)
            raise BusError(
                f"closing shared memory {self._shm.name!r}: memory is still exported (an object "
                "taken from a view is alive); it is unmapped later, once that object is gone",
                errno.EBUSY,
            ) from exc
        finally:
            if self._owner:
                _unlink_segment(self._shm)
        with _tracker_lock:
            _sweep_stranded()
