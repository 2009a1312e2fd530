"""The ``mmap`` window beyond the common contract: sharing, alignment, UIO, errors, leaks."""

from __future__ import annotations

import ctypes
import errno
import mmap
import os
from pathlib import Path

import pytest

from biris_hw.bus import BusError, open_window
from biris_hw.bus.mmapwin import MmapWindow

PAGE = mmap.PAGESIZE


def pattern(n: int) -> bytes:
    return bytes((i * 13 + 5) & 0xFF for i in range(n))


def fd_count() -> int:
    return len(os.listdir("/proc/self/fd"))


def mapped(path: Path | str) -> bool:
    return str(path) in Path("/proc/self/maps").read_text()


def make_uio_tree(root: Path, uio: int, index: int, size: str, offset: str) -> None:
    """One UIO map as the kernel shows it in sysfs (numbers as hex text)."""
    map_dir = root / f"uio{uio}" / "maps" / f"map{index}"
    map_dir.mkdir(parents=True)
    (map_dir / "size").write_text(size + "\n")
    (map_dir / "offset").write_text(offset + "\n")


@pytest.fixture
def data_file(tmp_path: Path) -> Path:
    path = tmp_path / "regs.bin"
    path.write_bytes(pattern(4 * PAGE))
    return path


@pytest.fixture
def uio_rig(tmp_path: Path) -> tuple[Path, Path]:
    """A fake ``uio4`` with map 2 of 0x80 bytes at 0x310 in its page, and a stand-in device."""
    sysfs = tmp_path / "sys"
    make_uio_tree(sysfs, 4, 2, "0x80", "0x310")
    device = tmp_path / "uio4"
    device.write_bytes(pattern(4 * PAGE))
    return sysfs, device


# -- regular files -------------------------------------------------------------------------------


def test_two_windows_on_one_file_share_writes(data_file: Path) -> None:
    with (
        MmapWindow(str(data_file), offset=PAGE, size=0x100) as a,
        MmapWindow(str(data_file), offset=PAGE, size=0x100) as b,
    ):
        a.write32(0x10, 0x01020304)
        assert b.read32(0x10) == 0x01020304
        b.write16(0x20, 0xCAFE)
        assert a.read16(0x20) == 0xCAFE


def test_unaligned_file_offset_maps_exactly_there(data_file: Path) -> None:
    original = pattern(4 * PAGE)
    with MmapWindow(str(data_file), offset=0x1003, size=0x40) as window:
        assert window.read(0, 0x40) == original[0x1003:0x1043]
        assert window.read8(0) == original[0x1003]
        window.write16(2, 0xBEEF)
        window.write(0x3F, b"\x99")
    raw = data_file.read_bytes()
    assert raw[0x1005:0x1007] == b"\xbe\xef"
    assert raw[0x1042] == 0x99
    assert raw[0x1003:0x1005] == original[0x1003:0x1005]
    assert raw[0x1043] == original[0x1043]


def test_window_may_cross_a_page_boundary(data_file: Path) -> None:
    with MmapWindow(str(data_file), offset=PAGE - 2, size=4) as window:
        window.write32(0, 0xA1B2C3D4)
    assert data_file.read_bytes()[PAGE - 2 : PAGE + 2] == b"\xa1\xb2\xc3\xd4"


def test_size_zero_maps_to_the_end_of_the_file(data_file: Path) -> None:
    with MmapWindow(str(data_file), offset=0x1801) as window:
        assert window.size == 4 * PAGE - 0x1801
        assert window.read(window.size - 3, 3) == pattern(4 * PAGE)[-3:]


def test_properties_and_repr(data_file: Path) -> None:
    with MmapWindow(str(data_file), offset=0x1234, size=0x10) as window:
        assert window.kind == "mmap"
        assert window.path == str(data_file)
        assert window.physical_offset == 0x1234
        assert str(data_file) in repr(window)
        assert "0x1234" in repr(window)


def test_close_removes_the_mapping(data_file: Path) -> None:
    window = MmapWindow(str(data_file), offset=0x10, size=0x10)
    assert mapped(data_file)
    window.close()
    assert not mapped(data_file)


def test_open_and_close_leave_the_descriptor_count_unchanged(data_file: Path) -> None:
    before = fd_count()
    window = MmapWindow(str(data_file), offset=0x123, size=0x10)
    window.write8(0, 1)
    window.close()
    assert fd_count() == before


# -- errors --------------------------------------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "absent"
    with pytest.raises(BusError) as caught:
        MmapWindow(str(path), size=16)
    assert caught.value.errno == errno.ENOENT
    assert str(caught.value).startswith(f"opening {path}: ")


def test_missing_dev_mem_says_what_it_was_doing(tmp_path: Path) -> None:
    path = tmp_path / "mem"  # a /dev/mem that is not there, forced down the device branch
    with pytest.raises(BusError) as caught:
        MmapWindow(str(path), offset=0xFE000000, size=0x100, device=True)
    assert caught.value.errno == errno.ENOENT
    assert str(caught.value).startswith(f"opening {path}: ")


@pytest.mark.parametrize(("offset", "size"), [(0, 4 * PAGE + 1), (4 * PAGE - 2, 4), (4 * PAGE, 0)])
def test_file_too_short(data_file: Path, offset: int, size: int) -> None:
    with pytest.raises(BusError) as caught:
        MmapWindow(str(data_file), offset=offset, size=size)
    assert caught.value.errno == errno.EINVAL
    assert str(caught.value).startswith(f"mapping {data_file}: ")


def test_short_stand_in_on_the_device_branch(tmp_path: Path) -> None:
    path = tmp_path / "physmem"
    path.write_bytes(bytes(PAGE))
    with pytest.raises(BusError) as caught:
        MmapWindow(str(path), offset=PAGE + 8, size=16, device=True)
    assert caught.value.errno == errno.EINVAL
    assert str(caught.value).startswith(f"mapping 0x18 bytes of {path} at 0x{PAGE:X}: ")


def _unwritable_path(tmp_path: Path) -> str:
    """A regular file this process may not open for writing, even as root if we can find one."""
    own = tmp_path / "readonly"
    own.write_bytes(bytes(PAGE))
    own.chmod(0o444)
    for candidate in (str(own), "/sys/devices/system/cpu/online"):
        try:
            os.close(os.open(candidate, os.O_RDWR))
        except PermissionError:
            return candidate
        except OSError:
            continue
    pytest.skip("no file here refuses O_RDWR to this user")


def test_permission_denied(tmp_path: Path) -> None:
    path = _unwritable_path(tmp_path)
    with pytest.raises(BusError) as caught:
        MmapWindow(path, size=4)
    assert caught.value.errno == errno.EACCES
    assert str(caught.value).startswith(f"opening {path}: ")


def test_a_fifo_cannot_be_mapped(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    before = fd_count()
    with pytest.raises(BusError) as caught:
        MmapWindow(str(fifo), offset=0x100, size=16)
    assert caught.value.errno == errno.ENODEV
    assert str(caught.value).startswith(f"mapping 0x110 bytes of {fifo} at 0x0: ")
    assert fd_count() == before


def test_a_device_needs_a_size() -> None:
    with pytest.raises(BusError) as caught:
        MmapWindow("/dev/zero")
    assert caught.value.errno == errno.EINVAL
    assert "size is required" in str(caught.value)


@pytest.mark.parametrize(("offset", "size"), [(-1, 16), (0, -16)])
def test_negative_offset_or_size(data_file: Path, offset: int, size: int) -> None:
    with pytest.raises(BusError) as caught:
        MmapWindow(str(data_file), offset=offset, size=size)
    assert caught.value.errno == errno.EINVAL


def test_failed_opens_leave_no_descriptor(tmp_path: Path, data_file: Path) -> None:
    short = tmp_path / "short"
    short.write_bytes(bytes(8))
    before = fd_count()
    for kwargs in (
        {"path": str(tmp_path / "absent"), "size": 16},
        {"path": str(data_file), "offset": 4 * PAGE, "size": 16},
        {"path": str(short), "size": 16, "device": True},
    ):
        with pytest.raises(BusError):
            open_window("mmap", **kwargs)
    assert fd_count() == before


# -- device flags --------------------------------------------------------------------------------


@pytest.fixture
def opened_flags(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Flags of every os.open the window makes, recorded on the way through."""
    seen: list[int] = []
    real_open = os.open

    def spy(path: str, flags: int, *args: int, **kwargs: int) -> int:
        seen.append(flags)
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", spy)
    return seen


def test_device_branch_opens_with_o_sync(tmp_path: Path, opened_flags: list[int]) -> None:
    physmem = tmp_path / "physmem"
    physmem.write_bytes(bytes(2 * PAGE))
    MmapWindow(str(physmem), offset=0x20, size=8, device=True).close()
    MmapWindow(str(physmem), offset=0x20, size=8, device=True, sync=False).close()
    MmapWindow(str(physmem), offset=0x20, size=8).close()
    assert [bool(f & os.O_SYNC) for f in opened_flags] == [True, False, False]
    assert all(f & os.O_ACCMODE == os.O_RDWR for f in opened_flags)


# -- UIO -----------------------------------------------------------------------------------------


def test_uio_window_starts_at_the_sysfs_offset(uio_rig: tuple[Path, Path]) -> None:
    sysfs, device = uio_rig
    start = 2 * PAGE + 0x310  # map 2 is at file offset 2 pages, the region 0x310 into it
    with MmapWindow(str(device), uio=4, map_index=2, sysfs_root=str(sysfs)) as window:
        assert window.size == 0x80
        assert window.path == str(device)
        assert window.read(0, 0x80) == pattern(4 * PAGE)[start : start + 0x80]
        window.write32(0x7C, 0x11223344)
        with pytest.raises(BusError):
            window.read8(0x80)
    assert device.read_bytes()[start + 0x7C : start + 0x80] == b"\x11\x22\x33\x44"


def test_uio_offset_and_size_select_part_of_the_map(uio_rig: tuple[Path, Path]) -> None:
    sysfs, device = uio_rig
    start = 2 * PAGE + 0x310 + 0x20
    with MmapWindow(
        str(device), offset=0x20, size=0x10, uio=4, map_index=2, sysfs_root=str(sysfs)
    ) as window:
        assert window.size == 0x10
        assert window.physical_offset == 0x20
        assert window.read(0, 0x10) == pattern(4 * PAGE)[start : start + 0x10]


def test_uio_size_larger_than_the_map(uio_rig: tuple[Path, Path]) -> None:
    sysfs, device = uio_rig
    with pytest.raises(BusError) as caught:
        MmapWindow(str(device), size=0x81, uio=4, map_index=2, sysfs_root=str(sysfs))
    assert caught.value.errno == errno.EINVAL
    assert str(caught.value).startswith("mapping uio4 map2: ")


def test_uio_bad_map_index(uio_rig: tuple[Path, Path]) -> None:
    sysfs, device = uio_rig
    with pytest.raises(BusError) as caught:
        MmapWindow(str(device), uio=4, map_index=3, sysfs_root=str(sysfs))
    assert caught.value.errno == errno.ENOENT
    assert str(caught.value).startswith(f"reading {sysfs}/uio4/maps/map3/size: ")
    with pytest.raises(BusError) as negative:
        MmapWindow(str(device), uio=4, map_index=-1, sysfs_root=str(sysfs))
    assert negative.value.errno == errno.EINVAL


def test_uio_device_defaults_to_dev_uio_n(tmp_path: Path) -> None:
    make_uio_tree(tmp_path, 87, 0, "0x1000", "0x0")
    with pytest.raises(BusError) as caught:
        MmapWindow(uio=87, sysfs_root=str(tmp_path))
    # The sysfs files were read, so the next thing is the device the window chose.
    assert str(caught.value).startswith("opening /dev/uio87: ")


def test_uio_number_is_taken_from_a_dev_uio_path(tmp_path: Path) -> None:
    with pytest.raises(BusError) as caught:
        MmapWindow("/dev/uio86", sysfs_root=str(tmp_path))
    assert str(caught.value).startswith(f"reading {tmp_path}/uio86/maps/map0/size: ")


@pytest.mark.parametrize("text", ["", "banana", "-0x10", "\xff"])
def test_uio_sysfs_garbage(tmp_path: Path, text: str) -> None:
    make_uio_tree(tmp_path, 1, 0, "0x100", "0x0")
    (tmp_path / "uio1" / "maps" / "map0" / "offset").write_text(text, encoding="latin-1")
    device = tmp_path / "dev"
    device.write_bytes(bytes(PAGE))
    with pytest.raises(BusError) as caught:
        MmapWindow(str(device), uio=1, sysfs_root=str(tmp_path))
    assert caught.value.errno == errno.EINVAL
    assert str(caught.value).startswith(f"reading {tmp_path}/uio1/maps/map0/offset: ")


def test_uio_stand_in_too_short_for_the_map(tmp_path: Path) -> None:
    make_uio_tree(tmp_path, 1, 1, "0x100", "0x80")
    device = tmp_path / "dev"
    device.write_bytes(bytes(PAGE + 0x100))  # map 1 needs PAGE + 0x80 + 0x100 bytes
    with pytest.raises(BusError) as caught:
        MmapWindow(str(device), uio=1, map_index=1, sysfs_root=str(tmp_path))
    assert caught.value.errno == errno.EINVAL
    assert str(caught.value).startswith(f"mapping 0x180 bytes of {device} at 0x{PAGE:X}: ")


def test_uio_close_unmaps_and_frees_the_descriptor(uio_rig: tuple[Path, Path]) -> None:
    sysfs, device = uio_rig
    before = fd_count()
    window = MmapWindow(str(device), uio=4, map_index=2, sysfs_root=str(sysfs))
    assert mapped(device)
    window.close()
    assert not mapped(device)
    assert fd_count() == before


# -- a caller that keeps memory from a view ------------------------------------------------------


class WithArray(ctypes.BigEndianStructure):
    _pack_ = 2
    _layout_ = "ms"
    _fields_ = [("words", ctypes.c_int16 * 4)]


def test_an_array_field_taken_from_a_view_does_not_pin_the_mapping(data_file: Path) -> None:
    window = MmapWindow(str(data_file), offset=0x40, size=0x40)
    window.write16(2, 0x0BAD)
    kept = window.view(WithArray, 0).words
    window.write16(2, 0x0600)
    assert kept[1] == 0x0BAD  # a copy
    window.close()
    assert window.closed
    assert not mapped(data_file)
    with pytest.raises(BusError):
        window.read8(0)
