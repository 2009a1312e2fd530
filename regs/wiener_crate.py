"""A Wiener VME crate's remote control over CAN: identifiers, payload layouts and bit fields.

Both sides of the crate monitor use this module: the driver (:mod:`biris_hw.crate`) and the
simulated crate (:mod:`sim.wiener_crate`). The facts are those of
``reference/transports-and-ecosystem.md`` section 2.4 (the layouts as public EPICS drivers for
these crates use them: read, not copied). Where the facts are open, the line says **Our
reading**: it is what our driver decodes and what our simulated crate sends.

**Identifiers.** Standard (11-bit) CAN ids only: ``(function << 7) | crate_id``, the crate id
1-126 set on the crate's fan tray, the function 0-7 (:class:`Function`). A read is a remote
frame (RTR) from the host with the function's id and dlc 8; the crate answers with a data frame
of the same id and 8 bytes. Function 1 is the one the host writes (:class:`Command`).

**Status** (function 0): byte 0 is :class:`Status0`, byte 1 :class:`Status1`, bytes 2-7 one
channel mask each (bit n = channel n): under-voltage, over-voltage, external temperature,
over-current, over-voltage protection tripped, power-supply temperature. Several bits of byte 0
are *good* when set (no inhibit, no power-supply error, no SYSFAIL): the names say so.

**Channels** (functions 2-5): channels n and n + 4 for n = 0..3, four 16-bit little-endian
words: V(n), I(n), V(n+4), I(n+4), 10 mV and 10 mA per bit. **Our reading**: the words are
two's-complement signed, since crates fit a -12 V channel (the current of a negative rail is
read the same way).

**Fans** (function 6): eight bytes, average speed, nominal speed, then fans 1-6, revolutions
per second (times 60 for rpm). **Temperatures** (function 7): eight sensors, one byte each,
degrees Celsius (**our reading**: unsigned).

**Commands** (function 1, a data frame from the host): crate on, crate off, VME SYSRESET, and
the nominal fan speed (a second byte, 0-64 rps).
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

__all__ = [
    "CHANNELS",
    "CRATE_IDS",
    "FANS",
    "FAN_SPEED_MAX_RPS",
    "FRAME_DLC",
    "HEALTHY_STATUS0",
    "PAIR_FUNCTIONS",
    "READ_FUNCTIONS",
    "SENSORS",
    "Command",
    "CrateReading",
    "Function",
    "Status0",
    "Status1",
    "can_id",
    "check_crate_id",
    "encode_channels",
    "encode_fans",
    "encode_status",
    "encode_temperatures",
    "function_name",
    "split_id",
]

CRATE_IDS = range(1, 127)
"""The crate ids a fan tray can be set to (seven bits; 0 and 127 are not used)."""

CHANNELS = 8
"""Power-supply channels a status mask and the four channel frames cover."""
FANS = 6
"""Fans the fan frame reports one by one."""
SENSORS = 8
"""Temperature sensors of the temperature frame."""
FRAME_DLC = 8
"""Every read request and every answer is 8 bytes long."""
FAN_SPEED_MAX_RPS = 64
"""The highest nominal fan speed the fan-speed command takes."""

_FUNCTION_SHIFT = 7
_CRATE_MASK = 0x7F
_STANDARD_ID_MAX = 0x7FF
_WORD_MIN, _WORD_MAX = -0x8000, 0x7FFF
_UNITS_PER_VOLT = 100
"""Channel words count 10 mV (and 10 mA)."""


class Function(enum.IntEnum):
    """The function field of a crate's CAN id (its upper four bits)."""

    STATUS = 0
    COMMAND = 1
    CHANNELS_0_4 = 2
    CHANNELS_1_5 = 3
    CHANNELS_2_6 = 4
    CHANNELS_3_7 = 5
    FANS = 6
    TEMPERATURES = 7


READ_FUNCTIONS = (
    Function.STATUS,
    Function.CHANNELS_0_4,
    Function.CHANNELS_1_5,
    Function.CHANNELS_2_6,
    Function.CHANNELS_3_7,
    Function.FANS,
    Function.TEMPERATURES,
)
"""The functions a host reads with a remote frame, in the order the monitor reads them."""

PAIR_FUNCTIONS = READ_FUNCTIONS[1:5]
"""The channel frames: ``PAIR_FUNCTIONS[n]`` carries channels n and n + 4."""

_NAMES = {
    Function.STATUS: "status",
    Function.COMMAND: "command",
    Function.CHANNELS_0_4: "channels 0/4",
    Function.CHANNELS_1_5: "channels 1/5",
    Function.CHANNELS_2_6: "channels 2/6",
    Function.CHANNELS_3_7: "channels 3/7",
    Function.FANS: "fans",
    Function.TEMPERATURES: "temperatures",
}


def function_name(function: int) -> str:
    """What ``function`` carries, for messages: ``"fans (function 6)"``."""
    try:
        return f"{_NAMES[Function(function)]} (function {function})"
    except ValueError:
        return f"function {function}"


class Command(enum.IntEnum):
    """First byte of a command frame (function 1)."""

    ON = 0x67
    OFF = 0x65
    SYSRESET = 0x44
    """Pulse VME SYSRESET on the crate's backplane."""
    FAN_SPEED = 0xC0
    """Set the nominal fan speed: the second byte, 0..:data:`FAN_SPEED_MAX_RPS` rps."""


class Status0(enum.IntFlag):
    """Byte 0 of the status frame. The ``NO_`` bits are set when all is well."""

    POWER_ON = 0x01
    NO_INHIBIT = 0x02
    """Clear while the external power inhibit is active."""
    SUPPLY_OK = 0x04
    """Clear on a power fail of the supply."""
    NO_PS_ERROR = 0x08
    """Clear on a power-supply error."""
    FANS_OK = 0x10
    """Clear when a fan is broken."""
    TRIP_ON_FAN_FAILURE = 0x20
    """The crate switches itself off when a fan fails."""
    TRIP_ON_ERROR = 0x40
    """The crate switches itself off on a supply error."""
    NO_SYSFAIL = 0x80
    """Clear while VME SYSFAIL is asserted on the backplane."""


HEALTHY_STATUS0 = (
    Status0.POWER_ON
    | Status0.NO_INHIBIT
    | Status0.SUPPLY_OK
    | Status0.NO_PS_ERROR
    | Status0.FANS_OK
    | Status0.NO_SYSFAIL
)
"""Byte 0 of a crate that is on with nothing wrong (no trip-off enabled)."""


class Status1(enum.IntFlag):
    """Byte 1 of the status frame (bit 0's meaning is not known)."""

    READ_ONLY = 0x02
    """CAN access is read-only: the crate ignores commands."""
    INCOMPATIBLE = 0x04
    """The power supply and the bin do not match."""
    BIN_ERROR = 0x08
    SOFT_START = 0x10
    """The supply is ramping up."""
    EEPROM_CHANGED = 0x20
    CHECKSUM_ERROR = 0x40
    WRITE_PROTECT = 0x80
    """The hardware write protection is on."""


_STATUS1_ALARMS = (
    (Status1.INCOMPATIBLE, "power supply and bin not compatible"),
    (Status1.BIN_ERROR, "bin error"),
    (Status1.CHECKSUM_ERROR, "checksum error"),
)
"""The byte-1 bits that are a problem (the others describe the crate's mode)."""

_MASKS = (
    ("under_voltage", "under-voltage"),
    ("over_voltage", "over-voltage"),
    ("external_temperature", "external over-temperature"),
    ("over_current", "over-current"),
    ("over_voltage_protection", "over-voltage protection tripped"),
    ("supply_temperature", "power-supply over-temperature"),
)
"""Status bytes 2-7 in order: the reading's field, and the alarm's words."""


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def check_crate_id(crate_id: object) -> int:
    """``crate_id`` if it is one of :data:`CRATE_IDS`; ValueError otherwise."""
    if isinstance(crate_id, bool) or not isinstance(crate_id, int) or crate_id not in CRATE_IDS:
        raise ValueError(f"Wiener crate id {crate_id!r} is not 1..126")
    return crate_id


def can_id(function: int, crate_id: int) -> int:
    """The 11-bit id of ``function`` (0-7) of crate ``crate_id`` (:data:`CRATE_IDS`)."""
    if not _is_int(function) or function not in range(len(Function)):
        raise ValueError(f"crate CAN function {function!r} is not 0..7")
    return (int(function) << _FUNCTION_SHIFT) | check_crate_id(crate_id)


def split_id(arbitration_id: int) -> tuple[int, int]:
    """``(function, crate_id)`` of a standard id; ValueError beyond 11 bits. The crate id is not
    checked: a frame of another device on the bus splits as well (and is ignored by its id)."""
    if not _is_int(arbitration_id) or not 0 <= arbitration_id <= _STANDARD_ID_MAX:
        raise ValueError(f"CAN id 0x{arbitration_id:X} is not an 11-bit standard id")
    return arbitration_id >> _FUNCTION_SHIFT, arbitration_id & _CRATE_MASK


def _byte(value: int, what: str) -> int:
    if not _is_int(value) or not 0 <= value <= 0xFF:
        raise ValueError(f"{what} {value!r} is not 0..255")
    return value


def _bytes(values: Sequence[int], count: int, what: str) -> bytes:
    if len(values) != count:
        raise ValueError(f"{what}: {len(values)} values, the frame has {count}")
    return bytes(_byte(v, what) for v in values)


def _word(value: float, what: str) -> int:
    """``value`` (volts or amperes) in 10 mV / 10 mA units, if a signed 16-bit word holds it."""
    if not math.isfinite(value):
        raise ValueError(f"{what} {value!r} is not a number")
    units = round(value * _UNITS_PER_VOLT)
    if not _WORD_MIN <= units <= _WORD_MAX:
        raise ValueError(f"{what} {value!r} is beyond +-327.67 (a signed 16-bit word)")
    return units


# -- encoders (the crate's side: the simulator, and tests) ---------------------------------------


def encode_status(
    *,
    power_on: bool = True,
    inhibit: bool = False,
    supply_ok: bool = True,
    power_supply_error: bool = False,
    fans_ok: bool = True,
    trip_on_fan_failure: bool = False,
    trip_on_error: bool = False,
    sysfail: bool = False,
    status1: int = 0,
    under_voltage: int = 0,
    over_voltage: int = 0,
    external_temperature: int = 0,
    over_current: int = 0,
    over_voltage_protection: int = 0,
    supply_temperature: int = 0,
) -> bytes:
    """The status frame. Arguments say what is *wrong* (``inhibit``, ``sysfail``...) whatever the
    polarity of the bit on the wire; ``status1`` is byte 1 (:class:`Status1`), the masks bytes
    2-7 (bit n = channel n). The defaults are a healthy crate."""
    byte0 = Status0(0)
    for flag, bit in (
        (power_on, Status0.POWER_ON),
        (not inhibit, Status0.NO_INHIBIT),
        (supply_ok, Status0.SUPPLY_OK),
        (not power_supply_error, Status0.NO_PS_ERROR),
        (fans_ok, Status0.FANS_OK),
        (trip_on_fan_failure, Status0.TRIP_ON_FAN_FAILURE),
        (trip_on_error, Status0.TRIP_ON_ERROR),
        (not sysfail, Status0.NO_SYSFAIL),
    ):
        if flag:
            byte0 |= bit
    masks = (
        under_voltage,
        over_voltage,
        external_temperature,
        over_current,
        over_voltage_protection,
        supply_temperature,
    )
    return bytes(
        [int(byte0), int(_byte(status1, "status byte 1"))]
        + [_byte(mask, f"{words} mask") for mask, (_, words) in zip(masks, _MASKS, strict=True)]
    )


def encode_channels(pair_index: int, v_n: float, i_n: float, v_n4: float, i_n4: float) -> bytes:
    """The frame of channels ``pair_index`` (0-3) and ``pair_index + 4`` (it goes out with id
    ``PAIR_FUNCTIONS[pair_index]``), from volts and amperes rounded to 10 mV / 10 mA."""
    if pair_index not in range(4) or isinstance(pair_index, bool):
        raise ValueError(f"channel pair {pair_index!r} is not 0..3")
    n, m = pair_index, pair_index + 4
    return struct.pack(
        "<4h",
        _word(v_n, f"channel {n} voltage"),
        _word(i_n, f"channel {n} current"),
        _word(v_n4, f"channel {m} voltage"),
        _word(i_n4, f"channel {m} current"),
    )


def encode_fans(average_rps: int, nominal_rps: int, fans_rps: Sequence[int]) -> bytes:
    """The fan frame: average and nominal speed, then the :data:`FANS` fans, in rps."""
    return bytes(
        [_byte(average_rps, "average fan speed"), _byte(nominal_rps, "nominal fan speed")]
    ) + _bytes(fans_rps, FANS, "fan speed")


def encode_temperatures(temperatures_c: Sequence[int]) -> bytes:
    """The temperature frame: :data:`SENSORS` sensors, whole degrees Celsius, 0..255."""
    return _bytes(temperatures_c, SENSORS, "temperature")


# -- the reading (the host's side) ----------------------------------------------------------------


@dataclass(frozen=True)
class CrateReading:
    """Everything one pass over the seven read functions told about crate ``crate_id``.

    The flags are what is true (``inhibit`` is the inhibit *active*, ``sysfail`` SYSFAIL
    *asserted*), whatever the bit's polarity; ``status_bytes`` keeps the whole status frame for
    what has no field. The masks have bit n for channel n; tuples are indexed by channel (0-7),
    fan (0-5: fans 1-6) and sensor (0-7). ``read_at`` is the monitor's clock when the last
    answer arrived, so an old reading can be told from a fresh one.
    """

    crate_id: int
    power_on: bool
    inhibit: bool
    supply_ok: bool
    power_supply_error: bool
    fans_ok: bool
    sysfail: bool
    status_bytes: bytes
    under_voltage: int
    over_voltage: int
    external_temperature: int
    over_current: int
    over_voltage_protection: int
    supply_temperature: int
    voltages_v: tuple[float, ...]
    currents_a: tuple[float, ...]
    fan_average_rps: int
    fan_nominal_rps: int
    fans_rps: tuple[int, ...]
    temperatures_c: tuple[int, ...]
    read_at: float

    def __post_init__(self) -> None:
        """Refuse a reading no crate can send, so a bad one built by hand (or from a dict)
        fails where it is made, not where it is shown."""
        check_crate_id(self.crate_id)
        if len(self.status_bytes) != FRAME_DLC:
            raise ValueError(f"status is {len(self.status_bytes)} bytes, not {FRAME_DLC}")
        for name, _ in _MASKS:
            _byte(getattr(self, name), f"{name} mask")
        _byte(self.fan_average_rps, "average fan speed")
        _byte(self.fan_nominal_rps, "nominal fan speed")
        for name, count in (
            ("voltages_v", CHANNELS),
            ("currents_a", CHANNELS),
            ("fans_rps", FANS),
            ("temperatures_c", SENSORS),
        ):
            values = getattr(self, name)
            if len(values) != count:
                raise ValueError(f"{name} has {len(values)} values, not {count}")
        for speed in self.fans_rps:
            _byte(speed, "fan speed")
        for temperature in self.temperatures_c:
            _byte(temperature, "temperature")

    # -- decoding ----------------------------------------------------------------------------------
    @classmethod
    def from_frames(
        cls, crate_id: int, frames: Mapping[int, bytes], read_at: float
    ) -> CrateReading:
        """Decode the answers to :data:`READ_FUNCTIONS`, ``frames[function]`` each 8 bytes;
        ValueError naming the function that is missing or of another length."""
        for function in READ_FUNCTIONS:
            data = frames.get(function)
            if data is None:
                raise ValueError(f"crate {crate_id}: no {function_name(function)} frame")
            if len(data) != FRAME_DLC:
                raise ValueError(
                    f"crate {crate_id}: {function_name(function)} frame is {len(data)} bytes,"
                    f" not {FRAME_DLC}"
                )
        status = bytes(frames[Function.STATUS])
        byte0 = Status0(status[0])
        voltages = [0.0] * CHANNELS
        currents = [0.0] * CHANNELS
        for n, function in enumerate(PAIR_FUNCTIONS):
            v_n, i_n, v_m, i_m = struct.unpack("<4h", frames[function])
            voltages[n], currents[n] = v_n / _UNITS_PER_VOLT, i_n / _UNITS_PER_VOLT
            voltages[n + 4], currents[n + 4] = v_m / _UNITS_PER_VOLT, i_m / _UNITS_PER_VOLT
        fans = bytes(frames[Function.FANS])
        return cls(
            crate_id=crate_id,
            power_on=Status0.POWER_ON in byte0,
            inhibit=Status0.NO_INHIBIT not in byte0,
            supply_ok=Status0.SUPPLY_OK in byte0,
            power_supply_error=Status0.NO_PS_ERROR not in byte0,
            fans_ok=Status0.FANS_OK in byte0,
            sysfail=Status0.NO_SYSFAIL not in byte0,
            status_bytes=status,
            under_voltage=status[2],
            over_voltage=status[3],
            external_temperature=status[4],
            over_current=status[5],
            over_voltage_protection=status[6],
            supply_temperature=status[7],
            voltages_v=tuple(voltages),
            currents_a=tuple(currents),
            fan_average_rps=fans[0],
            fan_nominal_rps=fans[1],
            fans_rps=tuple(fans[2:]),
            temperatures_c=tuple(bytes(frames[Function.TEMPERATURES])),
            read_at=read_at,
        )

    # -- judging -----------------------------------------------------------------------------------
    @property
    def status1(self) -> Status1:
        """Byte 1 of the status frame (read-only access, soft start, write protection...)."""
        return Status1(self.status_bytes[1])

    def alarms(self) -> tuple[str, ...]:
        """One short sentence per problem, worst first; empty for a healthy crate.

        A crate switched off is a problem here: the sensor in it is not running. The byte-1
        bits that only describe a mode (read-only access, soft start, write protection, EEPROM
        changed) are not alarms."""
        found: list[str] = []
        if not self.power_on:
            found.append("crate power is off")
        if self.inhibit:
            found.append("external power inhibit is active")
        if not self.supply_ok:
            found.append("power supply reports a power fail")
        if self.power_supply_error:
            found.append("power-supply error")
        if not self.fans_ok:
            found.append("fan failure")
        if self.sysfail:
            found.append("VME SYSFAIL is asserted")
        for name, words in _MASKS:
            mask = getattr(self, name)
            found.extend(f"{words} on channel {n}" for n in range(CHANNELS) if mask >> n & 1)
        status1 = self.status1
        found.extend(words for bit, words in _STATUS1_ALARMS if bit in status1)
        return tuple(found)

    @property
    def ok(self) -> bool:
        """No alarm."""
        return not self.alarms()

    def fitted(self) -> tuple[tuple[int, float, float], ...]:
        """``(channel, volts, amps)`` of each channel that delivers anything: a channel not
        fitted reads 0 V and 0 A, and a display that lists it only adds noise."""
        return tuple(
            (n, volts, amps)
            for n, (volts, amps) in enumerate(zip(self.voltages_v, self.currents_a, strict=True))
            if volts or amps
        )

    # -- across processes --------------------------------------------------------------------------
    def to_dict(self) -> dict[str, object]:
        """JSON-ready: lists for tuples, ``status_bytes`` as 16 hex digits, and the derived
        ``ok`` and ``alarms`` for a reader without this class (:meth:`from_dict` recomputes
        them rather than trust them)."""
        d: dict[str, object] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bytes):
                value = value.hex()
            elif isinstance(value, tuple):
                value = list(value)
            d[f.name] = value
        d["ok"] = self.ok
        d["alarms"] = list(self.alarms())
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CrateReading:
        """The reading :meth:`to_dict` made; ValueError on a missing key or a value of the wrong
        type or size. Keys it does not know are ignored (a newer sender's additions)."""
        if not isinstance(d, Mapping):
            raise ValueError(f"a crate reading is a mapping, not {type(d).__name__}")
        missing = [f.name for f in fields(cls) if f.name not in d]
        if missing:
            raise ValueError(f"crate reading without {', '.join(missing)}")
        values: dict[str, Any] = {}
        for f in fields(cls):
            value = d[f.name]
            if f.type == "bool":
                if not isinstance(value, bool):
                    raise ValueError(f"crate reading: {f.name} {value!r} is not a bool")
            elif f.type == "int":
                _check_int(value, f.name)
            elif f.type == "float":
                value = _number(value, f.name)
            elif f.type == "bytes":
                if not isinstance(value, str):
                    raise ValueError(f"crate reading: {f.name} {value!r} is not a hex string")
                try:
                    value = bytes.fromhex(value)
                except ValueError:
                    raise ValueError(f"crate reading: {f.name} {value!r} is not hex") from None
            elif f.type == "tuple[float, ...]":
                value = tuple(_number(v, f.name) for v in _list(value, f.name))
            else:  # tuple[int, ...]
                value = tuple(_check_int(v, f.name) for v in _list(value, f.name))
            values[f.name] = value
        return cls(**values)


def _check_int(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"crate reading: {name} {value!r} is not an integer")
    return value


def _number(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"crate reading: {name} {value!r} is not a number")
    return float(value)


def _list(value: object, name: str) -> list[object]:
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"crate reading: {name} {value!r} is not a list")
    return list(value)
