"""The server initialisation record (report, Appendices A and B) and the motor's parameters.

Harmony servers take every application-specific number from one compact record so that adapting a
server means editing one file, not the code; we keep that idea and make the file TOML. The
defaults are Appendix B's example, so ``BirisInitRecord()`` is the report's configured server.

Every value is checked when a record is made, however it is made (code, dict, file), and a bad one
raises :class:`~biris_hw.errors.RequestError` naming the key: a server must never start half
configured, and the motor controller must never receive a register value that does not fit.
"""

from __future__ import annotations

import operator
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from os import PathLike
from pathlib import Path
from typing import Any, ClassVar

from biris_hw.angles import exact_real, shown
from biris_hw.errors import RequestError
from biris_hw.geometry import Mount
from regs.hctl1000 import F_CLK_HZ, MOTION_LIMIT_COUNTS, accel_from_reg, sample_period

if sys.version_info >= (3, 11):
    import tomllib
else:  # tomli is a declared dependency below 3.11
    import tomli as tomllib  # type: ignore[import-not-found, unused-ignore]

__all__ = [
    "BirisInitRecord",
    "MotorParams",
    "acq_rate_counts_per_acq",
    "acquisitions_for",
]

MAX_CPU = 1023
"""The highest CPU number ``cpus`` accepts (Linux's default CPU set size is 1024)."""

MAX_HOME_REVS = 2.0
"""The most ``home_index_timeout_revs`` may be: homing searches half of it either way from where
it starts, and more than one revolution either way could wind the cable."""


def _int_field(key: str, value: object, lo: int, hi: int, *, zero: str | None = None) -> int:
    """A whole number in lo..hi; numpy integers pass, bools and floats do not (1.5 is no count).

    ``zero`` says why 0 is refused, where it fits the register but can never work: that reason
    is worth more to the caller than the bare range.
    """
    if isinstance(value, bool):
        raise RequestError(f"{key}: must be an integer, not a bool")
    try:
        number = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise RequestError(f"{key}: must be an integer, not {type(value).__name__}") from None
    if number == 0 and zero is not None:
        raise RequestError(f"{key}: 0 {zero}; use {lo}..{hi}")
    if not lo <= number <= hi:
        raise RequestError(f"{key}: must be in {lo}..{hi} (0x{hi:X} at most), not {shown(number)}")
    return number


def _float_field(
    key: str, value: object, *, positive: bool = False, at_most: float | None = None
) -> float:
    """A finite float from any real number type (TOML writes ``4`` as readily as ``4.0``, and
    code may hand over a numpy scalar); a value beyond a float's range is refused, not rounded
    to infinity."""
    exact = exact_real(value, key)
    try:
        number = float(exact)
    except OverflowError:
        raise RequestError(f"{key}: must be a finite number, not {shown(value)}") from None
    if positive and number <= 0.0:
        raise RequestError(f"{key}: must be a positive finite number, not {shown(value)}")
    if at_most is not None and number > at_most:
        raise RequestError(f"{key}: must be {at_most:g} at most, not {shown(value)}")
    return number


def _bool_field(key: str, value: object) -> bool:
    """A switch: TOML's true/false or Python's bool; 0 and 1 are refused, since a number in a
    switch's place is more likely a key put in the wrong place than a switch."""
    if not isinstance(value, bool):
        raise RequestError(f"{key}: must be true or false, not {type(value).__name__}")
    return value


def _name_field(key: str, value: object) -> str:
    """Text for a C ``char[32]``: 1..31 printable ASCII characters plus the NUL BIRIS adds."""
    if not isinstance(value, str):
        raise RequestError(f"{key}: must be a string, not {type(value).__name__}")
    if not 1 <= len(value) <= 31 or not (value.isascii() and value.isprintable()):
        raise RequestError(f"{key}: must be 1..31 printable ASCII characters, not {value!r}")
    return value


def _tuple_field(key: str, value: object, length: int) -> tuple[object, ...]:
    """A fixed-length sequence (TOML arrays arrive as lists) as a tuple; strings are refused."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (tuple, list)):
        raise RequestError(f"{key}: must be a sequence of {length} values, not {value!r}")
    if len(value) != length:
        raise RequestError(f"{key}: must have {length} values, not {len(value)}")
    return tuple(value)


@dataclass(frozen=True)
class MotorParams:
    """The HCTL-1000's operating parameters, Appendix B's vector and order.

    ``sample`` is the sample timer (R0FH), ``zero``/``pole``/``gain`` the digital filter's A, B
    and K (R20H..R22H), ``max_vel`` the trapezoid's maximum velocity in counts per sample (R28H)
    and ``max_accel`` its acceleration in 8.8 fixed-point counts per sample squared (R26H/R27H).
    They are kept as the raw register values the chip takes, so what the server writes is exactly
    what the record says; the properties give the physical meaning.

    Every field is a whole number of any integer type (numpy's too) within its register. A zero
    ``gain``, ``max_vel`` or ``max_accel`` fits its register but can never move the head (no
    torque; a profile that never leaves its start), and is refused here, up front: accepted, it
    would surface only later, as a scan that "completes" with the head standing still or as a
    motor stall.

    Raises:
        RequestError: a field that is not an integer (bools and floats included), outside its
            register, or zero where zero never moves the head; the message names the field.
    """

    sample: int = 0xAF
    zero: int = 0x7F
    pole: int = 0xEF
    gain: int = 0x3F
    max_vel: int = 0x2
    max_accel: int = 0x3322

    _LIMITS: ClassVar[Mapping[str, int]] = {
        "sample": 0xFF,
        "zero": 0xFF,
        "pole": 0xFF,
        "gain": 0xFF,
        "max_vel": 0x7F,
        "max_accel": 0x7FFF,
    }

    _CANNOT_MOVE: ClassVar[Mapping[str, str]] = {
        "gain": "is no gain: the motor gets no torque, so the head can never move",
        "max_vel": "counts per sample is a profile that never leaves its start, "
        "so the head can never move",
        "max_accel": "is a profile that never speeds up, so the head can never move",
    }
    """Why 0 is refused for these fields: each would leave the head standing still."""

    def __post_init__(self) -> None:
        for name, hi in self._LIMITS.items():
            why = self._CANNOT_MOVE.get(name)
            value = _int_field(name, getattr(self, name), 0 if why is None else 1, hi, zero=why)
            object.__setattr__(self, name, value)

    @property
    def sample_period_s(self) -> float:
        """Seconds per control sample, 16 (T + 1) / f_clk at the board's chip clock."""
        return sample_period(self.sample, F_CLK_HZ)

    @property
    def max_velocity_counts_per_s(self) -> float:
        """The trapezoid's cruise speed in encoder counts per second."""
        return self.max_vel / self.sample_period_s

    @property
    def accel_counts_per_s2(self) -> float:
        """The trapezoid's acceleration in encoder counts per second squared."""
        return accel_from_reg(self.max_accel) / self.sample_period_s**2

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> MotorParams:
        """From a mapping such as a TOML ``[motor]`` table; missing keys keep their defaults."""
        if not isinstance(data, Mapping):
            raise RequestError(f"motor: must be a table, not {type(data).__name__}")
        for key in data:
            if key not in cls._LIMITS:
                raise RequestError(f"motor: unknown key {key!r} (known: {', '.join(cls._LIMITS)})")
        return cls(**data)

    def to_dict(self) -> dict[str, int]:
        """Plain register values, in Appendix B's order."""
        return {name: getattr(self, name) for name in self._LIMITS}


@dataclass(frozen=True)
class BirisInitRecord:
    """Everything the server needs at start-up (Appendix A's BIRIS_INIT_REC, Appendix B's values).

    ``name`` is the server's registered name and ``boot_file`` the file on BIRIS's RAMdisk that
    the supervisor boots from (both C ``char[32]``). ``data_rate_ms`` is BIRIS_DATA_RATE, the time
    between acquisitions; ``max_range`` is BIRIS_MAX_RANGE, beyond which samples are discarded.

    Beyond the report (later features, harmless defaults): ``timeout_s`` is the BIRIS timeout in
    hardware seconds, and ``timeout_enabled`` whether it runs from start-up (on by default, so a
    BIRIS that hangs is a fault rather than a scan that never ends; BIRIS_TIMEOUT_ENABLE and
    BIRIS_TIMEOUT_DISABLE still switch it at run time); ``home_index_timeout_revs`` how far homing
    may turn looking for the zero index before it gives up (above 0, at most 2: a search beyond
    one revolution either way from where it starts could wind the cable);
    ``continuous_acquisition`` selects Appendix D's continuous mode; ``elevation_limits_counts``
    bounds the tilt axis and ``elevation_motor`` tunes its HCTL-1000 (None: the pan's ``motor``,
    as the report's single set served both; a tilt carries another load, so it may want its own
    filter and profile); ``mount_offset_m`` places the pan axis in the vehicle frame (x, y, z);
    ``head_height_m`` is the optical centre's height up the pan axis from that point and
    ``head_offset_m`` its distance out from the pan axis along the azimuth (the simulator's head:
    0.5 m and 0). :attr:`mount` gathers the three for :mod:`biris_hw.geometry`. ``cpus`` (Linux)
    keeps every server thread on those CPUs; empty, the default, leaves them to the scheduler (see
    :mod:`biris_hw.affinity` for why one might not).

    Numbers may be of any real type (numpy's scalars too); whole-number fields take integers
    only. A motor table holding a zero gain, max_vel or max_accel is refused (see
    :class:`MotorParams`).

    The report's eight task indices are Harmony globals, not configuration: the record does not
    carry them.
    """

    name: str = "BIRISSERV:"
    boot_file: str = "/dd/users/biris/binitlal.par"
    motor: MotorParams = field(default_factory=MotorParams)
    data_rate_ms: int = 30
    max_range: int = 0x7FFF
    timeout_s: float = 4.0
    timeout_enabled: bool = True
    home_index_timeout_revs: float = 1.0
    continuous_acquisition: bool = False
    elevation_limits_counts: tuple[int, int] = (-512, 512)
    elevation_motor: MotorParams | None = None
    mount_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    head_height_m: float = 0.5
    head_offset_m: float = 0.0
    cpus: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        def put(key: str, value: object) -> None:
            object.__setattr__(self, key, value)

        put("name", _name_field("name", self.name))
        put("boot_file", _name_field("boot_file", self.boot_file))
        if not isinstance(self.motor, MotorParams):
            raise RequestError(f"motor: must be MotorParams, not {type(self.motor).__name__}")
        put("data_rate_ms", _int_field("data_rate_ms", self.data_rate_ms, 1, 0x7FFF))
        put("max_range", _int_field("max_range", self.max_range, 1, 0xFFFF))
        put("timeout_s", _float_field("timeout_s", self.timeout_s, positive=True))
        put("timeout_enabled", _bool_field("timeout_enabled", self.timeout_enabled))
        key = "home_index_timeout_revs"
        revs = _float_field(key, self.home_index_timeout_revs, positive=True, at_most=MAX_HOME_REVS)
        put(key, revs)
        put(
            "continuous_acquisition",
            _bool_field("continuous_acquisition", self.continuous_acquisition),
        )
        if self.elevation_motor is not None and not isinstance(self.elevation_motor, MotorParams):
            raise RequestError(
                "elevation_motor: must be MotorParams or None, "
                f"not {type(self.elevation_motor).__name__}"
            )
        key = "elevation_limits_counts"
        lo, hi = (
            _int_field(key, v, -MOTION_LIMIT_COUNTS, MOTION_LIMIT_COUNTS)
            for v in _tuple_field(key, self.elevation_limits_counts, 2)
        )
        if lo > hi:
            raise RequestError(f"{key}: the lower limit {lo} is above the upper limit {hi}")
        put(key, (lo, hi))
        key = "mount_offset_m"
        x, y, z = (_float_field(key, v) for v in _tuple_field(key, self.mount_offset_m, 3))
        put(key, (x, y, z))
        put("head_height_m", _float_field("head_height_m", self.head_height_m))
        put("head_offset_m", _float_field("head_offset_m", self.head_offset_m))
        cpus: object = self.cpus  # whatever the caller passed: checked here
        if not isinstance(cpus, (tuple, list)):
            raise RequestError(f"cpus: must be a sequence of CPU numbers, not {cpus!r}")
        numbers = tuple(_int_field("cpus", cpu, 0, MAX_CPU) for cpu in cpus)
        if len(set(numbers)) != len(numbers):
            raise RequestError(f"cpus: names a CPU twice: {list(numbers)}")
        put("cpus", numbers)

    @property
    def tilt_motor(self) -> MotorParams:
        """The tilt axis's parameters: ``elevation_motor``, or the pan's when it is None."""
        return self.elevation_motor if self.elevation_motor is not None else self.motor

    @property
    def mount(self) -> Mount:
        """The head's place on the vehicle, as scans and points carry it."""
        return Mount(self.mount_offset_m, self.head_height_m, self.head_offset_m)

    # -- dicts and TOML ------------------------------------------------------------------------

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> BirisInitRecord:
        """From plain data (a parsed TOML document); missing keys keep their defaults."""
        if not isinstance(data, Mapping):
            raise RequestError(f"an init record must be a table, not {type(data).__name__}")
        known = [f.name for f in fields(cls)]
        for key in data:
            if key not in known:
                raise RequestError(f"unknown key {key!r} (known: {', '.join(known)})")
        values = dict(data)
        for key in ("motor", "elevation_motor"):
            if key in values and not isinstance(values[key], (MotorParams, type(None))):
                try:
                    values[key] = MotorParams.from_dict(values[key])
                except RequestError as exc:  # name the table the field is in
                    message = str(exc)
                    if message.startswith("motor"):
                        message = key + message[len("motor") :]
                    else:
                        message = f"{key}.{message}"
                    raise RequestError(message) from None
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """Plain data (lists for tuples, a dict for the motor) that :meth:`from_dict` reads back."""
        data: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue  # TOML has no null: an absent key reads back as the default, None
            if isinstance(value, MotorParams):
                value = value.to_dict()
            elif isinstance(value, tuple):
                value = list(value)
            data[f.name] = value
        return data

    @classmethod
    def from_toml(cls, text: str) -> BirisInitRecord:
        """Parse a TOML document; syntax errors are RequestErrors too."""
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise RequestError(f"init record is not valid TOML: {exc}") from None
        return cls.from_dict(data)

    def to_toml(self) -> str:
        """TOML text; the ``[motor]`` table in hex, as the report writes those registers.

        Needs the optional ``toml`` extra (tomli-w) for everything but the motor table, whose
        hex integers tomli-w cannot write.
        """
        try:
            import tomli_w
        except ImportError as exc:
            raise ModuleNotFoundError(
                "writing an init record needs tomli-w, the 'toml' extra: "
                "pip install 'biris-hw[toml]'",
                name="tomli_w",
            ) from exc
        data = self.to_dict()
        motor = data.pop("motor")
        tilt = data.pop("elevation_motor", None)
        lines = [
            "# BIRIS server initialisation record (NRC report 1992, Appendices A and B).",
            str(tomli_w.dumps(data)).rstrip("\n"),
            "",
            "# HCTL-1000 registers: sample timer, filter zero/pole/gain, max velocity (counts/",
            "# sample), acceleration (8.8 counts/sample^2). Appendix B: {0xAF, 0x7F, 0xEF, 0x3F,",
            "# 0x2, 0x3322}.",
            "[motor]",
        ]
        lines += _hex_table(motor)
        if tilt is not None:
            lines += [
                "",
                "# The tilt axis's HCTL-1000, when it is tuned apart.",
                "[elevation_motor]",
            ]
            lines += _hex_table(tilt)
        return "\n".join(lines) + "\n"

    @classmethod
    def load(cls, path: str | PathLike[str]) -> BirisInitRecord:
        """Read a TOML file; a missing file is the OSError it is, a bad one a RequestError."""
        text = Path(path).read_text(encoding="utf-8")
        try:
            return cls.from_toml(text)
        except RequestError as exc:
            raise RequestError(f"{path}: {exc}") from None

    def save(self, path: str | PathLike[str]) -> None:
        """Write :meth:`to_toml` to ``path`` (needs the ``toml`` extra)."""
        Path(path).write_text(self.to_toml(), encoding="utf-8")


def _hex_table(motor: Mapping[str, int]) -> list[str]:
    """A motor table's lines, in hex as the report writes those registers."""
    return [f"{key} = 0x{value:0{4 if key == 'max_accel' else 2}X}" for key, value in motor.items()]


def acq_rate_counts_per_acq(record: BirisInitRecord) -> float:
    """The report's _Get_acq_rate(): encoder counts the head turns during one acquisition.

    Maximum velocity (counts per sample) over the sample period, times BIRIS_DATA_RATE. About
    42.6 counts (3.7 degrees) for Appendix B's record. The report says this constant is below 1
    and uses its reciprocal to avoid floats; that holds for acquisitions per count, the reciprocal
    of what its text (and docs/design.md) defines, so we return counts per acquisition as defined.
    """
    return record.motor.max_velocity_counts_per_s * record.data_rate_ms / 1000.0


def acquisitions_for(scan_counts: int, record: BirisInitRecord) -> int:
    """The report's count of acquisitions for a scan of ``scan_counts`` (``_Get_acq_rate()``).

    scan length / :func:`acq_rate_counts_per_acq`, rounded *up*; at least 1 for any non-zero
    scan, 0 for none. The server no longer counts with it: it ignores BIRIS's start-up and the
    real acquisition period (whole video fields), so a scan counted so misses its start and
    stands at its end; :mod:`biris_hw.server.scan_timing` counts from the trapezoid instead.
    The sign of ``scan_counts`` (the direction) does not matter. Like the report, this ignores the
    trapezoid's ramps: at the default acceleration the head reaches speed within one sample.
    Computed in exact integers, so an exact multiple of the rate does not gain a spurious extra
    acquisition from float rounding.
    """
    counts = abs(_int_field("scan_counts", scan_counts, -(1 << 62), 1 << 62))
    if counts == 0:
        return 0
    motor = record.motor  # max_vel >= 1: MotorParams refuses a motor that cannot move
    # counts / (max_vel / (16 (T + 1) / f_clk) * rate_ms / 1000), kept as one integer fraction.
    numerator = counts * 16 * (motor.sample + 1) * 1000
    denominator = motor.max_vel * record.data_rate_ms * F_CLK_HZ
    return max(1, -(-numerator // denominator))
