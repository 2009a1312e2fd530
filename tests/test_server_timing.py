"""Acquisition times when the machine is busy: a scan's times are periodic and increasing.

BIRIS does not time-stamp its frames; the reader bounds the start of a sequence from each wake
(``now - ACQ_LINE * period``). A late first wake gives a loose bound that later, prompter wakes
tighten, so acquisitions read early carry later times than they should. The finished scan must
re-time them from the tightest bound: CI once saw a continuous sweep whose times went backwards.
"""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from biris_hw.bus.memory import MemoryWindow
from biris_hw.data import Direction
from biris_hw.server.acquisition import AcquisitionReader, RingState
from biris_hw.server.messages import Acquisition
from biris_hw.server.scan_assembly import ActiveScan, build_scan
from regs.biexec import ACQ_LINE_END, OFF_CURRENT_FRAME, BiexecCom
from regs.layout import FrameAddressing

SAMPLES = 64
PERIOD = 2 / 59.94
RING = 8
BIEXEC_COM_SIZE = ctypes.sizeof(BiexecCom)


class _Link:
    """ACQ_LINE as the test sets it; data-interrupt flags recorded; CURRENT_FRAME (which the
    reader reads once BIRIS has stopped a ring) in a small BIEXEC_COM window."""

    def __init__(self) -> None:
        self.line = -1
        self.flags: list[bool] = []
        self.window = MemoryWindow(BIEXEC_COM_SIZE)
        self.base = 0

    def set_current_frame(self, slot: int) -> None:
        self.window.write16(self.base + OFF_CURRENT_FRAME, slot & 0xFFFF)

    def acq_line(self) -> int:
        return self.line

    def command(self) -> int:
        return 0 if self.line == ACQ_LINE_END else 1  # completed only once the sequence ended

    def set_flags(self, *, data_int: bool) -> None:
        self.flags.append(data_int)


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _reader() -> tuple[AcquisitionReader, _Link, _Clock]:
    frame = 2 * (SAMPLES + 1)
    slots = 16  # room for a sequence of 10 and the ring of 8
    addr = FrameAddressing(0x40, frame, 0x40 + 2 * slots * frame)
    link, clock = _Link(), _Clock()
    reader = AcquisitionReader(
        MemoryWindow(addr.azimuth_offset + 4 * slots),
        link,  # type: ignore[arg-type]
        clock,
        2000,
    )
    reader.configure(addr, SAMPLES, PERIOD)
    return reader, link, clock


def _wake(
    reader: AcquisitionReader, link: _Link, clock: _Clock, line: int, t: float
) -> list[Acquisition]:
    link.line, clock.t = line, t
    with reader.lock:
        return list(reader.drain().acquisitions)


# wakes as (ACQ_LINE, how late after acquisition ACQ_LINE began): the first ones very late
LATE_THEN_PROMPT = [(2, 0.21), (3, 0.15), (5, 0.001), (6, 0.0005), (8, 0.0002)]


def _scan_of(acqs: list[Acquisition], ring: bool) -> np.ndarray:
    scan = ActiveScan(Direction.CW, 100, len(acqs), 1, ring=ring)
    for i, acq in enumerate(acqs):
        scan.acqs[i] = acq
    return build_scan(scan, SAMPLES, 1, None).t


def test_a_sequences_scan_is_timed_from_its_promptest_wake() -> None:
    reader, link, clock = _reader()
    start = 3.0  # acquisition 0 began here
    reader.begin(1, 10)
    reader.written()  # BI_ACQUIRE written: BIEXEC_COM is its sequence's from now
    acqs: list[Acquisition] = []
    for line, late in LATE_THEN_PROMPT:
        acqs += _wake(reader, link, clock, line, start + line * PERIOD + late)
    acqs += _wake(reader, link, clock, ACQ_LINE_END, start + 10 * PERIOD + 0.3)
    assert [a.index for a in acqs] == list(range(10))
    raw = np.array([a.t for a in acqs])
    assert np.any(np.diff(raw) <= 0)  # the stamps as read went backwards: the case in point
    t = _scan_of(acqs, ring=False)
    assert np.all(np.diff(t) > 0)
    np.testing.assert_allclose(np.diff(t), PERIOD, rtol=1e-9)
    # as late as the promptest wake (0.2 ms), never earlier than the truth
    truth = start + (np.arange(10) + 0.5) * PERIOD
    assert np.all(t >= truth - 1e-12)
    assert np.all(t - truth <= 0.0002 + 1e-12)


def test_a_continuous_sweep_is_timed_from_its_promptest_wake() -> None:
    reader, link, clock = _reader()
    reader.prime_ring()
    reader.ring_started(RING)
    _wake(reader, link, clock, 0, 1.0)  # the ring is live
    start = 1.0 + 20 * PERIOD  # ring acquisition 20 (slot 4) is in exposure when the sweep opens
    link.line, clock.t = 20 % RING, start + 0.25  # and the opening wake is very late
    reader.open_sweep(7)
    acqs: list[Acquisition] = []
    for line, late in LATE_THEN_PROMPT:
        k = 20 + line
        acqs += _wake(reader, link, clock, k % RING, start + line * PERIOD + late)
    assert len(acqs) == 8 and all(a.seq_id == 7 for a in acqs)
    raw = np.array([a.t for a in acqs])
    assert np.any(np.diff(raw) <= 0)
    t = _scan_of(acqs, ring=True)
    np.testing.assert_allclose(np.diff(t), PERIOD, rtol=1e-9)
    truth = start + (np.arange(8) + 0.5) * PERIOD
    assert np.all(t >= truth - 1e-9)
    assert np.all(t - truth <= 0.0002 + 1e-9)


@pytest.mark.parametrize("n", [0, 1])
def test_short_scans_keep_their_times(n: int) -> None:
    reader, link, clock = _reader()
    reader.begin(1, n)
    reader.written()  # BI_ACQUIRE written: BIEXEC_COM is its sequence's from now
    acqs = _wake(reader, link, clock, ACQ_LINE_END, 5.0)
    t = _scan_of(acqs, ring=False)
    assert len(t) == n
    if n:
        assert t[0] == acqs[0].t


# -- continuous scanning: a sweep that turns straight round carries on ---------------------------
def _ring_reader() -> tuple[AcquisitionReader, _Link, _Clock, MemoryWindow]:
    reader, link, clock = _reader()
    window = reader._window
    assert isinstance(window, MemoryWindow)
    reader.prime_ring()
    reader.ring_started(RING)
    _wake(reader, link, clock, 0, 1.0)  # live
    return reader, link, clock, window


def _sweep(
    reader: AcquisitionReader, link: _Link, clock: _Clock, seq: int, k0: int, k1: int, follows: bool
) -> list[int]:
    """Open sweep ``seq`` with ring acquisition ``k0`` in exposure, end it (the head at rest)
    with ``k1`` in exposure; the ring acquisitions (absolute numbers) the sweep was handed.
    Its last is k1 + 1, the first exposed wholly after the head came to rest."""
    link.line, clock.t = k0 % RING, 1.0 + k0 * PERIOD
    reader.open_sweep(seq, follows=follows)
    got: list[Acquisition] = []
    for k in range(k0 + 1, k1 + 1):
        got += _wake(reader, link, clock, k % RING, 1.0 + k * PERIOD)
    with reader.lock:
        got += reader.end_sweep().acquisitions
    got += _wake(reader, link, clock, (k1 + 1) % RING, 1.0 + (k1 + 1) * PERIOD)
    assert reader.ring_state is RingState.ENDING
    got += _wake(reader, link, clock, (k1 + 2) % RING, 1.0 + (k1 + 2) * PERIOD)
    assert reader.ring_state is RingState.IDLE  # closed once the last frame was read
    assert all(a.seq_id == seq for a in got)
    # each is stamped at the middle of its exposure: that says which acquisition it is
    return [round((a.t - 1.0) / PERIOD - 0.5) for a in got]


def test_a_following_sweep_reads_on_from_the_last_frame_of_the_previous() -> None:
    reader, link, clock, _ = _ring_reader()
    first = _sweep(reader, link, clock, 1, 10, 14, follows=False)
    assert first == [10, 11, 12, 13, 14, 15]
    # the turn-around: acquisition 16 made while the administrator turned round
    second = _sweep(reader, link, clock, 2, 17, 20, follows=True)
    assert second == [16, 17, 18, 19, 20, 21]
    # not following: a new sweep starts at the frame in exposure
    third = _sweep(reader, link, clock, 3, 24, 25, follows=False)
    assert third == [24, 25, 26]


def test_a_sweep_cannot_follow_across_a_lap_of_the_ring() -> None:
    reader, link, clock, _ = _ring_reader()
    _sweep(reader, link, clock, 1, 10, 12, follows=False)  # read up to 13, closed at 14
    # a whole lap later: which frames are new is ambiguous, so it starts afresh
    assert _sweep(reader, link, clock, 2, 14 + RING, 15 + RING, follows=True) == [
        14 + RING,
        15 + RING,
        16 + RING,
    ]


def test_a_sweep_cut_short_is_not_followed() -> None:
    reader, link, clock, _ = _ring_reader()
    link.line, clock.t = 10 % RING, 1.0 + 10 * PERIOD
    reader.open_sweep(1)
    _wake(reader, link, clock, 11 % RING, 1.0 + 11 * PERIOD)
    link.set_current_frame(11 % RING)  # its last completed frame
    _wake(reader, link, clock, -128, 1.0 + 12 * PERIOD)  # BIRIS stopped under the sweep
    assert reader.ring_state is RingState.IDLE
    assert _sweep(reader, link, clock, 2, 14, 15, follows=True) == [14, 15, 16]
