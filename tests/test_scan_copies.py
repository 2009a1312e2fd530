"""A scan's arrays: copied once from the frames when the scan completes, read-only from then on.

Issue 23 part 7. The acquisition reader hands the administrator each frame's profile and intensity
as read-only int16 arrays. :func:`~biris_hw.server.scan_assembly.build_scan` stacks them into the
scan's ``(n_acq, samples)`` arrays: that is the one copy a scan needs. It used to make two more --
an ``astype(np.int16)`` of a stack that already was int16, and :class:`~biris_hw.data.Scan`'s own
copy of the writable result, made so that it could freeze it. The delivery code hands one scan's
arrays to every connection (:func:`~biris_hw.server.delivery.stamp`), which is safe only because
they are read-only: a client that writes into one gets numpy's ValueError, and no other client's
scan changes.
"""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from biris_hw import protocol as p
from biris_hw.data import ConnectionKind, Direction, Point, Scan
from biris_hw.server import messages as m
from biris_hw.server import scan_assembly
from biris_hw.server.delivery import stamp
from biris_hw.server.scan_assembly import ActiveScan, build_scan, point_of
from regs.biexec import BiCommand
from tests.core import Core

ARRAYS = ("azimuth", "range_mm", "closest_mm", "intensity", "t")
"""A Scan's array fields, in the order docs/api.md lists them."""


def _frame(values: NDArray[np.integer[Any]]) -> NDArray[np.int16]:
    """``values`` as the acquisition reader hands a frame's line over: its own, read-only."""
    line = values.astype(np.int16)
    line.flags.writeable = False
    return line


def _sweep(n: int, samples: int, *, seed: int = 0) -> ActiveScan:
    """A CCW sweep from 0 to ``10 * (n - 1)`` counts holding ``n`` acquisitions, every frame
    different (so that a row out of place or out of order shows), and acquisition 0 stamped
    with the loosest origin, so that building the scan re-times every one of them."""
    rng = np.random.default_rng(seed)
    scan = ActiveScan(Direction.CCW, destination=10 * (n - 1), n=n, seq_id=1, start=0)
    for k in range(n):
        scan.acqs[k] = m.Acquisition(
            seq_id=1,
            index=k,
            azimuth=10 * k,
            closest_mm=int(rng.integers(1, 30000)),
            profile=_frame(rng.integers(0, 30000, samples)),
            intensity=_frame(rng.integers(0, 255, samples)),
            t=1.0 + 0.0334 * k,
            discarded=0,
            t_origin=0.001 if k == 0 else 0.0,
        )
    return scan


@dataclass
class _Allocated:
    kept: int = 0
    """Bytes allocated while the block ran and still held at its end."""
    peak: int = 0
    """The most bytes the block held allocated at any one time."""


@contextmanager
def _allocations() -> Iterator[_Allocated]:
    """What the block allocates, numpy's array data included (numpy reports it to tracemalloc),
    counted in bytes above what was allocated when it began."""
    tracing = tracemalloc.is_tracing()
    if not tracing:
        tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before, _ = tracemalloc.get_traced_memory()
        allocated = _Allocated()
        yield allocated
        now, peak = tracemalloc.get_traced_memory()
        allocated.kept, allocated.peak = now - before, peak - before
    finally:
        if not tracing:
            tracemalloc.stop()


# -- one copy ------------------------------------------------------------------------------------


def test_building_a_scan_copies_the_frame_data_once() -> None:
    """Counted in memory, whatever path a copy takes: a second copy of the frames can only be
    made from a first one (or the frames) while the first is still held, so the frame data held
    at once rises to two scans' worth if there is one copy too many -- it was two with the old
    stack, astype and Scan copies. Frames of 4096 samples make the frame data dwarf everything
    else the scan holds (its per-acquisition vectors, its few Python objects)."""
    sweep = _sweep(100, 4096)
    frame_bytes = sum(a.profile.nbytes + a.intensity.nbytes for a in sweep.acqs.values())
    with _allocations() as allocated:
        scan = build_scan(sweep, 4096, 1, None)
    assert scan.range_mm.nbytes + scan.intensity.nbytes == frame_bytes
    assert allocated.kept >= frame_bytes  # the scan holds its one copy
    copies_at_once = allocated.peak / frame_bytes
    assert copies_at_once < 1.5, f"{copies_at_once:.2f} copies of the frame data held at once"


def test_scan_keeps_the_arrays_build_scan_made(monkeypatch: pytest.MonkeyPatch) -> None:
    """The copy happens in build_scan and nowhere after it: Scan keeps the very arrays it is
    given (they are read-only already, so it has no reason to copy them), and those are new
    arrays of their own, sharing no memory with the reader's frames."""
    given: dict[str, Any] = {}

    def spy(**fields: Any) -> Scan:
        given.update(fields)
        return Scan(**fields)

    monkeypatch.setattr(scan_assembly, "Scan", spy)
    sweep = _sweep(8, 64)
    scan = build_scan(sweep, 64, 1, None)
    for name in ARRAYS:
        array = getattr(scan, name)
        assert array is given[name], f"Scan copied {name}"
        assert not array.flags.writeable, f"{name} is writable"
        assert array.base is None, f"{name} is a view into a temporary"
    for acq in sweep.acqs.values():
        for frame in (acq.profile, acq.intensity):
            assert not np.shares_memory(scan.range_mm, frame)
            assert not np.shares_memory(scan.intensity, frame)


# -- the same scan --------------------------------------------------------------------------------


def test_the_scan_holds_the_frames_in_acquisition_order_with_its_dtypes() -> None:
    """Acquisitions arrive in any order; the scan is in index order, in docs/api.md's dtypes and
    shapes, and re-timed from the tightest origin (the one in-place step, made before freezing)."""
    sweep = _sweep(6, 64, seed=3)
    acqs = [sweep.acqs[k] for k in range(6)]
    sweep.acqs = {k: sweep.acqs[k] for k in (3, 0, 5, 1, 4, 2)}
    scan = build_scan(sweep, 64, 7, None)
    assert (scan.seq, scan.direction, scan.partial, scan.dropped) == (7, Direction.CCW, False, 0)
    expected: dict[str, tuple[NDArray[Any], type[np.generic], tuple[int, ...]]] = {
        "azimuth": (np.array([a.azimuth for a in acqs]), np.int32, (6,)),
        "range_mm": (np.stack([a.profile for a in acqs]), np.int16, (6, 64)),
        "closest_mm": (np.array([a.closest_mm for a in acqs]), np.int16, (6,)),
        "intensity": (np.stack([a.intensity for a in acqs]), np.int16, (6, 64)),
        "t": (np.array([1.0 - 0.001] + [1.0 + 0.0334 * k for k in range(1, 6)]), np.float64, (6,)),
    }
    for name, (values, dtype, shape) in expected.items():
        array = getattr(scan, name)
        assert array.dtype == dtype and array.shape == shape, name
        if name == "t":
            np.testing.assert_allclose(array, values, rtol=0, atol=1e-12)
        else:
            np.testing.assert_array_equal(array, values)


def test_an_empty_scan_has_its_shape_and_is_read_only_too() -> None:
    scan = build_scan(ActiveScan(Direction.CW, destination=-400, n=5, seq_id=2), 64, 1, None)
    assert scan.partial and scan.dropped == 5
    assert scan.range_mm.shape == scan.intensity.shape == (0, 64)
    for name in ARRAYS:
        array = getattr(scan, name)
        assert not array.flags.writeable, name
        assert array.dtype == {"azimuth": np.int32, "t": np.float64}.get(name, np.int16), name


# -- read-only where delivered --------------------------------------------------------------------


def _writes(array: NDArray[Any]) -> Callable[[], None]:
    def write() -> None:
        array[(0,) * array.ndim] = 1

    return write


def _scan_of(answer: object) -> Scan:
    """The scan of READY_FOR_DATA's answer, ``(scan, dropped)``."""
    assert isinstance(answer, tuple)
    scan, _dropped = answer
    assert isinstance(scan, Scan)
    return scan


def test_a_delivered_scan_is_shared_read_only_between_connections(core: Core) -> None:
    """Two DATA connections waiting when the scan completes, and a NORMAL connection asking for
    it afterwards, all get the same arrays (the waiting ones even the same stamped Scan, the
    request a Scan of its own), and none of them can write into them."""
    conn = core.open()
    first, second = core.open(ConnectionKind.DATA), core.open(ConnectionKind.DATA)
    ready = [core.send(p.ReadyForData(data)) for data in (first, second)]
    assert core.call(p.SingleScanRqst(conn, 400)) == 400
    acquire = core.command()
    assert acquire is not None and acquire.code == BiCommand.BI_ACQUIRE
    assert core.move() is not None
    core.acquisitions(acquire.seq_id, range(acquire.n_acquisitions))
    core.complete(acquire)
    core.arrive()
    a, b = (_scan_of(ticket.wait(0)) for ticket in ready)
    requested = core.call(p.RequestScanData(conn, Direction.CCW))
    assert isinstance(requested, Scan)
    assert requested is not a and a.n_acq == acquire.n_acquisitions > 0
    for name in ARRAYS:
        array = getattr(a, name)
        assert array is getattr(b, name) and array is getattr(requested, name), name
        assert not array.flags.writeable, name
        with pytest.raises(ValueError, match="read-only"):
            _writes(array)()


def test_a_stamped_scan_or_point_shares_its_arrays_read_only() -> None:
    """What every delivery does to a scan or a point: a copy of the object, not of its arrays."""
    sweep = _sweep(4, 64)
    scan = build_scan(sweep, 64, 1, None)
    point = point_of(sweep.acqs[2], sweep, 1, None)
    delivered_scan, delivered_point = stamp(scan, 5.0), stamp(point, 5.0)
    assert delivered_scan.t_delivered == delivered_point.t_delivered == 5.0
    for name in ARRAYS:
        assert getattr(delivered_scan, name) is getattr(scan, name)
    for name in ("profile", "intensity"):
        array = getattr(delivered_point, name)
        assert array is getattr(point, name) and not array.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            _writes(array)()


def test_a_point_shares_its_frame_and_copies_a_writable_one() -> None:
    """A point is one frame's line as it is: the reader's read-only arrays are taken without a
    copy; a writable one (a test's fake feed) is copied once, so that its owner cannot change a
    delivered point."""
    sweep = _sweep(3, 64)
    acq = sweep.acqs[1]
    point = point_of(acq, sweep, 1, None)
    assert point.profile is acq.profile and point.intensity is acq.intensity
    line = np.arange(64, dtype=np.int16)
    loose = m.Acquisition(1, 1, 10, 100, line, line, 1.0, 0)
    copied = point_of(loose, sweep, 1, None)
    assert isinstance(copied, Point) and not copied.profile.flags.writeable
    assert not np.shares_memory(copied.profile, line)
    line[0] = 999
    assert copied.profile[0] == 0 and copied.intensity[0] == 0
