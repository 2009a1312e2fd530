"""The vehicle's pose at any acquisition's time: the buffer, its bounds, and every source.

The buffer is checked against paths worked out exactly (:class:`sim.Trajectory`); the pump on
virtual time against the simulator's truth; the Zenoh source through a real session on
loopback; the recording source through files written here.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from biris_hw.data import PoseSample
from biris_hw.errors import RequestError
from biris_hw.io import codec
from biris_hw.io.codec import ODOMETRY, TRANSFORM_STAMPED, WireError
from biris_hw.io.pose import (
    PoseBuffer,
    PoseFileError,
    PosePump,
    PoseSubscription,
    clock_offset,
    read_poses,
    subscribe_poses,
)
from biris_hw.opening import open_poses
from biris_hw.timebase import VirtualTime
from sim import OdometryParams, Scene, SimulatedBiris, Trajectory
from tests.conftest import WAIT, until
from tests.net_helpers import endpoint, free_port

RATE_HZ = 50.0


def _samples(path: Trajectory, t0: float, t1: float, *, twist: bool = True) -> list[PoseSample]:
    """What a perfect base reports at 50 Hz from ``t0`` to ``t1`` (stamps k / 50)."""
    seq = np.arange(math.ceil(t0 * RATE_HZ), math.floor(t1 * RATE_HZ) + 1)
    t = seq / RATE_HZ
    x, y, yaw = path.poses(t)
    v, w = path.twists(t) if twist else (np.full(t.shape, np.nan),) * 2
    return [PoseSample(*row) for row in zip(t, x, y, yaw, v, w, seq.tolist(), strict=True)]


def _rows(samples: list[PoseSample]) -> np.ndarray:
    """(t, x, y, yaw) of each sample, as an array pytest.approx compares."""
    return np.array([s[:4] for s in samples], dtype=np.float64)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| the short way round."""
    difference: np.ndarray = np.abs((a - b + math.pi) % (2 * math.pi) - math.pi)
    return difference


def _error(path: Trajectory, buffer: PoseBuffer, times: np.ndarray) -> tuple[float, float]:
    """Largest position (m) and yaw (rad) error of ``buffer`` against ``path`` at ``times``."""
    got = buffer.poses_at(times)
    assert got.valid.all()
    x, y, yaw = path.poses(times)
    return (
        float(np.hypot(got.x_m - x, got.y_m - y).max()),
        float(_angle(got.yaw_rad, yaw).max()),
    )


# --- interpolation ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "path",
    [
        Trajectory.arc(speed_mps=0.5, radius_m=3.0),
        Trajectory.arc(speed_mps=1.0, radius_m=-0.5),
        Trajectory.line(speed_mps=0.7, heading_deg=150.0),
        Trajectory.waypoints([(1.0, 0.0, 0.5), (1.0, 1.0, 0.5), (-1.0, -1.0, 1.0)]),
    ],
    ids=["arc", "tight-right-arc", "line", "waypoints"],
)
def test_between_samples_the_pose_is_the_path_s(path: Trajectory) -> None:
    buffer = PoseBuffer()
    assert buffer.extend(_samples(path, 0.0, 12.0)) == 601
    times = np.random.default_rng(5).uniform(0.0, 12.0, 2000)
    position, yaw = _error(path, buffer, times)
    # linear between samples 20 ms apart: the sagitta of the arc (v dt)^2 / 8 r
    assert position < 1e-4
    assert yaw < 1e-9 if path.twist(1.0)[1] == 0.0 else yaw < 1e-3
    # on a stamp the pose is the sample itself
    stamps = np.arange(1, 500) / RATE_HZ
    assert _error(path, buffer, stamps)[0] < 1e-12


def test_yaw_is_interpolated_the_short_way_across_pi() -> None:
    buffer = PoseBuffer()
    buffer.extend(
        [
            PoseSample(0.0, 0.0, 0.0, math.pi - 0.1, 0.0, 2.0, 0),
            PoseSample(0.1, 0.0, 0.0, -math.pi + 0.1, 0.0, 2.0, 1),
            PoseSample(0.2, 0.0, 0.0, -math.pi + 0.3, 0.0, 2.0, 2),
        ]
    )
    got = buffer.poses_at([0.05, 0.15])
    # half way from pi - 0.1 to -pi + 0.1 is pi, not 0 (in [-pi, pi): -pi)
    assert got.yaw_rad[0] == pytest.approx(-math.pi)
    assert got.yaw_rad[1] == pytest.approx(-math.pi + 0.2)
    assert np.all((-math.pi <= got.yaw_rad) & (got.yaw_rad < math.pi))


def test_a_spin_keeps_turning_through_many_revolutions() -> None:
    spin = Trajectory.arc(speed_mps=0.2, radius_m=0.01)  # 20 rad/s: 9.5 turns in 3 s
    buffer = PoseBuffer()
    buffer.extend(_samples(spin, 0.0, 3.0))  # 0.4 rad between samples, through +-pi 19 times
    position, yaw = _error(spin, buffer, np.linspace(0.0, 3.0, 777))
    assert yaw < 1e-9  # a constant yaw rate, interpolated on the unwrapped yaw: exact
    assert position < 2e-4  # the chord of a 1 cm circle, 0.4 rad at a time


# --- the bounds: nothing placed by a guess -----------------------------------------------------


def test_a_gap_longer_than_max_gap_is_marked() -> None:
    path = Trajectory.line(speed_mps=1.0)
    samples = _samples(path, 0.0, 2.0)
    kept = samples[:51] + samples[56:]  # 1.02 s .. 1.10 s missing: 1.00 to 1.12, 0.12 s
    buffer = PoseBuffer(max_gap_s=0.1)
    buffer.extend(kept)
    assert buffer.missed == 5
    got = buffer.poses_at([0.5, 0.99, 1.0, 1.05, 1.119, 1.12, 1.5])
    assert got.valid.tolist() == [True, True, True, False, False, True, True]
    assert np.isnan(got.x_m[3]) and np.isnan(got.yaw_rad[4])
    assert buffer.pose_at(1.05) is None
    wider = PoseBuffer(max_gap_s=0.15)
    wider.extend(kept)
    assert wider.pose_at(1.05) == pytest.approx((1.05, 0.0, 0.0))


def test_beyond_the_newest_sample_the_twist_carries_the_pose_within_the_bound() -> None:
    path = Trajectory.arc(speed_mps=0.5, radius_m=2.0)
    buffer = PoseBuffer(max_extrapolation_s=0.05)
    buffer.extend(_samples(path, 0.0, 4.0))
    got = buffer.poses_at([4.0, 4.03, 4.05, 4.051, 5.0])
    assert got.valid.tolist() == [True, True, True, False, False]
    x, y, yaw = path.poses(got.t[:3])
    # a constant twist is carried on exactly
    assert np.hypot(got.x_m[:3] - x, got.y_m[:3] - y).max() < 1e-12
    assert _angle(got.yaw_rad[:3], yaw).max() < 1e-12
    strict = PoseBuffer(max_extrapolation_s=0.0)
    strict.extend(_samples(path, 0.0, 4.0))
    assert strict.poses_at([4.0, 4.001]).valid.tolist() == [True, False]


def test_before_the_oldest_sample_and_without_samples_there_is_no_pose() -> None:
    empty = PoseBuffer()
    got = empty.poses_at([0.0, 1.0])
    assert not got.valid.any() and np.isnan(got.x_m).all()
    buffer = PoseBuffer(max_extrapolation_s=0.05)
    buffer.extend(_samples(Trajectory.line(speed_mps=1.0), 1.0, 2.0))
    got = buffer.poses_at([0.5, 0.96, 0.94, math.nan, math.inf])
    assert got.valid.tolist() == [False, True, False, False, False]
    # carried back 40 ms by the oldest sample's own twist (1 m/s)
    assert buffer.pose_at(0.96) == pytest.approx((0.96, 0.0, 0.0))


def test_the_buffer_is_bounded_and_forgets_the_oldest() -> None:
    path = Trajectory.line(speed_mps=1.0)
    buffer = PoseBuffer(capacity=100)
    samples = _samples(path, 0.0, 10.0)
    for chunk in range(0, len(samples), 37):  # arrivals in uneven batches
        buffer.extend(samples[chunk : chunk + 37])
    assert len(buffer) == 100
    assert buffer.span() == pytest.approx((8.02, 10.0))
    assert buffer.added == 501
    assert buffer.pose_at(8.0) is not None  # carried back within the 50 ms bound...
    assert buffer.pose_at(7.9) is None  # ...not further: forgotten
    assert buffer.pose_at(9.5) == pytest.approx((9.5, 0.0, 0.0))
    held = buffer.samples()
    assert [s.t for s in held] == pytest.approx([s.t for s in samples[-100:]])


def test_since_gives_the_held_samples_after_a_time_as_samples_gives_them() -> None:
    """What a sink reads each batch: only the new samples, the same as ``samples()``'s tail
    (stamps, wrapped yaw, twist, seq), across the store's wrap-around and a forgotten head."""
    path = Trajectory.arc(radius_m=0.5, speed_mps=1.0)  # yaw crosses pi: wrapped as samples()
    buffer = PoseBuffer(capacity=60)
    samples = _samples(path, 0.0, 6.0)
    taken: list[float] = []
    last = -math.inf
    for chunk in range(0, len(samples), 23):
        buffer.extend(samples[chunk : chunk + 23])
        fresh = buffer.since(last)
        held = buffer.samples()
        assert fresh == [s for s in held if s.t > last]
        if fresh:
            last = fresh[-1].t
            taken.extend(s.t for s in fresh)
    assert taken == pytest.approx([s.t for s in samples])  # each once, none lost
    assert buffer.since(math.inf) == []
    assert buffer.since(-math.inf) == buffer.samples()
    for bad in (math.nan, "1.0", None, True):
        with pytest.raises(ValueError, match="since: t_hw must be a number"):
            buffer.since(bad)  # type: ignore[arg-type]


def test_samples_out_of_order_or_not_finite_are_refused_and_counted() -> None:
    buffer = PoseBuffer()
    assert buffer.add(PoseSample(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0))
    assert not buffer.add(PoseSample(1.0, 5.0, 0.0, 0.0, 0.0, 0.0, 1))  # a repeat
    assert not buffer.add(PoseSample(0.5, 5.0, 0.0, 0.0, 0.0, 0.0, 2))  # overtaken
    assert not buffer.add(PoseSample(2.0, math.nan, 0.0, 0.0, 0.0, 0.0, 3))
    assert buffer.add(PoseSample(1.08, 0.08, 0.0, 0.0, 1.0, 0.0, 4))
    assert (buffer.refused, buffer.added, len(buffer)) == (3, 2, 2)
    assert buffer.pose_at(1.05) == pytest.approx((0.05, 0.0, 0.0))


def test_a_source_without_twist_gets_the_one_of_its_last_interval() -> None:
    path = Trajectory.arc(speed_mps=0.5, radius_m=2.0)
    buffer = PoseBuffer(max_extrapolation_s=0.05)
    first = _samples(path, 1.0, 1.0, twist=False)
    buffer.extend(first)
    # one sample alone: its stamp is known, nothing around it
    assert buffer.poses_at([1.0, 1.01]).valid.tolist() == [True, False]
    buffer.extend(_samples(path, 1.02, 3.0, twist=False))
    got = buffer.poses_at([3.04])
    x, y, _ = path.poses(got.t)
    assert got.valid[0] and math.hypot(got.x_m[0] - x[0], got.y_m[0] - y[0]) < 1e-5
    held = buffer.samples()[-1]
    assert held.v_mps == pytest.approx(0.5, abs=1e-4)
    assert held.omega_rad_s == pytest.approx(0.25, abs=1e-9)


def test_the_clock_offset_moves_every_stamp_onto_the_hardware_clock() -> None:
    path = Trajectory.line(speed_mps=1.0)
    offset = -1_700_000_000.0  # a base stamping Unix time, a target whose clock started at 0
    on_base = [s._replace(t=s.t - offset) for s in _samples(path, 0.0, 2.0)]
    buffer = PoseBuffer(clock_offset_s=offset)
    buffer.extend(on_base)
    assert buffer.span() == pytest.approx((0.0, 2.0))
    assert buffer.pose_at(1.234) == pytest.approx((1.234, 0.0, 0.0), abs=1e-6)
    buffer.clock_offset_s = offset + 10.0  # re-measured: applies to what comes next
    assert buffer.add(on_base[-1]._replace(t=on_base[-1].t + 0.02))
    assert buffer.span() == pytest.approx((0.0, 12.02))


def test_clock_offset_reads_both_clocks_as_one_instant() -> None:
    ticks = iter([100.0, 100.5])  # the source before and after the hardware clock
    assert clock_offset(lambda: 5.0, lambda: next(ticks)) == pytest.approx(5.0 - 100.25)
    assert math.isfinite(clock_offset())


@pytest.mark.parametrize(
    ("options", "error"),
    [
        ({"capacity": 1}, ValueError),
        ({"capacity": 10.0}, ValueError),
        ({"max_gap_s": 0.0}, ValueError),
        ({"max_gap_s": math.inf}, ValueError),
        ({"max_extrapolation_s": -0.01}, ValueError),
        ({"clock_offset_s": math.nan}, ValueError),
        ({"clock_offset_s": "0"}, TypeError),
        ({"max_gap_s": True}, TypeError),
    ],
)
def test_bad_settings_are_refused(options: dict[str, object], error: type[Exception]) -> None:
    with pytest.raises(error):
        PoseBuffer(**options)  # type: ignore[arg-type]


def test_times_must_be_one_dimensional() -> None:
    with pytest.raises(ValueError, match="1-D"):
        PoseBuffer().poses_at(np.zeros((2, 2)))


# --- the simulator's odometry, pumped on virtual time -----------------------------------------


def test_the_pump_follows_the_simulated_odometry_on_virtual_time(no_leaks: None) -> None:
    path = Trajectory.arc(speed_mps=0.5, radius_m=3.0)
    with SimulatedBiris(scene=Scene.circle(3.0), clock="virtual", trajectory=path) as rig:
        with open_poses(sim=rig) as poses:
            rig.timebase.sleep(2.99)
            # every sample due by now is in: the pump woke at each stamp
            assert poses.span() == pytest.approx((0.0, 2.98))
            assert poses.added == 150 and poses.missed == 0
            assert poses.wait_for(3.0, timeout_hw=1.0)
            assert rig.timebase.now() == pytest.approx(3.0)
            times = np.linspace(0.0, 3.0, 301)
            got = poses.poses_at(times)
            assert got.valid.all()
            for t, x, y, yaw in zip(times, got.x_m, got.y_m, got.yaw_rad, strict=True):
                tx, ty, tyaw = rig.true_pose(float(t))
                assert math.hypot(x - tx, y - ty) < 1e-5
                assert abs(yaw - tyaw) < 1e-9
            # a pose not yet made: wait_for sleeps until the first sample at or after it
            assert poses.pose_at(3.5) is None
            assert poses.wait_for(3.5, timeout_hw=1.0)
            assert rig.timebase.now() == pytest.approx(3.5)
            assert poses.pose_at(3.5) == pytest.approx(rig.true_pose(3.5), abs=1e-9)
            # and a timeout in hardware seconds
            assert not poses.wait_for(1e6, timeout_hw=0.01)
        assert rig.timebase.now() == pytest.approx(3.51)


def test_with_drift_the_buffer_holds_what_the_base_believes(no_leaks: None) -> None:
    """odom is the base's belief: the buffer gives it back as it came, not the truth."""
    path = Trajectory.line(speed_mps=1.0)
    drift = OdometryParams(scale_error=0.1)
    with (
        SimulatedBiris(clock="virtual", trajectory=path, odometry=drift) as rig,
        open_poses(sim=rig, max_gap_s=0.05) as poses,
    ):
        rig.timebase.sleep(2.0)
        assert poses.pose_at(2.0) == pytest.approx((2.2, 0.0, 0.0), abs=1e-9)
        assert poses.max_gap_s == 0.05


def test_the_pump_ends_with_the_error_its_source_raised(no_leaks: None) -> None:
    class Broken:
        period_s = 0.02

        def since(self, t_hw: float) -> list[PoseSample]:
            raise OSError("the base went away")

    tb = VirtualTime()
    buffer = PoseBuffer(timebase=tb)
    with PosePump(Broken(), buffer) as pump:
        tb.join_thread(pump._thread)  # type: ignore[arg-type]
        assert not pump.running
    assert isinstance(pump.error, OSError)
    tb.leave()


def test_open_poses_wants_a_simulator_with_odometry() -> None:
    with pytest.raises(TypeError, match="odometry"), open_poses(sim=object()):
        pass
    with pytest.raises(ValueError, match="period"):

        class Stuck:
            period_s = 0.0

            def since(self, t_hw: float) -> list[PoseSample]:
                return []

        PosePump(Stuck(), PoseBuffer())


# --- the wire: Odometry and TransformStamped in CDR ---------------------------------------------


def test_odometry_and_transforms_come_back_as_they_went() -> None:
    sample = PoseSample(12.345678901, 1.5, -2.25, 3.0, 0.5, -0.125, 7)
    odom = codec.decode_pose(codec.encode_odometry(sample), seq=3)
    assert (odom.frame_id, odom.child_frame_id) == ("odom", "vehicle")
    assert odom.sample == pytest.approx(sample._replace(seq=3))
    either = codec.decode_pose(codec.encode_odometry(sample, "map", "base_link"))
    assert (either.frame_id, either.child_frame_id) == ("map", "base_link")
    tf = codec.decode_pose(codec.encode_transform_stamped(sample), TRANSFORM_STAMPED)
    assert tf.sample[:4] == pytest.approx(sample[:4])
    assert math.isnan(tf.sample.v_mps) and math.isnan(tf.sample.omega_rad_s)
    assert codec.decode_pose(codec.encode_transform_stamped(sample)).sample[:4] == pytest.approx(
        sample[:4]
    )


def test_a_yaw_of_pi_comes_back_in_the_half_open_turn() -> None:
    for yaw in (math.pi, -math.pi, math.pi - 1e-12, 0.0):
        got = codec.decode_pose(codec.encode_odometry(PoseSample(1.0, 0, 0, yaw, 0, 0, 0)))
        assert -math.pi <= got.sample.yaw_rad < math.pi
        assert _angle(np.array(got.sample.yaw_rad), np.array(yaw)) < 1e-9


def test_the_odometry_message_is_what_an_independent_reader_reads() -> None:
    pytest.importorskip("mcap_ros2")
    from mcap_ros2._dynamic import generate_dynamic  # an independent CDR reader

    sample = PoseSample(2.5, 1.0, 2.0, math.pi / 2, 0.3, 0.1, 0)
    decoder = generate_dynamic(ODOMETRY, codec.schema_text(ODOMETRY))[ODOMETRY]
    msg = decoder(codec.encode_odometry(sample))
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (2, 500_000_000)
    assert msg.header.frame_id == "odom" and msg.child_frame_id == "vehicle"
    assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (1.0, 2.0)
    q = msg.pose.pose.orientation
    assert (q.z, q.w) == pytest.approx((math.sqrt(0.5), math.sqrt(0.5)))
    assert (msg.twist.twist.linear.x, msg.twist.twist.angular.z) == (0.3, 0.1)


def test_tf_messages_give_only_the_odom_to_vehicle_transforms() -> None:
    samples = [PoseSample(1.0 + k / 50, 0.1 * k, 0.0, 0.0, math.nan, math.nan, k) for k in range(3)]
    encoded = codec.odom_transforms(samples)
    assert (encoded.topic, encoded.msgtype) == ("/tf", codec.TF_MESSAGE)
    got = codec.decode_tf_poses(encoded.data, seq=10)
    assert [s.seq for s in got] == [10, 11, 12]
    assert _rows(got) == pytest.approx(_rows(samples))
    assert codec.decode_tf_poses(encoded.data, "odom", "base_link") == []
    with pytest.raises(WireError):
        codec.odom_transforms([])


def _cut_odometry() -> bytes:
    return codec.encode_odometry(PoseSample(1, 0, 0, 0, 0, 0, 0))[:40]


# the payloads are made in the test, so that collection does not build the codec's store
@pytest.mark.parametrize(
    "make",
    [lambda: b"", lambda: b"\x00\x01\x00\x00garbage", _cut_odometry],
    ids=["empty", "garbage", "cut_odometry"],
)
def test_a_payload_that_is_not_a_pose_is_a_wire_error(make: Callable[[], bytes]) -> None:
    payload = make()
    with pytest.raises(WireError):
        codec.decode_pose(payload)
    with pytest.raises(WireError):
        codec.decode_tf_poses(payload)


def test_an_odometry_payload_is_not_taken_for_a_transform_and_no_other_type_is_asked() -> None:
    data = codec.encode_odometry(PoseSample(1, 0, 0, 0, 0, 0, 0))
    with pytest.raises(WireError):
        codec.decode_pose(data, TRANSFORM_STAMPED)
    with pytest.raises(WireError, match="not a pose"):
        codec.decode_pose(data, codec.POINT_CLOUD2)
    nan = codec.encode_odometry(PoseSample(1, math.nan, 0, 0, 0, 0, 0))
    with pytest.raises(WireError, match="finite"):
        codec.decode_pose(nan)


# --- Zenoh ------------------------------------------------------------------------------------


@pytest.fixture
def zenoh_session() -> Iterator[object]:
    zenoh = pytest.importorskip("zenoh")
    from biris_hw.io.net.zconfig import make_config

    session = zenoh.open(make_config(listen=[endpoint(free_port())], multicast=False))
    try:
        yield session
    finally:
        session.close()


RMW_KEY = "0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_0000"


def test_a_base_s_odometry_on_zenoh_fills_the_buffer(zenoh_session: object) -> None:
    session: object = zenoh_session
    path = Trajectory.arc(speed_mps=0.5, radius_m=3.0)
    sent = _samples(path, 0.0, 1.0)
    buffer = PoseBuffer()
    with subscribe_poses("0/odom/**", buffer, session=session) as sub:
        publisher = session.declare_publisher(RMW_KEY)  # type: ignore[attr-defined]
        for sample in sent:
            publisher.put(codec.encode_odometry(sample, "odom", "base_link"))
        publisher.put(b"not a pose")
        session.put("0/odom/other", codec.encode_transform_stamped(sent[-1]))  # type: ignore[attr-defined]
        assert buffer.wait_for(1.0, timeout_hw=10.0)
        # the two after the last sample come on their own: wait for them before closing
        until(lambda: sub.received == len(sent) + 2, what="every publication at the subscriber")
        publisher.undeclare()
    assert sub.closed
    assert (sub.received, sub.taken, sub.malformed) == (len(sent) + 2, len(sent), 1)
    assert isinstance(sub.last_error, WireError)
    assert buffer.refused == 1  # the transform repeated the newest stamp
    assert _error(path, buffer, np.linspace(0.0, 1.0, 101))[0] < 1e-4


def test_frames_other_than_those_asked_for_are_left_out(zenoh_session: object) -> None:
    buffer = PoseBuffer()
    sub = subscribe_poses(
        "tf", buffer, session=zenoh_session, msgtype=TRANSFORM_STAMPED, child_frame_id="vehicle"
    )
    with sub:
        for k, child in enumerate(["vehicle", "camera", "vehicle"]):
            sample = PoseSample(float(k), float(k), 0.0, 0.0, math.nan, math.nan, k)
            sub.on_payload(codec.encode_transform_stamped(sample, "odom", child))
        sub.on_payload(codec.encode_odometry(PoseSample(5, 0, 0, 0, 0, 0, 5)))  # wrong type
    assert (sub.taken, sub.other, sub.malformed) == (2, 1, 1)
    assert buffer.span() == (0.0, 2.0)


def test_a_payload_is_counted_received_only_once_the_buffer_has_its_outcome() -> None:
    """A reader that waits for ``received`` to reach n must find the buffer as those n payloads
    left it: under load a Zenoh callback thread was once pre-empted between counting a payload
    and handing it to the buffer, and the reader saw ``refused`` still 0."""
    entered, release = threading.Event(), threading.Event()

    class SlowBuffer(PoseBuffer):
        def add(self, sample: PoseSample) -> bool:
            entered.set()
            release.wait(WAIT)
            return super().add(sample)

    sub = PoseSubscription(SlowBuffer(), ODOMETRY, None, None)
    sample = PoseSample(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1)
    worker = threading.Thread(target=sub.on_payload, args=(codec.encode_odometry(sample),))
    worker.start()
    try:
        assert entered.wait(WAIT)
        assert (sub.received, sub.taken) == (0, 0)  # in the buffer's hands: not yet counted
    finally:
        release.set()
        worker.join(WAIT)
    assert (sub.received, sub.taken, sub.buffer.refused) == (1, 1, 0)
    sub.on_payload(codec.encode_odometry(sample))  # the same stamp again: refused
    assert (sub.received, sub.taken, sub.buffer.refused) == (2, 1, 1)


def test_a_subscription_with_its_own_session_reaches_a_base_on_loopback(
    zenoh_session: object,
) -> None:
    zenoh = pytest.importorskip("zenoh")
    from biris_hw.io.net.zconfig import make_config

    port = free_port()
    base = zenoh.open(make_config(listen=[endpoint(port)], multicast=False))
    try:
        buffer = PoseBuffer()
        with subscribe_poses("odom", buffer, connect=[endpoint(port)]) as sub:
            # the subscription reaches the base some time after the link: publish until seen
            k = 0
            while not buffer.wait_for(0.0, timeout_hw=0.02):
                assert k < 500, "the pose subscription never reached the base"
                base.put("odom", codec.encode_odometry(PoseSample(k / 50, k, 0, 0, 0, 0, k)))
                k += 1
            assert sub.taken >= 1
        assert sub.closed
    finally:
        base.close()


def test_a_bad_subscription_is_refused() -> None:
    pytest.importorskip("zenoh")
    with pytest.raises(RequestError, match="msgtype"):
        subscribe_poses("odom", PoseBuffer(), msgtype=codec.POINT_CLOUD2)
    with pytest.raises(RequestError):
        subscribe_poses("odom", PoseBuffer(), connect=["nonsense/::"])


# --- recordings ---------------------------------------------------------------------------------


def _record(path: Path, samples: list[PoseSample]) -> None:
    """A recording (small chunks) with the head's transforms and odom -> vehicle on /tf, /odom,
    and a profile cloud on /biris/profile."""
    from biris_hw.data import Point
    from biris_hw.io.record.mcapfile import McapFile

    out = McapFile(path, chunk_size=4096)
    for sample in samples:
        point = Point(0, 1000, np.full(4, 900, np.int16), np.zeros(4, np.int16), sample.t, 0, 0)
        for message in (
            codec.transforms(point),
            codec.odom_transforms([sample]),
            codec.odometry_message(sample),
            codec.profile_cloud(point),
        ):
            out.write(
                message.topic,
                message.msgtype,
                codec.schema_text(message.msgtype),
                message.data,
                message.log_time_ns,
            )
    out.close()


def test_a_recording_s_tf_and_odom_give_the_vehicle_s_poses(tmp_path: Path) -> None:
    pytest.importorskip("mcap")
    path = Trajectory.arc(speed_mps=0.5, radius_m=3.0)
    sent = _samples(path, 0.0, 2.0)
    _record(tmp_path / "run.mcap", sent)
    from_tf = read_poses(tmp_path / "run.mcap")
    from_odom = read_poses(tmp_path / "run.mcap", "/odom")
    assert [s.seq for s in from_tf] == list(range(len(sent)))
    for got in (from_tf, from_odom):
        assert _rows(got) == pytest.approx(_rows(sent))
    assert from_odom[5].v_mps == 0.5 and math.isnan(from_tf[5].v_mps)
    buffer = PoseBuffer()
    buffer.extend(from_tf)
    assert _error(path, buffer, np.linspace(0.0, 2.0, 201))[0] < 1e-4
    assert read_poses(tmp_path / "run.mcap", child_frame_id="base_link") == []


def test_a_recording_cut_short_gives_the_poses_before_the_cut(tmp_path: Path) -> None:
    pytest.importorskip("mcap")
    sent = _samples(Trajectory.line(speed_mps=1.0), 0.0, 1.0)
    _record(tmp_path / "run.mcap", sent)
    data = (tmp_path / "run.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) * 6 // 10])  # a writer killed
    got = read_poses(tmp_path / "cut.mcap")
    assert 0 < len(got) < len(sent)
    assert [s.t for s in got] == pytest.approx([s.t for s in sent[: len(got)]])


def test_a_file_that_cannot_give_poses_says_why(tmp_path: Path) -> None:
    pytest.importorskip("mcap")
    with pytest.raises(PoseFileError, match="cannot read"):
        read_poses(tmp_path / "missing.mcap")
    (tmp_path / "text.mcap").write_text("not an MCAP file")
    with pytest.raises(PoseFileError, match="not an MCAP file"):
        read_poses(tmp_path / "text.mcap")
    _record(tmp_path / "run.mcap", _samples(Trajectory.standing(), 0.0, 0.1))
    with pytest.raises(PoseFileError, match="no channel /base/pose"):
        read_poses(tmp_path / "run.mcap", "/base/pose")
    with pytest.raises(PoseFileError, match="not a pose"):
        read_poses(tmp_path / "run.mcap", "/biris/profile")
