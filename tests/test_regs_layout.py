"""The BIRIS memory map and the target image pinned with explicit numbers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import sim
from regs.biexec import BIEXEC_COM_SIZE
from regs.bit3 import BIT3_SPACE
from regs.layout import (
    AZIMUTH_DTYPE,
    DEFAULT_BIRIS_BASE,
    FRAME_DTYPE,
    FRAME_POISON,
    SAMPLES_CHOICES,
    BirisMemoryMap,
    FrameAddressing,
    ImageRegion,
    TargetImage,
    fields_per_acquisition,
    frame_size_for,
)
from regs.tech80 import MOTION_WINDOW_SIZE

# -- frames ---------------------------------------------------------------------------------------


def test_frame_sizes() -> None:
    assert SAMPLES_CHOICES == (64, 128)
    assert frame_size_for(64) == 132  # (1 + 64) * 2 = 130, padded to 4
    assert frame_size_for(128) == 260  # (1 + 128) * 2 = 258, padded to 4
    assert fields_per_acquisition(64) == 2
    assert fields_per_acquisition(128) == 3


@pytest.mark.parametrize("samples", [0, 32, 63, 65, 96, 127, 256, -64])
def test_other_sample_counts_are_refused(samples: int) -> None:
    with pytest.raises(ValueError, match="64 or 128"):
        frame_size_for(samples)
    with pytest.raises(ValueError):
        fields_per_acquisition(samples)
    with pytest.raises(ValueError):
        BirisMemoryMap(samples=samples)


def test_dtypes_are_big_endian() -> None:
    assert FRAME_DTYPE.str == ">i2"
    assert AZIMUTH_DTYPE.str == ">i4"
    assert np.frombuffer(b"\x7a\x7a\xff\xfe", dtype=FRAME_DTYPE).tolist() == [0x7A7A, -2]


def test_poison_is_the_simulators() -> None:
    assert FRAME_POISON == 0x7A7A == sim.POISON


def test_frame_addressing_explicit() -> None:
    fa = FrameAddressing(range_offset=0x1000, frame_size=132, azimuth_offset=0x83000)
    assert fa.range_frame(0) == 0x1000
    assert fa.intensity_frame(0) == 0x1000 + 132
    assert fa.range_frame(1) == 0x1000 + 264
    assert fa.intensity_frame(1) == 0x1000 + 396
    assert fa.range_frame(4) == 0x1420
    assert fa.azimuth_entry(0) == 0x83000
    assert fa.azimuth_entry(5) == 0x83014


@given(
    base=st.integers(min_value=0, max_value=0x10000).map(lambda b: b * 2),
    samples=st.sampled_from(SAMPLES_CHOICES),
    k=st.integers(min_value=0, max_value=2047),
)
def test_range_and_intensity_alternate(base: int, samples: int, k: int) -> None:
    fs = frame_size_for(samples)
    fa = FrameAddressing(base, fs, 0)
    assert fa.range_frame(k) == base + 2 * k * fs
    assert fa.intensity_frame(k) == base + (2 * k + 1) * fs
    assert fa.intensity_frame(k) == fa.range_frame(k) + fs
    assert fa.range_frame(k + 1) == fa.intensity_frame(k) + fs


# -- the memory map -------------------------------------------------------------------------------


def test_default_map() -> None:
    mm = BirisMemoryMap()
    assert (mm.samples, mm.biris_base, mm.biexec_offset, mm.range_offset) == (
        64,
        0xC0_0000,
        0x0100,
        0x1000,
    )
    assert DEFAULT_BIRIS_BASE == 0xC0_0000
    assert mm.max_acquisitions == 1024
    assert mm.frame_size == 132
    assert mm.azimuth_offset == 0x83000  # 0x1000 + 2 * 1024 * 260, rounded to a page
    assert mm.size == 0x84000
    assert mm.addressing == FrameAddressing(0x1000, 132, 0x83000)
    assert mm.address(0x1000) == 0xC0_1000


@pytest.mark.parametrize("samples", SAMPLES_CHOICES)
@pytest.mark.parametrize("max_acq", [1, 100, 1024, 3000])
def test_map_covers_frames_and_azimuth_table(samples: int, max_acq: int) -> None:
    mm = BirisMemoryMap(samples=samples, max_acquisitions=max_acq)
    last = max_acq - 1
    end_of_frames = mm.addressing.intensity_frame(last) + mm.frame_size
    assert end_of_frames <= mm.azimuth_offset
    assert mm.addressing.azimuth_entry(last) + AZIMUTH_DTYPE.itemsize <= mm.size
    assert mm.biexec_offset + BIEXEC_COM_SIZE <= mm.range_offset
    assert mm.azimuth_offset % 0x1000 == 0 and mm.size % 0x1000 == 0


def test_map_size_does_not_depend_on_samples() -> None:
    # The simulator serves either rate from one map; the table sits past the larger frames.
    assert BirisMemoryMap(samples=64).size == BirisMemoryMap(samples=128).size


def test_map_refuses_bad_offsets() -> None:
    with pytest.raises(ValueError, match="overlaps"):
        BirisMemoryMap(biexec_offset=0x1000 - BIEXEC_COM_SIZE + 2)
    BirisMemoryMap(biexec_offset=0x1000 - BIEXEC_COM_SIZE)  # touching is fine
    with pytest.raises(ValueError, match="even"):
        BirisMemoryMap(biexec_offset=0x101)
    with pytest.raises(ValueError, match="even"):
        BirisMemoryMap(range_offset=0x1001)
    with pytest.raises(ValueError):
        BirisMemoryMap(biexec_offset=-2)


# -- the target image -----------------------------------------------------------------------------


def test_default_target_image() -> None:
    image = TargetImage()
    assert image.regions() == (
        ImageRegion("coupler", 0x0000, 0x20),
        ImageRegion("motion", 0x0100, 0x100),
        ImageRegion("biris", 0x1000, 0x84000),
    )
    assert (BIT3_SPACE, MOTION_WINDOW_SIZE) == (0x20, 0x100)
    assert image.biris == BirisMemoryMap()
    assert image.size == 0x85000
    assert image.biris_region.end == image.size


def test_target_image_follows_its_map() -> None:
    big = TargetImage(biris=BirisMemoryMap(max_acquisitions=2048))
    assert big.size == 0x1000 + big.biris.size
    assert big.size > TargetImage().size


def test_target_image_regions_can_move() -> None:
    image = TargetImage(coupler_offset=0x90000, motion_offset=0x0, biris_offset=0x1000)
    assert image.size == 0x90020
    assert image.coupler == ImageRegion("coupler", 0x90000, 0x20)


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"motion_offset": 0x10}, "overlaps"),
        ({"biris_offset": 0x180}, "overlaps"),
        ({"coupler_offset": 0x1F0}, "overlaps"),
        ({"biris_offset": 0x1002}, "multiple of 4"),
        ({"coupler_offset": -4}, "multiple of 4"),
    ],
)
def test_target_image_refuses_bad_layouts(kwargs: dict[str, int], words: str) -> None:
    with pytest.raises(ValueError, match=words):
        TargetImage(**kwargs)  # type: ignore[arg-type]


def test_target_image_is_frozen() -> None:
    image = TargetImage()
    with pytest.raises(AttributeError):
        image.biris_offset = 0  # type: ignore[misc]
