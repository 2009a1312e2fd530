"""The lossless half of biris_hw.io.codec (the biris_msgs payloads): round trips keep every field,
and bad bytes are WireErrors."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from biris_hw.data import Direction, Point, Scan
from biris_hw.errors import BirisError, HardwareFault
from biris_hw.geometry import Mount
from biris_hw.io import codec
from biris_hw.status import ConnectionStatus, ServerState, ServerStatus


def _scan(n_acq: int = 5, samples: int = 64, **options: object) -> Scan:
    rng = np.random.default_rng(n_acq * 1000 + samples)
    fields: dict[str, object] = {
        "direction": Direction.CCW,
        "seq": 7,
        "azimuth": rng.integers(-(2**31), 2**31, n_acq, dtype=np.int32),
        "range_mm": rng.integers(-(2**15), 2**15, (n_acq, samples), dtype=np.int16),
        "closest_mm": rng.integers(-(2**15), 2**15, n_acq, dtype=np.int16),
        "intensity": rng.integers(-(2**15), 2**15, (n_acq, samples), dtype=np.int16),
        "t": rng.random(n_acq) * 1e4,
        "dropped": 3,
        "elevation": -120,
        "t_delivered": 12.5,
        "mount": Mount(offset_m=(0.1, -0.2, 0.3), head_height_m=0.75, head_offset_m=0.01),
        "acquisition": "continuous",
        "partial": True,
    }
    fields.update(options)
    return Scan(**fields)  # type: ignore[arg-type]


def assert_scans_equal(a: Scan, b: Scan) -> None:
    """Every field equal, arrays element for element with their dtypes and shapes."""
    for name in ("direction", "seq", "dropped", "elevation", "mount", "acquisition", "partial"):
        assert getattr(a, name) == getattr(b, name), name
    assert a.t_delivered == b.t_delivered or (
        a.t_delivered is not None and b.t_delivered is not None and math.isnan(a.t_delivered)
    )
    for name in ("azimuth", "range_mm", "closest_mm", "intensity", "t"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(x, y, equal_nan=name == "t"), name


def assert_points_equal(a: Point, b: Point) -> None:
    for name in ("azimuth", "range_mm", "t", "acq", "scan_seq", "elevation", "t_delivered"):
        assert getattr(a, name) == getattr(b, name), name
    assert (a.mount, a.acquisition) == (b.mount, b.acquisition)
    for name in ("profile", "intensity"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name


def test_scan_round_trip_keeps_every_field() -> None:
    scan = _scan()
    back = codec.decode_scan(codec.encode_scan(scan))
    assert_scans_equal(scan, back)
    assert not back.range_mm.flags.writeable  # still a Scan's read-only arrays


def test_scan_without_options_and_empty_scan() -> None:
    for scan in (
        _scan(t_delivered=None, mount=None, acquisition="single", partial=False),
        _scan(n_acq=0, samples=128),
    ):
        assert_scans_equal(scan, codec.decode_scan(codec.encode_scan(scan)))


@settings(max_examples=40, deadline=None)
@given(
    n_acq=st.integers(0, 40),
    samples=st.integers(0, 130),
    seq=st.integers(0, 2**64 - 1),
    dropped=st.integers(0, 2**64 - 1),
    elevation=st.integers(-(2**31), 2**31 - 1),
    direction=st.sampled_from(Direction),
    times=st.data(),
)
def test_scan_round_trip_any_shape(
    n_acq: int,
    samples: int,
    seq: int,
    dropped: int,
    elevation: int,
    direction: Direction,
    times: st.DataObject,
) -> None:
    t = times.draw(hnp.arrays(np.float64, n_acq, elements=st.floats(allow_nan=True)))
    scan = _scan(n_acq, samples, seq=seq, dropped=dropped, elevation=elevation, t=t)
    scan = Scan(**{**scan.__dict__, "direction": direction})
    assert_scans_equal(scan, codec.decode_scan(codec.encode_scan(scan)))


@settings(max_examples=30, deadline=None)
@given(
    profile=hnp.arrays(np.int16, st.integers(0, 130)),
    t=st.floats(allow_nan=False),
    t_delivered=st.one_of(st.none(), st.floats(allow_nan=False)),
    acq=st.integers(0, 2**64 - 1),
    azimuth=st.integers(-(2**31), 2**31 - 1),
)
def test_point_round_trip(
    profile: np.ndarray, t: float, t_delivered: float | None, acq: int, azimuth: int
) -> None:
    point = Point(
        azimuth=azimuth,
        range_mm=int(profile.min()) if profile.size else 0,
        profile=profile,
        intensity=profile[::-1],
        t=t,
        acq=acq,
        scan_seq=3,
        elevation=5,
        t_delivered=t_delivered,
        mount=Mount() if acq % 2 else None,
        acquisition="continuous" if acq % 3 else "single",
    )
    assert_points_equal(point, codec.decode_point(codec.encode_point(point)))


def test_status_round_trip() -> None:
    latency = {
        "count": 2,
        "mean": 0.01,
        "max": 0.02,
        "p50": 0.01,
        "p99": 0.02,
        "histogram": [[0.001, 0.002, 1], [0.5, math.inf, 1]],
    }
    status = ServerStatus(
        state=ServerState.FAULT,
        fault="bus",
        azimuth=-1024,
        elevation=12,
        calibration=None,
        continuous=True,
        acquisition="continuous",
        ring="live",
        counters={"scans": 4, "acquisitions_read": 100},
        connections={
            3: ConnectionStatus("DATA", "every_buffer", 8, 1, 9, 2, latency),
            4: ConnectionStatus("NORMAL", "latest", 1, 0, 0, 0, {"count": 0}),
        },
        interrupts={"data": 9},
        azimuth_live=None,
        elevation_live=7,
        acquisitions_in_progress=5,
        acquisition_pending="continuous",
        tasks_down=("az_scan_start", "biris_cmd_notifier"),
        task_failures={"az_scan_start": 2, "biris_cmd_notifier": 1},
    )
    back = codec.decode_status(codec.encode_status(status, t=3.25))
    assert back.tasks_down == status.tasks_down
    assert dict(back.task_failures) == dict(status.task_failures)
    assert back.state_name == "fault:bus" and back["state"] == "fault:bus"
    for name in ("azimuth", "elevation", "calibration", "continuous", "acquisition", "ring"):
        assert back[name] == status[name], name
    assert dict(back.counters) == dict(status.counters)
    assert dict(back.interrupts) == {"data": 9}
    assert (back.azimuth_live, back.elevation_live) == (None, 7)
    assert back.acquisitions_in_progress == 5 and back.acquisition_pending == "continuous"
    assert back.connections[3].latency == latency
    assert dict(back.connections[3]) | {"latency": None} == dict(status.connections[3]) | {
        "latency": None
    }
    assert back.connections[4].latency["mean"] is None


def test_fault_round_trip() -> None:
    back = codec.decode_fault(codec.encode_fault(HardwareFault("parity", "PERR on level 2"), t=1.0))
    assert (back.kind, back.message) == ("parity", "PERR on level 2")


def test_definitions_are_registered_and_complete() -> None:
    store = codec.typestore()
    for msgtype in codec.MSG_DEFINITIONS:
        assert msgtype in store.types
        text = codec.full_definition(msgtype)
        assert text.startswith(codec.MSG_DEFINITIONS[msgtype].splitlines()[1][:0])
    assert "MSG: std_msgs/Header" in codec.full_definition(codec.SCAN)
    assert codec.typestore() is store  # cached


@pytest.mark.parametrize(
    ("decode", "payload"),
    [
        (codec.decode_scan, b""),
        (codec.decode_scan, b"\x00\x01\x00\x00"),
        (codec.decode_scan, b"\x07\x07\x00\x00" + bytes(64)),
        (codec.decode_scan, b"\x00\x01\x00\x00" + b"\xff" * 64),
        (codec.decode_point, b"\x00\x01\x00\x00" + bytes(3)),
        (codec.decode_status, b"garbage"),
        (codec.decode_fault, b"\x00\x01\x00\x00" + bytes(40)),
    ],
)
def test_malformed_bytes_are_wire_errors(decode: object, payload: bytes) -> None:
    with pytest.raises(codec.WireError):
        decode(payload)  # type: ignore[operator]


def test_truncated_extended_and_wrong_type_are_wire_errors() -> None:
    data = codec.encode_scan(_scan())
    for cut in (1, 5, 17, len(data) // 2, len(data) - 4):
        with pytest.raises(codec.WireError):
            codec.decode_scan(data[:cut])
    with pytest.raises(codec.WireError):
        codec.decode_scan(data + bytes(16))
    with pytest.raises(codec.WireError):
        codec.decode_point(data)
    point = codec.encode_point(Point(0, 0, np.zeros(4, np.int16), np.zeros(4, np.int16), 0.0, 0, 0))
    with pytest.raises(codec.WireError):
        codec.decode_scan(point)
    assert issubclass(codec.WireError, BirisError) and issubclass(codec.WireError, ValueError)


def test_inconsistent_shapes_and_values_are_wire_errors() -> None:
    store = codec.typestore()
    msg: Any = store.deserialize_cdr(codec.encode_scan(_scan()), codec.SCAN)
    msg.samples += 1  # the grid no longer adds up
    with pytest.raises(codec.WireError, match="samples"):
        codec.decode_scan(bytes(store.serialize_cdr(msg, codec.SCAN)))
    msg = store.deserialize_cdr(codec.encode_scan(_scan()), codec.SCAN)
    msg.acquisition = "sometimes"
    with pytest.raises(codec.WireError, match="acquisition"):
        codec.decode_scan(bytes(store.serialize_cdr(msg, codec.SCAN)))
    msg.acquisition, msg.direction = "single", 9
    with pytest.raises(codec.WireError):
        codec.decode_scan(bytes(store.serialize_cdr(msg, codec.SCAN)))


def test_oversized_payload_refused_before_parsing(monkeypatch: pytest.MonkeyPatch) -> None:
    data = codec.encode_scan(_scan(n_acq=50, samples=128))
    monkeypatch.setattr(codec, "MAX_PAYLOAD", len(data) - 1)
    with pytest.raises(codec.WireError, match="exceeds"):
        codec.decode_scan(data)
    with pytest.raises(codec.WireError):
        codec.decode_scan("not bytes")  # type: ignore[arg-type]


def test_values_outside_the_wire_types_are_wire_errors() -> None:
    with pytest.raises(codec.WireError):
        codec.encode_scan(_scan(seq=2**64))
    with pytest.raises(codec.WireError):
        codec.encode_scan("scan")  # type: ignore[arg-type]
