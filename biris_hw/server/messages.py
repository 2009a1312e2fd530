"""Every message the BIRIS server's administrator receives, named after the report.

Internal tasks send the first group (NEW_POINT, CMD_TRANSFER_RDY, AZ_READY, AZ_SCAN_DONE,
BIRIS_CMD_COMPLETE and the three *_ERR reports; the tilt axis's EL_READY and EL_SCAN_DONE, which
the report foresees with its future tasks _el_scan_start and _el_scan_notifier; and the two
reports of Appendix D's continuous mode, CONTINUOUS_LIVE and SWEEP_DATA_DONE); clients send the
second, and live in :mod:`biris_hw.protocol` below client and server. Orders the administrator
*replies* to its workers are the third group here. All are immutable; arrays inside them are
read-only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from biris_hw.errors import FaultKind
from biris_hw.records import MotorParams
from regs.tech80 import Axis

if TYPE_CHECKING:
    from biris_hw.server.start_schedule import StartSchedule

# --- from internal tasks ---------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Acquisition:
    """One acquisition as read out of BIRIS memory by a notifier."""

    seq_id: int
    index: int
    azimuth: int
    closest_mm: int
    profile: NDArray[np.int16]
    intensity: NDArray[np.int16]
    t: float
    discarded: int
    """Samples beyond BIRIS_MAX_RANGE, set to 0."""
    t_origin: float = 0.0
    """The bound on the start of acquisition 0 that ``t`` was computed from. Bounds only tighten
    as a sequence goes on (a later wake may come sooner after its interrupt), so a finished scan
    re-times every acquisition from the tightest origin any of them saw: its times are then exactly
    periodic and increasing however late the first wakes were."""


@dataclass(frozen=True, slots=True)
class NewPoint:
    """NEW_POINT: acquisitions completed since the last report (more than one on catch-up)."""

    acquisitions: tuple[Acquisition, ...]
    lost: int = 0
    """Acquisitions known to be gone (overwritten before they could be read)."""
    idle: int = 0
    """Continuous acquisition: ring frames BIRIS completed while no sweep wanted them, which the
    reader skipped unread (Drained.idle); counted in idle_ring_frames."""
    untrusted: int = 0
    """Frames read but not trusted to be the acquisition they should hold (BIRIS was seen
    overwriting them while they were read): dropped, counted in untrusted_frames."""


@dataclass(frozen=True, slots=True)
class CmdTransferRdy:
    """CMD_TRANSFER_RDY: the command-transfer worker is free to carry the next command."""


@dataclass(frozen=True, slots=True)
class AzReady:
    """AZ_READY: the azimuth worker is free to start the next motion."""

    error: str | None = None
    """Why the previous order failed, if it did."""
    kind: str | None = None
    """The failure's fault kind (a :data:`biris_hw.errors.FaultKind`), if it failed."""


@dataclass(frozen=True, slots=True)
class AzScanDone:
    """AZ_SCAN_DONE: MOTOR_END_OF_SCAN arrived (the profile's last setpoint was issued), and
    the notifier has waited for the head to come to rest and read where it stands."""

    position: int | None = None
    """The encoder after settling (counts), None if it could not be read."""
    settled: bool = True
    """False if the head did not come to rest within the settling limit."""
    token: int | None = None
    """The MoveOrder.token of the move that ended (None: unknown, taken as the current one)."""


@dataclass(frozen=True, slots=True)
class ElReady:
    """EL_READY: the elevation worker (_el_scan_start) is free to start the next tilt."""

    error: str | None = None
    """Why the previous order failed, if it did."""
    kind: str | None = None
    """The failure's fault kind (a :data:`biris_hw.errors.FaultKind`), if it failed."""


@dataclass(frozen=True, slots=True)
class ElScanDone:
    """EL_SCAN_DONE: ELEVATION_END_OF_SCAN arrived and the tilt has come to rest."""

    position: int | None = None
    """The encoder after settling (counts), None if it could not be read."""
    settled: bool = True
    """False if the tilt did not come to rest within the settling limit."""
    token: int | None = None
    """The MoveOrder.token of the move that ended (None: unknown, taken as the current one)."""


@dataclass(frozen=True, slots=True)
class SequenceStarted:
    """SEQUENCE_STARTED: BI_ACQUIRE sequence ``seq_id`` has begun its first acquisition (its
    240 ms start-up is over). A report-mode scan's motor starts now, so that its acquisitions
    span the motion (:mod:`~biris_hw.server.scan_timing`)."""

    seq_id: int
    began: float
    """When acquisition 0 began, at the latest (hardware clock)."""


@dataclass(frozen=True, slots=True)
class ContinuousLive:
    """CONTINUOUS_LIVE: after BI_START_CONTINUOUS, the first acquisition has begun (the 240 ms
    start-up is over), so a sweep started now loses nothing."""


@dataclass(frozen=True, slots=True)
class SweepDataDone:
    """SWEEP_DATA_DONE: every acquisition of continuous-mode sweep ``seq_id`` has been sent.

    The continuous-mode counterpart of BIRIS_CMD_COMPLETE for a BI_ACQUIRE: with AZ_SCAN_DONE it
    completes a scan. It follows the last NEW_POINT of the sweep (the inbox is FIFO).
    """

    seq_id: int


@dataclass(frozen=True, slots=True)
class BirisCmdComplete:
    """BIRIS_CMD_COMPLETE: BIRIS cleared COMMAND; its STATUS and PARAM answer."""

    status: int
    param: bytes
    token: int
    """The TransferOrder.token of the command that completed."""


@dataclass(frozen=True, slots=True)
class BirisTimeoutErr:
    """BIRIS_TIMEOUT_ERR: the timer expired for arming number ``generation``."""

    generation: int


@dataclass(frozen=True, slots=True)
class MotorWatchdogErr:
    """The motor did not report the end of its scan in time (beyond the report)."""

    generation: int
    axis: Axis = Axis.AZIMUTH


@dataclass(frozen=True, slots=True)
class BirisRechecked:
    """The BIRIS timeout ran out and the level-2 routine, asked, has read BIRIS afresh
    (beyond the report): ``progressed`` when BIRIS had made acquisitions or completed its
    command since the host last looked (posted after the NEW_POINT that carries them), so the
    timeout measured a host that did not look, not a BIRIS that did not progress."""

    progressed: bool


@dataclass(frozen=True, slots=True)
class MotionRechecked:
    """A motor watchdog ran out and the level-3 routine, asked, has read the controller
    afresh: ``ended`` is the bitmask of axes whose profile it found ended (their notifiers are
    woken and verify the arrival as for any move); an axis not in it had not ended its move.
    ``started`` is, per axis, the (token, hardware time) its worker last started a move at
    (:class:`~biris_hw.server.tasks.MoveLedger`), so the move is judged from its start;
    ``noticed`` the token of the move whose end its notifier last woke for (an end the routine
    acknowledged before the watchdog asked: the notifier is verifying it)."""

    ended: int
    started: dict[Axis, tuple[int, float] | None]
    noticed: dict[Axis, int | None]


@dataclass(frozen=True, slots=True)
class BirisBusErr:
    """BIRIS_BUS_ERR from the coupler."""


@dataclass(frozen=True, slots=True)
class BirisParityErr:
    """BIRIS_PARITY_ERR from the coupler."""


@dataclass(frozen=True, slots=True)
class TaskFailed:
    """A task met what it cannot carry on from (beyond the report): a bus error reading the
    target -- the link is gone --, a hardware fault it raised (the level-3 routine's held drive
    fault), or an exception nobody expected. Posted one-way; the administrator turns it into a
    fault of ``kind`` that every caller is told about, and a reset restarts the task."""

    task: str
    kind: FaultKind
    """The fault's kind: a HardwareFault's own (``motor_stall`` for a CiA 402 drive's EMCY,
    ``bus`` for its lost heartbeat...), ``bus`` for any other BusError, ``internal`` for
    anything else (see :meth:`~biris_hw.server.tasks.Supervisor.failed`)."""
    text: str
    generation: int = 0
    """The supervisor's reset count when the task failed (:attr:`Supervisor.resets`): a report
    read after a reset has restarted the task, or while the reset under way will restart it, is
    of a task that runs again, not a fault of the new initialisation (the administrator's
    ``_on_task_failed``)."""


@dataclass(frozen=True, slots=True)
class EncoderReading:
    """ENCODER_READING (beyond the report): the encoder reader is ready, with the pan and tilt
    encoders as its last order read them (None for an axis it could not read, the board gone
    or the drive silent). Its first report, before any order, carries ``read=False``. The reply
    is its next order (:class:`ReadEncoders`)."""

    azimuth: int | None = None
    elevation: int | None = None
    read: bool = True


@dataclass(frozen=True, slots=True)
class InitSync:
    """From the initialiser, before it looks at COMMAND: replied once the command-transfer
    worker is parked. A command the administrator handed the worker just before a reset may
    not be written yet; BIRIS must be seen busy with it, not idle a moment before it arrives."""


@dataclass(frozen=True, slots=True)
class InitCommand:
    """The initialiser asks for a BIRIS command; replied with (status, PARAM) on completion."""

    code: int
    param: str


@dataclass(frozen=True, slots=True)
class InitMove:
    """The initialiser asks for a trapezoid; replied when AZ_SCAN_DONE (EL_SCAN_DONE) arrives."""

    destination: int
    axis: Axis = Axis.AZIMUTH
    start: int | None = None
    """Where the axis's count stands as the move begins (the chip's command position). Only the
    initialiser knows it: its chip resets and re-zeroings move the count under the
    administrator, whose last destination is then no longer where the head is. None: where the
    administrator's last move on the axis ended."""


@dataclass(frozen=True, slots=True)
class InitDone:
    """The initialiser finished: ``error`` is None on success."""

    error: BaseException | None
    addressing: object | None = None


# --- orders the administrator replies to its workers -------------------------------------------


@dataclass(frozen=True, slots=True)
class TransferOrder:
    """To biris_cmd_transfer: write this command (and, for BI_ACQUIRE, expect ``n`` frames)."""

    code: int
    param: str
    seq_id: int
    n_acquisitions: int
    token: int
    """Names this command; its BIRIS_CMD_COMPLETE carries it back."""
    schedule: StartSchedule | None = None
    """BI_ACQUIRE of a report-mode scan: told when COMMAND was written, so that the scan's
    trapezoid starts at a hardware time fixed by the write
    (:mod:`~biris_hw.server.start_schedule`)."""


@dataclass(frozen=True, slots=True)
class MoveOrder:
    """To az_scan_start (el_scan_start): drive to ``destination`` with the trapezoid.

    ``sweep`` (continuous acquisition only) is the scan whose data interrupts the worker turns
    back on once the motor is moving: Appendix D's "re-enabled after the next scan is started".
    ``follows``: that sweep turns straight round from the one just ended (continuous scanning),
    so its data carry on from that sweep's last frame rather than from the frame in exposure.
    """

    destination: int
    sweep: int = 0
    follows: bool = False
    token: int = 0
    """Names this move (the administrator numbers every move it dispatches); the axis notifier
    reports it back in AZ_SCAN_DONE / EL_SCAN_DONE, so the end of a move abandoned by a reset is
    never taken for the end of the next one."""
    schedule: StartSchedule | None = None
    """A report-mode scan's move: started when the schedule says (BI_ACQUIRE's write plus the
    start-up), not at once; nothing starts if the schedule is cancelled meanwhile."""


@dataclass(frozen=True, slots=True)
class ReadEncoders:
    """To encoder_reader: read both axes' encoders now and report them."""


@dataclass(frozen=True, slots=True)
class ParamsOrder:
    """To az_scan_start: load new motor parameters while the motor stands still."""

    params: MotorParams
