"""The server's per-acquisition and per-delivery code paths, held to what they replace.

Each fast path here has a plain equivalent (``dataclasses.replace``, ``Scan.age``, two frame
reads, a poll before a look, a notified timer): the tests check that the results are the same,
including the corner cases the shortcuts rely on.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import weakref

import numpy as np
import pytest

from benchmarks.throughput import KEEP_UP, Trial
from biris_hw.bus.memory import MemoryWindow
from biris_hw.data import ConnectionKind, Direction, Point, Scan
from biris_hw.errors import LineClosed
from biris_hw.ipc import Mailbox
from biris_hw.irq.eventfd import EventFdLine
from biris_hw.server.acquisition import AcquisitionReader
from biris_hw.server.delivery import ClientConn, stamp
from biris_hw.server.tasks import DeadlineTimer
from biris_hw.timebase import timebase_of
from regs.biexec import ACQ_LINE_END
from regs.layout import AZIMUTH_DTYPE, FRAME_DTYPE, FrameAddressing
from tests.conftest import until

WAIT = 5.0


def _point(t: float = 1.0) -> Point:
    return Point(
        azimuth=5,
        range_mm=100,
        profile=np.arange(64, dtype=np.int16),
        intensity=np.zeros(64, np.int16),
        t=t,
        acq=3,
        scan_seq=2,
    )


def _scan(n: int = 20) -> Scan:
    return Scan(
        direction=Direction.CW,
        seq=1,
        azimuth=np.arange(n, dtype=np.int32),
        range_mm=np.zeros((n, 64), np.int16),
        closest_mm=np.zeros(n, np.int16),
        intensity=np.zeros((n, 64), np.int16),
        t=np.linspace(1.0, 2.0, n)[::-1].copy(),  # newest first: age must use the maximum
    )


# -- delivery ------------------------------------------------------------------------------------
@pytest.mark.parametrize("item", [_point(), _scan(), _scan(0)], ids=["point", "scan", "empty"])
def test_stamp_is_replace_without_revalidation(item: Scan | Point) -> None:
    got = stamp(item, 7)
    want = dataclasses.replace(item, t_delivered=7)
    assert type(got) is type(want)
    assert got.t_delivered == 7.0 and isinstance(got.t_delivered, float)
    assert item.t_delivered is None  # the original is untouched
    for f in dataclasses.fields(want):
        a, b = getattr(got, f.name), getattr(want, f.name)
        assert a is b or a == b, f.name
    with pytest.raises(dataclasses.FrozenInstanceError):
        got.t_delivered = 8.0  # type: ignore[misc]


def test_recorded_ages_are_the_items_ages() -> None:
    me = weakref.ref(threading.current_thread())
    conn = ClientConn(1, ConnectionKind.DATA, me)
    first, second, empty = _scan(), _scan(5), _scan(0)
    items: list[Scan | Point] = [stamp(first, 3.0), stamp(second, 3.5), stamp(first, 4.0)]
    items += [stamp(empty, 5.0), stamp(_point(2.0), 2.25), stamp(second, 6.0)]
    for item in items:
        conn.record(item)
    ages = [item.age for item in items if item.age is not None]
    assert conn.delivered == len(items)
    assert conn.latency.count == len(ages) == 5
    assert conn.latency.summary()["max"] == max(ages)
    assert conn.latency.summary()["mean"] == pytest.approx(sum(ages) / len(ages))


# -- frames --------------------------------------------------------------------------------------
class _Link:
    """BIEXEC_COM at the end of a sequence: every acquisition is complete."""

    def acq_line(self) -> int:
        return ACQ_LINE_END

    def command(self) -> int:
        return 0  # BI_ACQUIRE has completed: the -128 is its sequence's end


def _reference_read(
    window: MemoryWindow, addr: FrameAddressing, slot: int, samples: int, max_range: int
) -> tuple[int, int, int, np.ndarray, np.ndarray]:
    """The acquisition as two frame reads and the plain range test make it."""
    count = samples + 1
    rng = np.frombuffer(window.read(addr.range_frame(slot), 2 * count), FRAME_DTYPE)
    inten = np.frombuffer(window.read(addr.intensity_frame(slot), 2 * count), FRAME_DTYPE)
    azimuth = int(np.frombuffer(window.read(addr.azimuth_entry(slot), 4), AZIMUTH_DTYPE)[0])
    profile = rng[1:].astype(np.int16)
    bad = (profile > max_range) | (profile < 0)
    discarded = int(np.count_nonzero(bad & (profile != 0)))
    profile[bad] = 0
    closest = int(rng[0])
    closest = 0 if closest > max_range or closest < 0 else closest
    return azimuth, closest, discarded, profile, inten[1:].astype(np.int16)


@pytest.mark.parametrize("samples", [64, 128])
@pytest.mark.parametrize("gap_words", [0, 1, 7, 300])  # frame size beyond the frame itself
@pytest.mark.parametrize("max_range", [1, 2000, 0x7FFE, 0x7FFF, 0x8000, 0xFFFF])
def test_frame_read_matches_two_reads(samples: int, gap_words: int, max_range: int) -> None:
    frame_size = 2 * (samples + 1 + gap_words)
    addr = FrameAddressing(0x40, frame_size, 0x40 + 2 * 12 * frame_size)
    window = MemoryWindow(addr.azimuth_offset + 4 * 12)
    rng = np.random.default_rng(samples + gap_words)
    values = np.array([0, 1, 2000, 1999, 2001, 0x7FFE, 0x7FFF, -1, -0x8000, 12], dtype=">i2")
    words = rng.choice(values, addr.azimuth_offset // 2)
    window.write(0, words.tobytes())
    azimuths = rng.integers(-(2**31), 2**31, 12, dtype=np.int64).astype(">i4")
    window.write(addr.azimuth_offset, azimuths.tobytes())
    reader = AcquisitionReader(window, _Link(), lambda: 0.0, max_range)  # type: ignore[arg-type]
    reader.configure(addr, samples, 0.05)
    reader.begin(seq_id=1, n=12)
    reader.written()  # BI_ACQUIRE written: BIEXEC_COM is its sequence's from now
    with reader.lock:
        drained = reader.drain()
    assert drained.finished and drained.lost == 0
    assert [got.index for got in drained.acquisitions] == list(range(12))
    for slot, got in enumerate(drained.acquisitions):
        azimuth, closest, discarded, profile, intensity = _reference_read(
            window, addr, slot, samples, max_range
        )
        assert (got.azimuth, got.closest_mm, got.discarded) == (azimuth, closest, discarded)
        assert type(got.azimuth) is int
        for mine, theirs in ((got.profile, profile), (got.intensity, intensity)):
            assert mine.dtype == np.int16 and not mine.flags.writeable
            np.testing.assert_array_equal(mine, theirs)


# -- interrupt lines -----------------------------------------------------------------------------
def test_a_look_takes_what_is_pending_and_never_blocks() -> None:
    line = EventFdLine()
    try:
        assert line.wait(0) == 0
        line.trigger(3)
        assert line.wait(0) == 3
        assert line.wait(0) == 0
        assert line.wait(-1.0) == 0
    finally:
        line.close()
    with pytest.raises(LineClosed):
        line.wait(0)


def test_repeated_and_concurrent_waits_each_see_their_interrupts() -> None:
    line = EventFdLine()
    got: list[int] = []
    errors: list[BaseException] = []
    progress = threading.Condition()

    def waiter() -> None:
        try:
            while True:
                count = line.wait(WAIT)
                with progress:
                    got.append(count)
                    progress.notify_all()
        except LineClosed:
            pass
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=waiter) for _ in range(3)]
    for thread in threads:
        thread.start()
    with progress:
        for sent in range(1, 201):
            line.trigger()  # one at a time: three waiters race for each, two find nothing
            assert progress.wait_for(lambda sent=sent: sum(got) >= sent, WAIT)  # type: ignore[misc]
    line.close()
    for thread in threads:
        thread.join(WAIT)
    assert not errors and sum(got) == 200 and 0 not in got


def test_the_kept_poll_set_follows_no_closed_line() -> None:
    before = len(os.listdir("/proc/self/fd"))
    for _ in range(20):
        line = EventFdLine()
        line.trigger()
        assert line.wait(WAIT) == 1
        line.close()
    assert len(os.listdir("/proc/self/fd")) == before


# -- mailbox -------------------------------------------------------------------------------------
def test_a_receiver_that_blocks_is_woken_by_a_later_send() -> None:
    mailbox = Mailbox("admin")
    mailbox.post("early")  # no receiver waits: nothing to notify
    assert mailbox.receive(WAIT).message == "early"
    got: list[object] = []
    receiver = threading.Thread(target=lambda: got.append(mailbox.receive(WAIT).message))
    receiver.start()
    until(lambda: mailbox.receivers == 1, what="the receiver blocked with the queue empty")
    mailbox.post("late")
    receiver.join(WAIT)
    assert got == ["late"]
    with pytest.raises(TimeoutError):
        mailbox.receive(0.01)


# -- timers --------------------------------------------------------------------------------------
class _Clock:
    """A hardware clock the test moves: the timer's deadlines pass when the test says so."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_rearming_later_moves_the_expiry_and_sooner_is_noticed() -> None:
    admin = Mailbox("admin")
    clock = _Clock()
    timer = DeadlineTimer("t", admin, timebase_of(clock, 1.0), lambda gen: gen)
    timer.start()
    try:
        gen = timer.arm(0.05)
        for _ in range(5):  # re-armed later and later, each time before the deadline passed
            clock.now += 0.02
            gen = timer.arm(0.05)
        assert admin.queued == 0  # no deadline has passed yet
        clock.now += 0.05  # the last one passes: it fires, with the last generation
        env = admin.receive(WAIT)
        assert env.message == gen
        env.reply(None)
        timer.arm(30.0)  # the task now sleeps towards 30 s (30 real seconds at scale 1)
        gen = timer.arm(0.02)  # sooner: it must be told, or it sleeps on
        clock.now += 0.02
        env = admin.receive(2.0)  # far less than 30 s
        assert env.message == gen
        env.reply(None)
        timer.arm(0.05)
        timer.disarm()  # a disarmed deadline never fires, even if the task wakes for it
        clock.now += 1.0
        with pytest.raises(TimeoutError):
            admin.receive(0.2)  # the task wakes within 0.05 s for the deadline it slept towards
    finally:
        admin.close()
        timer.stop()


# -- the throughput benchmark's judgement --------------------------------------------------------
def test_a_trial_that_made_acquisitions_too_slowly_did_not_keep_time() -> None:
    trial = Trial(time_scale=200.0, window=3.0, nominal_per_s=4000.0, max_lag_s=0.01)
    trial.made = trial.received = 100
    trial.acq_per_s = (1.0 - KEEP_UP) * 4000.0
    assert (trial.kept_up, trial.passed) == (True, True)
    trial.acq_per_s = 2500.0  # a saturated rig that caught up between sequences: small lag
    assert (trial.lag_ok, trial.rate_ok, trial.passed) == (True, False, False)
    trial.acq_per_s, trial.max_lag_s = 4100.0, 0.5
    assert (trial.lag_ok, trial.passed) == (False, False)
