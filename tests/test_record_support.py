"""Helpers shared by the recording, replay and live-view tests (no tests here).

Synthetic scans and points (seeded, with a mount and an elevation so every transform matters),
a file of them written the way the recorder writes its lossless channels, and independent
readers: the ``mcap`` reader with ``mcap-ros2-support``'s decoder (which parses the schema text
in the file) and rosbags' CDR deserialiser.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from biris_hw.data import Direction, Point, Scan
from biris_hw.geometry import Mount
from biris_hw.io import codec
from biris_hw.io.record import RAW_POINT_TOPIC, RAW_SCAN_TOPIC
from biris_hw.io.record.mcapfile import McapFile

MOUNT = Mount(offset_m=(0.3, -0.1, 0.2), head_height_m=0.5, head_offset_m=0.05)
PERIOD = 1 / 30


def synthetic_scans(n: int = 4, n_acq: int = 12, samples: int = 64, seed: int = 3) -> list[Scan]:
    """Alternating sweeps with random ranges (some no-returns), times increasing."""
    rng = np.random.default_rng(seed)
    scans = []
    t = 10.0
    for k in range(n):
        direction = Direction.CCW if k % 2 else Direction.CW
        az = np.linspace(-200, 200, n_acq).astype(np.int32) * direction.sign
        rng_mm = rng.integers(500, 4000, size=(n_acq, samples)).astype(np.int16)
        rng_mm[rng.random((n_acq, samples)) < 0.2] = 0
        times = t + PERIOD * np.arange(n_acq)
        t = float(times[-1]) + 0.3
        scans.append(
            Scan(
                direction=direction,
                seq=k // 2 + 1,
                azimuth=az,
                range_mm=rng_mm,
                closest_mm=rng_mm.max(axis=1),
                intensity=rng.integers(0, 255, size=(n_acq, samples)).astype(np.int16),
                t=times,
                dropped=k,
                elevation=40,
                t_delivered=t - 0.2,
                mount=MOUNT,
            )
        )
    return scans


def points_of(scan: Scan) -> list[Point]:
    """The scan's acquisitions as the points a DATA EVERY_ACQUISITION connection gets, each
    handed over 10 ms after its acquisition."""
    return [dataclasses.replace(p, t_delivered=p.t + 0.01) for p in scan.as_points()]


def write_raw(path: Path, scans: list[Scan], chunk_size: int = 1 << 20) -> Path:
    """A file with the lossless scan and point channels, as the recorder writes them."""
    file = McapFile(path, chunk_size=chunk_size)
    for scan in scans:
        for point in points_of(scan):
            data = codec.encode_point(point)
            file.write(
                RAW_POINT_TOPIC,
                codec.POINT,
                codec.full_definition(codec.POINT),
                data,
                round(point.t * 1e9),
            )
        assert scan.t_delivered is not None
        file.write(
            RAW_SCAN_TOPIC,
            codec.SCAN,
            codec.full_definition(codec.SCAN),
            codec.encode_scan(scan),
            round(scan.t_delivered * 1e9),
        )
    assert file.close()
    return path


def damaged_recording(path: Path, scans: list[Scan]) -> Path:
    """A recording of ``scans`` in small chunks whose last chunk is overwritten in its middle
    (a bad sector, a bad copy): the summary still reads, the damage shows while playing."""
    from mcap.reader import make_reader

    write_raw(path, scans, chunk_size=4096)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 2
    last = max(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = bytearray(path.read_bytes())
    middle = last.chunk_start_offset + last.chunk_length // 2
    data[middle : middle + 64] = b"\xff" * 64
    path.write_bytes(bytes(data))
    return path


def read_decoded(path: Path, topics: list[str] | None = None) -> list[tuple[str, str, Any, bytes]]:
    """(topic, schema name, message decoded by mcap-ros2-support, raw CDR) for every message."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(
            topics=topics, log_time_order=True
        ):
            assert schema is not None
            out.append((channel.topic, schema.name, decoded, bytes(message.data)))
    return out


def cloud_xyz(msg: Any) -> np.ndarray:
    """x, y, z of a decoded PointCloud2 (any decoder's), read through its own field table."""
    offsets = {f.name: f.offset for f in msg.fields}
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(-1, msg.point_step)
    cols = [data[:, offsets[k] : offsets[k] + 4].copy().view("<f4")[:, 0] for k in "xyz"]
    return np.stack(cols, axis=1).astype(np.float64)


def assert_same_scan(a: Scan, b: Scan) -> None:
    assert (a.direction, a.seq, a.dropped, a.elevation) == (
        b.direction,
        b.seq,
        b.dropped,
        b.elevation,
    )
    for key in ("azimuth", "range_mm", "closest_mm", "intensity", "t"):
        got, want = getattr(a, key), getattr(b, key)
        assert got.dtype == want.dtype and np.array_equal(got, want), key
    assert a.mount == b.mount and a.acquisition == b.acquisition and a.partial == b.partial
