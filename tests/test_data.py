"""The client API's data types (biris_hw.data)."""

from __future__ import annotations

import dataclasses
import pickle
from typing import Any

import numpy as np
import pytest

from biris_hw import ConnectionKind, Direction, Point, Scan
from biris_hw.geometry import Mount


def make_scan(n_acq: int = 4, samples: int = 64, **changes: Any) -> Scan:
    fields: dict[str, object] = {
        "direction": Direction.CCW,
        "seq": 3,
        "azimuth": np.arange(n_acq, dtype=np.int32) * 43,
        "range_mm": np.full((n_acq, samples), 1500, dtype=np.int16),
        "closest_mm": np.full(n_acq, 1200, dtype=np.int16),
        "intensity": np.ones((n_acq, samples), dtype=np.int16),
        "t": np.arange(n_acq) * 0.0334,
        "dropped": 0,
    }
    fields.update(changes)
    return Scan(**fields)  # type: ignore[arg-type]


def test_direction_and_connection_kind() -> None:
    assert [d.name for d in Direction] == ["CW", "CCW"]
    assert Direction.CCW.sign == 1 and Direction.CW.sign == -1
    assert Direction.of_motion(0, 1024) is Direction.CCW  # towards larger counts
    assert Direction.of_motion(0, -1024) is Direction.CW
    with pytest.raises(ValueError):
        Direction.of_motion(5, 5)
    assert [k.name for k in ConnectionKind] == ["NORMAL", "DATA"]
    assert (int(ConnectionKind.NORMAL), int(ConnectionKind.DATA)) == (0, 1)


def test_scan_shapes_and_dtypes() -> None:
    scan = make_scan(n_acq=5, samples=128)
    assert scan.n_acq == 5 and scan.samples == 128
    assert scan.azimuth.dtype == np.int32 and scan.azimuth.shape == (5,)
    assert scan.range_mm.dtype == np.int16 and scan.range_mm.shape == (5, 128)
    assert scan.closest_mm.dtype == np.int16 and scan.closest_mm.shape == (5,)
    assert scan.intensity.dtype == np.int16 and scan.intensity.shape == (5, 128)
    assert scan.t.dtype == np.float64 and scan.t.shape == (5,)
    assert scan.elevation == 0 and scan.t_delivered is None


def test_scan_coerces_lists_and_plain_ints() -> None:
    scan = make_scan(
        n_acq=2,
        samples=2,
        direction=0,
        azimuth=[0, 1],
        range_mm=[[1, 2], [3, 4]],
        closest_mm=[1, 3],
        intensity=[[0, 0], [0, 0]],
        t=[0, 1],
        t_delivered=2,
    )
    assert scan.direction is Direction.CW
    assert scan.azimuth.dtype == np.int32 and scan.range_mm.dtype == np.int16
    assert scan.t_delivered == 2.0


def test_scan_arrays_are_read_only_and_detached_from_the_caller() -> None:
    azimuth = np.arange(4, dtype=np.int32)
    scan = make_scan(azimuth=azimuth)
    for array in (scan.azimuth, scan.range_mm, scan.closest_mm, scan.intensity, scan.t):
        assert not array.flags.writeable
        with pytest.raises(ValueError):
            array[0] = 1
    azimuth[0] = 999  # the caller's array stays writable and its changes do not leak in
    assert azimuth.flags.writeable and scan.azimuth[0] == 0


def test_read_only_input_is_not_copied() -> None:
    range_mm = np.zeros((4, 64), dtype=np.int16)
    range_mm.flags.writeable = False
    scan = make_scan(range_mm=range_mm)
    assert scan.range_mm is range_mm


def test_scan_is_frozen() -> None:
    scan = make_scan()
    with pytest.raises(dataclasses.FrozenInstanceError):
        scan.seq = 4  # type: ignore[misc]


def test_azimuth_deg() -> None:
    scan = make_scan(azimuth=np.array([0, 512, 1024, -2048], dtype=np.int32))
    np.testing.assert_allclose(scan.azimuth_deg, [0.0, 45.0, 90.0, -180.0])
    assert scan.azimuth_deg.dtype == np.float64


def test_a_scan_as_points_is_what_every_acquisition_hands_over() -> None:
    """Each row becomes the Point an EVERY_ACQUISITION connection gives, with the scan's own
    numbers (sequence, elevation, mount, mode); the points place their returns where the scan
    does."""
    mount = Mount(offset_m=(0.1, 0.0, 0.2), head_offset_m=0.05)
    closest = np.array([1200, 0, 900, 1500], dtype=np.int16)
    ranges = np.full((4, 64), 1500, dtype=np.int16)
    ranges[1] = 0  # no return at all
    ranges[2, ::2] = 0
    scan = make_scan(
        closest_mm=closest,
        range_mm=ranges,
        elevation=-128,
        mount=mount,
        acquisition="continuous",
        t_delivered=9.0,
    )
    points = scan.as_points()
    assert [p.acq for p in points] == [0, 1, 2, 3]
    for k, point in enumerate(points):
        assert point.azimuth == int(scan.azimuth[k]) and point.range_mm == int(closest[k])
        assert point.t == float(scan.t[k]) and point.t_delivered is None
        assert (point.scan_seq, point.elevation) == (3, -128)
        assert point.mount is mount and point.acquisition == "continuous"
        assert np.array_equal(point.profile, ranges[k])
        assert np.array_equal(point.intensity, scan.intensity[k])
    np.testing.assert_allclose(np.vstack([p.points() for p in points]), scan.points())
    assert make_scan(n_acq=0).as_points() == []


def test_empty_scan() -> None:
    scan = make_scan(n_acq=0)
    assert scan.n_acq == 0 and scan.samples == 64
    assert scan.azimuth_deg.shape == (0,)


@pytest.mark.parametrize(
    "changes",
    [
        {"closest_mm": np.zeros(3, dtype=np.int16)},
        {"t": np.zeros(5)},
        {"range_mm": np.zeros((3, 64), dtype=np.int16)},
        {"intensity": np.zeros((4, 32), dtype=np.int16)},
        {"range_mm": np.zeros(4, dtype=np.int16)},
        {"azimuth": np.zeros((4, 1), dtype=np.int32)},
        {"seq": -1},
        {"dropped": -2},
        {"direction": 2},
    ],
)
def test_scan_rejects_inconsistent_data(changes: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        make_scan(**changes)


def test_scan_pickles() -> None:
    scan = make_scan(dropped=2, t_delivered=1.5)
    copy = pickle.loads(pickle.dumps(scan))
    assert copy.dropped == 2 and copy.t_delivered == 1.5
    np.testing.assert_array_equal(copy.range_mm, scan.range_mm)


def make_point(**changes: Any) -> Point:
    fields: dict[str, object] = {
        "azimuth": 1024,
        "range_mm": 1200,
        "profile": np.full(64, 1500, dtype=np.int16),
        "intensity": np.ones(64, dtype=np.int16),
        "t": 10.0,
        "acq": 7,
        "scan_seq": 2,
    }
    fields.update(changes)
    return Point(**fields)  # type: ignore[arg-type]


def test_point_fields_and_age() -> None:
    point = make_point()
    assert point.elevation == 0 and point.t_delivered is None and point.age is None
    assert point.azimuth_deg == 90.0
    assert make_point(t_delivered=10.25).age == pytest.approx(0.25)


def test_point_arrays_are_read_only() -> None:
    profile = np.zeros(64, dtype=np.int16)
    point = make_point(profile=profile)
    for array in (point.profile, point.intensity):
        assert array.dtype == np.int16 and array.shape == (64,)
        with pytest.raises(ValueError):
            array[0] = 1
    profile[0] = 5
    assert point.profile[0] == 0


@pytest.mark.parametrize(
    "changes",
    [
        {"intensity": np.ones(32, dtype=np.int16)},
        {"profile": np.ones((2, 32), dtype=np.int16)},
        {"acq": -1},
        {"t": None},
        {"azimuth": 1.5},
    ],
)
def test_point_rejects_inconsistent_data(changes: dict[str, Any]) -> None:
    with pytest.raises((ValueError, TypeError)):
        make_point(**changes)
