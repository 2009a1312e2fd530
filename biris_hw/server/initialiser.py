"""Initialisation of the server's hardware (report: "Initialization of the BIRIS Server").

Runs as a worker of its own so the administrator never waits on it: configures both HCTL-1000s
with the init record's motor parameters, finds the zero index of each drive by polling the
board's index latch ("the zero index of each drive is found by polling") and stands at 0 on
both, boots BIRIS with the record's boot file, asks BIRIS where its range array, azimuth table
and frame size are, and loads the calibration table for elevation 0.

**Which index.** The pan's index fires once per revolution, so the one nearest the head is true
zero's only if the head is within half a revolution of true zero. The hardware bundle's
:class:`~biris_hw.pan_reference.PanReference` says what is known (issue 11, defect 1): before
the pan chip is reset its counter is read with the head standing still, and the reference turns
that into an interval of possible offsets to true zero -- exact after an in-process reset or a
restart with a consistent journal, +-180 degrees around the head at a fresh start (the
operator's precondition), the last recorded move's span when the chip lost its count. The
index is then looked for only where the head stays within +-0x1000 of true zero whichever
offset is the true one, and where an index found can only be true zero's
(:func:`~biris_hw.pan_reference.index_search_range`): a narrow window around true zero when
the reference is exact, never more than half a revolution either side of where the head woke
when it is not. An index missing from that window means the position is lost: a
HardwareFault("motor_stall") telling the operator what to check, and the reference is dropped.

The tilt axis is homed like the pan axis but within its own reach: a tilt head cannot turn a
revolution looking for its index, so the search stays within the widest of the record's
elevation limits either side of where the head woke up (the head is assumed to power up within
its limits, as a tilt head resting on its stops does). Its index marks the level head.

**The motors stop first, then a busy BIRIS is awaited.** The chips are reset before anything
else (the head coasts to rest where it is; nothing runs on while BIRIS is awaited). A driver
that died (or a reset that abandoned a scan) may leave BIRIS executing a command, typically a
long BI_ACQUIRE; a command written meanwhile is lost (CMD_WHILE_BUSY, defect 8). The
initialiser first asks the administrator (InitSync) to answer once the command-transfer worker
is parked -- a command handed to it just before the reset is then written, and seen -- and
before its first command it polls COMMAND until
BIRIS clears it, bounded by what can be running: for BI_ACQUIRE the count its PARAM still holds
times the longest acquisition period, plus the start-up and the record's BIRIS timeout;
otherwise the timeout alone. Then a BI_STOP_CONTINUOUS goes first, before anything moves: a
server that stopped (or faulted) during Appendix D's continuous mode leaves BIRIS acquiring,
homing the tilt under a running acquisition is exactly what must not happen, and BIRIS refuses
to boot meanwhile; when BIRIS is not acquiring the stop simply completes. Moves and BIRIS
commands go through the administrator (InitMove, InitCommand) so that they use the same workers
and notifiers as scans. Every step is bounded: no index where it may be, a command BIRIS never
completes, or a move that never ends is a HardwareFault, never a hang.

**Boards checked, not assumed.** What the driver assumes a board did is read back
(:mod:`biris_hw.devices`): the counter after a chip reset (the pan reference is told what it
reads, not what it should read) and after every clear on the index, the index latch after it is
cleared (where it shows again at once, once more a few counts off: a head at rest on the index's
edge dithers across it). Homing finds the index in one of two ways, by what the board's
INDEX_STATUS shows (:class:`~biris_hw.devices.IndexKind`, the target file's ``[homing] index``):

- a *latch* (the default, our reading of the Model 7600): coarse moves at full speed, each
  looked at afterwards, then a bisection crossing the index again for each half;
- a *live level*, true only while the encoder is on the index (a pulse of ``index_width``
  counts): a slow sweep that polls it. New ground is swept in :data:`SWEEP_CHUNK`-count moves at
  the chip's gentlest acceleration (a triangle peaking near a third of a count per sample, about
  250 counts a second at Appendix B's sample timer) while the level and the counter are read
  together every :func:`level_poll_s`; ground already searched is crossed at full speed. Every
  count passed must have been read at a poll (two polls more than ``index_width`` counts apart
  leave a gap, and the chunk is swept again, at most :data:`GAP_RETRIES` times). Once seen, the
  pulse is crossed again slowly, upward, and its first count taken from the polls (not at rest:
  a head stepped one count at a time stops where friction lets it, a count either side). A
  level board homed as a latch almost never sees its index (the head rarely stops on the
  pulse): "pan position lost" says to check the key.

**Lost links first.** Before anything is touched, the hardware bundle re-links whatever link to
the target was lost and can come back (:meth:`BirisHardware.relink <biris_hw.hardware.
BirisHardware.relink>`: a VM-USB found again by its serial number, a restarted ``biris sim``
reconnected, a CiA 402 drive whose heartbeat came back set up again), keeping the objects the
server holds; a link still missing fails the reset at once with a ``bus`` fault that says what to
restore. Then the Bit 3 coupler's link to the BIRIS crate is checked, as Bit 3's own drivers do
(:meth:`~biris_hw.devices.Coupler.check_link`): NO_CONNECT (the crate's power off, the cable
out) fails the reset with a ``bus`` fault at once, before anything crosses the coupler, and the
sticky errors are cleared. Only then are the server's failed tasks run again (``restart_tasks``,
the supervisor's reset): an interrupt routine restarted on a line still lost would fail again at
once, and fail this initialisation with it. When the re-link or the check fails they stay down
until a reset whose re-link and check succeed: run again, they would only fail again, and a
routine whose failure the supervisor records after the next reset has begun would sit out that
reset too (it waits for the one after).

The registers are reached through the hardware bundle's one set of drivers
(``BirisHardware.devices``), the same objects the server's tasks use, and only through the axis
interface (:class:`~biris_hw.axes.base.MotionAxis`, :class:`~biris_hw.axes.base.
MotionController`): the same homing runs on the Model 7600's HCTL-1000s and on CiA 402 drives
over CAN (index latch = the drive's touch probe on the zero impulse; chip reset = fault reset,
disable and homing on the current position).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol, cast

from biris_hw.angles import counts_to_deg
from biris_hw.axes.base import MotionAxis
from biris_hw.devices import LEVEL2_VECTOR, IndexKind, MotionBoard
from biris_hw.errors import BirisError, HardwareFault
from biris_hw.hardware import BirisHardware
from biris_hw.ipc import Mailbox, Ticket
from biris_hw.pan_reference import NARROW_WINDOW, index_search_range
from biris_hw.records import BirisInitRecord, MotorParams
from biris_hw.server.cmd_transfer import command_name, status_name
from biris_hw.server.messages import InitCommand, InitMove, InitSync
from biris_hw.timebase import StopEvent
from regs.biexec import BiCommand, BiStatus, decode_param
from regs.hctl1000 import COUNTS_PER_REV, MOTION_LIMIT_COUNTS
from regs.layout import (
    FIELD_PERIOD_S,
    SAMPLES_CHOICES,
    STARTUP_LATENCY_S,
    FrameAddressing,
    acquisition_period_s,
    samples_for_frame_size,
)
from regs.tech80 import DEFAULT_IRQ_VECTOR, Axis

__all__ = [
    "GAP_RETRIES",
    "SWEEP_ACCEL",
    "SWEEP_CHUNK",
    "InitResult",
    "Initialiser",
    "level_poll_s",
    "run_initialiser",
]

log = logging.getLogger(__name__)
progress = logging.getLogger("biris_hw.progress")
"""What initialisation is doing, one short sentence per step, for a person waiting for it (the
``biris`` commands print these while the server starts): INFO records."""

HOMING_CHUNK = 256
"""Counts per coarse homing move: small enough to stop soon after the index, large enough to
cover a revolution in a few moves."""

TILT_HOMING_CHUNK = 64
"""The tilt's first coarse move (5.6 degrees): a tilt head wakes near level, so its index is
near, and every count searched costs a bisection step."""

LONGEST_ACQUISITION_S = max(acquisition_period_s(samples) for samples in SAMPLES_CHOICES)
"""One acquisition at the slowest rate BIRIS runs (3 fields, 128 samples): before BI_BOOT's
answers the driver cannot know which rate the previous driver booted."""

UNREADABLE_ACQUIRE_COUNT = 1024
"""Acquisitions assumed when a running BI_ACQUIRE's PARAM is no longer readable: the most BIRIS
memory holds (``BirisMemoryMap.max_acquisitions``)."""

BUSY_POLL_S = FIELD_PERIOD_S
"""How often COMMAND is read while waiting for BIRIS: it completes commands at vertical sync."""

REBASE_ATTEMPTS = 3
"""Re-zeroings of the pan counter allowed to bring the search window within the chip's own
+-0x1000 (one is always enough for a head within a revolution of true zero)."""

RECLEAR_STEP_COUNTS = 4
"""How far the latch search steps off before it clears and reads back a latch that showed
again at once where the head stood (:meth:`_LatchSearch._clear`): a head at rest dithers a
count either way, so one standing on the index's edge crosses it as the latch is read (the
referenced pan's search starts on true zero's index itself). Four counts off, no dither reaches
the index, and a latch that still shows is the board's."""

SWEEP_CHUNK = 32
"""Counts per move of a slow sweep for a live index level (module notes): short, so the
acceleration alone keeps it slow (a triangle), and so a host that missed polls repeats little."""

SWEEP_ACCEL = 1
"""R26H/R27H during a slow sweep: 1/256 count per sample squared, the chip's gentlest. A
:data:`SWEEP_CHUNK` move then peaks at sqrt(32/256) = 0.35 count per sample."""

SWEEP_POLLS_PER_COUNT = 2.5
"""Polls of the index level per count at a slow sweep's peak speed: margin for the head running
ahead of its profile, so that consecutive polls read counts at most one apart."""

GAP_RETRIES = 3
"""Times one chunk of a slow sweep is swept again because polls came too far apart (a busy
host), before homing gives up."""


def level_poll_s(params: MotorParams, width: int = 1) -> float:
    """Hardware seconds between two polls of a live index level during a slow sweep: the
    sweep's peak speed (:data:`SWEEP_CHUNK`, :data:`SWEEP_ACCEL`, at ``params``' sample timer)
    crosses ``width`` counts in :data:`SWEEP_POLLS_PER_COUNT` polls."""
    peak_counts_per_sample = math.sqrt(SWEEP_CHUNK * SWEEP_ACCEL / 256.0)
    peak = peak_counts_per_sample / params.sample_period_s
    return width / (SWEEP_POLLS_PER_COUNT * peak)


@dataclass(frozen=True)
class InitResult:
    addressing: FrameAddressing
    samples: int
    period_s: float


class Initialiser:
    """One run of the initialisation sequence; ``run()`` returns an InitResult or raises."""

    def __init__(
        self,
        hw: BirisHardware,
        record: BirisInitRecord,
        admin: Mailbox,
        stop: StopEvent,
        restart_tasks: Callable[[], None] | None = None,
    ) -> None:
        self.hw = hw
        self.restart_tasks = restart_tasks
        """The supervisor's reset (every failed task run again), called once the links are
        back (:meth:`relink`); None when the server restarted them before this initialiser."""
        self.record = record
        self.admin = admin
        self.stop = stop
        self.devices = hw.devices
        self.board = hw.devices.board
        self.azimuth = hw.devices.azimuth
        self.elevation = hw.devices.elevation
        self.coupler = hw.devices.coupler
        self.link = hw.devices.link
        self.reference = hw.pan_reference
        self._position = {Axis.AZIMUTH: 0, Axis.ELEVATION: 0}
        self._tilt_level = 0
        """Where level is on the tilt's count after the chip reset (:meth:`_locate_tilt`)."""
        board = self.board
        self._search: _IndexSearch = (
            _LevelSearch(self, board, board.index_width)
            if isinstance(board, MotionBoard) and board.index_kind is IndexKind.LEVEL
            else _LatchSearch(self, model7600=isinstance(board, MotionBoard))
        )
        """How the board's index is searched (module notes)."""

    # -- steps ---------------------------------------------------------------------------------
    def run(self) -> InitResult:
        self.relink()  # the coupler's link checked, its errors cleared
        self.coupler.enable_interrupts(LEVEL2_VECTOR)
        progress.info("stopping the motors")
        self.configure_axes()  # stops the motors first: nothing runs on while BIRIS is awaited
        self.stop_acquisition()
        progress.info("homing the pan (its zero index)")
        self.find_zero_index()
        progress.info("homing the tilt (its zero index: level)")
        self.find_zero_index(Axis.ELEVATION)
        progress.info("booting BIRIS (BI_BOOT %s)", self.record.boot_file)
        return self.boot_biris()

    def relink(self) -> None:
        """Re-link what was lost, check the coupler's link to the BIRIS crate (see the module
        notes), then run the failed tasks again.

        Raises:
            HardwareFault: ``bus``, naming what is still missing or that the BIRIS crate is not
                connected; the failed tasks then stay down (see the module notes).
        """
        self.hw.relink()
        self.coupler.check_link()
        if self.restart_tasks is not None:
            self.restart_tasks()

    def stop_acquisition(self) -> None:
        """Quiet BIRIS before anything moves: interrupts as the server wants them, wait for a
        command still running, and BI_STOP_CONTINUOUS, since a tilt must never happen under a
        running acquisition."""
        self.link.set_flags(cmd_int=True, data_int=False, motor_access=True)
        self._send(InitSync())  # a command handed over before the reset is written by now
        self.wait_biris_idle()
        progress.info("stopping BIRIS's acquisition (BI_STOP_CONTINUOUS)")
        self._command(BiCommand.BI_STOP_CONTINUOUS)

    def wait_biris_idle(self) -> None:
        """Poll COMMAND until BIRIS has cleared it, on the hardware clock, bounded by what runs.

        A BI_ACQUIRE of n acquisitions takes BIRIS's start-up plus n acquisition periods; the
        record's BIRIS timeout comes on top (it is how long any command may take), and is the
        whole bound for any other command. The poll waits on the server's stop event, so a
        closing server is never held up; expiry is HardwareFault("timeout"), since a BIRIS that
        never clears COMMAND is hung and a command written now would be lost.
        """
        code = self.link.command()
        if code == 0:
            return
        name = command_name(code)
        limit = self.record.timeout_s
        if code == BiCommand.BI_ACQUIRE:
            count = self._running_acquisitions()
            limit += STARTUP_LATENCY_S + count * LONGEST_ACQUISITION_S
            name = f"{name} of {count} acquisitions"
        clock, timebase = self.hw.clock, self.hw.timebase
        started = clock()
        deadline = started + limit
        progress.info("waiting up to %.1f s for BIRIS to finish %s", limit, name)
        while True:
            if timebase.wait_event(self.stop, BUSY_POLL_S, what="BIRIS to finish"):
                return  # the server is closing: the next step finds the administrator gone
            code = self.link.command()
            if code == 0:
                log.info("BIRIS finished %s after %.2f s", name, clock() - started)
                return
            if clock() >= deadline:
                raise HardwareFault(
                    "timeout",
                    f"BIRIS still busy with {name} after {limit:.1f} s (COMMAND {code}): it "
                    f"does not answer; check BIRIS, then reset",
                )

    def _running_acquisitions(self) -> int:
        """The count a running BI_ACQUIRE was given: PARAM still holds the old driver's text
        until BIRIS answers in it. Unreadable, the most BIRIS memory could hold."""
        try:
            count = int(decode_param(self.link.param_raw()).strip())
        except ValueError:
            return UNREADABLE_ACQUIRE_COUNT
        return max(0, min(count, UNREADABLE_ACQUIRE_COUNT))

    def configure_axes(self) -> None:
        """Reset both chips, load the motor parameters, hold each axis where it stands, and
        enable both end-of-scan interrupts (MOTOR_END_OF_SCAN, ELEVATION_END_OF_SCAN).

        The pan is first stopped (init/idle: a scan may have been running) and, once it stands
        still, its counter and parameters are read and handed to the pan reference
        (:meth:`~biris_hw.pan_reference.PanReference.locate`): the reset is about to zero the
        counter where the head stands, and that reading is what ties the new count to true
        zero. A position already lost (see ``locate``) is a fault before anything moves.
        """
        self.board.disable_all()
        counter = self._locate_pan()
        self._tilt_level = self._locate_tilt()
        for which, axis, params in (
            (Axis.AZIMUTH, self.azimuth, self.record.motor),
            (Axis.ELEVATION, self.elevation, self.record.tilt_motor),
        ):
            self.board.reset_chip(which)  # the Model 7600's is read back there, and refused
            after = axis.actual_position()  # what the count restarted at, read, not assumed
            if which is Axis.AZIMUTH:
                # after the reset (a crash between them reads as a chip reset, see pan_reference)
                self.reference.chip_reset(counter, after)
            else:
                self._tilt_level += after
            axis.configure(params)
            axis.wait_still(self.stop)  # after a reset the motor coasts
            axis.hold_here()
            self.board.acknowledge(which)
            self._position[which] = axis.command_position()
        self.board.enable_end_of_scan(Axis.AZIMUTH, DEFAULT_IRQ_VECTOR)
        self.board.enable_end_of_scan(Axis.ELEVATION, DEFAULT_IRQ_VECTOR)

    def _locate_pan(self) -> int:
        """Stop the pan, let it come to rest, and ask the reference what its counter means;
        returns the counter (where the head stands). Raises the "position lost" fault."""
        pan = self.azimuth
        pan.idle()
        pan.wait_still(self.stop)
        counter = pan.actual_position()
        where = self.reference.locate(counter, pan.read_params())
        if where.lost:
            self.reference.lose(where.reason)
            raise _position_lost(f"{where.reason}. Nothing was moved")
        log.info(
            "pan: %s (%s); offset to true zero %s counts", where.how, where.reason, where.offset
        )
        return counter

    def _tilt_reach(self) -> int:
        """How far the tilt may be from level: the widest of the record's elevation limits."""
        return max(1, *(abs(v) for v in self.record.elevation_limits_counts))

    def _locate_tilt(self) -> int:
        """Stop the tilt and read its counter before the chip reset zeroes it where the head
        stands; returns where level will be on the new count.

        A tilt homed before (by this server, or a driver before it on a chip that kept power)
        counts from level, so level is at minus that reading after the reset -- and the search
        is centred there, not on wherever the head stood (at +45 degrees, a search centred on
        the head would put level on the edge of its reach). A fresh chip reads 0: the head is
        then taken to be level, the assumption a tilt head resting within its limits allows.
        The reading is bounded by the limits, so a garbage count can never send it further.
        """
        tilt = self.elevation
        tilt.idle()
        tilt.wait_still(self.stop)
        reach = self._tilt_reach()
        return -max(-reach, min(reach, tilt.actual_position()))

    def _move(self, destination: int, axis: Axis = Axis.AZIMUTH) -> None:
        if destination == self._position[axis]:
            return
        self._finish_move(self._post_move(destination, axis), destination, axis)

    def _post_move(self, destination: int, axis: Axis) -> Ticket:
        """Hand the move to the administrator without waiting (a slow sweep polls meanwhile);
        :meth:`_finish_move` waits for it."""
        # where the chip's count stands: the administrator cannot know it after a chip reset or
        # a re-zeroing, and its watchdog bounds the move by the distance really driven
        return self.admin.post(InitMove(destination, axis, start=self._position[axis]))

    def _finish_move(self, ticket: Ticket, destination: int, axis: Axis) -> None:
        self._wait(ticket)
        self._position[axis] = destination

    def _send(self, message: object) -> object:
        return self._wait(self.admin.post(message))

    def _wait(self, ticket: Ticket) -> object:
        timeout = (self.record.timeout_s * 4.0) / self.hw.time_scale + 5.0
        try:
            return ticket.wait(timeout)
        except TimeoutError as exc:
            raise HardwareFault(
                "timeout", f"initialisation step {ticket.message} timed out"
            ) from exc

    def find_zero_index(self, axis: Axis = Axis.AZIMUTH) -> None:
        """Find the axis's zero index and stand on it as encoder count 0.

        The pan looks only where the reference allows (:meth:`_home_pan`); the tilt searches
        outward from where it woke, within the widest elevation limit. Either way: coarse
        sweeps alternately each way, reaching further each time, clearing the board's index
        latch before each, until one sets it; then a bisection of the territory that sweep
        added, crossing the index again for each half, to one count.
        """
        if axis is Axis.AZIMUTH:
            self._home_pan()
            return
        start = self._tilt_level
        half = self._tilt_reach()
        self._move(start, axis)
        low, high = start - half, start + half
        bracket = self._sweep(axis, low, high, start, TILT_HOMING_CHUNK)
        if bracket is None:
            raise HardwareFault(
                "motor_stall",
                f"{axis.name.lower()}: no zero index within {half} counts of tilt"
                f"{self._search.hint}",
            )
        self._stand_on_index(axis, self.elevation, bracket, low, high)

    def _home_pan(self) -> None:
        """Home the pan on TRUE zero's index, never further than the reference allows.

        The window is :func:`~biris_hw.pan_reference.index_search_range` of the reference's
        interval: +-:data:`NARROW_WINDOW` around true zero when the counter is referenced (the
        head first goes to true zero, then sweeps to either edge), +-180 degrees around where
        the head woke at a fresh start (also never beyond half the record's
        ``home_index_timeout_revs`` either side), the span of the last recorded move when the
        chip lost its count. The chip's own counter may not reach that window (its +-0x1000 are
        counted from where the reset found the head, a revolution round perhaps): the head then
        goes to where the search starts, and the counter is re-zeroed there (the reference
        shifts with it).
        """
        referenced = self.reference.referenced
        for _ in range(REBASE_ATTEMPTS):
            low, high = self._pan_window(referenced)
            if low > high:
                raise self._pan_lost(referenced, "no safe search window")
            start = self._pan_start(referenced, low, high)
            if low >= -MOTION_LIMIT_COUNTS and high <= MOTION_LIMIT_COUNTS:
                break
            self._move(max(-MOTION_LIMIT_COUNTS, min(MOTION_LIMIT_COUNTS, start)))
            self._rezero_pan()
        else:
            raise self._pan_lost(referenced, "the counter cannot reach the search window")
        self._move(start)
        bracket = self._sweep(Axis.AZIMUTH, low, high, start, HOMING_CHUNK)
        if bracket is None:
            span = f"{counts_to_deg(high - low):.0f} deg searched, encoder counts {low}..{high}"
            raise self._pan_lost(referenced, f"no zero index ({span}{self._search.hint})")
        self.reference.homed(self._stand_on_index(Axis.AZIMUTH, self.azimuth, bracket, low, high))

    def _pan_start(self, referenced: bool, low: int, high: int) -> int:
        """Where the pan search starts: on true zero itself when the counter is referenced (the
        window is centred there, and the sweeps reach its edges), else the window's point
        nearest the head, from which the search goes outward."""
        if referenced:
            offset = self.reference.offset
            assert offset is not None
            return min(max(-offset[0], low), high)
        return min(max(self._position[Axis.AZIMUTH], low), high)

    def _pan_window(self, referenced: bool) -> tuple[int, int]:
        """Counters (now) where the pan may look for true zero's index; empty if low > high."""
        offset = self.reference.offset
        if offset is None:  # dropped meanwhile (a journal that could not be written)
            return (1, 0)
        low, high = index_search_range(offset, NARROW_WINDOW)
        if not referenced:
            half = max(1, round(self.record.home_index_timeout_revs * COUNTS_PER_REV / 2))
            centre = min(max(self._position[Axis.AZIMUTH], low), high)
            low, high = max(low, centre - half), min(high, centre + half)
        return (low, high)

    def _pan_lost(self, referenced: bool, what: str) -> HardwareFault:
        """Drop the reference and build the fault that says what happened; the head stays
        where the search left it, inside the window (safe whichever offset was the true one)."""
        offset = self.reference.offset or (0, 0)
        if referenced:
            text = (
                f"{what} within {counts_to_deg(NARROW_WINDOW):.1f} deg of where true zero must "
                f"be (encoder count {-offset[0]}): the head has moved without the driver "
                f"(turned by hand while the driver was down, a slipping coupling) or the "
                f"encoder lost counts"
            )
        else:
            text = (
                f"{what} where true zero may be (or the index sensor, the amplifier or the "
                f"motor does not work)"
            )
        self.reference.lose(text)
        return _position_lost(text)

    def _rezero_pan(self) -> None:
        """Re-zero the pan counter where the head stands (after a move): the reference keeps
        its relation to true zero, since the counter is read first."""
        pan = self.azimuth
        pan.idle()
        pan.wait_still(self.stop)
        counter = pan.actual_position()
        pan.hold_here(zero_counter=True)  # read back there: cleared, or refused
        after = pan.actual_position()
        self.reference.rezeroed(counter, after)
        self._position[Axis.AZIMUTH] = after

    def _sweep(
        self, axis: Axis, low: int, high: int, start: int, chunk: int
    ) -> tuple[int, int] | None:
        """Coarse search within [low, high] outward from ``start`` (where the head stands):
        the bracket the index is in, by the board's kind of index (module notes), or None."""
        return self._search.sweep(axis, low, high, start, chunk)

    def _stand_on_index(
        self, axis: Axis, driver: MotionAxis, bracket: tuple[int, int], low: int, high: int
    ) -> int:
        """Find the index's count within ``bracket`` (never beyond [low, high]), stand there and
        make it the origin; returns the counter read back there (0, or within a count)."""
        at = self._search.locate(axis, bracket, low, high)
        self._move(at, axis)
        driver.idle()
        driver.wait_still(self.stop)
        driver.hold_here(zero_counter=True)  # read back there: cleared, or refused
        here = driver.actual_position()
        self._position[axis] = here
        if self._search.latched:
            self.board.clear_index(axis)
        log.info("%s zero index found at encoder count %d", axis.name.lower(), at)
        return here

    def _command(self, code: BiCommand, param: str = "") -> str:
        reply = self._send(InitCommand(int(code), param))
        assert isinstance(reply, tuple)
        status, raw = reply
        if status != BiStatus.OK:
            name = status_name(status)
            raise HardwareFault("protocol", f"{code.name} failed: STATUS {status} ({name})")
        try:
            return decode_param(raw)
        except ValueError as exc:
            raise HardwareFault("protocol", f"{code.name}: malformed PARAM answer {raw!r}") from exc

    def boot_biris(self) -> InitResult:
        self._command(BiCommand.BI_BOOT, self.record.boot_file)
        self._command(BiCommand.BI_LOAD_LUT, "0")  # the table for the level head
        range_addr = _parse_int(self._command(BiCommand.BI_GET_VME_ADDR_DIST), 16, "range base")
        azim_addr = _parse_int(self._command(BiCommand.BI_GET_VME_ADDR_AZIM), 16, "azimuth table")
        frame_size = _parse_int(self._command(BiCommand.BI_GET_VME_INC_FRAME), 10, "frame size")
        try:
            range_off = self.hw.to_offset(range_addr)
            azim_off = self.hw.to_offset(azim_addr)
        except ValueError as exc:
            raise HardwareFault("protocol", str(exc)) from exc
        if frame_size <= 2 or frame_size % 2 or frame_size > 0x10000:
            raise HardwareFault("protocol", f"impossible frame size {frame_size}")
        samples = samples_for_frame_size(frame_size)
        try:
            period = acquisition_period_s(samples)
        except ValueError as exc:
            raise HardwareFault("protocol", f"frame size {frame_size}: {exc}") from exc
        self.link.set_flags(data_int=True)
        return InitResult(FrameAddressing(range_off, frame_size, azim_off), samples, period)


class _IndexSearch(Protocol):
    """One way of finding an axis's zero index (module notes)."""

    latched: bool
    """The board latches the index (it must be cleared once homed)."""
    hint: str
    """Said with "no zero index": what to check about this way of looking."""

    def sweep(
        self, axis: Axis, low: int, high: int, start: int, chunk: int
    ) -> tuple[int, int] | None:
        """The (low, high) counts the index was seen between, or None within [low, high]."""
        ...

    def locate(self, axis: Axis, bracket: tuple[int, int], low: int, high: int) -> int:
        """The count the index is at (crossed from below), found within ``bracket``."""
        ...


class _LatchSearch:
    """The index is latched (the Model 7600's INDEX_STATUS, a CiA 402 drive's touch probe):
    coarse moves looked at afterwards, then a bisection. ``model7600``: the latch is our reading
    of that board, which a "no zero index" then says may be wrong."""

    latched = True

    def __init__(self, init: Initialiser, *, model7600: bool) -> None:
        self._init = init
        self._model7600 = model7600
        self.hint = (
            '; or the board\'s index is a live level, not a latch: [homing] index = "level" '
            "in the target file"
            if model7600
            else ""
        )

    def _clear(self, axis: Axis, inward: int, low: int, high: int) -> None:
        """Clear the latch before a look; on the Model 7600 read it back too. A latch that does
        not clear (or an index that is a live level) would stop the search at its first look,
        at an index that is not there, so it is a ``protocol`` fault -- but only where no dither
        can set it again: a latch that shows again at once is cleared and read again
        :data:`RECLEAR_STEP_COUNTS` counts off (``inward``, kept within [low, high]), and only
        a latch that still shows there is the board's. The head stays where it stepped."""
        board = self._init.board
        board.clear_index(axis)
        if not self._model7600 or not board.index_seen(axis):
            return
        init = self._init
        here = init._position[axis]
        off = min(max(here + inward, low), high)
        log.info(
            "%s: the index latch showed again where the head stood (count %d), as a head "
            "dithering on the index's edge sets it; read again at count %d",
            axis.name.lower(),
            here,
            off,
        )
        init._move(off, axis)
        cast("MotionBoard", board).clear_index(axis, check=True)

    def sweep(
        self, axis: Axis, low: int, high: int, start: int, chunk: int
    ) -> tuple[int, int] | None:
        """Sweeps alternately each way, reaching further each time, clearing the latch before
        each, until one sets it: the (low, high) bracket of the sweep that did."""
        init, board = self._init, self._init.board
        covered_lo = covered_hi = start
        reach = chunk
        while covered_lo > low or covered_hi < high:
            for target in (min(start + reach, high), max(start - reach, low)):
                if covered_lo <= target <= covered_hi:
                    continue  # that side is searched to its end already
                here = init._position[axis]
                # off the index's edge, a step toward ground searched (or the window's inside)
                inward = (
                    -RECLEAR_STEP_COUNTS
                    if here > start or (here == start and here - RECLEAR_STEP_COUNTS >= low)
                    else RECLEAR_STEP_COUNTS
                )
                self._clear(axis, inward, low, high)
                if covered_lo == covered_hi:  # nothing searched yet: it starts where it stands
                    covered_lo = covered_hi = init._position[axis]
                init._move(target, axis)
                if board.index_seen(axis):
                    # 2 counts of margin at both ends: the head may have stopped on the index
                    # (it overshot it and came back), and the bisection must start below it
                    if target > covered_hi:
                        return (max(covered_hi - 2, low), min(target + 2, high))
                    return (max(target - 2, low), min(covered_lo + 2, high))
                covered_lo, covered_hi = min(covered_lo, target), max(covered_hi, target)
            reach *= 2
        return None

    def locate(self, axis: Axis, bracket: tuple[int, int], low: int, high: int) -> int:
        """Bisect the bracket to one count, always crossing from below."""
        init, board = self._init, self._init.board
        lo, hi = bracket
        checked = False
        while hi - lo > 1:
            mid = (lo + hi) // 2
            init._move(lo, axis)  # going back may cross the index: clear the latch afterwards
            if not checked:  # the bracket's end, clear of the index: a latch must clear there
                self._clear(axis, -RECLEAR_STEP_COUNTS, low, high)
                checked = True
            else:  # near the index a head at rest dithers a count: the latch may set again
                board.clear_index(axis)
            init._move(mid, axis)
            if board.index_seen(axis):
                hi = mid
            else:
                lo = mid
        return hi


class _LevelSearch:
    """INDEX_STATUS is the index's live level: a slow sweep that polls it, then a second slow
    crossing, upward, to place the index's first count (module notes)."""

    latched = False
    hint = (
        "; the board's index is taken to be a live level polled during a slow sweep "
        '([homing] index = "level"): check the index input and index_width'
    )

    def __init__(self, init: Initialiser, board: MotionBoard, width: int) -> None:
        self._init = init
        self._board = board
        self._width = width

    def sweep(
        self, axis: Axis, low: int, high: int, start: int, chunk: int
    ) -> tuple[int, int] | None:
        """Outward from ``start`` as the latch search goes, but each new stretch swept slowly
        while the level is polled; stretches already searched are crossed at full speed. The
        bracket is the counts read at the polls either side of the first sight."""
        init = self._init
        if self._board.index_seen(axis):  # standing on it
            return (start, start)
        covered_lo = covered_hi = start
        reach = chunk
        while covered_lo > low or covered_hi < high:
            for target in (min(start + reach, high), max(start - reach, low)):
                if covered_lo <= target <= covered_hi:
                    continue
                edge = covered_hi if target > covered_hi else covered_lo
                init._move(edge, axis)
                seen = self._slow(axis, edge, target, first_only=True)
                if seen:
                    return (min(seen), max(seen))
                covered_lo, covered_hi = min(covered_lo, target), max(covered_hi, target)
            reach *= 2
        return None

    def locate(self, axis: Axis, bracket: tuple[int, int], low: int, high: int) -> int:
        """Cross the bracket again slowly, upward, from ``index_width`` + 2 counts below it, and
        take the first count of the pulse: the first count read with the level set, unless the
        last one read with it, less the width, is higher (a count read at a poll may lag the
        head by a sample of the chip's, the direction it moves)."""
        init, width = self._init, self._width
        below = max(low, bracket[0] - width - 2)
        above = min(high, bracket[1] + width + 2)
        init._move(below, axis)
        seen = self._slow(axis, below, above, first_only=False)
        if not seen:
            raise HardwareFault(
                "motor_stall",
                f"{axis.name.lower()}: the index level seen between counts {bracket[0]} and "
                f"{bracket[1]} did not show again crossing {below}..{above} (a noisy index "
                f"input?); the axis is not homed",
            )
        return max(seen[0], seen[-1] - width + 1)

    def _slow(self, axis: Axis, start: int, target: int, *, first_only: bool) -> list[int]:
        """Sweep from ``start`` (where the head stands) to ``target`` slowly, polling: the
        counts read with the level set, in order (with ``first_only``, the count read at the
        poll before the first sight too, then the sweep ends with that chunk)."""
        init = self._init
        driver = init.azimuth if axis is Axis.AZIMUTH else init.elevation
        params = init.record.motor if axis is Axis.AZIMUTH else init.record.tilt_motor
        driver.configure(replace(params, max_vel=1, max_accel=SWEEP_ACCEL))
        seen: list[int] = []
        try:
            here = start
            step = SWEEP_CHUNK if target > start else -SWEEP_CHUNK
            while here != target:
                nxt = min(here + step, target) if step > 0 else max(here + step, target)
                seen += self._chunk(axis, here, nxt, level_poll_s(params, self._width), first_only)
                if seen and first_only:
                    break
                here = nxt
            return seen
        finally:
            driver.configure(params)

    def _chunk(
        self, axis: Axis, start: int, target: int, poll: float, first_only: bool
    ) -> list[int]:
        """One slow move from ``start`` to ``target`` with the level polled every ``poll``
        hardware seconds; swept again when the polls left a gap (module notes)."""
        init = self._init
        for attempt in range(GAP_RETRIES + 1):
            if attempt:
                init._move(start, axis)  # back, at the slow speed: a short move
            ticket = init._post_move(target, axis)
            last: int | None = None
            gap: tuple[int, int] | None = None
            seen: list[int] = []
            while True:
                finished = ticket.done
                level, counter = self._board.index_and_position(axis)
                if level:
                    if not seen and first_only and last is not None:
                        seen.append(last)
                    seen.append(counter)
                elif last is not None and abs(counter - last) > self._width and gap is None:
                    gap = (last, counter)
                last = counter
                if finished:
                    break
                init.hw.timebase.sleep(poll, what="the index level's next poll")
            init._finish_move(ticket, target, axis)
            if seen or gap is None:
                return seen
            log.warning(
                "%s: the index level was not polled between counts %d and %d (the host was "
                "late); sweeping %d..%d again",
                axis.name.lower(),
                gap[0],
                gap[1],
                start,
                target,
            )
        raise HardwareFault(
            "timeout",
            f"{axis.name.lower()}: the index level could not be polled often enough to see a "
            f"{self._width}-count pulse between counts {start} and {target} "
            f"({GAP_RETRIES + 1} sweeps, every one with a gap): the host is too busy; reset to "
            f"try again",
        )


def _position_lost(detail: str) -> HardwareFault:
    """The "position lost" fault: what happened, and what the operator must do about it."""
    return HardwareFault(
        "motor_stall",
        f"pan position lost: {detail}. The head's revolution is no longer known, so it is not "
        f"homed. Check the head and its cable; turn it by hand to within +-180 deg of dead "
        f"ahead, unwinding the cable, then reset: homing then searches afresh around it",
    )


def _parse_int(text: str, base: int, what: str) -> int:
    try:
        clean = text.strip()
        if base == 16 and not clean.lower().startswith("0x"):
            raise ValueError("no 0x prefix")
        return int(clean, base)
    except ValueError as exc:
        raise HardwareFault("protocol", f"BIRIS answered {text!r} for the {what}") from exc


def run_initialiser(
    init: Initialiser, report: Callable[[InitResult | BaseException], None]
) -> None:
    """Thread body: run, then hand the outcome to ``report`` (which sends InitDone)."""
    try:
        result: InitResult | BaseException = init.run()
    except BirisError as exc:
        result = exc
    except Exception as exc:  # a bug or an OS error must still end initialisation, visibly
        log.exception("initialisation failed")
        result = exc
    report(result)
