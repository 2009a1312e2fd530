"""A real VME target, described in TOML, opened as a :class:`~biris_hw.hardware.BirisHardware`.

The simulator builds its hardware bundle in code; the robot's VME host cannot, because where the
coupler window, the Model 7600 board and the interrupt lines live depends on how that machine is
wired and which kernel drivers it runs. So the wiring is data: one file whose top-level keys are
the bundle's own fields (``biris``, ``motion``, ``coupler``, ``level2``, ``level3``,
``biexec_offset``, ``biris_base``, ``clock``), each window and line named by its registry kind
with that kind's options. ``docs/target-example.toml`` documents every key. A target whose axes
are CiA 402 drives over CAN has an ``[axes]`` table instead of ``motion`` and ``level3``
(``docs/target-can-example.toml``). A ``[crate]`` table adds the VME crate's own monitor over
CAN (a Wiener crate's power, fans and temperatures in ``status()``).

Everything is checked before the server sees it, and every message names the key at fault: a
server must not start on half a description, and a person reading ``biris: ...`` must be able to
find the line to fix without a traceback. Content errors are :class:`RequestError`; failures of
the operating system to open a device (missing node, no permission) are :class:`BusError` with
the system's errno, so callers can tell "fix the file" from "fix the machine".
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import re
import sys
import time
from collections.abc import Callable, Mapping
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING, Any

from biris_hw.axes.base import AxisSet
from biris_hw.bus.base import BusWindow
from biris_hw.bus.registry import open_window
from biris_hw.devices import LEVEL2_VECTOR, IndexKind, MotionBoard, prefetch_reads
from biris_hw.errors import BusError, RequestError, UnknownKind
from biris_hw.hardware import BirisHardware
from biris_hw.irq.base import InterruptLine
from biris_hw.irq.poll import PollLine
from biris_hw.irq.registry import open_line
from biris_hw.pan_reference import default_journal_path
from regs.biexec import BIEXEC_COM_SIZE
from regs.bit3 import BIT3_SPACE
from regs.tech80 import DEFAULT_IRQ_VECTOR, MOTION_WINDOW_SIZE
from regs.wiener_crate import CRATE_IDS

if TYPE_CHECKING:
    from biris_hw.crate import CrateMonitor

if sys.version_info >= (3, 11):
    import tomllib
else:  # tomli is a declared dependency below 3.11
    import tomli as tomllib  # type: ignore[import-not-found, unused-ignore]

__all__ = [
    "AXES_KINDS",
    "CLOCKS",
    "CRATE_KINDS",
    "HOMING_KEY",
    "TARGET_KEYS",
    "WINDOW_MINIMUM",
    "load_target",
    "target_from_dict",
]

log = logging.getLogger(__name__)

WINDOW_MINIMUM: dict[str, int] = {
    "biris": BIEXEC_COM_SIZE,
    "motion": MOTION_WINDOW_SIZE,
    "coupler": BIT3_SPACE,
}
"""Bytes each window must at least hold (BIRIS: BIEXEC_COM beyond ``biexec_offset``); a smaller
window would only fail later, with a bus error in the middle of a scan."""

CLOCKS: dict[str, Callable[[], float]] = {"monotonic": time.monotonic}
"""Hardware clocks a target may name. The real sensor runs in real time, so the host's monotonic
clock is the hardware clock; the key exists so that a description says so explicitly."""

TARGET_KEYS = (
    "biris",
    "motion",
    "coupler",
    "level2",
    "level3",
    "biexec_offset",
    "biris_base",
    "clock",
    "pan_journal",
    "axes",
    "crate",
    "homing",
)

AXES_KINDS = ("cia402",)
"""What an ``[axes]`` table may name: CiA 402 drives over CANopen (``biris-hw[can]``)."""

_AXES_INTS = {
    "master_id": (0, 127),  # 0: no heartbeat of the host's own; else a node id
    "bitrate": (1, 8_000_000),
}
_AXES_RULED = ("pan_node", "tilt_node", "homing_method")
"""Keys whose rule is the driver's own (:mod:`biris_hw.axes.cia402`: ``check_node_id``,
``check_homing_method``), applied here so that the message names the key."""
_AXES_SECONDS = {
    "boot_timeout": "boot_timeout_s",
    "heartbeat_period": "heartbeat_period_s",
    "heartbeat_timeout": "heartbeat_timeout_s",
    "sdo_timeout": "sdo_timeout_s",
    "state_timeout": "state_timeout_s",
}
_AXES_STRINGS = ("interface", "channel", "context")
_AXES_TABLES = ("can", "gains")
"""Sub-tables of ``[axes]``: more ``can.Bus`` options, and the drive's own objects that take
BIRIS_MOTOR_PARAMS' sample and filter values (``[axes.gains]``, the driver's ``gains``)."""
_AXES_KEYS = frozenset(
    {"kind", *_AXES_TABLES, *_AXES_INTS, *_AXES_RULED, *_AXES_SECONDS, *_AXES_STRINGS}
)
_AXES_GONE = {
    "params_index": "the driver writes no 0x2000 record of its own any more: name the drive's "
    "own objects for the filter values in [axes.gains] (docs/targets.md), or leave them to the "
    "drive's tuning",
}
"""Keys a target file may still carry from an earlier release, and what to write instead."""

CRATE_KINDS = ("wiener-can",)
"""What a ``[crate]`` table may name: a Wiener VME crate's monitor over CAN (python-can)."""
_CRATE_KEYS = frozenset({"kind", "interface", "channel", "bitrate", "crate_id", "poll", "timeout"})

_WIDTHS = (8, 16, 32)
_SCALAR = (str, int, float, bool)
_BAD_KEYWORD = re.compile(r"unexpected keyword argument '(\w+)'")


# -- small validators ------------------------------------------------------------------------------


def _int(key: str, value: object, lo: int, hi: int) -> int:
    """A whole number in lo..hi; TOML booleans and floats are refused (0.5 is no address)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise RequestError(f"{key}: must be an integer, not {_type(value)}")
    if not lo <= value <= hi:
        raise RequestError(f"{key}: must be in 0x{lo:X}..0x{hi:X}, not 0x{value:X}")
    return value


def _seconds(key: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RequestError(f"{key}: must be a number of seconds, not {_type(value)}")
    if not (math.isfinite(value) and value > 0):
        raise RequestError(f"{key}: must be a positive number of seconds, not {value}")
    return float(value)


def _table(key: str, value: object) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise RequestError(f"{key}: must be a table such as {{kind = ...}}, not {_type(value)}")
    return value


def _kind(key: str, table: Mapping[str, Any]) -> str:
    kind = table.get("kind")
    if kind is None:
        raise RequestError(f"{key}.kind: missing (say which kind of {_what(key)} this is)")
    if not isinstance(kind, str):
        raise RequestError(f"{key}.kind: must be a string, not {_type(kind)}")
    return kind


def _options(key: str, table: Mapping[str, Any]) -> dict[str, Any]:
    """The table less ``kind``; only scalars, since every window and line option is one."""
    options = {k: v for k, v in table.items() if k != "kind"}
    for name, value in options.items():
        if not isinstance(value, _SCALAR):
            raise RequestError(f"{key}.{name}: must be a number, string or boolean")
        if name in ("offset", "size") and isinstance(value, int) and value < 0:
            raise RequestError(f"{key}.{name}: must not be negative, not {value}")
    return options


def _type(value: object) -> str:
    if isinstance(value, Mapping):
        return "a table"
    if isinstance(value, list):
        return "an array"
    return type(value).__name__


def _what(key: str) -> str:
    return "interrupt line" if key.startswith("level") else "bus window"


def _opening_error(key: str, kind: str, exc: Exception) -> Exception:
    """Turn what a window or line constructor raised into a message that names the key."""
    if isinstance(exc, UnknownKind):
        return RequestError(f"{key}.kind: {exc}")
    if isinstance(exc, TypeError):
        bad = _BAD_KEYWORD.search(str(exc))
        if bad:
            return RequestError(f"{key}.{bad[1]}: not an option of kind {kind!r}")
        return RequestError(f"{key}: {exc}")
    if isinstance(exc, OSError):
        return BusError(f"{key}: {exc.strerror or exc}", exc.errno or errno.EIO)
    return RequestError(f"{key}: {exc}")


# -- windows and lines -----------------------------------------------------------------------------


def _open_window(key: str, spec: object, minimum: int) -> BusWindow:
    table = _table(key, spec)
    kind = _kind(key, table)
    try:
        window = open_window(kind, **_options(key, table))
    except RequestError:
        raise
    except (UnknownKind, TypeError, ValueError, OSError) as exc:
        raise _opening_error(key, kind, exc) from exc
    if window.size < minimum:
        size = window.size
        window.close()
        raise RequestError(
            f"{key}: the window holds 0x{size:X} bytes, it needs at least 0x{minimum:X}"
        )
    return window


def _poll_line(key: str, table: Mapping[str, Any], windows: Mapping[str, BusWindow]) -> PollLine:
    """A register predicate: ``(register & mask) != 0``, or ``== equals`` when given."""
    known = {"kind", "window", "offset", "width", "mask", "equals", "period", "acknowledge"}
    for name in table:
        if name not in known:
            raise RequestError(f"{key}.{name}: not an option of kind 'poll'")
    named = table.get("window")
    if not isinstance(named, str) or named not in windows:
        raise RequestError(f"{key}.window: must be one of {', '.join(windows)}, not {named!r}")
    window = windows[named]
    width = table.get("width", 8)
    if width not in _WIDTHS or isinstance(width, bool):
        raise RequestError(f"{key}.width: must be 8, 16 or 32 (bits), not {width!r}")
    full = (1 << width) - 1
    offset = _register(f"{key}.offset", table.get("offset"), width, window)
    mask = _int(f"{key}.mask", table.get("mask", full), 1, full)
    equals = table.get("equals")
    if equals is not None:
        equals = _int(f"{key}.equals", equals, 0, full)
        if equals & ~mask:
            raise RequestError(f"{key}.equals: 0x{equals:X} has bits outside the mask 0x{mask:X}")
    period = _seconds(f"{key}.period", table.get("period", 0.001))
    read = _reader(window, width)

    def predicate() -> bool:
        value = read(offset) & mask
        return value == equals if equals is not None else value != 0

    acknowledge: Callable[[], None] | None = None
    if "acknowledge" in table:
        ack = _table(f"{key}.acknowledge", table["acknowledge"])
        extra = sorted(set(ack) - {"offset", "value", "width"})
        if extra:
            raise RequestError(f"{key}.acknowledge.{extra[0]}: not an option of an acknowledgement")
        ack_width = ack.get("width", width)
        if ack_width not in _WIDTHS or isinstance(ack_width, bool):
            raise RequestError(f"{key}.acknowledge.width: must be 8, 16 or 32, not {ack_width!r}")
        ack_offset = _register(f"{key}.acknowledge.offset", ack.get("offset"), ack_width, window)
        ack_value = _int(f"{key}.acknowledge.value", ack.get("value"), 0, (1 << ack_width) - 1)
        write = _writer(window, ack_width)

        def acknowledge() -> None:
            write(ack_offset, ack_value)

    return PollLine(predicate, period, acknowledge=acknowledge)


def _register(key: str, value: object, width: int, window: BusWindow) -> int:
    if value is None:
        raise RequestError(f"{key}: missing (the register's offset in its window)")
    nbytes = width // 8
    offset = _int(key, value, 0, max(0, window.size - nbytes))
    if offset % nbytes:
        raise RequestError(f"{key}: 0x{offset:X} is not aligned for a {width}-bit register")
    return offset


def _reader(window: BusWindow, width: int) -> Callable[[int], int]:
    return {8: window.read8, 16: window.read16, 32: window.read32}[width]


def _writer(window: BusWindow, width: int) -> Callable[[int, int], None]:
    return {8: window.write8, 16: window.write16, 32: window.write32}[width]


def _vmusb_line_options(
    key: str, options: dict[str, Any], windows: Mapping[str, BusWindow], biexec_offset: int
) -> dict[str, Any]:
    """A VM-USB line: its level is the key's, its vector the one the driver programs (both
    may be given, and must then agree), and its IRQ stack reads what the key's interrupt
    routine decides from (:func:`~biris_hw.devices.prefetch_reads`)."""
    level = int(key.removeprefix("level"))
    if "reads" in options:
        raise RequestError(f"{key}.reads: not an option (the driver chooses what its stack reads)")
    given = options.setdefault("level", level)
    if given != level:
        raise RequestError(f"{key}.level: the {key} line is level {level}, not {given!r}")
    options.setdefault("vector", LEVEL2_VECTOR if level == 2 else DEFAULT_IRQ_VECTOR)
    options["reads"] = prefetch_reads(
        level,
        biris=windows["biris"],
        motion=windows.get("motion"),
        coupler=windows["coupler"],
        biexec_offset=biexec_offset,
    )
    return options


def _open_line(
    key: str, spec: object, windows: Mapping[str, BusWindow], biexec_offset: int = 0
) -> InterruptLine:
    table = _table(key, spec)
    kind = _kind(key, table)
    if kind == "poll":
        return _poll_line(key, table, windows)
    options = _options(key, table)
    if kind == "vmusb":
        options = _vmusb_line_options(key, options, windows, biexec_offset)
    try:
        return open_line(kind, **options)
    except RequestError:
        raise
    except (UnknownKind, TypeError, ValueError, OSError) as exc:
        raise _opening_error(key, kind, exc) from exc


def _kind_table(
    name: str, spec: object, kinds: tuple[str, ...], keys: frozenset[str]
) -> Mapping[str, Any]:
    """A table naming its ``kind`` (one of ``kinds``) with no key but ``keys``."""
    table = _table(name, spec)
    kind = table.get("kind")
    if kind not in kinds:
        raise RequestError(f"{name}.kind: must be one of {', '.join(kinds)}, not {kind!r}")
    for key in table:
        if key not in keys:
            raise RequestError(f"{name}.{key}: not an option of kind {kind!r}")
    return table


def _axes_options(spec: object) -> dict[str, Any]:
    """The ``[axes]`` table as :class:`~biris_hw.axes.cia402.Cia402Axes` keywords: our keys
    checked and renamed, python-can's (``interface``, ``channel``, ``bitrate``, ``context``
    and the ``can`` sub-table's) passed to ``can.Bus`` as they are. Without ``interface`` and
    ``channel`` python-can takes them from its own configuration (``~/.canrc``, ``can.ini``,
    ``CAN_INTERFACE``/``CAN_CHANNEL``/``CAN_BITRATE``; ``context`` picks a section). The
    ``gains`` sub-table maps ``sample``/``zero``/``pole``/``gain`` to the drive's own objects
    (``"0x2000:1"``, ``"0x2101:3:u32"``; :func:`~biris_hw.axes.cia402.check_gains`'s rule)."""
    if isinstance(spec, Mapping):
        for key, instead in _AXES_GONE.items():
            if key in spec:
                raise RequestError(f"axes.{key}: not an option: {instead}")
    table = _kind_table("axes", spec, AXES_KINDS, _AXES_KEYS)
    try:
        from biris_hw.axes.cia402 import NODE_IDS, check_gains, check_homing_method, check_node_id
    except ImportError as exc:
        raise _no_canopen(exc) from None
    options: dict[str, Any] = {}
    for key in ("pan_node", "tilt_node"):
        if key not in table:
            raise RequestError(
                f"axes.{key}: missing (the drive's CANopen node id, "
                f"{NODE_IDS.start}..{NODE_IDS.stop - 1})"
            )
    rules = {
        "pan_node": check_node_id,
        "tilt_node": check_node_id,
        "homing_method": check_homing_method,
    }
    for key, rule in rules.items():
        if key in table:
            value = table[key]
            if isinstance(value, bool) or not isinstance(value, int):
                raise RequestError(f"axes.{key}: must be an integer, not {_type(value)}")
            try:
                options[key] = rule(value, key)
            except ValueError as exc:
                raise RequestError(f"axes.{exc}") from None
    for key, (lo, hi) in _AXES_INTS.items():
        if key in table:
            options[key] = _int(f"axes.{key}", table[key], lo, hi)
    if options.get("master_id") == 0:
        options["master_id"] = None  # no heartbeat of the host's own
    for key, keyword in _AXES_SECONDS.items():
        if key in table:
            options[keyword] = _seconds(f"axes.{key}", table[key])
    for key in _AXES_STRINGS:
        if key in table:
            if not isinstance(table[key], str):
                raise RequestError(f"axes.{key}: must be a string, not {_type(table[key])}")
            options[key] = table[key]
    if "gains" in table:
        try:
            options["gains"] = check_gains(_table("axes.gains", table["gains"]), "gains")
        except ValueError as exc:
            raise RequestError(f"axes.{exc}") from None
    extra = _table("axes.can", table.get("can", {}))
    for key, value in extra.items():
        if not isinstance(value, _SCALAR):
            raise RequestError(f"axes.can.{key}: must be a number, string or boolean")
        if key in options or key in _AXES_KEYS:
            raise RequestError(f"axes.can.{key}: give it in [axes] itself")
        options[key] = value
    return options


def _no_canopen(exc: ImportError) -> RequestError:
    """:mod:`biris_hw.axes.cia402` is imported only when a target names CiA 402 drives: it
    needs the ``canopen`` package (``biris-hw[can]``)."""
    return RequestError(
        f"axes: CiA 402 drives need the canopen package ({exc}); install biris-hw[can]"
    )


def _open_axes(spec: object, clock: Callable[[], float]) -> AxisSet:
    """CiA 402 drives as an ``[axes]`` table describes them (nothing is sent to them yet)."""
    options = _axes_options(spec)
    try:
        from biris_hw.axes.cia402 import Cia402Axes
    except ImportError as exc:
        raise _no_canopen(exc) from None
    try:
        return Cia402Axes(clock=clock, time_scale=1.0, **options)
    except BusError as exc:  # the CAN interface cannot be opened: the machine's problem
        raise BusError(f"axes: {exc}", exc.errno or errno.EIO) from exc
    except (TypeError, ValueError) as exc:
        raise RequestError(f"axes: {exc}") from exc


def _open_crate(spec: object) -> tuple[CrateMonitor, float]:
    """The crate monitor a ``[crate]`` table describes, and its poll period (real seconds).

    ``interface``, ``channel`` and ``bitrate`` are python-can's (without them, its own
    configuration); ``crate_id`` is the crate's CAN id (1..126, set on its front panel),
    ``poll`` the seconds between readings (default 1), ``timeout`` how long one answer may take
    (default 0.25 s)."""
    table = _kind_table("crate", spec, CRATE_KINDS, _CRATE_KEYS)
    if "crate_id" not in table:
        raise RequestError(
            f"crate.crate_id: missing (the crate's CAN id, {CRATE_IDS.start}..{CRATE_IDS.stop - 1})"
        )
    crate_id = _int("crate.crate_id", table["crate_id"], CRATE_IDS.start, CRATE_IDS.stop - 1)
    options: dict[str, Any] = {}
    for key in ("interface", "channel"):
        if key in table:
            if not isinstance(table[key], str):
                raise RequestError(f"crate.{key}: must be a string, not {_type(table[key])}")
            options[key] = table[key]
    if "bitrate" in table:
        options["bitrate"] = _int("crate.bitrate", table["bitrate"], 1, 8_000_000)
    poll = _seconds("crate.poll", table.get("poll", 1.0))
    timeout = _seconds("crate.timeout", table.get("timeout", 0.25))
    from biris_hw.crate import CrateMonitor  # python-can, only for a target with a crate

    try:
        return CrateMonitor.open(crate_id=crate_id, timeout_s=timeout, **options), poll
    except BusError as exc:  # the CAN interface cannot be opened: the machine's problem
        raise BusError(f"crate: {exc}", exc.errno or errno.EIO) from exc
    except (TypeError, ValueError) as exc:
        raise RequestError(f"crate: {exc}") from exc


def _check_crate_beside_axes(crate: object, axes: object) -> None:
    """A crate on the drives' bus must not share a node id with them: crate n's function 1
    frame is node n's EMCY id and its function 3 node n's TPDO1, so the drivers would read
    each other's frames."""
    if not isinstance(crate, Mapping) or not isinstance(axes, Mapping):
        return  # the tables' own checks say what is wrong
    same_bus = all(crate.get(key) == axes.get(key) for key in ("interface", "channel"))
    crate_id = crate.get("crate_id")
    if same_bus and crate_id in (axes.get("pan_node"), axes.get("tilt_node")):
        raise RequestError(
            f"crate.crate_id: {crate_id} is a drive's node id on the same CAN bus (the crate's "
            f"frames would be that drive's EMCY and PDOs); give the crate another id"
        )


def _pan_journal(value: object, base: Path | None) -> Path | None:
    """The journal's path: the key's (relative to the target file's directory), the default
    when absent, None for "" (memory only, with a warning: a restart then forgets the pan)."""
    if value is None:
        return default_journal_path()
    if not isinstance(value, str):
        raise RequestError(f"pan_journal: must be a path (a string), not {_type(value)}")
    if value == "":
        log.warning(
            "pan_journal is empty: the pan reference is kept in memory only, so a restarted "
            "driver cannot tell which revolution the head is in"
        )
        return None
    path = Path(value).expanduser()
    if not path.is_absolute() and base is not None:
        path = base / path
    return path


HOMING_KEY = "homing"
"""The ``[homing]`` table: what the Model 7600's INDEX_STATUS shows, which decides how homing
looks for the zero index (``index = "latch"``, the default, or ``"level"`` with
``index_width`` counts; :class:`~biris_hw.devices.IndexKind`, docs/targets.md)."""


def _homing(spec: object, with_axes: bool) -> tuple[IndexKind, int]:
    """The ``[homing]`` table as (kind, width); refused beside ``[axes]`` (a CiA 402 drive's
    touch probe latches its index)."""
    table = _table(HOMING_KEY, spec)
    if with_axes:
        raise RequestError(
            "homing: not with [axes] (a CiA 402 drive's touch probe latches the index)"
        )
    for key in table:
        if key not in ("index", "index_width"):
            raise RequestError(f"homing.{key}: not an option (index, index_width)")
    kinds = ", ".join(repr(k.value) for k in IndexKind)
    value = table.get("index", IndexKind.LATCH.value)
    if not isinstance(value, str) or value not in {k.value for k in IndexKind}:
        raise RequestError(f"homing.index: must be one of {kinds}, not {value!r}")
    kind = IndexKind(value)
    if "index_width" in table and kind is not IndexKind.LEVEL:
        raise RequestError('homing.index_width: only with index = "level"')
    width = _int("homing.index_width", table.get("index_width", 1), 1, 256)
    return kind, width


# -- the whole description -------------------------------------------------------------------------


def target_from_dict(data: Mapping[str, Any], base: Path | None = None) -> BirisHardware:
    """Open every window and line a parsed description names; on any error, close what was
    opened and raise (RequestError for the description, BusError for the machine).

    ``base`` is the directory a relative ``pan_journal`` is taken from (the target file's);
    None takes it from the working directory.
    """
    if not isinstance(data, Mapping):
        raise RequestError(f"a target description must be a table, not {_type(data)}")
    for key in data:
        if key not in TARGET_KEYS:
            known = ", ".join(TARGET_KEYS)
            raise RequestError(f"unknown key {key!r} (known: {known})")
    with_axes = "axes" in data
    for key in TARGET_KEYS[:5]:
        if with_axes and key in ("motion", "level3"):
            if key in data:
                raise RequestError(
                    f"{key}: not with [axes] (the CiA 402 drives replace the Model 7600, "
                    "and their end of motion comes over CAN)"
                )
            continue
        if key not in data:
            raise RequestError(
                f"{key}: missing (a target names biris, motion, coupler, level2 and level3; "
                "biris, coupler, level2 and [axes] when the axes are CiA 402 drives)"
            )
    biexec_offset = _int("biexec_offset", data.get("biexec_offset", 0x100), 0, 0xFFFF_FFFF)
    if biexec_offset % 2:
        raise RequestError(
            f"biexec_offset: must be even (16-bit registers), not 0x{biexec_offset:X}"
        )
    biris_base = _int("biris_base", data.get("biris_base", 0x00C0_0000), 0, 0xFFFF_FFFF)
    clock_name = data.get("clock", "monotonic")
    if clock_name not in CLOCKS:
        raise RequestError(f"clock: must be one of {', '.join(CLOCKS)}, not {clock_name!r}")
    pan_journal = _pan_journal(data.get("pan_journal"), base)
    homing = _homing(data[HOMING_KEY], with_axes) if HOMING_KEY in data else None
    minimum = dict(WINDOW_MINIMUM, biris=biexec_offset + BIEXEC_COM_SIZE)
    with contextlib.ExitStack() as opened:
        windows: dict[str, BusWindow] = {}
        for key in ("biris", "motion", "coupler"):
            if key in data:
                windows[key] = _open_window(key, data[key], minimum[key])
                opened.callback(windows[key].close)
        lines: dict[str, InterruptLine] = {}
        for key in ("level2", "level3"):
            if key in data:
                lines[key] = _open_line(key, data[key], windows, biexec_offset)
                opened.callback(lines[key].close)
        axes: AxisSet | None = None
        if with_axes:
            axes = _open_axes(data["axes"], CLOCKS[clock_name])
            opened.callback(axes.close)
            lines["level3"] = axes.end_of_motion
        crate: CrateMonitor | None = None
        poll = 1.0
        if "crate" in data:
            _check_crate_beside_axes(data["crate"], data.get("axes"))
            crate, poll = _open_crate(data["crate"])
            opened.callback(crate.close)
        hardware = BirisHardware(
            biris=windows["biris"],
            motion=windows.get("motion"),
            coupler=windows["coupler"],
            level2=lines["level2"],
            level3=lines["level3"],
            axes=axes,
            biexec_offset=biexec_offset,
            biris_base=biris_base,
            clock=CLOCKS[clock_name],
            time_scale=1.0,
            pan_journal=pan_journal,
            crate=crate,
            crate_poll_s=poll,
        )
        if homing is not None:
            board = hardware.devices.board
            assert isinstance(board, MotionBoard)  # [homing] with [axes] was refused
            board.set_index(*homing)
        opened.pop_all()
    return hardware


def load_target(path: str | PathLike[str]) -> BirisHardware:
    """Open the target a TOML file describes; the caller closes it (``hardware.close()``).

    A file that cannot be read is the OSError it is; every message about its content starts
    with the file's name and names the key.
    """
    text = Path(path).read_text(encoding="utf-8")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RequestError(f"{path}: not valid TOML: {exc}") from None
    try:
        return target_from_dict(data, Path(path).resolve().parent)
    except RequestError as exc:
        raise RequestError(f"{path}: {exc}") from None
    except BusError as exc:
        raise BusError(f"{path}: {exc}", exc.errno or errno.EIO) from exc
