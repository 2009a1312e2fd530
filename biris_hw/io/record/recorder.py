"""Recording a sensor to MCAP: the standard ROS 2 channels, the lossless channels, metadata.

A :class:`Recorder` is a sink of the sensor's feed (:mod:`biris_hw.io.feed`: one reader per
sensor and process, which collects in batches out of step with the acquisitions and encodes each
message once, whoever else serves or shows the same sensor in the process) and writes, in the
sink's own thread, per acquisition its profile cloud, the pan/tilt transforms and the lossless
point; per completed scan, its cloud and the lossless scan; per status reading, a
DiagnosticArray (the server's status and the recorder's own drops) and the lossless status.
So the recorder adds almost nothing to the moment an acquisition reaches the other clients, and
a file being slow to write holds up neither the sensor's other clients nor the feed's other
sinks. Metadata records say what was recorded and how: ``biris`` at the start (software
version, init record, frame, whatever the caller adds: target description, scene),
``biris.recording`` at the end (counts and drops).

Nothing is dropped silently: what the recorder was too slow for is counted (by the sensor on
the feed's connections, and by the recorder's queue in the feed) and written in the file (every
``biris: recorder`` diagnostic and the end record) and in :class:`RecordSummary`. The file is
valid however the run ends (see :mod:`biris_hw.io.record.mcapfile`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from types import TracebackType

from biris_hw._version import __version__
from biris_hw.data import Scan
from biris_hw.geometry import Frame, Mount
from biris_hw.io import codec, feed
from biris_hw.io.record.mcapfile import CHUNK_SIZE, McapFile, RecordError
from biris_hw.sensor import Sensor

__all__ = [
    "RAW_POINT_TOPIC",
    "RAW_SCAN_TOPIC",
    "RAW_STATUS_TOPIC",
    "RecordSummary",
    "Recorder",
    "write_scans",
]

RAW_SCAN_TOPIC = codec.RAW_SCAN_TOPIC
RAW_POINT_TOPIC = codec.RAW_POINT_TOPIC
RAW_STATUS_TOPIC = codec.RAW_STATUS_TOPIC

FLUSH_S = 2.0
"""Real seconds between chunk flushes, so a crash (not Ctrl-C: that closes properly) loses at
most this much; at full rate a chunk fills sooner and is written anyway."""

_WRITTEN = (codec.POINT_CLOUD2, codec.TF_MESSAGE, codec.DIAGNOSTIC_ARRAY, codec.SCAN, codec.POINT)
"""Every type a recording holds (besides the status, warmed with them)."""


def _write(file: McapFile, message: codec.Encoded) -> None:
    if not file.write(
        message.topic,
        message.msgtype,
        codec.schema_text(message.msgtype),
        message.data,
        message.log_time_ns,
    ):
        assert file.error is not None
        raise file.error


def _warm() -> None:
    """Build the typestore, the schema texts and rosbags' generated encoders now.

    Together they take a few tenths of a second of interpreter time on first use; done in the
    feed's first batch, that landed just as the caller began its first scan and delayed the
    server seeing BIRIS start it (a short scan then lost its acquisitions). Cached for the
    process, so this costs nothing the second time.
    """
    for msgtype in (*_WRITTEN, codec.STATUS):
        codec.warm(msgtype)


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

    ``source`` is any :class:`biris_hw.sensor.Sensor`: a :class:`~biris_hw.BirisServer`, a
    network client's sensor, a replay. ``frame`` is the frame of the scan clouds (``"vehicle"``
    or ``"sensor"``, as ``Scan.points``); ``profiles=False`` leaves the per-acquisition profile
    clouds out (a smaller file; the lossless points stay); ``metadata`` adds string (or
    JSON-able) entries to the ``biris`` metadata record: the target description, the scene.
    ``batch_s`` is how often what the sensor queued is collected (at most: the feed collects as
    often as its most demanding sink asks); ``point_depth`` and ``scan_depth`` how much may wait
    for the recorder in the feed before it is dropped and counted (:mod:`biris_hw.io.feed`).
    The recorder does not command the sensor: it records whatever is done meanwhile.

    Raises:
        RecordError: the file cannot be written (before anything is read from the sensor); on
            leaving the block, writing failed during the run (the file stays valid).
        ConnectionClosed: the source has stopped.
    """

    def __init__(
        self,
        source: Sensor,
        path: str | os.PathLike[str],
        *,
        frame: Frame = "vehicle",
        profiles: bool = True,
        metadata: Mapping[str, object] | None = None,
        status_period_s: float = 1.0,
        batch_s: float = feed.BATCH_S,
        point_depth: int = feed.POINT_DEPTH,
        scan_depth: int = feed.SCAN_DEPTH,
        chunk_size: int = CHUNK_SIZE,
    ) -> None:
        codec.cloud_frame_id(frame)  # ValueError for a frame that is neither
        self.source = source
        self.frame: Frame = frame
        self.profiles = profiles
        self._file = McapFile(path, chunk_size=chunk_size)
        self.path = self._file.path
        self._extra = dict(metadata or {})
        topics = {
            codec.TF_TOPIC,
            codec.RAW_POINT_TOPIC,
            codec.POINTS_TOPIC,
            codec.RAW_SCAN_TOPIC,
            codec.RAW_STATUS_TOPIC,
        }
        if profiles:
            topics.add(codec.PROFILE_TOPIC)
        self._options = {
            "name": "recorder",
            "topics": topics,
            "frame": frame,
            "status_period_s": status_period_s,
            "batch_s": batch_s,
            "point_depth": point_depth,
            "scan_depth": scan_depth,
        }
        self._sink: feed.Sink | None = None
        self._failed = threading.Event()
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
        record = self.source.record
        header: dict[str, object] = {
            "software": f"biris-hw {__version__}",
            "started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "frame": self.frame,
            "cloud_frame_id": codec.cloud_frame_id(self.frame),
            "raw_topics": [RAW_SCAN_TOPIC, RAW_POINT_TOPIC, RAW_STATUS_TOPIC],
        }
        if record is not None:
            header["init_record"] = record.to_dict()
        header.update(self._extra)
        _warm()
        if not self._file.metadata("biris", _metadata_strings(header)):
            raise self._file.error or RecordError(f"cannot write {self.path}")
        self._started = time.monotonic()
        try:
            self._sink = feed.attach(self.source, self._batch, **self._options)
        except BaseException:
            self._file.close()
            raise
        return self

    @property
    def failed(self) -> threading.Event:
        """Set when recording stopped on its own (a write failure, a damaged source):
        :attr:`error` says why."""
        return self._sink.failed if self._sink is not None else self._failed

    @property
    def error(self) -> BaseException | None:
        """Why recording stopped early, or None."""
        return self._file.error or (self._sink.error if self._sink is not None else None)

    @property
    def dropped_points(self) -> int:
        """Acquisitions the recording misses so far (the sensor's drops and the feed's)."""
        return self._sink.dropped_points if self._sink is not None else 0

    @property
    def dropped_scans(self) -> int:
        return self._sink.dropped_scans if self._sink is not None else 0

    def close(self) -> RecordSummary:
        """Stop reading (what is queued is written first), write the end metadata and the
        summary, close the file; returns the summary. Idempotent."""
        if self._summary is not None:
            return self._summary
        if self._sink is not None:
            self._sink.detach()
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
            dropped_points=self.dropped_points,
            dropped_scans=self.dropped_scans,
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

    # -- what the feed hands over (the recorder's own thread, in batches) ----------------------
    def _counts(self) -> dict[str, object]:
        return {
            "points": self.points,
            "scans": self.scans,
            "statuses": self.statuses,
            "dropped_points": self.dropped_points,
            "dropped_scans": self.dropped_scans,
            "lost_messages": self._file.lost,
        }

    def _static(self, mount: Mount | None, t: float) -> None:
        if not self._static_written:
            self._static_written = True
            _write(self._file, codec.static_transforms(mount, t))

    def _batch(self, batch: feed.Batch) -> None:
        """Write one batch: the data's messages as the feed encoded them, then the status."""
        if batch.points:
            self._now = max(self._now, batch.points[-1].t)
            self._static(batch.points[0].mount, batch.points[0].t)
        for scan in batch.scans:
            self._now = max(self._now, codec.scan_time(scan))
            self._static(scan.mount, codec.scan_time(scan))
        status_messages = []
        for message in batch.messages:
            if message.topic == codec.RAW_STATUS_TOPIC:
                status_messages.append(message)  # after its diagnostics, as it was read
            else:
                _write(self._file, message)
        self.points += len(batch.points)
        for scan in batch.scans:
            self.scans += 1
            if scan.partial:
                self.partial_scans.append(_partial_name(scan))
        reading = batch.status
        if reading is not None:
            extra = {"recorder": self._counts()}
            status = reading.status
            _write(
                self._file, codec.diagnostics(status, reading.t, extra=extra, error=reading.error)
            )
            for message in status_messages:
                _write(self._file, message)
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
            t = codec.scan_time(scan)  # every message of the scan logged when it was complete
            ns = codec.stamp_ns(t)
            if first:
                _write(file, codec.static_transforms(scan.mount, t))
                first = False
            _write(file, dataclasses.replace(codec.scan_cloud(scan, frame), log_time_ns=ns))
            _write(file, codec.Encoded(RAW_SCAN_TOPIC, codec.SCAN, codec.encode_scan(scan), ns))
    finally:
        file.close()
    if file.error is not None:
        raise file.error
    return file.path
