"""The mechanisms that shorten the data path, held to the behaviour they must keep.

* the level-2 demultiplexer runs the data notifier itself (no logical line, no second thread);
* the data notifier sends NEW_POINT and collects the reply only before its next send;
* the mailbox wakes its receiver with a doorbell lock instead of a condition;
* a complete scan handed to many connections is stamped once;
* a Point whose fields are already valid skips the conversions.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest

from biris_hw.bus.memory import MemoryWindow
from biris_hw.data import ConnectionKind, DeliveryPolicy, Direction, Point, Scan
from biris_hw.ipc import Mailbox, TaskStopped
from biris_hw.irq import EventFdLine
from biris_hw.server.acquisition import Drained
from biris_hw.server.connections import Connections
from biris_hw.server.counters import Counters
from biris_hw.server.isr import Level2Demux, Logical
from biris_hw.server.messages import Acquisition, ContinuousLive, NewPoint, SweepDataDone
from biris_hw.server.tasks import BirisDataNotifier
from regs.biexec import OFF_COMMAND, BiCommand
from regs.bit3 import BIT3_SPACE
from tests.conftest import until

WAIT = 5.0
"""Timeout for things that should happen almost at once; only reached when a test fails."""

BIEXEC = 0x100
DATA, CMD = Logical.BIRIS_DATA_DEV, Logical.BIRIS_CMD


# -- the demultiplexer runs the data notifier ----------------------------------------------------


@dataclass
class Level2:
    physical: EventFdLine
    biris: MemoryWindow
    demux: Level2Demux

    def interrupt(self, command: int) -> None:
        self.biris.write16(BIEXEC + OFF_COMMAND, command)
        self.physical.trigger()


@pytest.fixture
def l2() -> Iterator[Level2]:
    physical = EventFdLine()
    coupler = MemoryWindow(BIT3_SPACE)
    biris = MemoryWindow(0x1000)
    demux = Level2Demux(physical, coupler, biris, BIEXEC)
    try:
        yield Level2(physical, biris, demux)
    finally:
        demux.close()
        physical.close()
        coupler.close()
        biris.close()


@dataclass
class Recorder:
    """A data notifier that records its calls and answers what it is told to."""

    answer: bool = True
    fail: bool = False
    calls: list[tuple[int, str]] = field(default_factory=list)
    called: threading.Semaphore = field(default_factory=lambda: threading.Semaphore(0))

    def __call__(self, count: int) -> bool:
        self.calls.append((count, threading.current_thread().name))
        self.called.release()
        if self.fail:
            raise RuntimeError("notifier bug")
        return self.answer


def test_data_runs_the_attached_notifier_in_the_demultiplexer_thread(l2: Level2) -> None:
    notifier = Recorder()
    l2.demux.attach_data_notifier(notifier)
    l2.demux.start()
    l2.interrupt(BiCommand.BI_ACQUIRE)
    assert notifier.called.acquire(timeout=WAIT)
    assert notifier.calls == [(1, "level2_isr")]
    assert l2.demux.counts[DATA] == 1
    assert l2.demux.line(DATA).wait(0) == 0  # the line was not raised as well


def test_a_notifier_whose_task_ended_hands_data_back_to_the_line(l2: Level2) -> None:
    notifier = Recorder(answer=False)
    l2.demux.attach_data_notifier(notifier)
    l2.demux.start()
    l2.interrupt(BiCommand.BI_ACQUIRE)
    assert notifier.called.acquire(timeout=WAIT)
    l2.interrupt(BiCommand.BI_ACQUIRE)
    assert l2.demux.line(DATA).wait(WAIT) == 1
    assert len(notifier.calls) == 1
    assert l2.demux.counts[DATA] == 2


def test_a_failing_notifier_does_not_stop_the_other_interrupts(l2: Level2) -> None:
    notifier = Recorder(fail=True)
    l2.demux.attach_data_notifier(notifier)
    l2.demux.start()
    l2.interrupt(BiCommand.BI_ACQUIRE)
    assert notifier.called.acquire(timeout=WAIT)
    l2.interrupt(0)  # COMMAND cleared: a completion
    assert l2.demux.line(CMD).wait(WAIT) == 1
    l2.interrupt(BiCommand.BI_ACQUIRE)
    assert notifier.called.acquire(timeout=WAIT)  # still attached
    assert l2.demux.running


def test_in_continuous_mode_data_is_notified_before_the_command_line_is_raised(
    l2: Level2,
) -> None:
    seen_cmd_pending: list[int] = []

    def notifier(count: int) -> bool:
        seen_cmd_pending.append(l2.demux.line(CMD).wait(0))
        return True

    l2.demux.attach_data_notifier(notifier)
    l2.demux.set_continuous(True)
    l2.demux.start()
    l2.interrupt(0)
    assert l2.demux.line(CMD).wait(WAIT) == 1
    assert seen_cmd_pending == [0]


# -- the data notifier: send now, collect the reply before the next send --------------------------


def _acq(index: int) -> Acquisition:
    profile = np.zeros(4, np.int16)
    return Acquisition(1, index, 0, 0, profile, profile, float(index), 0)


class FakeReader:
    def __init__(self, *drains: Drained) -> None:
        self.lock = threading.Lock()
        self._drains = list(drains)

    def drain(self) -> Drained:
        assert self.lock.locked()
        return self._drains.pop(0)


def _notifier(inbox: Mailbox, reader: FakeReader) -> BirisDataNotifier:
    return BirisDataNotifier(inbox, reader)  # type: ignore[arg-type]


def test_new_point_is_posted_one_way_and_the_routine_never_waits() -> None:
    """The data notifier runs in the level-2 routine's thread: it must never block on the
    administrator, or BIRIS_CMD, PERR and BERR would be demultiplexed late."""
    inbox = Mailbox("admin")
    reader = FakeReader(
        Drained((_acq(0),), 0, False), Drained((_acq(1),), 2, False), Drained((), 0, False)
    )
    notify = _notifier(inbox, reader)
    assert notify(1) is True  # NEW_POINT queued, unanswered
    assert notify(1) is True  # and the next one too: no wait for the first's reply
    assert inbox.queued == 2
    first, second = inbox.receive(timeout=0), inbox.receive(timeout=0)
    assert isinstance(first.message, NewPoint) and first.message.acquisitions[0].index == 0
    assert (
        isinstance(second.message, NewPoint) and second.message.lost == 2
    )  # in the reader's order
    assert notify(1) is True  # nothing drained: nothing sent
    assert inbox.queued == 0


def test_everything_a_drain_completed_is_sent_in_order() -> None:
    inbox = Mailbox("admin")
    reader = FakeReader(Drained((_acq(0),), 0, True, live=True, sweep_done=7))
    kinds: list[type] = []

    def admin() -> None:
        for _ in range(3):
            env = inbox.receive(timeout=WAIT)
            kinds.append(type(env.message))
            env.reply(None)

    thread = threading.Thread(target=admin)
    thread.start()
    assert _notifier(inbox, reader)(1) is True
    thread.join(WAIT)
    assert kinds == [NewPoint, ContinuousLive, SweepDataDone]


def test_a_refused_message_is_logged_and_the_notifier_goes_on() -> None:
    inbox = Mailbox("admin")
    reader = FakeReader(Drained((_acq(0),), 0, False), Drained((_acq(1),), 0, False))
    notify = _notifier(inbox, reader)
    notify(1)
    inbox.receive(timeout=0).fail(ValueError("refused"))
    assert notify(1) is True
    assert inbox.queued == 1


def test_the_notifier_ends_when_the_administrator_stops() -> None:
    inbox = Mailbox("admin")
    reader = FakeReader(Drained((_acq(0),), 0, False))
    inbox.close()
    assert _notifier(inbox, reader)(1) is False


# -- the mailbox's doorbell -----------------------------------------------------------------------


def _blocked_receiver(inbox: Mailbox, got: list[object], timeout: float | None = WAIT) -> Callable:
    def run() -> None:
        try:
            got.append(inbox.receive(timeout=timeout).message)
        except (TaskStopped, TimeoutError) as exc:
            got.append(type(exc))

    return run


def _wait_receiving(inbox: Mailbox, n: int) -> None:
    until(lambda: inbox.receivers == n, what=f"{n} receiver(s) blocked in receive()")


def test_a_ring_nobody_took_does_not_make_the_next_receive_return_empty() -> None:
    inbox = Mailbox("admin")
    with pytest.raises(TimeoutError):
        inbox.receive(timeout=0.01)
    # leave the doorbell rung with nobody waiting: a receiver that timed out just as it rang
    with inbox._lock:
        inbox._receiving += 1
    inbox.post("stale ring")
    with inbox._lock:
        inbox._receiving -= 1
    assert inbox.receive(timeout=0).message == "stale ring"
    with pytest.raises(TimeoutError):  # the stale ring is taken, the queue is empty: it waits
        inbox.receive(timeout=0.05)
    got: list[object] = []
    thread = threading.Thread(target=_blocked_receiver(inbox, got))
    thread.start()
    _wait_receiving(inbox, 1)
    inbox.post("later")
    thread.join(WAIT)
    assert got == ["later"]


def test_two_blocked_receivers_each_get_one_of_two_messages() -> None:
    inbox = Mailbox("admin")
    got: list[object] = []
    threads = [threading.Thread(target=_blocked_receiver(inbox, got)) for _ in range(2)]
    for thread in threads:
        thread.start()
    _wait_receiving(inbox, 2)
    inbox.post("a")
    inbox.post("b")
    for thread in threads:
        thread.join(WAIT)
    assert sorted(got) == ["a", "b"]  # type: ignore[type-var]
    assert inbox.receivers == 0


def test_close_wakes_every_blocked_receiver() -> None:
    inbox = Mailbox("admin")
    got: list[object] = []
    threads = [threading.Thread(target=_blocked_receiver(inbox, got, None)) for _ in range(3)]
    for thread in threads:
        thread.start()
    _wait_receiving(inbox, 3)
    inbox.close()
    for thread in threads:
        thread.join(WAIT)
    assert got == [TaskStopped] * 3


# -- one stamped scan for every connection ---------------------------------------------------------


def _scan() -> Scan:
    return Scan(
        direction=Direction.CW,
        seq=1,
        azimuth=np.arange(3, dtype=np.int32),
        range_mm=np.zeros((3, 4), np.int16),
        closest_mm=np.zeros(3, np.int16),
        intensity=np.zeros((3, 4), np.int16),
        t=np.array([1.0, 2.0, 3.0]),
    )


def test_a_scan_for_many_waiting_connections_is_stamped_once_and_counted_for_each() -> None:
    counters = Counters()
    clients = Connections(lambda: 5.0, counters)
    inbox = Mailbox("admin")
    owner = threading.current_thread()
    conns = [clients.open(ConnectionKind.DATA, DeliveryPolicy.LATEST, None, owner)]
    conns.append(clients.open(ConnectionKind.DATA, DeliveryPolicy.EVERY_BUFFER, None, owner))
    queued = clients.open(ConnectionKind.DATA, DeliveryPolicy.LATEST, None, owner)
    tickets = []
    for conn in conns:
        tickets.append(inbox.post(conn.ident))
        clients.ready(inbox.receive(timeout=0), conn)
    scan = _scan()
    clients.deliver(scan)
    sent = [ticket.wait(WAIT) for ticket in tickets]
    items = [item for item, _ in sent]  # type: ignore[misc]
    assert items[0] is items[1] and items[0] is not scan
    assert items[0].t_delivered == 5.0 and scan.t_delivered is None
    np.testing.assert_array_equal(items[0].t, scan.t)
    assert counters.deliveries == 2
    assert [c.delivered for c in conns] == [1, 1]
    assert list(queued.queue) == [scan]  # not ready: queued unstamped, stamped when asked for


# -- Point: already-valid fields ------------------------------------------------------------------


def _frozen(values: list[int]) -> np.ndarray:
    array = np.array(values, np.int16)
    array.flags.writeable = False
    return array


def test_a_point_of_valid_fields_is_the_point_the_checks_would_make() -> None:
    profile, intensity = _frozen([1, 2, 3]), _frozen([4, 5, 6])
    fast = Point(5, 100, profile, intensity, 1.5, 3, 2)
    slow = Point(np.int64(5), np.int16(100), [1, 2, 3], [4, 5, 6], 1.5, 3, 2)  # type: ignore[arg-type]
    for name in ("azimuth", "range_mm", "t", "acq", "scan_seq", "elevation", "t_delivered"):
        assert getattr(fast, name) == getattr(slow, name)
        assert type(getattr(fast, name)) is type(getattr(slow, name))
    assert fast.profile is profile and fast.intensity is intensity  # shared, not copied
    np.testing.assert_array_equal(fast.profile, slow.profile)


@pytest.mark.parametrize(
    "change",
    [
        {"acq": -1},
        {"scan_seq": -1},
        {"t": None},
        {"mount": "roof"},
        {"intensity": _frozen([1, 2])},
    ],
)
def test_a_point_with_a_bad_field_is_still_refused(change: dict[str, object]) -> None:
    fields: dict[str, object] = {
        "azimuth": 5,
        "range_mm": 100,
        "profile": _frozen([1, 2, 3]),
        "intensity": _frozen([4, 5, 6]),
        "t": 1.5,
        "acq": 3,
        "scan_seq": 2,
    }
    fields.update(change)
    with pytest.raises(ValueError):
        Point(**fields)  # type: ignore[arg-type]


def test_a_writable_array_is_still_copied() -> None:
    profile = np.array([1, 2, 3], np.int16)
    point = Point(5, 100, profile, _frozen([4, 5, 6]), 1.5, 3, 2)
    assert point.profile is not profile and not point.profile.flags.writeable
