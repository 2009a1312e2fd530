"""Recording to MCAP: read back by independent readers, standard schemas, failures kept valid."""

from __future__ import annotations

import errno
import functools
import io
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from biris_hw import BirisInitRecord, BirisServer, ConnectionKind, DeliveryPolicy
from biris_hw.data import Scan
from biris_hw.io import codec as ros2
from biris_hw.io import codec as wire
from biris_hw.io.feed import SensorFeed
from biris_hw.io.record import Recorder, RecordError, mcapfile, write_scans
from biris_hw.io.record.replay import ReplayServer
from sim import Scene, SimulatedBiris
from tests.test_record_support import (
    assert_same_scan,
    cloud_xyz,
    read_decoded,
    synthetic_scans,
    write_raw,
)


@functools.cache
def standard() -> Typestore:
    """rosbags' own ROS 2 Humble typestore, as a stranger's reader holds it (built on first use, not
    at collection, where it cost every test worker a fifth of a second)."""
    return get_typestore(Stores.ROS2_HUMBLE)


WAIT = 10.0


def _schemas(path: Path) -> dict[str, tuple[str, str, bytes]]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return {
        c.topic: (
            summary.schemas[c.schema_id].name,
            c.message_encoding,
            summary.schemas[c.schema_id].data,
        )
        for c in summary.channels.values()
    }


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    with open(path, "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}


def test_recording_a_sweeping_sensor_reads_back_everywhere(tmp_path: Path) -> None:
    """Record live sweeps; mcap + mcap-ros2-support and rosbags decode every message; clouds
    equal Scan.points() to float32; the lossless scans equal what a client received.

    On virtual time: the recorder's feed is a plain thread, outside the domain, but it only
    polls the server (``timeout=0``) and asks for its status, never waiting for time to pass,
    and the rig runs only while this thread waits for its own scans: the feed, draining again
    after the stop, sees every one of them (a few dozen acquisitions, far from its queue's
    depth), whenever its real-time batches fall."""
    out = tmp_path / "run.mcap"
    received: list[Scan] = []
    with SimulatedBiris(
        scene=Scene.circle(2.0), samples=64, time_scale=30.0, seed=5, clock="virtual"
    ) as rig:
        rig.start()
        with BirisServer(rig.hardware, BirisInitRecord()) as server:
            data = server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=16)
            conn = server.open()
            with Recorder(
                server, out, metadata={"scene": repr(rig.scene)}, status_period_s=0.05
            ) as recorder:
                conn.continuous_scan(-15.0, 15.0)
                while sum(1 for s in received if s.n_acq) < 2:
                    received.append(data.ready_for_data(timeout=WAIT))
                conn.stop_scan()
                conn.wait_idle(timeout=WAIT)
                while len(received) < server.status()["counters"]["scans"]:
                    received.append(data.ready_for_data(timeout=WAIT))
            conn.close()
            data.close()
    summary = recorder.summary
    assert summary is not None and summary.complete and summary.error is None
    assert summary.dropped == 0 and summary.scans == len(received)

    schemas = _schemas(out)
    for topic in ("/biris/points", "/biris/profile", "/tf", "/tf_static", "/diagnostics"):
        name, encoding, text = schemas[topic]
        assert name == ros2.TOPICS[topic] and encoding == "cdr"
        assert text.decode() == standard().generate_msgdef(name, ros_version=2)[0]
    assert schemas["/biris/raw/scan"][0] == wire.SCAN

    messages = read_decoded(out)
    raw_scans = [wire.decode_scan(m[3]) for m in messages if m[0] == "/biris/raw/scan"]
    clouds = [m for m in messages if m[0] == "/biris/points"]
    assert len(raw_scans) == len(clouds) == len(received)
    for scan, got, (_t, _n, decoded, cdr) in zip(raw_scans, received, clouds, strict=False):
        assert_same_scan(scan, got)
        np.testing.assert_allclose(cloud_xyz(decoded), got.points(), rtol=1e-6, atol=1e-6)
        again = standard().deserialize_cdr(cdr, ros2.POINT_CLOUD2)  # the second reader
        np.testing.assert_array_equal(cloud_xyz(again), cloud_xyz(decoded))
    acquisitions = sum(s.n_acq for s in received)
    for topic in ("/biris/profile", "/tf", "/biris/raw/point"):
        assert sum(1 for m in messages if m[0] == topic) >= acquisitions
    diagnostics = [m[2] for m in messages if m[0] == "/diagnostics"]
    assert diagnostics and diagnostics[-1].status[0].name == "server"
    meta = _metadata(out)
    assert meta["biris"]["software"].startswith("biris-hw ")
    assert "init_record" in meta["biris"] and meta["biris"]["scene"].startswith("Scene(")
    assert meta["biris.recording"]["dropped_points"] == "0"
    assert int(meta["biris.recording"]["scans"]) == len(received)


class _Untouchable:
    def open(self, *args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the sensor was touched")

    def status(self) -> Any:
        raise AssertionError("the sensor was touched")


def test_unwritable_path_is_an_error_before_the_sensor_is_touched(tmp_path: Path) -> None:
    for bad in (tmp_path / "missing" / "x.mcap", tmp_path):
        with pytest.raises(RecordError, match="cannot write"):
            Recorder(_Untouchable(), bad)
    assert list(tmp_path.iterdir()) == []


def _replay_source(tmp_path: Path, n: int = 6) -> ReplayServer:
    return ReplayServer(
        write_raw(tmp_path / "source.mcap", synthetic_scans(n)), speed=None, autostart=False
    )


def test_ctrl_c_leaves_a_complete_file(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    source = _replay_source(tmp_path)
    with source, pytest.raises(KeyboardInterrupt), Recorder(source, out) as recorder:
        source.start()
        assert source.wait_done(WAIT)
        raise KeyboardInterrupt
    summary = recorder.summary
    assert summary is not None and summary.complete and summary.scans == 6
    with open(out, "rb") as f:
        assert make_reader(f).get_summary() is not None  # the summary section was written
    assert _metadata(out)["biris.recording"]["scans"] == "6"
    replayed = ReplayServer(out, speed=None)
    with replayed:
        data = replayed.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        got = [data.ready_for_data(timeout=WAIT) for _ in range(6)]
    for a, b in zip(got, synthetic_scans(6), strict=False):
        assert_same_scan(a, b)


def _full_disk(limit: int) -> Any:
    def opener(path: Path) -> io.BufferedWriter:
        class Full(io.FileIO):
            def write(self, data: Any) -> int:
                view = memoryview(data).cast("B")
                room = limit - self.tell()
                if len(view) > room:
                    super().write(view[: max(room, 0)])
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                return int(super().write(view))

        return io.BufferedWriter(Full(path, "wb"))

    return opener


def test_full_disk_stops_with_an_error_and_a_valid_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(mcapfile, "_open_stream", _full_disk(60_000))
    out = tmp_path / "run.mcap"
    with _replay_source(tmp_path, 12) as source:
        recorder = Recorder(source, out, chunk_size=8_000)
        with pytest.raises(RecordError, match="No space left") as caught, recorder:
            source.start()
            assert recorder.failed.wait(WAIT)
    assert caught.value.errno == errno.ENOSPC
    summary = recorder.summary
    assert summary is not None and not summary.complete and summary.error
    assert 0 < out.stat().st_size <= 60_000
    with open(out, "rb") as f:  # valid: every message up to the cut decodes
        reader = make_reader(f)
        assert reader.get_summary() is None
        kept = list(reader.iter_messages())
    assert kept and len(kept) == summary.messages
    for _schema, channel, message in kept:
        if channel.topic == "/biris/raw/scan":
            wire.decode_scan(message.data)


def test_write_scans_for_scan_save(tmp_path: Path) -> None:
    scans = synthetic_scans(3)
    path = write_scans(tmp_path / "scans.mcap", scans, frame="sensor")
    clouds = read_decoded(path, ["/biris/points"])
    for scan, (_t, _n, decoded, _c) in zip(scans, clouds, strict=False):
        assert decoded.header.frame_id == ros2.BASE_FRAME
        np.testing.assert_allclose(cloud_xyz(decoded), scan.points("sensor"), atol=1e-5)
    with ReplayServer(path, speed=None) as replay:
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        for scan in scans:
            assert_same_scan(data.ready_for_data(timeout=WAIT), scan)


def test_feed_keeps_the_callback_error(tmp_path: Path) -> None:
    with _replay_source(tmp_path, 2) as source:
        failed = threading.Event()

        def boom(_scans: list[Scan]) -> None:
            failed.set()
            raise ValueError("callback broke")

        feed = SensorFeed(source, on_scans=boom).start()
        source.start()
        assert feed.failed.wait(WAIT) and failed.is_set()
        feed.stop()
        assert isinstance(feed.error, ValueError)


def test_close_wakes_the_feed_at_once_and_writes_what_waits(tmp_path: Path) -> None:
    """With a batch period and a status period of a minute, close() still returns at once
    (the feed waits on an event, not a timer) and what the sensor had queued is written."""
    out = tmp_path / "run.mcap"
    with _replay_source(tmp_path, 6) as source:
        recorder = Recorder(source, out, batch_s=60.0, status_period_s=60.0).start()
        source.start()
        assert source.wait_done(WAIT)
        begun = time.monotonic()
        summary = recorder.close()
        took = time.monotonic() - begun
    assert took < 5.0, took  # a timer would have taken 60 s
    assert summary.complete and summary.scans == 6 and summary.points == 6 * 12
    assert summary.dropped == 0
