"""The server's running counts, for ``status()``: one object, one field per thing counted.

Every component that counts is handed this object and increments its own fields; nothing else
writes them. A typo in a field name is a mypy error, not a silently new key.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

__all__ = ["Counters"]


@dataclass(slots=True)
class Counters:
    """What the server has done since it was built (reset keeps them: they are a history)."""

    acquisitions: int = 0
    """Acquisitions kept in a scan (and offered as points)."""
    scans: int = 0
    dropped_acquisitions: int = 0
    """Acquisitions a completed scan lacks (lost before they could be read)."""
    discarded_samples: int = 0
    """Samples beyond BIRIS_MAX_RANGE, set to 0."""
    constant_azimuth: int = 0
    """Continuous acquisition: acquisitions made with the head standing at a sweep's end."""
    deliveries: int = 0
    tilts: int = 0
    lut_loads: int = 0
    continuous_starts: int = 0
    faults: int = 0
    spurious_motor_end: int = 0
    stale_acquisitions: int = 0
    """Acquisitions of a sequence the server no longer waits for (after a reset or fault)."""
    stale_completions: int = 0
    """Completions of a command or sweep the server no longer waits for."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)
