"""The ``mmap`` window: a file, a physical address through ``/dev/mem``, or a UIO map.

On the real VME host the coupler's window onto BIRIS memory and the Model 7600 board are reached
by mapping ``/dev/mem`` at a physical address, or through a UIO device when a kernel driver
exports the region (hardware.md 5.1). A regular file takes the same path, which is how this code
is tested without hardware.

``mmap`` can only map from a page boundary, while a board's registers rarely start on one: the
window maps from the boundary below and keeps the difference, so window offset 0 is exactly the
address asked for.
"""

from __future__ import annotations

import errno
import mmap
import os
import re
import stat
import sys
from dataclasses import dataclass
from pathlib import Path

from biris_hw.bus.base import BufferWindow
from biris_hw.errors import BusError

__all__ = ["DEFAULT_PATH", "MmapWindow"]

DEFAULT_PATH = "/dev/mem"
"""Physical memory; also what ``path`` is when a UIO device is chosen by number alone."""

_UIO_DEVICE = re.compile(r"/dev/uio(\d+)")


@dataclass(frozen=True)
class _Plan:
    """What to map: ``length`` bytes of ``path`` from ``file_offset``, window at ``start``."""

    path: str
    flags: int
    file_offset: int
    length: int
    start: int


class MmapWindow(BufferWindow):
    """A window over a memory mapping of a file or a device.

    Three cases, chosen by the arguments:

    * ``uio=N`` or ``path="/dev/uioN"``: map ``map_index`` of that UIO device. Its size and its
      offset inside the first page come from ``{sysfs_root}/uioN/maps/map{map_index}``; the device
      is ``/dev/uioN`` unless another ``path`` is given. ``offset`` is an offset into the map and
      ``size`` 0 means the rest of the map.
    * a regular file: ``size`` bytes at file ``offset`` (0 = to the end of the file).
    * anything else (``/dev/mem``, another character device): ``offset`` is a physical address,
      ``size`` is required, and the device is opened with ``O_SYNC`` when ``sync`` is true so the
      kernel maps it uncached. ``device=True`` or ``False`` overrides the choice between this case
      and the previous one (a regular file standing in for ``/dev/mem``, say).

    Raises:
        BusError: with the operating system's errno (``ENOENT``, ``EACCES``, ...) when the device
            or the sysfs files cannot be read or mapped, and ``EINVAL`` when the span does not fit
            the file or the map. The message starts with what was being done.
    """

    kind = "mmap"

    def __init__(
        self,
        path: str = DEFAULT_PATH,
        offset: int = 0,
        size: int = 0,
        *,
        uio: int | None = None,
        map_index: int = 0,
        sysfs_root: str = "/sys/class/uio",
        sync: bool = True,
        device: bool | None = None,
    ) -> None:
        if offset < 0 or size < 0:
            raise BusError(
                f"mapping {path}: offset 0x{offset:X} and size {size} must not be negative",
                errno.EINVAL,
            )
        named = _UIO_DEVICE.fullmatch(path)
        if uio is None and named is not None:
            uio = int(named[1])
        if uio is not None:
            if path == DEFAULT_PATH:
                path = f"/dev/uio{uio}"
            plan = _plan_uio(path, offset, size, uio, map_index, Path(sysfs_root), sync)
        else:
            plan = _plan_direct(path, offset, size, sync, device)
        self._mmap: mmap.mmap | None = _map(plan)
        self._path = plan.path
        self._physical_offset = offset
        window_size = plan.length - plan.start
        self._span = memoryview(self._mmap)[plan.start :]
        super().__init__(self._span, window_size)

    @property
    def path(self) -> str:
        """The file or device that is mapped."""
        return self._path

    @property
    def physical_offset(self) -> int:
        """The offset asked for: a file offset, a physical address, or an offset in a UIO map."""
        return self._physical_offset

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        return (
            f"<{type(self).__name__} path={self._path!r} offset=0x{self._physical_offset:X} "
            f"size=0x{self.size:X} {state}>"
        )

    def _release(self) -> None:
        mapping, self._mmap = self._mmap, None
        try:
            self._span.release()
            if mapping is not None:
                mapping.close()
        except BufferError as exc:
            # A ctypes object a caller took out of a view (an array field) still points into
            # the mapping. Once no reference of ours is left (the traceback keeps this frame's
            # locals), the mapping goes when that object does.
            mapping = None
            raise BusError(
                f"closing {self._path}: memory is still exported (an object taken from a view "
                "is alive); it is unmapped once that object is gone",
                errno.EBUSY,
            ) from exc


def _plan_direct(path: str, offset: int, size: int, sync: bool, device: bool | None) -> _Plan:
    """A regular file or a physical address: map from the page boundary at or below ``offset``."""
    if device is None:
        try:
            device = not stat.S_ISREG(os.stat(path).st_mode)
        except OSError as exc:
            raise _os_error(f"opening {path}", exc) from exc
    if device and size == 0:
        raise BusError(f"mapping {path}: size is required for a device", errno.EINVAL)
    if not device:
        length = _file_length(path)
        if size == 0:
            size = length - offset
        if size <= 0 or offset + size > length:
            raise BusError(
                f"mapping {path}: the file is 0x{length:X} bytes long, too short for "
                f"0x{size:X} bytes at 0x{offset:X}",
                errno.EINVAL,
            )
    flags = os.O_RDWR | (os.O_SYNC if device and sync else 0)
    delta = offset % mmap.ALLOCATIONGRANULARITY
    return _Plan(path, flags, offset - delta, delta + size, delta)


def _plan_uio(
    path: str, offset: int, size: int, uio: int, map_index: int, sysfs_root: Path, sync: bool
) -> _Plan:
    """UIO selects map N by mapping the device at N pages; sysfs says where the region starts."""
    if uio < 0 or map_index < 0:
        raise BusError(
            f"mapping uio{uio} map{map_index}: device and map numbers must not be negative",
            errno.EINVAL,
        )
    map_dir = sysfs_root / f"uio{uio}" / "maps" / f"map{map_index}"
    map_size = _read_sysfs_int(map_dir / "size")
    map_offset = _read_sysfs_int(map_dir / "offset")
    if size == 0:
        size = map_size - offset
    if size <= 0 or offset + size > map_size:
        raise BusError(
            f"mapping uio{uio} map{map_index}: 0x{size:X} bytes at 0x{offset:X} do not fit the "
            f"map (0x{map_size:X} bytes)",
            errno.EINVAL,
        )
    flags = os.O_RDWR | (os.O_SYNC if sync else 0)
    start = map_offset + offset
    return _Plan(path, flags, map_index * mmap.PAGESIZE, start + size, start)


def _map(plan: _Plan) -> mmap.mmap:
    """Open, map and close the descriptor again: the mapping keeps the device reachable."""
    try:
        fd = os.open(plan.path, plan.flags)
    except OSError as exc:
        raise _os_error(f"opening {plan.path}", exc) from exc
    doing = f"mapping 0x{plan.length:X} bytes of {plan.path} at 0x{plan.file_offset:X}"
    try:
        prot = mmap.PROT_READ | mmap.PROT_WRITE
        if sys.version_info >= (3, 13):
            return mmap.mmap(
                fd, plan.length, mmap.MAP_SHARED, prot, offset=plan.file_offset, trackfd=False
            )
        return mmap.mmap(fd, plan.length, mmap.MAP_SHARED, prot, offset=plan.file_offset)
    except OSError as exc:
        raise _os_error(doing, exc) from exc
    except ValueError as exc:  # Python's own checks, e.g. a span past the end of a file
        raise BusError(f"{doing}: {exc}", errno.EINVAL) from exc
    finally:
        os.close(fd)


def _file_length(path: str) -> int:
    try:
        return os.stat(path).st_size
    except OSError as exc:
        raise _os_error(f"opening {path}", exc) from exc


def _read_sysfs_int(path: Path) -> int:
    """A sysfs number such as ``0x1000``."""
    try:
        text = path.read_text(encoding="ascii").strip()
    except OSError as exc:
        raise _os_error(f"reading {path}", exc) from exc
    except UnicodeDecodeError as exc:
        raise BusError(f"reading {path}: not a number", errno.EINVAL) from exc
    try:
        value = int(text, 0)
    except ValueError as exc:
        raise BusError(f"reading {path}: {text!r} is not a number", errno.EINVAL) from exc
    if value < 0:
        raise BusError(f"reading {path}: {text!r} is negative", errno.EINVAL)
    return value


def _os_error(doing: str, exc: OSError) -> BusError:
    reason = exc.strerror or str(exc)
    return BusError(f"{doing}: {reason}", exc.errno or errno.EIO)
