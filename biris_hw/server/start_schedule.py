"""When a report-mode scan's trapezoid starts: at a hardware time fixed by BI_ACQUIRE's write.

A report-mode scan writes BI_ACQUIRE first; BIRIS then spends its start-up (the report's 240 ms:
whole video fields, from the vertical sync at which it sees the command) acquiring nothing, and
its first acquisition begins. The motor must start then, so that the scan's first acquisition
is made as the head leaves its start and its last as the head arrives.

Starting the motor when the host *sees* BIRIS's first data interrupt makes the scan's coverage
depend on how late the host is: every millisecond between the interrupt and the trapezoid is a
millisecond of acquisitions missing at the scan's end, and a scan of a few degrees could come
back empty. So the start is a *schedule* instead: biris_cmd_transfer writes COMMAND and notes
the hardware time of the write (:meth:`StartSchedule.written`); az_scan_start, which has the
scan's move order already, waits on the hardware clock until ``written + lead`` -- the start-up
the server has measured on earlier scans (:class:`~biris_hw.server.scan_timing.ScanTiming`) --
and starts the trapezoid. Nothing on that path waits for an interrupt to be delivered or for
the administrator to run; what is left to the host is one timed wake of one thread, and how
late that was is measured (:attr:`StartSchedule.late_s`), allowed for in the next scans' count,
and said in the scan when it cost coverage.

The administrator cancels a schedule when the scan is abandoned (a fault, a reset, the server
stopping): the waiting worker then starts nothing and reports ready.
"""

from __future__ import annotations

from collections.abc import Callable

from biris_hw.timebase import timebase_of

__all__ = ["StartSchedule"]

WRITE_WAIT_S = 2.0
"""Real seconds az_scan_start waits for BI_ACQUIRE's write before giving the start up: the
command worker writes within microseconds of being ordered, so a write this late means the
worker failed (a bus fault, reported by the supervisor) or the scan was abandoned."""


class StartSchedule:
    """The hand-over between BI_ACQUIRE's write and the scan's trapezoid (module notes).

    ``lead_s`` is the hardware time from the write to the motor's start; ``clock`` the hardware
    clock, waited on through its time base (:func:`~biris_hw.timebase.timebase_of`: scaled at
    ``time_scale``, or the simulator's virtual time). Shared by three threads: the command
    worker (:meth:`written`), the azimuth worker (:meth:`wait_start`, :meth:`started`) and the
    administrator (:meth:`cancel`, and reading the times once the scan is over); every field is
    guarded by one condition.
    """

    def __init__(self, lead_s: float, clock: Callable[[], float], time_scale: float = 1.0) -> None:
        self.lead_s = max(0.0, lead_s)
        self._timebase = timebase_of(clock, time_scale)
        self._clock = self._timebase.now
        self._cond = self._timebase.Condition()
        self._written_at: float | None = None
        self._started_at: float | None = None
        self._cancelled = False

    # -- the command worker --------------------------------------------------------------------
    def written(self, at: float) -> None:
        """BI_ACQUIRE was written to COMMAND at hardware time ``at``."""
        with self._cond:
            self._written_at = at
            self._cond.notify_all()

    # -- the administrator -----------------------------------------------------------------------
    def cancel(self) -> None:
        """The scan is abandoned: a worker waiting to start it starts nothing. Never blocks
        beyond the condition's hand-over."""
        with self._cond:
            self._cancelled = True
            self._cond.notify_all()

    @property
    def cancelled(self) -> bool:
        return self._cancelled

    @property
    def written_at(self) -> float | None:
        """When BI_ACQUIRE was written (hardware clock), once it has been."""
        return self._written_at

    @property
    def start_at(self) -> float | None:
        """When the trapezoid is due (hardware clock), once BI_ACQUIRE has been written."""
        written = self._written_at
        return None if written is None else written + self.lead_s

    @property
    def started_at(self) -> float | None:
        """When the worker started the trapezoid (hardware clock, read just before it did)."""
        return self._started_at

    @property
    def late_s(self) -> float | None:
        """How much later than due the trapezoid started (hardware seconds; 0 if on time), once
        it has."""
        due, started = self.start_at, self._started_at
        if due is None or started is None:
            return None
        return max(0.0, started - due)

    # -- the azimuth worker ----------------------------------------------------------------------
    def wait_start(self) -> bool:
        """Block until the trapezoid is due; False if the scan was cancelled (or its command
        never written) meanwhile, and then nothing may start.

        The wait is on the hardware clock's time base: woken by :meth:`cancel`, and otherwise at
        the due time (re-checked on waking, so a clock that ran slow or fast is still honoured).
        """
        with self._cond:
            if not self._cond.wait_for(
                lambda: self._cancelled or self._written_at is not None,
                self._timebase.timeout_hw(WRITE_WAIT_S),
                what="BI_ACQUIRE written",
            ):
                return False
            while not self._cancelled:
                due = self.start_at
                assert due is not None
                remaining = due - self._clock()
                if remaining <= 0.0:
                    self._started_at = self._clock()
                    return True
                self._cond.wait(remaining, what="the trapezoid's start")
            return False
