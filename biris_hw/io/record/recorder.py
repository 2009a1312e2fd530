"""Recording a sensor to MCAP: the standard ROS 2 channels, the lossless channels, metadata.

A :class:`Recorder` reads a sensor through the client API (:class:`~biris_hw.io.ros2.SensorFeed`:
one DATA connection for every acquisition, one for every completed scan, the status at a
period, collected in batches by one thread that also encodes and writes them, so the
recorder adds almost nothing to the moment an acquisition reaches the other clients) and
writes, per acquisition, its profile cloud, the pan/tilt transforms and the lossless
point; per completed scan, its cloud and the lossless scan; per status poll, a DiagnosticArray
(the server's status and the recorder's own drops) and the lossless status. Metadata records say
what was recorded and how: ``biris`` at the start (software version, init record, frame,
whatever the caller adds: target description, scene), ``biris.recording`` at the end (counts
and drops).

Nothing is dropped silently: what the recorder was too slow for is counted by the server on its
connections and written in the file (every ``biris: recorder`` diagnostic and the end record)
and in :class:`RecordSummary`. The file is valid however the run ends (see
:mod:`biris_hw.io.record.mcapfile`).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

from biris_hw._version import __version__
from biris_hw.data import Point, Scan
from biris_hw.geometry import Frame, Mount
from biris_hw.io import ros2, wire
from biris_hw.io.record.mcapfile import CHUNK_SIZE, McapFile, RecordError
from biris_hw.status import ServerStatus

__all__ = [
    "RAW_POINT_TOPIC",
    "RAW_SCAN_TOPIC",
    "RAW_STATUS_TOPIC",
    "RecordSummary",
    "Recorder",
    "write_scans",
]

RAW_SCAN_TOPIC = ros2.RAW_SCAN_TOPIC
RAW_POINT_TOPIC = ros2.RAW_POINT_TOPIC
RAW_STATUS_TOPIC = ros2.RAW_STATUS_TOPIC

FLUSH_S = 2.0
"""Real seconds between chunk flushes, so a crash (not Ctrl-C: that closes properly) loses at
most this much; at full rate a chunk fills sooner and is written anyway."""


def _raw(topic: str, msgtype: str, data: bytes, log_time_ns: int) -> ros2.Encoded:
    return ros2.Encoded(topic, msgtype, data, log_time_ns)


def _definition(msgtype: str) -> str:
    if msgtype.startswith("biris_msgs/"):
        return wire.full_definition(msgtype)
    return ros2.schema_text(msgtype)


def _write(file: McapFile, message: ros2.Encoded, log_time_ns: int | None = None) -> None:
    t = message.log_time_ns if log_time_ns is None else log_time_ns
    if not file.write(
        message.topic, message.msgtype, _definition(message.msgtype), message.data, t
    ):
        assert file.error is not None
        raise file.error


def _warm() -> None:
    """Build the type stores, the schema texts and rosbags' generated encoders now.

    Together they take a few tenths of a second of interpreter time on first use; done in the
    feed's first batch, that landed just as the caller began its first scan and delayed the
    server seeing BIRIS start it (a short scan then lost its acquisitions). Cached for the
    process, so this costs nothing the second time.
    """
    for msgtype in {*ros2.TOPICS.values(), wire.SCAN, wire.POINT, wire.STATUS}:
        _definition(msgtype)
    ros2.diagnostics(None, 0.0, error="warming up")
    ros2.static_transforms(None)
    profile = np.zeros(1, dtype=np.int16)
    wire.encode_point(Point(0, 0, profile, profile, 0.0, 0, 0))


def _scan_time(scan: Scan) -> int:
    """When the scan was complete (its hand-over), for its messages' log time."""
    if scan.t_delivered is not None:
        return ros2.stamp_ns(scan.t_delivered)
    return ros2.stamp_ns(float(scan.t[-1]) if scan.n_acq else 0.0)


def _metadata_strings(values: Mapping[str, object]) -> dict[str, str]:
    return {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in values.items()}


@dataclass(frozen=True)
class RecordSummary:
    """What a recording holds, and what it missed."""

    path: Path
    complete: bool
    """The MCAP summary was written (False after a write failure: still a valid file)."""
    messages: int
    points: int
    scans: int
    statuses: int
    dropped_points: int
    """Acquisitions the recorder's connection missed (server-counted: too slow, or lost)."""
    dropped_scans: int
    lost_messages: int
    """Messages handed to the file that never reached the disk (a write failure)."""
    bytes: int
    seconds: float
    error: str | None = None
    partial_scans: tuple[str, ...] = ()
    """The partial scans recorded, each named with its reason when it has one (``"CW #1
    (partial: ended 312 counts (27.4 deg) short of its destination -2048)"``): a recording of
    short sweeps says so where the person who made it looks."""

    @property
    def dropped(self) -> int:
        """Everything that is not in the file: drops and lost messages."""
        return self.dropped_points + self.dropped_scans + self.lost_messages

    def __str__(self) -> str:
        text = (
            f"{self.path}: {self.scans} scans, {self.points} acquisitions, {self.statuses} "
            f"status records in {self.seconds:.1f} s, {self.bytes / 1e6:.2f} MB; dropped "
            f"{self.dropped_points} acquisitions and {self.dropped_scans} scans"
        )
        if self.lost_messages:
            text += f", {self.lost_messages} messages lost"
        if self.partial_scans:
            n = len(self.partial_scans)
            text += f"; {n} partial scan{'s' if n > 1 else ''}: " + ", ".join(self.partial_scans)
        if not self.complete:
            text += " (no summary: file cut short, still valid)"
        return text


class Recorder:
    """Record everything a sensor produces, while the ``with`` block runs, into an MCAP file.

    ``source`` is a :class:`~biris_hw.BirisServer`, a network client's sensor, or anything with
    ``open`` and ``status`` (:class:`~biris_hw.io.ros2.SensorSource`). ``frame`` is the frame of the
    scan clouds (``"vehicle"`` or ``"sensor"``, as ``Scan.points``); ``profiles=False`` leaves
    the per-acquisition profile clouds out (a smaller file; the lossless points stay);
    ``metadata`` adds string (or JSON-able) entries to the ``biris`` metadata record: the target
    description, the scene. ``batch_s`` is how often what the sensor queued is collected and
    written (:class:`~biris_hw.io.ros2.SensorFeed`). The recorder does not command the sensor: it
    records whatever is done meanwhile.

    Raises:
        RecordError: the file cannot be written (before anything is read from the sensor); on
            leaving the block, writing failed during the run (the file stays valid).
        ConnectionClosed: the source has stopped.
    """

    def __init__(
        self,
        source: ros2.SensorSource,
        path: str | os.PathLike[str],
        *,
        frame: Frame = "vehicle",
        profiles: bool = True,
        metadata: Mapping[str, object] | None = None,
        status_period_s: float = 1.0,
        batch_s: float = ros2.BATCH_S,
        point_depth: int = 4096,
        scan_depth: int = 256,
        chunk_size: int = CHUNK_SIZE,
    ) -> None:
        ros2.cloud_frame_id(frame)  # ValueError for a frame that is neither
        self.source = source
        self.frame: Frame = frame
        self.profiles = profiles
        self._file = McapFile(path, chunk_size=chunk_size)
        self.path = self._file.path
        self._extra = dict(metadata or {})
        self._feed = ros2.SensorFeed(
            source,
            on_points=self._points,
            on_scans=self._scans,
            on_status=self._status,
            status_period_s=status_period_s,
            batch_s=batch_s,
            point_depth=point_depth,
            scan_depth=scan_depth,
        )
        self._now = 0.0
        self._static_written = False
        self._last_flush = time.monotonic()
        self._started = 0.0
        self._stopped: float | None = None
        self.points = 0
        self.scans = 0
        self.statuses = 0
        self.partial_scans: list[str] = []
        """Each partial scan recorded so far, named with its reason (see RecordSummary)."""
        self._summary: RecordSummary | None = None

    # -- the run ---------------------------------------------------------------------------------
    def start(self) -> Recorder:
        """Write the start metadata and begin reading (``with`` does this)."""
        record = getattr(self.source, "record", None)
        header: dict[str, object] = {
            "software": f"biris-hw {__version__}",
            "started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "frame": self.frame,
            "cloud_frame_id": ros2.cloud_frame_id(self.frame),
            "raw_topics": [RAW_SCAN_TOPIC, RAW_POINT_TOPIC, RAW_STATUS_TOPIC],
        }
        if record is not None and hasattr(record, "to_dict"):
            header["init_record"] = record.to_dict()
        header.update(self._extra)
        _warm()
        if not self._file.metadata("biris", _metadata_strings(header)):
            raise self._file.error or RecordError(f"cannot write {self.path}")
        self._started = time.monotonic()
        try:
            self._feed.start()
        except BaseException:
            self._file.close()
            raise
        return self

    @property
    def failed(self) -> threading.Event:
        """Set when recording stopped on its own (a write failure): :attr:`error` says why."""
        return self._feed.failed

    @property
    def error(self) -> BaseException | None:
        """Why recording stopped early, or None."""
        return self._file.error or self._feed.error

    def close(self) -> RecordSummary:
        """Stop reading (what is queued is written first), write the end metadata and the
        summary, close the file; returns the summary. Idempotent."""
        if self._summary is not None:
            return self._summary
        self._feed.stop()
        self._stopped = time.monotonic()
        self._file.metadata("biris.recording", _metadata_strings(self._counts()))
        self._file.close()
        error = self.error
        self._summary = RecordSummary(
            path=self.path,
            complete=self._file.complete,
            messages=self._file.messages - self._file.lost,
            points=self.points,
            scans=self.scans,
            statuses=self.statuses,
            dropped_points=self._feed.dropped_points,
            dropped_scans=self._feed.dropped_scans,
            lost_messages=self._file.lost,
            bytes=self.path.stat().st_size if self.path.exists() else 0,
            seconds=self._stopped - self._started if self._started else 0.0,
            error=None if error is None else str(error),
            partial_scans=tuple(self.partial_scans),
        )
        return self._summary

    @property
    def summary(self) -> RecordSummary | None:
        """The summary, once closed."""
        return self._summary

    def __enter__(self) -> Recorder:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
        error = self.error
        if exc is None and error is not None:
            raise error

    # -- what the feed hands over (its one thread, in batches) -------------------------------
    def _counts(self) -> dict[str, object]:
        return {
            "points": self.points,
            "scans": self.scans,
            "statuses": self.statuses,
            "dropped_points": self._feed.dropped_points,
            "dropped_scans": self._feed.dropped_scans,
            "lost_messages": self._file.lost,
        }

    def _static(self, mount: Mount | None, t: float) -> None:
        if not self._static_written:
            self._static_written = True
            _write(self._file, ros2.static_transforms(mount, t))

    def _points(self, points: list[Point]) -> None:
        self._now = max(self._now, points[-1].t)
        self._static(points[0].mount, points[0].t)
        clouds = ros2.profile_clouds(points) if self.profiles else None
        for i, point in enumerate(points):
            if clouds is not None:
                _write(self._file, clouds[i])
            tf = ros2.transforms(point)
            _write(self._file, tf)
            raw = wire.encode_point(point)
            _write(self._file, _raw(RAW_POINT_TOPIC, wire.POINT, raw, tf.log_time_ns))
        self.points += len(points)

    def _scans(self, scans: list[Scan]) -> None:
        for scan in scans:
            t = _scan_time(scan)
            self._now = max(self._now, t / 1e9)
            self._static(scan.mount, t / 1e9)
            _write(self._file, ros2.scan_cloud(scan, self.frame), t)
            _write(self._file, _raw(RAW_SCAN_TOPIC, wire.SCAN, wire.encode_scan(scan), t))
            self.scans += 1
            if scan.partial:
                self.partial_scans.append(_partial_name(scan))

    def _status(self, status: Mapping[str, Any] | None, error: str | None) -> None:
        t = ros2.sensor_time(self.source, self._now)
        extra = {"recorder": self._counts()}
        _write(self._file, ros2.diagnostics(status, t, extra=extra, error=error))
        if isinstance(status, ServerStatus):
            data = wire.encode_status(status, t)
            _write(self._file, _raw(RAW_STATUS_TOPIC, wire.STATUS, data, ros2.stamp_ns(t)))
        self.statuses += 1
        if time.monotonic() - self._last_flush > FLUSH_S:
            self._last_flush = time.monotonic()
            if not self._file.flush():
                raise self._file.error or RecordError(f"cannot write {self.path}")


def _partial_name(scan: Scan) -> str:
    """``CW #1 (partial: why)``: a partial scan named for a summary line, with its reason when
    the data give one."""
    why = f": {scan.partial_reason}" if scan.partial_reason else ""
    return f"{scan.direction.name} #{scan.seq} (partial{why})"


def write_scans(
    path: str | os.PathLike[str],
    scans: Iterable[Scan],
    *,
    frame: Frame = "vehicle",
    metadata: Mapping[str, object] | None = None,
) -> Path:
    """Write scans to an MCAP file (``biris scan --save x.mcap``): per scan its cloud on
    ``/biris/points`` and the lossless scan, plus ``/tf_static`` and the ``biris`` metadata;
    :class:`~biris_hw.io.record.ReplayServer` serves them back equal. Returns the path.

    Raises:
        RecordError: the file cannot be written (it stays a valid MCAP file if it was begun).
    """
    file = McapFile(path)
    try:
        header = {"software": f"biris-hw {__version__}", "frame": frame, **(metadata or {})}
        file.metadata("biris", _metadata_strings(header))
        first = True
        for scan in scans:
            t = _scan_time(scan)
            if first:
                _write(file, ros2.static_transforms(scan.mount, t / 1e9))
                first = False
            _write(file, ros2.scan_cloud(scan, frame), t)
            _write(file, _raw(RAW_SCAN_TOPIC, wire.SCAN, wire.encode_scan(scan), t))
    finally:
        file.close()
    if file.error is not None:
        raise file.error
    return file.path
