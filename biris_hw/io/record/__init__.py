"""Recording a BIRIS sensor to MCAP with ROS 2 message types (extra ``.[record]``).

``with Recorder(server_or_remote, "run.mcap"):`` writes everything the sensor produces meanwhile
-- standard ``sensor_msgs``/``tf2_msgs``/``diagnostic_msgs`` messages that ``ros2 bag``, Foxglove
and Lichtblick open as they are, and lossless ``biris_msgs`` channels that
:class:`biris_hw.io.record.ReplayServer` turns back into equal :class:`~biris_hw.Scan` and
:class:`~biris_hw.Point` objects. :func:`write_scans` writes a list of scans (``biris scan --save
x.mcap``). Topics and frames: :mod:`biris_hw.io.codec`; the file's failure modes:
:mod:`biris_hw.io.record.mcapfile`; a file whose writer was killed, played up to its last
complete chunk: :mod:`biris_hw.io.record.cutfile`.
"""

from __future__ import annotations

from biris_hw.io.record.mcapfile import RecordError
from biris_hw.io.record.recorder import (
    CLOSE_TIMEOUT_S,
    RAW_POINT_TOPIC,
    RAW_SCAN_TOPIC,
    RAW_STATUS_TOPIC,
    Recorder,
    RecordSummary,
    write_scans,
)
from biris_hw.io.record.replay import EndOfRecording, ReplayServer

__all__ = [
    "CLOSE_TIMEOUT_S",
    "RAW_POINT_TOPIC",
    "RAW_SCAN_TOPIC",
    "RAW_STATUS_TOPIC",
    "EndOfRecording",
    "RecordError",
    "RecordSummary",
    "Recorder",
    "ReplayServer",
    "write_scans",
]
