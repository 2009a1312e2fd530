"""``biris regdump``: the registers of a target, decoded for people and for scripts.

A dump reads one :class:`~regs.layout.TargetImage` (coupler, Model 7600 board, BIRIS memory)
through a bus window and decodes it with the register descriptions in :mod:`regs`, so there is
no second table to drift. Reads follow the hardware's rules even though a dump file has none:
HCTL-1000 composites are read in their ``read_order`` (R14H first, since on a live chip that read
latches R13H/R12H), write-only registers and registers whose read has an effect are not read, and
nothing is ever written.

The library half (:func:`snapshot`, :func:`changed_rows`, :func:`format_table`, :func:`to_json`)
works on any window; the CLI half (:func:`add_arguments`, :func:`run`) is what ``biris regdump``
calls.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import sys
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol, TextIO

import numpy as np

from biris_hw.bus import BusWindow, open_window
from biris_hw.errors import BirisError, BusError
from biris_hw.hardware import BirisHardware
from regs.biexec import (
    ACQ_LINE_END,
    BIEXEC_PARAM_SIZE,
    BIEXEC_REGISTERS,
    OFF_PARAM,
    decode_param,
)
from regs.bit3 import BIT3_REGISTERS, ERROR_MASK, LocalStatus
from regs.describe import Register, RegisterSet
from regs.hctl1000 import Status, counts_to_deg, sample_period
from regs.layout import FRAME_DTYPE, FRAME_POISON, BirisMemoryMap, TargetImage
from regs.tech80 import BOARD_REGISTERS, Axis, hctl_registers_for

__all__ = [
    "Dump",
    "DumpError",
    "FrameSummary",
    "Reader",
    "Region",
    "Row",
    "Section",
    "add_arguments",
    "changed_rows",
    "format_table",
    "last_complete_frame",
    "run",
    "snapshot",
    "snapshot_hardware",
    "snapshot_regions",
    "summarize_frame",
    "to_json",
]

Json = Any
"""A value ``json.dumps`` accepts (numbers, strings, None, lists and dicts of them)."""


class DumpError(BirisError, ValueError):
    """The dump cannot be made as asked: a missing or short source, a layout that does not fit."""


class Reader(Protocol):
    """What a dump needs of a window: its size and width-explicit reads."""

    @property
    def size(self) -> int: ...

    def read(self, offset: int, n: int) -> bytes: ...

    def read8(self, offset: int) -> int: ...

    def read16(self, offset: int) -> int: ...

    def read32(self, offset: int) -> int: ...


class Region:
    """One area of a window, addressed from its own start, reads forwarded at their own width.

    Forwarding ``read16`` as ``read16`` (not as two bytes) keeps a one-access register a
    one-access register on a live target.
    """

    def __init__(self, window: Reader, base: int, size: int) -> None:
        self.window = window
        self.base = base
        self._size = size

    @property
    def size(self) -> int:
        return self._size

    def _at(self, offset: int, n: int) -> int:
        if offset < 0 or offset + n > self._size:
            raise BusError(
                f"{n}-byte read at 0x{offset:X} is outside an area of 0x{self._size:X} bytes"
            )
        return self.base + offset

    def read(self, offset: int, n: int) -> bytes:
        return self.window.read(self._at(offset, n), n)

    def read8(self, offset: int) -> int:
        return self.window.read8(self._at(offset, 1))

    def read16(self, offset: int) -> int:
        return self.window.read16(self._at(offset, 2))

    def read32(self, offset: int) -> int:
        return self.window.read32(self._at(offset, 4))


# -- the dump's data model ------------------------------------------------------------------------


@dataclass(frozen=True)
class Row:
    """One line of a dump: a register (``register=True``, ``raw`` read or None) or a derived value.

    ``offset`` is relative to the section's base; ``value`` is what ``--json`` shows.
    """

    name: str
    decoded: str
    offset: int | None = None
    width: int = 0
    access: str = ""
    raw: int | None = None
    value: Json = None
    register: bool = False

    @property
    def raw_text(self) -> str:
        return "" if self.raw is None else f"0x{self.raw:0{2 * self.width}X}"


@dataclass(frozen=True)
class Section:
    """The rows of one register area; ``base`` is its offset in the source it was read from."""

    key: str
    title: str
    where: str
    base: int
    rows: tuple[Row, ...]

    def row(self, name: str) -> Row:
        for row in self.rows:
            if row.name == name:
                return row
        raise KeyError(f"{self.key} has no row {name!r}")


@dataclass(frozen=True)
class Dump:
    """Everything one pass read, in display order, plus where it came from."""

    source: str
    layout: dict[str, int]
    sections: tuple[Section, ...]

    def section(self, key: str) -> Section:
        for section in self.sections:
            if section.key == key:
                return section
        raise KeyError(f"no section {key!r}")


# -- reading a register set -----------------------------------------------------------------------


def _dumpable(reg: Register) -> bool:
    return reg.access.readable and not reg.read_has_effect


def _read_width(reader: Reader, offset: int, width: int) -> int:
    if width == 1:
        return reader.read8(offset)
    if width == 2:
        return reader.read16(offset)
    if width == 4:
        return reader.read32(offset)
    return int.from_bytes(reader.read(offset, width), "big")


def read_register_set(reader: Reader, regset: RegisterSet) -> dict[str, int]:
    """Raw values by name, each register read once, composites' parts first in read order.

    On a live HCTL-1000 reading R14H latches R13H/R12H, so the parts of a composite are read as
    one group in the order its description gives, before anything else can disturb the latch.
    """
    values: dict[str, int] = {}

    def read(reg: Register) -> None:
        if reg.name not in values and _dumpable(reg):
            values[reg.name] = _read_width(reader, reg.offset, reg.width)

    for composite in regset.composites:
        for name in composite.read_order:
            read(regset.by_name(name))
    for reg in regset:
        read(reg)
    return values


def _register_rows(regset: RegisterSet, values: dict[str, int]) -> list[Row]:
    rows = []
    for reg in regset:
        common: dict[str, Any] = {
            "offset": reg.offset,
            "width": reg.width,
            "access": reg.access.value,
            "register": True,
        }
        if reg.name in values:
            raw = values[reg.name]
            rows.append(Row(reg.name, reg.decode(raw), raw=raw, value=reg.to_signed(raw), **common))
        elif not reg.access.readable:
            rows.append(Row(reg.name, "(write-only)", **common))
        else:
            rows.append(Row(reg.name, "(not read: reading it has side effects)", **common))
    return rows


def _composite_rows(regset: RegisterSet, values: dict[str, int]) -> list[Row]:
    rows = []
    for composite in regset.composites:
        if not all(part in values for part in composite.parts):
            continue
        combined = composite.combine(values)
        value: Json = {"value": combined}
        if composite.name.endswith("_position"):
            value = {"counts": combined, "deg": counts_to_deg(combined)}
        rows.append(Row(composite.name, composite.decoder(combined), value=value))
    return rows


def _hex(offset: int) -> str:
    return f"0x{offset:04X}"


# -- sections -------------------------------------------------------------------------------------


def _biexec_section(biris: Region, mm: BirisMemoryMap) -> tuple[Section, dict[str, int]]:
    com = Region(biris, mm.biexec_offset, BIEXEC_REGISTERS.size)
    values = read_register_set(com, BIEXEC_REGISTERS)
    rows = _register_rows(BIEXEC_REGISTERS, values)
    raw_param = com.read(OFF_PARAM, BIEXEC_PARAM_SIZE)
    shown = raw_param.rstrip(b"\0")
    try:
        text: str | None = decode_param(raw_param)
        decoded = json.dumps(text)
    except ValueError:
        text = None
        decoded = "not NUL-terminated ASCII: " + shown.hex(" ").upper()
    rows.insert(
        3,
        Row(
            "PARAM",
            decoded,
            offset=OFF_PARAM,
            width=BIEXEC_PARAM_SIZE,
            value={"text": text, "hex": shown.hex()},
        ),
    )
    where = (
        f"BIRIS window {_hex(mm.biexec_offset)}, BIRIS address 0x{mm.address(mm.biexec_offset):08X}"
    )
    signed = {name: BIEXEC_REGISTERS.by_name(name).to_signed(raw) for name, raw in values.items()}
    section = Section("biexec", "BIEXEC_COM", where, biris.base + mm.biexec_offset, tuple(rows))
    return section, signed


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


def _frames_section(
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
            f"BIRIS window {_hex(base)}, BIRIS address 0x{mm.address(base):08X}",
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


def _hctl_rows(values: dict[str, int]) -> list[Row]:
    rows: list[Row] = []
    if "STATUS" in values:
        status = Status(values["STATUS"])
        f0, f1 = Status.PROFILE in status, Status.INIT_IDLE in status
        rows.append(
            Row(
                "flags",
                f"F0 trapezoid {'set' if f0 else 'clear'}, F1 init/idle "
                f"{'set' if f1 else 'clear'} (from status; F3/F5 are write-only)",
                value={"F0": f0, "F1": f1},
            )
        )
        stop = Status.STOP_CLEAR not in status
        limit = Status.LIMIT_CLEAR not in status
        rows.append(
            Row(
                "stop_limit",
                f"STOP {'triggered' if stop else 'clear'}, "
                f"LIMIT {'triggered' if limit else 'clear'} (active low)",
                value={"stop": stop, "limit": limit},
            )
        )
        if f1:
            mode, text = "init/idle", "init/idle (motor command held at zero)"
        elif f0:
            mode, text = "trapezoid", "trapezoidal profile running (F0 set)"
        else:
            mode, text = "control", "control: position, or a velocity mode (F3/F5 unreadable)"
        rows.append(Row("mode", text, value=mode))
    if {"FILTER_ZERO", "FILTER_POLE", "FILTER_GAIN"} <= values.keys():
        a, b, k = values["FILTER_ZERO"], values["FILTER_POLE"], values["FILTER_GAIN"]
        rows.append(
            Row(
                "filter",
                f"D(z) = ({k}/4)(z - {a / 256:.4f})/(z + {b / 256:.4f})",
                value={"A": a, "B": b, "K": k},
            )
        )
    if {"MAX_VELOCITY", "SAMPLE_TIMER"} <= values.keys():
        vmax, period = values["MAX_VELOCITY"], sample_period(values["SAMPLE_TIMER"])
        deg_s = counts_to_deg(vmax / period)
        rows.append(
            Row(
                "max_velocity",
                f"{vmax} counts/sample = {deg_s:.1f} deg/s at {period * 1e3:.3f} ms",
                value={"counts_per_sample": vmax, "deg_per_s": round(deg_s, 3)},
            )
        )
    return rows


def _hctl_section(motion: Region, axis: Axis) -> Section:
    regset = hctl_registers_for(axis)
    values = read_register_set(motion, regset)
    rows = _register_rows(regset, values) + _composite_rows(regset, values) + _hctl_rows(values)
    where = f"Model 7600 board offsets {_hex(regset.base)}..{_hex(regset.base + regset.size - 1)}"
    key = f"hctl_{axis.name.lower()}"
    return Section(key, regset.name, where, motion.base, tuple(rows))


def _coupler_rows(values: dict[str, int]) -> list[Row]:
    if "LOCAL_STATUS" not in values:
        return []
    status = values["LOCAL_STATUS"]
    errors = [bit.name or "" for bit in LocalStatus if bit & ERROR_MASK and status & bit]
    connected = not status & LocalStatus.NO_CONNECT
    return [
        Row("errors", " ".join(errors) if errors else "none", value=errors),
        Row("connected", "yes" if connected else "no (NO_CONNECT)", value=connected),
    ]


def _plain_section(
    key: str,
    region: Region,
    regset: RegisterSet,
    derive: Callable[[dict[str, int]], list[Row]] = lambda values: [],
) -> Section:
    values = read_register_set(region, regset)
    rows = _register_rows(regset, values) + derive(values)
    return Section(key, regset.name, f"{regset.size} bytes", region.base, tuple(rows))


# -- whole dumps ----------------------------------------------------------------------------------


def snapshot_regions(
    biris: Region,
    motion: Region,
    coupler: Region,
    memory_map: BirisMemoryMap,
    *,
    frame_size: int | None = None,
    source: str = "",
) -> Dump:
    """Read and decode the three areas; ``frame_size`` overrides the map's (as BIRIS reports it)."""
    mm = memory_map
    size = mm.frame_size if frame_size is None else frame_size
    needed = FRAME_DTYPE.itemsize * (mm.samples + 1)
    if size < needed or size % 2:
        raise DumpError(f"a frame of {mm.samples} samples needs an even frame size >= {needed}")
    biexec, values = _biexec_section(biris, mm)
    sections = (
        biexec,
        _frames_section(biris, mm, size, values["ACQ_LINE"], values["CURRENT_FRAME"]),
        _hctl_section(motion, Axis.AZIMUTH),
        _hctl_section(motion, Axis.ELEVATION),
        _plain_section("board", motion, BOARD_REGISTERS),
        _plain_section("coupler", coupler, BIT3_REGISTERS, _coupler_rows),
    )
    layout = {
        "coupler": coupler.base,
        "motion": motion.base,
        "biris": biris.base,
        "biris_base": mm.biris_base,
        "biexec_offset": mm.biexec_offset,
        "range_base": mm.range_offset,
        "frame_size": size,
        "samples": mm.samples,
    }
    return Dump(source, layout, sections)


def snapshot(
    window: Reader,
    image: TargetImage | None = None,
    *,
    base: int = 0,
    frame_size: int | None = None,
    source: str = "",
) -> Dump:
    """Dump one :class:`TargetImage` that starts at ``base`` in ``window``."""
    image = image or TargetImage()
    if base < 0 or base + image.size > window.size:
        raise DumpError(
            f"the image needs 0x{image.size:X} bytes from 0x{base:X}; "
            f"the window holds 0x{window.size:X}"
        )
    coupler, motion, biris = (Region(window, base + r.offset, r.size) for r in image.regions())
    return snapshot_regions(
        biris, motion, coupler, image.biris, frame_size=frame_size, source=source
    )


def snapshot_hardware(
    hw: BirisHardware, memory_map: BirisMemoryMap | None = None, *, frame_size: int | None = None
) -> Dump:
    """Dump a hardware bundle's three windows (the range base is the map's: a dump asks BIRIS
    nothing, so pass the map the server learned when it differs from the default)."""
    mm = memory_map or BirisMemoryMap(biris_base=hw.biris_base, biexec_offset=hw.biexec_offset)
    return snapshot_regions(
        Region(hw.biris, 0, hw.biris.size),
        Region(hw.motion, 0, hw.motion.size),
        Region(hw.coupler, 0, hw.coupler.size),
        mm,
        frame_size=frame_size,
        source="hardware bundle",
    )


def changed_rows(previous: Dump | None, current: Dump) -> frozenset[tuple[str, str]]:
    """(section key, row name) of every row whose raw value or decoding differs from before."""
    if previous is None:
        return frozenset()
    before = {(s.key, r.name): (r.raw, r.decoded) for s in previous.sections for r in s.rows}
    return frozenset(
        (s.key, r.name)
        for s in current.sections
        for r in s.rows
        if before.get((s.key, r.name)) != (r.raw, r.decoded)
    )


# -- output ---------------------------------------------------------------------------------------


def format_table(dump: Dump, changed: frozenset[tuple[str, str]] = frozenset()) -> str:
    """The dump as aligned text, one section per heading; changed rows start with ``*``."""
    all_rows = [r for s in dump.sections for r in s.rows]
    w_name = max(len("name"), *(len(r.name) for r in all_rows))
    w_off = max(len("offset"), *(len(_hex(r.offset)) for r in all_rows if r.offset is not None))
    w_raw = max(len("raw"), *(len(r.raw_text) for r in all_rows))
    lines = [f"source: {dump.source}" if dump.source else "source: (unnamed)"]
    for section in dump.sections:
        lines += ["", f"{section.title}  [{section.where}; at 0x{section.base:04X} of the source]"]
        lines.append(f"  {'name':<{w_name}}  {'offset':<{w_off}}  {'raw':<{w_raw}}  decoded")
        for row in section.rows:
            mark = "*" if (section.key, row.name) in changed else " "
            off = "" if row.offset is None else _hex(row.offset)
            decoded = "" if row.decoded == row.raw_text else row.decoded  # plain hex: say it once
            line = f"{mark} {row.name:<{w_name}}  {off:<{w_off}}  {row.raw_text:<{w_raw}}  "
            lines.append((line + decoded).rstrip())
    return "\n".join(lines) + "\n"


def to_json(dump: Dump, changed: frozenset[tuple[str, str]] = frozenset()) -> dict[str, Json]:
    """The dump as one JSON-ready object with stable keys.

    Each section holds ``title``, ``base``, ``registers`` (by name: offset, width, access, raw,
    value, decoded; raw and value are null when not read) and its derived values by name.
    ``changed`` lists ``"section.row"`` for rows that differ from the previous dump.
    """
    out: dict[str, Json] = {"source": dump.source, "layout": dict(dump.layout)}
    for section in dump.sections:
        body: dict[str, Json] = {"title": section.title, "base": section.base, "registers": {}}
        for row in section.rows:
            if row.register:
                body["registers"][row.name] = {
                    "offset": row.offset,
                    "width": row.width,
                    "access": row.access,
                    "raw": row.raw,
                    "value": row.value,
                    "decoded": row.decoded,
                }
            else:
                body[row.name] = row.value
        out[section.key] = body
    out["changed"] = sorted(f"{key}.{name}" for key, name in changed)
    return out


# -- CLI adapter ----------------------------------------------------------------------------------

_sleep: Callable[[float], None] = time.sleep
"""Pacing between ``--watch`` dumps (a module attribute so tests can replace it)."""


def _offset(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an offset: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"offset must not be negative: {text}")
    return value


def _positive(text: str) -> int:
    value = _offset(text)
    if value == 0:
        raise argparse.ArgumentTypeError("must be at least 1")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``regdump`` options (the caller owns the parser)."""
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--file", metavar="PATH", help="a raw image file")
    src.add_argument("--mmap", metavar="PATH", help="map a file or device (see --offset)")
    src.add_argument("--shm", metavar="NAME", help="a shared-memory segment (the simulator's)")
    parser.add_argument(
        "--offset", type=_offset, default=0, metavar="N", help="where the image starts (bytes)"
    )
    img = TargetImage()
    mm = img.biris
    for flag, default, what in (
        ("--coupler-at", img.coupler_offset, "Bit 3 coupler registers"),
        ("--motion-at", img.motion_offset, "Model 7600 board"),
        ("--biris-at", img.biris_offset, "BIRIS memory"),
    ):
        parser.add_argument(
            flag, type=_offset, default=default, metavar="N", help=f"image offset of the {what}"
        )
    parser.add_argument(
        "--samples", type=int, choices=(64, 128), default=mm.samples, help="samples per frame"
    )
    parser.add_argument(
        "--biexec-offset", type=_offset, default=mm.biexec_offset, metavar="N",
        help="BIEXEC_COM's offset in the BIRIS window",
    )  # fmt: skip
    parser.add_argument(
        "--range-base", type=_offset, default=mm.range_offset, metavar="N",
        help="range array's offset in the BIRIS window",
    )  # fmt: skip
    parser.add_argument(
        "--frame-size", type=_positive, default=None, metavar="N",
        help="bytes per frame (default: from --samples)",
    )  # fmt: skip
    parser.add_argument("--json", action="store_true", help="one JSON object per dump")
    parser.add_argument(
        "--watch",
        type=_positive,
        default=None,
        metavar="MS",
        help="dump every MS ms, marking changes with *",
    )
    parser.add_argument(
        "--count", type=_positive, default=None, metavar="K", help="stop after K dumps"
    )
    parser.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks"
    )


def _image(args: argparse.Namespace) -> TargetImage:
    try:
        mm = BirisMemoryMap(
            samples=args.samples, biexec_offset=args.biexec_offset, range_offset=args.range_base
        )
        return TargetImage(args.coupler_at, args.motion_at, args.biris_at, mm)
    except ValueError as exc:
        raise DumpError(f"bad layout: {exc}") from exc


def _read_file(path: str, offset: int, size: int) -> bytes:
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read(size)
    except FileNotFoundError:
        raise DumpError(f"no such file: {path}") from None
    if len(data) < size:
        raise DumpError(
            f"{path} is too short: {len(data)} bytes from offset 0x{offset:X}, "
            f"the image needs 0x{size:X}"
        )
    return data


@contextlib.contextmanager
def _file_images(path: str, offset: int, size: int) -> Iterator[Callable[[], BusWindow]]:
    """Each dump re-reads the file, so ``--watch`` follows a file that is being rewritten."""
    yield lambda: open_window("memory", size=size, buffer=bytearray(_read_file(path, offset, size)))


@contextlib.contextmanager
def _window_images(window: BusWindow) -> Iterator[Callable[[], BusWindow]]:
    try:
        yield lambda: window
    finally:
        window.close()


def _open_mmap(path: str, offset: int, size: int) -> BusWindow:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise DumpError(f"no such file: {path}") from None
    if os.path.isfile(path) and st.st_size < offset + size:
        raise DumpError(
            f"{path} is too short: {st.st_size} bytes, the image needs 0x{size:X} "
            f"from offset 0x{offset:X}"
        )
    try:
        return open_window("mmap", path=path, offset=offset, size=size)
    except ImportError as exc:
        raise DumpError(f"the mmap window is not available: {exc}") from exc


def _open_shm(name: str, offset: int, size: int) -> BusWindow:
    try:
        window = open_window("shm", name=name, create=False)
    except OSError as exc:
        if exc.errno == errno.ENOENT:
            raise DumpError(f"no shared memory segment {name!r}") from None
        raise
    except ImportError as exc:
        raise DumpError(f"the shm window is not available: {exc}") from exc
    if window.size < offset + size:
        window.close()
        raise DumpError(
            f"shared memory {name!r} is too short: 0x{window.size:X} bytes, the image needs "
            f"0x{size:X} from offset 0x{offset:X}"
        )
    return window


def _images(
    args: argparse.Namespace, size: int
) -> tuple[contextlib.AbstractContextManager[Callable[[], BusWindow]], int, str]:
    """(context giving a window per dump, image offset in that window, source label)."""
    if args.file is not None:
        return _file_images(args.file, args.offset, size), 0, f"file {args.file}"
    if args.mmap is not None:
        label = f"mmap {args.mmap} at 0x{args.offset:X}"
        return _window_images(_open_mmap(args.mmap, args.offset, size)), 0, label
    label = f"shm {args.shm}"
    return _window_images(_open_shm(args.shm, args.offset, size)), args.offset, label


def _emit(
    dump: Dump, changed: frozenset[tuple[str, str]], n: int, args: argparse.Namespace, out: TextIO
) -> None:
    if args.json:
        data = to_json(dump, changed)
        data["dump"] = n
        text = json.dumps(data, separators=(",", ":")) if args.watch else json.dumps(data, indent=2)
        out.write(text + "\n")
    else:
        if args.watch:
            out.write(f"=== dump {n}: {len(changed)} changed ===\n")
        out.write(format_table(dump, changed))
    out.flush()


def _dump_loop(args: argparse.Namespace, out: TextIO) -> int:
    if args.count is not None and args.watch is None:
        raise DumpError("--count needs --watch")
    image = _image(args)
    context, base, label = _images(args, image.size)
    with context as next_window:
        previous: Dump | None = None
        n = 0
        while True:
            n += 1
            window = next_window()
            try:
                dump = snapshot(window, image, base=base, frame_size=args.frame_size, source=label)
            finally:
                if args.file is not None:
                    window.close()
            _emit(dump, changed_rows(previous, dump), n, args, out)
            previous = dump
            if args.watch is None or (args.count is not None and n >= args.count):
                return 0
            _sleep(args.watch / 1000.0)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Run ``biris regdump``: 0 when done (or on Ctrl-C), 2 with one line on stderr on error."""
    try:
        return _dump_loop(args, out or sys.stdout)
    except KeyboardInterrupt:
        return 0
    except (BirisError, OSError, ValueError, LookupError) as exc:
        if getattr(args, "debug", False):
            traceback.print_exc(file=sys.stderr)
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"biris regdump: {message}", file=sys.stderr)
        return 2
