"""The proximity alarm: the nearest return inside the zone on the vehicle's path, with its age.

By hand on acquisitions made here, and end to end on virtual time: the simulated vehicle drives
straight at an obstacle placed in its path (``Scene.with_shapes``), the head sweeping ahead, and
the alarm's distance is held against the truth.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from numpy.typing import ArrayLike

from biris_hw import BirisServer
from biris_hw.data import Direction, VehiclePoses
from biris_hw.io import codec
from biris_hw.io.grid import StandingPoses
from biris_hw.io.proximity import Proximity, ProximityAlarm, ProximityZone
from biris_hw.opening import open_poses
from sim import Scene, SimulatedBiris, Trajectory
from sim.scene.shapes import Cylinder

QUARTER = 1024  # counts: 90 degrees


class _Poses:
    """The vehicle on the x axis, facing +x, at x = speed * t (none before ``start``)."""

    def __init__(self, speed: float = 0.0, start: float = -math.inf) -> None:
        self.speed, self.start = speed, start

    def poses_at(self, times: ArrayLike) -> VehiclePoses:
        t = np.asarray(times, dtype=np.float64)
        ok = t >= self.start
        x = np.where(ok, self.speed * t, np.nan)
        zero = np.where(ok, 0.0, np.nan)
        return VehiclePoses(t, x, zero, zero.copy(), ok)


def _wall(alarm: ProximityAlarm, t: float, depth_mm: int, azimuth: int, poses: object) -> None:
    """One acquisition whose every row sees a surface ``depth_mm`` away at ``azimuth``."""
    r = np.full((1, 64), depth_mm, dtype=np.int16)
    alarm.add_acquisitions(r, [azimuth], 0, [t], poses)  # type: ignore[arg-type]


def test_the_zone_grows_with_the_forward_speed() -> None:
    zone = ProximityZone(length_m=0.5, time_s=1.5)
    assert zone.length_at(0.0) == 0.5 and zone.length_at(0.4) == pytest.approx(1.1)
    assert zone.length_at(-0.3) == 0.5  # reversing: the zone ahead does not grow
    alarm = ProximityAlarm(zone)
    _wall(alarm, 1.0, 1000, 0, _Poses(0.4))  # seen from x = 0.4: a surface at x = 1.4
    moving = alarm.check(1.0, _Poses(0.4))
    assert moving is not None and moving.speed_mps == pytest.approx(0.4)
    assert moving.found and moving.distance_m == pytest.approx(1.0, abs=0.01)
    still = alarm.check(1.0, _Poses(0.4), speed_mps=0.0)
    assert still is not None and not still.found and still.zone_length_m == 0.5


def test_the_nearest_surface_in_the_zone_with_its_age_and_where_it_is() -> None:
    alarm = ProximityAlarm(ProximityZone(width_m=0.6, length_m=1.5, front_m=0.2))
    poses = StandingPoses()
    _wall(alarm, 1.0, 1200, 0, poses)  # ahead, 1.2 m
    _wall(alarm, 1.1, 900, 100, poses)  # 8.8 deg left: y = 0.14, inside the 0.3 m half-width
    _wall(alarm, 1.2, 500, QUARTER, poses)  # to the left: outside the zone
    _wall(alarm, 1.3, 800, 270, poses)  # 23.7 deg left: y = 0.32, just outside
    answer = alarm.check(1.5, poses)
    assert answer is not None and answer.found
    x = 0.9 * math.cos(math.radians(100 * 360 / 4096))
    assert answer.x_m == pytest.approx(x, abs=0.005) and answer.y_m == pytest.approx(
        0.138, abs=0.005
    )
    assert answer.distance_m == pytest.approx(x - 0.2, abs=0.005)  # from the zone's start
    assert answer.age_s == pytest.approx(0.4)
    assert answer.looked_age_s == pytest.approx(0.2)  # the ray at 23.7 deg crossed the zone
    # what the head saw longer ago than the memory is forgotten
    later = alarm.check(1.1 + ProximityZone().memory_s + 0.01, poses)
    assert later is not None and not later.found and later.distance_m == math.inf
    assert math.isnan(later.age_s) and math.isnan(later.x_m)


def test_a_resighting_keeps_the_news_fresh_and_a_ray_through_a_surface_clears_it() -> None:
    alarm = ProximityAlarm()
    poses = StandingPoses()
    _wall(alarm, 1.0, 400, 0, poses)
    _wall(alarm, 1.5, 403, 0, poses)  # the same obstacle, 3 mm farther: one obstacle
    seen = alarm.check(1.6, poses, speed_mps=0.0)
    assert seen is not None and seen.found
    assert seen.distance_m == pytest.approx(0.4, abs=0.002)  # the nearer sighting
    assert seen.age_s == pytest.approx(0.1)  # the fresher one's age
    _wall(alarm, 1.7, 2500, 0, poses)  # a newer ray passes where it was: it is gone
    gone = alarm.check(1.8, poses, speed_mps=0.0)
    assert gone is not None and not gone.found and gone.looked_age_s == pytest.approx(0.1)


def test_without_a_pose_nothing_is_placed_and_nothing_is_said() -> None:
    alarm = ProximityAlarm()
    poses = _Poses(0.0, start=2.0)
    _wall(alarm, 1.0, 400, 0, poses)
    assert (alarm.unplaced, alarm.acquisitions) == (1, 0)
    assert alarm.check(1.0, poses) is None  # where is the zone? nobody knows
    answer = alarm.check(2.5, poses)  # the pose 0.2 s before is missing: speed 0
    assert answer is not None and answer.speed_mps == 0.0 and not answer.found


def test_the_answer_goes_out_as_a_message_and_comes_back() -> None:
    answer = Proximity(12.25, True, 0.31, 0.61, -0.05, 0.08, 0.03, 1.1, 0.6, 0.4)
    message = answer.message()
    assert (message.topic, message.msgtype) == ("/biris/proximity", "biris_msgs/msg/Proximity")
    assert message.log_time_ns == 12_250_000_000
    back = codec.decode_proximity(message.data)
    assert back.frame_id == "vehicle" and back.t == pytest.approx(12.25)
    assert tuple(back)[2:] == pytest.approx(tuple(answer)[1:])
    clear = Proximity(3.0, False, math.inf, math.nan, math.nan, math.nan, math.inf, 0.5, 0.6, 0.0)
    back = codec.decode_proximity(clear.message().data)
    assert not back.found and back.distance_m == math.inf and math.isnan(back.age_s)
    with pytest.raises(codec.WireError):
        codec.decode_proximity(message.data[:-5])


@pytest.mark.parametrize(
    "options",
    [{"width_m": 0.0}, {"length_m": -1.0}, {"time_s": math.inf}, {"band_m": (2.0, 1.0)}],
)
def test_bad_zones_are_refused(options: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        ProximityZone(**options)  # type: ignore[arg-type]


# -- end to end: an obstacle in the path -----------------------------------------------------------

OBSTACLE = Cylinder(center=(1.6, 0.05), radius=0.15, height=1.0)
SPEED = 0.4
START_S = 8.0


@dataclass
class Drive:
    answers: list[Proximity]
    x: list[float]
    """The vehicle's true x at each answer."""


def _drive(scene: Scene, until_s: float = START_S + 3.0) -> Drive:
    """Straight along +x at SPEED from START_S, the head sweeping +-30 degrees ahead until
    hardware time ``until_s``; the alarm fed each scan and asked at its last acquisition's
    time."""
    alarm = ProximityAlarm()
    path = Trajectory.line(SPEED, start_s=START_S)
    drive = Drive([], [])
    rig = SimulatedBiris(scene=scene, seed=3, clock="virtual", trajectory=path)
    with rig, BirisServer(rig.hardware) as server, open_poses(sim=rig) as poses:
        conn = server.open()
        conn.wait_idle()
        conn.single_scan(-30.0)
        conn.wait_idle()
        i = 0
        while server.clock() < until_s:
            to = 30.0 if i % 2 == 0 else -30.0
            i += 1
            conn.single_scan(to)
            conn.wait_idle()
            scan = conn.request_scan_data(Direction.CCW if to > 0 else Direction.CW)
            assert scan is not None and scan.n_acq > 5
            now = float(scan.t[-1])
            assert poses.wait_for(now, timeout_hw=1.0)
            assert alarm.add_scan(scan, poses).unplaced == 0
            answer = alarm.check(now, poses)
            assert answer is not None
            drive.answers.append(answer)
            drive.x.append(rig.true_pose(now)[0])
    return drive


@pytest.fixture(scope="module")
def with_obstacle() -> Iterator[Drive]:
    yield _drive(Scene.room().with_shapes(OBSTACLE))


def test_an_obstacle_in_the_path_is_reported_at_its_true_distance(with_obstacle: Drive) -> None:
    front = OBSTACLE.center[0] - OBSTACLE.radius
    reported = 0
    for answer, x in zip(with_obstacle.answers, with_obstacle.x, strict=True):
        ahead = front - x  # the truth: how far ahead the obstacle's face is
        assert answer.looked_age_s < 0.6  # a +-30 degree sweep looks ahead all the time
        if answer.t > START_S + 0.3:
            assert answer.speed_mps == pytest.approx(SPEED, abs=0.01)
            assert answer.zone_length_m == pytest.approx(0.5 + 1.5 * SPEED, abs=0.02)
        if ahead > answer.zone_length_m + 0.1:
            assert not answer.found, (answer, ahead)  # nothing else lies in the path
        elif 0.35 < ahead < answer.zone_length_m - 0.1:  # in the zone, in the sensor's range
            assert answer.found, (answer, ahead)
            assert answer.distance_m == pytest.approx(ahead, abs=0.03)
            assert abs(answer.y_m - OBSTACLE.center[1]) < OBSTACLE.radius
            assert 0.0 <= answer.age_s < 0.6
            reported += 1
    assert reported >= 2  # the drive did bring it into the zone


@pytest.mark.slow  # the fast tier keeps a cheaper test of the same (make test-slow runs this)
def test_nothing_in_the_path_leaves_the_alarm_quiet() -> None:
    clear = _drive(Scene.room())
    for answer, x in zip(clear.answers, clear.x, strict=True):
        assert 2.9 - x > answer.zone_length_m  # the front wall stays beyond the zone
        assert not answer.found, answer
        assert answer.looked_age_s < 0.6  # and it is a fresh "nothing"
