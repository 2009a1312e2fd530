"""The standard views of biris_hw.io.codec: standard schemas, decodable CDR, the right geometry."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from biris_hw.io import codec
from biris_hw.status import ServerState, ServerStatus
from tests.conftest import idle_status
from tests.test_record_support import cloud_xyz, points_of, synthetic_scans


@functools.cache
def standard() -> Typestore:
    """rosbags' own ROS 2 Humble typestore, as a stranger's reader holds it (built on first use, not
    at collection, where it cost every test worker a fifth of a second)."""
    return get_typestore(Stores.ROS2_HUMBLE)


"""Another ROS 2 distribution's store than the codec's (Jazzy): the same standard text."""


@pytest.mark.parametrize("msgtype", sorted(set(codec.TOPICS.values())))
def test_schema_text_is_the_standard_definition(msgtype: str) -> None:
    text, _ = standard().generate_msgdef(msgtype, ros_version=2)
    assert codec.schema_text(msgtype) == text
    assert "MSG: std_msgs/Header" in text or msgtype == codec.TF_MESSAGE


@pytest.mark.parametrize("frame", ["vehicle", "sensor"])
def test_scan_cloud_holds_scan_points(frame: str) -> None:
    scan = synthetic_scans(1)[0]
    encoded = codec.scan_cloud(scan, frame)  # type: ignore[arg-type]
    msg = standard().deserialize_cdr(encoded.data, codec.POINT_CLOUD2)
    assert msg.header.frame_id == codec.cloud_frame_id(frame)  # type: ignore[arg-type]
    assert [f.name for f in msg.fields] == [f[0] for f in codec.CLOUD_FIELDS]
    want = scan.points(frame)  # type: ignore[arg-type]
    assert msg.width == len(want) and msg.is_dense
    np.testing.assert_allclose(cloud_xyz(msg), want, rtol=0, atol=1e-6 * 8)
    assert encoded.log_time_ns == round(float(scan.t[0]) * 1e9)


def _matrix(tf: object) -> np.ndarray:
    q = tf.transform.rotation  # type: ignore[attr-defined]
    x, y, z, w = q.x, q.y, q.z, q.w
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    t = tf.transform.translation  # type: ignore[attr-defined]
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, (t.x, t.y, t.z)
    return m


def test_profile_through_the_transform_chain_lands_on_point_points() -> None:
    point = points_of(synthetic_scans(1)[0])[5]
    profile = standard().deserialize_cdr(codec.profile_cloud(point).data, codec.POINT_CLOUD2)
    assert profile.header.frame_id == codec.SENSOR_FRAME
    chain = {}
    for encoded in (codec.static_transforms(point.mount), codec.transforms(point)):
        for tf in standard().deserialize_cdr(encoded.data, codec.TF_MESSAGE).transforms:
            chain[tf.child_frame_id] = (tf.header.frame_id, _matrix(tf))
    frame, m = codec.SENSOR_FRAME, np.eye(4)
    while frame in chain:
        parent, step = chain[frame]
        m, frame = step @ m, parent
    assert frame == codec.VEHICLE_FRAME
    xyz = cloud_xyz(profile)
    placed = (m[:3, :3] @ xyz.T).T + m[:3, 3]
    np.testing.assert_allclose(placed, point.points("vehicle"), atol=1e-5)


def test_diagnostics_levels_follow_the_state() -> None:
    def status(state: ServerState, fault: str | None = None) -> ServerStatus:
        return idle_status(state=state, fault=fault, counters={"scans": 3})

    def levels(encoded: codec.Encoded) -> list[tuple[str, int]]:
        msg = standard().deserialize_cdr(encoded.data, codec.DIAGNOSTIC_ARRAY)
        return [(s.name, s.level) for s in msg.status]

    ok = codec.diagnostics(status(ServerState.IDLE), 1.0, extra={"recorder": {"dropped_points": 0}})
    assert levels(ok) == [("server", 0), ("recorder", 0)]
    bad = codec.diagnostics(
        status(ServerState.FAULT, "bus"), 1.0, extra={"recorder": {"dropped_points": 2}}
    )
    assert levels(bad) == [("server", 2), ("recorder", 1)]
    assert levels(codec.diagnostics(None, 1.0, error="gone")) == [("server", 2)]
    assert codec.stamp_ns(1.5) == 1_500_000_000 and codec.stamp_ns(-1.0) == 0
    assert math.isclose(codec.stamp_ns(2.25) / 1e9, 2.25)


def test_hand_encoded_cdr_is_what_rosbags_writes() -> None:
    """The per-acquisition messages are encoded by hand (codec._Cdr); rosbags, decoding and
    encoding them again, gives the same bytes: canonical CDR, alignment and all."""
    scans = synthetic_scans(2)
    encoded = [codec.transforms(p) for s in scans for p in points_of(s)]
    encoded += codec.profile_clouds([p for s in scans for p in points_of(s)])
    encoded += [codec.scan_cloud(s, f) for s in scans for f in ("vehicle", "sensor")]  # type: ignore[arg-type]
    for message in encoded:
        decoded = standard().deserialize_cdr(message.data, message.msgtype)
        assert bytes(standard().serialize_cdr(decoded, message.msgtype)) == message.data


def test_batched_profiles_equal_one_at_a_time() -> None:
    """profile_clouds projects a batch at once (mixed profile lengths too); each message is the
    one profile_cloud makes alone, and point_rows' per-point origins are kept."""
    points = points_of(synthetic_scans(1)[0]) + points_of(synthetic_scans(1, samples=32)[0])
    batch = codec.profile_clouds(points)
    assert [m.data for m in batch] == [codec.profile_cloud(p).data for p in points]
    starts = [p.t - 1.0 for p in points]
    rows = codec.point_rows(points, "vehicle", starts)
    for p, got, t0 in zip(points, rows, starts, strict=True):
        assert got.tobytes() == codec.sweep_rows(p, t0).tobytes()
        assert len(got) == int((p.profile > 0).sum())


def test_sweep_pieces_put_together_are_the_scan_cloud() -> None:
    """/biris/sweep carries the acquisitions since its previous message: one message of a whole
    scan's acquisitions is the scan's cloud byte for byte, and pieces of it (each a well-formed
    cloud: numpy's concatenate must not pack the rows' padding away) hold the same points."""
    for scan in synthetic_scans(2):
        points = points_of(scan)
        assert codec.sweep_cloud(points).data == codec.scan_cloud(scan).data
        pieces = [codec.sweep_cloud(points[i : i + 5]) for i in range(0, len(points), 5)]
        decoded = [standard().deserialize_cdr(m.data, m.msgtype) for m in pieces]
        assert all(len(m.data) == m.width * m.point_step for m in decoded)
        xyz = np.concatenate([cloud_xyz(m) for m in decoded])
        np.testing.assert_allclose(xyz, scan.points(), rtol=1e-6, atol=1e-6)
        first = decoded[1].header.stamp
        assert first.sec + first.nanosec / 1e9 == pytest.approx(points[5].t)
        assert pieces[1].log_time_ns == codec.stamp_ns(points[9].t)
