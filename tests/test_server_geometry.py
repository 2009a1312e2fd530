"""Full 3-D data: BIRIS profiles become points in the sensor and vehicle frames.

The pure geometry is checked on hand-made scans; the chain from the simulator's optics through
the server to ``Scan.points`` is checked against scenes whose surfaces are known exactly.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from biris_hw import BirisInitRecord, Direction, Scan
from biris_hw.geometry import (
    FAN_DEG,
    Mount,
    point_points,
    project_profiles,
    sample_elevations,
    scan_points,
)
from biris_hw.server import BirisServer
from sim import Scene
from sim.optics import BirisOptics
from tests.conftest import RigFactory

WAIT = 30.0


@pytest.fixture
def time_scale() -> float:
    """One fast scale: these tests are about geometry, not timing."""
    return 30.0


def _scan(range_mm: list[list[int]], azimuth: list[int], elevation: int = 0, **kw: object) -> Scan:
    n = len(azimuth)
    rng = np.asarray(range_mm, dtype=np.int16)
    return Scan(
        direction=Direction.CCW,
        seq=1,
        azimuth=np.asarray(azimuth, dtype=np.int32),
        range_mm=rng,
        closest_mm=np.zeros(n, dtype=np.int16),
        intensity=np.zeros_like(rng),
        t=np.arange(n, dtype=np.float64),
        elevation=elevation,
        **kw,  # type: ignore[arg-type]
    )


# --- pure geometry ---------------------------------------------------------------------------


def test_sample_elevations_match_the_simulated_optics() -> None:
    for n in (64, 128):
        optics = BirisOptics(n, np.random.default_rng(0))
        assert np.allclose(sample_elevations(n), optics.elevations)
    e = sample_elevations(4)
    half = math.radians(FAN_DEG) / 2
    assert np.allclose(e, [0.75 * half, 0.25 * half, -0.25 * half, -0.75 * half])
    with pytest.raises(ValueError):
        sample_elevations(0)


def test_range_is_depth_along_the_optical_axis() -> None:
    scan = _scan([[1000, 0, 2000, 1000]], [0])
    pts = scan.points("sensor")
    assert pts.shape == (3, 3)  # the no-return sample is left out
    e = sample_elevations(4)
    assert np.allclose(pts[:, 0], [1.0, 2.0, 1.0])
    assert np.allclose(pts[:, 1], 0.0)
    assert np.allclose(pts[:, 2], [1.0 * math.tan(e[0]), 2.0 * math.tan(e[2]), math.tan(e[3])])


def test_azimuth_turns_counter_clockwise_and_elevation_looks_up() -> None:
    left = _scan([[1000, 1000]], [1024]).points("sensor")  # +90 degrees: to the left
    assert np.allclose(left[:, 0], 0.0, atol=1e-12) and np.allclose(left[:, 1], 1.0)
    up = _scan([[1000, 1000]], [0], elevation=1024).points("sensor")  # looking straight up
    e = sample_elevations(2)
    assert np.allclose(up[:, 2], 1.0)  # depth along the axis is now height
    assert np.allclose(up[:, 0], -np.tan(e))  # the upper row leans back


def test_vehicle_frame_adds_the_mount() -> None:
    mount = Mount(offset_m=(0.3, -0.2, 0.1), head_height_m=0.6, head_offset_m=0.05)
    scan = _scan([[1000, 2000]], [1024], mount=mount)
    sensor, vehicle = scan.points("sensor"), scan.points("vehicle")
    assert np.allclose(vehicle - sensor, [0.3, -0.2, 0.7])
    assert np.allclose(sensor[:, 1], [1.05, 2.05])  # optical centre 5 cm out along the azimuth
    assert np.allclose(scan_points(scan, "vehicle", Mount()) - sensor, [0.0, -0.05, 0.5])
    with pytest.raises(ValueError):
        scan.points("world")  # type: ignore[arg-type]


def test_grid_keeps_gaps_as_nan() -> None:
    grid = project_profiles([[1000, 0], [0, 500]], [0, 512], 0)
    assert grid.shape == (2, 2, 3)
    assert np.isnan(grid[0, 1]).all() and np.isnan(grid[1, 0]).all()
    assert np.isfinite(grid[0, 0]).all() and np.isfinite(grid[1, 1]).all()


def test_init_record_carries_the_mount() -> None:
    record = BirisInitRecord(mount_offset_m=(1.0, 2.0, 3.0), head_height_m=0.4)
    assert record.mount == Mount((1.0, 2.0, 3.0), 0.4, 0.0)
    assert BirisInitRecord.from_dict(record.to_dict()) == record
    assert BirisInitRecord().mount == Mount()


# --- against the simulator -------------------------------------------------------------------


def test_circle_points_lie_on_the_cylinder(make_rig: RigFactory) -> None:
    rig = make_rig(scene=Scene.circle(2.0), noise=False)
    offset = (0.3, -0.2, 0.1)
    with BirisServer(rig.hardware, BirisInitRecord(mount_offset_m=offset)) as server:
        conn = server.open()
        conn.single_scan(120.0)
        conn.wait_idle(timeout=WAIT)
        scan = conn.request_scan_data(Direction.CCW)
        point = conn.request_point()
    assert scan is not None and point is not None
    assert scan.mount == Mount(offset)
    pts = scan.points("vehicle")
    assert pts.shape[0] == np.count_nonzero(scan.range_mm) > 0.9 * scan.range_mm.size
    horizontal = np.hypot(pts[:, 0] - offset[0], pts[:, 1] - offset[1])
    assert np.abs(horizontal - 2.0).max() < 0.005  # millimetre ranges, no noise
    # the fan spans +-11 degrees about the optical centre, 0.5 m up the pan axis
    height = pts[:, 2] - offset[2] - 0.5
    assert height.max() == pytest.approx(2.0 * math.tan(math.radians(11.0)), abs=0.03)
    assert height.min() == pytest.approx(-2.0 * math.tan(math.radians(11.0)), abs=0.03)
    # bearings follow the scan's azimuths
    bearing = np.degrees(np.arctan2(pts[:, 1] - offset[1], pts[:, 0] - offset[0]))
    assert bearing.min() > -2.0 and bearing.max() < 122.0
    last = point.points("sensor")
    assert last.shape == (np.count_nonzero(point.profile), 3)
    assert np.allclose(point_points(point, "vehicle") - last, [0.3, -0.2, 0.6])


def test_room_points_lie_on_its_walls_and_furniture(make_rig: RigFactory) -> None:
    scene = Scene.room()
    rig = make_rig(scene=scene, noise=False)
    with BirisServer(rig.hardware) as server:
        conn = server.open()
        conn.single_scan(175.0)
        conn.wait_idle(timeout=WAIT)
        conn.single_scan(-175.0)
        conn.wait_idle(timeout=WAIT)
        scans = [conn.request_scan_data(d) for d in (Direction.CCW, Direction.CW)]
    pts = np.vstack([s.points("vehicle") for s in scans if s is not None])
    assert pts.shape[0] > 5000
    # the low crate (0.35 m high, 0.8 x 0.5 m at (-1.2, -1.6)) shows its top to the lower rows
    on_top = (np.abs(pts[:, 2] - 0.35) < 0.005) & (np.abs(pts[:, 0] + 1.2) <= 0.4)
    on_top &= np.abs(pts[:, 1] + 1.6) <= 0.25
    assert 0 < np.count_nonzero(on_top) < 100
    miss = scene.distance_to_surface_2d(pts[~on_top, :2])
    # each acquisition is tagged with the encoder's whole count at mid-exposure; a count is
    # ~5 mm at 3.5 m, more along a wall seen at a glancing angle
    assert miss.max() < 0.02
    assert np.median(miss) < 0.005
    # the fan never reaches above the walls or below the floor (to a count of tilt)
    assert pts[:, 2].min() > -0.01 and pts[:, 2].max() < 2.5
