"""The BIRIS memory map as seen through the coupler (report Fig. 3, docs/design.md).

BIEXEC_COM sits at ``biexec_offset``. Range and intensity frames alternate from the range base:
range(k) at ``base + 2 k frame_size``, intensity(k) at ``base + (2k+1) frame_size``. A frame is
big-endian i16: element 0 is the closest sample of acquisition k, elements 1..N the N samples
along the laser line, top to bottom. The azimuth table holds one big-endian i32 (encoder counts)
per acquisition. The driver learns the range base, the table and the frame size from BIRIS
(BI_GET_VME_ADDR_DIST, BI_GET_VME_ADDR_AZIM, BI_GET_VME_INC_FRAME); the defaults below are what
the simulator serves.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from regs.biexec import BIEXEC_COM_SIZE
from regs.bit3 import BIT3_SPACE
from regs.tech80 import MOTION_WINDOW_SIZE

__all__ = [
    "AZIMUTH_DTYPE",
    "DEFAULT_BIRIS_BASE",
    "FIELD_PERIOD_S",
    "FRAME_DTYPE",
    "FRAME_POISON",
    "SAMPLES_CHOICES",
    "STARTUP_LATENCY_S",
    "BirisMemoryMap",
    "FrameAddressing",
    "ImageRegion",
    "TargetImage",
    "acquisition_period_s",
    "fields_per_acquisition",
    "frame_size_for",
    "samples_for_frame_size",
]

FRAME_DTYPE = np.dtype(">i2")
AZIMUTH_DTYPE = np.dtype(">i4")

SAMPLES_CHOICES = (64, 128)
"""Samples per acquisition: 64 at 2 fields per acquisition, 128 at 3."""

DEFAULT_BIRIS_BASE = 0x00C0_0000
"""BIRIS-side VME address at which the coupler window starts (simulator default)."""

FRAME_POISON = 0x7A7A
"""What every element of a frame holds while it is being exposed (the simulator's ``POISON``);
a frame that still holds it everywhere was read too early."""


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
        # 16-bit fields and i16 frames need even offsets for one-access reads on the 68k bus.
        for name in ("biexec_offset", "range_offset"):
            value = getattr(self, name)
            if value < 0 or value % 2:
                raise ValueError(f"{name} must be a non-negative even offset, not {value:#x}")
        if self.biexec_offset + BIEXEC_COM_SIZE > self.range_offset:
            raise ValueError("BIEXEC_COM overlaps the frame area")


class ImageRegion(NamedTuple):
    """One register area inside a :class:`TargetImage`."""

    name: str
    offset: int
    size: int

    @property
    def end(self) -> int:
        return self.offset + self.size


@dataclass(frozen=True)
class TargetImage:
    """One flat image of the three areas the host reaches: coupler, motion board, BIRIS memory.

    A raw dump file holds this image and the simulator process exposes it in shared memory
    (mirroring the board and coupler registers there), so a dump tool reads every source the same
    way. Offsets are multiples of 4 so that every 16- and 32-bit quantity stays aligned.
    """

    coupler_offset: int = 0x0000
    motion_offset: int = 0x0100
    biris_offset: int = 0x1000
    biris: BirisMemoryMap = field(default_factory=BirisMemoryMap)

    @property
    def coupler(self) -> ImageRegion:
        return ImageRegion("coupler", self.coupler_offset, BIT3_SPACE)

    @property
    def motion(self) -> ImageRegion:
        return ImageRegion("motion", self.motion_offset, MOTION_WINDOW_SIZE)

    @property
    def biris_region(self) -> ImageRegion:
        return ImageRegion("biris", self.biris_offset, self.biris.size)

    def regions(self) -> tuple[ImageRegion, ImageRegion, ImageRegion]:
        """The three areas, in the order coupler, motion, BIRIS."""
        return self.coupler, self.motion, self.biris_region

    @property
    def size(self) -> int:
        """Bytes an image needs: up to the end of the last area."""
        return max(region.end for region in self.regions())

    def __post_init__(self) -> None:
        regions = self.regions()
        for region in regions:
            if region.offset < 0 or region.offset % 4:
                raise ValueError(
                    f"the {region.name} area must start at a non-negative multiple of 4, "
                    f"not {region.offset:#x}"
                )
        ordered = sorted(regions, key=lambda r: r.offset)
        for first, second in itertools.pairwise(ordered):
            if first.end > second.offset:
                raise ValueError(
                    f"the {first.name} area ({first.offset:#x}..{first.end - 1:#x}) overlaps "
                    f"the {second.name} area at {second.offset:#x}"
                )


FIELD_PERIOD_S = 1.0 / 59.94
"""One RS-170 video field; BIRIS synchronises commands and exposures to it."""

STARTUP_LATENCY_S = 0.240
"""Start-up delay of each acquisition sequence (the report's 240 ms)."""


def samples_for_frame_size(frame_size: int) -> int:
    """Samples per acquisition for a frame size BIRIS reported (BI_GET_VME_INC_FRAME)."""
    for samples in SAMPLES_CHOICES:
        if frame_size_for(samples) == frame_size:
            return samples
    return frame_size // 2 - 1


def acquisition_period_s(samples: int) -> float:
    """Seconds between acquisitions: 2 fields at 64 samples, 3 at 128."""
    return fields_per_acquisition(samples) * FIELD_PERIOD_S
