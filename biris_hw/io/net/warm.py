"""Paying the codec's one-time cost up front, never on the data path.

:mod:`biris_hw.io.wire` builds a rosbags typestore the first time it is used (about 0.1 s of pure
Python, measured on the 2-core development machine, longer when it is loaded) and generates
each message type's CDR (de)serialiser on its first use (another 10-20 ms each). All of it
holds the interpreter lock. Paid lazily, it landed on the first acquisition: in the service
process the feed thread built the store while the server's own threads waited for the lock (the
server logged "BIRIS's start was seen 60 ms late"), and in each subscriber process the first
Points waited behind it (ten subscribers starting at once on two cores delayed their first half
second of Points by up to 0.5-0.8 s: ``make bench``'s fan-out p99, see docs/benchmarks.md). So
the service warms every type it encodes before it starts serving, and a client warms the type
it subscribes to before its subscription is declared.
"""

from __future__ import annotations

import functools

import numpy as np

from biris_hw.data import Direction, Point, Scan
from biris_hw.errors import HardwareFault
from biris_hw.io import wire
from biris_hw.status import ServerState, ServerStatus

__all__ = ["warm", "warm_all"]

KINDS = ("point", "scan", "status", "fault")


def _sample_status() -> ServerStatus:
    return ServerStatus(
        state=ServerState.IDLE,
        fault=None,
        azimuth=0,
        elevation=0,
        calibration=None,
        continuous=False,
        acquisition="single",
        ring="off",
        counters={"scans": 0},
        connections={},
    )


@functools.cache
def warm(kind: str) -> None:
    """Encode and decode one sample of ``kind`` ("point", "scan", "status", "fault") once in this
    process, so that later calls find the typestore and the type's generated code ready."""
    profile = np.zeros(2, dtype=np.int16)
    if kind == "point":
        wire.decode_point(wire.encode_point(Point(0, 0, profile, profile, 0.0, 0, 0)))
    elif kind == "scan":
        grid = np.zeros((1, 2), dtype=np.int16)
        scan = Scan(
            direction=Direction.CW,
            seq=0,
            azimuth=np.zeros(1, dtype=np.int32),
            range_mm=grid,
            closest_mm=np.zeros(1, dtype=np.int16),
            intensity=grid,
            t=np.zeros(1),
        )
        wire.decode_scan(wire.encode_scan(scan))
    elif kind == "status":
        wire.decode_status(wire.encode_status(_sample_status()))
    elif kind == "fault":
        wire.decode_fault(wire.encode_fault(HardwareFault("internal", "warm-up")))
    else:
        raise ValueError(f"no payload kind {kind!r}")


def warm_all() -> None:
    """Every payload type the service publishes or replies with."""
    for kind in KINDS:
        warm(kind)
