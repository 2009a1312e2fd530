"""The certainty grid: exact ray traversal, the log-odds update, its message, and one drive
through the simulated room held against the scene's truth (the ``grid`` benchmark's
measurement, shorter, with a looser bound)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import ArrayLike

from benchmarks.grid import DriveMap, drive_and_map
from biris_hw.data import Direction, PoseSample, Scan, VehiclePoses
from biris_hw.geometry import Mount, project_profiles
from biris_hw.io import codec
from biris_hw.io.grid import (
    CertaintyGrid,
    GridFeeder,
    GridParams,
    PoseWait,
    Rays,
    StandingPoses,
    crossed_cells,
    grid_figure,
    profile_rays,
)
from biris_hw.io.pose import PoseBuffer
from biris_hw.io.record import RAW_SCAN_TOPIC
from biris_hw.io.record.mcapfile import McapFile
from sim import Scene
from sim.drives import DRIVE_CLEARANCE_M, default_drive, path_clearance
from tests.conftest import Run

RES = 0.05
LOG_HIT = math.log(0.7 / 0.3)
LOG_MISS = math.log(0.4 / 0.6)


def _rays(t: ArrayLike, origin: ArrayLike, heading: ArrayLike, distance: ArrayLike) -> Rays:
    return Rays(
        np.asarray(t, dtype=np.float64),
        np.asarray(origin, dtype=np.float64).reshape(-1, 2),
        np.asarray(heading, dtype=np.float64),
        np.asarray(distance, dtype=np.float64).reshape(len(np.atleast_1d(t)), -1),
    )


def _small(**options: object) -> CertaintyGrid:
    """A 4 m x 4 m grid round the origin, 5 cm cells."""
    return CertaintyGrid(GridParams(extent_m=(-2.0, -2.0, 2.0, 2.0), **options))  # type: ignore[arg-type]


def _cell(grid: CertaintyGrid, x: float, y: float) -> tuple[int, int]:
    row, col = grid.cell_of([(x, y)])
    return int(row[0]), int(col[0])


# -- the ray traversal -----------------------------------------------------------------------------


def _sampled(u0: float, v0: float, u1: float, v1: float) -> list[tuple[int, int]]:
    """The cells a segment passes, by sampling it very finely (the reference), in order."""
    t = np.linspace(0.0, 1.0, 200_001)
    cells = np.floor(np.column_stack((u0 + t * (u1 - u0), v0 + t * (v1 - v0)))).astype(int)
    keep = np.ones(t.shape[0], dtype=bool)
    keep[1:] = np.any(cells[1:] != cells[:-1], axis=1)
    return [(int(a), int(b)) for a, b in cells[keep]]


def test_the_cells_a_segment_crosses_are_found_exactly_and_in_order() -> None:
    rng = np.random.default_rng(5)
    ends = rng.uniform(-7.0, 7.0, size=(24, 4))
    ends[0] = (0.5, 0.5, 0.5, 9.5)  # along a column
    ends[1] = (3.2, 1.5, -4.7, 1.5)  # along a row, backwards
    ends[2] = (2.3, 2.3, 2.3, 2.3)  # no length: the cell it sits in
    seg, ci, cj = crossed_cells(ends[:, 0], ends[:, 1], ends[:, 2], ends[:, 3])
    for k, (u0, v0, u1, v1) in enumerate(ends):
        found = [(int(a), int(b)) for a, b in zip(ci[seg == k], cj[seg == k], strict=True)]
        assert found == _sampled(u0, v0, u1, v1), k
    empty = crossed_cells([], [], [], [])
    assert all(a.size == 0 for a in empty)


def test_a_segment_through_a_grid_corner_names_no_cell_it_does_not_enter() -> None:
    seg, ci, cj = crossed_cells([0.5], [0.5], [2.5], [2.5])
    assert list(zip(ci.tolist(), cj.tolist(), strict=True)) == [(0, 0), (1, 1), (2, 2)]
    assert seg.tolist() == [0, 0, 0]


# -- the update ------------------------------------------------------------------------------------


def test_a_ray_frees_the_cells_before_its_surface_and_marks_the_surface() -> None:
    grid = _small()
    grid.integrate(_rays([1.0], [(0.01, 0.01)], [0.0], [[1.0]]))
    lo = grid.log_odds()
    row, start = _cell(grid, 0.01, 0.01)
    _, end = _cell(grid, 1.01, 0.01)
    assert np.allclose(lo[row, start:end], LOG_MISS)
    assert lo[row, end] == pytest.approx(LOG_HIT)
    values = grid.values()
    assert (values[row, start:end] == 40).all() and values[row, end] == 70
    assert np.count_nonzero(values >= 0) == end - start + 1  # the rest is unknown: -1
    assert np.count_nonzero(grid.occupied()) == 1
    assert np.allclose(grid.occupied_xy(), [(1.025, 0.025)])
    assert (grid.acquisitions, grid.t) == (1, 1.0)


def test_free_space_ends_at_the_nearest_surface_and_each_surface_is_marked() -> None:
    grid = _small(join_m=None)
    grid.integrate(_rays([0.0], [(0.01, 0.01)], [math.pi / 2], [[0.5, 1.5]]))
    lo = grid.log_odds()
    row_near, col = _cell(grid, 0.01, 0.51)
    row_far, _ = _cell(grid, 0.01, 1.51)
    assert lo[row_near, col] == pytest.approx(LOG_HIT)
    assert lo[row_far, col] == pytest.approx(LOG_HIT)
    assert (lo[row_near + 1 : row_far, col] == 0.0).all()  # behind the first: nothing said
    assert not grid.known()[row_near + 1 : row_far, col].any()


def test_a_ray_without_a_surface_says_nothing_and_surfaces_outside_are_counted() -> None:
    grid = _small()
    grid.integrate(_rays([0.0, 0.1], [(0.01, 0.01), (1.81, 0.01)], [0.0, 0.0], [[math.nan], [0.5]]))
    assert grid.outside == 1  # the second's surface lies beyond x = 2
    lo = grid.log_odds()
    row, col = _cell(grid, 1.9, 0.01)
    assert lo[row, col] == pytest.approx(LOG_MISS)  # its ray still frees what is inside
    assert np.count_nonzero(grid.known()) == 4  # 1.8 .. 2.0: four cells, all free


def test_evidence_is_clamped_and_fades_by_its_half_life() -> None:
    grid = _small(half_life_s=2.0)
    for k in range(30):
        grid.integrate(_rays([0.01 * k], [(0.01, 0.01)], [0.0], [[1.0]]))
    row, col = _cell(grid, 1.01, 0.01)
    high = math.log(0.97 / 0.03)
    assert grid.log_odds(0.29)[row, col] == pytest.approx(high, rel=1e-3)
    assert grid.log_odds(2.29)[row, col] == pytest.approx(high / 2, rel=1e-3)
    assert grid.values(1000.0)[row, col] == -1  # faded to nothing: unknown again
    # the next update starts from the faded belief
    grid.integrate(_rays([4.29], [(0.01, 0.01)], [0.0], [[1.0]]))
    assert grid.log_odds()[row, col] == pytest.approx(high / 4 + LOG_HIT, rel=1e-3)


def _wall_rays(t: list[float], bearings_deg: list[float]) -> Rays:
    """Rays from (0, 0.01) to a wall at x = 1.51 m."""
    h = np.radians(bearings_deg)
    return _rays(t, np.tile([0.0, 0.01], (len(t), 1)), h, 1.51 / np.cos(h))


def test_neighbouring_surfaces_are_joined_and_distant_or_late_ones_are_not() -> None:
    grid = _small()
    grid.integrate(_wall_rays([0.0, 1 / 30], [0.0, 6.0]))  # 16 cm apart on the wall
    occupied = grid.occupied_xy()
    assert np.allclose(occupied[:, 0], 1.525)
    assert occupied[:, 1].min() < 0.05 and occupied[:, 1].max() > 0.15
    assert occupied.shape[0] == 4  # every cell between the two: a wall, not two dots
    apart = _small()
    apart.integrate(_wall_rays([0.0, 1 / 30], [0.0, 14.0]))  # 37 cm apart: a gap stays open
    assert apart.occupied_xy().shape[0] == 2
    late = _small()
    late.integrate(_wall_rays([0.0], [0.0]))
    late.integrate(_wall_rays([0.5], [6.0]))  # the next sweep, not the next acquisition
    assert late.occupied_xy().shape[0] == 2
    joined = _small()  # across two batches, as a live feed hands them over
    joined.integrate(_wall_rays([0.0], [0.0]))
    joined.integrate(_wall_rays([1 / 30], [6.0]))
    assert np.array_equal(joined.occupied(), grid.occupied())


# -- acquisitions in -------------------------------------------------------------------------------


class _Poses:
    """Fixed poses by time; none at other times."""

    def __init__(self, poses: dict[float, tuple[float, float, float]]) -> None:
        self.poses = poses

    def poses_at(self, times: ArrayLike) -> VehiclePoses:
        t = np.asarray(times, dtype=np.float64)
        rows = [self.poses.get(float(x), (math.nan,) * 3) for x in t]
        x, y, yaw = (np.array(c, dtype=np.float64) for c in zip(*rows, strict=True))
        return VehiclePoses(t, x, y, yaw, np.isfinite(x))


def _scan(range_mm: np.ndarray, azimuth: list[int], t: list[float], **kw: object) -> Scan:
    return Scan(
        direction=Direction.CCW,
        seq=1,
        azimuth=np.asarray(azimuth, dtype=np.int32),
        range_mm=range_mm.astype(np.int16),
        closest_mm=np.where(range_mm > 0, range_mm, 32767).min(axis=1).astype(np.int16),
        intensity=np.zeros(range_mm.shape, dtype=np.int16),
        t=np.asarray(t, dtype=np.float64),
        **kw,  # type: ignore[arg-type]
    )


def test_a_profile_is_placed_as_the_geometry_module_places_it() -> None:
    mount = Mount(offset_m=(0.2, -0.1, 0.3), head_height_m=0.45, head_offset_m=0.07)
    rng = np.random.default_rng(2)
    r = np.full((3, 16), 0, dtype=np.int16)
    r[0, :] = 1500  # a wall: one surface
    r[1, :8], r[1, 8:] = 900, 2600  # two surfaces
    r[2, ::2] = rng.integers(2000, 2050, size=8)  # a wall with gaps
    az = np.array([100, -700, 1500])
    el = 60  # tilted up 5 degrees
    pose = VehiclePoses(
        np.array([1.0, 2.0, 3.0]),
        np.array([0.5, -1.0, 2.0]),
        np.array([0.0, 0.3, -0.4]),
        np.array([0.2, -2.5, 3.0]),
        np.ones(3, dtype=bool),
    )
    rays = profile_rays(r, az, el, r.max(axis=1), pose, mount, params=GridParams(band_m=(0.0, 9.0)))
    points = pose.to_odom(project_profiles(r, az, el, "vehicle", mount))  # the reference
    assert np.allclose(rays.heading, az * 2 * math.pi / 4096 + pose.yaw_rad)
    for k in range(3):
        flat = np.hypot(*(points[k, :, :2] - rays.origin[k]).T)
        # the origin is the optical centre: every return lies on the ray from it
        direction = (points[k, :, :2] - rays.origin[k]) / flat[:, None]
        ok = r[k] > 0
        expected = np.column_stack((np.cos(rays.heading[k]), np.sin(rays.heading[k])))
        assert np.allclose(direction[ok], expected)
        surfaces = rays.distance[k][np.isfinite(rays.distance[k])]
        if k == 1:
            assert np.allclose(surfaces, [flat[:8].mean(), flat[8:].mean()])
        else:
            assert np.allclose(surfaces, [flat[ok].mean()])


def test_returns_outside_the_height_band_count_for_nothing() -> None:
    r = np.full((1, 64), 1000, dtype=np.int16)  # 1 m ahead: rows from 0.31 to 0.69 m high
    scan = _scan(r, [0], [0.0])
    below = CertaintyGrid(GridParams(band_m=(0.8, 2.0)))
    assert below.add_scan(scan, StandingPoses()).placed == 1
    assert not below.known().any()
    inside = CertaintyGrid(GridParams(band_m=(0.6, 2.0)))  # the top rows only
    inside.add_scan(scan, StandingPoses())
    assert np.allclose(inside.occupied_xy(), [(1.025, 0.025)])


def test_an_acquisition_without_a_pose_is_counted_and_never_placed() -> None:
    r = np.full((3, 64), 1000, dtype=np.int16)
    scan = _scan(r, [0, 512, 1024], [0.0, 1.0, 2.0])
    grid = CertaintyGrid()
    done = grid.add_scan(scan, _Poses({0.0: (0.0, 0.0, 0.0), 2.0: (0.0, 0.0, 0.0)}))
    assert (done.placed, done.unplaced, grid.unplaced, grid.acquisitions) == (2, 1, 1, 2)
    occupied = grid.occupied_xy()
    assert occupied.shape[0] == 2  # ahead (0 deg) and to the left (90 deg), not at 45 deg
    assert not np.any(np.isclose(occupied[:, 0], occupied[:, 1]))


def test_the_closest_range_is_the_report_s_2d_data() -> None:
    r = np.zeros((1, 64), dtype=np.int16)
    r[0, 40:] = 1200  # a low box 1.2 m ahead; nothing above it
    scan = _scan(r, [1024], [0.0])  # looking left
    grid = CertaintyGrid()
    grid.add_scan(scan, _Poses({0.0: (1.0, 1.0, 0.0)}), source="closest")
    assert np.allclose(grid.occupied_xy(), [(1.025, 2.225)])
    with pytest.raises(ValueError, match="source"):
        grid.add_scan(scan, StandingPoses(), source="sideways")  # type: ignore[arg-type]


def test_the_feeder_waits_for_the_pose_of_each_acquisition_then_places_or_counts_it() -> None:
    r = np.full((4, 64), 1500, dtype=np.int16)
    scan = _scan(r, [0, 40, 80, 120], [1.0, 1.0 + 1 / 30, 1.0 + 2 / 30, 3.0])
    points = scan.as_points()
    poses = PoseBuffer()
    grid = CertaintyGrid()
    feeder = GridFeeder(grid, poses, wait_s=0.5, rate_hz=2.0)
    assert feeder.add(points[:2]) == (0, 0) and feeder.pending == 2  # no pose yet: they wait
    poses.extend(PoseSample(0.9 + 0.02 * k, 0.0, 0.0, 0.0, 0.0, 0.0, k) for k in range(11))
    assert feeder.add(points[2:3]).placed == 3 and feeder.pending == 0  # poses to 1.1 s
    # a gap in the poses: the next one waits, then is counted once it is too old to wait for
    assert feeder.add(points[3:]) == (0, 0) and feeder.pending == 1
    assert feeder.flush() == (0, 1) and grid.unplaced == 1
    assert feeder.due(0.0) and not feeder.due(0.4) and feeder.due(0.5)


def test_the_pose_wait_hands_on_in_order_what_has_a_pose_or_waited_long_enough() -> None:
    """The rule both feeders keep (grid.PoseWait): an acquisition is ready once a pose at or
    after its time is held, or once it is wait_s behind the newest acquisition; flush hands on
    everything; the newest pose time tells the caller which had a pose."""
    scan = _scan(np.full((5, 64), 1500, dtype=np.int16), [0] * 5, [1.0, 1.2, 1.4, 1.8, 1.95])
    points = scan.as_points()
    poses = PoseBuffer()
    waiting = PoseWait(poses, wait_s=0.5)
    assert waiting.take(points[:2]) == ([], -math.inf) and waiting.pending == 2
    poses.extend(PoseSample(1.0 + 0.05 * k, 0.0, 0.0, 0.0, 0.0, 0.0, k) for k in range(5))  # ..1.2
    ready, newest = waiting.take(points[2:3])
    assert [p.t for p in ready] == [1.0, 1.2] and newest == pytest.approx(1.2)
    ready, _ = waiting.take(points[3:4])  # 1.4 is 0.4 s behind 1.8: it waits on
    assert ready == [] and waiting.pending == 2
    ready, _ = waiting.take(points[4:])  # 1.4 is now 0.55 s behind 1.95: it waited long enough
    assert [p.t for p in ready] == [1.4] and waiting.pending == 2
    ready, newest = waiting.take((), flush=True)
    assert [p.t for p in ready] == [1.8, 1.95] and waiting.pending == 0
    assert newest == pytest.approx(1.2)  # neither had a pose: the caller counts them unplaced
    with pytest.raises(ValueError, match="wait_s"):
        PoseWait(poses, wait_s=math.nan)


def test_live_acquisitions_build_the_grid_a_whole_scan_builds() -> None:
    rng = np.random.default_rng(9)
    r = rng.integers(900, 2500, size=(40, 64)).astype(np.int16)
    r[:, :20] = np.repeat(rng.integers(1000, 3000, size=(40, 1)), 20, axis=1)
    r[rng.random(r.shape) < 0.1] = 0
    times = 5.0 + np.arange(40) / 30.0
    scan = _scan(r, np.linspace(-1024, 1024, 40).astype(int).tolist(), times.tolist())
    poses = PoseBuffer()
    poses.extend(
        PoseSample(4.9 + 0.02 * k, 0.01 * k, 0.0, 0.002 * k, 0.5, 0.1, k) for k in range(80)
    )
    wide = GridParams(clamp=(0.001, 0.999))  # no clamping: the sums must agree exactly
    whole, live = CertaintyGrid(wide), CertaintyGrid(wide)
    whole.add_scan(scan, poses)
    for point in scan.as_points():
        live.add_point(point, poses)
    assert np.allclose(whole.log_odds(), live.log_odds())
    assert np.count_nonzero(whole.occupied()) > 40


# -- the message -----------------------------------------------------------------------------------


def test_the_grid_goes_out_as_a_ros_occupancy_grid() -> None:
    grid = CertaintyGrid(GridParams(extent_m=(-1.0, -0.5, 1.0, 0.5), resolution_m=0.1))
    grid.integrate(_rays([12.5], [(-0.95, -0.45)], [0.0], [[1.5]]))  # along the bottom row
    message = grid.message()
    assert (message.topic, message.msgtype) == ("/biris/grid", "nav_msgs/msg/OccupancyGrid")
    assert message.log_time_ns == 12_500_000_000
    back = codec.decode_occupancy_grid(message.data)
    assert back.frame_id == "odom" and back.t == pytest.approx(12.5)
    assert back.resolution_m == pytest.approx(0.1) and back.origin_m == (-1.0, -0.5)
    assert back.origin_yaw_rad == 0.0 and back.data.shape == (10, 20)
    # row-major from the lower-left cell: the ray runs along row 0 from column 0
    assert back.data[0, :15].tolist() == [40] * 15 and back.data[0, 15] == 70
    assert (back.data[1:] == -1).all() and (back.data[0, 16:] == -1).all()
    assert np.array_equal(back.data, grid.values())
    # an independent reader: rosbags' own store of the standard types
    from rosbags.typesys import Stores, get_typestore

    msg: Any = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(message.data, codec.OCCUPANCY_GRID)
    assert (msg.info.width, msg.info.height) == (20, 10)
    assert msg.data.tolist()[:16] == [40] * 15 + [70]


@pytest.mark.parametrize(
    "values",
    [
        np.full((2, 2), 101),
        np.full((2, 2), -2),
        np.zeros(4),
        np.zeros((0, 3)),
        np.full((2, 2), 0.5),
    ],
)
def test_what_is_not_a_grid_is_refused(values: np.ndarray) -> None:
    with pytest.raises(codec.WireError):
        codec.encode_occupancy_grid(values, 0.05, (0.0, 0.0), 1.0)


def test_a_payload_that_is_not_a_grid_is_a_wire_error() -> None:
    good = codec.encode_occupancy_grid(np.zeros((3, 4), dtype=np.int8), 0.05, (0.0, 0.0), 1.0)
    types = codec.typestore().types
    msg: Any = codec.typestore().deserialize_cdr(good, codec.OCCUPANCY_GRID)
    msg.info = types["nav_msgs/msg/MapMetaData"](
        map_load_time=msg.info.map_load_time, resolution=0.05, width=5, height=3,
        origin=msg.info.origin,
    )  # fmt: skip
    wrong = bytes(codec.typestore().serialize_cdr(msg, codec.OCCUPANCY_GRID))
    with pytest.raises(codec.WireError, match="12 cells for a grid of 5 x 3"):
        codec.decode_occupancy_grid(wrong)
    with pytest.raises(codec.WireError):
        codec.decode_occupancy_grid(good[:-3])


@pytest.mark.parametrize(
    "options",
    [
        {"resolution_m": 0.0},
        {"extent_m": (1.0, 0.0, 0.0, 1.0)},
        {"extent_m": (0.0, 0.0, 1e4, 1e4), "resolution_m": 0.01},
        {"band_m": (1.0, 1.0)},
        {"hit": 0.4},
        {"miss": 1.0},
        {"clamp": (0.6, 0.9)},
        {"half_life_s": -1.0},
        {"join_m": 0.0},
        {"split_ratio": math.nan},
    ],
)
def test_bad_settings_are_refused(options: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        GridParams(**options)  # type: ignore[arg-type]


# -- the drive and the truth -----------------------------------------------------------------------


def test_the_default_drive_keeps_clear_of_everything_and_fits_other_scenes() -> None:
    room = Scene.room()
    drive = default_drive(room)
    t = np.linspace(0.0, drive.end_s, 4000)
    x, y, _ = drive.poses(t)
    assert room.distance_to_surface_2d(np.column_stack((x, y))).min() >= DRIVE_CLEARANCE_M
    assert drive.end_s > 40.0 and drive.pose(drive.end_s)[:2] == pytest.approx((0.0, 0.0))
    circle = default_drive(Scene.circle(3.0))
    x, y, _ = circle.poses(np.linspace(0.0, circle.end_s, 4000))
    assert np.hypot(x, y).max() <= 3.0 - DRIVE_CLEARANCE_M
    with pytest.raises(ValueError, match="does not fit"):
        default_drive(Scene.circle(0.5))
    assert path_clearance(room, [(5.0, 0.0)]) == pytest.approx(0.0, abs=1e-9)  # a wall


@pytest.fixture(scope="module")
def short_drive() -> Iterator[DriveMap]:
    """The first 12 s of the default drive (it sets off at 8 s), swept between +-90 degrees,
    on virtual time."""
    yield drive_and_map(until_s=20.0, seed=1)


def test_one_drive_maps_the_walls_it_swept(short_drive: DriveMap) -> None:
    assert short_drive.unplaced == 0 and len(short_drive.scans) >= 6
    profile = short_drive.score("profile")
    assert profile.swept > 500  # the truth is not a handful of points
    assert profile.precision >= 0.95, profile
    assert profile.recall >= 0.85, profile
    # a cell next to a true wall, and none on the far side of the room from where it drove
    closest = short_drive.score("closest")
    assert closest.recall < profile.recall  # the closest range alone sees less of each wall


def test_a_grid_built_standing_still_is_not_that_of_the_drive(short_drive: DriveMap) -> None:
    """Placed as if the vehicle had stood still, the same scans smear the walls: the truth
    catches it (what the poses are for)."""
    grid = CertaintyGrid()
    for scan in short_drive.scans:
        grid.add_scan(scan, StandingPoses())
    from sim.drives import score_occupied

    wrong = score_occupied(
        short_drive.scene, grid.occupied_xy(), short_drive.swept(), grid.resolution_m
    )
    assert wrong.precision < 0.8


def test_the_picture_shows_the_grid_over_the_true_walls(short_drive: DriveMap) -> None:
    grid = short_drive.grids["profile"]
    fig = grid_figure(grid, short_drive.scene.outline_2d(), path_xy=np.zeros((2, 2)))
    ax = fig.axes[0]
    shown = ax.images[0].get_array() if ax.images else None
    assert shown is not None and shown.shape == grid.shape
    labels = [line.get_label() for line in ax.lines]
    assert "true walls" in labels and "vehicle path" in labels
    x0, x1 = ax.get_xlim()
    assert x0 < -2.1 and x1 > 2.9  # the room, not the whole 20 m grid


# -- the command -----------------------------------------------------------------------------------


def _recording(path: Path, drive: DriveMap, *, poses: bool) -> Path:
    """The drive's scans on the lossless channel and, with ``poses``, odom -> vehicle on /tf."""
    file = McapFile(path)
    for scan in drive.scans:
        file.write(
            RAW_SCAN_TOPIC,
            codec.SCAN,
            codec.schema_text(codec.SCAN),
            codec.encode_scan(scan),
            codec.stamp_ns(float(scan.t[-1])),
        )
    if poses:
        for sample in drive.poses.samples():
            message = codec.odom_transforms([sample])
            file.write(
                message.topic,
                message.msgtype,
                codec.schema_text(message.msgtype),
                message.data,
                message.log_time_ns,
            )
    assert file.close()
    return path


@pytest.mark.slow  # the fast tier keeps a cheaper test of the same (make test-slow runs this)
def test_grid_command_builds_the_grid_of_a_recording(
    fonts_open: None, biris: Run, short_drive: DriveMap, tmp_path: Path
) -> None:
    path = _recording(tmp_path / "run.mcap", short_drive, poses=True)
    code, out, err = biris("grid", str(path), "--plot", str(tmp_path / "grid.png"))
    assert code == 0, err
    expected = int(np.count_nonzero(short_drive.grids["profile"].occupied()))
    assert f"{len(short_drive.scans)} scans; vehicle" in out and "poses from /tf" in out
    assert f" {expected} occupied" in out and "0 without a pose" in out
    assert (tmp_path / "grid.png").stat().st_size > 0
    bare = _recording(tmp_path / "bare.mcap", short_drive, poses=False)
    code, out, err = biris("grid", str(bare))
    assert code == 2 and "holds no vehicle poses" in err and "--standing" in err
    code, out, err = biris("grid", str(bare), "--standing", "--source", "closest")
    assert code == 0 and "standing at the odom origin" in out


@pytest.mark.slow  # the fast tier keeps a cheaper test of the same (make test-slow runs this)
def test_grid_command_on_the_simulator_scores_itself(
    fonts_open: None, biris: Run, tmp_path: Path
) -> None:
    code, out, err = biris("grid", "--sim", "--sweeps", "2", "--plot", str(tmp_path / "g.svg"))
    assert code == 0, err
    assert "vehicle standing at the origin: 2 scans" in out
    assert "against the scene's truth: precision" in out
    precision = float(out.split("precision ")[1].split()[0])
    assert precision >= 0.9
    assert (tmp_path / "g.svg").read_text().startswith("<?xml")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ((), "a recording FILE or --sim"),
        (("--sim", "x.mcap"), "a recording FILE or --sim"),
        (("x.mcap", "--drive"), "--drive goes with --sim"),
        (("x.mcap", "--seed", "3"), "--seed goes with --sim"),
        (("--sim", "--standing"), "--standing is for a recording"),
        (("--sim", "--sweep", "200"), "at most 180"),
        (("--sim", "--resolution", "0.001", "--size", "100"), "cells"),
        (("--sim", "--plot", "grid.unknown"), "unknown extension"),
        (("nothing-here.mcap",), "no such file"),
    ],
)
def test_grid_command_refuses_what_does_not_fit(
    biris: Run, argv: tuple[str, ...], message: str
) -> None:
    code, _, err = biris("grid", *argv)
    assert code == 2 and message in err, err


def test_cli_help_lists_grid(biris: Run) -> None:
    code, out, _ = biris("--help")
    assert code == 0 and "grid" in out
    code, out, _ = biris("grid", "--help")
    assert code == 0 and "--drive" in out and "--standing" in out
