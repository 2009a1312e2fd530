"""Paying the codec's one-time cost up front, never on the data path.

:mod:`biris_hw.io.codec` builds a rosbags typestore the first time it is used (about 0.1 s of
pure Python, measured on the 2-core development machine, longer when it is loaded) and generates
each message type's CDR (de)serialiser on its first use (another 10-20 ms each). All of it
holds the interpreter lock. Paid lazily, it landed on the first acquisition: in the service
process the feed thread built the store while the server's own threads waited for the lock (the
server logged "BIRIS's start was seen 60 ms late"), and in each subscriber process the first
Points waited behind it (ten subscribers starting at once on two cores delayed their first half
second of Points by up to 0.5-0.8 s: ``make bench``'s fan-out p99, see docs/benchmarks.md). So
the service warms every type it encodes before it starts serving, and a client warms the type
it subscribes to before its subscription is declared (:func:`biris_hw.io.codec.warm` does the
work; this module names the service's payloads by what a client subscribes to).
"""

from __future__ import annotations

from biris_hw.io import codec

__all__ = ["KINDS", "warm", "warm_all"]

KINDS: dict[str, str] = {
    "point": codec.POINT,
    "scan": codec.SCAN,
    "status": codec.STATUS,
    "fault": codec.FAULT,
}
"""Each kind of payload the service publishes or replies with, and its message type."""


def warm(kind: str) -> None:
    """Encode and decode one sample of ``kind`` ("point", "scan", "status", "fault") once in this
    process, so that later calls find the typestore and the type's generated code ready."""
    if kind not in KINDS:
        raise ValueError(f"no payload kind {kind!r}")
    codec.warm(KINDS[kind])


def warm_all() -> None:
    """Every payload type the service publishes or replies with."""
    for kind in KINDS:
        warm(kind)
