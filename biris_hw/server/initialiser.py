"""Initialisation of the server's hardware (report: "Initialization of the BIRIS Server").

Runs as a worker of its own so the administrator never waits on it: configures both HCTL-1000s
with the init record's motor parameters, finds the zero index of each drive by polling the
board's index latch ("the zero index of each drive is found by polling") and stands at 0 on
both, boots BIRIS with the record's boot file, asks BIRIS where its range array, azimuth table
and frame size are, and loads the calibration table for elevation 0.

The tilt axis is homed like the pan axis but within its own reach: a tilt head cannot turn a
revolution looking for its index, so the search stays within the widest of the record's
elevation limits either side of where the head woke up (the head is assumed to power up within
its limits, as a tilt head resting on its stops does). Its index marks the level head.

A BI_STOP_CONTINUOUS goes first, before anything moves: a server that stopped (or faulted)
during Appendix D's continuous mode leaves BIRIS acquiring, homing the tilt under a running
acquisition is exactly what must not happen, and BIRIS refuses to boot meanwhile; when BIRIS is
not acquiring the stop simply completes. Moves and BIRIS commands go through the
administrator (InitMove, InitCommand) so that they use the same workers and notifiers as scans.
Every step is bounded: no index within the configured revolutions, a command BIRIS never
completes, or a move that never ends is a HardwareFault, never a hang.

The registers are reached through the hardware bundle's one set of drivers
(``BirisHardware.devices``), the same objects the server's tasks use.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

from biris_hw.errors import BirisError, HardwareFault
from biris_hw.hardware import BirisHardware
from biris_hw.ipc import Mailbox
from biris_hw.records import BirisInitRecord
from biris_hw.server.cmd_transfer import status_name
from biris_hw.server.messages import InitCommand, InitMove
from regs.biexec import BiCommand, BiStatus, decode_param
from regs.hctl1000 import COUNTS_PER_REV
from regs.layout import FrameAddressing, acquisition_period_s, samples_for_frame_size
from regs.tech80 import DEFAULT_IRQ_VECTOR, Axis

__all__ = ["InitResult", "Initialiser", "run_initialiser"]

log = logging.getLogger(__name__)

LEVEL2_VECTOR = 0x42
"""The vector we program for every level-2 (BIRIS) interrupt."""

HOMING_CHUNK = 256
"""Counts per coarse homing move: small enough to stop soon after the index, large enough to
cover a revolution in a few moves."""

TILT_HOMING_CHUNK = 64
"""The tilt's first coarse move (5.6 degrees): a tilt head wakes near level, so its index is
near, and every count searched costs a bisection step."""


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
        stop: threading.Event,
    ) -> None:
        self.hw = hw
        self.record = record
        self.admin = admin
        self.stop = stop
        self.devices = hw.devices
        self.board = hw.devices.board
        self.azimuth = hw.devices.azimuth
        self.elevation = hw.devices.elevation
        self.coupler = hw.devices.coupler
        self.link = hw.devices.link
        self._position = {Axis.AZIMUTH: 0, Axis.ELEVATION: 0}

    # -- steps ---------------------------------------------------------------------------------
    def run(self) -> InitResult:
        self.coupler.clear_errors()
        self.coupler.enable_interrupts(LEVEL2_VECTOR)
        self.stop_acquisition()
        self.configure_axes()
        self.find_zero_index()
        self.find_zero_index(Axis.ELEVATION)
        return self.boot_biris()

    def stop_acquisition(self) -> None:
        """Quiet BIRIS before anything moves: interrupts as the server wants them, and
        BI_STOP_CONTINUOUS, since a tilt must never happen under a running acquisition."""
        self.link.set_flags(cmd_int=True, data_int=False, motor_access=True)
        self._command(BiCommand.BI_STOP_CONTINUOUS)

    def configure_axes(self) -> None:
        """Reset both chips, load the motor parameters, hold each axis where it stands, and
        enable both end-of-scan interrupts (MOTOR_END_OF_SCAN, ELEVATION_END_OF_SCAN)."""
        self.board.disable_all()
        for axis, params in (
            (self.azimuth, self.record.motor),
            (self.elevation, self.record.tilt_motor),
        ):
            self.board.reset_chip(axis.axis)
            axis.configure(params)
            axis.wait_still(self.stop)  # after a reset the motor coasts
            axis.hold_here()
            self.board.acknowledge(axis.axis)
            self._position[axis.axis] = axis.command_position()
        self.board.enable_end_of_scan(Axis.AZIMUTH, DEFAULT_IRQ_VECTOR)
        self.board.enable_end_of_scan(Axis.ELEVATION, DEFAULT_IRQ_VECTOR)

    def _move(self, destination: int, axis: Axis = Axis.AZIMUTH) -> None:
        if destination == self._position[axis]:
            return
        self._send(InitMove(destination, axis))
        self._position[axis] = destination

    def _send(self, message: object) -> object:
        timeout = (self.record.timeout_s * 4.0) / self.hw.time_scale + 5.0
        try:
            return self.admin.send(message, timeout=timeout)
        except TimeoutError as exc:
            raise HardwareFault("timeout", f"initialisation step {message} timed out") from exc

    def find_zero_index(self, axis: Axis = Axis.AZIMUTH) -> None:
        """Find the index nearest the power-up position, then stand on it as encoder count 0.

        Coarse: sweep alternately counter-clockwise and clockwise, each sweep reaching further
        (256, 512, 1024 ... counts either side, up to half the configured revolutions), clearing
        the board's index latch before each; the first sweep that sets it found the index in the
        territory that sweep added. Searching outwards keeps the head within half a revolution
        of where it woke up, so the cable is never wound further than it has to be. Fine: bisect
        that territory, crossing the index again for each half, to one count.

        The tilt searches the same way from 64 counts, within the widest elevation limit.
        """
        board = self.board
        start = self._position[axis]
        if axis is Axis.AZIMUTH:
            half = max(1, round(self.record.home_index_timeout_revs * COUNTS_PER_REV / 2))
            chunk, driver, what = HOMING_CHUNK, self.azimuth, "revolution(s)"
        else:
            half = max(1, *(abs(v) for v in self.record.elevation_limits_counts))
            chunk, driver, what = TILT_HOMING_CHUNK, self.elevation, "counts of tilt"
        reach, targets = min(chunk, half), []
        while True:
            targets += [start + reach, start - reach]
            if reach >= half:
                break
            reach = min(reach * 2, half)
        covered_lo = covered_hi = start
        bracket: tuple[int, int] | None = None
        for target in targets:
            board.clear_index(axis)
            self._move(target, axis)
            if board.index_seen(axis):
                if target > covered_hi:
                    bracket = (covered_hi - 2, target)
                else:
                    bracket = (target, covered_lo + 2)
                break
            covered_lo, covered_hi = min(covered_lo, target), max(covered_hi, target)
        if bracket is None:
            reach_text = (
                f"{self.record.home_index_timeout_revs:g}" if axis is Axis.AZIMUTH else f"{half}"
            )
            raise HardwareFault(
                "motor_stall",
                f"{driver.axis.name.lower()}: no zero index within {reach_text} {what}",
            )
        low, high = bracket
        while high - low > 1:
            mid = (low + high) // 2
            self._move(low, axis)  # going back may cross the index: clear the latch afterwards
            board.clear_index(axis)
            self._move(mid, axis)
            if board.index_seen(axis):
                high = mid
            else:
                low = mid
        self._move(high, axis)
        driver.idle()
        driver.wait_still(self.stop)
        driver.hold_here(zero_counter=True)
        self._position[axis] = 0
        board.clear_index(axis)
        log.info("%s zero index found at encoder count %d", axis.name.lower(), high)

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
