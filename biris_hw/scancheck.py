"""The invariants every delivered :class:`~biris_hw.data.Scan` keeps, checked on the scans alone.

Issue 21: a client must never be handed a scan that is silently short or empty, nor one that
holds rows of another scan. The server keeps these rules when it builds a scan; this module
states them once, as pure functions of the data, so that the same rules judge a live stream (the
test suite checks every scan the server completes), a recording (``biris replay --check``) and a
scan file. Nothing here imports the server: the server imports :func:`coverage_shortfall` from
here, so "covers its span" has one definition.

The rules, for one scan (:func:`check_scan`):

* ``t`` strictly increases (acquisitions are made one after the other);
* azimuths move the scan's way: towards larger counts for CCW, smaller for CW, never more than
  :data:`BACKSTEP_COUNTS` back from the furthest reached (an encoder at a near standstill
  jitters by a count or two; anything more is a row out of place);
* a scan whose ``span`` is known and that is not ``partial`` covers that span
  (:func:`coverage_shortfall` finds nothing short), and its span runs the scan's way;
* a scan with no acquisition is ``partial`` (an empty whole scan would be silent data loss);
* a ``partial`` scan says why (``partial_reason``); only data from before the reason existed
  (``span`` None) may be partial without one;
* with ``expect_returns``: no row is all zero (range, closest and intensity). BIRIS writes 0 for
  "no return", so such a row is a real acquisition that saw nothing *or* a frame BIRIS never
  wrote (BIRIS memory is zero from power-up, see below); only a caller who knows every azimuth
  returns light -- a test on a simulated round wall within reach -- can tell them apart. (A
  frame read while it is being exposed is another matter: the simulator fills it with a poison
  pattern, 0x7A7A, not zeros, which the data path's own tests look for.)

And across a stream (:class:`ScanChecker`): no acquisition appears in two scans, nor twice in one.

Why an all-zero row is ambiguous: the simulator's optics (``sim.optics.BirisOptics.acquire``)
write a row's range *and* intensity as 0 for every sample without a valid return, and element 0
(closest) as 0 when no sample returned; a wall beyond ``max_range_m`` (3.5 m by default, e.g.
``circle:40`` or a far corner of ``Scene.room()``) gives exactly such rows at the azimuths where
it is out of reach, as the real sensor does. A frame never written since power-up reads the
same. So the rule is opt-in.

Why a row's key is its data and not its time: a row "in two scans" is one acquisition delivered
twice, or a frame read again after BIRIS moved on (a ring slot, a stale buffer). The second read is
stamped afresh by the server, so ``t`` differs while the azimuth table entry and the frame do not; a
key with ``t`` in it would miss exactly the case it is for. The key is therefore the azimuth and the
range and intensity bytes. Two genuinely different acquisitions share it only if every sample of the
line rounds to the same millimetre: on the simulator, with its default ``noise=True``, every row of
every acquisition draws fresh Gaussian jitter on its peak separation (sigma_z = 0.5 mm at 0.3 m, the
closest BIRIS reads, 5.7 mm at 1 m, 23 mm at 2 m): two acquisitions of one surface read the same
millimetre on one sample with a probability of 0.5, 0.05 and 0.01 there (measured on the optics), so
on all 64 samples of a line with about 1e-19, 1e-84 and 1e-122 -- and that at exactly the same
azimuth count. Without noise (``noise=False``) the optics are a pure function of the pose: two
sweeps over the same azimuth give identical rows, and the repeat rule must be turned off
(``ScanChecker(repeats=False)``). Rows with no return at all are not keyed (every acquisition that
saw nothing looks the same).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from biris_hw.angles import counts_to_deg
from biris_hw.data import Direction, Scan

__all__ = [
    "BACKSTEP_COUNTS",
    "SETTLE_COUNTS",
    "ScanChecker",
    "check_scan",
    "coverage_shortfall",
    "scan_name",
]

SETTLE_COUNTS = 2
"""Counts a head at rest may sit from where it was ordered (a count or two of settling): added
to one acquisition's travel when judging whether a scan reached its ends."""

BACKSTEP_COUNTS = 2
"""Counts an azimuth may fall back against the scan's direction (encoder jitter at a near
standstill, at the ends of a sweep) before the row counts as out of place."""


def _counts(counts: int) -> str:
    """``312 counts (27.4 deg)``: both units, since people think in degrees and the data are in
    counts."""
    return f"{counts} counts ({counts_to_deg(counts):.1f} deg)"


def coverage_shortfall(azimuth: NDArray[np.int32], start: int, destination: int) -> str | None:
    """Why ``azimuth`` does not cover a sweep from ``start`` to ``destination``, or None if it does.

    The one coverage rule (the server calls it when it builds a scan, the checker when it reads
    one). Covered means: at least two acquisitions; and, with one acquisition's travel taken as
    the largest step between consecutive azimuths, the first azimuth within that travel (plus
    :data:`SETTLE_COUNTS`) of ``start`` and the last within it of ``destination``. One travel of
    slack because BIRIS samples the moving head once a period: the first acquisition of a sweep
    that started on time may lie up to one period's travel past the start, the last one short of
    the destination. Returns a sentence naming what is missing, in counts and degrees, e.g.
    ``"ended 312 counts (27.4 deg) short of its destination 2048"``; both ends' problems are
    joined with ``"; "``.
    """
    az = np.asarray(azimuth, dtype=np.int64).reshape(-1)
    start, destination = int(start), int(destination)
    if az.size == 0:
        return "no acquisition"
    if az.size == 1:
        return f"only one acquisition (at {int(az[0])})"
    travel = int(np.abs(np.diff(az)).max())
    slack = travel + SETTLE_COUNTS
    sign = (destination > start) - (destination < start)
    problems = []
    first, last = int(az[0]), int(az[-1])
    if sign == 0:  # no way to go: both ends must be where it stands
        if abs(first - start) > slack:
            problems.append(f"began {_counts(abs(first - start))} away from its start {start}")
        if abs(last - destination) > slack:
            problems.append(
                f"ended {_counts(abs(last - destination))} away from its destination {destination}"
            )
    else:
        late = (first - start) * sign
        if late > slack:
            problems.append(f"began {_counts(late)} after its start {start}")
        elif -late > slack:
            problems.append(f"began {_counts(-late)} before its start {start}")
        short = (destination - last) * sign
        if short > slack:
            problems.append(f"ended {_counts(short)} short of its destination {destination}")
        elif -short > slack:
            problems.append(f"ended {_counts(-short)} beyond its destination {destination}")
    return "; ".join(problems) or None


def scan_name(scan: Scan) -> str:
    """``CCW #3``: how a violation names its scan (direction and per-direction ``seq``)."""
    return f"{scan.direction.name} #{scan.seq}"


def _first_and_more(rows: NDArray[np.intp]) -> tuple[int, str]:
    """The first offending row, and ``" (and 4 more rows)"`` when there are others: one line per
    rule and scan, so a scan broken throughout does not bury the rest of the report."""
    more = rows.size - 1
    return int(rows[0]), (f" (and {more} more row{'s' if more > 1 else ''})" if more else "")


def check_scan(scan: Scan, *, expect_returns: bool = False, physical: bool = True) -> list[str]:
    """The rules one scan breaks (see the module), one sentence each, naming the scan and the
    first row concerned; ``[]`` for a good scan.

    ``expect_returns``: every acquisition must have returned light somewhere along its line, so
    an all-zero row is a frame BIRIS never wrote (only true of scenes known to return light at
    every azimuth; see the module for why it cannot be the default). ``physical=False`` judges
    only the server's bookkeeping -- an empty scan is partial, a partial one says why, a span
    runs the scan's way -- and not the rows' physics (time, motion, coverage): for scans built
    from made-up acquisitions, such as a test's fake BIRIS feeds the server.
    """
    name = scan_name(scan)
    found: list[str] = []
    n = scan.n_acq

    t = scan.t
    if physical and n > 1:
        bad = np.flatnonzero(~(np.diff(t) > 0)) + 1  # NaN is not an increase either
        if bad.size:
            k, more = _first_and_more(bad)
            found.append(
                f"{name}: row {k}: t {t[k]:.6f} s is not after row {k - 1}'s {t[k - 1]:.6f} s{more}"
            )

    az = scan.azimuth.astype(np.int64)
    if physical and n > 1:
        sign = scan.direction.sign
        furthest = np.maximum.accumulate(az * sign) * sign  # the furthest reached so far
        back = (furthest[:-1] - az[1:]) * sign
        bad = np.flatnonzero(back > BACKSTEP_COUNTS) + 1
        if bad.size:
            k, more = _first_and_more(bad)
            found.append(
                f"{name}: row {k}: azimuth {int(az[k])} is {int(back[k - 1])} counts back from "
                f"{int(furthest[k - 1])}, against the scan's direction ({scan.direction.name})"
                f"{more}"
            )

    if n == 0 and not scan.partial:
        found.append(f"{name}: holds no acquisition, yet is not marked partial")
    if scan.span is not None:
        start, destination = scan.span
        if start != destination and Direction.of_motion(start, destination) != scan.direction:
            found.append(
                f"{name}: its span {start} -> {destination} runs "
                f"{Direction.of_motion(start, destination).name}, the scan {scan.direction.name}"
            )
        if physical and not scan.partial and n > 0:
            shortfall = coverage_shortfall(scan.azimuth, start, destination)
            if shortfall is not None:
                found.append(
                    f"{name}: not marked partial, yet it {shortfall} "
                    f"(span {start} -> {destination})"
                )
        if scan.partial and not scan.partial_reason:
            found.append(f"{name}: partial without a reason (partial_reason is empty)")

    if physical and expect_returns and n:
        silent = ~(scan.range_mm.any(axis=1) | scan.intensity.any(axis=1) | (scan.closest_mm != 0))
        bad = np.flatnonzero(silent)
        if bad.size:
            k, more = _first_and_more(bad)
            found.append(
                f"{name}: row {k} (azimuth {int(az[k])}) is all zero -- range, closest and "
                f"intensity -- where the scene returns light everywhere: a frame BIRIS never "
                f"wrote{more}"
            )
    return found


@dataclass(frozen=True)
class _Seen:
    """Where a row was first delivered: the scan's name, its place in the stream, the row."""

    scan: str
    ordinal: int
    row: int


def _row_keys(scan: Scan) -> list[bytes | None]:
    """Per row, a digest of (azimuth, range bytes, intensity bytes); None for a row with no
    return at all. A 16-byte digest instead of the ~260 bytes themselves keeps an hour-long
    recording's set small; a collision between two different rows (2^-128) is not a concern."""
    keys: list[bytes | None] = []
    az = np.ascontiguousarray(scan.azimuth, dtype="<i4")
    rng = np.ascontiguousarray(scan.range_mm, dtype="<i2")
    inten = np.ascontiguousarray(scan.intensity, dtype="<i2")
    returned = np.count_nonzero(rng, axis=1) > 0
    for k in range(scan.n_acq):
        if not returned[k]:
            keys.append(None)
            continue
        digest = hashlib.blake2b(az[k].tobytes(), digest_size=16)
        digest.update(rng[k].tobytes())
        digest.update(inten[k].tobytes())
        keys.append(digest.digest())
    return keys


class ScanChecker:
    """:func:`check_scan` over a stream of scans, plus "never a row in two scans".

    ``add`` each scan in the order it was delivered; it returns the violations that scan brings
    (also kept in :attr:`violations`). ``repeats=False`` turns the repeat rule off for sources
    whose rows are a pure function of the pose (a simulator without noise; see the module);
    ``expect_returns`` and ``physical`` are passed to :func:`check_scan` (``physical=False``
    turns the repeat rule off too: made-up rows repeat).
    """

    def __init__(
        self, *, expect_returns: bool = False, repeats: bool = True, physical: bool = True
    ) -> None:
        self.expect_returns = expect_returns
        self.physical = physical
        self.repeats = repeats and physical
        self.violations: list[str] = []
        self.scans = 0
        """Scans checked so far."""
        self.bad_scans = 0
        """Scans that broke at least one rule."""
        self._seen: dict[bytes, _Seen] = {}

    def add(self, scan: Scan) -> list[str]:
        """Check ``scan`` against its own rules and against every row seen before it."""
        found = check_scan(scan, expect_returns=self.expect_returns, physical=self.physical)
        self.scans += 1
        if self.repeats:
            found += self._repeats(scan)
        if found:
            self.bad_scans += 1
            self.violations += found
        return found

    def extend(self, scans: Iterable[Scan]) -> list[str]:
        """:meth:`add` each of ``scans``; the violations they brought."""
        found: list[str] = []
        for scan in scans:
            found += self.add(scan)
        return found

    def _repeats(self, scan: Scan) -> list[str]:
        name = scan_name(scan)
        repeated: list[tuple[int, _Seen]] = []
        for k, key in enumerate(_row_keys(scan)):
            if key is None:
                continue
            earlier = self._seen.get(key)
            if earlier is not None:
                repeated.append((k, earlier))
            else:
                self._seen[key] = _Seen(name, self.scans, k)
        if not repeated:
            return []
        k, earlier = repeated[0]
        if earlier.ordinal == self.scans:
            where = f"row {earlier.row} of the same scan"
        else:
            where = f"{earlier.scan} row {earlier.row} (scan {earlier.ordinal} of the stream)"
        more = len(repeated) - 1
        tail = f" (and {more} more row{'s' if more > 1 else ''})" if more else ""
        return [
            f"{name}: row {k} (azimuth {int(scan.azimuth[k])}) repeats {where}: one acquisition "
            f"delivered twice{tail}"
        ]

    @property
    def ok(self) -> bool:
        """No scan has broken a rule so far."""
        return not self.violations

    def summary(self) -> str:
        """``checked 12 scans: OK`` or ``3 violations in 2 scans (of 12 checked)``."""
        if self.ok:
            return f"checked {self.scans} scan{'s' if self.scans != 1 else ''}: OK"
        n = len(self.violations)
        return (
            f"{n} violation{'s' if n != 1 else ''} in {self.bad_scans} "
            f"scan{'s' if self.bad_scans != 1 else ''} (of {self.scans} checked)"
        )
