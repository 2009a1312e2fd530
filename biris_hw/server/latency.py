"""Delivery latency per connection: how old data were when the client got them.

The report worried that a client asking for "the latest complete scan" gets data a whole sweep
old, too late for collision avoidance; this is the measurement that shows it. Latency is
``t_delivered - t`` in hardware seconds: for a Point its acquisition's age, for a Scan its
newest acquisition's age (:attr:`biris_hw.data.Scan.age`).

The administrator records every delivery, for ever, so the memory must not grow: a fixed set of
logarithmic bins (ten per decade from 100 us to 1000 s, plus under- and overflow) holds the
distribution, and percentiles are interpolated inside a bin, which is good to about 12 percent
of the value -- plenty to tell 30 ms from a sweep.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["LatencyHistogram"]

_LOW_S = 1e-4
_PER_DECADE = 10
_DECADES = 7
_BINS = _PER_DECADE * _DECADES


class LatencyHistogram:
    """Counts of latencies in logarithmic bins, with count, max, mean and percentiles."""

    __slots__ = ("_counts", "_max", "_n", "_sum")

    EDGES_S: tuple[float, ...] = tuple(_LOW_S * 10.0 ** (k / _PER_DECADE) for k in range(_BINS + 1))
    """Bin edges in seconds; bin 0 is everything below the first edge, the last bin above."""

    def __init__(self) -> None:
        self._counts = [0] * (_BINS + 2)
        self._n = 0
        self._sum = 0.0
        self._max = 0.0

    def add(self, latency_s: float) -> None:
        """Record one delivery. A negative latency (clock jitter) counts as zero."""
        value = max(0.0, float(latency_s))
        if value < _LOW_S:
            index = 0
        else:
            index = min(_BINS + 1, 1 + int(math.log10(value / _LOW_S) * _PER_DECADE))
        self._counts[index] += 1
        self._n += 1
        self._sum += value
        self._max = max(self._max, value)

    @property
    def count(self) -> int:
        return self._n

    def percentile(self, q: float) -> float | None:
        """The ``q``-th percentile (0..100) in seconds, None before the first delivery."""
        if self._n == 0:
            return None
        rank = q / 100.0 * self._n
        seen = 0
        for index, count in enumerate(self._counts):
            if count and seen + count >= rank:
                return min(self._max, self._inside(index, (rank - seen) / count))
            seen += count
        return self._max

    def _inside(self, index: int, fraction: float) -> float:
        """A value ``fraction`` of the way through bin ``index`` (geometrically)."""
        edges = self.EDGES_S
        if index == 0:
            return _LOW_S * fraction
        if index > _BINS:
            return self._max
        low, high = edges[index - 1], edges[index]
        return float(low * (high / low) ** max(0.0, min(1.0, fraction)))

    def summary(self) -> dict[str, Any]:
        """Plain data for ``server.status()``: count, mean, max, p50, p99 (seconds) and the
        non-empty bins as ``[[low_s, high_s, count], ...]``."""
        edges = (0.0, *self.EDGES_S, math.inf)
        bins = [[edges[i], edges[i + 1], count] for i, count in enumerate(self._counts) if count]
        return {
            "count": self._n,
            "mean": self._sum / self._n if self._n else None,
            "max": self._max if self._n else None,
            "p50": self.percentile(50.0),
            "p99": self.percentile(99.0),
            "histogram": bins,
        }
