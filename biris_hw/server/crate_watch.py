"""The VME crate's health beside the sensor's: the crate monitor polled in a thread of its own.

A Wiener crate reports its power, supply voltages and currents, fans and temperatures over CAN
(:mod:`biris_hw.crate`). None of it is the report's: BIRIS and the Model 7600 only see the
crate die, as a bus fault, when its power goes. Knowing *why* (fans stopped, a supply
over-current, a temperature trip coming) is what an operator needs next to the fault, so the
server polls the monitor and ``status()`` carries the last reading and its alarms.

It is not one of the report's tasks (:mod:`biris_hw.server.task_table`): it sends the
administrator nothing and touches no window, so a crate that stops answering can never stall
the sensor. ``status()`` reads what it holds without waiting on the bus. An alarm that appears,
a crate that stops answering and one that answers again are logged once each, as warnings.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

from biris_hw.errors import BirisError
from regs.wiener_crate import CrateReading

if TYPE_CHECKING:
    from biris_hw.crate import CrateMonitor

__all__ = ["CrateWatch"]

log = logging.getLogger("biris_hw.server")


class CrateWatch:
    """Reads ``monitor`` every ``poll_s`` real seconds until closed; :meth:`latest` is the
    last good reading and the last poll's error.

    Args:
        monitor: the hardware bundle's crate monitor (owned by the bundle, not closed here).
        poll_s: real seconds between two readings (at least 10 ms).
    """

    THREAD = "crate_watch"

    def __init__(self, monitor: CrateMonitor, poll_s: float) -> None:
        if not poll_s >= 0.01:
            raise ValueError(f"the crate's poll period must be at least 0.01 s, not {poll_s!r}")
        self._monitor = monitor
        self._poll_s = poll_s
        self._lock = threading.Lock()
        self._reading: CrateReading | None = None
        self._error: str | None = None
        self._alarms: tuple[str, ...] = ()
        self._polls = 0
        self._polled = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=self.THREAD, daemon=True)

    def start(self) -> CrateWatch:
        self._thread.start()
        return self

    def latest(self) -> tuple[CrateReading | None, str | None]:
        """The last good reading (kept when a later poll fails) and the last poll's error."""
        with self._lock:
            return self._reading, self._error

    def wait_polls(self, count: int, timeout: float) -> bool:
        """Wait until ``count`` polls have been made since the start (tests, and a caller that
        wants a fresh reading after changing something): True when they have."""
        with self._polled:
            return self._polled.wait_for(lambda: self._polls >= count, timeout)

    @property
    def polls(self) -> int:
        with self._lock:
            return self._polls

    def poll(self) -> None:
        """One reading, kept or its failure said (the thread's body calls it)."""
        try:
            reading: CrateReading | None = self._monitor.read()
            error = None
        except BirisError as exc:  # BusError: no answer, a malformed frame, the adapter gone
            reading, error = None, str(exc)
        with self._polled:
            was_error = self._error
            if reading is not None:
                self._reading = reading
            self._error = error
            self._polls += 1
            self._polled.notify_all()
        self._say(reading, error, was_error)

    def _say(self, reading: CrateReading | None, error: str | None, was: str | None) -> None:
        """Log what changed, once: a crate lost or back, an alarm raised or cleared."""
        if error is not None:
            if was is None:
                log.warning("VME crate: %s (its last reading is kept in status())", error)
            return
        if was is not None:
            log.warning("VME crate answers again")
        assert reading is not None
        alarms = reading.alarms()
        for alarm in alarms:
            if alarm not in self._alarms:
                log.warning("VME crate %d: %s", reading.crate_id, alarm)
        for alarm in self._alarms:
            if alarm not in alarms:
                log.warning("VME crate %d: cleared: %s", reading.crate_id, alarm)
        self._alarms = alarms

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.poll()
            except Exception:  # never die silently: say it and try again at the next period
                log.exception("VME crate: polling failed")
            self._stop.wait(self._poll_s)

    def close(self) -> None:
        """Stop polling; returns once the thread has ended (idempotent)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()
