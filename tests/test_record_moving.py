"""Recordings and the live view on a moving robot: ``/odom``, ``odom -> vehicle`` on ``/tf``,
``/biris/points`` in ``odom`` (deskewed) and the certainty grid on ``/biris/grid``.

One drive is recorded once for the module, on virtual time (a few seconds): the simulated
vehicle on the default drive through the room while the head sweeps, logged on the wall clock.
The file is then read by independent decoders (rosbags, mcap-ros2-support) and held against the
simulator's truth -- the poses against the true path, the clouds against the true walls (and
against the same scans placed without deskewing, which must be far worse) -- replayed (the
replay's clock is the hardware's, not the wall's), turned into a grid by ``biris grid FILE``
and shown by a live view to a real WebSocket client. The moving encoder's rules (an
acquisition without a pose is counted and left out; each pose once) are checked on scans made
here; the commands' flags end to end.
"""

from __future__ import annotations

import functools
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from biris_hw.data import ConnectionKind, DeliveryPolicy, PoseSample, Scan
from biris_hw.geometry import project_profiles
from biris_hw.io import codec
from biris_hw.io.deskew import deskewed
from biris_hw.io.feed import Batch, StatusReading
from biris_hw.io.grid import GridParams
from biris_hw.io.liveview import LiveView
from biris_hw.io.moving_sink import LEAD_S, MovingEncoder, RecordedPoses
from biris_hw.io.pose import PoseBuffer, read_poses
from biris_hw.io.record import Recorder, RecordSummary
from biris_hw.io.record.replay import EndOfRecording, ReplayServer
from biris_hw.opening import open_poses, open_sensor
from sim import Scene, SimulatedBiris
from sim.drives import DRIVE_START_S, default_drive
from tests import foxglove_client as fox
from tests.conftest import Run
from tests.test_record_support import cloud_xyz, read_decoded, synthetic_scans


@functools.cache
def standard() -> Typestore:
    """rosbags' own ROS 2 Jazzy typestore, as a stranger's reader holds it (built on first use, not
    at collection, where it cost every test worker a fifth of a second)."""
    return get_typestore(Stores.ROS2_JAZZY)


SUBPROTOCOL = Subprotocol(fox.SUBPROTOCOL)
WAIT = 10.0
SWEEPS = (-90.0, 90.0, -90.0, 90.0)


@dataclass(frozen=True)
class Drive:
    """The module's recording and the truth it is held against."""

    path: Path
    summary: RecordSummary
    scene: Scene
    truth: dict[float, tuple[float, float, float]]
    """The vehicle's true pose at each recorded /odom stamp (hardware seconds)."""
    started_wall_s: float


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Drive:
    """Four sweeps of -90..+90 degrees while the vehicle drives (it sets off at 8 s), recorded
    with poses and a grid, logged on the wall clock; everything stopped before the tests."""
    import time

    path = tmp_path_factory.mktemp("moving") / "drive.mcap"
    scene = Scene.room()
    started = time.time()
    with SimulatedBiris(
        scene=scene, seed=1, clock="virtual", trajectory=default_drive(scene)
    ) as rig:
        with open_sensor(sim=rig) as sensor, open_poses(sim=rig) as poses:
            recorder = Recorder(sensor, path, poses=poses, grid=GridParams(), stamp="wall")
            with recorder:
                conn = sensor.open()
                conn.wait_idle()
                for to in SWEEPS:
                    conn.single_scan(to)
                    conn.wait_idle()
        assert not rig.audit.violations, rig.audit.violations
        stamps = [s.t for s in read_poses(path, codec.ODOM_TOPIC)]
        truth = {t: tuple(rig.true_pose(t)) for t in stamps}
    assert recorder.summary is not None
    return Drive(path, recorder.summary, scene, truth, started)  # type: ignore[arg-type]


def _messages(path: Path, topic: str) -> list[tuple[Any, int]]:
    """(message decoded by rosbags, log time ns) of ``topic``, in log-time order."""
    out = []
    with open(path, "rb") as f:
        for schema, _channel, message in make_reader(f).iter_messages(
            topics=[topic], log_time_order=True
        ):
            assert schema is not None
            out.append((standard().deserialize_cdr(message.data, schema.name), message.log_time))
    return out


def _stamp(header: Any) -> float:
    return int(header.stamp.sec) + int(header.stamp.nanosec) * 1e-9


def _raw_scans(path: Path) -> list[Scan]:
    return [codec.decode_scan(m[3]) for m in read_decoded(path, [codec.RAW_SCAN_TOPIC])]


def _file_poses(path: Path) -> PoseBuffer:
    samples = read_poses(path, codec.ODOM_TOPIC)
    buffer = PoseBuffer(capacity=len(samples))
    buffer.extend(samples)
    return buffer


# -- the recording ---------------------------------------------------------------------------------


def test_the_drive_records_each_pose_once_on_odom_and_tf(drive: Drive) -> None:
    with open(drive.path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    types = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert types[codec.ODOM_TOPIC] == "nav_msgs/msg/Odometry"
    assert types[codec.GRID_TOPIC] == "nav_msgs/msg/OccupancyGrid"
    assert types[codec.POINTS_TOPIC] == "sensor_msgs/msg/PointCloud2"
    odom = _messages(drive.path, codec.ODOM_TOPIC)
    stamps = np.array([_stamp(m.header) for m, _ in odom])
    assert all(m.header.frame_id == "odom" and m.child_frame_id == "vehicle" for m, _ in odom)
    assert np.all(np.diff(stamps) > 0)  # each sample once, in order
    assert np.allclose(np.diff(stamps), 0.02, atol=1e-6)  # 50 Hz, none missing
    # from LEAD_S before the recording's first item (its first status), not the buffer's
    # whole history (from t = 0)
    first = _stamp(_messages(drive.path, codec.DIAGNOSTICS_TOPIC)[0][0].header)
    assert first - LEAD_S <= stamps[0] < first - LEAD_S + 0.02 and stamps[0] > 1.0
    assert drive.summary.moving and drive.summary.poses == len(odom)
    tf = [
        t
        for m, _ in _messages(drive.path, codec.TF_TOPIC)
        for t in m.transforms
        if t.header.frame_id == "odom"
    ]
    assert [t.child_frame_id for t in tf] == ["vehicle"] * len(odom)
    assert np.array_equal([_stamp(t.header) for t in tf], stamps)
    # the poses are the simulator's (exact odometry by default): the path it drove
    moved = 0.0
    for m, _ in odom:
        x, y, yaw = drive.truth[_stamp(m.header)]
        p, q = m.pose.pose.position, m.pose.pose.orientation
        assert math.hypot(p.x - x, p.y - y) < 1e-3
        assert abs(math.remainder(2 * math.atan2(q.z, q.w) - yaw, 2 * math.pi)) < 1e-3
        moved = max(moved, math.hypot(p.x, p.y))
    assert moved > 1.0  # it drove while the head swept
    assert stamps[-1] > DRIVE_START_S + 3.0


def test_the_clouds_are_in_odom_deskewed_on_the_true_walls(drive: Drive) -> None:
    clouds = read_decoded(drive.path, [codec.POINTS_TOPIC])  # by mcap-ros2-support
    scans = _raw_scans(drive.path)
    assert len(clouds) == len(scans) == len(SWEEPS) == drive.summary.scans
    assert drive.summary.unplaced_points == 0 and drive.summary.dropped == 0
    poses = _file_poses(drive.path)
    placed, smeared = [], []
    for (_topic, _type, cloud, _raw), scan in zip(clouds, scans, strict=True):
        assert cloud.header.frame_id == "odom"
        xyz = cloud_xyz(cloud)
        # the file's cloud is the scan deskewed with the file's own poses
        np.testing.assert_allclose(xyz, deskewed(scan, poses).points(), atol=1e-4)
        placed.append(xyz)
        # the same scan placed as if the vehicle had stood still at its first acquisition
        at = poses.poses_at(np.full(scan.n_acq, scan.t[0]))
        grid = project_profiles(scan.range_mm, scan.azimuth, scan.elevation, "vehicle", scan.mount)
        smeared.append(at.to_odom(grid)[scan.range_mm > 0])
    off = drive.scene.distance_to_surface_2d(np.vstack(placed)[:, :2])
    off_smeared = drive.scene.distance_to_surface_2d(np.vstack(smeared)[:, :2])
    assert np.median(off) < 0.05
    assert np.median(off_smeared) > 2 * np.median(off)


def test_the_grid_is_recorded_in_ros_terms_and_lies_on_the_walls(drive: Drive) -> None:
    grids = _messages(drive.path, codec.GRID_TOPIC)
    assert len(grids) >= 3 and drive.summary.grid_messages == len(grids)
    stamps = [_stamp(m.header) for m, _ in grids]
    assert stamps == sorted(stamps)
    last = grids[-1][0]
    assert last.header.frame_id == "odom"
    width, height, res = int(last.info.width), int(last.info.height), float(last.info.resolution)
    assert (width, height) == (400, 400) and res == pytest.approx(0.05)
    cells = np.asarray(last.data, dtype=np.int8)
    assert cells.size == width * height
    assert set(np.unique(cells)) <= {-1, *range(101)}
    assert np.count_nonzero(cells == -1) > 0 and np.count_nonzero((cells >= 0) & (cells < 50)) > 0
    occupied = np.flatnonzero(cells >= 65)
    assert occupied.size > 100
    rows, cols = np.divmod(occupied, width)
    origin = last.info.origin.position
    xy = np.column_stack((origin.x + (cols + 0.5) * res, origin.y + (rows + 0.5) * res))
    assert np.mean(drive.scene.distance_to_surface_2d(xy) <= 0.1) > 0.9
    # our own decoder reads the same
    with open(drive.path, "rb") as f:
        raw = [m.data for _s, _c, m in make_reader(f).iter_messages(topics=[codec.GRID_TOPIC])]
    ours = codec.decode_occupancy_grid(raw[-1])
    assert np.array_equal(ours.data.reshape(-1), cells) and ours.frame_id == "odom"


def test_the_metadata_says_how_it_was_recorded(drive: Drive) -> None:
    with open(drive.path, "rb") as f:
        meta = {r.name: dict(r.metadata) for r in make_reader(f).iter_metadata()}
    assert meta["biris"]["cloud_frame_id"] == "odom" and meta["biris"]["log_time"] == "wall"
    moving = json.loads(meta["biris"]["moving"])
    assert moving["frame"] == "odom" and moving["grid"]["resolution_m"] == 0.05
    end = meta["biris.recording"]
    assert int(end["poses"]) == drive.summary.poses and int(end["unplaced_points"]) == 0
    assert "vehicle poses" in str(drive.summary) and "certainty grids" in str(drive.summary)


def test_wall_log_times_keep_hardware_stamps(drive: Drive) -> None:
    for m, log_ns in _messages(drive.path, codec.ODOM_TOPIC)[:5]:
        assert _stamp(m.header) < 100.0  # hardware seconds
        assert log_ns / 1e9 > drive.started_wall_s - 60.0  # today


# -- read back -------------------------------------------------------------------------------------


def test_a_wall_stamped_recording_replays_on_the_hardware_clock(drive: Drive) -> None:
    """The replay's clock is its items' hardware time, not the wall log time (was ~1.8e9)."""
    scans = []
    with ReplayServer(drive.path, speed=None) as replay:
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=64)
        while True:
            try:
                scans.append(data.ready_for_data(timeout=WAIT))
            except EndOfRecording:
                break
            assert replay.clock() >= codec.scan_time(scans[-1])
        assert replay.wait_done(WAIT)
        clock = replay.clock()
    points = _raw_points_newest(drive.path)
    assert clock == pytest.approx(max(points, codec.scan_time(scans[-1])))
    assert clock < 100.0
    assert len(scans) == len(SWEEPS)


def _raw_points_newest(path: Path) -> float:
    return max(codec.decode_point(m[3]).t for m in read_decoded(path, [codec.RAW_POINT_TOPIC]))


def test_biris_grid_builds_the_grid_of_the_recording(biris: Run, drive: Drive) -> None:
    code, out, err = biris("grid", str(drive.path))
    assert code == 0, err
    odom = len(read_poses(drive.path, codec.ODOM_TOPIC))
    assert f"{len(SWEEPS)} scans; vehicle {odom} poses from /tf" in out
    placed = sum(s.n_acq for s in _raw_scans(drive.path))
    assert f"grid: {placed} acquisitions placed, 0 without a pose" in out


# -- the live view ---------------------------------------------------------------------------------


@pytest.fixture(scope="module", autouse=True)
def _foxglove_runtime() -> None:
    """foxglove-sdk keeps its runtime for the life of the process once a server has run: start
    it before any test's leak check takes its snapshot (as tests/test_liveview.py does)."""
    import foxglove

    foxglove.start_server(port=0, context=foxglove.Context()).stop()


def test_the_live_view_of_a_moving_recording_advertises_and_sends_odom_and_grid(
    drive: Drive,
) -> None:
    """``biris view --replay FILE --grid``: the recording's poses handed on with its data."""
    poses = RecordedPoses(read_poses(drive.path))
    replay = ReplayServer(drive.path, speed=None, autostart=False)
    view = LiveView(replay, port=0, status_period_s=0.05, poses=poses, grid=GridParams())
    topics = {**codec.TOPICS, **codec.MOVING_TOPICS}
    with replay, view, connect(f"ws://127.0.0.1:{view.port}", subprotocols=[SUBPROTOCOL]) as ws:
        channels = fox.advertised(ws, len(topics))
        assert {t: c["schemaName"] for t, c in channels.items()} == topics
        stream = fox.messages(ws, fox.subscribe(ws, channels.values()), standard())
        got: dict[str, list[Any]] = {}
        started = False
        while len(got.get(codec.POINTS_TOPIC, [])) < len(SWEEPS) or not all(
            got.get(t) for t in (codec.ODOM_TOPIC, codec.GRID_TOPIC)
        ):
            if not started and view.published.get(codec.DIAGNOSTICS_TOPIC):
                replay.start()  # the subscriptions are in place
                started = True
            topic, message, _ = next(stream)
            got.setdefault(topic, []).append(message)
    assert all(m.header.frame_id == "odom" for m in got[codec.POINTS_TOPIC])
    assert all(m.header.frame_id == "odom" for m in got[codec.GRID_TOPIC])
    recorded = [_stamp(m.header) for m, _ in _messages(drive.path, codec.ODOM_TOPIC)]
    sent = [_stamp(m.header) for m in got[codec.ODOM_TOPIC]]
    assert sent == recorded[: len(sent)]  # each once, in order
    assert view.moving is not None and view.moving.unplaced_points == 0


def test_biris_view_replay_shows_a_moving_recording_in_odom(drive: Drive) -> None:
    """``biris view --replay FILE --grid``: the file's poses go to the view, the grid is fed."""
    from biris_hw.cli import build_parser
    from biris_hw.commands import view as view_command

    views: list[LiveView] = []

    def ready(view: LiveView) -> None:  # the replay has begun: let it play to its end
        views.append(view)
        assert isinstance(view.source, ReplayServer) and view.source.wait_done(WAIT)

    argv = ["view", "--replay", str(drive.path), "--grid", "--port", "0", "--speed", "100"]
    args = build_parser("view").parse_args([*argv, "--duration", "0.1"])
    assert view_command.run(args, io.StringIO(), ready=ready) == 0
    moving = views[0].moving
    assert moving is not None and moving.grid is not None
    assert moving.poses_out == drive.summary.poses  # every recorded pose, once
    assert moving.grid.acquisitions == sum(s.n_acq for s in _raw_scans(drive.path))
    assert moving.unplaced_points == 0 and moving.grid.unplaced == 0


# -- the moving encoder's rules, on scans made here -----------------------------------------------


class _Poses:
    """A PoseBuffer's samples through ``samples()`` only (the fallback the encoder polls)."""

    def __init__(self, buffer: PoseBuffer) -> None:
        self.buffer = buffer
        self.copies = 0

    def poses_at(self, times: Any) -> Any:
        return self.buffer.poses_at(times)

    def span(self) -> tuple[float, float] | None:
        return self.buffer.span()

    def samples(self) -> list[PoseSample]:
        self.copies += 1
        return self.buffer.samples()


def _samples(t0: float, t1: float, dt: float = 0.02) -> list[PoseSample]:
    n = round((t1 - t0) / dt) + 1
    return [PoseSample(t0 + i * dt, 0.1 * i * dt, 0.0, 0.0, 0.1, 0.0, i) for i in range(n)]


@pytest.mark.parametrize("through", ["since", "samples"])
def test_each_pose_goes_out_once_up_to_the_data_seen(through: str) -> None:
    buffer = PoseBuffer()
    buffer.extend(_samples(0.0, 10.0))
    poses: Any = RecordedPoses(buffer.samples()) if through == "since" else _Poses(buffer)
    encoder = MovingEncoder(poses, poll_s=0.0)
    first = encoder.messages(Batch(status=StatusReading(None, None, 4.0)))
    odom = [codec.decode_pose(m.data).sample.t for m in first if m.topic == codec.ODOM_TOPIC]
    assert odom[0] == pytest.approx(4.0 - LEAD_S) and odom[-1] == pytest.approx(4.0)
    assert [m.log_time_ns for m in first] == sorted(m.log_time_ns for m in first)
    second = encoder.messages(Batch(status=StatusReading(None, None, 6.0)))
    more = [codec.decode_pose(m.data).sample.t for m in second if m.topic == codec.ODOM_TOPIC]
    assert more[0] == pytest.approx(4.02) and more[-1] == pytest.approx(6.0)
    last = encoder.messages(Batch(final=True))
    rest = [codec.decode_pose(m.data).sample.t for m in last if m.topic == codec.ODOM_TOPIC]
    assert rest[0] == pytest.approx(6.02) and rest[-1] == pytest.approx(10.0)
    assert encoder.poses_out == len(odom) + len(more) + len(rest) == 351  # 3..10 s
    tf = [m for m in (*first, *second, *last) if m.topic == codec.TF_TOPIC]
    assert len(tf) == encoder.poses_out


def test_a_pose_buffer_without_since_is_copied_at_most_every_poll() -> None:
    buffer = PoseBuffer()
    buffer.extend(_samples(0.0, 2.0))
    poses = _Poses(buffer)
    encoder = MovingEncoder(poses, poll_s=3600.0)
    for t in (1.0, 1.5, 2.0):
        encoder.messages(Batch(status=StatusReading(None, None, t)))
    assert poses.copies == 1 and encoder.poses_out == 51  # 0..1 s: the first copy
    encoder.messages(Batch(final=True))
    assert poses.copies == 2 and encoder.poses_out == 101


def test_acquisitions_without_a_pose_are_counted_and_left_out() -> None:
    scans = synthetic_scans(2, n_acq=10)  # acquisitions 0.05 s apart
    scan, lone = scans
    half = float(scan.t[4]) + 0.01
    buffer = PoseBuffer(max_extrapolation_s=0.0)
    buffer.extend(_samples(float(scan.t[0]) - 0.1, half))  # none for acquisitions 5..9
    encoder = MovingEncoder(buffer, wait_s=0.2)
    got = encoder.messages(Batch(scans=(scan,)))  # waits: the poses may still come
    assert not [m for m in got if m.topic == codec.POINTS_TOPIC]
    late = Batch(status=StatusReading(None, None, float(scan.t[-1]) + 0.5))
    clouds = [m for m in encoder.messages(late) if m.topic == codec.POINTS_TOPIC]
    assert len(clouds) == 1 and encoder.unplaced_points == 5 and encoder.placed_scans == 1
    xyz = cloud_xyz(standard().deserialize_cdr(clouds[0].data, codec.POINT_CLOUD2))
    keep = scan.range_mm[:5] > 0
    assert xyz.shape[0] == int(keep.sum())  # the placed acquisitions' returns only
    np.testing.assert_allclose(xyz, deskewed(scan, buffer).points(), atol=1e-5)
    # a scan with no pose at all gives no cloud, and is counted (at the end, however new)
    final = encoder.messages(Batch(scans=(lone,), final=True))
    assert not [m for m in final if m.topic == codec.POINTS_TOPIC]
    assert encoder.unplaced_scans == 1 and encoder.unplaced_points == 5 + lone.n_acq


def test_a_grid_needs_poses_and_bad_poses_are_refused(tmp_path: Path) -> None:
    replay = ReplayServer(_synthetic(tmp_path), autostart=False)
    with replay, pytest.raises(ValueError, match="grid= needs poses="):
        Recorder(replay, tmp_path / "x.mcap", grid=GridParams())
    with pytest.raises(ValueError, match="grid= needs poses="):
        LiveView(replay, port=0, grid=GridParams())
    with pytest.raises(TypeError, match="pose buffer"):
        MovingEncoder(object())  # type: ignore[arg-type]
    assert not (tmp_path / "x.mcap").exists()


def _synthetic(tmp_path: Path) -> Path:
    from tests.test_record_support import write_raw

    return write_raw(tmp_path / "raw.mcap", synthetic_scans(1))


def test_hand_written_pose_messages_are_rosbags_bytes() -> None:
    for sample in (
        PoseSample(12.345678, 1.5, -2.25, 0.7, 0.5, 0.1, 3),
        PoseSample(1e-3, 0.0, 0.0, -math.pi, math.nan, math.nan, 0),
    ):
        odom = codec.odometry_messages([sample])[0]
        assert odom == codec.odometry_message(sample)
        tf = codec.odom_transform_messages([sample])[0]
        assert tf == codec.odom_transforms([sample])


# -- the commands ----------------------------------------------------------------------------------


@pytest.mark.usefixtures("no_target_env")
@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["record", "--target", "t.toml", "--drive"], "--drive goes with --sim"),
        (["record", "--target", "t.toml", "--grid"], "--grid needs the vehicle's poses"),
        (["view", "--replay", "{raw}", "--drive"], "--drive goes with --sim"),
        (["view", "--replay", "{raw}", "--grid", "--port", "0"], "holds no vehicle poses"),
    ],
)
def test_moving_flags_without_poses_are_usage_errors(
    biris: Run, tmp_path: Path, argv: list[str], said: str
) -> None:
    raw = str(_synthetic(tmp_path))
    args = [a.replace("{raw}", raw) for a in argv]
    if args[0] == "record":
        args += ["--out", str(tmp_path / "x.mcap"), "--duration", "1"]
    else:
        args += ["--duration", "1"]
    code, _out, err = biris(*args)
    assert code == 2 and said in err, err
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.usefixtures("no_target_env")
@pytest.mark.parametrize("command", ["record", "view", "serve"])
def test_a_scene_too_tight_for_the_drive_is_a_usage_error_before_anything_starts(
    biris: Run, tmp_path: Path, command: str
) -> None:
    out = tmp_path / "x.mcap"
    extra = ["--out", str(out), "--duration", "1"] if command == "record" else []
    code, _out, err = biris(command, "--sim", "--drive", "--scene", "circle:0.5", *extra)
    assert code == 2, err
    assert "--drive in --scene circle:0.5: the default drive does not fit this scene" in err
    assert not out.exists()


@pytest.mark.realtime  # biris record keeps scaled time: it records as time passes
@pytest.mark.usefixtures("no_target_env")
def test_biris_record_drive_grid(biris: Run, tmp_path: Path) -> None:
    out = tmp_path / "d.mcap"
    sim = ["--sim", "--time-scale", "10", "--seed", "3"]
    code, stdout, err = biris("record", *sim, "--drive", "--grid", "--out", str(out), "--to", "90")
    assert code == 0, err
    assert "vehicle poses" in stdout and "dropped 0 acquisitions" in stdout
    topics = {m[0] for m in read_decoded(out)}
    assert {codec.ODOM_TOPIC, codec.GRID_TOPIC, codec.POINTS_TOPIC} <= topics
    clouds = _messages(out, codec.POINTS_TOPIC)
    assert [m.header.frame_id for m, _ in clouds] == ["odom"]
    odom = _messages(out, codec.ODOM_TOPIC)
    assert odom and all(log == codec.stamp_ns(_stamp(m.header)) for m, log in odom)  # hardware
    with open(out, "rb") as f:
        meta = {r.name: dict(r.metadata) for r in make_reader(f).iter_metadata()}
    assert json.loads(meta["biris"]["simulator"])["drive"] == "sim.drives.default_drive"
