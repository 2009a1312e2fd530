"""Acquisition sequences: BI_ACQUIRE n, and Appendix D's continuous acquisition into a ring.

**BI_ACQUIRE n.** 240 ms start-up (the boot file's ``startup_ms``, rounded up to whole fields:
15 fields, 250 ms) with ACQ_LINE = -1; then acquisition k is exposed for 2 fields (64 samples)
or 3 (128 samples), back to back, on the field grid. At the start of k: range and intensity
frame k are filled with :data:`sim.POISON`, CURRENT_FRAME = ACQ_LINE = k, and the data
interrupt announces that k-1 is complete. At mid-exposure the head's azimuth (and elevation)
are sampled and the optics produce the frames; at the end of k they are written, with azimuth
table entry k (i32 counts, mid-exposure azimuth) if ``_Biris_motor_access`` is set at that
moment. After the last: ACQ_LINE = -128, one more data interrupt (announcing n-1), then the
command completes. Data interrupts need ``_Biris_data_int_enable``. A BI_ACQUIRE while
``_Biris_motor_access`` is clear is recorded as ``ACQUIRE_WITHOUT_MOTOR_ACCESS`` (when
``require_motor_access``); the acquisitions still run and untagged entries keep their old values.

**Continuous (Appendix D).** BI_START_CONTINUOUS completes as soon as it is accepted, answering
the ring's length in frames (decimal, as BI_ACQUIRE answers its count), so the host
can issue BI_STOP_CONTINUOUS (and queries, BI_LOAD_LUT) while acquisitions run; BI_ACQUIRE,
BI_BOOT or a second start are refused with BAD_PARAM meanwhile. After one start-up, acquisitions
run back to back into a ring of ``memory_map.max_acquisitions`` frames; ACQ_LINE and
CURRENT_FRAME give the ring index, each start raises a data interrupt. Because COMMAND is 0
during these interrupts, the driver needs its own continuous-mode flag to demultiplex them, as
the report foresees. BI_STOP_CONTINUOUS ceases at the field it is seen: the frame being exposed
is abandoned and *restored* to what it held before its exposure, so no ring slot is left
poisoned and every slot holds a complete acquisition (of this lap or the previous one) with
its matching azimuth entry; CURRENT_FRAME names the last slot this ring completed (-1 when it
completed none: stopped in its start-up or during its first exposure), ACQ_LINE = -128, no
further data interrupt. A stop while not continuous just completes.

**Audit.** At each acquisition start, ``tilting()`` true is ``ACQUIRE_WHILE_TILTING`` and a
table more than ``LUT_TOLERANCE_COUNTS`` away from the true tilt (``true_elevation_counts(t)``:
the encoder reading is no judge, a driver may reset the tilt's chip and zero it while BIRIS
still acquires with the table that matches where the head truly stands) is
``WRONG_CALIBRATION``; each is
recorded when it begins (once per episode within a sequence, not once per acquisition).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from regs.biexec import (
    ACQ_LINE_END,
    ACQ_LINE_STARTUP,
    OFF_ACQ_LINE,
    OFF_CURRENT_FRAME,
    OFF_CURRENT_PROJ,
    OFF_MOTOR_ACCESS,
    BiStatus,
)
from regs.hctl1000 import COUNTS_PER_REV
from regs.layout import AZIMUTH_DTYPE, FRAME_DTYPE
from sim.audit import Rule
from sim.clock import FIELD_PERIOD
from sim.supervisor.state import Frame, SupervisorState, parse_int

__all__ = ["Acquisition", "AcquisitionSequence"]

LUT_TOLERANCE_COUNTS = 3.0
"""How far (counts of tilt, 0.26 degrees) the loaded table may be from the true tilt before the
audit calls it WRONG_CALIBRATION: a homed tilt stands on its index only to within a count or two
(the encoder then reads 0 with the head that far from true level), which no table resolves."""


def _counts_to_rad(counts: float) -> float:
    return counts * 2.0 * math.pi / COUNTS_PER_REV


@dataclass
class AcquisitionSequence:
    """An acquisition sequence in progress (single or continuous); times are field numbers."""

    continuous: bool
    count: int
    """Acquisitions to make (single) or ring slots (continuous)."""
    first_field: int
    """Field at which acquisition 0 starts (end of start-up)."""
    fpa: int
    next_index: int = 0
    exposing: int | None = None
    slot: int = 0
    frames: tuple[bytes, bytes] | None = None
    mid_time: float = 0.0
    mid_azimuth: float = 0.0
    saved: bytes = b""
    tilting_noted: bool = False
    wrong_lut_noted: bool = False

    def start_field(self, k: int) -> int:
        return self.first_field + k * self.fpa


class Acquisition(SupervisorState):
    """BI_ACQUIRE, BI_START_CONTINUOUS, BI_STOP_CONTINUOUS, and the exposures they run."""

    # -- the commands ------------------------------------------------------------------------
    def _acquisition_refusal(self) -> tuple[BiStatus, str] | None:
        if self._boot is None:
            return BiStatus.NOT_BOOTED, "not booted"
        if self._continuous:
            return BiStatus.BAD_PARAM, "continuous acquisition running"
        return None

    def _check_motor_access(self) -> None:
        if self._require_motor_access and self._get(OFF_MOTOR_ACCESS) == 0:
            self._record(
                Rule.ACQUIRE_WITHOUT_MOTOR_ACCESS,
                "acquisitions will not be tagged with the azimuth",
                _Biris_motor_access=0,
            )

    def _cmd_acquire(self, field: int, t: float) -> None:
        refusal = self._acquisition_refusal()
        if refusal is not None:
            self._finish_later(t, *refusal)
            return
        text = self._param_text()
        count = parse_int(text, signed=False)
        if count is None or not 0 < count <= self._map.max_acquisitions:
            self._finish_later(t, BiStatus.BAD_PARAM, f"bad acquisition count {text!r}")
            return
        self._check_motor_access()
        self._begin_sequence(field, t, continuous=False, count=count)

    def _cmd_start_continuous(self, field: int, t: float) -> None:
        refusal = self._acquisition_refusal()
        if refusal is not None:
            self._finish_later(t, *refusal)
            return
        self._check_motor_access()
        self._begin_sequence(field, t, continuous=True, count=self._map.max_acquisitions)
        self._finish_later(t, BiStatus.OK, str(self._map.max_acquisitions))

    def _cmd_stop_continuous(self, done: float) -> None:
        seq = self._seq
        if self._continuous and seq is not None:
            if seq.exposing is not None:
                self._restore_slot(seq)
            # the last slot this ring completed, -1 when it completed none (the exposure
            # under way was its first): a slot left there by an earlier ring, or by the
            # abandoned frame's start, would name a frame this ring never made
            last = self._last_slot
            self._set(OFF_CURRENT_FRAME, last if last is not None else -1)
            self._set(OFF_ACQ_LINE, ACQ_LINE_END)
            self._seq = None
            self._continuous = False
        self._finish_later(done, BiStatus.OK, "")

    def _begin_sequence(self, field: int, t: float, *, continuous: bool, count: int) -> None:
        boot = self._boot
        startup_s = (boot.startup_ms if boot is not None else 240) / 1000.0
        startup_fields = math.ceil(startup_s / FIELD_PERIOD - 1e-9)
        self._seq = AcquisitionSequence(continuous, count, field + startup_fields, self._fpa)
        self._continuous = continuous
        self._last_slot = None
        self._sequence_starts.append(t)
        self._set(OFF_ACQ_LINE, ACQ_LINE_STARTUP)

    # -- at vertical sync --------------------------------------------------------------------
    def _exposure_ends(self, field: int) -> None:
        seq = self._seq
        if (
            seq is not None
            and seq.exposing is not None
            and field == seq.start_field(seq.exposing + 1)
        ):
            self._finish_exposure(seq)

    def _exposure_starts(self, field: int, t: float) -> None:
        seq = self._seq
        if seq is not None and seq.exposing is None and field == seq.start_field(seq.next_index):
            if not seq.continuous and seq.next_index == seq.count:
                self._end_sequence(seq, t)
            else:
                self._start_exposure(seq, t)

    # -- one exposure ------------------------------------------------------------------------
    def _start_exposure(self, seq: AcquisitionSequence, t: float) -> None:
        k = seq.next_index
        slot = k % seq.count if seq.continuous else k
        seq.exposing, seq.slot, seq.frames = k, slot, None
        seq.next_index += 1
        addr = self._map.addressing
        if seq.continuous:
            seq.saved = self._mem.read(addr.range_frame(slot), 2 * self._map.frame_size)
        self._mem.write(addr.range_frame(slot), self._poison)
        self._mem.write(addr.intensity_frame(slot), self._poison)
        self._set(OFF_CURRENT_FRAME, slot)
        self._set(OFF_CURRENT_PROJ, 0)
        self._set(OFF_ACQ_LINE, slot)
        self._audit_exposure(seq, t)
        self._data_interrupt()
        mid = (seq.start_field(k) + seq.fpa / 2.0) * FIELD_PERIOD
        self._fields.at(mid, lambda when: self._mid_exposure(seq, k, when))

    def _audit_exposure(self, seq: AcquisitionSequence, t: float) -> None:
        tilting = self._tilting is not None and self._tilting()
        if tilting and not seq.tilting_noted:
            self._record(Rule.ACQUIRE_WHILE_TILTING, "acquisition while the head tilts")
        seq.tilting_noted = tilting
        wrong = False
        if self._true_elevation is not None and self._lut is not None:
            elevation = self._true_elevation(t)
            wrong = abs(self._lut - elevation) > LUT_TOLERANCE_COUNTS
            if wrong and not seq.wrong_lut_noted:
                self._record(
                    Rule.WRONG_CALIBRATION,
                    "calibration table for another elevation",
                    LUT=self._lut,
                    ELEVATION=round(elevation),
                )
        seq.wrong_lut_noted = wrong

    def _mid_exposure(self, seq: AcquisitionSequence, k: int, t: float) -> None:
        """Sample the head and let the optics expose: what the frame will hold at its end."""
        if self._seq is not seq or seq.exposing != k:
            return  # abandoned by BI_STOP_CONTINUOUS
        azimuth = float(self._azimuth(t))
        tilt = float(self._elevation(t)) if self._elevation is not None else 0.0
        lut = _counts_to_rad(self._lut) if self._lut is not None else None
        rng_frame, int_frame = self._acquire(_counts_to_rad(azimuth), _counts_to_rad(tilt), lut)
        seq.frames = (self._checked(rng_frame, "range"), self._checked(int_frame, "intensity"))
        seq.mid_time = t
        seq.mid_azimuth = azimuth

    def _checked(self, frame: Frame, what: str) -> bytes:
        array = np.asarray(frame)
        if array.shape != (self._elements,):
            raise ValueError(
                f"acquire() returned a {what} frame of shape {array.shape}, "
                f"expected ({self._elements},)"
            )
        return array.astype(FRAME_DTYPE).tobytes()

    def _finish_exposure(self, seq: AcquisitionSequence) -> None:
        """Write acquisition ``seq.exposing``: frames, then its azimuth entry if allowed."""
        if seq.frames is None:  # pragma: no cover - the mid-exposure event always runs first
            raise RuntimeError("exposure ended before its middle")
        addr = self._map.addressing
        range_bytes, intensity_bytes = seq.frames
        self._mem.write(addr.range_frame(seq.slot), range_bytes)
        self._mem.write(addr.intensity_frame(seq.slot), intensity_bytes)
        if self._get(OFF_MOTOR_ACCESS):
            entry = np.array([round(seq.mid_azimuth)], dtype=AZIMUTH_DTYPE).tobytes()
            self._mem.write(addr.azimuth_entry(seq.slot), entry)
        self._acquisitions_made += 1
        self._acquisition_times.append(seq.mid_time)
        self._last_slot = seq.slot
        seq.exposing, seq.frames = None, None

    def _restore_slot(self, seq: AcquisitionSequence) -> None:
        """Put back what the abandoned slot held before its exposure began."""
        self._mem.write(self._map.addressing.range_frame(seq.slot), seq.saved)
        seq.exposing, seq.frames = None, None
        self._acquisitions_abandoned += 1

    def _end_sequence(self, seq: AcquisitionSequence, t: float) -> None:
        """After the last acquisition: -128, the interrupt announcing it, then completion."""
        self._set(OFF_ACQ_LINE, ACQ_LINE_END)
        self._data_interrupt()
        self._seq = None
        self._continuous = False
        self._finish_later(t, BiStatus.OK, str(seq.count))
