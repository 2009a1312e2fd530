"""Whole dumps: BIEXEC_COM, the frames, both HCTL-1000s, the Model 7600 board and the coupler
(and a target's VME crate, read over CAN, when it has a ``[crate]``).

Each section is read with the hardware's rules (see :mod:`biris_hw.regdump.registers`) and gets,
besides its registers, the derived values a person would otherwise work out by hand: the flags
and mode of an HCTL-1000, its filter and velocity in real units, the coupler's errors.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import TYPE_CHECKING

from biris_hw.errors import BirisError
from biris_hw.hardware import BirisHardware
from biris_hw.regdump.frames import frames_section
from biris_hw.regdump.model import Dump, DumpError, Row, Section, hex_offset
from biris_hw.regdump.regions import Reader, Region
from biris_hw.regdump.registers import composite_rows, read_register_set, register_rows
from regs.biexec import BIEXEC_PARAM_SIZE, BIEXEC_REGISTERS, OFF_PARAM, decode_param
from regs.bit3 import BIT3_REGISTERS, ERROR_MASK, LocalStatus
from regs.describe import RegisterSet
from regs.hctl1000 import Status, counts_to_deg, sample_period
from regs.layout import FRAME_DTYPE, BirisMemoryMap, TargetImage
from regs.tech80 import BOARD_REGISTERS, Axis, hctl_registers_for

if TYPE_CHECKING:
    from biris_hw.crate import CrateMonitor

__all__ = ["crate_section", "snapshot", "snapshot_hardware", "snapshot_regions"]


def _biexec_section(biris: Region, mm: BirisMemoryMap) -> tuple[Section, dict[str, int]]:
    com = Region(biris, mm.biexec_offset, BIEXEC_REGISTERS.size)
    values = read_register_set(com, BIEXEC_REGISTERS)
    rows = register_rows(BIEXEC_REGISTERS, values)
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
    at = mm.biexec_offset
    where = f"BIRIS window {hex_offset(at)}, BIRIS address 0x{mm.address(at):08X}"
    signed = {name: BIEXEC_REGISTERS.by_name(name).to_signed(raw) for name, raw in values.items()}
    section = Section("biexec", "BIEXEC_COM", where, biris.base + mm.biexec_offset, tuple(rows))
    return section, signed


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
    rows = register_rows(regset, values) + composite_rows(regset, values) + _hctl_rows(values)
    first, last = hex_offset(regset.base), hex_offset(regset.base + regset.size - 1)
    where = f"Model 7600 board offsets {first}..{last}"
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
    rows = register_rows(regset, values) + derive(values)
    return Section(key, regset.name, f"{regset.size} bytes", region.base, tuple(rows))


def snapshot_regions(
    biris: Region,
    motion: Region | None,
    coupler: Region,
    memory_map: BirisMemoryMap,
    *,
    frame_size: int | None = None,
    source: str = "",
) -> Dump:
    """Read and decode the three areas; ``frame_size`` overrides the map's (as BIRIS reports it).
    ``motion`` is None on a target whose axes are CiA 402 drives (no Model 7600): its three
    sections are then left out, and the layout has no ``motion`` entry."""
    mm = memory_map
    size = mm.frame_size if frame_size is None else frame_size
    needed = FRAME_DTYPE.itemsize * (mm.samples + 1)
    if size < needed or size % 2:
        raise DumpError(f"a frame of {mm.samples} samples needs an even frame size >= {needed}")
    biexec, values = _biexec_section(biris, mm)
    board: tuple[Section, ...] = ()
    if motion is not None:
        board = (
            _hctl_section(motion, Axis.AZIMUTH),
            _hctl_section(motion, Axis.ELEVATION),
            _plain_section("board", motion, BOARD_REGISTERS),
        )
    sections = (
        biexec,
        frames_section(biris, mm, size, values["ACQ_LINE"], values["CURRENT_FRAME"]),
        *board,
        _plain_section("coupler", coupler, BIT3_REGISTERS, _coupler_rows),
    )
    layout = {
        "coupler": coupler.base,
        **({"motion": motion.base} if motion is not None else {}),
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
    dump = snapshot_regions(
        Region(hw.biris, 0, hw.biris.size),
        Region(hw.motion, 0, hw.motion.size) if hw.motion is not None else None,
        Region(hw.coupler, 0, hw.coupler.size),
        mm,
        frame_size=frame_size,
        source="hardware bundle",
    )
    if hw.crate is None:
        return dump
    return Dump(dump.source, dump.layout, (*dump.sections, crate_section(hw.crate)))


def crate_section(monitor: CrateMonitor) -> Section:
    """The VME crate's reading over CAN (a target's ``[crate]``), decoded; a crate that does
    not answer is a row saying so, not a failed dump (the boards may still be readable)."""
    title = f"Wiener VME crate {monitor.crate_id}"
    try:
        reading = monitor.read()
    except BirisError as exc:
        answer = Row("answer", str(exc), value=str(exc))
        return Section("crate", title, monitor.channel_info, 0, (answer,))
    alarms = reading.alarms()
    rows = [
        Row("status", reading.status_bytes.hex(" ").upper(), value=reading.status_bytes.hex()),
        Row("power", "on" if reading.power_on else "off", value=reading.power_on),
        Row("alarms", "; ".join(alarms) or "none", value=list(alarms)),
    ]
    for n, (volts, amps) in enumerate(zip(reading.voltages_v, reading.currents_a, strict=True)):
        rows.append(Row(f"channel {n}", f"{volts:+.2f} V  {amps:.2f} A", value=[volts, amps]))
    rows.append(
        Row(
            "fans",
            " ".join(str(rps * 60) for rps in reading.fans_rps)
            + f" rpm (nominal {reading.fan_nominal_rps * 60})",
            value=list(reading.fans_rps),
        )
    )
    rows.append(
        Row(
            "temperatures",
            " ".join(str(c) for c in reading.temperatures_c) + " C",
            value=list(reading.temperatures_c),
        )
    )
    return Section("crate", title, monitor.channel_info, 0, tuple(rows))
