"""``BirisSupervisor``: the supervisor thread, run at every video field, and its public face.

The thread sleeps on the simulator clock until the next field or event (an idle BIRIS: until
:data:`IDLE_CHECK_FIELDS` fields on, or a write of COMMAND); at a field it ends the
exposure due, polls COMMAND, then starts the next exposure, in that order, so a command written
during an exposure is seen at the field that ends it. Everything the thread changes is
observable under the lock, and :meth:`BirisSupervisor.wait_for` lets a test wait for any state
without sleeping.

The thread, its kick and the state condition all belong to the clock's time base
(:attr:`sim.clock.SimClock.timebase`), so the supervisor runs unchanged on scaled real time or
on virtual time, where its fields fall at exactly ``k * FIELD_PERIOD`` whatever the host does.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from regs.biexec import OFF_COMMAND
from sim.clock import FIELD_PERIOD
from sim.supervisor.acquisition import Acquisition
from sim.supervisor.boot import Boot
from sim.supervisor.commands import Commands
from sim.supervisor.faults import SupervisorFaults

__all__ = ["IDLE_CHECK_FIELDS", "BirisSupervisor"]

log = logging.getLogger("sim.supervisor")

IDLE_CHECK_FIELDS = 30
"""Fields an idle supervisor thread sleeps at a time (half a hardware second). At an idle field
BIRIS only finds COMMAND clear, so the fields slept through are run together when it wakes,
each as it would have run; a COMMAND write from the driver wakes it at once. So only where every
write is seen: not with BIRIS memory shared with another process (``sleep_when_idle=False``).
Woken at every field, an idle simulator's thread would wake 60 times a hardware second for
nothing (on virtual time a thread hand-over each)."""


class BirisSupervisor(Commands, Boot, Acquisition, SupervisorFaults):
    """The BIRIS side of BIEXEC_COM, run by one thread on the simulator clock."""

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> None:
        """Run the supervisor thread; does nothing if it already runs."""
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                return
            self._stopping = False
            self._kick.clear()
            self._shift_schedule()
            self._thread = self._tb.Thread(self._run, name="biris-supervisor", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the thread and join it; idempotent. State and memory are left as they are.

        The join is a wait in the time base, so a participant (a virtual-time test's own
        thread) may stop the supervisor: the kick hands the thread its wake at once.
        """
        with self._lock:
            self._stopping = True
            thread = self._thread
        self._kick.set()
        if thread is not None and thread is not threading.current_thread():
            self._tb.join_thread(thread)

    def __enter__(self) -> BirisSupervisor:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def booted(self) -> bool:
        with self._lock:
            return self._boot is not None

    @property
    def busy(self) -> bool:
        """A command has been accepted and not yet completed."""
        with self._lock:
            return self._executing != 0

    @property
    def continuous(self) -> bool:
        with self._lock:
            return self._continuous

    @property
    def hung(self) -> bool:
        with self._lock:
            return self._hung_since is not None

    @property
    def loaded_lut(self) -> int | None:
        """Elevation (counts) of the calibration table in use, None before boot."""
        with self._lock:
            return self._lut

    @property
    def commands_completed(self) -> int:
        with self._lock:
            return self._commands_completed

    @property
    def acquisitions_made(self) -> int:
        """Acquisitions whose frames were written (abandoned ones do not count)."""
        with self._lock:
            return self._acquisitions_made

    @property
    def acquisitions_abandoned(self) -> int:
        """Exposures cut short by BI_STOP_CONTINUOUS (their slot was restored)."""
        with self._lock:
            return self._acquisitions_abandoned

    @property
    def exposing(self) -> int | None:
        """The frame (ring slot) being exposed now, None in start-up or between sequences."""
        with self._lock:
            seq = self._seq
            return seq.slot if seq is not None and seq.exposing is not None else None

    @property
    def acquisition_times(self) -> list[float]:
        """Mid-exposure clock time of the acquisitions made, oldest first: all of them up to
        ``times_kept`` (:data:`~sim.supervisor.state.ACQUISITION_TIMES_KEPT` by default), the
        newest that many after that, so that a long run's memory stays bounded. Index k is
        acquisition k until then; :meth:`acquisition_times_since` numbers them for ever."""
        with self._lock:
            return self._acquisition_times.recent()

    def acquisition_times_since(self, index: int) -> list[float]:
        """Mid-exposure times of acquisition ``index`` (0 = the first ever made; compare
        :attr:`acquisitions_made`) and every later one; ValueError if it is no longer kept."""
        with self._lock:
            return self._acquisition_times.since(index)

    @property
    def sequence_starts(self) -> list[float]:
        """Clock time (a field) at which each acquisition sequence was accepted: the newest
        ``starts_kept`` (:data:`~sim.supervisor.state.SEQUENCE_STARTS_KEPT` by default). Count
        sequences with :attr:`sequences_started`, which stays exact."""
        with self._lock:
            return self._sequence_starts.recent()

    @property
    def sequences_started(self) -> int:
        """Acquisition sequences accepted since power-up (BI_ACQUIRE and BI_START_CONTINUOUS)."""
        with self._lock:
            return self._sequence_starts.count

    @property
    def failure(self) -> BaseException | None:
        """What stopped the thread, if it died (a bad frame from ``acquire``, a closed window)."""
        with self._lock:
            return self._failure

    def wait_for(self, predicate: Callable[[BirisSupervisor], bool], timeout: float) -> bool:
        """Block up to ``timeout`` seconds of the caller's patience until ``predicate(self)``
        holds; its last value.

        The predicate is re-evaluated whenever the supervisor's state may have changed, so tests
        can wait for "busy", "acquisition k exposed" and the like without sleeping. ``timeout``
        is read by the time base (``timeout_hw``): real seconds in scaled time, seconds at the
        nominal scale in virtual time, so a test keeps its meaning on either.
        """
        with self._changed:
            return self._changed.wait_for(
                lambda: predicate(self), self._tb.timeout_hw(timeout), what="supervisor state"
            )

    def catch_up(self) -> None:
        """Do now whatever was due by now, on the caller's thread.

        BIRIS is a processor of its own and never falls behind the video fields; this thread
        can, when the host is busy. A driver reading BIRIS memory calls this first (as a
        Model 7600 read catches the chips up), so that ACQ_LINE, the frames and the
        interrupts it sees are those of the present, not of the last time this thread ran.
        A hung, stopped or failed supervisor does nothing, as its thread would.
        """
        with self._changed:
            thread = self._thread
            if (
                thread is None
                or self._stopping
                or self._hung_since is not None
                or self._failure is not None
            ):
                return
            now = self._clock.now()
            if self._running_due or self._fields.next_wake() > now:
                return  # already being done: a read from inside an event (an interrupt hook)
            try:
                self._run_due(now)
            except Exception as exc:
                log.exception("BIRIS supervisor stopped (caught up by a reader)")
                self._failure = exc
                self._stopping = True
                self._kick.set()
            self._changed.notify_all()

    def wake_idle(self) -> None:
        """The driver has just written COMMAND (or a byte of it): an idle thread, asleep for
        several fields, looks again at once, and the first field it runs is the first after
        now. The fields it slept through found COMMAND clear (idle) and did nothing, so they
        are passed over, not run with the new COMMAND in place (the rig's window runs them
        before the write lands: :meth:`catch_up`)."""
        with self._lock:
            idle, self._idle = self._idle, False
            if idle:
                self._fields.resume(self._clock.now())
        if idle:
            self._kick.set()

    def run_until(self, t: float) -> None:
        """Do everything due by clock time ``t`` on the caller's thread, whatever the clock says.

        For a supervisor whose thread is not running (never started, or stopped): a test then
        drives it through any number of fields deterministically, as fast as the host computes
        them, instead of waiting for real time. A hung supervisor does nothing, as its thread
        would. RuntimeError while the thread runs: it keeps its own time.
        """
        with self._changed:
            thread = self._thread
            if thread is not None and thread.is_alive():
                raise RuntimeError("the supervisor thread is running; it keeps its own time")
            if self._hung_since is None:
                self._run_due(t)
            self._changed.notify_all()

    # -- the thread --------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while True:
                with self._lock:
                    if self._stopping:
                        return
                    self._kick.clear()
                    hung = self._hung_since is not None
                    wake = self._fields.next_wake()
                    self._idle = self._sleep_when_idle and self._quiescent_locked()
                    if self._idle:
                        wake = self._fields.idle_wake(IDLE_CHECK_FIELDS)
                if hung:
                    self._kick.wait(what="supervisor unhang")
                    continue
                # labelled "next field" by the clock (a test's stand-in clock takes no label)
                if not self._clock.wait_until(wake, self._kick):
                    continue
                with self._changed:
                    if self._hung_since is None and not self._stopping:
                        self._run_due(self._clock.now())
                    self._changed.notify_all()
        except Exception as exc:
            log.exception("BIRIS supervisor stopped")
            with self._changed:
                self._failure = exc
                self._changed.notify_all()

    def _quiescent_locked(self) -> bool:
        """Nothing to do at a field but find COMMAND clear: no command executing or written, no
        sequence, nothing scheduled. The thread then sleeps :data:`IDLE_CHECK_FIELDS` fields at
        a time; a COMMAND write wakes it (:meth:`note_command_write`), and the driver's window
        runs the fields due before the write lands (:meth:`catch_up`), so every field still
        happens, at its own time, as it would have."""
        return (
            self._seq is None
            and not self._continuous
            and self._executing == 0
            and not self._outstanding_write
            and not self._fields.pending
            and self._get(OFF_COMMAND) == 0
        )

    def _run_due(self, now: float) -> None:
        """Everything due by ``now``, once: an event may read BIRIS memory through the driver's
        window (a test's interrupt hook does), and that read must not start it over."""
        self._running_due = True
        try:
            self._fields.run_due(now, self._on_vsync)
        finally:
            self._running_due = False

    def _on_vsync(self, field: int) -> None:
        """One vertical sync: end the exposure due now, poll COMMAND, start the next exposure."""
        self._exposure_ends(field)
        self._poll_command(field, field * FIELD_PERIOD)
        self._exposure_starts(field, field * FIELD_PERIOD)
