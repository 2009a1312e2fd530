"""Where ``biris regdump`` finds its image: a file, a mapped file or device, or shared memory.

Each source is checked before anything is read, so a short file or a missing segment is one
clear line, not a bus error halfway through a dump.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
from collections.abc import Callable, Iterator

from biris_hw.bus import BusWindow, open_window
from biris_hw.regdump.model import DumpError
from regs.layout import BirisMemoryMap, TargetImage

__all__ = ["image_layout", "images"]


def image_layout(args: argparse.Namespace) -> TargetImage:
    try:
        mm = BirisMemoryMap(
            samples=args.samples, biexec_offset=args.biexec_offset, range_offset=args.range_base
        )
        return TargetImage(args.coupler_at, args.motion_at, args.biris_at, mm)
    except ValueError as exc:
        raise DumpError(f"bad layout: {exc}") from exc


def _read_file(path: str, offset: int, size: int) -> bytes:
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read(size)
    except FileNotFoundError:
        raise DumpError(f"no such file: {path}") from None
    if len(data) < size:
        raise DumpError(
            f"{path} is too short: {len(data)} bytes from offset 0x{offset:X}, "
            f"the image needs 0x{size:X}"
        )
    return data


@contextlib.contextmanager
def _file_images(path: str, offset: int, size: int) -> Iterator[Callable[[], BusWindow]]:
    """Each dump re-reads the file, so ``--watch`` follows a file that is being rewritten."""
    yield lambda: open_window("memory", size=size, buffer=bytearray(_read_file(path, offset, size)))


@contextlib.contextmanager
def _window_images(window: BusWindow) -> Iterator[Callable[[], BusWindow]]:
    try:
        yield lambda: window
    finally:
        window.close()


def _open_mmap(path: str, offset: int, size: int) -> BusWindow:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise DumpError(f"no such file: {path}") from None
    if os.path.isfile(path) and st.st_size < offset + size:
        raise DumpError(
            f"{path} is too short: {st.st_size} bytes, the image needs 0x{size:X} "
            f"from offset 0x{offset:X}"
        )
    try:
        return open_window("mmap", path=path, offset=offset, size=size)
    except ImportError as exc:
        raise DumpError(f"the mmap window is not available: {exc}") from exc


def _open_shm(name: str, offset: int, size: int) -> BusWindow:
    try:
        window = open_window("shm", name=name, create=False)
    except OSError as exc:
        if exc.errno == errno.ENOENT:
            raise DumpError(f"no shared memory segment {name!r}") from None
        raise
    except ImportError as exc:
        raise DumpError(f"the shm window is not available: {exc}") from exc
    if window.size < offset + size:
        window.close()
        raise DumpError(
            f"shared memory {name!r} is too short: 0x{window.size:X} bytes, the image needs "
            f"0x{size:X} from offset 0x{offset:X}"
        )
    return window


def images(
    args: argparse.Namespace, size: int
) -> tuple[contextlib.AbstractContextManager[Callable[[], BusWindow]], int, str]:
    """(context giving a window per dump, image offset in that window, source label)."""
    if args.file is not None:
        return _file_images(args.file, args.offset, size), 0, f"file {args.file}"
    if args.mmap is not None:
        label = f"mmap {args.mmap} at 0x{args.offset:X}"
        return _window_images(_open_mmap(args.mmap, args.offset, size)), 0, label
    label = f"shm {args.shm}"
    return _window_images(_open_shm(args.shm, args.offset, size)), args.offset, label
