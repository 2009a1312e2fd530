"""The BIRIS memory map as seen through the coupler (report Fig. 3, DESIGN.md section 4).

BIEXEC_COM sits at ``biexec_offset``. Range and intensity frames alternate from the range base:
range(k) at ``base + 2 k frame_size``, intensity(k) at ``base + (2k+1) frame_size``. A frame is
big-endian i16: element 0 is the closest sample of acquisition k, elements 1..N the N samples
along the laser line, top to bottom. The azimuth table holds one big-endian i32 (encoder counts)
per acquisition. The driver learns the range base, the table and the frame size from BIRIS
(BI_GET_VME_ADDR_DIST, BI_GET_VME_ADDR_AZIM, BI_GET_VME_INC_FRAME); the defaults below are what
the simulator serves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from regs.biexec import BIEXEC_COM_SIZE

__all__ = [
    "AZIMUTH_DTYPE",
    "DEFAULT_BIRIS_BASE",
    "FRAME_DTYPE",
    "SAMPLES_CHOICES",
    "BirisMemoryMap",
    "FrameAddressing",
    "fields_per_acquisition",
    "frame_size_for",
]

FRAME_DTYPE = np.dtype(">i2")
AZIMUTH_DTYPE = np.dtype(">i4")

SAMPLES_CHOICES = (64, 128)
"""Samples per acquisition: 64 at 2 fields per acquisition, 128 at 3."""

DEFAULT_BIRIS_BASE = 0x00C0_0000
"""BIRIS-side VME address at which the coupler window starts (simulator default)."""


def fields_per_acquisition(samples: int) -> int:
    """Video fields per acquisition: 2 for 64 samples (30 Hz), 3 for 128 (20 Hz)."""
    if samples == 64:
        return 2
    if samples == 128:
        return 3
    raise ValueError(f"samples must be 64 or 128, not {samples}")


def frame_size_for(samples: int) -> int:
    """Bytes per frame: the closest sample plus ``samples`` samples, i16, padded to 4 bytes."""
    fields_per_acquisition(samples)
    raw = 2 * (samples + 1)
    return (raw + 3) & ~3


@dataclass(frozen=True)
class FrameAddressing:
    """Where acquisition k's frames and azimuth are, as window offsets."""

    range_offset: int
    frame_size: int
    azimuth_offset: int

    def range_frame(self, k: int) -> int:
        return self.range_offset + 2 * k * self.frame_size

    def intensity_frame(self, k: int) -> int:
        return self.range_offset + (2 * k + 1) * self.frame_size

    def azimuth_entry(self, k: int) -> int:
        return self.azimuth_offset + AZIMUTH_DTYPE.itemsize * k


@dataclass(frozen=True)
class BirisMemoryMap:
    """The whole BIRIS window: control block, frame area, azimuth table."""

    samples: int = 64
    biris_base: int = DEFAULT_BIRIS_BASE
    biexec_offset: int = 0x0100
    range_offset: int = 0x1000
    max_acquisitions: int = 1024

    @property
    def frame_size(self) -> int:
        return frame_size_for(self.samples)

    @property
    def azimuth_offset(self) -> int:
        end_of_frames = self.range_offset + 2 * self.max_acquisitions * frame_size_for(128)
        return (end_of_frames + 0xFFF) & ~0xFFF

    @property
    def size(self) -> int:
        end = self.azimuth_offset + AZIMUTH_DTYPE.itemsize * self.max_acquisitions
        return (end + 0xFFF) & ~0xFFF

    @property
    def addressing(self) -> FrameAddressing:
        return FrameAddressing(self.range_offset, self.frame_size, self.azimuth_offset)

    def address(self, offset: int) -> int:
        """BIRIS-side VME address of a window offset."""
        return self.biris_base + offset

    def __post_init__(self) -> None:
        frame_size_for(self.samples)
        if self.biexec_offset + BIEXEC_COM_SIZE > self.range_offset:
            raise ValueError("BIEXEC_COM overlaps the frame area")
