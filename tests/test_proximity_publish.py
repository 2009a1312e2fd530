"""The proximity alarm published: ``proximity=`` puts its answers on ``/biris/proximity``.

End to end on virtual time, once for the module: the simulated vehicle drives straight at an
obstacle in its path (the drive of ``tests/test_proximity.py``), the head sweeping ahead, and a
:class:`~biris_hw.io.record.Recorder` given ``proximity=`` records the answers the moving
encoder makes from the live acquisitions; the file's answers are read back with the codec and
held against the truth. The encoder's rules (an acquisition waits for its pose; built only
when wanted, fed whatever is watched; nothing without ``proximity=``) are checked on
acquisitions made here; the commands' flags by parsing them. The service's key is in
``tests/test_serve_moving.py``.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from biris_hw.data import Point, PoseSample
from biris_hw.io import codec
from biris_hw.io.feed import Batch, StatusReading
from biris_hw.io.grid import GridParams
from biris_hw.io.liveview import LiveView
from biris_hw.io.moving_sink import MovingEncoder, RecordedPoses
from biris_hw.io.pose import PoseBuffer
from biris_hw.io.proximity import (
    DEFAULT_ZONE,
    RATE_HZ,
    ProximityAlarm,
    ProximityFeeder,
    ProximityZone,
)
from biris_hw.io.record import Recorder, RecordSummary
from biris_hw.io.record.replay import ReplayServer
from biris_hw.opening import open_poses, open_sensor
from sim import Scene, SimulatedBiris, Trajectory
from tests.conftest import Run
from tests.test_proximity import OBSTACLE, SPEED, START_S
from tests.test_record_support import synthetic_scans, write_raw

UNTIL_S = START_S + 3.0
"""Hardware time the drive ends: the obstacle's face (1.45 m) is then 0.25 m ahead."""


@dataclass(frozen=True)
class Published:
    """The module's recording: every answer on /biris/proximity, and the truth."""

    path: Path
    summary: RecordSummary
    answers: list[codec.ProximityMessage]
    true_x: list[float]
    """The vehicle's true x at each answer's stamp."""
    log_ns: list[int]


@pytest.fixture(scope="module")
def published(tmp_path_factory: pytest.TempPathFactory) -> Published:
    """Straight at the obstacle at SPEED from START_S, the head sweeping +-30 degrees, recorded
    with the poses and the alarm's default zone; everything stopped before the tests."""
    path = tmp_path_factory.mktemp("proximity") / "alarm.mcap"
    scene = Scene.room().with_shapes(OBSTACLE)
    rig = SimulatedBiris(
        scene=scene, seed=3, clock="virtual", trajectory=Trajectory.line(SPEED, start_s=START_S)
    )
    with rig, open_sensor(sim=rig) as sensor, open_poses(sim=rig) as poses:
        recorder = Recorder(sensor, path, poses=poses, proximity=DEFAULT_ZONE)
        with recorder:
            conn = sensor.open()
            conn.wait_idle()
            i = 0
            while sensor.clock() < UNTIL_S:
                conn.single_scan(30.0 if i % 2 == 0 else -30.0)
                conn.wait_idle()
                i += 1
        assert not rig.audit.violations, rig.audit.violations
        answers, log_ns = [], []
        with open(path, "rb") as f:
            for _s, _c, message in make_reader(f).iter_messages(
                topics=[codec.PROXIMITY_TOPIC], log_time_order=True
            ):
                answers.append(codec.decode_proximity(message.data))
                log_ns.append(message.log_time)
        true_x = [rig.true_pose(a.t)[0] for a in answers]
    assert recorder.summary is not None
    return Published(path, recorder.summary, answers, true_x, log_ns)


def test_a_recording_carries_the_alarm_at_a_few_hz(published: Published) -> None:
    with open(published.path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        meta = {r.name: dict(r.metadata) for r in reader.iter_metadata()}
    assert summary is not None
    types = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert types[codec.PROXIMITY_TOPIC] == codec.PROXIMITY
    answers = published.answers
    stamps = np.array([a.t for a in answers])
    assert all(a.frame_id == "vehicle" for a in answers)
    assert published.log_ns == [codec.stamp_ns(t) for t in stamps]  # logged at their stamps
    gaps = np.diff(stamps)
    assert np.all(gaps[:-1] >= 1 / RATE_HZ - 1e-9)  # at most RATE_HZ; the last: the end's
    assert gaps[-1] > 0
    # a few Hz of hardware time from the first acquisition to the last, however the virtual
    # clock batched them (a sweep at a time): silent only while the head turns between sweeps
    assert np.all(gaps < 0.5)
    assert len(answers) >= 0.7 * RATE_HZ * (stamps[-1] - stamps[0])
    assert published.summary.proximity_messages == len(answers)
    assert "proximity answers" in str(published.summary)
    moving = json.loads(meta["biris"]["moving"])
    assert moving["proximity"]["topic"] == codec.PROXIMITY_TOPIC
    assert moving["proximity"]["width_m"] == DEFAULT_ZONE.width_m
    end = meta["biris.recording"]
    assert int(end["proximity_messages"]) == len(answers)
    assert int(end["proximity_acquisitions"]) > 0 and int(end["proximity_unplaced"]) == 0


def test_the_recorded_answers_find_the_obstacle_at_its_true_distance(
    published: Published,
) -> None:
    front = OBSTACLE.center[0] - OBSTACLE.radius
    reported = quiet = 0
    for answer, x in zip(published.answers, published.true_x, strict=True):
        ahead = front - x  # the truth: how far ahead the obstacle's face is
        if answer.t > START_S + 0.3:
            assert answer.speed_mps == pytest.approx(SPEED, abs=0.01)
            assert answer.looked_age_s < 0.6  # a +-30 degree sweep looks ahead all the time
        if ahead > answer.zone_length_m + 0.1:
            assert not answer.found, (answer, ahead)  # nothing else lies in the path
            assert answer.distance_m == math.inf and math.isnan(answer.age_s)
            quiet += 1
        elif 0.35 < ahead < answer.zone_length_m - 0.1:  # in the zone, in the sensor's range
            assert answer.found, (answer, ahead)
            assert answer.distance_m == pytest.approx(ahead, abs=0.03)
            assert abs(answer.y_m - OBSTACLE.center[1]) < OBSTACLE.radius
            assert 0.0 <= answer.age_s < 0.9  # seen at least once a sweep and a turn
            reported += 1
    assert reported >= 3 and quiet >= 3  # the drive brought it from beyond the zone into it


# -- the moving encoder's rules, on acquisitions made here -----------------------------------------


def _poses(t0: float, t1: float) -> list[PoseSample]:
    """Standing at the odom origin facing x, 50 Hz from t0 to t1."""
    n = round((t1 - t0) / 0.02) + 1
    return [PoseSample(t0 + 0.02 * i, 0.0, 0.0, 0.0, 0.0, 0.0, i) for i in range(n)]


def _ahead(t: float, depth_mm: int = 400, azimuth: int = 0) -> Point:
    """One acquisition straight ahead (or at ``azimuth`` counts; no mount: from the vehicle
    frame's origin) whose every row sees a surface ``depth_mm`` away."""
    profile = np.full(64, depth_mm, dtype=np.int16)
    return Point(azimuth, depth_mm, profile, profile, t, 0, 1)


def _on(topic: str, messages: list[codec.Encoded]) -> list[codec.Encoded]:
    return [m for m in messages if m.topic == topic]


def test_an_acquisition_waits_for_its_pose_and_answers_come_at_the_rate_however_batched() -> None:
    samples = _poses(9.0, 11.0)
    buffer = PoseBuffer(max_extrapolation_s=0.0)
    buffer.extend(samples[:51])  # up to 10.0
    encoder = MovingEncoder(buffer, proximity=ProximityZone())
    assert encoder.topics[codec.PROXIMITY_TOPIC] == codec.PROXIMITY

    def stamps(*points: Point, final: bool = False) -> list[float]:
        got = encoder.messages(Batch(points=points, final=final))
        answers = [codec.decode_proximity(m.data) for m in _on(codec.PROXIMITY_TOPIC, got)]
        assert all(a.found and a.distance_m == pytest.approx(0.4, abs=0.002) for a in answers)
        return [a.t for a in answers]

    assert stamps(_ahead(9.8), _ahead(10.1)) == [9.8]  # 10.1 has no pose yet: it waits
    assert encoder.proximity_feeder is not None and encoder.proximity_feeder.pending == 1
    buffer.extend(samples[51:])
    # one batch, two answers: 10.1 (0.3 s on, its pose come) and 10.45 (at least 0.2 s later)
    assert stamps(_ahead(10.15), _ahead(10.25), _ahead(10.45)) == [10.1, 10.45]
    assert encoder.proximity_feeder.pending == 0
    assert stamps(_ahead(10.5)) == []  # not owed yet
    assert stamps(final=True) == [10.5]  # at the end, once more at the newest
    assert stamps(final=True) == []  # said already
    counts = encoder.counts()
    assert counts["proximity_messages"] == encoder.proximity_messages == 4
    assert (counts["proximity_acquisitions"], counts["proximity_unplaced"]) == (6, 0)


def test_unwatched_the_alarm_is_fed_but_nothing_is_built() -> None:
    buffer = PoseBuffer()
    buffer.extend(_poses(9.0, 11.0))
    encoder = MovingEncoder(buffer, proximity=ProximityAlarm())

    def unwatched(topic: str) -> bool:
        return topic != codec.PROXIMITY_TOPIC

    for t in (9.5, 10.0):
        got = encoder.messages(Batch(points=(_ahead(t),)), unwatched)
        assert not _on(codec.PROXIMITY_TOPIC, got)
    assert encoder.alarm is not None and encoder.alarm.acquisitions == 2
    assert encoder.proximity_messages == 0
    # a viewer who subscribes now hears what the head saw before (looking left meanwhile)
    left = _ahead(10.5, 2500, azimuth=1024)
    (now,) = _on(codec.PROXIMITY_TOPIC, encoder.messages(Batch(points=(left,))))
    answer = codec.decode_proximity(now.data)
    assert answer.found and answer.age_s == pytest.approx(0.5)


def test_without_proximity_nothing_new_is_made() -> None:
    buffer = PoseBuffer()
    buffer.extend(_poses(9.0, 11.0))
    encoder = MovingEncoder(buffer, GridParams())
    got = encoder.messages(Batch(points=(_ahead(9.5), _ahead(10.0))))
    got += encoder.messages(Batch(status=StatusReading(None, None, 11.0), final=True))
    assert encoder.proximity_feeder is None and encoder.alarm is None
    assert codec.PROXIMITY_TOPIC not in encoder.topics
    assert not _on(codec.PROXIMITY_TOPIC, got) and _on(codec.GRID_TOPIC, got)
    assert not any(k.startswith("proximity") for k in encoder.counts())
    assert "proximity" not in encoder.describe()


def test_proximity_needs_poses_and_is_one_of_its_kinds(tmp_path: Path) -> None:
    replay = ReplayServer(write_raw(tmp_path / "raw.mcap", synthetic_scans(1)), autostart=False)
    with replay, pytest.raises(ValueError, match="proximity= needs poses="):
        Recorder(replay, tmp_path / "x.mcap", proximity=DEFAULT_ZONE)
    with pytest.raises(ValueError, match="proximity= needs poses="):
        LiveView(replay, port=0, proximity=DEFAULT_ZONE)
    with pytest.raises(TypeError, match="proximity= takes"):
        MovingEncoder(PoseBuffer(), proximity=GridParams())  # type: ignore[arg-type]
    assert not (tmp_path / "x.mcap").exists()
    buffer = PoseBuffer()
    feeder = ProximityFeeder(ProximityAlarm(), buffer, rate_hz=1.0)
    assert MovingEncoder(buffer, proximity=feeder).proximity_feeder is feeder  # as given
    with pytest.raises(ValueError, match="rate_hz"):
        ProximityFeeder(ProximityAlarm(), buffer, rate_hz=0.0)


# -- the live view ---------------------------------------------------------------------------------


@pytest.fixture()
def _foxglove_runtime() -> Iterator[None]:
    """foxglove-sdk keeps its runtime for the life of the process once a server has run: start
    it before the test's leak check takes its snapshot (as tests/test_liveview.py does)."""
    import foxglove

    foxglove.start_server(port=0, context=foxglove.Context()).stop()
    yield


@pytest.mark.usefixtures("_foxglove_runtime")
def test_the_live_view_offers_the_alarm_channel(tmp_path: Path) -> None:
    from websockets.sync.client import connect
    from websockets.typing import Subprotocol

    replay = ReplayServer(write_raw(tmp_path / "raw.mcap", synthetic_scans(1)), autostart=False)
    poses = RecordedPoses(_poses(9.0, 11.0))
    view = LiveView(replay, port=0, layout_port=None, poses=poses, proximity=DEFAULT_ZONE)
    protocol = [Subprotocol("foxglove.sdk.v1")]
    with replay, view, connect(f"ws://127.0.0.1:{view.port}", subprotocols=protocol) as ws:
        assert json.loads(ws.recv(timeout=10.0))["op"] == "serverInfo"
        channels: dict[str, str] = {}
        while codec.PROXIMITY_TOPIC not in channels:
            for channel in json.loads(ws.recv(timeout=10.0)).get("channels", []):
                channels[channel["topic"]] = channel["schemaName"]
    assert channels[codec.PROXIMITY_TOPIC] == codec.PROXIMITY
    assert view.moving is not None and view.moving.alarm is not None


# -- the commands ----------------------------------------------------------------------------------


def _parse(*argv: str) -> argparse.Namespace:
    from biris_hw.cli import build_parser

    out = ["--out", "x.mcap"] if argv[0] == "record" else []
    return build_parser(argv[0]).parse_args([*argv, *out])


@pytest.mark.parametrize("command", ["record", "view", "serve"])
def test_the_commands_take_proximity_and_its_zone(command: str) -> None:
    from biris_hw.commands.record import check_moving_arguments, proximity_zone

    assert proximity_zone(_parse(command, "--sim")) is None
    assert proximity_zone(_parse(command, "--sim", "--proximity")) == DEFAULT_ZONE
    args = _parse(command, "--sim", "--drive", "--proximity-zone", "0.2,0.8,0.6")
    assert proximity_zone(args) == ProximityZone(front_m=0.2, width_m=0.8, length_m=0.6)
    check_moving_arguments(args)  # on the simulator: it has the poses


@pytest.mark.usefixtures("_foxglove_runtime")
def test_biris_view_replay_proximity_feeds_the_alarm_from_the_file(published: Published) -> None:
    """``biris view --replay FILE --proximity``: the file's poses and acquisitions feed an
    alarm of the view's own, as they fed the recorder's."""
    import io

    from biris_hw.commands import view as view_command

    views: list[LiveView] = []

    def ready(view: LiveView) -> None:  # the replay has begun: let it play to its end
        views.append(view)
        assert isinstance(view.source, ReplayServer) and view.source.wait_done(10.0)

    argv = ["view", "--replay", str(published.path), "--proximity", "--port", "0"]
    args = _parse(*argv, "--speed", "100", "--duration", "0.1")
    assert view_command.run(args, io.StringIO(), ready=ready) == 0
    moving = views[0].moving
    assert moving is not None and moving.alarm is not None
    assert moving.alarm.acquisitions == published.summary.points  # every one, placed
    assert moving.alarm.unplaced == 0 and moving.alarm.zone == DEFAULT_ZONE


@pytest.mark.usefixtures("no_target_env")
@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["record", "--target", "t.toml", "--proximity"], "--proximity needs the vehicle's poses"),
        (["view", "--sim", "--proximity-zone", "0,0,1"], "must be positive"),
        (["view", "--sim", "--proximity-zone", "1,2"], "not three numbers"),
    ],
)
def test_proximity_flags_that_cannot_be_are_usage_errors(
    biris: Run, tmp_path: Path, argv: list[str], said: str
) -> None:
    extra = ["--out", str(tmp_path / "x.mcap"), "--duration", "1"] if argv[0] == "record" else []
    code, _out, err = biris(*argv, *extra)
    assert code == 2 and said in err, err
    assert not (tmp_path / "x.mcap").exists()
