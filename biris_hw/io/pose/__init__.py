"""The vehicle's pose, from wherever the robot gives it, at every acquisition's time.

A BIRIS head rides on a vehicle; to put a scan taken while driving where it belongs, each
acquisition needs the vehicle's pose at its own time. This package takes poses in and answers
for any time: :class:`PoseBuffer` (bounded; interpolates, or marks a time it cannot answer),
fed by a :class:`PosePump` from a :class:`PoseSource` (the simulator's odometry), by a Zenoh
subscription to what a ROS 2 base publishes (:func:`subscribe_poses`: ``nav_msgs/msg/Odometry``
or ``geometry_msgs/msg/TransformStamped`` in CDR), or from a recording's ``/tf`` or ``/odom``
(:func:`read_poses`). :func:`biris_hw.io.deskew.deskewed` places a scan with it. docs/moving.md.
"""

from __future__ import annotations

from biris_hw.io.pose.buffer import (
    DEFAULT_CAPACITY,
    DEFAULT_MAX_EXTRAPOLATION_S,
    DEFAULT_MAX_GAP_S,
    PoseBuffer,
    PosePump,
    PoseSource,
    clock_offset,
    follow,
)
from biris_hw.io.pose.net import PoseSubscription, subscribe_poses
from biris_hw.io.pose.recording import PoseFileError, read_poses

__all__ = [
    "DEFAULT_CAPACITY",
    "DEFAULT_MAX_EXTRAPOLATION_S",
    "DEFAULT_MAX_GAP_S",
    "PoseBuffer",
    "PoseFileError",
    "PosePump",
    "PoseSource",
    "PoseSubscription",
    "clock_offset",
    "follow",
    "read_poses",
    "subscribe_poses",
]
