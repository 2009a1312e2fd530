"""The ``shm`` window beyond the common contract: owner and attacher, unlinking, the tracker."""

from __future__ import annotations

import ctypes
import errno
import os
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from biris_hw.bus import BusError, open_window
from biris_hw.bus.shm import SharedMemoryWindow
from regs.biexec import OFF_COMMAND, BiexecCom

SHM_DIR = Path("/dev/shm")

needs_dev_shm = pytest.mark.skipif(not SHM_DIR.is_dir(), reason="no /dev/shm to look into")


def fd_count() -> int:
    return len(os.listdir("/proc/self/fd"))


def mapping_count(name: str) -> int:
    return Path("/proc/self/maps").read_text().count(f"/dev/shm/{name}")


def mapped(name: str) -> bool:
    return mapping_count(name) > 0


def fresh_name() -> str:
    return f"biris-test-{os.getpid()}-{uuid.uuid4().hex[:12]}"


@pytest.fixture
def owner() -> Iterator[SharedMemoryWindow]:
    window = SharedMemoryWindow(size=0x1000, create=True)
    yield window
    window.close()


def run_python(code: str, *args: str) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in a fresh interpreter; its resource tracker is its own."""
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


# -- owner and attacher --------------------------------------------------------------------------


def test_owner_and_attacher_see_each_others_writes(owner: SharedMemoryWindow) -> None:
    with SharedMemoryWindow(owner.name) as attached:
        assert attached.name == owner.name
        assert attached.size == owner.size
        owner.write32(0x100, 0xDEADBEEF)
        assert attached.read32(0x100) == 0xDEADBEEF
        attached.write16(0xFFE, 0x1234)
        assert owner.read(0xFFE, 2) == b"\x12\x34"
        com = attached.view(BiexecCom, 0x200)
        owner.write16(0x200 + OFF_COMMAND, 4)
        assert com.COMMAND == 4


def test_open_window_reaches_both_roles() -> None:
    with open_window("shm", size=64, create=True) as made:
        assert isinstance(made, SharedMemoryWindow)
        assert made.owner
        with open_window("shm", name=made.name) as attached:
            assert isinstance(attached, SharedMemoryWindow)
            assert not attached.owner
            made.write8(63, 0x7F)
            assert attached.read8(63) == 0x7F


def test_a_new_segment_is_zero_filled(owner: SharedMemoryWindow) -> None:
    with SharedMemoryWindow(owner.name) as attached:
        assert attached.read(0, attached.size) == bytes(0x1000)


def test_attacher_may_take_less_than_the_segment(owner: SharedMemoryWindow) -> None:
    owner.write16(0x10, 0xAAAA)
    with SharedMemoryWindow(owner.name, size=0x20) as attached:
        assert attached.size == 0x20
        assert attached.read16(0x10) == 0xAAAA
        with pytest.raises(BusError):
            attached.read8(0x20)
        with pytest.raises(BusError):
            attached.view(BiexecCom, 0)  # 80 bytes do not fit in 0x20


def test_attach_larger_than_the_segment(owner: SharedMemoryWindow) -> None:
    before = fd_count()
    mappings = mapping_count(owner.name)
    with pytest.raises(BusError) as caught:
        SharedMemoryWindow(owner.name, size=0x1001)
    assert caught.value.errno == errno.EINVAL
    assert owner.name in str(caught.value)
    assert fd_count() == before
    assert mapping_count(owner.name) == mappings  # the failed attach left no mapping behind
    owner.write8(0, 1)  # the segment is still there
    with SharedMemoryWindow(owner.name) as attached:
        assert attached.read8(0) == 1


@needs_dev_shm
def test_owner_close_unlinks(owner: SharedMemoryWindow) -> None:
    path = SHM_DIR / owner.name
    assert path.exists()
    owner.close()
    assert not path.exists()
    assert not mapped(owner.name)


@needs_dev_shm
def test_attacher_close_does_not_unlink(owner: SharedMemoryWindow) -> None:
    attached = SharedMemoryWindow(owner.name)
    attached.write8(5, 0x55)
    attached.close()
    assert (SHM_DIR / owner.name).exists()
    assert owner.read8(5) == 0x55
    with SharedMemoryWindow(owner.name) as again:
        assert again.read8(5) == 0x55


@needs_dev_shm
def test_attacher_keeps_its_mapping_after_the_owner_unlinks(owner: SharedMemoryWindow) -> None:
    attached = SharedMemoryWindow(owner.name)
    owner.write32(0, 0x0BADCAFE)
    owner.close()
    assert not (SHM_DIR / owner.name).exists()
    assert attached.read32(0) == 0x0BADCAFE
    attached.close()
    assert not mapped(owner.name)


def test_open_and_close_leave_the_descriptor_count_unchanged(owner: SharedMemoryWindow) -> None:
    before = fd_count()
    made = SharedMemoryWindow(size=0x100, create=True)
    attached = SharedMemoryWindow(made.name)
    attached.write8(0, 1)
    attached.close()
    made.close()
    with SharedMemoryWindow(owner.name) as again:
        again.read8(0)
    assert fd_count() == before


# -- errors --------------------------------------------------------------------------------------


def test_missing_segment() -> None:
    name = fresh_name()
    with pytest.raises(BusError) as caught:
        SharedMemoryWindow(name)
    assert caught.value.errno == errno.ENOENT
    assert isinstance(caught.value, OSError)
    assert str(caught.value).startswith(f"attaching to shared memory {name!r}: ")


def test_creating_a_taken_name(owner: SharedMemoryWindow) -> None:
    with pytest.raises(BusError) as caught:
        SharedMemoryWindow(owner.name, size=0x10, create=True)
    assert caught.value.errno == errno.EEXIST
    assert str(caught.value).startswith(f"creating shared memory {owner.name!r}: ")
    owner.write8(0, 9)  # the failed create did not take the segment away
    assert owner.read8(0) == 9


def test_create_with_a_chosen_name() -> None:
    name = fresh_name()
    with SharedMemoryWindow(name, size=16, create=True) as made:
        assert made.name == name
        with SharedMemoryWindow(name) as attached:
            assert attached.size == 16


@pytest.mark.parametrize(
    "kwargs",
    [
        {"size": None, "create": True},
        {"name": None, "create": False},
        {"size": 0, "create": True},
        {"size": -5, "create": True},
    ],
    ids=["create without size", "attach without name", "size 0", "negative size"],
)
def test_bad_arguments(kwargs: dict[str, object]) -> None:
    with pytest.raises(BusError) as caught:
        SharedMemoryWindow(**kwargs)  # type: ignore[arg-type]
    assert caught.value.errno == errno.EINVAL


# -- a caller that keeps memory from a view ------------------------------------------------------


class WithArray(ctypes.BigEndianStructure):
    _pack_ = 2
    _layout_ = "ms"
    _fields_ = [("words", ctypes.c_int16 * 4)]


@needs_dev_shm
def test_an_array_field_taken_from_a_view_is_a_copy_and_does_not_pin() -> None:
    window = SharedMemoryWindow(size=64, create=True)
    name = window.name
    window.write16(0, 0x1234)
    kept = window.view(WithArray, 0).words
    window.write16(0, 0x5678)
    assert kept[0] == 0x1234  # a copy, taken when it was read
    window.close()  # nothing pins the mapping
    assert not (SHM_DIR / name).exists()
    assert not mapped(name)
    assert list(kept) == [0x1234, 0, 0, 0]


# -- the resource tracker ------------------------------------------------------------------------

ATTACH_AND_FORGET = """
import sys
from biris_hw.bus.shm import SharedMemoryWindow
window = SharedMemoryWindow(sys.argv[1])
window.write32(0, 0xFEEDF00D)
"""


@needs_dev_shm
def test_an_attacher_that_exits_leaves_the_segment_alone(owner: SharedMemoryWindow) -> None:
    # Before Python 3.13 the attaching process's tracker would unlink the segment at exit and
    # warn about a leak; the owner lives on in this process and must keep it.
    done = run_python(ATTACH_AND_FORGET, owner.name)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    assert (SHM_DIR / owner.name).exists()
    assert owner.read32(0) == 0xFEEDF00D


OWNER_AND_ATTACHER_IN_ONE_PROCESS = """
import os, sys
from biris_hw.bus.shm import SharedMemoryWindow
owner = SharedMemoryWindow(size=64, create=True)
attached = SharedMemoryWindow(owner.name)
attached.write8(1, 2)
assert owner.read8(1) == 2
attached.close()
late = SharedMemoryWindow(owner.name)
owner.close()
late.close()
print(owner.name)
"""


@needs_dev_shm
def test_owner_and_attacher_in_one_process_leave_the_tracker_quiet() -> None:
    # An attacher's unregister would otherwise remove the owner's registration, and the
    # tracker would print a KeyError when the owner unlinks.
    done = run_python(OWNER_AND_ATTACHER_IN_ONE_PROCESS)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    assert not (SHM_DIR / done.stdout.strip()).exists()


CREATE_AND_FORGET = """
from biris_hw.bus.shm import SharedMemoryWindow
window = SharedMemoryWindow(size=64, create=True)
print(window.name, flush=True)
"""


@needs_dev_shm
def test_an_owner_that_exits_without_closing_is_cleaned_up() -> None:
    # The owner stays registered, so a crashed simulator does not leave its segment behind.
    done = run_python(CREATE_AND_FORGET)
    assert done.returncode == 0, done.stderr
    name = done.stdout.strip()
    assert name
    assert not (SHM_DIR / name).exists()
