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
- **spurious()** raises an interrupt with no cause behind it.

Counters obey ``raised == delivered + dropped + lost + pending``: ``lost`` counts interrupts the
line refused because the driver had already closed it (a shutdown race, not a fault).

**Measurement hook.** :attr:`InterruptGate.on_raise` (None by default) is called for every
raise with the source and the ``time.perf_counter_ns()`` taken as the model raised it, so a
benchmark can time the driver from the moment the hardware asserted the interrupt. It exists for
``biris_hw.bench`` only and changes nothing about delivery.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable

from biris_hw.errors import LineClosed
from sim.clock import SimClock

__all__ = ["BIRIS_SOURCES", "DEFAULT_MAX_HOLD", "SPURIOUS", "InterruptGate"]

DEFAULT_MAX_HOLD = 0.1
"""Hardware seconds a coalesced interrupt may wait for its burst to fill (six video fields)."""

SPURIOUS = "spurious"
"""The source name of an interrupt with no cause."""

BIRIS_SOURCES = frozenset({"data", "cmd"})
"""Sources that are BIRIS's own (remote IRQ2 through the coupler), as opposed to the coupler's."""


class InterruptGate:
    """Shapes the delivery of one physical interrupt level; every method is thread-safe.

    ``trigger(count)`` is the level itself, typically ``EventFdLine.trigger``. It is called
    outside the gate's lock, so a slow or re-entrant trigger cannot stall the device models.
    """

    def __init__(self, trigger: Callable[[int], None], clock: SimClock) -> None:
        self._trigger = trigger
        self._clock = clock
        self._lock = threading.Lock()
        self._coalescing = False
        self._burst = 3
        self._max_hold: float | None = DEFAULT_MAX_HOLD
        self._pending = 0
        self._generation = 0
        self._timer: threading.Timer | None = None
        self._timers: list[threading.Timer] = []
        self._drops: Counter[str] = Counter()
        self._by_source: Counter[str] = Counter()
        self._raised = 0
        self._delivered = 0
        self._dropped = 0
        self._lost = 0
        self._last_source: str | None = None
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
                self._delivered += 1
                deliver = 1
            else:
                self._pending += 1
                if self._pending >= self._burst:
                    deliver = self._take_pending()
                elif self._pending == 1:
                    self._arm_timer()
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

    def flush(self) -> None:
        """Deliver every held interrupt now, as one burst."""
        with self._lock:
            deliver = self._take_pending()
        self._deliver(deliver)

    def close(self) -> None:
        """Cancel and join the hold timers; held interrupts stay held (nobody is left to take
        them). Joining matters: a rig that closes must leave no thread behind."""
        with self._lock:
            self._generation += 1
            self._timer = None
            timers, self._timers = self._timers, []
        for timer in timers:
            timer.cancel()
            if timer is not threading.current_thread():
                timer.join()

    # -- observability -------------------------------------------------------------------------
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
        """Empty the hold (lock held) and disarm its timer; returns the count to deliver."""
        count, self._pending = self._pending, 0
        self._delivered += count
        self._generation += 1
        timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()
        return count

    def _arm_timer(self) -> None:
        """Start the max-hold timer for a burst that just began (lock held)."""
        if self._max_hold is None:
            return
        generation = self._generation
        timer = threading.Timer(
            self._clock.to_real(self._max_hold), self._expire, args=(generation,)
        )
        timer.daemon = True
        timer.name = "irqgate-hold"
        self._timer = timer
        self._timers = [t for t in self._timers if t.is_alive()]
        self._timers.append(timer)
        timer.start()

    def _expire(self, generation: int) -> None:
        """The hold timer fired: release the burst it was armed for, unless already gone."""
        with self._lock:
            if generation != self._generation:
                return
            self._timer = None
            deliver = self._take_pending()
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
