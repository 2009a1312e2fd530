"""The range array as BIRIS announces it: which frame is complete, and what it holds.

A dump reads frames as the driver would: the newest complete one is the one the last data
interrupt announced (ACQ_LINE - 1, or CURRENT_FRAME once ACQ_LINE is -128), never the one being
exposed, which holds POISON until its exposure ends.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from biris_hw.regdump.model import Json, Row, Section, hex_offset
from biris_hw.regdump.regions import Region
from regs.biexec import ACQ_LINE_END, BIEXEC_REGISTERS
from regs.layout import FRAME_DTYPE, FRAME_POISON, BirisMemoryMap

__all__ = ["FrameSummary", "frames_section", "last_complete_frame", "summarize_frame"]


def last_complete_frame(acq_line: int, current_frame: int) -> int | None:
    """The newest acquisition whose frame is complete, as the data interrupt announces it.

    The interrupt comes *during* acquisition k, so ACQ_LINE = k means k-1 is complete; -128 ends
    the sequence with CURRENT_FRAME complete; -1 (start-up) and 0 mean nothing is complete yet.
    """
    if acq_line >= 1:
        return acq_line - 1
    if acq_line == ACQ_LINE_END and current_frame >= 0:
        return current_frame
    return None


@dataclass(frozen=True)
class FrameSummary:
    """What a range frame holds: its closest sample and a digest of its samples."""

    closest_mm: int
    samples: int
    valid: int
    min_mm: int | None
    max_mm: int | None
    poisoned: bool

    def text(self) -> str:
        if self.poisoned:
            return f"0x{FRAME_POISON:04X} everywhere (being exposed, or never written)"
        spread = f", {self.min_mm}..{self.max_mm} mm" if self.min_mm is not None else ", none valid"
        return f"closest {self.closest_mm} mm; {self.valid}/{self.samples} valid{spread}"

    def as_json(self) -> dict[str, Json]:
        return {
            "closest_mm": self.closest_mm,
            "samples": self.samples,
            "valid": self.valid,
            "min_mm": self.min_mm,
            "max_mm": self.max_mm,
            "poisoned": self.poisoned,
        }


def summarize_frame(raw: bytes) -> FrameSummary:
    """Digest of a frame's bytes: element 0 is the closest sample, the rest the samples."""
    frame = np.frombuffer(raw, dtype=FRAME_DTYPE).astype(np.int32)
    samples = frame[1:]
    valid = samples[samples != 0]
    return FrameSummary(
        closest_mm=int(frame[0]),
        samples=int(samples.size),
        valid=int(valid.size),
        min_mm=int(valid.min()) if valid.size else None,
        max_mm=int(valid.max()) if valid.size else None,
        poisoned=bool(np.all(frame == FRAME_POISON)),
    )


def _frame_row(biris: Region, mm: BirisMemoryMap, frame_size: int, k: int, name: str) -> Row:
    """Acquisition k's range frame, summarised; range(k) is at base + 2 k frame_size."""
    offset = mm.range_offset + 2 * k * frame_size
    nbytes = FRAME_DTYPE.itemsize * (mm.samples + 1)
    where: dict[str, Json] = {"index": k, "offset": offset, "address": mm.address(offset)}
    if offset + nbytes > biris.size:
        return Row(name, f"range({k}) is outside the BIRIS window", offset=offset, value=where)
    summary = summarize_frame(biris.read(offset, nbytes))
    value = {**where, **summary.as_json()}
    return Row(name, f"range({k}): {summary.text()}", offset=offset, value=value)


def frames_section(
    biris: Region, mm: BirisMemoryMap, frame_size: int, acq_line: int, current_frame: int
) -> Section:
    k = last_complete_frame(acq_line, current_frame)
    if k is not None:
        why = "ACQ_LINE - 1" if acq_line >= 1 else "CURRENT_FRAME, sequence ended"
        last_text = f"{k} ({why})"
    elif acq_line == ACQ_LINE_END:
        last_text = "none (sequence ended, CURRENT_FRAME invalid)"
    else:
        last_text = "none (start-up)" if acq_line < 0 else "none (first acquisition running)"
    base = mm.range_offset
    rows = [
        Row(
            "range_base",
            f"BIRIS window {hex_offset(base)}, BIRIS address 0x{mm.address(base):08X}",
            offset=base,
            value={"offset": base, "address": mm.address(base)},
        ),
        Row(
            "frame_size",
            f"{frame_size} bytes ({mm.samples} samples + closest)",
            value=frame_size,
        ),
        Row("samples", str(mm.samples), value=mm.samples),
        Row("acq_line", BIEXEC_REGISTERS.by_name("ACQ_LINE").decode(acq_line), value=acq_line),
        Row("last_complete", last_text, value=k),
    ]
    if k is not None:
        rows.append(_frame_row(biris, mm, frame_size, k, "last_frame"))
    else:
        rows.append(Row("last_frame", "none", value=None))
    if acq_line >= 0:
        rows.append(_frame_row(biris, mm, frame_size, acq_line, "exposing"))
    else:
        rows.append(Row("exposing", "none", value=None))
    where = f"BIRIS memory, 0x{biris.size:X} bytes"
    return Section("frames", "Frames (range array)", where, biris.base, tuple(rows))
