"""The vehicle's poses in a recording: ``odom -> vehicle`` on ``/tf``, or ``/odom``.

A recording made on a robot holds the vehicle's pose beside the sensor's data: the ``odom ->
vehicle`` transform on ``/tf`` (``tf2_msgs/msg/TFMessage``, whose messages also carry the head's
own transforms) and the base's ``/odom`` (``nav_msgs/msg/Odometry``). :func:`read_poses` reads
one topic's poses into a list for a :class:`~biris_hw.io.pose.PoseBuffer` (``buffer.extend``),
decoded by :mod:`biris_hw.io.codec`. A file whose writer never closed it (a robot that lost
power) is read up to its last complete record, as a replay reads it
(:mod:`biris_hw.io.record.cutfile`).

mcap is imported on first use (the ``record`` extra).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from typing import IO, Any

from biris_hw.data import PoseSample
from biris_hw.errors import BirisError
from biris_hw.io.codec import (
    ODOM_FRAME,
    TF_MESSAGE,
    TF_TOPIC,
    VEHICLE_FRAME,
    WireError,
    decode_pose,
    decode_tf_poses,
)

__all__ = ["PoseFileError", "read_poses"]


class PoseFileError(BirisError, ValueError):
    """A recording's poses cannot be read: the file is missing or not MCAP, the topic is not in
    it, or a message on it is not a pose (named)."""


def read_poses(
    path: str | os.PathLike[str],
    topic: str = TF_TOPIC,
    *,
    frame_id: str = ODOM_FRAME,
    child_frame_id: str = VEHICLE_FRAME,
) -> list[PoseSample]:
    """The ``frame_id -> child_frame_id`` poses recorded on ``topic`` of the MCAP file
    ``path``, in stamp order, numbered from 0 (``seq``), stamped as recorded (the hardware
    clock, in a biris recording).

    ``topic`` carries ``tf2_msgs/msg/TFMessage`` (``/tf``: only the transforms between the two
    frames are taken), ``nav_msgs/msg/Odometry`` (``/odom``) or
    ``geometry_msgs/msg/TransformStamped``; the type is the channel's schema name. A transform
    has no twist (NaN: the buffer derives one). An empty list if the topic holds no pose between
    those frames.

    Raises:
        PoseFileError: the file cannot be read or is not MCAP, has no channel ``topic``, or a
            message on it is not of its type.
    """
    from mcap.exceptions import McapError

    found: list[PoseSample] = []
    seen = False
    try:
        with open(path, "rb") as f:
            for schema, _channel, message in _messages(f, path, topic):
                seen = True
                msgtype = schema.name if schema is not None else TF_MESSAGE
                if msgtype == TF_MESSAGE:
                    found.extend(
                        decode_tf_poses(message.data, frame_id, child_frame_id, seq=len(found))
                    )
                    continue
                pose = decode_pose(message.data, msgtype, seq=len(found))
                if pose.frame_id == frame_id and pose.child_frame_id == child_frame_id:
                    found.append(pose.sample)
        if not seen and not _has_channel(path, topic):
            raise PoseFileError(f"{path} has no channel {topic}")
    except PoseFileError:
        raise
    except WireError as exc:
        raise PoseFileError(f"{path}: a message on {topic} is not a pose: {exc}") from exc
    except OSError as exc:
        raise PoseFileError(f"cannot read {path}: {exc.strerror or exc}") from exc
    except (McapError, ValueError, EOFError) as exc:  # the reader's ways of failing
        raise PoseFileError(f"{path} is not a readable MCAP file: {exc}") from exc
    found.sort(key=lambda s: s.t)  # stable: messages of one stamp keep their order
    return [s._replace(seq=i) for i, s in enumerate(found)]


def _messages(f: IO[bytes], path: str | os.PathLike[str], topic: str) -> Iterator[Any]:
    """(schema, channel, message) of ``topic``, the file closed or cut short."""
    from mcap.reader import make_reader

    from biris_hw.io.record import cutfile

    if cutfile.ends_with_footer(f):
        f.seek(0)
        yield from make_reader(f, validate_crcs=True).iter_messages(topics=[topic])
        return
    cut = cutfile.cut_of(f)
    if cut is None:
        raise PoseFileError(f"{path} is not an MCAP file (it does not begin with the magic)")
    yield from cutfile.messages(f, cut, [topic])


def _has_channel(path: str | os.PathLike[str], topic: str) -> bool:
    """Whether ``topic`` has a channel in the file (one with no message still counts)."""
    from mcap.reader import make_reader

    from biris_hw.io.record import cutfile

    with open(path, "rb") as f:
        if cutfile.ends_with_footer(f):
            f.seek(0)
            summary = make_reader(f).get_summary()
            if summary is not None:
                return topic in _topics(summary.channels.values())
        cut = cutfile.cut_of(f)
        if cut is None:
            return False
        return topic in _topics(r for r in cutfile.records(f, cut) if hasattr(r, "topic"))


def _topics(channels: Iterable[Any]) -> set[str]:
    return {str(c.topic) for c in channels}
