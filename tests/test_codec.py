"""One codec (biris_hw.io.codec): one typestore of one ROS 2 distribution and one header rule,
writing the schema texts and bytes that files and the network held before the lossless and the
standard halves were joined; a recording made then replays; the old module names resolve to the
new objects. The round trips themselves: tests/test_wire.py (biris_msgs) and tests/test_ros2.py
(the standard views)."""

from __future__ import annotations

import functools
import importlib
import math
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from biris_hw.data import ConnectionKind, DeliveryPolicy, Point
from biris_hw.errors import HardwareFault
from biris_hw.io import codec, feed
from biris_hw.io.net import warm
from biris_hw.io.record.mcapfile import McapFile
from biris_hw.io.record.replay import ReplayServer
from regs.wiener_crate import CrateReading
from tests.conftest import idle_status
from tests.test_record_support import assert_same_scan, points_of, synthetic_scans
from tests.test_wire import assert_points_equal

WAIT = 10.0

STANDARD_TYPES = (
    "builtin_interfaces/msg/Time",
    "std_msgs/msg/Header",
    "sensor_msgs/msg/PointField",
    "sensor_msgs/msg/PointCloud2",
    "geometry_msgs/msg/Vector3",
    "geometry_msgs/msg/Quaternion",
    "geometry_msgs/msg/Transform",
    "geometry_msgs/msg/TransformStamped",
    "tf2_msgs/msg/TFMessage",
    "diagnostic_msgs/msg/KeyValue",
    "diagnostic_msgs/msg/DiagnosticStatus",
    "diagnostic_msgs/msg/DiagnosticArray",
)
"""Every standard type a message of ours is or holds."""


@functools.cache
def humble() -> Any:
    """ROS 2 Humble's store with the biris_msgs types: the store the lossless half was written
    with before the codec chose one distribution (built on first use, not at collection)."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in codec.MSG_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def test_one_store_holds_every_type_and_is_the_distributions() -> None:
    store = codec.typestore()
    assert store is codec.typestore()  # built once
    assert Stores(codec.DISTRIBUTION) is Stores.ROS2_JAZZY
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    for msgtype in STANDARD_TYPES:
        assert store.generate_msgdef(msgtype, ros_version=2) == jazzy.generate_msgdef(
            msgtype, ros_version=2
        ), msgtype
    assert set(codec.MSG_DEFINITIONS) <= set(store.types)


@pytest.mark.parametrize("msgtype", [*STANDARD_TYPES, *codec.MSG_DEFINITIONS])
def test_the_schema_texts_are_those_written_before(msgtype: str) -> None:
    """Humble, which the lossless half used, and Jazzy, which the standard half used and the
    codec now uses for both, define every type we write alike: the texts in the files (and so
    what ros2 bag, mcap-ros2-support and Foxglove parse) are what they were."""
    text, _ = humble().generate_msgdef(msgtype, ros_version=2)
    assert codec.schema_text(msgtype) == text
    assert codec.full_definition is codec.schema_text


def test_the_bytes_are_those_written_before() -> None:
    """Each message decoded and encoded again by the Humble store is the codec's bytes."""
    scans = synthetic_scans(2)
    points = [p for s in scans for p in points_of(s)]
    messages = [(codec.SCAN, codec.encode_scan(s)) for s in scans]
    messages += [(codec.POINT, codec.encode_point(p)) for p in points]
    messages += [(codec.STATUS, codec.encode_status(idle_status(), 3.25))]
    messages += [(codec.FAULT, codec.encode_fault(HardwareFault("bus", "BERR"), 1.5))]
    for encoded in (
        codec.scan_cloud(scans[0]),
        codec.transforms(points[0]),
        codec.diagnostics(idle_status(), 2.0),
    ):
        messages.append((encoded.msgtype, encoded.data))
    for msgtype, data in messages:
        assert (
            bytes(humble().serialize_cdr(humble().deserialize_cdr(data, msgtype), msgtype)) == data
        )


def test_a_recording_written_with_the_humble_store_replays(tmp_path: Path) -> None:
    """A file as the recorder wrote it before: Humble's schema texts, payloads serialised by
    Humble's store. The replay reads it back equal."""
    scans = synthetic_scans(3)
    path = tmp_path / "before.mcap"
    file = McapFile(path)
    for scan in scans:
        for point in points_of(scan):
            msg = humble().deserialize_cdr(codec.encode_point(point), codec.POINT)
            text, _ = humble().generate_msgdef(codec.POINT, ros_version=2)
            data = bytes(humble().serialize_cdr(msg, codec.POINT))
            file.write(codec.RAW_POINT_TOPIC, codec.POINT, text, data, codec.stamp_ns(point.t))
        msg = humble().deserialize_cdr(codec.encode_scan(scan), codec.SCAN)
        text, _ = humble().generate_msgdef(codec.SCAN, ros_version=2)
        data = bytes(humble().serialize_cdr(msg, codec.SCAN))
        file.write(codec.RAW_SCAN_TOPIC, codec.SCAN, text, data, codec.stamp_ns(scan.t[-1]))
    assert file.close()
    with ReplayServer(path, speed=None, autostart=False) as replay:
        scans_conn = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        points_conn = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
        replay.start()
        for scan in scans:
            for point in points_of(scan):
                assert_points_equal(points_conn.ready_for_data(timeout=WAIT), point)
            assert_same_scan(scans_conn.ready_for_data(timeout=WAIT), scan)


@pytest.mark.parametrize("t", [0.0, 1.5, 12.345678901, 86_400.000_000_5, -3.0, math.nan])
def test_every_header_is_stamped_by_the_one_rule(t: float) -> None:
    """biris_msgs and standard views alike: ``header.stamp`` is :func:`codec.stamp_ns`."""
    sec, nanosec = divmod(codec.stamp_ns(t), 1_000_000_000)
    profile = np.array([1000, 0, 1200], dtype=np.int16)
    point = Point(5, 1000, profile, profile, t, 1, 1, mount=None)
    store = codec.typestore()
    made = [
        (codec.POINT, codec.encode_point(point)),
        (codec.STATUS, codec.encode_status(idle_status(), t)),
        (codec.FAULT, codec.encode_fault(HardwareFault("parity", "PERR"), t)),
    ]
    for encoded in (
        codec.diagnostics(idle_status(), t),
        codec.static_transforms(None, t),
        codec.transforms(point),
        codec.profile_cloud(point),
        codec.sweep_cloud([point]),
    ):
        made.append((encoded.msgtype, encoded.data))
        assert encoded.log_time_ns == codec.stamp_ns(t)
    for msgtype, data in made:
        msg = store.deserialize_cdr(data, msgtype)
        headers = (
            [tf.header for tf in msg.transforms] if msgtype == codec.TF_MESSAGE else [msg.header]
        )
        for header in headers:
            assert (header.stamp.sec, header.stamp.nanosec) == (sec, nanosec), msgtype
    if math.isfinite(t):  # the payload keeps the time itself, exactly
        assert codec.decode_point(codec.encode_point(point)).t == t


def test_stamps_clamp_into_what_time_holds() -> None:
    assert codec.stamp_ns(2.25) == 2_250_000_000
    assert codec.stamp_ns(-1.0) == codec.stamp_ns(math.nan) == 0
    assert codec.stamp_ns(math.inf) == codec.stamp_ns(1e12) == codec.MAX_STAMP_NS
    assert divmod(codec.MAX_STAMP_NS, 1_000_000_000) == (2**31 - 1, 999_999_999)
    far = Point(0, 0, np.zeros(2, np.int16), np.zeros(2, np.int16), 1e12, 0, 0)
    assert codec.decode_point(codec.encode_point(far)).t == 1e12  # the stamp saturates only
    assert codec.transforms(far).log_time_ns == codec.MAX_STAMP_NS


def test_every_hand_written_message_is_what_rosbags_writes() -> None:
    """The messages written by hand (codec._Cdr): decoded and encoded again by rosbags, the same
    bytes, alignment and all: the static transforms too, and an empty sweep."""
    scans = synthetic_scans(2)
    points = [p for s in scans for p in points_of(s)]
    made = [codec.transforms(p) for p in points] + codec.profile_clouds(points)
    made += [codec.scan_cloud(s, f) for s in scans for f in ("vehicle", "sensor")]  # type: ignore[arg-type]
    made += [codec.static_transforms(s.mount, 4.5) for s in scans] + [codec.static_transforms(None)]
    made += [codec.sweep_cloud(points[:7]), codec.sweep_cloud([])]
    store = codec.typestore()
    for message in made:
        decoded = store.deserialize_cdr(message.data, message.msgtype)
        assert bytes(store.serialize_cdr(decoded, message.msgtype)) == message.data


@pytest.mark.parametrize("samples", [0, 1, 7, 128])
def test_a_hand_written_point_is_what_rosbags_writes(samples: int) -> None:
    """``encode_point`` writes the lossless Point by hand (around the bytes its shape shares with
    every acquisition): the same bytes as rosbags' serialisation of the same message, for every
    shape a Point takes -- with and without a mount and a delivery time, each acquisition mode,
    arrays of another byte order or not contiguous."""
    from biris_hw.geometry import Mount

    rng = np.random.default_rng(samples)
    store = codec.typestore()
    profile = rng.integers(-32768, 32767, size=2 * samples, dtype=np.int16)
    intensity = rng.integers(-32768, 32767, size=samples, dtype=np.int16)
    for mount in (None, Mount(offset_m=(0.1, -0.2, 0.3), head_height_m=0.45)):
        for t_delivered in (None, math.nan, 12.75):
            for acquisition, arrays in (
                ("single", (profile[:samples], intensity)),
                ("continuous", (profile[::2], intensity.astype(">i2"))),
            ):
                point = Point(
                    azimuth=-1234,
                    range_mm=4321,
                    profile=arrays[0],
                    intensity=arrays[1],
                    t=12.5 + samples,
                    acq=7,
                    scan_seq=3,
                    elevation=-40,
                    t_delivered=t_delivered,
                    mount=mount,
                    acquisition=acquisition,
                )
                data = codec.encode_point(point)
                decoded = store.deserialize_cdr(data, codec.POINT)
                assert bytes(store.serialize_cdr(decoded, codec.POINT)) == data
                back = codec.decode_point(data)
                assert back.acquisition == acquisition and back.mount == mount
                np.testing.assert_array_equal(back.profile, arrays[0])
                np.testing.assert_array_equal(back.intensity, arrays[1])


def _reading() -> CrateReading:
    return CrateReading(
        crate_id=3,
        power_on=True,
        inhibit=False,
        supply_ok=True,
        power_supply_error=False,
        fans_ok=False,
        sysfail=True,
        status_bytes=bytes(range(8)),
        under_voltage=0x01,
        over_voltage=0x80,
        external_temperature=0,
        over_current=0x0F,
        over_voltage_protection=0,
        supply_temperature=0x10,
        voltages_v=(5.01, 12.0, -12.0, 3.3, 0.0, 0.0, 0.0, 0.0),
        currents_a=(20.5, 1.25, 0.75, 4.0, 0.0, 0.0, 0.0, 0.0),
        fan_average_rps=42,
        fan_nominal_rps=45,
        fans_rps=(40, 41, 42, 43, 44, 0),
        temperatures_c=(30, 31, 32, 33, 0, 0, 0, 0),
        read_at=1234.5,
    )


def test_a_crate_reading_round_trips_alone_and_in_a_status() -> None:
    reading = _reading()
    assert codec.decode_crate(codec.encode_crate(reading)) == reading
    status = codec.decode_status(codec.encode_status(idle_status(crate=reading)))
    assert status.crate == reading and status.crate_error is None
    with pytest.raises(codec.WireError):
        codec.encode_crate("not a reading")  # type: ignore[arg-type]
    with pytest.raises(codec.WireError):
        codec.decode_crate(codec.encode_crate(reading)[:-9])


def test_warming_pays_each_type_once() -> None:
    codec.warm.cache_clear()
    codec.warm(codec.STATUS)
    codec.warm(codec.STATUS)
    assert codec.warm.cache_info().hits == 1
    warm.warm_all()
    assert codec.warm.cache_info().currsize == len(warm.KINDS)
    with pytest.raises(KeyError):
        codec.warm("biris_msgs/msg/Nothing")
    with pytest.raises(ValueError, match="no payload kind"):
        warm.warm("nothing")


OLD_ROS2_NAMES = (
    "BASE_FRAME", "CLOUD_FIELDS", "DIAGNOSTIC_ARRAY", "PAN_FRAME", "POINT_CLOUD2",
    "RAW_POINT_TOPIC", "RAW_SCAN_TOPIC", "RAW_STATUS_TOPIC", "SENSOR_FRAME", "TF_MESSAGE",
    "TILT_FRAME", "TOPICS", "VEHICLE_FRAME", "Encoded", "SensorFeed", "SensorSource",
    "cloud_frame_id", "diagnostics", "point_rows", "profile_cloud", "profile_clouds",
    "scan_cloud", "schema_text", "sensor_time", "stamp_ns", "static_transforms",
    "sweep_cloud", "sweep_rows", "transforms", "typestore", "BATCH_S", "DRAIN_MAX",
)  # fmt: skip
"""biris_hw.io.ros2's public names before its messages went to the codec, its reader to the feed."""

OLD_WIRE_NAMES = (
    "FAULT", "FRAME_ID", "MAX_PAYLOAD", "MSG_DEFINITIONS", "POINT", "SCAN", "STATUS",
    "WireError", "decode_fault", "decode_point", "decode_scan", "decode_status",
    "encode_fault", "encode_point", "encode_scan", "encode_status", "full_definition",
    "typestore",
)  # fmt: skip


def _fresh(name: str) -> Any:
    """Import ``name`` as a fresh process would (not yet in sys.modules), warning caught."""
    sys.modules.pop(name, None)
    with pytest.warns(DeprecationWarning, match=f"{name} moved to biris_hw.io.codec"):
        return importlib.import_module(name)


@pytest.mark.parametrize("old", ["biris_hw.wire", "biris_hw.io.wire"])
def test_the_old_wire_is_the_codec(old: str) -> None:
    module = _fresh(old)
    assert module is codec
    assert all(hasattr(module, name) for name in OLD_WIRE_NAMES)


@pytest.mark.parametrize("old", ["biris_hw.ros2", "biris_hw.io.ros2"])
def test_the_old_ros2_names_are_the_codecs_and_the_feeds(old: str) -> None:
    module = _fresh(old)
    for name in OLD_ROS2_NAMES:
        new = getattr(codec, name, None)
        if new is None:
            new = getattr(feed, name)
        assert getattr(module, name) is new, name
    assert set(OLD_ROS2_NAMES) <= set(module.__all__) <= set(dir(module))
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        module.nothing_here  # noqa: B018
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # imported once: no second warning
        namespace: dict[str, Any] = {}
        exec(f"from {old} import SensorFeed, scan_cloud", namespace)
    assert (namespace["SensorFeed"], namespace["scan_cloud"]) == (feed.SensorFeed, codec.scan_cloud)
