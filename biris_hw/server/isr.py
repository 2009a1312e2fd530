"""The BIRIS server's interrupt service routines: physical levels 2 and 3 into the report's
logical interrupts.

Each routine is a :class:`~biris_hw.irq.Demultiplexer` (the generic thread, logical lines,
counters and lifecycle); what is here is the report's protocol for deciding which logical
interrupt a physical one was.

**Level 2** (BIRIS and the Bit 3 coupler), per physical interrupt, in this order:

1. The coupler's LOCAL_STATUS. PARITY_ERROR raises BIT3_PERR, REMOTE_BUS_ERROR raises BIT3_BERR.
   Both bits are sticky until the driver writes CLR_ERROR, so only a bit that is newly set since
   the routine last looked is an interrupt; a still-set bit is old news, and a bit that has been
   cleared is forgotten, so that it counts again when it is next set.
2. If an error was raised and the physical count is 1, that interrupt was the coupler's: done.
3. Otherwise COMMAND in BIEXEC_COM: non-zero means a command is still running, so this is a
   data interrupt and BIRIS_DATA_DEV is raised with the count; zero means BIRIS has cleared it on
   completion, so BIRIS_CMD is raised.

**Continuous mode** (Appendix D). While BIRIS acquires continuously, COMMAND stays zero during
its data interrupts, so step 3 alone would take every one of them for a completion. The report
foresees "a new flag to identify the continuous mode": :attr:`Level2Demux.continuous`, set by
biris_cmd_transfer before it writes BI_START_CONTINUOUS and cleared by biris_cmd_notifier once
BI_STOP_CONTINUOUS has completed. While it is set, an interrupt with COMMAND zero raises
BIRIS_DATA_DEV (counted) *and* wakes BIRIS_CMD (not counted: most of these wakes are not
completions). Neither wake can mislead: the data path catches up by ACQ_LINE, so a wake with
nothing new reads nothing, and the command notifier completes a command only if one is
outstanding and COMMAND reads zero, which is exactly the state after BIRIS has finished it. An
interrupt with COMMAND non-zero is data, as before.

Coalescing (a count above 1) must not lose data. With COMMAND zero, a burst may hold data
interrupts as well as the completion, and the last of them is the one that announces the final
acquisition (ACQ_LINE -128). So BIRIS_DATA_DEV is raised too, before BIRIS_CMD, even when the
burst might have been an error plus the completion: the data path catches up by ACQ_LINE rather
than by counting, so a spare wake finds nothing new, while a missed one would lose the end of a
sequence. With COMMAND non-zero no completion can be hidden in the burst, because the driver
never writes the next command before it has serviced BIRIS_CMD.

A BusError while reading the coupler or COMMAND is itself a failed cycle across the coupler, so
it raises BIT3_BERR and the routine keeps running.

**The BIRIS crate's connection** (beyond the report). LOCAL_STATUS also says whether BIRIS can be
reached at all: NO_CONNECT (bit 0: the BIRIS crate's power is off, or the cable is out) and the
sticky TIMEOUT error (bit 2: an access across the coupler got no answer). Either, newly set, is
the end of every exchange with BIRIS, so the routine raises ``HardwareFault("bus")`` naming it,
which its supervisor reports to every caller at once (and the routine waits for the next reset,
whose initialiser checks the link before anything else: :meth:`~biris_hw.devices.Coupler.
check_link`). A TIMEOUT the first look finds after the routine begins to serve is old news left
to that check, which clears it (a sticky bit latched before a power cycle); NO_CONNECT is a
state and is reported whenever seen. NO_CONNECT raises no interrupt of its own, and a BIRIS
without power raises none either, so the routine does not wait for one: it reads LOCAL_STATUS
whenever :data:`COUPLER_WATCH_S` of hardware time has passed without its having read it, which
bounds how long a powered-off crate goes unnoticed by every caller, idle or mid-scan. While
interrupts keep coming (a scan's data, 30 a second) each of them reads LOCAL_STATUS anyway and
no extra read is made; idle, the watch costs four reads of a host-side register a second.

**Failure.** The server runs both routines under its supervisor
(:meth:`~biris_hw.irq.Demultiplexer.serve`). A physical line that is closed under a routine, or
that fails, means the target has gone: the supervisor reports a ``bus`` fault. A HardwareFault a
routine raises (level 3's held drive fault) is reported with its own kind; anything else is an
``internal`` one. Either way the routine then waits for the next reset and
runs again. The data notifier that shares the level-2 thread reports its own failures and is
detached until that reset re-attaches it (:meth:`Level2Demux.attach_data_notifier`).

**biris_data_notifier shares the level-2 thread** (the server's task table says so, and why). A
data notifier attached with :meth:`Level2Demux.attach_data_notifier` is run here in place of
raising BIRIS_DATA_DEV: it reads the completed acquisitions and *posts* NEW_POINT one-way, so it
never waits for the administrator, and the routine is back on the physical line as soon as the
frames are read; BIRIS_CMD, BIT3_PERR and BIT3_BERR are never held up by the administrator. Run
on a thread of its own instead, the notifier would cost every acquisition one more thread
wake-up; measured, that added 50-100 us to the interrupt-to-client latency (p50) and did not
make BIRIS_CMD's service any prompter (numbers: :mod:`biris_hw.server.task_table`). With no
notifier attached the line is raised as for every other logical interrupt.

**Level 3** (the motion controller: the Model 7600 board, or CiA 402 drives over CAN):
``ended_axes()`` (the board's IRQ_STATUS) names the axes whose trapezoidal profile ended.
Each is acknowledged (the board: write 1 to its bit) *before* its logical interrupt is raised,
so the acknowledgement can never clear the end of a move the woken notifier has already started:
azimuth raises MOTOR_END_OF_SCAN, elevation ELEVATION_END_OF_SCAN. An interrupt with no bit set
is spurious: counted, nothing raised. Before any of that, a fault the controller holds
(``take_fault()``: CiA 402 drives' EMCYs and lost heartbeats; never on the Model 7600) is
raised as the HardwareFault it is, with its kind (``motor_stall`` or ``bus``), and the
supervisor reports that kind to every caller at once, even with both axes standing idle.

**Registers read by the interrupt itself.** A line that reads registers at interrupt time
(the VM-USB runs an IRQ stack and sends what it read with the interrupt:
:class:`~biris_hw.irq.vmusb.VmUsbLine`) offers them through ``prefetched()``: level 2's stack
reads LOCAL_STATUS and COMMAND (:data:`LEVEL2_PREFETCH`), level 3's IRQ_STATUS
(:data:`LEVEL3_PREFETCH`). The routines then decide from those values, which are the ones the
registers held when the interrupt was serviced, and spend no bus round trip on deciding; a line
without them (or a wake that brought none) is served by reading the registers as above.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Callable, Collection

from biris_hw.axes.base import MotionController
from biris_hw.bus.base import BusWindow
from biris_hw.devices import LEVEL2_PREFETCH, LEVEL3_PREFETCH, MotionBoard, coupler_status_text
from biris_hw.errors import BusError, HardwareFault
from biris_hw.irq.base import InterruptLine
from biris_hw.irq.demux import Demultiplexer
from biris_hw.timebase import ScaledTime, TimeBase
from regs.biexec import OFF_COMMAND
from regs.bit3 import Bit3Reg, LocalStatus
from regs.tech80 import Axis, AxisBit

__all__ = [
    "COUPLER_WATCH_S",
    "LEVEL2_LOGICALS",
    "LEVEL2_PREFETCH",
    "LEVEL3_LOGICALS",
    "LEVEL3_PREFETCH",
    "Level2Demux",
    "Level3Demux",
    "Logical",
    "prefetched",
]

log = logging.getLogger(__name__)


class Logical(enum.IntEnum):
    """The report's logical interrupts (device codes), plus the future elevation one."""

    BIRIS_DATA_DEV = 1
    BIRIS_CMD = 2
    BIT3_PERR = 3
    BIT3_BERR = 4
    MOTOR_END_OF_SCAN = 5
    ELEVATION_END_OF_SCAN = 6


LEVEL2_LOGICALS = (
    Logical.BIRIS_DATA_DEV,
    Logical.BIRIS_CMD,
    Logical.BIT3_PERR,
    Logical.BIT3_BERR,
)
LEVEL3_LOGICALS = (Logical.MOTOR_END_OF_SCAN, Logical.ELEVATION_END_OF_SCAN)

LEVEL2_THREAD = "level2_isr"
"""The level-2 routine's thread name (a row of the task table)."""
LEVEL3_THREAD = "level3_isr"
"""The level-3 routine's thread name (a row of the task table)."""

_PERR = int(LocalStatus.PARITY_ERROR)
_BERR = int(LocalStatus.REMOTE_BUS_ERROR)
_TIMEOUT = int(LocalStatus.TIMEOUT)
_LINK = int(LocalStatus.NO_CONNECT) | _TIMEOUT

COUPLER_WATCH_S = 0.9
"""Most hardware seconds the level-2 routine lets pass without reading the coupler's
LOCAL_STATUS (module notes): a BIRIS crate that loses power is a ``bus`` fault to every caller
within this, plus one administrator case: under the 1 s of hardware time issue 26 asks for,
at about one read a second, what an idle sensor can spare (the idle benchmark's bus reads: the
encoders' once a second at rest, and this)."""


def prefetched(line: InterruptLine, n: int) -> tuple[int, ...] | None:
    """The ``n`` values ``line`` read at interrupt time for its last wake, or None when it
    reads nothing itself (every kind but the VM-USB's) or brought a different count."""
    get = getattr(line, "prefetched", None)
    if get is None:
        return None
    values = get()
    if values is None or len(values) != n:
        return None
    return tuple(int(v) for v in values)


class Level2Demux(Demultiplexer[Logical]):
    """Level 2: BIRIS_DATA_DEV, BIRIS_CMD, BIT3_PERR, BIT3_BERR (decision order: module doc).

    ``coupler`` is the Bit 3 register window, ``biris`` BIRIS memory, and ``biexec_offset``
    where BIEXEC_COM sits in it. ``watch_s``: hardware seconds between two reads of
    LOCAL_STATUS at most (:data:`COUPLER_WATCH_S`; None: only when an interrupt comes).
    """

    def __init__(
        self,
        line: InterruptLine,
        coupler: BusWindow,
        biris: BusWindow,
        biexec_offset: int,
        name: str = LEVEL2_THREAD,
        *,
        timebase: TimeBase | None = None,
        watch_s: float | None = COUPLER_WATCH_S,
    ) -> None:
        super().__init__(line, LEVEL2_LOGICALS, name, timebase=timebase)
        if watch_s is not None and not watch_s > 0.0:
            raise ValueError(f"watch_s must be positive, not {watch_s}")
        self._watch_s = watch_s
        self._clock: TimeBase = timebase if timebase is not None else ScaledTime()
        self._next_watch = 0.0  # hardware time of the next look at LOCAL_STATUS, if none before
        self._first_look = True  # the first look since the routine began to serve
        self._coupler = coupler
        self._biris = biris
        self._command_offset = biexec_offset + OFF_COMMAND
        self._seen_errors = 0  # only the service thread touches it
        self._continuous = False
        self._data_notifier: Callable[[int], bool] | None = None
        self._attach_lock = (timebase if timebase is not None else ScaledTime()).Lock()
        self._recheck: Callable[[], bool] | None = None

    def attach_recheck(self, recheck: Callable[[], bool] | None) -> None:
        """Run ``recheck()`` in this thread when asked (:meth:`~biris_hw.irq.demux.
        Demultiplexer.recheck`: the BIRIS timeout ran out): it reads BIRIS afresh and reports
        to the server, and returns True when BIRIS has completed its command, whose BIRIS_CMD
        is then raised (its interrupt may be the one the host is late with). None detaches."""
        self._recheck = recheck

    def _look(self) -> None:
        """The BIRIS timeout ran out: read BIRIS afresh (the attached recheck), and wake the
        command notifier if BIRIS had completed its command meanwhile."""
        recheck = self._recheck
        if recheck is not None and recheck():
            self._raise(Logical.BIRIS_CMD, counted=False)

    def attach_data_notifier(self, notifier: Callable[[int], bool] | None) -> None:
        """Run ``notifier(count)`` in this thread for BIRIS_DATA_DEV instead of raising its line.

        ``notifier`` must not block on another task (the server's posts one-way). It returns
        False once its task has ended (the administrator stopped, or it failed and reported
        so); it is then detached and the line is raised again, until a notifier is attached
        anew. None detaches. Safe at any time, from any thread: a notifier attached while the
        previous one is ending is never detached in its place.
        """
        with self._attach_lock:
            self._data_notifier = notifier

    @property
    def continuous(self) -> bool:
        """Appendix D's continuous-mode flag (see the module notes)."""
        return self._continuous

    def set_continuous(self, on: bool) -> None:
        """Set or clear the flag; a plain store, so a notifier may call it at any time."""
        self._continuous = bool(on)

    def _waiter(self, line_fd: int) -> Callable[[], Collection[int]]:
        """The frame's wait, bounded so that LOCAL_STATUS is read at least every ``watch_s``
        (module notes); the look is made here, in the routine's thread, before the wait
        returns (a HardwareFault from it ends the routine, as from ``_service``)."""
        self._first_look = True
        if self._watch_s is None:
            return super()._waiter(line_fd)
        fds = (self._stop_fd, line_fd, self._look_fd)
        clock = self._clock
        what = f"{self.name}: its physical interrupt line or the coupler's next look"
        self._next_watch = clock.now() + self._watch_s

        def ready() -> Collection[int]:
            left = self._next_watch - clock.now()
            got = clock.poll(fds, max(0.0, left), what=what) if left > 0.0 else []
            if not got and clock.now() >= self._next_watch:
                # read here, not in _coupler_errors: a coupler that cannot be read at all is
                # a target gone (the BusError ends the routine as a ``bus`` fault, once),
                # not a BIT3_BERR raised again at every look
                self._coupler_errors(self._coupler.read8(Bit3Reg.LOCAL_STATUS))
            return got

        return ready

    def _service(self, count: int) -> None:
        pre = prefetched(self._line, len(LEVEL2_PREFETCH))
        error_raised = self._coupler_errors(None if pre is None else pre[0])
        if error_raised and count == 1:
            return  # the coupler's own interrupt
        try:
            command = self._biris.read16(self._command_offset) if pre is None else pre[1]
        except BusError as exc:
            log.error("level 2: COMMAND unreadable (%s); raising BIT3_BERR", exc)
            self._raise(Logical.BIT3_BERR)
            return
        biris_interrupts = count - 1 if error_raised else count
        if command:
            self._data(biris_interrupts)
            return
        if self._continuous:
            self._data(max(1, biris_interrupts))
            self._raise(Logical.BIRIS_CMD, counted=False)
            return
        if count > 1:
            self._data(max(1, biris_interrupts - 1))
        self._raise(Logical.BIRIS_CMD)

    def _data(self, count: int) -> None:
        """BIRIS_DATA_DEV: to the attached data notifier, run here, or else raised on its line.

        Counted before the notifier runs, as a raise is counted before its notifier wakes. The
        routine goes on whatever the notifier does, because the other logical interrupts of the
        level must not die with it. The server's notifier reports its own failure and returns
        False, which detaches it until a reset attaches a new one. A notifier that raises
        instead is logged and stays attached.
        """
        notifier = self._data_notifier
        if notifier is None:
            self._raise(Logical.BIRIS_DATA_DEV, count)
            return
        self._count(Logical.BIRIS_DATA_DEV, count)
        try:
            ended = not notifier(count)
        except Exception:  # a notifier that does not report its own failures
            log.exception("level 2: the data notifier failed; it stays attached")
            return
        if ended:
            with self._attach_lock:
                if self._data_notifier is notifier:  # not one attached since it was called
                    self._data_notifier = None

    def _coupler_errors(self, status: int | None = None) -> bool:
        """Raise the error interrupts newly shown in LOCAL_STATUS (``status`` when the line
        read it at interrupt time); True if any was raised.

        Raises:
            HardwareFault: ``bus``, when NO_CONNECT or TIMEOUT is newly set (module notes).
        """
        if self._watch_s is not None:
            self._next_watch = self._clock.now() + self._watch_s
        try:
            if status is None:
                status = self._coupler.read8(Bit3Reg.LOCAL_STATUS)
        except BusError as exc:
            log.error("level 2: coupler status unreadable (%s); raising BIT3_BERR", exc)
            self._raise(Logical.BIT3_BERR)
            return True
        errors = status & (_PERR | _BERR | _LINK)
        new = errors & ~self._seen_errors
        self._seen_errors = errors  # a cleared bit is forgotten, so its next setting is new
        if self._first_look:
            # a TIMEOUT latched before this routine ran is the initialiser's to clear (it
            # checks the link at every start and reset)
            self._first_look = False
            new &= ~_TIMEOUT
        if new & _LINK:
            raise HardwareFault("bus", _link_text(status))
        if new & _PERR:
            self._raise(Logical.BIT3_PERR)
        if new & _BERR:
            self._raise(Logical.BIT3_BERR)
        return bool(new)


def _link_text(status: int) -> str:
    """What a LOCAL_STATUS with NO_CONNECT or TIMEOUT means, for the fault's message."""
    what = coupler_status_text(status)
    if status & LocalStatus.NO_CONNECT:
        return (
            f"the Bit 3 coupler lost the BIRIS crate (LOCAL_STATUS {what}): its power is off "
            f"or the cable is out; restore it, then reset"
        )
    return (
        f"an access across the Bit 3 coupler timed out (LOCAL_STATUS {what}): BIRIS does not "
        f"answer; check the BIRIS crate's power and the cable, then reset"
    )


_AXES = (
    (Axis.AZIMUTH, int(AxisBit.AZIMUTH), Logical.MOTOR_END_OF_SCAN),
    (Axis.ELEVATION, int(AxisBit.ELEVATION), Logical.ELEVATION_END_OF_SCAN),
)


class Level3Demux(Demultiplexer[Logical]):
    """Level 3: the end-of-motion interrupts of the motion controller, one logical line per axis.

    ``controller`` is the device's :class:`~biris_hw.axes.base.MotionController`: the Model
    7600's board registers (:class:`~biris_hw.devices.MotionBoard`; its window alone will do),
    or the controller of CiA 402 drives over CAN, whose line is raised by the drives' event
    TPDOs.
    """

    def __init__(
        self,
        line: InterruptLine,
        controller: MotionController | BusWindow,
        name: str = LEVEL3_THREAD,
        *,
        timebase: TimeBase | None = None,
    ) -> None:
        super().__init__(line, LEVEL3_LOGICALS, name, timebase=timebase)
        if isinstance(controller, BusWindow):  # the Model 7600's window: its board registers
            controller = MotionBoard(controller)
        self._controller: MotionController = controller
        self._look_report: Callable[[int], None] | None = None

    def _service(self, count: int) -> None:
        """Raise a fault the controller holds, else acknowledge and raise each axis that ended.

        A fault the controller holds (:meth:`MotionController.take_fault`: a CAN drive's
        heartbeat lost or communication EMCY, ``bus``; any other EMCY, ``motor_stall``, from a
        drive moving or standing idle) is raised here as the HardwareFault it is, so the
        server's supervisor reports it with that kind to every caller at once, rather than the
        motor watchdog later or the next move's refusal. A BusError on the board's
        IRQ_STATUS is raised on too: the board sits on the host's own bus, so this is not a
        coupler fault that BIT3_BERR could carry, and waiting for the motor watchdog would
        report a lost board as a stalled motor.
        """
        pre = prefetched(self._line, len(LEVEL3_PREFETCH))
        if not self._raise_ended(None if pre is None else pre[0]):
            self._count_spurious(count)

    def attach_look_report(self, report: Callable[[int], None] | None) -> None:
        """Call ``report(ended)`` after each look :meth:`_look` makes, with the ended-axes mask
        it read: the motor watchdog's answer. None detaches."""
        self._look_report = report

    def _look(self) -> None:
        """A motor watchdog ran out (:meth:`~biris_hw.irq.demux.Demultiplexer.recheck`): read
        the controller fresh (never an IRQ stack's old read) and raise each axis whose end is
        latched there: its interrupt was lost on the way (or the host ran this routine late),
        and the move's notifier, woken now, still verifies the arrival. Said as a warning;
        nothing latched, nothing raised. What was read is reported (:meth:`attach_look_report`)
        so the watchdog decides on what the controller says."""
        fault = self._controller.take_fault()
        if fault is not None:
            raise fault
        status = self._controller.ended_axes()
        self._raise_ended(status, asked=True)
        report = self._look_report
        if report is not None:
            report(status)

    def _raise_ended(self, status: int | None, *, asked: bool = False) -> bool:
        """Raise a fault the controller holds; else acknowledge and raise each axis that ended
        by ``status`` (the controller's, read now, when None). True if any had."""
        fault = self._controller.take_fault()
        if fault is not None:
            raise fault
        if status is None:
            status = self._controller.ended_axes()
        ended = [(axis, logical) for axis, bit, logical in _AXES if status & bit]
        for axis, logical in ended:
            if asked:
                log.warning(
                    "%s: %s was latched but its interrupt never came; raised on asking",
                    self.name,
                    logical.name,
                )
            self._controller.acknowledge(axis)
            self._raise(logical)
        return bool(ended)
