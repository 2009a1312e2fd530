"""The client/server protocol: every message a client sends to the BIRIS server's administrator.

Named after the report's client messages (OPEN_REQUEST, REQUEST_POINT, REQUEST_SCAN_DATA, ...,
READY_FOR_DATA, and SET_ELEVATION, the "new message" the report asks for to servo the elevation
axis). It sits below both :mod:`biris_hw.client` and :mod:`biris_hw.server`, so neither imports
the other for it. All messages are immutable.
"""

from __future__ import annotations

from dataclasses import dataclass

from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction
from biris_hw.records import MotorParams


@dataclass(frozen=True, slots=True)
class OpenRequest:
    kind: ConnectionKind
    owner_ident: object
    """The opening thread: the connection is released when it ends."""
    policy: DeliveryPolicy = DeliveryPolicy.LATEST
    depth: int | None = None
    """None: the policy's default."""


@dataclass(frozen=True, slots=True)
class CloseRequest:
    conn: int


@dataclass(frozen=True, slots=True)
class RequestPoint:
    conn: int


@dataclass(frozen=True, slots=True)
class RequestScanData:
    conn: int
    direction: Direction


@dataclass(frozen=True, slots=True)
class TimeoutEnable:
    conn: int


@dataclass(frozen=True, slots=True)
class TimeoutDisable:
    conn: int


@dataclass(frozen=True, slots=True)
class BirisMotorParams:
    conn: int
    params: MotorParams


@dataclass(frozen=True, slots=True)
class SingleScanRqst:
    conn: int
    destination: int


@dataclass(frozen=True, slots=True)
class ContScanRqst:
    conn: int
    cw_limit: int
    ccw_limit: int


@dataclass(frozen=True, slots=True)
class StopScanRqst:
    conn: int


@dataclass(frozen=True, slots=True)
class BirisHome:
    conn: int


@dataclass(frozen=True, slots=True)
class SetElevation:
    """The report's future elevation message: tilt to ``destination`` counts and reload the
    calibration table for it."""

    conn: int
    destination: int


@dataclass(frozen=True, slots=True)
class ReadyForData:
    conn: int


@dataclass(frozen=True, slots=True)
class WaitIdle:
    conn: int


@dataclass(frozen=True, slots=True)
class ResetRequest:
    conn: int


@dataclass(frozen=True, slots=True)
class StatusRequest:
    conn: int | None = None
