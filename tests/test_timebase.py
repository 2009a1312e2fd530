"""The time-and-wait abstraction (biris_hw.timebase): scaled real time and virtual time.

Virtual time is checked to the exact float: a wait that times out returns at exactly its
deadline, and time moves only when every participant waits. Synchronisation is never a real
sleep: in virtual time the domain itself orders things (a driver's ``tb.sleep(1)`` returns only
once everyone else waits), and the few checks of state no event announces use ``until``.
Scaled time runs the same behaviours at x1000, with real waits.
"""

from __future__ import annotations

import contextlib
import os
import random
import sys
import threading
import time
from collections.abc import Callable, Iterator
from types import FrameType

import pytest

from biris_hw.timebase import (
    HwCondition,
    HwThread,
    ScaledTime,
    TimeBase,
    VirtualTime,
    VirtualTimeDeadlock,
    VirtualTimeStall,
)
from tests.conftest import until

pytestmark = pytest.mark.timeout(20)  # a broken domain hangs: fail fast instead

FAST = 1000.0  # scaled time's rate in these tests: 1 hw s is 1 real ms


class Crew:
    """Threads of one time base; their exceptions are collected and re-raised by ``finish``."""

    def __init__(self, tb: TimeBase) -> None:
        self.tb = tb
        self.threads: list[HwThread] = []
        self.errors: list[BaseException] = []

    def spawn(self, name: str, body: Callable[..., object], *args: object) -> HwThread:
        def run() -> None:
            try:
                body(*args)
            except BaseException as exc:
                self.errors.append(exc)

        thread = self.tb.Thread(run, name=name, daemon=True)
        thread.start()
        self.threads.append(thread)
        return thread

    def finish(self) -> None:
        for thread in self.threads:
            assert self.tb.join_thread(thread), f"{thread.name} did not end"
        if self.errors:
            raise self.errors[0]


def steps(*actions: Callable[[], object]) -> Callable[[], None]:
    """One thread body doing ``actions`` in turn."""

    def body() -> None:
        for action in actions:
            action()

    return body


@contextlib.contextmanager
def eventfds(count: int) -> Iterator[list[int]]:
    fds = [os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK) for _ in range(count)]
    try:
        yield fds
    finally:
        for fd in fds:
            os.close(fd)


def raise_fd(tb: TimeBase, fd: int) -> None:
    """What an interrupt line's trigger will do: write the descriptor, then kick the domain."""
    os.eventfd_write(fd, 1)
    tb.kick(fd)


# -- virtual time: when time moves --------------------------------------------------------------


def test_time_starts_where_asked_and_stands_still_while_anyone_runs() -> None:
    tb = VirtualTime(start=5.0)
    order: list[str] = []
    seen: list[float] = []

    def spin() -> None:  # a participant busy on the CPU for 50 ms of real time
        end = time.monotonic() + 0.05
        while time.monotonic() < end:
            seen.append(tb.now())
        order.append("spun")

    def nap() -> None:
        tb.sleep(1.0)
        order.append(f"slept until {tb.now()}")

    crew = Crew(tb)
    crew.spawn("napper", nap)
    crew.spawn("spinner", spin)
    end = time.monotonic() + 0.05  # the driver (this thread) spins too
    while time.monotonic() < end:
        assert tb.now() == 5.0
    crew.finish()
    assert set(seen) == {5.0}
    assert order == ["spun", "slept until 6.0"]  # the nap could not end while anyone ran
    assert tb.now() == 6.0 and tb.advances == 1


def test_sleepers_wake_in_deadline_order_at_exactly_their_deadlines() -> None:
    tb = VirtualTime()
    woke: list[tuple[float, float]] = []
    deadlines = [0.3, 0.1, 1.0 / 3.0, 0.1, 0.2]

    def sleeper(deadline: float) -> None:
        tb.sleep_until(deadline, what=f"deadline {deadline}")
        woke.append((deadline, tb.now()))

    crew = Crew(tb)
    for i, deadline in enumerate(deadlines):
        crew.spawn(f"sleeper-{i}", sleeper, deadline)
    crew.finish()
    assert [t for _, t in woke] == sorted(deadlines)  # in order, ties side by side
    assert all(deadline == t for deadline, t in woke)  # each at exactly its deadline
    assert tb.now() == 1.0 / 3.0 and tb.advances == 4  # one jump per distinct deadline


def test_relative_sleeps_add_up_exactly() -> None:
    tb = VirtualTime(start=0.1)
    tb.sleep(0.2)
    tb.sleep(0.2)
    assert tb.now() == 0.1 + 0.2 + 0.2
    tb.sleep(0.0)
    tb.sleep(-1.0)
    tb.sleep_until(0.0)  # in the past: at once
    assert tb.now() == 0.1 + 0.2 + 0.2 and tb.advances == 2


def test_condition_wait_times_out_at_exactly_now_plus_timeout() -> None:
    tb = VirtualTime(start=1.0 / 3.0)
    cond = tb.Condition()
    t0 = tb.now()
    with cond:
        assert cond.wait(0.1, what="a timer") is False
        assert tb.now() == t0 + 0.1
        t1 = tb.now()
        assert cond.wait_for(lambda: False, 0.7) is False
        assert tb.now() == t1 + 0.7
        t2 = tb.now()
        assert cond.wait(0.0) is False and cond.wait(-3.0) is False
        assert cond.wait_for(lambda: 42, 1.0) == 42  # true at once: no wait
    assert tb.now() == t2
    with pytest.raises(RuntimeError, match="un-acquired"):
        cond.wait(1.0)
    with pytest.raises(RuntimeError, match="un-acquired"):
        cond.notify()


def test_a_notify_wakes_the_waiter_at_the_instant_it_is_made() -> None:
    tb = VirtualTime()
    cond = tb.Condition(threading.Lock())  # a plain lock works too
    state = {"ready": False}
    got: list[tuple[bool, float]] = []

    def waiter() -> None:
        with cond:
            ok = cond.wait_for(lambda: state["ready"], 10.0, what="ready")
            got.append((ok, tb.now()))

    crew = Crew(tb)
    crew.spawn("waiter", waiter)
    tb.sleep(2.0)  # returns at 2 only once the waiter waits (the driver counts until then)
    with cond:
        state["ready"] = True
        cond.notify()
    crew.finish()
    assert got == [(True, 2.0)]
    assert tb.now() == 2.0  # the waiter's 10 s timeout never came due


def test_notify_n_wakes_exactly_n_waiters_and_notify_all_the_rest() -> None:
    tb = VirtualTime()
    cond = tb.Condition()
    woken: list[str] = []

    def waiter(name: str) -> None:
        with cond:
            assert cond.wait(what="a notify")
            woken.append(name)

    crew = Crew(tb)
    for name in "abcd":
        crew.spawn(name, waiter, name)
    tb.sleep(1.0)  # everyone waits now
    with cond:
        cond.notify(2)
    tb.sleep(1.0)  # the two woken have finished; the others wait again
    assert len(woken) == 2
    with cond:
        cond.notify_all()
    crew.finish()
    assert sorted(woken) == ["a", "b", "c", "d"]


def test_a_notify_never_goes_to_a_waiter_that_has_timed_out() -> None:
    tb = VirtualTime()
    cond = tb.Condition()
    results: dict[str, tuple[bool, float]] = {}

    def waiter(name: str, timeout: float | None) -> None:
        with cond:
            results[name] = (cond.wait(timeout, what=name), tb.now())

    crew = Crew(tb)
    crew.spawn("impatient", waiter, "impatient", 1.0)
    crew.spawn("patient", waiter, "patient", None)
    tb.sleep(0.5)  # both wait
    with cond:
        # "impatient" times out at 1.0 and then needs this lock back: it has timed out but not
        # yet returned when we notify. threading.Condition may spend the notify on it.
        tb.sleep_until(1.0)
        cond.notify(1)
    crew.finish()
    assert results == {"impatient": (False, 1.0), "patient": (True, 1.0)}


def test_event_set_wakes_every_waiter_and_clear_rearms_it() -> None:
    tb = VirtualTime()
    event = tb.Event()
    woke: list[tuple[bool, float]] = []

    def waiter() -> None:
        woke.append((event.wait(what="the event"), tb.now()))

    crew = Crew(tb)
    for i in range(3):
        crew.spawn(f"w{i}", waiter)
    tb.sleep(1.0)
    assert not event.is_set()
    event.set()
    crew.finish()
    assert woke == [(True, 1.0)] * 3
    assert event.is_set() and event.wait(5.0) and tb.now() == 1.0  # set: no wait
    event.clear()
    assert event.wait(0.5) is False and tb.now() == 1.5


# -- the hand-over rule -------------------------------------------------------------------------


@pytest.mark.parametrize("timeout", [1.0, None], ids=["timeouts", "no-deadlines"])
def test_a_token_passed_thousands_of_times_never_lets_time_move(timeout: float | None) -> None:
    """Six threads pass a token round a ring, each stage through another primitive (a
    condition, an event, an eventfd with a kick). If any wake were not handed over at the
    moment it is caused, the domain would see nobody running between a signal and the woken
    thread's resumption: time would jump (to a 1 s timeout, or to the sentinel's 0.5 s), or,
    with no deadline anywhere, the driver's join would see a deadlock."""
    tb = VirtualTime()
    stages, rounds = 6, 500
    passes = [0]
    failures: list[str] = []
    conds = [tb.Condition() for _ in range(stages)]
    counts = [0] * stages
    events = [tb.Event() for _ in range(stages)]
    sentinel_saw: list[int] = []

    with eventfds(stages) as fds:

        def give(i: int) -> None:
            kind = i % 3
            if kind == 0:
                with conds[i]:
                    counts[i] += 1
                    conds[i].notify()
            elif kind == 1:
                events[i].set()
            else:
                raise_fd(tb, fds[i])

        def take(i: int) -> bool:
            kind = i % 3
            if kind == 0:
                with conds[i]:
                    if not conds[i].wait_for(lambda: counts[i] > 0, timeout, what=f"stage {i}"):
                        return False
                    counts[i] -= 1
                    return True
            if kind == 1:
                if not events[i].wait(timeout, what=f"stage {i}"):
                    return False
                events[i].clear()
                return True
            if not tb.poll([fds[i]], timeout, what=f"stage {i}"):
                return False
            os.eventfd_read(fds[i])
            return True

        def stage(i: int) -> None:
            for _ in range(rounds):
                if not take(i):
                    failures.append(f"stage {i} timed out at t={tb.now()} after {passes[0]}")
                    return
                if tb.now() != 0.0:
                    failures.append(f"time moved to {tb.now()} after {passes[0]} passes")
                passes[0] += 1
                give((i + 1) % stages)

        crew = Crew(tb)
        if timeout is not None:
            crew.spawn(
                "sentinel", steps(lambda: tb.sleep(0.5), lambda: sentinel_saw.append(passes[0]))
            )
        for i in range(stages):
            crew.spawn(f"stage-{i}", stage, i)
        give(0)
        crew.finish()

    assert failures == []
    assert passes[0] == stages * rounds
    if timeout is None:
        assert tb.now() == 0.0 and tb.advances == 0
    else:
        assert sentinel_saw == [stages * rounds]  # it woke only after the ring had finished
        assert tb.now() == 0.5 and tb.advances == 1
        # timeouts that never fired do not pile up in the domain's deadline heap
        assert len(tb._deadlines) < 200
    assert tb.deadlock is None


def _slow_start(frame: FrameType, event: str, arg: object) -> None:
    """A trace hook for new threads: each one dawdles 5 ms before its first line of Python
    (fault injection: the gap a loaded host may leave between ``start()`` and ``run()``)."""
    sys.settrace(None)
    time.sleep(0.005)


def test_a_started_thread_counts_before_its_first_line() -> None:
    tb = VirtualTime()
    first_seen: list[float] = []
    crew = Crew(tb)
    threading.settrace(_slow_start)
    try:
        for i in range(8):
            crew.spawn(f"t{i}", steps(lambda: first_seen.append(tb.now()), lambda: tb.sleep(2.0)))
            tb.sleep(1.0)  # the driver waits the moment start() returns
    finally:
        threading.settrace(None)
    crew.finish()
    # Had a new thread not been counted until its first line ran, the driver's sleep would have
    # ended before it started, and it would have seen a later time.
    assert first_seen == [float(i) for i in range(8)]


# -- the driver, outsiders, deadlocks, stalls ---------------------------------------------------


def test_a_deadlock_raises_in_every_waiter_naming_who_waits_on_what() -> None:
    tb = VirtualTime()
    cond = tb.Condition()
    event = tb.Event()
    errors: dict[str, VirtualTimeDeadlock] = {}

    def on_inbox() -> None:
        with cond:
            try:
                cond.wait(what="inbox ALPHA")
            except VirtualTimeDeadlock as exc:
                errors["alpha"] = exc

    def on_line() -> None:
        try:
            event.wait(what="irq L2")
        except VirtualTimeDeadlock as exc:
            errors["beta"] = exc

    def outside() -> None:  # an outsider: not a participant
        try:
            tb.Event().wait(what="a reply")
        except VirtualTimeDeadlock as exc:
            errors["gamma"] = exc

    crew = Crew(tb)
    alpha = crew.spawn("alpha", on_inbox)
    crew.spawn("beta", on_line)
    gamma = threading.Thread(target=outside, name="gamma", daemon=True)
    gamma.start()
    until(lambda: any(w.thread == "gamma" for w in tb.waiting()), what="gamma to wait")
    with pytest.raises(VirtualTimeDeadlock) as caught:
        tb.join_thread(alpha)
    gamma.join(5.0)
    crew.finish()

    message = str(caught.value)
    assert "deadlock at t=0" in message
    for expected in (
        "'alpha' (participant) waits on inbox ALPHA, no deadline",
        "'beta' (participant) waits on irq L2, no deadline",
        "'gamma' (outsider) waits on a reply, no deadline",
        "'MainThread' (driver) waits on thread 'alpha' to end, no deadline",
    ):
        assert expected in message
    assert sorted(errors) == ["alpha", "beta", "gamma"]
    assert all(str(exc) == message for exc in errors.values())
    assert {w.thread for w in caught.value.waits} == {"alpha", "beta", "gamma", "MainThread"}
    assert isinstance(caught.value, RuntimeError)
    assert tb.deadlock is not None and str(tb.deadlock) == message
    assert tb.now() == 0.0


def test_an_idle_rig_is_not_a_deadlock_while_the_driver_is_outside() -> None:
    tb = VirtualTime()
    event = tb.Event()
    got: list[tuple[bool, float]] = []
    crew = Crew(tb)
    crew.spawn("server", lambda: got.append((event.wait(what="a request"), tb.now())))
    tb.leave()  # the test goes about its business outside the domain
    until(lambda: len(tb.waiting()) == 1, what="the server to wait")
    assert tb.deadlock is None  # everyone in the domain waits, nothing is due: idle
    tb.join()
    event.set()
    crew.finish()
    assert got == [(True, 0.0)] and tb.deadlock is None


def test_an_outsiders_deadline_counts_and_it_holds_no_time() -> None:
    tb = VirtualTime()
    jumps: list[float] = []
    tb.on_advance(jumps.append)
    woke: list[float] = []
    crew = Crew(tb)
    server = crew.spawn(
        "server", steps(lambda: tb.sleep_until(10.0), lambda: woke.append(tb.now()))
    )
    outsider = threading.Thread(
        target=lambda: tb.sleep_until(3.0, what="a nap"), name="outsider", daemon=True
    )
    outsider.start()
    until(lambda: any(w.thread == "outsider" for w in tb.waiting()), what="the outsider to wait")
    assert ("outsider", "a nap", 3.0, "outsider") in tb.waiting()
    tb.leave()  # the driver goes outside too: nobody in the domain runs now
    # Plain joins, outside the domain: the outsider's deadline is the earliest, so time jumps
    # there first; waking it holds no time, so the server gets its 10 with nobody's help.
    outsider.join(5.0)
    server.join(5.0)
    assert not outsider.is_alive() and not server.is_alive()
    assert jumps == [3.0, 10.0] and woke == [10.0]
    with pytest.raises(RuntimeError, match="does not participate"):
        tb.leave()


def test_the_driver_acts_at_the_instant_its_wait_ends() -> None:
    """Time does not run on behind the driver's back between two of its waits."""
    tb = VirtualTime()
    event = tb.Event()
    got: list[tuple[bool, float]] = []
    crew = Crew(tb)
    crew.spawn("watcher", lambda: got.append((event.wait(10.0), tb.now())))
    crew.spawn("ticker", steps(*[lambda: tb.sleep(0.25)] * 100))  # always something due
    tb.sleep(3.0)
    assert tb.now() == 3.0
    event.set()  # at exactly 3, however busy the others are
    crew.finish()
    assert got == [(True, 3.0)]


def test_participation_nests_and_leave_without_join_is_refused() -> None:
    tb = VirtualTime()
    with tb.participate("again"):  # the driver participates already: this nests
        pass
    tb.sleep(1.0)  # still a participant (counted), time moved only while it waited
    seen: list[object] = []

    def stranger() -> None:
        try:
            tb.leave()
        except RuntimeError as exc:
            seen.append(exc)
        with tb.participate("named"), tb.participate():
            seen.append(tb.describe())

    thread = threading.Thread(target=stranger)
    thread.start()
    thread.join(5.0)
    assert len(seen) == 2 and "does not participate" in str(seen[0])
    assert "2 runnable: 'MainThread', 'named'" in str(seen[1])
    assert tb.now() == 1.0 and "1 runnable: 'MainThread'" in tb.describe()


def test_a_thread_body_run_directly_participates_for_its_length() -> None:
    """An owner may run a thread's body in a thread of its own (Demultiplexer.run's shape)."""
    tb = VirtualTime()
    body = tb.Thread(lambda: tb.sleep(1.0), name="direct")
    body.run()  # in the driver, which participates already: the participation nests
    assert tb.now() == 1.0 and body._finished.is_set()
    assert "1 runnable: 'MainThread'" in tb.describe()
    other = tb.Thread(lambda: tb.sleep(1.0), name="owned")
    owner = threading.Thread(target=other.run, name="owner")
    owner.start()  # a plain thread: it joins for the body's length, then leaves
    # (the domain cannot know of it before it joins: let it get there before the driver waits)
    until(lambda: any(w.thread == "owned" for w in tb.waiting()), what="the body to sleep")
    assert tb.join_thread(other) and tb.now() == 2.0
    owner.join(5.0)
    assert not owner.is_alive() and "1 runnable: 'MainThread'" in tb.describe()


def test_a_thread_blocked_outside_the_domain_is_named_in_a_stall() -> None:
    tb = VirtualTime(stall_timeout=0.2)
    outside = threading.Event()  # a plain event: the domain cannot see this wait
    crew = Crew(tb)
    crew.spawn("stuck", outside.wait)
    started = time.monotonic()
    with pytest.raises(VirtualTimeStall) as caught:
        tb.sleep(1.0, what="a nap")
    assert time.monotonic() - started < 5.0
    outside.set()
    crew.finish()
    message = str(caught.value)
    assert "stalled" in message and "'stuck'" in message and "a nap" in message
    assert isinstance(caught.value, VirtualTimeDeadlock)
    assert tb.now() == 0.0


def test_join_thread_times_out_in_hardware_time_and_checks_its_thread() -> None:
    tb = VirtualTime()
    crew = Crew(tb)
    slow = crew.spawn("slow", lambda: tb.sleep(5.0))
    assert tb.join_thread(slow, 1.0) is False and tb.now() == 1.0
    assert slow.is_alive() and not slow.finished
    assert tb.join_thread(slow) is True and tb.now() == 5.0
    assert not slow.is_alive() and slow.timebase is tb and slow._finished.is_set()
    with pytest.raises(TypeError):
        tb.join_thread(threading.Thread(target=print))  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        tb.join_thread(VirtualTime().Thread(print))
    assert tb.join_thread(tb.Thread(print), 0.5) is False and tb.now() == 5.5  # never started
    with pytest.raises(VirtualTimeDeadlock, match="thread 'never' to end"):
        tb.join_thread(tb.Thread(print, name="never"))


# -- advance hooks ------------------------------------------------------------------------------


def test_advance_hooks_run_at_each_jump_before_the_due_waiters_wake() -> None:
    tb = VirtualTime()
    hardware = {"t": -1.0}  # what a simulator hooked here would update
    calls: list[float] = []
    refused: list[str] = []
    doorbell = tb.Event()
    rang: list[float] = []

    def hook(t: float) -> None:
        calls.append(t)
        assert tb.now() == t
        time.sleep(0.003)  # a slow update: a reader released too early would see the old value
        hardware["t"] = t
        if t == 1.5:
            doorbell.set()  # a hook may signal
        try:
            tb.sleep(1.0)
        except RuntimeError as exc:
            refused.append(str(exc))

    remove = tb.on_advance(hook)
    seen: list[tuple[float, float]] = []

    def reader(deadline: float) -> None:
        tb.sleep_until(deadline)
        seen.append((deadline, hardware["t"]))

    crew = Crew(tb)
    for deadline in (1.0, 2.0):
        crew.spawn(f"reader {deadline}", reader, deadline)
    crew.spawn("doorbell", steps(doorbell.wait, lambda: rang.append(tb.now())))
    crew.spawn("early", lambda: tb.sleep_until(1.5))
    crew.finish()
    assert calls == [1.0, 1.5, 2.0]
    assert sorted(seen) == [(1.0, 1.0), (2.0, 2.0)]  # the hardware was updated before they woke
    assert rang == [1.5]
    assert refused and all("must not wait" in text for text in refused)
    remove()
    tb.sleep(1.0)
    assert calls == [1.0, 1.5, 2.0] and tb.now() == 3.0


def test_a_failing_hook_is_logged_and_time_goes_on(caplog: pytest.LogCaptureFixture) -> None:
    tb = VirtualTime()

    def broken(t: float) -> None:
        raise ValueError(f"broken at {t}")

    tb.on_advance(broken)
    tb.sleep(1.0)
    tb.sleep(1.0)
    assert tb.now() == 2.0
    failures = [r for r in caplog.records if "advance hook" in r.getMessage() and r.exc_info]
    assert len(failures) == 2


# -- determinism ----------------------------------------------------------------------------------


def _watchdog_run(seed: int) -> list[tuple[float, str]]:
    """A worker doing jobs of random lengths under a watchdog re-armed by each job (a
    DeadlineTimer's shape), with a poller woken through an eventfd: the trace of who did what
    when."""
    rng = random.Random(seed)
    durations = [rng.uniform(0.05, 0.6) for _ in range(40)]
    tb = VirtualTime()
    trace: list[tuple[float, str]] = []
    lock = threading.Lock()

    def note(text: str) -> None:
        with lock:
            trace.append((tb.now(), text))

    cond = tb.Condition()
    state = {"armed": 0, "done": False}

    def watchdog() -> None:
        with cond:
            while not state["done"]:
                generation = state["armed"]

                def rearmed(generation: int = generation) -> bool:
                    return state["armed"] != generation or bool(state["done"])

                if not cond.wait_for(rearmed, 0.35, what="re-arm"):
                    note(f"watchdog expired (generation {generation})")
                    cond.wait_for(rearmed, what="re-arm after expiry")

    with eventfds(1) as (fd,):

        def worker() -> None:
            for i, duration in enumerate(durations):
                tb.sleep(duration, what=f"job {i}")
                note(f"job {i} done")
                raise_fd(tb, fd)
                with cond:
                    state["armed"] += 1
                    cond.notify()
            with cond:
                state["done"] = True
                cond.notify()

        def poller() -> None:
            for _ in durations:
                assert tb.poll([fd], what="the worker's fd") == [fd]
                os.eventfd_read(fd)
                note("poller saw a job")

        crew = Crew(tb)
        crew.spawn("watchdog", watchdog)
        crew.spawn("poller", poller)
        crew.spawn("worker", worker)
        crew.finish()
    return sorted(trace)


def test_two_runs_with_one_seed_give_the_same_trace() -> None:
    first = _watchdog_run(7)
    assert first == _watchdog_run(7)
    assert any("expired" in text for _, text in first)  # the watchdog did fire
    assert len(first) > 80


# -- both time bases: the same behaviours ------------------------------------------------------


@pytest.fixture(params=["scaled", "virtual"])
def tb(request: pytest.FixtureRequest) -> TimeBase:
    return ScaledTime(FAST) if request.param == "scaled" else VirtualTime()


def test_either_sleeper_wakes_at_or_after_its_deadline(tb: TimeBase) -> None:
    woke: list[float] = []

    def sleeper(deadline: float) -> None:
        tb.sleep_until(deadline)
        woke.append(tb.now())

    crew = Crew(tb)
    for deadline in (0.02, 0.01):
        crew.spawn(f"s{deadline}", sleeper, deadline)
    crew.finish()
    assert len(woke) == 2 and min(woke) >= 0.01 and max(woke) >= 0.02
    if tb.virtual:
        assert woke == [0.01, 0.02]


def test_either_condition_times_out_or_is_notified(tb: TimeBase) -> None:
    cond: HwCondition = tb.Condition()
    with cond:
        t0 = tb.now()
        assert cond.wait(5.0) is False
        assert tb.now() >= t0 + 5.0
    flag = [False]
    got: list[bool] = []

    def waiter() -> None:
        with cond:
            got.append(cond.wait_for(lambda: flag[0], 5000.0))

    crew = Crew(tb)
    crew.spawn("waiter", waiter)
    with cond:
        flag[0] = True
        cond.notify_all()
    crew.finish()
    assert got == [True]


def test_either_event_wakes_its_waiter(tb: TimeBase) -> None:
    event = tb.Event()
    assert event.wait(2.0) is False
    got: list[bool] = []
    crew = Crew(tb)
    crew.spawn("waiter", lambda: got.append(event.wait(5000.0)))
    event.set()
    crew.finish()
    assert got == [True] and event.is_set()
    event.clear()
    assert not event.is_set()


def test_either_poll_sees_a_raised_eventfd(tb: TimeBase) -> None:
    with eventfds(2) as (a, b):
        t0 = tb.now()
        assert tb.poll([a, b], 3.0) == []  # nothing raised: the timeout
        assert tb.now() >= t0 + 3.0
        got: list[list[int]] = []
        crew = Crew(tb)
        crew.spawn("poller", lambda: got.append(tb.poll([a, b], 5000.0, what="two lines")))
        raise_fd(tb, b)
        crew.finish()
        assert got == [[b]]
        raise_fd(tb, a)
        assert tb.poll([b, a, a]) == [b, a]  # both pending: at once, in the order given
        tb.kick(a)  # a kick with nobody polling is harmless


def test_virtual_poll_waits_on_after_a_kick_with_nothing_to_read() -> None:
    tb = VirtualTime()
    with eventfds(1) as (fd,):
        got: list[tuple[list[int], float]] = []
        crew = Crew(tb)
        crew.spawn("poller", lambda: got.append((tb.poll([fd], 4.0), tb.now())))
        tb.sleep(1.0)  # the poller waits
        tb.kick(fd)  # spurious: nothing written
        tb.sleep(1.0)
        assert got == []  # it looked, found nothing, and waits on
        crew.finish()
        assert got == [([], 4.0)]  # then it times out at exactly its deadline


def test_scaled_time_follows_the_monotonic_clock() -> None:
    t0 = time.monotonic() - 2.0
    tb = ScaledTime(50.0, t0=t0)
    before = (time.monotonic() - t0) * 50.0
    now = tb.now()
    after = (time.monotonic() - t0) * 50.0
    assert before <= now <= after and tb() >= now
    assert tb.t0 == t0 and tb.time_scale == 50.0 and not tb.virtual
    assert tb.hw_from_real(0.1) == pytest.approx(5.0) and tb.to_real(5.0) == pytest.approx(0.1)
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError):
            ScaledTime(bad)
    with tb.participate("anyone"):  # nothing to count in real time
        pass
    tb.leave()


def test_virtual_time_has_no_real_rate() -> None:
    tb = VirtualTime(start=2.5)
    assert tb() == 2.5 and tb.virtual and tb.time_scale == float("inf")
    assert tb.hw_from_real(10.0) == 0.0
    assert "2.5" in repr(tb) and "1 runnable: 'MainThread'" in tb.describe()
    with pytest.raises(ValueError):
        VirtualTime(start=float("nan"))
    with pytest.raises(ValueError):
        VirtualTime(stall_timeout=0.0)
    with pytest.raises(ValueError):
        VirtualTime(driver=threading.Thread(target=print))
