"""``InterruptGate``: the one door every simulated interrupt on a physical level goes through.

The driver's notifiers must survive interrupts that arrive late, merged, lost or for no reason;
the report's ISR demultiplexes a shared level by looking at registers, not by counting. A gate
per physical level lets the fault panel shape delivery without the device models knowing:

- **coalescing** holds interrupts and delivers them in bursts, so one ``wait()`` on the line
  returns a count above 1 (the data path must catch up by ACQ_LINE). A burst is released when it
  reaches ``burst`` interrupts, when it has been held for ``max_hold`` hardware seconds (so a
  lone command interrupt is late, never lost), when coalescing is switched off, or by
  :meth:`InterruptGate.flush`;
- **drop_next(source)** loses the next interrupt from that source;
- **spurious()** raises an interrupt with no cause behind it;
- **late(max_delay_s)** plays a host that is slow to take its interrupts: whatever the gate would
  deliver is held for a delay drawn uniformly in ``[0, max_delay_s]`` hardware seconds from a
  seeded generator, so a run is reproducible. Held interrupts leave in the order they came (an
  interrupt is never delivered before one raised earlier: its due time is at least the previous
  one's), and those that fall due together are delivered as one count. One thread per gate
  releases them while lateness is on; ``late(None)`` delivers what is held at once and stops
  delaying. Lateness comes after coalescing: a released burst is late as a whole.

Time: the gate's threads (the late-release thread, and one ``irqgate-hold`` thread per burst
that may have to be released by ``max_hold``), their waits and their joins all go through the
clock's time base (:attr:`sim.clock.SimClock.timebase`), in hardware seconds, so a gate runs
unchanged on scaled real time or on virtual time, where a held interrupt leaves exactly when it
is due.

Counters obey ``raised == delivered + dropped + lost + pending + late_pending``: ``lost`` counts
interrupts the line refused because the driver had already closed it (a shutdown race, not a
fault).

**Measurement hook.** :attr:`InterruptGate.on_raise` (None by default) is called for every
raise with the source and the ``time.perf_counter_ns()`` taken as the model raised it, so a
benchmark can time the driver from the moment the hardware asserted the interrupt. It exists for
``biris_hw.bench`` only and changes nothing about delivery.
"""

from __future__ import annotations

import math
import random
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import NamedTuple

from biris_hw.errors import LineClosed
from biris_hw.timebase import HwThread
from sim.clock import SimClock

__all__ = [
    "BIRIS_SOURCES",
    "DEFAULT_MAX_HOLD",
    "LATE_LOG_SIZE",
    "SPURIOUS",
    "InterruptGate",
    "LateDelivery",
]

DEFAULT_MAX_HOLD = 0.1
"""Hardware seconds a coalesced interrupt may wait for its burst to fill (six video fields)."""

SPURIOUS = "spurious"
"""The source name of an interrupt with no cause."""

BIRIS_SOURCES = frozenset({"data", "cmd"})
"""Sources that are BIRIS's own (remote IRQ2 through the coupler), as opposed to the coupler's."""

LATE_LOG_SIZE = 1024
"""Late deliveries a gate remembers (:attr:`InterruptGate.late_log`): enough for a test to check
every one of a scan's, bounded so a long run with lateness on stays small."""


class LateDelivery(NamedTuple):
    """One batch of interrupts (``interrupts`` of them: one, or a coalesced burst) that lateness
    held, as it left the gate (times in hardware seconds).

    ``delay_s`` is the delay drawn for it; ``due_s`` may be later than ``raised_s + delay_s``
    because a batch never leaves before the one ahead of it. ``delivered_s`` is when the gate's
    thread handed it to the line, at or after ``due_s`` (by the host's scheduling latency), or
    earlier when lateness was switched off and everything held went at once.
    """

    interrupts: int
    raised_s: float
    delay_s: float
    due_s: float
    delivered_s: float


class _Held(NamedTuple):
    interrupts: int
    raised_s: float
    delay_s: float
    due_s: float


class InterruptGate:
    """Shapes the delivery of one physical interrupt level; every method is thread-safe.

    ``trigger(count)`` is the level itself, typically ``EventFdLine.trigger``. It is called
    outside the gate's lock, so a slow or re-entrant trigger cannot stall the device models.
    """

    def __init__(self, trigger: Callable[[int], None], clock: SimClock) -> None:
        self._trigger = trigger
        self._clock = clock
        self._tb = clock.timebase
        self._lock = threading.Lock()
        self._coalescing = False
        self._burst = 3
        self._max_hold: float | None = DEFAULT_MAX_HOLD
        self._pending = 0
        self._generation = 0
        """Counts the bursts taken out of the hold: a hold thread whose burst is gone ends."""
        self._hold_cond = self._tb.Condition(self._lock)
        """Wakes the hold threads when their burst leaves the hold early (or the gate closes)."""
        self._holds: list[HwThread] = []
        self._drops: Counter[str] = Counter()
        self._by_source: Counter[str] = Counter()
        self._raised = 0
        self._delivered = 0
        self._dropped = 0
        self._lost = 0
        self._last_source: str | None = None
        self._closed = False
        # lateness (see late()): all under self._lock; the condition wakes the releasing thread
        self._late_cond = self._tb.Condition(self._lock)
        self._late_max: float | None = None
        self._late_rng = random.Random(0)
        self._late_queue: deque[_Held] = deque()
        self._late_pending = 0
        self._late_delivered = 0
        self._late_delay_max = 0.0
        self._late_busy = False
        """The releasing thread is handing a batch to the line, outside the lock: a raise
        meanwhile must queue behind it even once lateness is off, or it could overtake."""
        self._late_thread: HwThread | None = None
        self._late_threads: list[HwThread] = []
        self._late_log: deque[LateDelivery] = deque(maxlen=LATE_LOG_SIZE)
        self.on_raise: Callable[[str, int], None] | None = None
        """Measurement hook: ``on_raise(source, t_ns)`` for every raise (dropped ones too), in the
        raising thread, after the interrupt was handed to the line; ``t_ns`` is
        ``time.perf_counter_ns()`` at entry, so the hook's own work is not in the timestamp. Keep
        it short: the device model waits for it."""

    # -- raising -------------------------------------------------------------------------------
    def raise_irq(self, source: str) -> None:
        """One interrupt from ``source`` ("data", "cmd", "perr", "berr", "motor", ...)."""
        hook = self.on_raise
        t_ns = time.perf_counter_ns() if hook is not None else 0
        self._raise(source)
        if hook is not None:
            hook(source, t_ns)

    def _raise(self, source: str) -> None:
        deliver = 0
        with self._lock:
            self._raised += 1
            self._by_source[source] += 1
            if self._drops and self._drops[source] > 0:  # no Counter lookup when none is armed
                self._drops[source] -= 1
                self._dropped += 1
                return
            self._last_source = source
            if not self._coalescing:
                deliver = self._release(1)
            else:
                self._pending += 1
                if self._pending >= self._burst:
                    deliver = self._take_pending()
                elif self._pending == 1:
                    self._arm_hold()
        self._deliver(deliver)

    def spurious(self) -> None:
        """An interrupt with no cause: the driver's demultiplexer must find nothing to do."""
        self.raise_irq(SPURIOUS)

    # -- faults --------------------------------------------------------------------------------
    def coalesce(
        self, enabled: bool, burst: int = 3, *, max_hold: float | None = DEFAULT_MAX_HOLD
    ) -> None:
        """Hold interrupts and deliver them ``burst`` at a time; switching off flushes.

        ``max_hold`` (hardware seconds, None = until the burst fills or a flush) bounds how
        late a held interrupt can be, so coalescing delays the last interrupt of a sequence
        instead of swallowing it.
        """
        if burst < 1:
            raise ValueError(f"burst must be at least 1, not {burst}")
        if max_hold is not None and not max_hold > 0.0:
            raise ValueError(f"max_hold must be positive or None, not {max_hold}")
        deliver = 0
        with self._lock:
            self._coalescing = enabled
            self._burst = burst
            self._max_hold = max_hold
            if not enabled or self._pending >= burst:
                deliver = self._take_pending()
        self._deliver(deliver)

    def drop_next(self, source: str) -> None:
        """Lose the next interrupt from ``source`` (calls accumulate: two calls lose two)."""
        with self._lock:
            self._drops[source] += 1

    def late(self, max_delay_s: float | None, rng: random.Random | None = None) -> None:
        """Deliver every interrupt late by a delay drawn uniformly in ``[0, max_delay_s]``
        hardware seconds, or, with None, deliver what is held now and stop delaying.

        ``rng`` draws the delays (kept from the previous call when None): seeding it makes the
        delays reproducible, one draw per delivery in the order the gate makes them. Calling it
        again while on changes the bound for interrupts raised from then on. Switching off
        returns once the held interrupts have reached the line (in order, as one count or a
        few), unless it is called from the releasing thread itself.
        """
        if max_delay_s is not None and not (math.isfinite(max_delay_s) and max_delay_s >= 0.0):
            raise ValueError(f"max_delay_s must be finite and not negative, not {max_delay_s}")
        with self._lock:
            if rng is not None:
                self._late_rng = rng
            self._late_max = max_delay_s
            if max_delay_s is None:
                self._late_cond.notify_all()
                me = threading.current_thread()
                # until the releasing thread has flushed the queue (it exits once it is empty),
                # or someone switched lateness on again, or the gate was closed
                while (
                    (self._late_queue or self._late_busy)
                    and self._late_max is None
                    and self._late_thread is not None
                    and self._late_thread is not me
                ):
                    self._late_cond.wait(what="irqgate late interrupts flushed")
                return
            if self._late_thread is None and not self._closed:
                thread = self._tb.Thread(self._late_run, name="irqgate-late", daemon=True)
                self._late_thread = thread
                self._late_threads = [t for t in self._late_threads if t.is_alive()]
                self._late_threads.append(thread)
                thread.start()

    def flush(self) -> None:
        """Deliver every held interrupt now, as one burst."""
        with self._lock:
            deliver = self._take_pending()
        self._deliver(deliver)

    def close(self) -> None:
        """End and join the hold threads and the late-release thread; held interrupts stay
        held (nobody is left to take them). Joining matters: a rig that closes must leave no
        thread behind. The joins are waits in the time base, so a participant may close."""
        with self._lock:
            self._closed = True
            self._generation += 1
            holds, self._holds = self._holds, []
            self._hold_cond.notify_all()
            self._late_thread = None
            self._late_cond.notify_all()
            late_threads, self._late_threads = self._late_threads, []
        me = threading.current_thread()
        for thread in holds + late_threads:
            if thread is not me:
                self._tb.join_thread(thread)

    # -- observability -------------------------------------------------------------------------
    @property
    def clock(self) -> SimClock:
        """The hardware clock the gate's holds and delays are measured on."""
        return self._clock

    @property
    def raised(self) -> int:
        """Interrupts raised by the models (including spurious and dropped ones)."""
        with self._lock:
            return self._raised

    @property
    def delivered(self) -> int:
        """Interrupts that reached the line."""
        with self._lock:
            return self._delivered

    @property
    def dropped(self) -> int:
        """Interrupts lost on purpose by :meth:`drop_next`."""
        with self._lock:
            return self._dropped

    @property
    def lost(self) -> int:
        """Interrupts the line refused because it was already closed."""
        with self._lock:
            return self._lost

    @property
    def pending(self) -> int:
        """Interrupts held by coalescing, not yet delivered."""
        with self._lock:
            return self._pending

    @property
    def late_pending(self) -> int:
        """Interrupts held by lateness, not yet delivered."""
        with self._lock:
            return self._late_pending

    @property
    def late_delivered(self) -> int:
        """Interrupts delivered after lateness held them (included in :attr:`delivered`)."""
        with self._lock:
            return self._late_delivered

    @property
    def late_delay_max(self) -> float:
        """The largest delay drawn so far, hardware seconds (0.0 before any)."""
        with self._lock:
            return self._late_delay_max

    @property
    def late_bound(self) -> float | None:
        """The bound delays are drawn under, hardware seconds; None while lateness is off."""
        with self._lock:
            return self._late_max

    @property
    def late_log(self) -> tuple[LateDelivery, ...]:
        """The latest :data:`LATE_LOG_SIZE` late deliveries, oldest first."""
        with self._lock:
            return tuple(self._late_log)

    @property
    def coalescing(self) -> bool:
        with self._lock:
            return self._coalescing

    @property
    def last_source(self) -> str | None:
        """Source of the most recent interrupt that was not dropped (None before the first)."""
        with self._lock:
            return self._last_source

    def raised_by(self, source: str) -> int:
        """Interrupts raised by ``source`` so far, dropped ones included."""
        with self._lock:
            return self._by_source[source]

    # -- internals -----------------------------------------------------------------------------
    def _take_pending(self) -> int:
        """Empty the hold (lock held) and end its hold thread; returns the count to deliver."""
        count, self._pending = self._pending, 0
        self._generation += 1
        self._hold_cond.notify_all()
        return self._release(count)

    def _release(self, count: int) -> int:
        """``count`` interrupts leave the gate's hold (lock held): counted as delivered and
        returned for :meth:`_deliver`, or queued for the late-release thread (returns 0).

        They queue while lateness is on, and also while anything is still queued or on its way
        out after it was switched off, so that nothing overtakes an interrupt raised earlier.
        """
        if count <= 0:
            return 0
        if self._late_max is None and not self._late_queue and not self._late_busy:
            self._delivered += count
            return count
        now = self._clock.now()
        delay = 0.0 if self._late_max is None else self._late_rng.uniform(0.0, self._late_max)
        # never before the batch ahead (a batch already flushed early does not count: the bound
        # holds again as soon as lateness is back on)
        ahead = self._late_queue[-1].due_s if self._late_queue else now
        due = max(now + delay, ahead)
        self._late_queue.append(_Held(count, now, delay, due))
        self._late_pending += count
        self._late_delay_max = max(self._late_delay_max, delay)
        self._late_cond.notify_all()
        return 0

    def _late_run(self) -> None:
        """The late-release thread: hands each queued batch to the line once it is due (all of
        them at once after lateness is switched off), then exits when off and empty."""
        me = threading.current_thread()
        with self._lock:
            try:
                while self._late_thread is me:
                    if not self._late_queue and self._late_max is None:
                        return
                    self._late_step()
            finally:
                # also when the line raised something unexpected: whoever waits for the flush
                # in late(None) must not wait for a thread that is gone
                if self._late_thread is me:
                    self._late_thread = None
                self._late_cond.notify_all()

    def _late_step(self) -> None:
        """One turn of the late-release thread (lock held): wait for the head of the queue to
        fall due, or deliver every batch that is due (every batch, once lateness is off)."""
        queue = self._late_queue
        if not queue:
            self._late_cond.wait(what="irqgate late: an interrupt to hold")
            return
        now = self._clock.now()
        if self._late_max is not None:
            due = queue[0].due_s
            if due > now:
                self._late_cond.wait(
                    self._clock.timeout_until(due, now), what="irqgate late: next one due"
                )
                return
        count = 0
        while queue and (self._late_max is None or queue[0].due_s <= now):
            held = queue.popleft()
            count += held.interrupts
            self._late_log.append(
                LateDelivery(held.interrupts, held.raised_s, held.delay_s, held.due_s, now)
            )
        self._late_pending -= count
        self._late_delivered += count
        self._delivered += count
        self._late_busy = True
        self._lock.release()
        try:
            self._deliver(count)
        finally:
            self._lock.acquire()
            self._late_busy = False
            self._late_cond.notify_all()

    def _arm_hold(self) -> None:
        """Start the max-hold thread for a burst that just began (lock held); none once the
        gate is closed (nobody would join it)."""
        if self._max_hold is None or self._closed:
            return
        due = self._clock.now() + self._max_hold
        thread = self._tb.Thread(
            self._hold_run, name="irqgate-hold", args=(self._generation, due), daemon=True
        )
        self._holds = [t for t in self._holds if t.is_alive()]
        self._holds.append(thread)
        thread.start()

    def _hold_run(self, generation: int, due: float) -> None:
        """A hold thread: at hardware time ``due``, release the burst it was started for,
        unless the burst left the hold before (``generation`` moved on: it ends at once)."""
        deliver = 0
        with self._lock:
            while generation == self._generation:
                now = self._clock.now()
                if now >= due:
                    deliver = self._take_pending()
                    break
                self._hold_cond.wait(self._clock.timeout_until(due, now), what="irqgate max hold")
        self._deliver(deliver)

    def _deliver(self, count: int) -> None:
        """Pull the level ``count`` times; already counted as delivered under the lock, so the
        counters add up at every instant, and moved to ``lost`` if the line turns out closed."""
        if count <= 0:
            return
        try:
            self._trigger(count)
        except LineClosed:
            with self._lock:
                self._delivered -= count
                self._lost += count
