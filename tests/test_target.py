"""Target descriptions: a TOML file over regular files and software lines becomes a hardware
bundle with the right fields, its poll lines fire on their registers, and every mistake is one
message that names its key."""

from __future__ import annotations

import errno
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from biris_hw.bus.mmapwin import MmapWindow
from biris_hw.errors import BusError, RequestError
from biris_hw.hardware import BirisHardware
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.irq.poll import PollLine
from biris_hw.target import TARGET_KEYS, load_target, target_from_dict

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "target-example.toml"
SIZES = {"biris": 0x84000, "motion": 0x100, "coupler": 0x20}
WAIT = 5.0  # real seconds: far beyond a 1 ms polling period


@pytest.fixture
def images(tmp_path: Path) -> dict[str, Path]:
    """One zero-filled regular file per window, standing in for /dev/mem."""
    paths = {}
    for name, size in SIZES.items():
        path = tmp_path / f"{name}.img"
        path.write_bytes(bytes(size))
        paths[name] = path
    return paths


def _toml(images: dict[str, Path], extra: str = "") -> str:
    return f"""
biexec_offset = 0x100
biris_base = 0x00C0_0000
clock = "monotonic"
biris = {{ kind = "mmap", path = "{images["biris"]}", size = 0x84000 }}
motion = {{ kind = "mmap", path = "{images["motion"]}", offset = 0, size = 0x100 }}
coupler = {{ kind = "mmap", path = "{images["coupler"]}" }}
level2 = {{ kind = "eventfd" }}
level3 = {{ kind = "poll", window = "motion", offset = 0x82, mask = 0x01, period = 0.001 }}
{extra}"""


@pytest.fixture
def hardware(tmp_path: Path, images: dict[str, Path], no_leaks: None) -> Iterator[BirisHardware]:
    path = tmp_path / "target.toml"
    path.write_text(_toml(images))
    hw = load_target(path)
    yield hw
    hw.close()


def test_a_target_file_becomes_a_hardware_bundle(hardware: BirisHardware) -> None:
    for name, size in SIZES.items():
        window = getattr(hardware, name)
        assert isinstance(window, MmapWindow) and window.size == size
    assert hardware.biexec_offset == 0x100
    assert hardware.biris_base == 0x00C0_0000
    assert hardware.clock is time.monotonic
    assert hardware.time_scale == 1.0
    assert isinstance(hardware.level2, EventFdLine)
    assert isinstance(hardware.level3, PollLine) and hardware.level3.period == 0.001
    assert hardware.to_offset(0x00C0_0100) == 0x100


def test_windows_reach_the_files(hardware: BirisHardware, images: dict[str, Path]) -> None:
    hardware.biris.write16(0x100, 0x1234)
    assert images["biris"].read_bytes()[0x100:0x102] == b"\x12\x34"


def test_a_poll_line_fires_on_its_register(hardware: BirisHardware) -> None:
    assert hardware.level3.wait(timeout=0.02) == 0
    hardware.motion.write8(0x82, 0x02)  # another axis: outside the mask
    assert hardware.level3.wait(timeout=0.02) == 0
    hardware.motion.write8(0x82, 0x01)
    assert hardware.level3.wait(timeout=WAIT) >= 1


def test_a_poll_line_can_compare_and_acknowledge(
    tmp_path: Path, images: dict[str, Path], no_leaks: None
) -> None:
    level2 = (
        'level2 = { kind = "poll", window = "coupler", offset = 0x02, width = 16, mask = 0xFF00, '
        "equals = 0x8000, period = 0.001, acknowledge = { offset = 0x02, value = 0 } }"
    )
    text = _toml(images).replace('level2 = { kind = "eventfd" }', level2)
    path = tmp_path / "target.toml"
    path.write_text(text)
    hw = load_target(path)
    try:
        hw.coupler.write16(0x02, 0xC000)  # masked value 0xC000: not equal
        assert hw.level2.wait(timeout=0.02) == 0
        hw.coupler.write16(0x02, 0x8001)
        assert hw.level2.wait(timeout=WAIT) == 1
        assert hw.coupler.read16(0x02) == 0  # acknowledged before it was raised
    finally:
        hw.close()


def _example() -> dict[str, Any]:
    return tomllib.loads(EXAMPLE.read_text(encoding="utf-8"))


def test_the_example_file_documents_every_key() -> None:
    """Every key but ``axes``, which replaces ``motion`` and ``level3`` and so has an example
    of its own (docs/target-can-example.toml, tests/test_target_can.py), named here, and the
    ``[crate]`` table, a CAN device shown in that example too."""
    data = _example()
    assert set(data) == set(TARGET_KEYS) - {"axes", "crate"}
    text = EXAMPLE.read_text(encoding="utf-8")
    for key in TARGET_KEYS:
        if key not in ("axes", "crate"):
            assert f"\n{key} =" in text
    assert "target-can-example.toml" in text


def test_the_example_file_loads_over_files(images: dict[str, Path], no_leaks: None) -> None:
    """The example's shape (sizes, offsets, the poll line) is valid once its devices exist."""
    data = _example()
    for name in SIZES:
        data[name] = {**data[name], "path": str(images[name]), "offset": 0}
    data["level2"] = {"kind": "eventfd"}  # there is no /dev/uio0 here
    hw = target_from_dict(data)
    try:
        assert isinstance(hw.level3, PollLine)
        assert hw.biris.size == data["biris"]["size"]
    finally:
        hw.close()


def _replace(text: str, old: str, new: str) -> str:
    assert old in text, old
    return text.replace(old, new)


MOTION = 'motion = { kind = "mmap", path = "MOTION", offset = 0, size = 0x100 }'
LEVEL3 = 'level3 = { kind = "poll", window = "motion", offset = 0x82, mask = 0x01, period = 0.001 }'


@pytest.mark.parametrize(
    ("old", "new", "words"),
    [
        ("clock", "clocks", "unknown key 'clocks'"),
        (LEVEL3, "", "level3: missing"),
        (MOTION, 'motion = { path = "MOTION" }', "motion.kind: missing"),
        (MOTION, 'motion = { kind = "vme", path = "MOTION" }', "motion.kind: no bus window kind"),
        (MOTION, 'motion = { kind = "mmap", path = "MOTION", sise = 4 }', "motion.sise: not an"),
        (MOTION, 'motion = { kind = "mmap", path = "MOTION", size = -1 }', "motion.size: must not"),
        (MOTION, 'motion = { kind = "mmap", path = "MOTION", size = 0x40 }', "motion: the window"),
        (MOTION, 'motion = { kind = "mmap", path = ["MOTION"] }', "motion.path: must be"),
        (MOTION, 'motion = "MOTION"', "motion: must be a table"),
        ("biexec_offset = 0x100", "biexec_offset = 0x101", "biexec_offset: must be even"),
        ("biexec_offset = 0x100", "biexec_offset = 1.5", "biexec_offset: must be an integer"),
        ("biris_base = 0x00C0_0000", "biris_base = -1", "biris_base: must be in"),
        ('clock = "monotonic"', 'clock = "realtime"', "clock: must be one of monotonic"),
        ('window = "motion"', 'window = "vme"', "level3.window: must be one of"),
        ("offset = 0x82", "offset = 0x200", "level3.offset: must be in"),
        ("mask = 0x01", "mask = 0x01, width = 12", "level3.width: must be 8, 16 or 32"),
        ("mask = 0x01", "mask = 0x01, equals = 2", "level3.equals: 0x2 has bits outside"),
        ("period = 0.001", "period = 0", "level3.period: must be a positive"),
        ("period = 0.001", "period = 0.001, colour = 1", "level3.colour: not an option"),
        ('level2 = { kind = "eventfd" }', 'level2 = { kind = "irq" }', "level2.kind: no interrupt"),
        ('level2 = { kind = "eventfd" }', 'level2 = { kind = "eventfd", x = 1 }', "level2.x: not"),
        ("biris_base", "biris_base = = ", "not valid TOML"),
    ],
)
def test_mistakes_name_their_key(
    tmp_path: Path, images: dict[str, Path], no_leaks: None, old: str, new: str, words: str
) -> None:
    text = _toml(images).replace(str(images["motion"]), "MOTION")
    text = _replace(text, old, new).replace("MOTION", str(images["motion"]))
    path = tmp_path / "target.toml"
    path.write_text(text)
    with pytest.raises(RequestError) as caught:
        load_target(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: ") and words in message, message
    assert "\n" not in message


def test_a_missing_device_is_a_bus_error_naming_the_key(
    tmp_path: Path, images: dict[str, Path], no_leaks: None
) -> None:
    """The windows opened before the failure are closed again (no_leaks checks the fds)."""
    text = _toml(images).replace(str(images["coupler"]), str(tmp_path / "no-such-device"))
    path = tmp_path / "target.toml"
    path.write_text(text)
    with pytest.raises(BusError) as caught:
        load_target(path)
    assert caught.value.errno == errno.ENOENT
    assert str(caught.value).startswith(f"{path}: coupler: ")


def test_a_missing_uio_device_is_a_bus_error(
    tmp_path: Path, images: dict[str, Path], no_leaks: None
) -> None:
    text = _toml(images).replace(
        'level2 = { kind = "eventfd" }', f'level2 = {{ kind = "uio", path = "{tmp_path}/uio9" }}'
    )
    path = tmp_path / "target.toml"
    path.write_text(text)
    with pytest.raises(BusError, match="level2: cannot open UIO device"):
        load_target(path)


def test_a_missing_file_is_the_os_error_it_is(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        load_target(tmp_path / "nope.toml")
