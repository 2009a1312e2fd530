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
``biris.recording`` at the end (counts and drops, what close() had no time to write, the spans
without the network).

Nothing is dropped silently: what the recorder was too slow for is counted (by the sensor on
the feed's connections, by the recorder's queue in the feed, and what was left in that queue
when :meth:`Recorder.close` could wait no longer) and written in the file (every ``biris:
recorder`` diagnostic and the end record) and in :class:`RecordSummary`; a span without the
network to a remote sensor is named in both. The file is valid however the run ends (see
:mod:`biris_hw.io.record.mcapfile`); a recorder killed outright leaves a file without a footer,
which :class:`~biris_hw.io.record.ReplayServer` plays up to its last complete chunk (at most
:data:`FLUSH_S` of data, or a chunk, lost). ``close()`` returns within :data:`CLOSE_TIMEOUT_S`
whatever the backlog, and an unclosed Recorder is closed when it is collected or at exit.

On a moving robot (``poses=``, and ``grid=``, ``proximity=``) the recording also carries the
vehicle's ``/odom``, ``odom -> vehicle`` on ``/tf``, ``/biris/points`` in ``odom`` (each scan
deskewed), the certainty grid on ``/biris/grid`` and the proximity alarm's answers on
``/biris/proximity``, made by a
:class:`~biris_hw.io.moving_sink.MovingEncoder` in the sink's thread; acquisitions without a
pose are counted in the summary and the end record.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import math
import os
import threading
import time
import weakref
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from types import TracebackType

from biris_hw._version import __version__
from biris_hw.data import Scan
from biris_hw.geometry import Frame, Mount
from biris_hw.io import codec, feed
from biris_hw.io.moving_sink import (
    GridOption,
    MovingEncoder,
    PoseFeed,
    ProximityOption,
    moving_encoder,
)
from biris_hw.io.record.mcapfile import CHUNK_SIZE, McapFile, RecordError
from biris_hw.sensor import Sensor

__all__ = [
    "CLOSE_TIMEOUT_S",
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

log = logging.getLogger(__name__)

CLOSE_TIMEOUT_S = 10.0
"""Real seconds :meth:`Recorder.close` takes at most, whatever the backlog: the first half
writes what waits for the recorder (the rest is dropped and counted), the second finishes the
file."""

FLUSH_S = 2.0
"""Real seconds between chunk flushes, so a crash (not Ctrl-C: that closes properly) loses at
most this much; at full rate a chunk fills sooner and is written anyway."""

_WRITTEN = (codec.POINT_CLOUD2, codec.TF_MESSAGE, codec.DIAGNOSTIC_ARRAY, codec.SCAN, codec.POINT)
"""Every type a recording holds (besides the status, warmed with them)."""


def _write(file: McapFile, message: codec.Encoded, log_time_ns: int | None = None) -> None:
    """Write ``message``, logged at its own time or at ``log_time_ns``."""
    if not file.write(
        message.topic,
        message.msgtype,
        codec.schema_text(message.msgtype),
        message.data,
        message.log_time_ns if log_time_ns is None else log_time_ns,
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
    """The MCAP summary was written (False after a write failure: still a valid file; or when
    :meth:`Recorder.close` could not finish the file within its bound: ``error`` says so)."""
    messages: int
    points: int
    scans: int
    statuses: int
    dropped_points: int
    """Acquisitions the recorder missed: counted by the sensor on the recorder's connection (too
    slow, or lost), by its queue in the feed, and left in that queue at close
    (``unwritten_points``)."""
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
    unwritten_points: int = 0
    """Acquisitions still waiting to be written when close() had no more time for them (a disk
    slower than the sensor): dropped, counted in ``dropped_points`` too."""
    unwritten_scans: int = 0
    lost_spans: tuple[str, ...] = ()
    """Each span without the network to a remote sensor (``from 14:02:11.3 to 14:02:14.5 (3.2
    s; ...)``): what the sensor made then is not in the file, and is in the drops only as far
    as the sensor counted it."""
    lost_seconds: float = 0.0
    """How long those spans lasted, together."""
    finished: bool = True
    """False when close() returned before a blocked write did: the file has no footer yet (it
    is finished if that write returns while the process lives; else it plays up to its last
    complete chunk)."""
    moving: bool = False
    """Recorded with the vehicle's poses (``/odom``, ``/biris/points`` in ``odom``)."""
    poses: int = 0
    """Pose samples written (each once on ``/odom`` and ``/tf``)."""
    unplaced_points: int = 0
    """Acquisitions of completed scans left out of ``/biris/points`` for want of a pose (they
    stay in the lossless channels)."""
    unplaced_scans: int = 0
    """Completed scans none of whose acquisitions had a pose: no cloud on ``/biris/points``."""
    grid_messages: int = 0
    """Certainty grids written on ``/biris/grid``."""
    proximity_messages: int = 0
    """The proximity alarm's answers written on ``/biris/proximity``."""

    @property
    def dropped(self) -> int:
        """Everything that is not in the file and was counted: drops and lost messages (a span
        without the network is not a count: see ``lost_spans``)."""
        return self.dropped_points + self.dropped_scans + self.lost_messages

    def __str__(self) -> str:
        text = (
            f"{self.path}: {self.scans} scans, {self.points} acquisitions, {self.statuses} "
            f"status records in {self.seconds:.1f} s, {self.bytes / 1e6:.2f} MB; "
        )
        counted = f"{self.dropped_points} acquisitions and {self.dropped_scans} scans"
        if self.lost_spans:  # never "dropped 0" when the network took a span away
            n = len(self.lost_spans)
            text += (
                f"missed everything for {self.lost_seconds:.1f} s without the network "
                f"({n} span{'s' if n > 1 else ''}: {'; '.join(self.lost_spans)}), plus "
                f"{counted} counted as dropped"
            )
        else:
            text += f"dropped {counted}"
        if self.unwritten_points or self.unwritten_scans:
            text += (
                f" ({self.unwritten_points} acquisitions and {self.unwritten_scans} scans of "
                f"them still waiting to be written at close)"
            )
        if self.lost_messages:
            text += f", {self.lost_messages} messages lost"
        if self.moving:
            text += f"; {self.poses} vehicle poses"
            if self.unplaced_points or self.unplaced_scans:
                text += (
                    f", {self.unplaced_points} acquisitions without a pose left out of "
                    f"/biris/points ({self.unplaced_scans} scans wholly)"
                )
            if self.grid_messages:
                text += f", {self.grid_messages} certainty grids"
            if self.proximity_messages:
                text += f", {self.proximity_messages} proximity answers"
        if self.partial_scans:
            n = len(self.partial_scans)
            text += f"; {n} partial scan{'s' if n > 1 else ''}: " + ", ".join(self.partial_scans)
        if not self.finished:
            text += " (not finished at close: a write was still under way)"
        elif not self.complete:
            text += " (no summary: file cut short, still valid)"
        return text


class _Writing:
    """One recording under way: the file, what was written, the feed's sink.

    The sink calls this object, never the :class:`Recorder`, so a Recorder its program forgot
    to close can be collected, and its finaliser closes this.
    """

    def __init__(
        self,
        file: McapFile,
        close_timeout_s: float,
        log_times: codec.LogTimes,
        moving: MovingEncoder | None = None,
    ) -> None:
        self.file = file
        self.close_timeout_s = close_timeout_s
        self.log_times = log_times
        self.moving = moving
        """Adds the vehicle's poses, the clouds in ``odom``, the grid and the proximity alarm
        (``poses=``)."""
        self.sink: feed.Sink | None = None
        self.failed = threading.Event()
        """Set when the sink could not be attached; the sink's own afterwards."""
        self.now = 0.0
        self.static_written = False
        self.last_flush = time.monotonic()
        self.started = 0.0
        self.stopped: float | None = None
        self.points = 0
        self.scans = 0
        self.statuses = 0
        self.partial_scans: list[str] = []
        self.summary: RecordSummary | None = None
        self.unfinished: RecordError | None = None
        """close() could not finish the file within its bound (a write that blocks)."""
        self._finish_lock = threading.Lock()
        self._finished = False

    # -- counts ----------------------------------------------------------------------------------
    @property
    def error(self) -> BaseException | None:
        sink_error = self.sink.error if self.sink is not None else None
        return self.file.error or sink_error or self.unfinished

    @property
    def dropped_points(self) -> int:
        return self.sink.dropped_points if self.sink is not None else 0

    @property
    def dropped_scans(self) -> int:
        return self.sink.dropped_scans if self.sink is not None else 0

    @property
    def lost_spans(self) -> tuple[feed.LostSpan, ...]:
        return self.sink.lost_spans if self.sink is not None else ()

    def counts(self) -> dict[str, object]:
        """The counts the diagnostics and the end record carry."""
        counts: dict[str, object] = {
            "points": self.points,
            "scans": self.scans,
            "statuses": self.statuses,
            "dropped_points": self.dropped_points,
            "dropped_scans": self.dropped_scans,
            "lost_messages": self.file.lost,
        }
        spans = self.lost_spans
        if spans:
            counts["dropped_network_s"] = f"{sum(span.seconds for span in spans):.1f}"
        if self.moving is not None:
            counts.update(self.moving.counts())
        return counts

    def end_record(self) -> dict[str, object]:
        """``biris.recording``: the counts, what close() had no time to write, the spans
        without the network."""
        sink = self.sink
        record = self.counts()
        record["unwritten_points"] = sink.unhandled_points if sink is not None else 0
        record["unwritten_scans"] = sink.unhandled_scans if sink is not None else 0
        record["lost_spans"] = [str(span) for span in self.lost_spans]
        record["stopped_utc"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        record.update(_log_time_record(self.log_times))
        return record

    def write(self, message: codec.Encoded) -> None:
        """Write one message, logged by :attr:`log_times`."""
        _write(self.file, message, self.log_times(message.log_time_ns))

    # -- what the feed hands over (the sink's thread, in batches) --------------------------------
    def static(self, mount: Mount | None, t: float) -> None:
        if not self.static_written:
            self.static_written = True
            self.write(codec.static_transforms(mount, t))

    def batch(self, batch: feed.Batch) -> None:
        """Write one batch: the data's messages as the feed encoded them, then the status; the
        last one ends the file."""
        if batch.points:
            self.now = max(self.now, batch.points[-1].t)
            self.static(batch.points[0].mount, batch.points[0].t)
        for scan in batch.scans:
            self.now = max(self.now, codec.scan_time(scan))
            self.static(scan.mount, codec.scan_time(scan))
        status_messages = []
        for message in batch.messages:
            if message.topic == codec.RAW_STATUS_TOPIC:
                status_messages.append(message)  # after its diagnostics, as it was read
            else:
                self.write(message)
        if self.moving is not None:
            for encoded in self.moving.messages(batch):
                self.write(encoded)
        self.points += len(batch.points)
        for scan in batch.scans:
            self.scans += 1
            if scan.partial:
                self.partial_scans.append(_partial_name(scan))
        reading = batch.status
        if reading is not None:
            extra = {"recorder": self.counts()}
            status = reading.status
            self.write(codec.diagnostics(status, reading.t, extra=extra, error=reading.error))
            for message in status_messages:
                self.write(message)
            self.statuses += 1
        if batch.final:
            self.finish()
        elif time.monotonic() - self.last_flush > FLUSH_S:
            self.last_flush = time.monotonic()
            if not self.file.flush():
                raise self.file.error or RecordError(f"cannot write {self.file.path}")

    def finish(self) -> None:
        """Write the end record and the summary, close the file (once)."""
        with self._finish_lock:
            if self._finished:
                return
            self._finished = True
            self.file.metadata("biris.recording", _metadata_strings(self.end_record()))
            self.file.close()

    # -- closing ---------------------------------------------------------------------------------
    def close(self, timeout: float) -> RecordSummary:
        """Detach within ``timeout`` and finish the file (see :meth:`Recorder.close`)."""
        if self.summary is not None and self.unfinished is None:
            return self.summary
        begun = time.monotonic()
        if self.stopped is None:
            self.stopped = begun  # the recording's length: until close() was called
        sink = self.sink
        done = True
        if sink is not None:
            sink.detach(timeout)
            in_sink = threading.current_thread() is sink._thread  # a finaliser run there
            left = 0.0 if in_sink else max(0.0, begun + timeout - time.monotonic())
            done = sink.done.wait(left)
        if done:  # nothing is written any more: the file can be ended here (idempotent)
            self.finish()
            self.unfinished = None
        else:
            self.unfinished = RecordError(
                f"{self.file.path} not finished within {timeout:g} s of close(): a write "
                f"still under way (a slow or hung disk). It is finished when that write "
                f"returns if the process goes on, else it is left as a killed recording is: "
                f"biris replay plays it up to its last complete chunk",
                errno.ETIMEDOUT,
            )
            log.error("%s", self.unfinished)
        error = self.error
        path = self.file.path
        spans = self.lost_spans
        moving = self.moving
        self.summary = RecordSummary(
            path=path,
            complete=self.file.complete and self.unfinished is None,
            messages=self.file.messages - self.file.lost,
            points=self.points,
            scans=self.scans,
            statuses=self.statuses,
            dropped_points=self.dropped_points,
            dropped_scans=self.dropped_scans,
            lost_messages=self.file.lost,
            bytes=path.stat().st_size if path.exists() else 0,
            seconds=self.stopped - self.started if self.started else 0.0,
            error=None if error is None else str(error),
            partial_scans=tuple(self.partial_scans),
            unwritten_points=sink.unhandled_points if sink is not None else 0,
            unwritten_scans=sink.unhandled_scans if sink is not None else 0,
            lost_spans=tuple(str(span) for span in spans),
            lost_seconds=sum(span.seconds for span in spans),
            finished=self.unfinished is None,
            moving=moving is not None,
            poses=0 if moving is None else moving.poses_out,
            unplaced_points=0 if moving is None else moving.unplaced_points,
            unplaced_scans=0 if moving is None else moving.unplaced_scans,
            grid_messages=0 if moving is None else moving.grid_messages,
            proximity_messages=0 if moving is None else moving.proximity_messages,
        )
        return self.summary

    def close_unclosed(self, path: Path) -> None:
        """The finaliser of a Recorder that was never closed: at interpreter exit, or when
        it is collected. Closes within the bound; never raises."""
        log.warning("a Recorder of %s was not closed: closing it", path)
        try:
            self.close(self.close_timeout_s)
        except Exception:
            log.exception("closing an unclosed Recorder of %s failed", path)


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
    ``overwrite=False`` refuses a file that exists (``biris record`` without ``--force``).
    ``close_timeout_s`` bounds :meth:`close` (:data:`CLOSE_TIMEOUT_S`); ``lost_limit_s`` is how
    long a lost network to a remote sensor is waited for (None:
    :data:`biris_hw.io.feed.LOST_LIMIT_S`, 30 s) before recording stops with a
    :class:`~biris_hw.errors.ConnectionLost` naming the span. ``stamp`` is what the messages are
    logged at: ``"hardware"``, their stamps' hardware-clock seconds (a timeline in 1970), or
    ``"wall"``, those moved onto the host's wall clock by one offset measured at the start
    (:class:`~biris_hw.io.codec.LogTimes`), so that the file lines up with the robot's other
    recordings; the messages' stamps stay the hardware's either way, and the ``biris``
    metadata says which (``log_time``, and ``log_time_offset_ns``: log time minus hardware
    time).

    On a moving robot, ``poses`` is the vehicle's pose (a
    :class:`~biris_hw.io.pose.PoseBuffer`, or any :class:`~biris_hw.io.moving_sink.PoseFeed`,
    on the sensor's hardware clock): the file then also carries ``/odom`` and ``odom ->
    vehicle`` on ``/tf`` (each pose sample once), and ``/biris/points`` in ``odom`` instead of
    ``frame`` (each scan deskewed, its acquisitions without a pose left out and counted);
    ``grid`` (a :class:`~biris_hw.io.grid.GridParams`, a
    :class:`~biris_hw.io.grid.CertaintyGrid` or a :class:`~biris_hw.io.grid.GridFeeder`; it
    needs ``poses``) adds the certainty grid on ``/biris/grid`` at a few Hz, fed with every
    acquisition, and ``proximity`` (a :class:`~biris_hw.io.proximity.ProximityZone`, a
    :class:`~biris_hw.io.proximity.ProximityAlarm` or a
    :class:`~biris_hw.io.proximity.ProximityFeeder`; it needs ``poses``) the proximity alarm's
    answers on ``/biris/proximity``, five a second of hardware time
    (:mod:`biris_hw.io.moving_sink`).
    The recorder does not command the sensor: it records whatever is done meanwhile.

    A Recorder that is never closed is closed when it is collected, or at the latest when the
    interpreter exits (within the same bound): a script that forgets ``close()`` ends with a
    complete file, and its process is not kept alive.

    Raises:
        RecordError: the file cannot be written (before anything is read from the sensor); on
            leaving the block, writing failed during the run (the file stays valid) or could
            not be finished within the close bound.
        ConnectionClosed: the source has stopped.
        ConnectionLost: on leaving the block, the network to a remote sensor was lost for
            longer than ``lost_limit_s``; the message names the span.
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
        overwrite: bool = True,
        close_timeout_s: float = CLOSE_TIMEOUT_S,
        lost_limit_s: float | None = None,
        stamp: codec.Stamp = "hardware",
        poses: PoseFeed | None = None,
        grid: GridOption | None = None,
        proximity: ProximityOption | None = None,
    ) -> None:
        codec.cloud_frame_id(frame)  # ValueError for a frame that is neither
        log_times = codec.LogTimes(stamp)  # ValueError for a stamp that is neither
        moving = moving_encoder(poses, grid, proximity)
        if not (close_timeout_s > 0 and math.isfinite(close_timeout_s)):
            raise ValueError(f"close_timeout_s must be a positive number, not {close_timeout_s!r}")
        self.source = source
        self.frame: Frame = frame
        self.profiles = profiles
        self.close_timeout_s = close_timeout_s
        file = McapFile(path, chunk_size=chunk_size, overwrite=overwrite)
        self.path = file.path
        self._writing = _Writing(file, close_timeout_s, log_times, moving)
        self._finalizer = weakref.finalize(self, self._writing.close_unclosed, file.path)
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
        if moving is not None:  # its clouds are in odom, made by the moving encoder
            topics.discard(codec.POINTS_TOPIC)
        self._options = {
            "name": "recorder",
            "topics": topics,
            "frame": frame,
            "status_period_s": status_period_s,
            "batch_s": batch_s,
            "point_depth": point_depth,
            "scan_depth": scan_depth,
            "lost_limit_s": lost_limit_s,
        }

    # -- the run ---------------------------------------------------------------------------------
    def start(self) -> Recorder:
        """Write the start metadata and begin reading (``with`` does this)."""
        writing = self._writing
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
        if writing.moving is not None:
            header["cloud_frame_id"] = codec.ODOM_FRAME
            header["moving"] = writing.moving.describe()
            writing.moving.warm()
        writing.log_times.anchor_to(self.source)
        header.update(_log_time_record(writing.log_times))
        header.update(self._extra)
        _warm()
        if not writing.file.metadata("biris", _metadata_strings(header)):
            raise writing.file.error or RecordError(f"cannot write {self.path}")
        writing.started = time.monotonic()
        try:
            writing.sink = feed.attach(self.source, writing.batch, **self._options)
        except BaseException:
            writing.file.close()
            self._finalizer.detach()
            raise
        return self

    @property
    def moving(self) -> MovingEncoder | None:
        """What adds the vehicle's poses, the clouds in ``odom``, the grid and the proximity
        alarm (with ``poses=``): its counts so far, its grid and its alarm
        (``recorder.moving.grid``, ``recorder.moving.alarm``)."""
        return self._writing.moving

    @property
    def failed(self) -> threading.Event:
        """Set when recording stopped on its own (a write failure, a damaged source, a network
        lost for too long): :attr:`error` says why."""
        sink = self._writing.sink
        return sink.failed if sink is not None else self._writing.failed

    @property
    def error(self) -> BaseException | None:
        """Why recording stopped early, or the file could not be finished; None."""
        return self._writing.error

    @property
    def points(self) -> int:
        """Acquisitions written so far."""
        return self._writing.points

    @property
    def scans(self) -> int:
        return self._writing.scans

    @property
    def statuses(self) -> int:
        return self._writing.statuses

    @property
    def partial_scans(self) -> list[str]:
        """Each partial scan recorded so far, named with its reason (see RecordSummary)."""
        return self._writing.partial_scans

    @property
    def dropped_points(self) -> int:
        """Acquisitions the recording misses so far (the sensor's drops and the feed's)."""
        return self._writing.dropped_points

    @property
    def dropped_scans(self) -> int:
        return self._writing.dropped_scans

    @property
    def lost_spans(self) -> tuple[feed.LostSpan, ...]:
        """The spans without the network to a remote sensor so far (see RecordSummary)."""
        return self._writing.lost_spans

    def close(self, timeout: float | None = None) -> RecordSummary:
        """Stop reading, write what waits, the end record and the summary, close the file;
        returns the summary.

        Returns within ``timeout`` real seconds (``close_timeout_s``, :data:`CLOSE_TIMEOUT_S`
        by default) whatever the backlog -- a slow disk, a head still scanning, a recorder
        slower than the sensor: a shutdown that waits for a backlog of unknown size is a
        process that does not stop when asked to. What waits for the recorder is written for
        the first half of it; what is left then is dropped and counted (``unwritten_points``,
        in the drops, in the summary and in the file's ``biris.recording`` record); the second
        half is for the file's last chunk and its summary. If a write blocks past the bound (a
        hung disk), close() returns all the same with ``complete`` and ``finished`` False and
        :attr:`error` saying so, and the file is finished in the background when the write
        returns. Calling it again waits again; once the file is finished it returns the same
        summary at once.
        """
        summary = self._writing.close(self.close_timeout_s if timeout is None else timeout)
        if self._writing.unfinished is None:
            self._finalizer.detach()
        return summary

    @property
    def summary(self) -> RecordSummary | None:
        """The summary, once closed."""
        return self._writing.summary

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


def _log_time_record(log_times: codec.LogTimes) -> dict[str, object]:
    """What the metadata says of the log times: which clock, and the offset once measured."""
    record: dict[str, object] = {"log_time": log_times.stamp}
    if log_times.stamp == "wall" and log_times.offset_ns is not None:
        record["log_time_offset_ns"] = log_times.offset_ns
    return record


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
