"""The BIRIS supervisor's nonvolatile RAMdisk (``/dd``), which initialises BIRIS on BI_BOOT.

The report names one file on it, the boot file of Appendix B, ``/dd/users/biris/binitlal.par``,
without giving its content. We write a plausible OS-9 style parameter file: one ``key value``
per line, ``*`` starts a comment. It carries what the supervisor needs to come up: samples per
acquisition and fields per acquisition (which must agree with the memory map the supervisor was
built for), the start-up latency of a sequence, and the calibration (lookup) tables: one archive
file on the RAMdisk holding a table per elevation count in a range, and the elevation loaded at
boot. Lookup is by exact name (interpretation: we do not model OS-9's case folding).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass

from regs.layout import fields_per_acquisition

__all__ = [
    "BOOT_FILE",
    "CALIBRATION_FILE",
    "BootParameters",
    "RamDisk",
    "boot_file_text",
]

BOOT_FILE = "/dd/users/biris/binitlal.par"
"""Appendix B's boot file name."""

CALIBRATION_FILE = "/dd/users/biris/cal/elev.lut"
"""The calibration archive the standard boot file names."""

_REQUIRED = (
    "samples",
    "fields_per_acq",
    "startup_ms",
    "lut_file",
    "lut_elev_min",
    "lut_elev_max",
    "lut_default",
)


def boot_file_text(samples: int = 64) -> str:
    """The standard boot file for a camera delivering ``samples`` samples per acquisition."""
    fields = fields_per_acquisition(samples)
    rate_hz = 30 if fields == 2 else 20
    return (
        "* binitlal.par - BIRIS initialisation, read by the 68020 supervisor on BI_BOOT\n"
        "* one laser projector, azimuth scanning head, mobile robot set-up\n"
        "*\n"
        "camera          rs170           * 59.94 fields per second\n"
        "projectors      1\n"
        "laser_mw        19.5\n"
        f"samples         {samples:<15d} * range samples along the laser line\n"
        f"fields_per_acq  {fields:<15d} * {rate_hz} Hz acquisition rate\n"
        "startup_ms      240             * latency of each new acquisition sequence\n"
        "range_units     mm\n"
        "max_range_mm    3500\n"
        "*\n"
        "* calibration: one lookup table per elevation count, loaded by BI_LOAD_LUT\n"
        f"lut_file        {CALIBRATION_FILE}\n"
        "lut_elev_min    -1024           * -90 degrees\n"
        "lut_elev_max    1024            * +90 degrees\n"
        "lut_default     0               * loaded at boot: head level\n"
    )


def _calibration_text() -> str:
    return (
        "* elev.lut - BIRIS calibration archive (range and elevation lookup tables)\n"
        "format          lut-archive-1\n"
        "tables          2049\n"
        "first_elev      -1024\n"
    )


@dataclass(frozen=True)
class BootParameters:
    """What the supervisor takes from a boot file."""

    samples: int
    fields_per_acq: int
    startup_ms: int
    lut_file: str
    lut_elev_min: int
    lut_elev_max: int
    lut_default: int

    @classmethod
    def parse(cls, text: str) -> BootParameters:
        """Read a parameter file; ValueError when a key is missing or a value is malformed."""
        values: dict[str, str] = {}
        for number, line in enumerate(text.splitlines(), start=1):
            body = line.split("*", 1)[0].strip()
            if not body:
                continue
            parts = body.split(None, 1)
            if len(parts) != 2:
                raise ValueError(f"line {number}: {parts[0]!r} has no value")
            values[parts[0]] = parts[1].strip()
        missing = [key for key in _REQUIRED if key not in values]
        if missing:
            raise ValueError(f"boot file lacks {', '.join(missing)}")
        params = cls(
            samples=int(values["samples"]),
            fields_per_acq=int(values["fields_per_acq"]),
            startup_ms=int(values["startup_ms"]),
            lut_file=values["lut_file"],
            lut_elev_min=int(values["lut_elev_min"]),
            lut_elev_max=int(values["lut_elev_max"]),
            lut_default=int(values["lut_default"]),
        )
        if fields_per_acquisition(params.samples) != params.fields_per_acq:
            raise ValueError(
                f"{params.samples} samples need {fields_per_acquisition(params.samples)} "
                f"fields per acquisition, not {params.fields_per_acq}"
            )
        if params.startup_ms < 0:
            raise ValueError("startup_ms must not be negative")
        if not params.lut_elev_min <= params.lut_default <= params.lut_elev_max:
            raise ValueError("lut_default lies outside the calibrated elevations")
        return params

    def has_calibration(self, elevation_counts: int) -> bool:
        """Whether the archive holds a table for that elevation."""
        return self.lut_elev_min <= elevation_counts <= self.lut_elev_max


class RamDisk:
    """Named files, in memory; thread-safe so a fault panel can remove a file mid-run.

    With no ``files`` it holds the standard boot file (for ``samples``) and its calibration
    archive; pass ``files`` to build any other disk (an empty mapping is an empty disk).
    """

    def __init__(self, files: Mapping[str, bytes] | None = None, *, samples: int = 64) -> None:
        self._lock = threading.Lock()
        if files is None:
            files = {
                BOOT_FILE: boot_file_text(samples).encode("ascii"),
                CALIBRATION_FILE: _calibration_text().encode("ascii"),
            }
        self._files: dict[str, bytes] = dict(files)

    def __contains__(self, name: object) -> bool:
        with self._lock:
            return name in self._files

    def read(self, name: str) -> bytes:
        """The file's content; FileNotFoundError when the disk has no such file."""
        with self._lock:
            try:
                return self._files[name]
            except KeyError:
                raise FileNotFoundError(name) from None

    def write(self, name: str, data: bytes) -> None:
        """Create or replace a file."""
        with self._lock:
            self._files[name] = bytes(data)

    def remove(self, name: str) -> None:
        """Delete a file; FileNotFoundError when there is none."""
        with self._lock:
            try:
                del self._files[name]
            except KeyError:
                raise FileNotFoundError(name) from None

    def names(self) -> list[str]:
        """Every file name, sorted."""
        with self._lock:
            return sorted(self._files)
