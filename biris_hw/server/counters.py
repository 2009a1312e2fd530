"""The server's running counts, for ``status()``: one object, one field per thing counted.

Every component that counts is handed this object and increments its own fields; nothing else
writes them. A typo in a field name is a mypy error, not a silently new key.

**The acquisition accounts.** Every acquisition BIRIS makes ends in exactly one of these
counters, so that they reconcile with what BIRIS made (:meth:`biris_hw.status.ServerStatus.accounts`
checks it)::

    made = acquisitions_read + idle_ring_frames + lost_acquisitions       # the reader's side
    acquisitions_read = acquisitions_in_scans + constant_azimuth          # the administrator's
        + stale_acquisitions + aborted_acquisitions + (held by the scan under way)

The first line holds once the server has looked at everything BIRIS made (no BI_ACQUIRE under
way; in continuous acquisition, the ring stopped: idle ring frames are counted when a sweep next
opens or when the ring stops). The second holds at every ``status()``, since the administrator
answers it between two messages.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

__all__ = ["Counters"]


@dataclass(slots=True)
class Counters:
    """What the server has done since it was built (reset keeps them: they are a history)."""

    acquisitions: int = 0
    """Acquisitions kept in a scan (and offered as points) -- whether that scan then completed
    (``acquisitions_in_scans``) or was abandoned by a fault or reset (``aborted_acquisitions``)."""
    scans: int = 0
    dropped_acquisitions: int = 0
    """Acquisitions a completed scan lacks (lost before they could be read); a part of
    ``lost_acquisitions``, which also counts those of scans that never completed."""
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
    """Acquisitions of a sequence or sweep the server no longer waits for (read after a reset or
    fault forgot it, or after its scan had completed)."""
    stale_completions: int = 0
    """Completions of a command or sweep the server no longer waits for."""
    overtaken_task_failures: int = 0
    """Task failures read after the reset that restarts the task had begun (met in the outage
    the reset recovers from): logged, not faults."""
    acquisitions_read: int = 0
    """Acquisitions the reader read out of BIRIS memory and handed to the administrator
    (NEW_POINT), whatever became of them: the administrator's side of the accounts starts here."""
    acquisitions_in_scans: int = 0
    """Acquisitions in completed scans (the sum of their ``n_acq``): what clients were given."""
    aborted_acquisitions: int = 0
    """Acquisitions kept by a scan that a fault or a reset abandoned (with the turn-around
    acquisitions it held for the next sweep): read, offered as points, never part of a Scan."""
    idle_ring_frames: int = 0
    """Continuous acquisition: ring frames BIRIS completed while no sweep wanted them -- after
    the ring went live and before the first sweep, between sweeps that do not follow straight
    on, after the last sweep until the ring stopped. The reader skips them unread and counts
    them exactly (from ACQ_LINE, or CURRENT_FRAME once stopped, and the hardware clock)."""
    lost_acquisitions: int = 0
    """Acquisitions known to be gone: overwritten in the ring (or never announced by BIRIS)
    before the reader could read them, or read but not trusted (``untrusted_frames``). They
    were made, so the accounts count them."""
    untrusted_frames: int = 0
    """Frames the reader read but could not trust to hold the acquisition it wanted (BIRIS was
    seen overwriting their ring slot while they were read): dropped, and a part of
    ``lost_acquisitions``."""
    partial_scans: int = 0
    """Completed scans marked ``partial`` (short of their span, the first sweep of a continuous
    scan, a sweep STOP_CONTINUOUS cut): each says why in ``Scan.partial_reason``."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)
