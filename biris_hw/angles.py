"""Binary degrees: 4096 counts per revolution, positive counter-clockwise seen from above."""

from __future__ import annotations

import math

from regs.hctl1000 import COUNTS_PER_REV, MOTION_LIMIT_COUNTS

__all__ = ["MOTION_LIMIT_COUNTS", "clamp_counts", "counts_to_deg", "deg_to_counts"]


def deg_to_counts(deg: float) -> int:
    """Nearest whole count for ``deg`` degrees; ValueError for NaN, infinities and non-numbers."""
    if isinstance(deg, bool) or not isinstance(deg, (int, float)):
        raise ValueError(f"an angle must be a number, not {type(deg).__name__}")
    if not math.isfinite(deg):
        raise ValueError(f"an angle must be finite, not {deg}")
    return round(deg * COUNTS_PER_REV / 360.0)


def counts_to_deg(counts: float) -> float:
    """Degrees for ``counts`` binary-degree counts."""
    return counts * 360.0 / COUNTS_PER_REV


def clamp_counts(counts: int) -> int:
    """The report's _Scan_limit: truncate a destination to +-0x1000 counts (+-360 degrees)."""
    return max(-MOTION_LIMIT_COUNTS, min(MOTION_LIMIT_COUNTS, counts))
