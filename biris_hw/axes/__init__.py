"""Servo axes behind one interface: the Model 7600's HCTL-1000s, or CiA 402 drives over CANopen.

:mod:`biris_hw.axes.base` holds the interface (:class:`MotionAxis`, :class:`MotionController`)
and the settling rules every axis kind shares; :mod:`biris_hw.axes.cia402` the CANopen drives,
imported on demand because it needs the optional ``canopen`` package (``biris-hw[can]``).
"""

from __future__ import annotations

from biris_hw.axes.base import (
    SETTLE_HOLD_S,
    SETTLE_LIMIT_S,
    SETTLE_POLL_S,
    MotionAxis,
    MotionController,
    wait_settled,
    wait_still,
)

__all__ = [
    "SETTLE_HOLD_S",
    "SETTLE_LIMIT_S",
    "SETTLE_POLL_S",
    "MotionAxis",
    "MotionController",
    "wait_settled",
    "wait_still",
]
