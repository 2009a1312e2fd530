"""Harmony's interrupt service routine: physical levels into the report's logical interrupts.

Harmony lets several logical interrupts share one physical level and demultiplexes them in a
service routine; a notifier task blocks on its logical interrupt only. Here each demultiplexer is
a thread that waits on the physical line (and its own stop eventfd, so ``close()`` is immediate)
and raises one :class:`EventFdLine` per logical interrupt.

**Level 2** (BIRIS and the Bit 3 coupler), per physical interrupt, in this order:

1. The coupler's LOCAL_STATUS. PARITY_ERROR raises BIT3_PERR, REMOTE_BUS_ERROR raises BIT3_BERR.
   Both bits are sticky until the driver writes CLR_ERROR, so only a bit that is newly set since
   the demultiplexer last looked is an interrupt; a still-set bit is old news, and a bit that
   has been cleared is forgotten, so that it counts again when it is next set.
2. If an error was raised and the physical count is 1, that interrupt was the coupler's: done.
3. Otherwise COMMAND in BIEXEC_COM: non-zero means a command is still running, so this is a
   data interrupt and BIRIS_DATA_DEV is raised with the count; zero means BIRIS has cleared it on
   completion, so BIRIS_CMD is raised.

**Continuous mode** (Appendix D). While BIRIS acquires continuously, COMMAND stays zero during
its data interrupts, so step 3 alone would take every one of them for a completion. The report
foresees "a new flag to identify the continuous mode": :attr:`Level2Demux.continuous`, set by the
server before it writes BI_START_CONTINUOUS and cleared once BI_STOP_CONTINUOUS has completed.
While it is set, an interrupt with COMMAND zero raises BIRIS_DATA_DEV (counted) *and* wakes
BIRIS_CMD (not counted: most of these wakes are not completions). Neither wake can mislead: the
data path catches up by ACQ_LINE, so a wake with nothing new reads nothing, and the command
notifier completes a command only if one is outstanding and COMMAND reads zero, which is exactly
the state after BIRIS has finished it. An interrupt with COMMAND non-zero is data, as before.

Coalescing (a count above 1) must not lose data. With COMMAND zero, a burst may hold data
interrupts as well as the completion, and the last of them is the one that announces the final
acquisition (ACQ_LINE -128). So BIRIS_DATA_DEV is raised too, before BIRIS_CMD, even when the
burst might have been an error plus the completion: the data path catches up by ACQ_LINE rather
than by counting, so a spare wake finds nothing new, while a missed one would lose the end of a
sequence. With COMMAND non-zero no completion can be hidden in the burst, because the driver
never writes the next command before it has serviced BIRIS_CMD.

A BusError while reading the coupler or COMMAND is itself a failed cycle across the coupler, so
it raises BIT3_BERR and the routine keeps running.

**The data notifier runs here.** Harmony's service routine could only signal a logical interrupt;
a thread can do the notifier's work itself. Waking a second thread for every acquisition costs a
thread wake-up and a handover of the interpreter lock, often from one CPU to another, and that
was the largest single share of the time from the interrupt to a client holding the data. So
:meth:`Level2Demux.attach_data_notifier` hands BIRIS_DATA_DEV to a callable that this thread runs
in place of raising the line: the server attaches ``biris_data_notifier`` there, which then *is*
this thread (it still only waits on an interrupt and sends to the administrator). It is counted
as before; with no notifier attached the line is raised as for every other logical interrupt.

**Level 3** (the Model 7600 board): IRQ_STATUS names the axes whose trapezoidal profile ended.
Each set bit is written back (write 1 to acknowledge) *before* its logical interrupt is raised,
so the acknowledgement can never clear the end of a move the woken notifier has already started:
azimuth raises MOTOR_END_OF_SCAN, elevation ELEVATION_END_OF_SCAN. An interrupt with no bit set
is spurious: counted, nothing raised.

The demultiplexers do not own the physical line (the hardware bundle does). If it is closed
under them they close their logical lines, so every notifier raises ``LineClosed``; so does any
unexpected failure, after logging it, so that no notifier waits forever on a dead routine.
"""

from __future__ import annotations

import enum
import logging
import os
import select
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable
from types import TracebackType
from typing import ClassVar, TypeVar

from biris_hw.bus.base import BusWindow
from biris_hw.errors import BusError, LineClosed
from biris_hw.irq.base import InterruptLine
from biris_hw.irq.eventfd import EventFdLine
from regs.biexec import OFF_COMMAND
from regs.bit3 import Bit3Reg, LocalStatus
from regs.tech80 import AxisBit, BoardReg

__all__ = ["LEVEL2_LOGICALS", "LEVEL3_LOGICALS", "Level2Demux", "Level3Demux", "Logical"]

log = logging.getLogger(__name__)

_D = TypeVar("_D", bound="_Demux")


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


class _Demux(ABC):
    """The thread, the logical lines, the counters and the lifecycle shared by both levels."""

    carries: ClassVar[tuple[Logical, ...]] = ()
    level: ClassVar[int] = 0

    def __init__(self, line: InterruptLine) -> None:
        self._line = line
        self._lines: dict[Logical, EventFdLine] = {}
        try:
            for logical in self.carries:
                self._lines[logical] = EventFdLine()
            self._stop_fd = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        except BaseException:
            self._close_logical()
            raise
        self._lifecycle = threading.Lock()
        self._stats = threading.Lock()
        self._counts = dict.fromkeys(self.carries, 0)
        self._spurious = 0
        self._thread: threading.Thread | None = None
        self._closed = False

    # -- what notifiers and status reports use ---------------------------------------------------
    def line(self, logical: Logical) -> InterruptLine:
        """The line a notifier blocks on for ``logical``; ValueError if this level lacks it."""
        try:
            return self._lines[logical]
        except KeyError:
            raise ValueError(f"level {self.level} does not carry {Logical(logical).name}") from None

    @property
    def counts(self) -> dict[Logical, int]:
        """Interrupts raised so far per logical kind (a copy)."""
        with self._stats:
            return dict(self._counts)

    @property
    def spurious(self) -> int:
        """Physical interrupts that turned out to have no source."""
        with self._stats:
            return self._spurious

    @property
    def running(self) -> bool:
        """True while the service thread is alive."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    @property
    def closed(self) -> bool:
        return self._closed

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> None:
        """Start servicing the physical line; RuntimeError if started before or closed."""
        with self._lifecycle:
            if self._closed:
                raise RuntimeError(f"level {self.level} demultiplexer is closed")
            if self._thread is not None:
                raise RuntimeError(f"level {self.level} demultiplexer is already running")
            self._thread = threading.Thread(
                target=self._run, name=f"biris-level{self.level}-isr", daemon=True
            )
            self._thread.start()

    def close(self) -> None:
        """Stop and join the thread, then close the logical lines (waking their notifiers).

        Leaves the physical line open: it belongs to the hardware bundle. Idempotent; a second
        caller returns once the first has finished.
        """
        with self._lifecycle:
            if self._closed:
                return
            self._closed = True
            os.eventfd_write(self._stop_fd, 1)
            thread = self._thread
            if thread is not None and thread is not threading.current_thread():
                thread.join()
            self._close_logical()
            if thread is None or thread is not threading.current_thread():
                os.close(self._stop_fd)  # nobody polls it any more

    def __enter__(self: _D) -> _D:
        """Start the thread (unless already started); the block ends with :meth:`close`."""
        if self._thread is None:
            self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- the service thread ----------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._serve()
        except Exception:
            log.exception("level %d demultiplexer failed; closing its logical lines", self.level)
            self._close_logical()

    def _serve(self) -> None:
        poller = select.poll()
        poller.register(self._stop_fd, select.POLLIN)
        try:
            line_fd = self._line.fileno()
        except LineClosed:
            self._physical_closed()
            return
        poller.register(line_fd, select.POLLIN | select.POLLERR)
        while True:
            ready = dict(poller.poll())
            if self._stop_fd in ready:  # checked first: shutdown wins over an interrupt flood
                return
            if line_fd not in ready:
                continue
            try:
                count = self._line.wait(0)
            except LineClosed:
                self._physical_closed()
                return
            if count:
                self._service(count)

    def _physical_closed(self) -> None:
        log.info("level %d line closed; closing its logical lines", self.level)
        self._close_logical()

    def _close_logical(self) -> None:
        for logical_line in self._lines.values():
            logical_line.close()

    def _raise(self, logical: Logical, count: int = 1, *, counted: bool = True) -> None:
        """Raise a logical interrupt and (unless ``counted`` is False) count it.

        Counted under the same lock as the trigger, so a notifier that has been woken always
        finds its interrupt in :attr:`counts`.
        """
        with self._stats:
            try:
                self._lines[logical].trigger(count)
            except LineClosed:
                log.debug("%s line closed by its user; interrupt dropped", logical.name)
                return
            if counted:
                self._counts[logical] += count

    def _count_spurious(self, count: int) -> None:
        with self._stats:
            self._spurious += count

    @abstractmethod
    def _service(self, count: int) -> None:
        """Decode ``count`` coalesced physical interrupts into logical ones."""


_PERR = int(LocalStatus.PARITY_ERROR)
_BERR = int(LocalStatus.REMOTE_BUS_ERROR)


class Level2Demux(_Demux):
    """Level 2: BIRIS_DATA_DEV, BIRIS_CMD, BIT3_PERR, BIT3_BERR (decision order: module doc).

    ``coupler`` is the Bit 3 register window, ``biris`` BIRIS memory, and ``biexec_offset``
    where BIEXEC_COM sits in it.
    """

    carries = LEVEL2_LOGICALS
    level = 2

    def __init__(
        self, line: InterruptLine, coupler: BusWindow, biris: BusWindow, biexec_offset: int
    ) -> None:
        super().__init__(line)
        self._coupler = coupler
        self._biris = biris
        self._command_offset = biexec_offset + OFF_COMMAND
        self._seen_errors = 0  # only the service thread touches it
        self._continuous = False
        self._data_notifier: Callable[[int], bool] | None = None

    def attach_data_notifier(self, notifier: Callable[[int], bool] | None) -> None:
        """Run ``notifier(count)`` in this thread for BIRIS_DATA_DEV instead of raising its line.

        ``notifier`` returns False once its task has ended (the administrator stopped); the line
        is raised again from then on. None detaches. A plain store: safe at any time.
        """
        self._data_notifier = notifier

    @property
    def continuous(self) -> bool:
        """Appendix D's continuous-mode flag (see the module notes)."""
        return self._continuous

    def set_continuous(self, on: bool) -> None:
        """Set or clear the flag; a plain store, so a notifier may call it at any time."""
        self._continuous = bool(on)

    def _service(self, count: int) -> None:
        error_raised = self._coupler_errors()
        if error_raised and count == 1:
            return  # the coupler's own interrupt
        try:
            command = self._biris.read16(self._command_offset)
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

        Counted before the notifier runs, as a raise is counted before its notifier wakes. A
        notifier's failure is logged and the routine goes on: the other logical interrupts of
        the level must not die with it.
        """
        notifier = self._data_notifier
        if notifier is None:
            self._raise(Logical.BIRIS_DATA_DEV, count)
            return
        with self._stats:
            self._counts[Logical.BIRIS_DATA_DEV] += count
        try:
            if not notifier(count):
                self._data_notifier = None
        except Exception:
            log.exception("level 2: the data notifier failed; it stays attached")

    def _coupler_errors(self) -> bool:
        """Raise the error interrupts newly shown in LOCAL_STATUS; True if any was raised."""
        try:
            status = self._coupler.read8(Bit3Reg.LOCAL_STATUS)
        except BusError as exc:
            log.error("level 2: coupler status unreadable (%s); raising BIT3_BERR", exc)
            self._raise(Logical.BIT3_BERR)
            return True
        errors = status & (_PERR | _BERR)
        new = errors & ~self._seen_errors
        self._seen_errors = errors  # a cleared bit is forgotten, so its next setting is new
        if new & _PERR:
            self._raise(Logical.BIT3_PERR)
        if new & _BERR:
            self._raise(Logical.BIT3_BERR)
        return bool(new)


_AXES = (
    (int(AxisBit.AZIMUTH), Logical.MOTOR_END_OF_SCAN),
    (int(AxisBit.ELEVATION), Logical.ELEVATION_END_OF_SCAN),
)


class Level3Demux(_Demux):
    """Level 3: the Model 7600's end-of-profile interrupts, one logical line per axis."""

    carries = LEVEL3_LOGICALS
    level = 3

    def __init__(self, line: InterruptLine, motion: BusWindow) -> None:
        super().__init__(line)
        self._motion = motion

    def _service(self, count: int) -> None:
        try:
            status = self._motion.read8(BoardReg.IRQ_STATUS)
            ended = [(bit, logical) for bit, logical in _AXES if status & bit]
            if not ended:
                self._count_spurious(count)
                return
            for bit, logical in ended:
                self._motion.write8(BoardReg.IRQ_STATUS, bit)
                self._raise(logical)
        except BusError as exc:
            # The board sits on the host's own bus: this is not a coupler fault, and the motor
            # notifier's stall detection will report the missing end of scan.
            log.error("level 3: Model 7600 IRQ_STATUS not serviced: %s", exc)
