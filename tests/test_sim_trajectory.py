"""A moving vehicle in the simulator: its paths, the optics seeing from it, and its odometry.

The paths and the odometry are checked by direct calls against poses worked out by hand; the
optics against a round wall seen from off its centre; the whole rig on virtual time, through
BIRIS's own commands and through a server's scan.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

import sim
from biris_hw import BirisServer
from biris_hw.data import Direction
from biris_hw.timebase import ScaledTime
from regs import biexec
from sim import OdometryParams, Scene, SimulatedBiris, Trajectory
from sim.odometry import Odometry, OdometrySample
from sim.optics import BirisOptics, OpticsParams
from sim.ramdisk import BOOT_FILE
from sim.trajectory import wrap_angle

TIMES = np.linspace(-1.0, 20.0, 211)


def _angle_error(a: float | np.ndarray, b: float | np.ndarray) -> float:
    return float(np.max(np.abs((np.asarray(a) - b + math.pi) % (2 * math.pi) - math.pi)))


def _assert_pose(got: tuple[float, float, float], want: tuple[float, float, float]) -> None:
    assert got[0] == pytest.approx(want[0], abs=1e-9)
    assert got[1] == pytest.approx(want[1], abs=1e-9)
    assert _angle_error(got[2], want[2]) < 1e-9
    assert -math.pi <= got[2] < math.pi


# --- the paths ------------------------------------------------------------------------------------


def test_the_design_name_is_exported() -> None:
    assert sim.Trajectory is Trajectory and sim.OdometryParams is OdometryParams


@pytest.mark.parametrize("heading_deg", [0.0, 30.0, -135.0])
def test_a_line_runs_at_its_speed_along_its_heading(heading_deg: float) -> None:
    v, start = 0.4, 2.0
    path = Trajectory.line(speed_mps=v, heading_deg=heading_deg, start_s=start)
    h = math.radians(heading_deg)
    for t in TIMES:
        s = v * max(0.0, t - start)
        _assert_pose(path.pose(float(t)), (s * math.cos(h), s * math.sin(h), h))
        assert path.twist(float(t)) == ((v, 0.0) if t >= start else (0.0, 0.0))
    assert path.end_s == math.inf and path.moves


@pytest.mark.parametrize("radius", [3.0, -1.5])
def test_an_arc_rounds_its_circle_from_the_origin(radius: float) -> None:
    v = 0.5
    path = Trajectory.arc(speed_mps=v, radius_m=radius)
    for t in TIMES:
        yaw = v * max(0.0, t) / radius  # left for a positive radius, centre at (0, r)
        want = (radius * math.sin(yaw), radius * (1.0 - math.cos(yaw)), yaw)
        _assert_pose(path.pose(float(t)), want)
        assert math.hypot(want[0], want[1] - radius) == pytest.approx(abs(radius))
    lap = 2.0 * math.pi * abs(radius) / v
    _assert_pose(path.pose(lap), (0.0, 0.0, 0.0))
    assert path.twist(1.0) == (v, v / radius)


def test_waypoints_are_reached_at_the_times_their_legs_and_turns_take() -> None:
    points = [(1.0, 0.0, 0.5), (1.0, 1.0, 0.25), (0.0, 0.0, 1.0)]
    path = Trajectory.waypoints(points, start_s=1.0, turn_rate_deg_s=90.0)
    # by hand: 1 m at 0.5 m/s; turn left 90 degrees (1 s); 1 m at 0.25 m/s; turn to face
    # (0, 0) from (1, 1), heading -135 degrees: 135 more to the left (1.5 s); sqrt(2) m at 1 m/s
    arrive = [1.0 + 2.0, 1.0 + 2.0 + 1.0 + 4.0, 1.0 + 2.0 + 1.0 + 4.0 + 1.5 + math.sqrt(2.0)]
    headings = [0.0, math.pi / 2.0, -3.0 * math.pi / 4.0]
    for (x, y, _), t, h in zip(points, arrive, headings, strict=True):
        _assert_pose(path.pose(t), (x, y, h))
    assert path.end_s == pytest.approx(arrive[-1])
    _assert_pose(path.pose(0.5), (0.0, 0.0, 0.0))  # standing until start_s
    _assert_pose(path.pose(2.0), (0.5, 0.0, 0.0))  # half way along the first leg
    _assert_pose(path.pose(3.5), (1.0, 0.0, math.pi / 4.0))  # half way through the first turn
    speed, yaw_rate = path.twist(3.5)
    assert speed == 0.0 and yaw_rate == pytest.approx(math.pi / 2.0)
    _assert_pose(path.pose(100.0), (0.0, 0.0, headings[-1]))  # stands on the last point
    assert path.twist(100.0) == (0.0, 0.0)


def test_standing_never_moves() -> None:
    path = Trajectory.standing()
    assert not path.moves
    for t in TIMES:
        assert path.pose(float(t)) == (0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    "path",
    [
        Trajectory.arc(0.5, 3.0, start_s=0.5),
        Trajectory.line(1.0, 45.0),
        Trajectory.waypoints([(1.0, 0.0, 0.5), (1.0, 1.0, 0.25), (-1.0, 0.5, 1.0)]),
    ],
    ids=repr,
)
def test_the_array_form_is_the_scalar_form(path: Trajectory) -> None:
    t = np.concatenate((TIMES, np.linspace(0.0, 12.0, 1201)))
    x, y, yaw = path.poses(t)
    v, w = path.twists(t)
    for i, ti in enumerate(t):
        px, py, pyaw = path.pose(float(ti))
        assert abs(px - x[i]) < 1e-12 and abs(py - y[i]) < 1e-12
        assert _angle_error(pyaw, yaw[i]) < 1e-12
        assert path.twist(float(ti)) == (v[i], w[i])
    _, _, unwrapped = path.poses(t, unwrapped=True)
    assert _angle_error(unwrapped, yaw) < 1e-12
    _, _, unwrapped = path.poses(np.linspace(0.0, 60.0, 6001), unwrapped=True)
    assert np.all(np.abs(np.diff(unwrapped)) < 0.1)  # continuous: no jump of 2 pi


@pytest.mark.parametrize(
    "make",
    [
        lambda: Trajectory.line(0.0),
        lambda: Trajectory.line(-1.0),
        lambda: Trajectory.line(math.nan),
        lambda: Trajectory.line(0.5, heading_deg=math.inf),
        lambda: Trajectory.line(0.5, start_s=math.nan),
        lambda: Trajectory.arc(0.5, 0.0),
        lambda: Trajectory.arc(0.5, math.inf),
        lambda: Trajectory.waypoints([]),
        lambda: Trajectory.waypoints([(1.0, 0.0, 0.0)]),
        lambda: Trajectory.waypoints([(1.0, 0.0, 0.5), (1.0, 0.0, 0.5)]),
        lambda: Trajectory.waypoints([(1.0, 0.0)]),  # type: ignore[list-item]
        lambda: Trajectory.waypoints([(1.0, 0.0, 0.5)], turn_rate_deg_s=0.0),
    ],
)
def test_bad_paths_are_refused(make: Callable[[], Trajectory]) -> None:
    with pytest.raises(ValueError):
        make()


def test_wrap_angle_brings_angles_into_the_half_open_turn() -> None:
    assert wrap_angle(math.pi) == -math.pi
    assert wrap_angle(3.0 * math.pi / 2.0) == pytest.approx(-math.pi / 2.0)
    assert wrap_angle(-0.25) == -0.25


# --- the optics on a moving vehicle ---------------------------------------------------------------


def _depths(optics: BirisOptics, azimuth: float, pose: tuple[float, float, float] | None) -> float:
    """Every row's range (m) of one noiseless acquisition: equal on a round wall."""
    a = optics.acquire(Scene.circle(3.0), azimuth, vehicle_pose=pose)
    rows = a.range_mm[1:]
    assert rows.min() == rows.max() > 0
    return float(rows[0]) / 1000.0


def _wall_distance(x: float, y: float, heading: float, radius: float = 3.0) -> float:
    """Horizontal distance from (x, y) along ``heading`` to the inside of a circle round 0."""
    c, s = math.cos(heading), math.sin(heading)
    b = x * c + y * s
    return -b + math.sqrt(b * b - (x * x + y * y - radius * radius))


@pytest.mark.parametrize(
    ("pose", "azimuth"),
    [
        ((1.0, 0.0, 0.0), 0.0),  # driven 1 m towards the wall: it is 1 m closer
        ((0.3, 0.0, 0.0), math.pi),  # and further from the wall behind
        ((1.0, 0.0, math.pi / 2.0), 0.0),  # turned left: looking along +y
        ((-0.5, 1.2, -2.0), 2.7),
    ],
)
def test_the_optics_see_from_where_the_vehicle_stands(
    pose: tuple[float, float, float], azimuth: float
) -> None:
    optics = BirisOptics(64, np.random.default_rng(0), noise=False)
    want = _wall_distance(pose[0], pose[1], pose[2] + azimuth)
    assert want < 3.45  # within reach
    assert _depths(optics, azimuth, pose) == pytest.approx(want, abs=0.0006)
    if pose == (1.0, 0.0, 0.0) and azimuth == 0.0:
        assert _depths(optics, azimuth, None) == pytest.approx(3.0)  # standing: the radius


def test_the_head_rides_on_its_mount() -> None:
    """A pan axis 0.5 m ahead of the vehicle's origin is 0.5 m to the left once it faces +y."""
    optics = BirisOptics(64, np.random.default_rng(0), OpticsParams(mount_xy_m=(0.5, 0.0)))
    origin, directions = optics.rays(0.0, vehicle_pose=(1.0, -1.0, math.pi / 2.0))
    assert origin == pytest.approx([1.0, -0.5, 0.5])
    assert np.allclose(directions[:, 0], 0.0, atol=1e-12) and np.all(directions[:, 1] > 0.9)
    with pytest.raises(ValueError):
        OpticsParams(mount_xy_m=(0.0, math.nan))


# --- the rig --------------------------------------------------------------------------------------


def _execute(rig: SimulatedBiris, code: int, param: str = "") -> None:
    hw = rig.hardware
    done = rig.supervisor.commands_completed + 1
    hw.biris.write(hw.biexec_offset + biexec.OFF_PARAM, biexec.encode_param(param))
    hw.biris.write16(hw.biexec_offset + biexec.OFF_COMMAND, code)
    assert rig.supervisor.wait_for(lambda s: s.commands_completed == done, 10.0)
    assert hw.biris.read16(hw.biexec_offset + biexec.OFF_STATUS) == biexec.BiStatus.OK


def test_driving_at_the_wall_shortens_the_range_by_the_distance_driven(no_leaks: None) -> None:
    """Head dead ahead, vehicle driving along +x inside a 3 m round wall: each acquisition reads
    3 m less how far the vehicle had come at its exposure."""
    n, speed = 30, 0.5
    with SimulatedBiris(
        scene=Scene.circle(3.0),
        noise=False,
        initial_azimuth_counts=0.0,
        clock="virtual",
        trajectory=Trajectory.line(speed, start_s=0.1),
    ) as rig:
        hw = rig.hardware
        _execute(rig, biexec.BiCommand.BI_BOOT, BOOT_FILE)
        hw.biris.write16(hw.biexec_offset + biexec.OFF_MOTOR_ACCESS, 1)
        _execute(rig, biexec.BiCommand.BI_ACQUIRE, str(n))
        times = rig.supervisor.acquisition_times_since(0)
        assert len(times) == n and times[0] > 0.1
        elements = rig.samples + 1
        ranges = []
        for k, t in enumerate(times):
            raw = hw.biris.read(rig.memory_map.addressing.range_frame(k), 2 * elements)
            frame = np.frombuffer(raw, dtype=">i2")
            assert frame.min() == frame.max()  # every row and the closest: one depth
            driven = speed * (t - 0.1)
            assert rig.true_pose(t) == pytest.approx((driven, 0.0, 0.0))
            assert frame[1] == round(1000.0 * (3.0 - driven))
            ranges.append(int(frame[1]))
        assert ranges[0] - ranges[-1] == pytest.approx(
            1000.0 * speed * (times[-1] - times[0]), abs=1
        )
        assert rig.audit.violations == []


def _scan_on(trajectory: Trajectory) -> tuple[SimulatedBiris, np.ndarray, np.ndarray]:
    """One 180 degree scan of a 3 m round wall from a vehicle on ``trajectory``: the rig, the
    scan's vehicle-frame points (x, y), and each placed in the scene by the true pose at its
    acquisition's time."""
    points = []
    with SimulatedBiris(
        scene=Scene.circle(3.0), seed=3, noise=False, clock="virtual", trajectory=trajectory
    ) as rig:
        with BirisServer(rig.hardware) as server:
            conn = server.open()
            conn.single_scan(180.0)
            conn.wait_idle()
            scan = conn.request_scan_data(Direction.CCW) or conn.request_scan_data(Direction.CW)
            assert scan is not None and len(scan.t) > 30
        grid = scan.points("vehicle")
        at = np.repeat(scan.t, (scan.range_mm > 0).sum(axis=1))
        for t, p in zip(at, grid, strict=True):
            x, y, yaw = rig.true_pose(float(t))
            c, s = math.cos(yaw), math.sin(yaw)
            points.append((x + c * p[0] - s * p[1], y + s * p[0] + c * p[1]))
    return rig, grid[:, :2], np.array(points)


def test_a_scan_from_a_vehicle_on_an_arc_lies_on_the_wall_placed_by_the_truth(
    no_leaks: None,
) -> None:
    rig, in_vehicle, in_scene = _scan_on(Trajectory.arc(0.5, 1.0))
    assert rig.true_pose(2.0)[2] == pytest.approx(1.0)  # it has turned a radian by the scan
    # the scan's azimuths are the encoder's (whole counts, a few counts behind the true head):
    # a few millimetres on a wall 2-3.5 m away
    assert np.abs(np.hypot(*in_scene.T) - 3.0).max() < 0.015
    # taken as if the vehicle stood at the origin, the same points miss the wall by far
    assert np.abs(np.hypot(*in_vehicle.T) - 3.0).max() > 0.5


def test_without_a_trajectory_the_vehicle_stands_at_the_origin(no_leaks: None) -> None:
    with SimulatedBiris(scene=Scene.circle(2.0), clock="virtual") as rig:
        assert rig.trajectory is None
        rig.timebase.sleep(1.0)
        assert rig.true_pose(0.5) == (0.0, 0.0, 0.0)
        samples = rig.odometry.since(-1.0)
        assert [s.seq for s in samples] == list(range(51))
        assert all(s[1:6] == (0.0, 0.0, 0.0, 0.0, 0.0) for s in samples)


# --- odometry -------------------------------------------------------------------------------------


class _Clock:
    """A hand-moved hardware clock, for direct calls."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _odometry(path: Trajectory, params: OdometryParams, seed: int = 0) -> tuple[Odometry, _Clock]:
    clock = _Clock()
    return Odometry(
        path, params, seed=seed, clock=clock, timebase=ScaledTime(1.0, clock=clock)
    ), clock


def _run(odom: Odometry, clock: _Clock, until_s: float, step_s: float) -> list[OdometrySample]:
    """Poll as a consumer does, every ``step_s``, until ``until_s``."""
    got: list[OdometrySample] = []
    last = -1.0
    while clock.t < until_s:
        clock.t = min(until_s, clock.t + step_s)
        new = odom.since(last)
        if new:
            got += new
            last = new[-1].t
    return got


WAYPOINTS = Trajectory.waypoints([(2.0, 0.0, 0.5), (2.0, 2.0, 0.5), (0.0, 1.0, 1.0)])


@pytest.mark.parametrize("path", [Trajectory.arc(0.5, 3.0), WAYPOINTS], ids=repr)
def test_odometry_without_drift_is_the_truth_at_its_stamps(path: Trajectory) -> None:
    odom, clock = _odometry(path, OdometryParams())
    samples = _run(odom, clock, 15.0, 0.37)
    assert [s.seq for s in samples] == list(range(751))  # 50 Hz, none lost, none twice
    t, x, y, yaw, v, w, seq = np.array(samples).T
    assert np.abs(t - seq / 50.0).max() < 1e-12
    tx, ty, tyaw = path.poses(t)
    assert np.abs(x - tx).max() < 1e-9 and np.abs(y - ty).max() < 1e-9
    assert _angle_error(yaw, tyaw) < 1e-9 and np.all((-math.pi <= yaw) & (yaw < math.pi))
    tv, tw = path.twists(t)
    assert np.array_equal(v, tv) and np.array_equal(w, tw)


def test_odometry_drifts_as_configured() -> None:
    """2 % long wheels on a straight run: 2 % too far; a 0.01 rad/s gyro bias standing still:
    0.01 rad a second; both while driving an arc: the heading departs by the bias alone."""
    line = Trajectory.line(0.5)
    odom, clock = _odometry(line, OdometryParams(scale_error=0.02))
    s = _run(odom, clock, 10.0, 1.0)[-1]
    assert (s.x_m, s.y_m, s.yaw_rad) == pytest.approx((1.02 * 5.0, 0.0, 0.0))
    assert s.v_mps == pytest.approx(0.51)

    odom, clock = _odometry(Trajectory.standing(), OdometryParams(yaw_rate_bias_rad_s=0.01))
    s = _run(odom, clock, 10.0, 1.0)[-1]
    assert (s.x_m, s.y_m, s.yaw_rad, s.omega_rad_s) == pytest.approx((0.0, 0.0, 0.1, 0.01))

    arc = Trajectory.arc(0.5, 3.0)
    odom, clock = _odometry(arc, OdometryParams(yaw_rate_bias_rad_s=0.01))
    samples = _run(odom, clock, 10.0, 0.5)
    for s in samples:
        assert _angle_error(s.yaw_rad, arc.pose(s.t)[2] + 0.01 * s.t) < 1e-9
    # a heading 0.1 rad off by the end bends the path it believes: tens of centimetres
    end = samples[-1]
    off = math.hypot(end.x_m - arc.pose(10.0)[0], end.y_m - arc.pose(10.0)[1])
    assert 0.05 < off < 0.5


def test_odometry_noise_is_as_configured_and_fixed_by_the_seed() -> None:
    params = OdometryParams(distance_noise=0.05, yaw_rate_noise_rad_s=0.02)
    path = Trajectory.line(0.5)

    def samples(seed: int, step: float) -> list[OdometrySample]:
        odom, clock = _odometry(path, params, seed)
        return _run(odom, clock, 40.0, step)

    a = samples(1, 0.05)
    assert a == samples(1, 3.3)  # whenever and in whatever pieces it is asked for
    assert a != samples(2, 0.05)
    v = np.array([s.v_mps for s in a[1:]])
    w = np.array([s.omega_rad_s for s in a[1:]])
    assert np.std(v / 0.5 - 1.0) == pytest.approx(0.05, rel=0.1)
    assert np.std(w) == pytest.approx(0.02, rel=0.1) and abs(np.mean(w)) < 0.003
    assert a[-1].x_m != pytest.approx(20.0, abs=1e-6)  # it wanders off the truth


def test_odometry_holds_a_bounded_history() -> None:
    odom, clock = _odometry(Trajectory.line(0.5), OdometryParams(history=100))
    clock.t = 1000.0
    held = odom.since(-1.0)
    assert [s.seq for s in held] == list(range(49901, 50001))
    assert odom.latest() == held[-1] and held[-1].x_m == pytest.approx(500.0)
    assert odom.since(held[-1].t) == []
    clock.t = 1000.01
    assert odom.since(held[-1].t) == []  # the next stamp is not due yet
    clock.t = 1000.02
    assert [s.seq for s in odom.since(held[-1].t)] == [50001]


@pytest.mark.parametrize(
    "changes",
    [
        {"rate_hz": 0.0},
        {"rate_hz": math.inf},
        {"scale_error": -1.0},
        {"yaw_rate_bias_rad_s": math.nan},
        {"distance_noise": -0.1},
        {"yaw_rate_noise_rad_s": math.inf},
        {"history": 0},
        {"history": 2.5},
    ],
)
def test_bad_odometry_settings_are_refused(changes: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        OdometryParams(**changes)  # type: ignore[arg-type]


def test_a_consumer_waits_for_each_sample_on_virtual_time(no_leaks: None) -> None:
    """The rig's odometry on virtual time: each wait ends at the next stamp, to the sample."""
    path = Trajectory.arc(0.5, 2.0)
    with SimulatedBiris(scene=Scene.circle(2.0), clock="virtual", trajectory=path) as rig:
        got: list[OdometrySample] = []
        last = rig.odometry.latest().t
        while len(got) < 100:
            new = rig.odometry.wait(last)
            assert [s.seq for s in new] == [round(last * 50.0) + 1]
            assert rig.clock.now() == pytest.approx(new[0].t, abs=1e-12)
            got += new
            last = new[-1].t
        for s in got:
            _assert_pose((s.x_m, s.y_m, s.yaw_rad), rig.true_pose(s.t))
        before = rig.clock.now()
        assert rig.odometry.wait(last, timeout_hw=0.005) == []
        assert rig.clock.now() == pytest.approx(before + 0.005)
