"""Hardware time, and every wait measured in it: scaled real time or virtual time (issue 22).

Why
---
The simulator runs on a scaled clock: hardware time is ``(monotonic - t0) * time_scale``. That is
fast, but only while the host keeps up: a thread scheduled 10 ms late at x300 sees its video
field three hardware seconds late, and what the driver reads depends on how the OS schedules it.
*Virtual time* removes the host from the picture: hardware time advances only when every thread
of the rig is blocked waiting, and then jumps to the next thing due. A run then takes as long as
its computation, whatever its hardware duration, and gives the same result each time.

This module is the one small time-and-wait abstraction both modes share. A :class:`TimeBase`
gives hardware time (:meth:`TimeBase.now`) and the primitives every thread of the server, the
simulator and the client API waits with, all with timeouts in *hardware* seconds:

* :meth:`TimeBase.Condition` (a ``threading.Condition``), :meth:`TimeBase.Event`,
  :meth:`TimeBase.sleep_until` / :meth:`TimeBase.sleep`;
* :meth:`TimeBase.poll` on descriptors (eventfd interrupt lines), with :meth:`TimeBase.kick`,
  which whoever makes a descriptor readable calls after the write;
* :meth:`TimeBase.Thread` and :meth:`TimeBase.join_thread`, :meth:`TimeBase.participate` (or
  :meth:`TimeBase.join` / :meth:`TimeBase.leave`) for the threads themselves.

:class:`ScaledTime` is today's clock: each wait is an ordinary real wait of ``hw / time_scale``
seconds and a wake-up is a plain notify; :meth:`TimeBase.kick` does nothing (the descriptor's
write wakes a real ``poll``), the participant calls do nothing. :class:`VirtualTime` is the new
one. Code written against :class:`TimeBase` runs unchanged on either.

The rules of virtual time
-------------------------
This is trio's autojump clock (``MockClock(autojump_threshold=0)``) carried over to threads, as
FoundationDB's and TigerBeetle's simulators do for whole systems. It works because *the domain
always knows how many of its threads can still run* (the ``runnable`` count, under one lock):

1. **Participants.** A thread made with :meth:`TimeBase.Thread` is a participant from the moment
   ``start()`` is called (counted on its behalf before ``start`` returns, so the domain never
   sees "nobody runs" between the start and the thread's first line); any other thread becomes
   one with ``with tb.participate():``. A participant counts as runnable except while it waits
   through the domain; its deadline, in hardware time, is registered while it waits.
2. **A wake is handed over at the moment it is caused.** ``notify()``, ``set()``, ``kick()``
   and a thread's end (for :meth:`TimeBase.join_thread`) mark the waiters runnable, under the
   domain's lock, *before they return*: the count never drops to zero in the instant between a
   signal and the woken thread resuming, which is the one thing that makes quiescence detection
   sound. A woken thread that finds its predicate false and waits again just decrements again.
3. **When nobody can run** (the count reaches zero as the last runnable thread waits or leaves),
   time jumps to the earliest deadline of any waiter, the advance hooks run
   (:meth:`VirtualTime.on_advance`, time held still while they do), and every waiter due by
   then is woken (timed out). Nothing else moves time: a participant spinning on the CPU for a
   second of real time sees ``now()`` unchanged.
4. **The driver.** The thread that makes the :class:`VirtualTime` (a test's main thread;
   ``driver=`` names another) is a participant from the start: nothing moves while a test sets
   up a rig, looks at a reply or asserts, and time passes only while the test waits through the
   domain (a client call, a sleep, a join). So a test that sleeps 3 s and then sets an event
   acts at exactly t = 3. The driver may :meth:`TimeBase.leave` to let the rig run on its own
   (and :meth:`TimeBase.join` again); while it is outside, it is an *outsider* (below). A
   driver that ends while it still participates holds time for ever: it leaves first.
5. **Deadlock.** If nobody can run, nothing is due and the driver is not outside the domain
   (it waits in it, or has ended), no wait can ever end: every waiter gets a
   :class:`VirtualTimeDeadlock` whose message lists each waiting thread, what it waits on (the
   ``what=`` label its wait site passed, such as ``"inbox BIRISSERV"``) and its deadline. While
   the driver has left and runs outside, a rig with nothing to do is merely idle: the driver may
   still post to it, so nothing is raised and time stays where it is.
6. **Outsiders.** Threads that do not participate (the driver after ``leave()``, a helper
   thread) may wait in the domain too: their deadlines count like any waiter's, they are never
   counted runnable (time runs on behind their backs once they are woken), and a deadlock wakes
   them with the error like everyone else.
7. **Stall.** With ``stall_timeout`` (real seconds), a wait of the driver or of an outsider
   that sees no activity at all in the domain for that long (no wait begun, no wake) raises
   :class:`VirtualTimeStall`, naming the threads counted runnable: one of them is blocked
   outside the domain (or computing for that long), and the test fails with who instead of
   hanging. Participants' waits never time out in real time.

What cannot be modelled
-----------------------
* **A thread outside the domain.** Library threads (Zenoh, canopen's notifier, pyusb's reader)
  do not report their waits. If one of them signals the rig, the wake reaches a thread the domain
  may already have timed out or declared deadlocked; a rig that uses them stays on
  :class:`ScaledTime`, unless a seam makes their callbacks enter the domain (a participant thread
  that receives from them through :meth:`TimeBase.poll`, for instance).
* **Blocking outside the domain.** A participant (the driver included) that blocks on a plain
  lock held by a waiting thread, on ``thread.join()`` of a thread that needs time to pass, on a
  socket or a ``time.sleep``, is counted runnable all along: time stops, and the rig hangs (a
  stall, if ``stall_timeout`` is set). Plain locks for short critical sections are fine (their
  holder runs); never wait through the domain while holding a lock another participant needs to
  make progress. A descriptor written without a :meth:`TimeBase.kick` is never seen by a poller
  in virtual time.
* **True parallelism and durations of computation.** Computation takes no hardware time at all:
  while any participant runs, time stands still. Anything that should cost hardware time (a
  VM-USB transfer, a register access's latency) must say so by sleeping in the domain. Real
  timeouts mean nothing: ``time_scale`` is infinite and :meth:`TimeBase.hw_from_real` is 0.
* **One process.** The count lives in this process's memory: a simulator in another process
  (``sim.process``) shares scaled time (``t0`` and the scale), never virtual time.
* **Order among threads runnable at the same instant** is the OS's. Determinism holds for what
  depends on time (which deadlines fire when, what a thread reads from hardware at a given
  instant), not for the interleaving of threads woken at the same moment unless they
  synchronise.

Design decisions (and where this departs from the suggestion in DESIGN.md section 7)
--------------------------------------------------------------------------------------
* **The driver participates from the start (4, 5).** With "non-participants are never counted
  as runnable" alone, time would run on while a test's main thread looks at a reply (the
  simulator's periodic fields firing at CPU speed until the test's next request, which then
  lands at an arbitrary virtual time), and "deadlock when every participant waits and nothing is
  due" would fire whenever an idle rig waits for its next request, at start-up first of all.
  Counting the driver, and declaring a deadlock only when the driver itself is stuck in the
  domain, fixes both and makes the test's own actions part of the deterministic schedule.
* **Threads are spawned through the domain** (:meth:`TimeBase.Thread`): without it, a thread
  that starts and then joins has a window in which the domain believes nobody runs.
* **Advance hooks run before the timed-out waiters are released**, with time held still: a
  simulator hooked there updates the hardware at t before any thread woken at t reads it.
* **Every wait site passes what it waits on** (``what=``), for the deadlock message and
  :meth:`VirtualTime.describe`; the label is free text and costs nothing in scaled time.
* **Condition waiters are held by the domain**, not the condition's lock: a waiter that timed
  out but has not yet re-taken the lock is never chosen by ``notify()`` (threading's Condition
  can lose a notify to one), so ``notify(n)`` wakes n threads that were really waiting.
* **Waits in virtual time block with no real timeout** (participants) and no polling: a waiter
  sleeps on a private lock until the domain releases it.
* Lock order: a condition's own lock, then the domain's lock; the domain's lock is never held
  while running user code (hooks, predicates), so no cycle can form.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import logging
import math
import select
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from types import TracebackType
from typing import Any, NamedTuple, Protocol, TypeVar

__all__ = [
    "HwCondition",
    "HwEvent",
    "HwLock",
    "HwThread",
    "ScaledTime",
    "StopEvent",
    "TimeBase",
    "VirtualTime",
    "VirtualTimeDeadlock",
    "VirtualTimeStall",
    "WaitInfo",
    "timebase_of",
]

log = logging.getLogger(__name__)

_T = TypeVar("_T")

_POLL_EVENTS = select.POLLIN | select.POLLPRI


class WaitInfo(NamedTuple):
    """One thread waiting in a virtual-time domain, for messages and tests."""

    thread: str
    """The waiting thread's name (its participant name, if it joined with one)."""
    what: str
    """What it waits on, as its wait site labelled it (``what=``)."""
    deadline: float | None
    """Hardware time at which its wait times out; None: no timeout."""
    role: str
    """``"driver"`` (rule 4), ``"participant"`` or ``"outsider"`` (rule 6)."""

    def __str__(self) -> str:
        until = "no deadline" if self.deadline is None else f"until t={self.deadline:.9g}"
        return f"{self.thread!r} ({self.role}) waits on {self.what}, {until}"


class VirtualTimeDeadlock(RuntimeError):
    """Every thread of a virtual-time domain waits and nothing is due: no wait can ever end.

    Raised in every waiting thread (each gets its own instance, with the same message).
    ``waits`` lists who waited on what when it was found.
    """

    def __init__(self, message: str, waits: Sequence[WaitInfo] = ()) -> None:
        super().__init__(message)
        self.waits: tuple[WaitInfo, ...] = tuple(waits)


class VirtualTimeStall(VirtualTimeDeadlock):
    """The driver or an outsider waited ``stall_timeout`` real seconds with nothing happening in the
    domain while some thread was counted runnable: that thread is blocked outside the domain
    (or spinning). Raised in the waiter whose patience ran out."""


# -- the primitives' interfaces -------------------------------------------------------------------


class HwCondition(ABC):
    """A condition variable whose timeouts are in hardware seconds (``threading.Condition``).

    Use it as ``threading.Condition``: hold its lock (``with cond:``) to wait or notify. Made by
    :meth:`TimeBase.Condition`.
    """

    @abstractmethod
    def acquire(self, blocking: bool = True) -> bool:
        """Take the condition's lock (a real lock: hold it only for short critical sections)."""

    @abstractmethod
    def release(self) -> None:
        """Release the condition's lock."""

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.release()

    @abstractmethod
    def wait(self, timeout_hw: float | None = None, *, what: str | None = None) -> bool:
        """Release the lock, block until notified or ``timeout_hw`` hardware seconds have passed,
        take the lock again; True if notified, False on timeout.

        ``what`` labels the wait for deadlock messages. RuntimeError if the lock is not held;
        :class:`VirtualTimeDeadlock` (with the lock held again) in a deadlocked virtual domain.
        """

    @abstractmethod
    def wait_for(
        self,
        predicate: Callable[[], _T],
        timeout_hw: float | None = None,
        *,
        what: str | None = None,
    ) -> _T:
        """Wait until ``predicate()`` is true (checked with the lock held), at most
        ``timeout_hw`` hardware seconds in all; returns the predicate's last value."""

    @abstractmethod
    def notify(self, n: int = 1) -> None:
        """Wake up to ``n`` waiting threads (the lock must be held)."""

    def notify_all(self) -> None:
        """Wake every waiting thread (the lock must be held)."""
        self.notify(1 << 62)


class HwEvent(ABC):
    """A ``threading.Event`` whose ``wait`` takes hardware seconds. Made by
    :meth:`TimeBase.Event`."""

    @abstractmethod
    def is_set(self) -> bool: ...

    @abstractmethod
    def set(self) -> None:
        """Set the flag and wake every waiter."""

    @abstractmethod
    def clear(self) -> None: ...

    @abstractmethod
    def wait(self, timeout_hw: float | None = None, *, what: str | None = None) -> bool:
        """Block until the flag is set or ``timeout_hw`` hardware seconds have passed; the flag."""


class HwThread(threading.Thread):
    """A thread that is a participant of its time base for its whole life.

    Made by :meth:`TimeBase.Thread`. In virtual time, ``start()`` counts the new thread as
    runnable before it returns (the domain never sees a gap between the start and the thread's
    first line) and the thread leaves the domain when its target returns or raises. Join it with
    :meth:`TimeBase.join_thread` (a wait in the domain, in hardware seconds); a plain ``join()``
    works too, but in virtual time only from a thread that does not participate.
    """

    def __init__(
        self,
        timebase: TimeBase,
        target: Callable[..., object],
        name: str | None = None,
        args: Iterable[object] = (),
        kwargs: Mapping[str, object] | None = None,
        *,
        daemon: bool | None = None,
    ) -> None:
        super().__init__(name=name, daemon=daemon)
        self.timebase = timebase
        self._body: Callable[..., object] | None = target
        self._body_args = tuple(args)
        self._body_kwargs = dict(kwargs or {})
        self._token: object = None
        self._spawned = False  # start() reserved its place; False while run() is called directly
        self._finished = timebase.Event()

    def start(self) -> None:
        token = self.timebase._spawn_reserve(self.name)
        self._token = token
        self._spawned = True
        try:
            super().start()
        except BaseException:
            self._spawned = False
            self.timebase._spawn_abort(token)
            raise

    def run(self) -> None:
        timebase = self.timebase
        spawned = self._spawned and threading.current_thread() is self
        if spawned:
            timebase._spawn_bind(self._token)
        else:  # an owner running the body in a thread of its own
            timebase.join(self.name)
        try:
            if self._body is not None:
                self._body(*self._body_args, **self._body_kwargs)
        finally:
            # no reference cycle through the target (as threading.Thread.run does)
            self._body = None
            self._body_args = ()
            self._body_kwargs = {}
            if spawned:
                timebase._spawn_finish(self)
            else:
                self._finished.set()  # handed over to joiners before this thread leaves
                timebase.leave()

    @property
    def finished(self) -> bool:
        """True once the thread has left its time base (its target returned or raised)."""
        return self._finished.is_set()


class HwLock(Protocol):
    """What :meth:`TimeBase.Lock` gives: ``threading.Lock``'s acquire, release and ``with``."""

    def acquire(self, blocking: bool = ..., timeout: float = ...) -> bool: ...

    def release(self) -> None: ...

    def __enter__(self) -> bool: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...


StopEvent = HwEvent | threading.Event
"""A stop signal handed to a wait: a time base's event, or (on scaled time only) a plain one
(:meth:`TimeBase.wait_event`)."""


# -- the time base --------------------------------------------------------------------------------


class TimeBase(ABC):
    """Hardware time and the waits measured in it, for every thread of one rig (its *domain*).

    All timeouts and instants are hardware seconds. See the module notes for the rules.
    """

    virtual: bool = False
    """True for :class:`VirtualTime`."""

    @abstractmethod
    def now(self) -> float:
        """Hardware time, in seconds."""

    def __call__(self) -> float:
        """``now()``: a time base is a clock (``Callable[[], float]``) too."""
        return self.now()

    @property
    @abstractmethod
    def time_scale(self) -> float:
        """Hardware seconds per real second; infinite in virtual time (never divide by it to
        get a real timeout: wait through the time base instead)."""

    @abstractmethod
    def hw_from_real(self, real_s: float) -> float:
        """Hardware seconds that ``real_s`` real seconds amount to: slack for work that threads
        do (a watchdog on a busy host). 0 in virtual time, where computation takes no time."""

    @abstractmethod
    def timeout_hw(self, real_s: float) -> float:
        """Hardware seconds a caller's timeout of ``real_s`` seconds stands for.

        A client's or a test's timeout is written in seconds of its own patience (``send(m,
        timeout=10)``). In scaled time that is ``real_s * time_scale`` hardware seconds, exactly
        what the real wait lasts. In virtual time computation takes no time, so the same timeout
        is read at the rig's *nominal* scale (:class:`VirtualTime`'s ``nominal_scale``, the
        scale it would have run at): a test moved from scaled to virtual time keeps the
        hardware meaning of every timeout it passes."""

    # -- participants ----------------------------------------------------------------------------

    @abstractmethod
    def join(self, name: str | None = None) -> None:
        """Make the calling thread a participant (counted runnable until it waits); nests.

        ``name`` (default: the thread's name) is what messages call it. In virtual time the
        driver is a participant from the start (module notes, rule 4).
        """

    @abstractmethod
    def leave(self) -> None:
        """Undo one :meth:`join` (the last one ends the participation; time may then advance).

        The driver leaves to let the rig run on its own (an outsider: rule 6). RuntimeError
        (virtual time) from a thread that does not participate.
        """

    @contextlib.contextmanager
    def participate(self, name: str | None = None) -> Iterator[None]:
        """``with tb.participate():`` the calling thread is a participant inside the block."""
        self.join(name)
        try:
            yield
        finally:
            self.leave()

    # -- primitives ------------------------------------------------------------------------------

    @abstractmethod
    def Condition(  # noqa: N802 (named as threading's factory, which it replaces)
        self, lock: threading.Lock | threading.RLock | None = None
    ) -> HwCondition:
        """A condition on ``lock`` (default: a new RLock), with waits in hardware seconds."""

    @abstractmethod
    def Event(self) -> HwEvent:  # noqa: N802 (named as threading's factory, which it replaces)
        """An event, with waits in hardware seconds."""

    def Lock(self) -> HwLock:  # noqa: N802 (named as threading's factory, which it replaces)
        """A lock for a critical section that may wait in the domain while held (a bus read the
        simulator slows, :meth:`sleep`-ing in the reading thread). On scaled time a plain
        ``threading.Lock``. On virtual time a thread blocked on a plain lock counts as
        runnable, so time would stand still while the holder waits for it to move: this lock's
        contended acquire waits in the domain instead (module notes, "Blocking outside the
        domain")."""
        return threading.Lock()

    def Thread(  # noqa: N802 (named as threading's class, which it replaces)
        self,
        target: Callable[..., object],
        name: str | None = None,
        args: Iterable[object] = (),
        kwargs: Mapping[str, object] | None = None,
        *,
        daemon: bool | None = None,
    ) -> HwThread:
        """A thread that participates in this time base for its whole life (not started)."""
        return HwThread(self, target, name, args, kwargs, daemon=daemon)

    def join_thread(self, thread: HwThread, timeout_hw: float | None = None) -> bool:
        """Wait until the body of ``thread`` (made by :meth:`Thread`) has ended, at most
        ``timeout_hw`` hardware seconds; True if it has. A wait in the domain, so a participant
        may join. The body may have been started, or run by an owner's thread (``run()``);
        joining one that never runs waits as long as it is told (in virtual time, forever is a
        deadlock)."""
        if not isinstance(thread, HwThread) or thread.timebase is not self:
            raise TypeError(f"{thread!r} was not made by this time base's Thread()")
        if thread is threading.current_thread():
            raise RuntimeError("cannot join the current thread")
        if not thread._finished.wait(timeout_hw, what=f"thread {thread.name!r} to end"):
            return False
        if thread.ident is not None:
            thread.join()  # it has left the domain: only its last lines of Python remain
        return True

    @abstractmethod
    def sleep_until(self, t_hw: float, *, what: str | None = None) -> None:
        """Block until hardware time ``t_hw`` (at once if it has passed)."""

    def sleep(self, dt_hw: float, *, what: str | None = None) -> None:
        """Block for ``dt_hw`` hardware seconds."""
        self.sleep_until(self.now() + dt_hw, what=what)

    @abstractmethod
    def poll(
        self, fds: Sequence[int], timeout_hw: float | None = None, *, what: str | None = None
    ) -> list[int]:
        """Block until one of ``fds`` is readable (or in error), at most ``timeout_hw`` hardware
        seconds; the ready descriptors in the order given, [] on timeout.

        Whoever makes one readable must call :meth:`kick` after the write: in virtual time
        that is the only thing that wakes a poller (the descriptors are looked at without
        blocking, under the domain's lock, so a write and kick are never missed).
        """

    @abstractmethod
    def kick(self, fd: int) -> None:
        """Say that ``fd`` was just made readable: wakes (hands over to) its pollers in virtual
        time; does nothing in scaled time, where the write itself wakes them."""

    def wait_event(
        self,
        event: HwEvent | threading.Event,
        timeout_hw: float | None = None,
        *,
        what: str | None = None,
    ) -> bool:
        """``event.wait`` in hardware seconds, for code handed a stop event it did not make.

        An :class:`HwEvent` of this time base waits in the domain; a plain ``threading.Event``
        (a caller on the target, a test) waits ``timeout_hw / time_scale`` real seconds, which
        only scaled time can do: in virtual time it is a TypeError (the wait would hold time
        still for ever), so a virtual rig's stop events are always made by its time base."""
        if isinstance(event, HwEvent):
            return event.wait(timeout_hw, what=what)
        if self.virtual:
            raise TypeError(
                f"a plain threading.Event cannot be waited on in virtual time ({what or 'wait'}):"
                " make it with the time base's Event()"
            )
        return event.wait(None if timeout_hw is None else max(0.0, timeout_hw) / self.time_scale)

    # -- for HwThread ----------------------------------------------------------------------------

    @abstractmethod
    def _spawn_reserve(self, name: str) -> object:
        """Count a thread about to start as runnable; the token for the calls below."""

    @abstractmethod
    def _spawn_abort(self, token: object) -> None:
        """The thread did not start after all: undo :meth:`_spawn_reserve`."""

    @abstractmethod
    def _spawn_bind(self, token: object) -> None:
        """In the new thread: make it the participant reserved by ``token``."""

    @abstractmethod
    def _spawn_finish(self, thread: HwThread) -> None:
        """In the ending thread: set its ``_finished`` event and leave, as one step."""


# -- scaled real time -----------------------------------------------------------------------------


class ScaledTime(TimeBase):
    """Hardware time ``(time.monotonic() - t0) * time_scale``; every wait a real one.

    ``t0`` (default: now) is the monotonic instant of hardware time 0; CLOCK_MONOTONIC is
    system-wide on Linux, so two processes that share ``t0`` and the scale agree on the time.
    """

    virtual = False

    def __init__(
        self,
        time_scale: float = 1.0,
        *,
        t0: float | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        if not (time_scale > 0.0 and math.isfinite(time_scale)):
            raise ValueError(f"time_scale must be positive and finite, not {time_scale}")
        self._scale = float(time_scale)
        self._t0 = time.monotonic() if t0 is None else float(t0)
        self._clock = clock
        if clock is not None:
            self.now = clock  # type: ignore[method-assign]  # a hardware clock of its own

    @property
    def t0(self) -> float:
        """``time.monotonic()`` when hardware time was 0."""
        return self._t0

    def now(self) -> float:
        return (time.monotonic() - self._t0) * self._scale

    @property
    def time_scale(self) -> float:
        return self._scale

    def hw_from_real(self, real_s: float) -> float:
        return real_s * self._scale

    def timeout_hw(self, real_s: float) -> float:
        return real_s * self._scale

    def to_real(self, hw_s: float) -> float:
        """Real seconds that ``hw_s`` hardware seconds take."""
        return hw_s / self._scale

    def _real_timeout(self, timeout_hw: float | None) -> float | None:
        return None if timeout_hw is None else max(0.0, timeout_hw) / self._scale

    def join(self, name: str | None = None) -> None:
        pass  # real time flows whoever runs

    def leave(self) -> None:
        pass

    def Condition(  # noqa: N802
        self, lock: threading.Lock | threading.RLock | None = None
    ) -> HwCondition:
        return _ScaledCondition(self, lock)

    def Event(self) -> HwEvent:  # noqa: N802
        return _ScaledEvent(self)

    def sleep_until(self, t_hw: float, *, what: str | None = None) -> None:
        while True:
            remaining = t_hw - self.now()
            if remaining <= 0.0:
                return
            time.sleep(remaining / self._scale)

    def poll(
        self, fds: Sequence[int], timeout_hw: float | None = None, *, what: str | None = None
    ) -> list[int]:
        order = tuple(dict.fromkeys(fds))
        poller = select.poll()
        for fd in order:
            poller.register(fd, _POLL_EVENTS)
        if timeout_hw is None:
            deadline = None
        else:
            deadline = time.monotonic() + max(0.0, timeout_hw) / self._scale
        while True:
            if deadline is None:
                ms = -1
            else:
                ms = max(0, math.ceil((deadline - time.monotonic()) * 1000.0))
            ready = {fd for fd, _ in poller.poll(ms)}
            if ready or (deadline is not None and time.monotonic() >= deadline):
                return [fd for fd in order if fd in ready]

    def kick(self, fd: int) -> None:
        pass  # the write to the descriptor wakes a real poll

    def _spawn_reserve(self, name: str) -> object:
        return None

    def _spawn_abort(self, token: object) -> None:
        pass

    def _spawn_bind(self, token: object) -> None:
        pass

    def _spawn_finish(self, thread: HwThread) -> None:
        thread._finished.set()

    def __repr__(self) -> str:
        return f"<ScaledTime x{self._scale:g}: t={self.now():.6f}>"


class _ScaledCondition(HwCondition):
    __slots__ = ("_cond", "_timebase")

    def __init__(self, timebase: ScaledTime, lock: threading.Lock | threading.RLock | None) -> None:
        self._timebase = timebase
        self._cond = threading.Condition(lock)

    def acquire(self, blocking: bool = True) -> bool:
        return self._cond.acquire(blocking)

    def release(self) -> None:
        self._cond.release()

    def wait(self, timeout_hw: float | None = None, *, what: str | None = None) -> bool:
        return self._cond.wait(self._timebase._real_timeout(timeout_hw))

    def wait_for(
        self,
        predicate: Callable[[], _T],
        timeout_hw: float | None = None,
        *,
        what: str | None = None,
    ) -> _T:
        return self._cond.wait_for(predicate, self._timebase._real_timeout(timeout_hw))

    def notify(self, n: int = 1) -> None:
        self._cond.notify(n)

    def notify_all(self) -> None:
        self._cond.notify_all()


class _ScaledEvent(HwEvent):
    __slots__ = ("_event", "_timebase")

    def __init__(self, timebase: ScaledTime) -> None:
        self._timebase = timebase
        self._event = threading.Event()

    def is_set(self) -> bool:
        return self._event.is_set()

    def set(self) -> None:
        self._event.set()

    def clear(self) -> None:
        self._event.clear()

    def wait(self, timeout_hw: float | None = None, *, what: str | None = None) -> bool:
        return self._event.wait(self._timebase._real_timeout(timeout_hw))


# -- virtual time ---------------------------------------------------------------------------------

# A wait's states. Only the domain's lock moves a wait out of _WAITING, once.
_WAITING = 0
_NOTIFIED = 1  # notify(), set(), kick(), a thread's end
_TIMED_OUT = 2
_DEADLOCKED = 3  # its error is a VirtualTimeDeadlock (or a VirtualTimeStall)
_CANCELLED = 4  # the waiting thread was interrupted (KeyboardInterrupt)


class _Wait:
    """One blocked call: who, on what, until when, and the private lock it sleeps on."""

    __slots__ = (
        "began",
        "deadline",
        "driver",
        "error",
        "fds",
        "home",
        "ident",
        "name",
        "participant",
        "seq",
        "signal",
        "state",
        "what",
    )

    def __init__(
        self, seq: int, ident: int, name: str, what: str, deadline: float | None, driver: bool
    ) -> None:
        self.seq = seq
        self.ident = ident
        self.name = name
        self.what = what
        self.deadline = deadline
        self.driver = driver
        self.began = 0.0  # hardware time the wait began (set by its domain)
        self.participant = False
        self.state = _WAITING
        self.error: VirtualTimeDeadlock | None = None
        self.fds: tuple[int, ...] = ()
        self.home: dict[int, _Wait] | None = None  # a condition's or event's waiters
        # Held from birth, released once by the domain when the wait ends: the thread sleeps on it.
        self.signal = threading.Lock()
        self.signal.acquire()

    def info(self) -> WaitInfo:
        role = "driver" if self.driver else "participant" if self.participant else "outsider"
        return WaitInfo(self.name, self.what, self.deadline, role)


class _Participant:
    __slots__ = ("depth", "name")

    def __init__(self, name: str) -> None:
        self.name = name
        self.depth = 1


class VirtualTime(TimeBase):
    """Hardware time that advances only when no thread of the domain can run (module notes).

    ``start``: hardware time at the beginning. ``driver``: the thread that drives the domain
    (default: the calling thread), a participant from now on (rules 4 and 5).
    ``stall_timeout``: real seconds the driver or an outsider waits with nothing happening in
    the domain before it raises :class:`VirtualTimeStall` (default: never; rule 7).
    ``nominal_scale``: hardware seconds per second of a caller's timeout
    (:meth:`TimeBase.timeout_hw`).
    ``runaway``: hardware seconds a wait of the driver with no deadline may see pass before it
    is called a deadlock (default: never). A simulator with periodic work (video fields) always
    has something due, so rule 5 never fires on it: a driver waiting for what will never come
    would run time on for ever at the CPU's speed. With ``runaway`` it gets a
    :class:`VirtualTimeDeadlock` naming every wait instead.
    """

    virtual = True

    def __init__(
        self,
        start: float = 0.0,
        *,
        driver: threading.Thread | None = None,
        stall_timeout: float | None = None,
        nominal_scale: float = 1.0,
        runaway: float | None = None,
    ) -> None:
        if runaway is not None and not runaway > 0.0:
            raise ValueError(f"runaway must be positive, not {runaway}")
        self._runaway = runaway
        if not (nominal_scale > 0.0 and math.isfinite(nominal_scale)):
            raise ValueError(f"nominal_scale must be positive and finite, not {nominal_scale}")
        self.nominal_scale = float(nominal_scale)
        """The scale a caller's timeout is read at (:meth:`TimeBase.timeout_hw`)."""
        if not math.isfinite(start):
            raise ValueError(f"start must be finite, not {start}")
        if stall_timeout is not None and not stall_timeout > 0.0:
            raise ValueError(f"stall_timeout must be positive, not {stall_timeout}")
        self._lock = threading.Lock()
        self._now = float(start)
        self._advances = 0
        self._runnable = 0  # participants not waiting + spawns starting + hooks running
        self._participants: dict[int, _Participant] = {}  # by thread ident
        self._starting: dict[int, _Participant] = {}  # spawned, not yet running: by token
        self._waiting: dict[int, _Wait] = {}  # by seq: in order of waiting
        self._deadlines: list[tuple[float, int, _Wait]] = []  # a heap; entries go stale
        self._stale = 0  # heap entries whose wait has ended
        self._by_fd: dict[int, dict[int, _Wait]] = {}
        self._seq = itertools.count()
        self._driver = threading.current_thread() if driver is None else driver
        if self._driver.ident is None:
            raise ValueError(f"the driver {self._driver!r} has not started")
        self._driver_ident = self._driver.ident
        self._driver_waits = 0
        self._hooks: list[Callable[[float], None]] = []
        self._hooks_running = 0
        self._activity = 0  # waits begun and ended: what a stall check watches
        self._stall_timeout = stall_timeout
        self._deadlock: VirtualTimeDeadlock | None = None
        self._local = threading.local()
        # Rule 4: the driver participates from the start.
        self._participants[self._driver_ident] = _Participant(self._driver.name)
        self._runnable = 1

    # -- time ------------------------------------------------------------------------------------

    def now(self) -> float:
        return self._now

    @property
    def time_scale(self) -> float:
        return math.inf

    def hw_from_real(self, real_s: float) -> float:
        return 0.0

    def timeout_hw(self, real_s: float) -> float:
        return real_s * self.nominal_scale

    @property
    def advances(self) -> int:
        """How many times time has jumped forward."""
        return self._advances

    @property
    def deadlock(self) -> VirtualTimeDeadlock | None:
        """The first deadlock (or stall) found, if any: a fixture can assert there was none."""
        return self._deadlock

    @property
    def driver(self) -> threading.Thread:
        """The thread that drives the domain from outside (rules 4 and 5)."""
        return self._driver

    def on_advance(self, hook: Callable[[float], None]) -> Callable[[], None]:
        """Call ``hook(t)`` after each jump of time to ``t``; returns a function that removes it.

        Hooks run in whichever thread found the domain quiescent, outside the domain's lock, one
        after another, with time held still until they return, and before the waiters due at
        ``t`` are released. A hook may signal (notify, set, kick) but must not wait; an
        exception from it is logged and otherwise ignored.
        """
        with self._lock:
            self._hooks.append(hook)

        def remove() -> None:
            with self._lock, contextlib.suppress(ValueError):
                self._hooks.remove(hook)

        return remove

    # -- participants ----------------------------------------------------------------------------

    def join(self, name: str | None = None) -> None:
        ident = threading.get_ident()
        with self._lock:
            participant = self._participants.get(ident)
            if participant is not None:
                participant.depth += 1
                return
            self._participants[ident] = _Participant(name or threading.current_thread().name)
            self._runnable += 1

    def leave(self) -> None:
        ident = threading.get_ident()
        with self._lock:
            participant = self._participants.get(ident)
            if participant is None:
                raise RuntimeError(
                    f"{threading.current_thread().name!r} does not participate in {self!r}"
                )
            participant.depth -= 1
            if participant.depth:
                return
            del self._participants[ident]
            self._runnable -= 1
            self._activity += 1
            hook_time = self._settle_locked()
        self._run_hooks(hook_time)

    def _spawn_reserve(self, name: str) -> object:
        token = next(self._seq)
        with self._lock:
            self._starting[token] = _Participant(name)
            self._runnable += 1
        return token

    def _spawn_abort(self, token: object) -> None:
        assert isinstance(token, int)
        with self._lock:
            if self._starting.pop(token, None) is None:
                return
            self._runnable -= 1
            hook_time = self._settle_locked()
        self._run_hooks(hook_time)

    def _spawn_bind(self, token: object) -> None:
        assert isinstance(token, int)
        ident = threading.get_ident()
        with self._lock:
            self._participants[ident] = self._starting.pop(token)  # already counted runnable

    def _spawn_finish(self, thread: HwThread) -> None:
        finished = thread._finished
        assert isinstance(finished, _VirtualEvent)
        with self._lock:
            finished._set_locked()  # handed over to joiners before this thread stops counting
            if self._participants.pop(threading.get_ident(), None) is not None:
                self._runnable -= 1
            self._activity += 1
            hook_time = self._settle_locked()
        self._run_hooks(hook_time)

    # -- primitives ------------------------------------------------------------------------------

    def Condition(  # noqa: N802
        self, lock: threading.Lock | threading.RLock | None = None
    ) -> HwCondition:
        return _VirtualCondition(self, lock)

    def Event(self) -> HwEvent:  # noqa: N802
        return _VirtualEvent(self)

    def Lock(self) -> HwLock:  # noqa: N802
        return _VirtualLock(self)

    def sleep_until(self, t_hw: float, *, what: str | None = None) -> None:
        wait = self._new_wait(what or "sleep", t_hw)
        with self._lock:
            hook_time = self._enter_locked(wait)
        self._await(wait, hook_time)

    def poll(
        self, fds: Sequence[int], timeout_hw: float | None = None, *, what: str | None = None
    ) -> list[int]:
        order = tuple(dict.fromkeys(fds))
        poller = select.poll()
        for fd in order:
            poller.register(fd, _POLL_EVENTS)
        deadline = None if timeout_hw is None else self._now + max(0.0, timeout_hw)
        label = what or f"poll {list(order)}"
        while True:
            wait = self._new_wait(label, deadline)
            with self._lock:
                # Looked at under the domain's lock: a writer's kick() takes it after its write,
                # so either the write is seen here or the kick finds this wait registered.
                ready = _ready(poller, order)
                if ready:
                    return ready
                wait.fds = order
                hook_time = self._enter_locked(wait)
                if wait.state == _WAITING:
                    for fd in order:
                        self._by_fd.setdefault(fd, {})[wait.seq] = wait
            state = self._await(wait, hook_time)
            if state == _TIMED_OUT:
                return _ready(poller, order)
            # kicked: look again (another poller may have taken it; then wait on)

    def kick(self, fd: int) -> None:
        with self._lock:
            waits = self._by_fd.get(fd)
            if waits:
                for wait in list(waits.values()):
                    self._wake_locked(wait, _NOTIFIED)

    # -- diagnostics -----------------------------------------------------------------------------

    def waiting(self) -> tuple[WaitInfo, ...]:
        """Who waits on what right now, in the order they began waiting."""
        with self._lock:
            return tuple(wait.info() for wait in self._waiting.values())

    def describe(self) -> str:
        """The domain's state in a few lines: time, who can run, who waits on what."""
        with self._lock:
            return self._describe_locked()

    def _runnable_names_locked(self) -> list[str]:
        waiting = {wait.ident for wait in self._waiting.values()}
        names = [repr(p.name) for ident, p in self._participants.items() if ident not in waiting]
        names += [f"{p.name!r} (starting)" for p in self._starting.values()]
        if self._hooks_running:
            names.append("advance hooks")
        return names

    def _describe_locked(self) -> str:
        runnable = self._runnable_names_locked()
        lines = [
            f"virtual time t={self._now:.9g} hw s after {self._advances} advance(s); "
            f"{self._runnable} runnable" + (f": {', '.join(runnable)}" if runnable else "")
        ]
        waits = list(self._waiting.values())
        lines.append("waiting:" if waits else "nobody waits")
        lines += [f"  {wait.info()}" for wait in waits]
        return "\n".join(lines)

    def __repr__(self) -> str:
        return f"<VirtualTime t={self._now:.9g}: {self._runnable} runnable>"

    # -- the machinery ---------------------------------------------------------------------------

    def _new_wait(self, what: str, deadline: float | None) -> _Wait:
        if getattr(self._local, "in_hook", False):
            raise RuntimeError("an advance hook must not wait in the domain")
        ident = threading.get_ident()
        name = threading.current_thread().name
        wait = _Wait(next(self._seq), ident, name, what, deadline, ident == self._driver_ident)
        wait.began = self._now
        return wait

    def _enter_locked(self, wait: _Wait) -> float | None:
        """Register ``wait``: its thread stops counting as runnable. Then settle the domain,
        which may end this very wait (timed out, deadlock). Returns the time for which advance
        hooks must run (see :meth:`_run_hooks`), if any."""
        if wait.deadline is not None and wait.deadline <= self._now:
            wait.state = _TIMED_OUT  # due already: no wait at all, nothing counted
            wait.signal.release()
            return None
        participant = self._participants.get(wait.ident)
        if participant is not None:
            wait.participant = True
            wait.name = participant.name
            self._runnable -= 1
        if wait.driver:
            self._driver_waits += 1
        self._activity += 1
        self._waiting[wait.seq] = wait
        if wait.home is not None:
            wait.home[wait.seq] = wait
        if wait.deadline is not None:
            heap = self._deadlines
            heapq.heappush(heap, (wait.deadline, wait.seq, wait))
            if self._stale > 64 and 2 * self._stale > len(heap):
                # waits that ended before their deadline (most timeouts do not fire): drop them
                self._deadlines = [entry for entry in heap if entry[2].state == _WAITING]
                heapq.heapify(self._deadlines)
                self._stale = 0
        return self._settle_locked()

    def _wake_locked(self, wait: _Wait, state: int) -> bool:
        """End ``wait`` with ``state``, counting its thread runnable at once (the hand-over)."""
        if wait.state != _WAITING:
            return False
        wait.state = state
        del self._waiting[wait.seq]
        if wait.home is not None:
            wait.home.pop(wait.seq, None)
        for fd in wait.fds:
            pollers = self._by_fd.get(fd)
            if pollers is not None:
                pollers.pop(wait.seq, None)
                if not pollers:
                    del self._by_fd[fd]
        if wait.deadline is not None:
            self._stale += 1  # its heap entry
        if wait.participant:
            self._runnable += 1
        if wait.driver:
            self._driver_waits -= 1
        self._activity += 1
        wait.signal.release()
        return True

    def _settle_locked(self) -> float | None:
        """If nobody can run: jump to the earliest deadline and wake what is due, or declare
        the deadlock. Returns a time if advance hooks must run (time is then held by a token
        the caller gives back in :meth:`_run_hooks`)."""
        while self._runnable == 0:
            heap = self._deadlines
            while heap and heap[0][2].state != _WAITING:
                heapq.heappop(heap)
                self._stale -= 1
            if not heap:
                if self._waiting and not self._driver_outside_locked():
                    self._deadlock_locked()
                return None  # idle: the driver may still act
            due = heap[0][0]
            if self._runaway is not None and self._driver_waits and self._runaway_locked(due):
                return None
            if due > self._now:
                self._now = due
                self._advances += 1
                if self._hooks:
                    self._runnable += 1  # held by the hooks; the due waits wake after them
                    self._hooks_running += 1
                    return due
            while heap and heap[0][0] <= self._now:
                _, _, wait = heapq.heappop(heap)
                self._wake_locked(wait, _TIMED_OUT)  # no-op for a stale entry
                self._stale -= 1
            # Only outsiders woken (or nothing): they are never counted, so go on to the next.
        return None

    def _runaway_locked(self, due: float) -> bool:
        """True (and the domain deadlocked) if the driver waits with no deadline and jumping to
        ``due`` would take time more than ``runaway`` past the start of that wait."""
        assert self._runaway is not None
        for wait in self._waiting.values():
            if wait.driver and wait.deadline is None and due - wait.began > self._runaway:
                self._deadlock_locked(
                    f"virtual time ran {self._runaway:g} hw s while the driver waited on "
                    f"{wait.what} with no deadline: only periodic work is due, and none of "
                    "these waits may ever end"
                )
                return True
        return False

    def _driver_outside_locked(self) -> bool:
        """True while the driver has left the domain and runs outside it: it may still post to
        the rig, so a domain with nothing to do is idle, not deadlocked."""
        return (
            self._driver_waits == 0
            and self._driver_ident not in self._participants
            and self._driver.is_alive()
        )

    def _deadlock_locked(self, why: str | None = None) -> None:
        waits = list(self._waiting.values())
        infos = [wait.info() for wait in waits]
        message = (
            f"virtual time deadlock at t={self._now:.9g} hw s: "
            + (
                why
                or "every thread of the domain waits and nothing is due, so none of these "
                "waits can ever end"
            )
            + ":\n"
            + "\n".join(f"  {info}" for info in infos)
        )
        log.error("%s", message)
        if self._deadlock is None:
            self._deadlock = VirtualTimeDeadlock(message, infos)
        for wait in waits:
            wait.error = VirtualTimeDeadlock(message, infos)  # one per thread: own traceback
            self._wake_locked(wait, _DEADLOCKED)

    def _run_hooks(self, hook_time: float | None) -> None:
        """Run the advance hooks for ``hook_time`` (if not None) with time held, then give the
        hold back and settle again (which wakes the waits due, or jumps again)."""
        while hook_time is not None:
            with self._lock:
                hooks = tuple(self._hooks)
            self._local.in_hook = True
            try:
                for hook in hooks:
                    try:
                        hook(hook_time)
                    except Exception:
                        log.exception("advance hook %r failed at t=%.9g", hook, hook_time)
            finally:
                self._local.in_hook = False
                with self._lock:
                    self._hooks_running -= 1
                    self._runnable -= 1
            with self._lock:
                hook_time = self._settle_locked()

    def _await(self, wait: _Wait, hook_time: float | None) -> int:
        """Block the calling thread until the domain ends ``wait``; its final state.

        Raises the wait's :class:`VirtualTimeDeadlock` if it ended in one.
        """
        try:
            self._run_hooks(hook_time)
            signal = wait.signal
            if self._stall_timeout is None or (wait.participant and not wait.driver):
                signal.acquire()
            else:
                self._await_watching(wait, self._stall_timeout)
        except BaseException:
            with self._lock:
                self._wake_locked(wait, _CANCELLED)  # counted runnable again, as it is
            raise
        if wait.state == _DEADLOCKED:
            assert wait.error is not None
            raise wait.error
        return wait.state

    def _await_watching(self, wait: _Wait, patience: float) -> None:
        """The driver's or an outsider's block: raise a stall if the domain does nothing for
        ``patience`` real seconds while someone is counted runnable."""
        seen = self._activity
        while not wait.signal.acquire(True, patience):
            with self._lock:
                if wait.state != _WAITING or self._activity != seen:
                    seen = self._activity
                    continue
                runnable = self._runnable_names_locked()
                message = (
                    f"virtual time stalled at t={self._now:.9g} hw s: nothing happened in the "
                    f"domain for {patience:g} real s while {wait.name!r} waited on {wait.what}; "
                    f"counted runnable but not waiting (blocked outside the domain, or "
                    f"spinning): {', '.join(runnable) or 'nobody'}\n" + self._describe_locked()
                )
                error = VirtualTimeStall(message, [w.info() for w in self._waiting.values()])
                if self._deadlock is None:
                    self._deadlock = error
                wait.error = error
                self._wake_locked(wait, _DEADLOCKED)
            log.error("%s", message)


def _ready(poller: select.poll, order: tuple[int, ...]) -> list[int]:
    ready = {fd for fd, _ in poller.poll(0)}
    return [fd for fd in order if fd in ready] if ready else []


class _VirtualEvent(HwEvent):
    __slots__ = ("_flag", "_timebase", "_waiters")

    def __init__(self, timebase: VirtualTime) -> None:
        self._timebase = timebase
        self._flag = False
        self._waiters: dict[int, _Wait] = {}

    def is_set(self) -> bool:
        return self._flag

    def set(self) -> None:
        with self._timebase._lock:
            self._set_locked()

    def _set_locked(self) -> None:
        self._flag = True
        timebase = self._timebase
        for wait in list(self._waiters.values()):
            timebase._wake_locked(wait, _NOTIFIED)

    def clear(self) -> None:
        with self._timebase._lock:
            self._flag = False

    def wait(self, timeout_hw: float | None = None, *, what: str | None = None) -> bool:
        timebase = self._timebase
        if self.is_set():
            return True
        deadline = None if timeout_hw is None else timebase._now + max(0.0, timeout_hw)
        wait = timebase._new_wait(what or "event", deadline)
        with timebase._lock:
            if self._flag:
                return True
            wait.home = self._waiters
            hook_time = timebase._enter_locked(wait)
        return timebase._await(wait, hook_time) == _NOTIFIED or self._flag


class _VirtualCondition(HwCondition):
    __slots__ = ("_acquire_restore", "_is_owned", "_lock", "_release_save", "_timebase", "_waiters")

    def __init__(
        self, timebase: VirtualTime, lock: threading.Lock | threading.RLock | None
    ) -> None:
        self._timebase = timebase
        self._lock: threading.Lock | threading.RLock = threading.RLock() if lock is None else lock
        self._waiters: dict[int, _Wait] = {}  # guarded by the domain's lock, not self._lock
        # An RLock is released whole for the wait, however deep it is held (as threading does).
        lk = self._lock
        self._release_save: Callable[[], Any] = getattr(lk, "_release_save", self._plain_release)
        self._acquire_restore: Callable[[Any], None] = getattr(
            lk, "_acquire_restore", self._plain_acquire
        )
        self._is_owned: Callable[[], bool] = getattr(lk, "_is_owned", self._plain_owned)

    def _plain_release(self) -> None:
        self._lock.release()

    def _plain_acquire(self, _state: object) -> None:
        self._lock.acquire()

    def _plain_owned(self) -> bool:
        if self._lock.acquire(False):
            self._lock.release()
            return False
        return True

    def acquire(self, blocking: bool = True) -> bool:
        return self._lock.acquire(blocking)

    def release(self) -> None:
        self._lock.release()

    def wait(self, timeout_hw: float | None = None, *, what: str | None = None) -> bool:
        deadline = None if timeout_hw is None else self._timebase._now + max(0.0, timeout_hw)
        return self._wait_until(deadline, what)

    def _wait_until(self, deadline: float | None, what: str | None) -> bool:
        if not self._is_owned():
            raise RuntimeError("cannot wait on un-acquired lock")
        timebase = self._timebase
        wait = timebase._new_wait(what or "condition", deadline)
        with timebase._lock:
            wait.home = self._waiters
            hook_time = timebase._enter_locked(wait)
        saved = self._release_save()
        try:
            state = timebase._await(wait, hook_time)
        finally:
            self._acquire_restore(saved)
        return state == _NOTIFIED

    def wait_for(
        self,
        predicate: Callable[[], _T],
        timeout_hw: float | None = None,
        *,
        what: str | None = None,
    ) -> _T:
        timebase = self._timebase
        deadline = None if timeout_hw is None else timebase._now + max(0.0, timeout_hw)
        result = predicate()
        while not result:
            if deadline is not None and timebase._now >= deadline:
                break
            self._wait_until(deadline, what)
            result = predicate()
        return result

    def notify(self, n: int = 1) -> None:
        if not self._is_owned():
            raise RuntimeError("cannot notify on un-acquired lock")
        if n <= 0 or not self._waiters:
            return
        timebase = self._timebase
        with timebase._lock:
            for wait in list(itertools.islice(self._waiters.values(), n)):
                timebase._wake_locked(wait, _NOTIFIED)


def timebase_of(clock: Callable[[], float], time_scale: float = 1.0) -> TimeBase:
    """The time base behind a hardware ``clock``: the clock itself when it is one (a simulator
    passes its :class:`TimeBase` as the clock), else a :class:`ScaledTime` reading ``clock``
    whose waits are real waits of ``hw / time_scale`` seconds (a target's own clock).

    Components that were handed ``(clock, time_scale)`` wait through what this returns, so
    they run unchanged on either kind of time.
    """
    if isinstance(clock, TimeBase):
        return clock
    owner = getattr(clock, "__self__", None)
    if isinstance(owner, TimeBase) and getattr(clock, "__name__", "") in ("now", "__call__"):
        return owner
    scale = time_scale if time_scale > 0.0 and math.isfinite(time_scale) else 1.0
    return ScaledTime(scale, clock=clock)


class _VirtualLock:
    """A lock whose contended acquire waits in the virtual domain (:meth:`TimeBase.Lock`);
    ``timeout`` is in hardware seconds. Uncontended, it costs one short critical section."""

    __slots__ = ("_cond", "_held")

    def __init__(self, timebase: VirtualTime) -> None:
        self._cond = timebase.Condition(threading.Lock())
        self._held = False

    def acquire(self, blocking: bool = True, timeout: float = -1.0) -> bool:
        with self._cond:
            if not self._held:
                self._held = True
                return True
            if not blocking:
                return False
            free = self._cond.wait_for(
                lambda: not self._held, None if timeout < 0 else timeout, what="a held lock"
            )
            if not free:
                return False
            self._held = True
            return True

    def release(self) -> None:
        with self._cond:
            if not self._held:
                raise RuntimeError("release unlocked lock")
            self._held = False
            self._cond.notify()

    def locked(self) -> bool:
        return self._held

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.release()
