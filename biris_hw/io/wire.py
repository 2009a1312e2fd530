"""The payload codec shared by the network service and recordings: ROS 2 messages in CDR.

A scan that crosses the network or lands in a file must come back *equal*: the same ``seq``, the
same int16 samples, the same float64 hardware times, the same drop count. A home-made byte layout
would do that too, but nobody else could read it; ROS 2 message types serialised as CDR (the
encoding of every ROS 2 transport and of ``ros2 bag``'s MCAP files) are self-describing through
their ``.msg`` text, so a C++ or Rust client, Foxglove, Lichtblick or ``ros2 bag`` decodes them
with nothing from this package. The definitions are module constants (:data:`MSG_DEFINITIONS`),
registered into a rosbags typestore built from ROS 2 Humble's standard types (for
``std_msgs/msg/Header``), and documented in ``docs/wire-format.md``.

Why custom types and not ``sensor_msgs/LaserScan``: a LaserScan holds float32 metres of one
profile; a BIRIS scan is an int16 ``(n_acq, samples)`` grid with per-acquisition azimuths and
times, and converting would lose exactly what a lossless recording must keep. Standard views
(LaserScan, PointCloud2) are the business of :mod:`biris_hw.io.ros2`, derived from these.

Conventions: optional values travel as a value plus a ``has_*`` flag (CDR has no null); a 2-D
array is flattened row-major with its row and column counts beside it; ``std_msgs/Header`` stamps
carry hardware-clock time (seconds since the target's clock started), frame ``biris``.

Every decoding failure -- truncated, garbage, a wrong type, values a ``Scan`` refuses, an
oversized payload -- is a :class:`WireError`: bytes from the network are never trusted, and a
caller must be able to catch one error, not whatever the CDR parser happened to trip over.
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from biris_hw.data import Direction, Point, Scan
from biris_hw.errors import BirisError, HardwareFault
from biris_hw.geometry import Mount
from biris_hw.status import ConnectionStatus, ServerState, ServerStatus
from regs.wiener_crate import CrateReading

__all__ = [
    "FAULT",
    "FRAME_ID",
    "MAX_PAYLOAD",
    "MSG_DEFINITIONS",
    "POINT",
    "SCAN",
    "STATUS",
    "WireError",
    "decode_fault",
    "decode_point",
    "decode_scan",
    "decode_status",
    "encode_fault",
    "encode_point",
    "encode_scan",
    "encode_status",
    "full_definition",
    "typestore",
]


class WireError(BirisError, ValueError):
    """Bytes that are not a valid payload of the type asked for (or a value that cannot be
    encoded); nothing was delivered. A ``ValueError`` too, as for any malformed input."""


MAX_PAYLOAD = 64 * 1024 * 1024
"""Largest payload :func:`decode_scan` and friends accept (bytes). A 128-sample scan of 4096
acquisitions is about 2.2 MB; anything near this limit is an attack or a bug, and refusing it
before parsing keeps a bad sender from making us allocate what it claims."""

FRAME_ID = "biris"
"""``header.frame_id`` of every message: the sensor frame (see :mod:`biris_hw.geometry`)."""

MOUNT = "biris_msgs/msg/Mount"
SCAN = "biris_msgs/msg/Scan"
POINT = "biris_msgs/msg/Point"
LATENCY = "biris_msgs/msg/Latency"
COUNTER = "biris_msgs/msg/Counter"
CONNECTION = "biris_msgs/msg/ConnectionStatus"
CRATE = "biris_msgs/msg/CrateStatus"
STATUS = "biris_msgs/msg/Status"
FAULT = "biris_msgs/msg/Fault"

MSG_DEFINITIONS: dict[str, str] = {
    MOUNT: """\
# Where the head sits on the vehicle (biris_hw.geometry.Mount).
float64[3] offset_m
float64 head_height_m
float64 head_offset_m
""",
    SCAN: """\
# One sweep's data, as the server buffered it (biris_hw.data.Scan), losslessly.
# header.stamp: hardware time of the newest acquisition (t[n_acq-1]), or 0 when empty.
std_msgs/Header header
uint8 DIRECTION_CW=0
uint8 DIRECTION_CCW=1
uint8 direction
uint64 seq
# acquisitions (rows) and samples per acquisition (columns) of range_mm and intensity
uint32 n_acq
uint32 samples
int32[] azimuth
# row-major, n_acq * samples; 0 = no return or discarded
int16[] range_mm
int16[] closest_mm
int16[] intensity
# hardware-clock seconds of each acquisition
float64[] t
uint64 dropped
int32 elevation
bool has_t_delivered
float64 t_delivered
bool has_mount
biris_msgs/Mount mount
# "single" or "continuous"
string acquisition
# true when the scan does not cover its requested span; partial_reason says why ("" if whole)
bool partial
string partial_reason
# the span the scan was asked to cover, in counts: where the head stood when it began, and the
# requested end (has_span false: not known)
bool has_span
int32 span_start
int32 span_destination
""",
    POINT: """\
# One acquisition (biris_hw.data.Point), losslessly.
# header.stamp: hardware time of the acquisition (t).
std_msgs/Header header
int32 azimuth
int32 range_mm
int16[] profile
int16[] intensity
float64 t
uint64 acq
uint64 scan_seq
int32 elevation
bool has_t_delivered
float64 t_delivered
bool has_mount
biris_msgs/Mount mount
string acquisition
""",
    LATENCY: """\
# Delivery latency of one connection; NaN stands for "no value yet".
uint64 count
float64 mean
float64 max
float64 p50
float64 p99
# histogram bins: [low_s, high_s) and the deliveries in each (non-empty bins only)
float64[] bin_low_s
float64[] bin_high_s
uint64[] bin_count
""",
    COUNTER: """\
string name
int64 value
""",
    CONNECTION: """\
uint64 ident
string kind
string policy
uint64 depth
uint64 queued
uint64 delivered
uint64 dropped
biris_msgs/Latency latency
""",
    CRATE: """\
# A Wiener VME crate's reading over CAN (regs.wiener_crate.CrateReading).
uint8 crate_id
bool power_on
# external power inhibit active
bool inhibit
bool supply_ok
bool power_supply_error
bool fans_ok
# VME SYSFAIL asserted
bool sysfail
# the crate's 8 raw status bytes
uint8[8] status_bytes
# channel masks, bit n = supply channel n
uint8 under_voltage
uint8 over_voltage
uint8 external_temperature
uint8 over_current
uint8 over_voltage_protection
uint8 supply_temperature
float64[8] voltages_v
float64[8] currents_a
# revolutions per second
uint8 fan_average_rps
uint8 fan_nominal_rps
uint8[6] fans_rps
uint8[8] temperatures_c
# the reading's time on the host that polled the crate (seconds)
float64 read_at
""",
    STATUS: """\
# What the server is doing and has done (biris_hw.status.ServerStatus).
std_msgs/Header header
# initialising, idle, homing, tilting, scanning, busy, fault
string state
# the fault's kind while state is "fault", else empty
string fault
int32 azimuth
int32 elevation
bool has_calibration
int32 calibration
bool continuous
string acquisition
string ring
biris_msgs/Counter[] counters
biris_msgs/ConnectionStatus[] connections
biris_msgs/Counter[] interrupts
bool has_azimuth_live
int32 azimuth_live
bool has_elevation_live
int32 elevation_live
uint64 acquisitions_in_progress
# the acquisition mode asked for and not yet in force, else empty
string acquisition_pending
# the server's tasks that failed and wait for the next reset; failures per task so far
string[] tasks_down
biris_msgs/Counter[] task_failures
# the VME crate's last reading, when the sensor has a crate monitor
bool has_crate
biris_msgs/CrateStatus crate
# why the crate's last poll failed, else empty
string crate_error
""",
    FAULT: """\
# A hardware fault the server reported (biris_hw.errors.HardwareFault).
# header.stamp: hardware time at which the service saw it.
std_msgs/Header header
# timeout, bus, parity, motor_stall, protocol, internal
string kind
string message
""",
}
"""msgtype -> its ``.msg`` text (what an MCAP ``ros2msg`` schema or a ROS 2 package holds).
Each text names its own fields only; :func:`full_definition` appends the types it uses."""

_V1_END = "bool partial\n"
_SCAN_V1 = MSG_DEFINITIONS[SCAN][: MSG_DEFINITIONS[SCAN].index(_V1_END) + len(_V1_END)]
"""``biris_msgs/msg/Scan`` as written before ``partial_reason`` and ``span`` were appended: the
current definition up to ``bool partial``, its last field then. Recordings made before hold it,
and :func:`decode_scan` still reads them. Fields are only ever appended, so that the old layout
stays a prefix of the new one and a payload tells which it is by where it ends."""

_FAULT_KINDS = ("timeout", "bus", "parity", "motor_stall", "protocol", "internal")


@functools.cache
def typestore() -> Typestore:
    """A rosbags typestore of ROS 2 Humble's types with the ``biris_msgs`` types registered.

    Cached: building it parses every standard definition, which costs tens of milliseconds.
    """
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name, text in MSG_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@functools.cache
def _legacy_typestore() -> Typestore:
    """A typestore in which ``biris_msgs/msg/Scan`` has its first definition (:data:`_SCAN_V1`):
    a store of its own, since one store holds one definition per name."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name in (MOUNT, SCAN):
        types.update(get_types_from_msg(_SCAN_V1 if name == SCAN else MSG_DEFINITIONS[name], name))
    store.register(types)
    return store


def full_definition(msgtype: str) -> str:
    """``msgtype``'s definition with those of every type it uses appended (``=====`` and
    ``MSG: pkg/msg/Type`` separators): what an MCAP ``ros2msg`` schema's data must be."""
    text, _ = typestore().generate_msgdef(msgtype, ros_version=2)
    return text


# -- helpers ---------------------------------------------------------------------------------------


def _cls(name: str) -> Any:
    return typestore().types[name]


def _header(t: float) -> Any:
    """A Header stamped with hardware time ``t`` (clamped into Time's range; 0 if not finite)."""
    store = typestore()
    if not math.isfinite(t) or t < 0:
        t = 0.0
    if t >= 2**31 - 1:  # beyond int32 seconds (68 years): the stamp saturates, t stays exact
        sec, nanosec = 2**31 - 1, 0
    else:
        sec = int(t)
        nanosec = min(round((t - sec) * 1e9), 999_999_999)
    stamp = store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    return store.types["std_msgs/msg/Header"](stamp=stamp, frame_id=FRAME_ID)


def _mount(mount: Mount | None) -> Any:
    if mount is None:
        return _cls(MOUNT)(offset_m=np.zeros(3), head_height_m=0.0, head_offset_m=0.0)
    return _cls(MOUNT)(
        offset_m=np.array(mount.offset_m, dtype=np.float64),
        head_height_m=mount.head_height_m,
        head_offset_m=mount.head_offset_m,
    )


def _unmount(has: bool, msg: Any) -> Mount | None:
    if not has:
        return None
    return Mount(
        offset_m=tuple(float(v) for v in msg.offset_m),  # type: ignore[arg-type]
        head_height_m=float(msg.head_height_m),
        head_offset_m=float(msg.head_offset_m),
    )


def _serialize(msg: Any, msgtype: str) -> bytes:
    try:
        return bytes(typestore().serialize_cdr(msg, msgtype))
    except (OverflowError, ValueError, TypeError, struct.error) as exc:  # outside a CDR type
        raise WireError(f"cannot encode {msgtype}: {exc}") from exc


def _deserialize(
    data: bytes | bytearray | memoryview, msgtype: str, store: Typestore | None = None
) -> Any:
    """Parse ``data`` as ``msgtype`` (in ``store``, by default :func:`typestore`);
    :class:`WireError` for anything but one whole message."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError(f"{msgtype}: payload must be bytes, not {type(data).__name__}")
    raw = bytes(data)
    if len(raw) > MAX_PAYLOAD:
        raise WireError(f"{msgtype}: payload of {len(raw)} bytes exceeds {MAX_PAYLOAD}")
    if len(raw) < 4 or raw[0] != 0 or raw[1] not in (0, 1):
        raise WireError(f"{msgtype}: not a CDR payload (bad encapsulation header)")
    try:
        # rosbags checks that the message ends where the bytes do (save CDR's alignment pad)
        return (store or typestore()).deserialize_cdr(raw, msgtype)
    except Exception as exc:  # the parser's failure modes are not ours to list
        raise WireError(f"{msgtype}: malformed payload ({type(exc).__name__}: {exc})") from exc


def _optional(has: bool, value: float) -> float | None:
    return float(value) if has else None


def _nan_none(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _none_nan(value: float) -> float | None:
    return None if math.isnan(value) else float(value)


def _array(values: Any, dtype: type[np.generic]) -> NDArray[Any]:
    return np.ascontiguousarray(values, dtype=dtype)


# -- Scan and Point --------------------------------------------------------------------------------


def encode_scan(scan: Scan) -> bytes:
    """``scan`` as a CDR ``biris_msgs/msg/Scan`` (little-endian)."""
    if not isinstance(scan, Scan):
        raise WireError(f"encode_scan takes a Scan, not {type(scan).__name__}")
    n_acq, samples = scan.range_mm.shape
    msg = _cls(SCAN)(
        header=_header(float(scan.t[-1]) if n_acq else 0.0),
        direction=int(scan.direction),
        seq=scan.seq,
        n_acq=n_acq,
        samples=samples,
        azimuth=_array(scan.azimuth, np.int32),
        range_mm=_array(scan.range_mm, np.int16).reshape(-1),
        closest_mm=_array(scan.closest_mm, np.int16),
        intensity=_array(scan.intensity, np.int16).reshape(-1),
        t=_array(scan.t, np.float64),
        dropped=scan.dropped,
        elevation=scan.elevation,
        has_t_delivered=scan.t_delivered is not None,
        t_delivered=_nan_none(scan.t_delivered),
        has_mount=scan.mount is not None,
        mount=_mount(scan.mount),
        acquisition=scan.acquisition,
        partial=scan.partial,
        partial_reason=scan.partial_reason,
        has_span=scan.span is not None,
        span_start=scan.span[0] if scan.span is not None else 0,
        span_destination=scan.span[1] if scan.span is not None else 0,
    )
    return _serialize(msg, SCAN)


def decode_scan(data: bytes | bytearray | memoryview) -> Scan:
    """The :class:`Scan` that :func:`encode_scan` (or any CDR writer of the type) encoded.

    A payload of the first definition (:data:`_SCAN_V1`, recordings made before ``partial_reason``
    and ``span`` existed) decodes too, with ``partial_reason=""`` and ``span=None``: tried only
    when the payload is not one of the current type, so a current payload costs nothing more.
    """
    try:
        msg = _deserialize(data, SCAN)
    except WireError as current:
        try:
            msg = _deserialize(data, SCAN, _legacy_typestore())
        except WireError:
            raise current from None  # neither: the current type's complaint is the useful one
    try:
        n_acq, samples = int(msg.n_acq), int(msg.samples)
        if msg.range_mm.size != n_acq * samples or msg.intensity.size != n_acq * samples:
            raise ValueError(
                f"range_mm/intensity hold {msg.range_mm.size}/{msg.intensity.size} samples, "
                f"not {n_acq} x {samples}"
            )
        return Scan(
            direction=Direction(int(msg.direction)),
            seq=int(msg.seq),
            azimuth=msg.azimuth,
            range_mm=msg.range_mm.reshape(n_acq, samples),
            closest_mm=msg.closest_mm,
            intensity=msg.intensity.reshape(n_acq, samples),
            t=msg.t,
            dropped=int(msg.dropped),
            elevation=int(msg.elevation),
            t_delivered=_optional(msg.has_t_delivered, msg.t_delivered),
            mount=_unmount(msg.has_mount, msg.mount),
            acquisition=str(msg.acquisition),
            partial=bool(msg.partial),
            partial_reason=str(getattr(msg, "partial_reason", "")),
            span=(int(msg.span_start), int(msg.span_destination))
            if getattr(msg, "has_span", False)
            else None,
        )
    except (ValueError, TypeError) as exc:
        raise WireError(f"{SCAN}: not a valid scan: {exc}") from exc


def encode_point(point: Point) -> bytes:
    """``point`` as a CDR ``biris_msgs/msg/Point`` (little-endian)."""
    if not isinstance(point, Point):
        raise WireError(f"encode_point takes a Point, not {type(point).__name__}")
    msg = _cls(POINT)(
        header=_header(point.t),
        azimuth=point.azimuth,
        range_mm=point.range_mm,
        profile=_array(point.profile, np.int16),
        intensity=_array(point.intensity, np.int16),
        t=point.t,
        acq=point.acq,
        scan_seq=point.scan_seq,
        elevation=point.elevation,
        has_t_delivered=point.t_delivered is not None,
        t_delivered=_nan_none(point.t_delivered),
        has_mount=point.mount is not None,
        mount=_mount(point.mount),
        acquisition=point.acquisition,
    )
    return _serialize(msg, POINT)


def decode_point(data: bytes | bytearray | memoryview) -> Point:
    """The :class:`Point` that :func:`encode_point` encoded."""
    msg = _deserialize(data, POINT)
    try:
        return Point(
            azimuth=int(msg.azimuth),
            range_mm=int(msg.range_mm),
            profile=msg.profile,
            intensity=msg.intensity,
            t=float(msg.t),
            acq=int(msg.acq),
            scan_seq=int(msg.scan_seq),
            elevation=int(msg.elevation),
            t_delivered=_optional(msg.has_t_delivered, msg.t_delivered),
            mount=_unmount(msg.has_mount, msg.mount),
            acquisition=str(msg.acquisition),
        )
    except (ValueError, TypeError) as exc:
        raise WireError(f"{POINT}: not a valid point: {exc}") from exc


# -- status and faults -----------------------------------------------------------------------------


def _counters(values: Mapping[str, int]) -> list[Any]:
    counter = _cls(COUNTER)
    return [counter(name=str(k), value=int(v)) for k, v in values.items()]


def _latency(summary: Mapping[str, Any]) -> Any:
    bins = list(summary.get("histogram", ()))
    return _cls(LATENCY)(
        count=int(summary.get("count", 0)),
        mean=_nan_none(summary.get("mean")),
        max=_nan_none(summary.get("max")),
        p50=_nan_none(summary.get("p50")),
        p99=_nan_none(summary.get("p99")),
        bin_low_s=np.array([b[0] for b in bins], dtype=np.float64),
        bin_high_s=np.array([b[1] for b in bins], dtype=np.float64),
        bin_count=np.array([b[2] for b in bins], dtype=np.uint64),
    )


def _unlatency(msg: Any) -> dict[str, Any]:
    if not len(msg.bin_low_s) == len(msg.bin_high_s) == len(msg.bin_count):
        raise ValueError("latency histogram columns differ in length")
    return {
        "count": int(msg.count),
        "mean": _none_nan(msg.mean),
        "max": _none_nan(msg.max),
        "p50": _none_nan(msg.p50),
        "p99": _none_nan(msg.p99),
        "histogram": [
            [float(lo), float(hi), int(n)]
            for lo, hi, n in zip(msg.bin_low_s, msg.bin_high_s, msg.bin_count, strict=True)
        ],
    }


def encode_status(status: ServerStatus, t: float = 0.0) -> bytes:
    """``status`` as a CDR ``biris_msgs/msg/Status``; ``t`` stamps the header (hardware s)."""
    if not isinstance(status, ServerStatus):
        raise WireError(f"encode_status takes a ServerStatus, not {type(status).__name__}")
    connection = _cls(CONNECTION)
    msg = _cls(STATUS)(
        header=_header(t),
        state=status.state.value,
        fault=status.fault or "",
        azimuth=status.azimuth,
        elevation=status.elevation,
        has_calibration=status.calibration is not None,
        calibration=status.calibration or 0,
        continuous=status.continuous,
        acquisition=status.acquisition,
        ring=status.ring,
        counters=_counters(status.counters),
        connections=[
            connection(
                ident=int(ident),
                kind=c.kind,
                policy=c.policy,
                depth=c.depth,
                queued=c.queued,
                delivered=c.delivered,
                dropped=c.dropped,
                latency=_latency(c.latency),
            )
            for ident, c in status.connections.items()
        ],
        interrupts=_counters(status.interrupts),
        has_azimuth_live=status.azimuth_live is not None,
        azimuth_live=status.azimuth_live or 0,
        has_elevation_live=status.elevation_live is not None,
        elevation_live=status.elevation_live or 0,
        acquisitions_in_progress=status.acquisitions_in_progress,
        acquisition_pending=status.acquisition_pending or "",
        tasks_down=list(status.tasks_down),
        task_failures=_counters(status.task_failures),
        has_crate=status.crate is not None,
        crate=_crate(status.crate),
        crate_error=status.crate_error or "",
    )
    return _serialize(msg, STATUS)


_CRATE_BOOLS = ("power_on", "inhibit", "supply_ok", "power_supply_error", "fans_ok", "sysfail")
_CRATE_MASKS = (
    "under_voltage",
    "over_voltage",
    "external_temperature",
    "over_current",
    "over_voltage_protection",
    "supply_temperature",
)
"""The crate reading's channel masks (bit n = supply channel n), carried as they are."""


def _crate(reading: CrateReading | None) -> Any:
    """A reading as ``biris_msgs/msg/CrateStatus`` (zeros for none: ``has_crate`` says)."""
    if reading is None:
        return _cls(CRATE)(
            crate_id=0,
            **dict.fromkeys(_CRATE_BOOLS, False),
            **dict.fromkeys(_CRATE_MASKS, 0),
            status_bytes=np.zeros(8, np.uint8),
            voltages_v=np.zeros(8),
            currents_a=np.zeros(8),
            fan_average_rps=0,
            fan_nominal_rps=0,
            fans_rps=np.zeros(6, np.uint8),
            temperatures_c=np.zeros(8, np.uint8),
            read_at=0.0,
        )
    return _cls(CRATE)(
        crate_id=reading.crate_id,
        **{key: getattr(reading, key) for key in (*_CRATE_BOOLS, *_CRATE_MASKS)},
        status_bytes=np.frombuffer(bytes(reading.status_bytes), np.uint8).copy(),
        voltages_v=_array(reading.voltages_v, np.float64),
        currents_a=_array(reading.currents_a, np.float64),
        fan_average_rps=reading.fan_average_rps,
        fan_nominal_rps=reading.fan_nominal_rps,
        fans_rps=_array(reading.fans_rps, np.uint8),
        temperatures_c=_array(reading.temperatures_c, np.uint8),
        read_at=reading.read_at,
    )


def _uncrate(msg: Any) -> CrateReading:
    """The reading :func:`_crate` encoded."""
    flags: dict[str, Any] = {key: bool(getattr(msg, key)) for key in _CRATE_BOOLS}
    flags.update({key: int(getattr(msg, key)) for key in _CRATE_MASKS})
    return CrateReading(
        crate_id=int(msg.crate_id),
        **flags,
        status_bytes=bytes(np.asarray(msg.status_bytes, np.uint8)),
        voltages_v=tuple(float(v) for v in msg.voltages_v),
        currents_a=tuple(float(v) for v in msg.currents_a),
        fan_average_rps=int(msg.fan_average_rps),
        fan_nominal_rps=int(msg.fan_nominal_rps),
        fans_rps=tuple(int(v) for v in msg.fans_rps),
        temperatures_c=tuple(int(v) for v in msg.temperatures_c),
        read_at=float(msg.read_at),
    )


def decode_status(data: bytes | bytearray | memoryview) -> ServerStatus:
    """The :class:`~biris_hw.status.ServerStatus` that :func:`encode_status` encoded."""
    msg = _deserialize(data, STATUS)
    try:
        fault = str(msg.fault) or None
        if fault is not None and fault not in _FAULT_KINDS:
            raise ValueError(f"unknown fault kind {fault!r}")
        return ServerStatus(
            state=ServerState(str(msg.state)),
            fault=fault,  # type: ignore[arg-type]  # checked against _FAULT_KINDS above
            azimuth=int(msg.azimuth),
            elevation=int(msg.elevation),
            calibration=int(msg.calibration) if msg.has_calibration else None,
            continuous=bool(msg.continuous),
            acquisition=str(msg.acquisition),
            ring=str(msg.ring),
            counters={str(c.name): int(c.value) for c in msg.counters},
            connections={
                int(c.ident): ConnectionStatus(
                    kind=str(c.kind),
                    policy=str(c.policy),
                    depth=int(c.depth),
                    queued=int(c.queued),
                    delivered=int(c.delivered),
                    dropped=int(c.dropped),
                    latency=_unlatency(c.latency),
                )
                for c in msg.connections
            },
            interrupts={str(c.name): int(c.value) for c in msg.interrupts},
            azimuth_live=int(msg.azimuth_live) if msg.has_azimuth_live else None,
            elevation_live=int(msg.elevation_live) if msg.has_elevation_live else None,
            acquisitions_in_progress=int(msg.acquisitions_in_progress),
            acquisition_pending=str(msg.acquisition_pending) or None,
            tasks_down=tuple(str(name) for name in msg.tasks_down),
            task_failures={str(c.name): int(c.value) for c in msg.task_failures},
            crate=_uncrate(msg.crate) if msg.has_crate else None,
            crate_error=str(msg.crate_error) or None,
        )
    except (ValueError, TypeError) as exc:
        raise WireError(f"{STATUS}: not a valid status: {exc}") from exc


def encode_fault(fault: HardwareFault, t: float = 0.0) -> bytes:
    """``fault`` as a CDR ``biris_msgs/msg/Fault``; ``t`` stamps the header (hardware s)."""
    if not isinstance(fault, HardwareFault):
        raise WireError(f"encode_fault takes a HardwareFault, not {type(fault).__name__}")
    msg = _cls(FAULT)(header=_header(t), kind=fault.kind, message=fault.message)
    return _serialize(msg, FAULT)


def decode_fault(data: bytes | bytearray | memoryview) -> HardwareFault:
    """The :class:`~biris_hw.errors.HardwareFault` that :func:`encode_fault` encoded."""
    msg = _deserialize(data, FAULT)
    kind = str(msg.kind)
    if kind not in _FAULT_KINDS:
        raise WireError(f"{FAULT}: unknown fault kind {kind!r}")
    return HardwareFault(kind, str(msg.message))  # type: ignore[arg-type]  # checked above
