"""Target files whose axes are CiA 402 drives on CAN: the ``[axes]`` table (issue 13 B).

The CAN side is python-can's ``virtual`` interface on a channel of the test's own; nothing is
sent to a drive until a server uses it, so these need none.
"""

from __future__ import annotations

import json
import sys
import uuid
from pathlib import Path

import pytest

from biris_hw.axes.cia402 import Cia402Axes, Cia402Axis, GainObject
from biris_hw.errors import RequestError
from biris_hw.target import TARGET_KEYS, load_target, target_from_dict
from tests.conftest import Run

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "target-can-example.toml"


def _toml(tmp_path: Path, axes: str) -> Path:
    images = {}
    for name, size in (("biris", 0x84000), ("coupler", 0x20)):
        images[name] = tmp_path / f"{name}.img"
        images[name].write_bytes(bytes(size))
    path = tmp_path / "robot.toml"
    path.write_text(
        f"""
biris = {{ kind = "mmap", path = "{images["biris"]}", size = 0x84000 }}
coupler = {{ kind = "mmap", path = "{images["coupler"]}" }}
level2 = {{ kind = "eventfd" }}
pan_journal = ""
[axes]
{axes}
"""
    )
    return path


def _virtual() -> str:
    return f'kind = "cia402"\ninterface = "virtual"\nchannel = "t-{uuid.uuid4().hex}"\n'


def test_an_axes_table_opens_cia402_drives_on_the_named_bus(tmp_path: Path, no_leaks: None) -> None:
    path = _toml(
        tmp_path,
        _virtual() + "pan_node = 5\ntilt_node = 6\nheartbeat_timeout = 0.8\nsdo_timeout = 0.2\n",
    )
    hardware = load_target(path)
    try:
        assert hardware.motion is None
        axes = hardware.axes
        assert isinstance(axes, Cia402Axes)
        assert (axes.pan.node_id, axes.tilt.node_id) == (5, 6)
        assert axes.bus.heartbeat_timeout_s == 0.8 and axes.bus.sdo_timeout_s == 0.2
        assert hardware.level3 is axes.end_of_motion
        assert isinstance(hardware.devices.azimuth, Cia402Axis)
        assert axes.pan.reference is hardware.pan_reference  # _Scan_limit from true zero
    finally:
        hardware.close()


@pytest.mark.parametrize(
    ("axes", "message"),
    [
        ('kind = "cia402"\npan_node = 2', r"axes\.tilt_node: missing"),
        ('kind = "cia402"\npan_node = 128\ntilt_node = 3', r"axes\.pan_node: must be in 1\.\.127"),
        ('kind = "cia402"\npan_node = 2\ntilt_node = 3.0', r"axes\.tilt_node: must be an integer"),
        (
            'kind = "cia402"\npan_node = 2\ntilt_node = 3\nhoming_method = 36',
            r"axes\.homing_method: must be 37 \(homing on the current position\), or 35 for a "
            r"drive of the older numbering, not 36$",
        ),
        (
            'kind = "cia402"\npan_node = 2\ntilt_node = 3\nparams_index = 0x2000',
            r"axes\.params_index: not an option: .*\[axes\.gains\]",
        ),
        (
            'kind = "cia402"\npan_node = 2\ntilt_node = 3\n[axes.gains]\nmax_vel = "0x2000:5"',
            r"axes\.gains\.max_vel: not a value a drive's own object takes .*0x6081",
        ),
        (
            'kind = "cia402"\npan_node = 2\ntilt_node = 3\n[axes.gains]\nzero = "0x2000"',
            r"axes\.gains\.zero: '0x2000' is not INDEX:SUB\[:TYPE\]",
        ),
        (
            'kind = "cia402"\npan_node = 2\ntilt_node = 3\n[axes.gains]\nzero = "0x6081:0"',
            r"axes\.gains\.zero: 0x6081 is not a manufacturer object",
        ),
        (
            'kind = "cia402"\npan_node = 2\ntilt_node = 3\n[axes.gains]\nzero = "0x2000:1:f32"',
            r"axes\.gains\.zero: type 'f32' is none of u8, u16",
        ),
        (
            'kind = "cia402"\npan_node = 2\ntilt_node = 3\n[axes.gains]\nzero = 0x2000',
            r"axes\.gains\.zero: must be a string such as",
        ),
        (
            'kind = "cia402"\npan_node = 2\ntilt_node = 3\n[axes.gains]\n'
            'zero = "0x2000:1"\npole = "0x2000:0x01"',
            r"axes\.gains\.pole: 0x2000:1 is zero's$",
        ),
        ('kind = "hctl"\npan_node = 2\ntilt_node = 3', r"axes\.kind: must be one of cia402"),
        ('kind = "cia402"\npan_node = 2\ntilt_node = 3\nbitrat = 1', r"axes\.bitrat: not an"),
        ('kind = "cia402"\npan_node = 2\ntilt_node = 2\ninterface = "virtual"', r"axes: pan and"),
        ('kind = "cia402"\npan_node = 2\ntilt_node = 3\nsdo_timeout = -1', r"axes\.sdo_timeout"),
    ],
)
def test_axes_mistakes_name_their_key(
    tmp_path: Path, axes: str, message: str, no_leaks: None
) -> None:
    with pytest.raises(RequestError, match=message):
        load_target(_toml(tmp_path, axes))


def test_an_axes_gains_table_names_the_drives_own_objects(tmp_path: Path, no_leaks: None) -> None:
    """Off by default (nothing but standard objects); given, each key's object and type."""
    plain = load_target(_toml(tmp_path, _virtual() + "pan_node = 5\ntilt_node = 6\n"))
    try:
        assert isinstance(plain.axes, Cia402Axes)
        assert plain.axes.pan.gains == {} and plain.axes.tilt.gains == {}
        assert plain.axes.pan.homing_method == 37
    finally:
        plain.close()
    path = _toml(
        tmp_path,
        _virtual()
        + 'pan_node = 5\ntilt_node = 6\nhoming_method = 35\n[axes.gains]\nsample = "0x2000:1"\n'
        'gain = "0x2101:0x0A:u32"\n',
    )
    hardware = load_target(path)
    try:
        axes = hardware.axes
        assert isinstance(axes, Cia402Axes)
        for drive in (axes.pan, axes.tilt):
            assert drive.gains == {
                "sample": GainObject(0x2000, 1, "u16"),
                "gain": GainObject(0x2101, 10, "u32"),
            }
            assert drive.homing_method == 35
    finally:
        hardware.close()


def test_motion_and_level3_are_refused_beside_axes(no_leaks: None) -> None:
    data = {
        "biris": {"kind": "memory", "size": 0x1000},
        "coupler": {"kind": "memory", "size": 0x20},
        "motion": {"kind": "memory", "size": 0x100},
        "level2": {"kind": "eventfd"},
        "axes": {"kind": "cia402", "pan_node": 2, "tilt_node": 3},
    }
    with pytest.raises(RequestError, match=r"^motion: not with \[axes\]"):
        target_from_dict(data)


def test_the_can_example_parses_and_names_real_interfaces() -> None:
    text = EXAMPLE.read_text()
    data = tomllib.loads(text)
    # [homing] is the Model 7600's index; a CiA 402 drive's touch probe latches its own
    assert set(data) == set(TARGET_KEYS) - {"motion", "level3", "homing"}
    assert "\n[axes]\n" in text
    assert data["axes"]["kind"] == "cia402"
    assert (data["axes"]["interface"], data["axes"]["channel"]) == ("socketcan", "can0")
    assert data["axes"]["pan_node"] != data["axes"]["tilt_node"]
    assert "\n[crate]\n" in text and data["crate"]["kind"] == "wiener-can"
    assert data["crate"]["channel"] == data["axes"]["channel"]  # one bus, different ids


def test_regdump_reads_a_can_target_without_a_board(tmp_path: Path, biris: Run) -> None:
    path = _toml(tmp_path, _virtual() + "pan_node = 2\ntilt_node = 3\n")
    code, out, err = biris("regdump", "--target", str(path), "--json")
    assert code == 0, err
    dump = json.loads(out)
    assert "motion" not in dump["layout"]
    assert "coupler" in dump and "biexec" in dump
    assert not any(key.startswith("hctl") or key == "board" for key in dump)
