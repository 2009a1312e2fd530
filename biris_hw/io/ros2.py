"""Standard ROS 2 messages from what the sensor produces, CDR-encoded, with their schemas.

Robotics tools (``ros2 bag``, Foxglove, Lichtblick) understand the standard ROS 2 message types,
not our :class:`~biris_hw.Scan`; this module is the one translation, shared by the recorder
(:mod:`biris_hw.io.record`) and the live view (:mod:`biris_hw.io.liveview`) so a file and a live
stream carry the same bytes. Types and CDR come from rosbags' ROS 2 (Jazzy) typestore; the schema
text of each type is what :meth:`rosbags.typesys.store.Typestore.generate_msgdef` gives -- the
type's definition followed by those of its dependencies, each after a line of 80 ``=`` and ``MSG:
pkg/Type``, the layout ``ros2 bag`` (rosbag2_storage_mcap) writes, without the comments of the
``.msg`` files (which a ROS install would add, and which no reader needs).

**Frames** (REP 103: x forward, y left, z up; metres, radians), a chain from the vehicle to the
head's optics:

==================  ==================  ==================================================
frame               parent              transform
==================  ==================  ==================================================
``vehicle``         --                  the vehicle (``Scan.points("vehicle")``)
``biris_base``      ``vehicle``         static: up to the optical centre's height on the pan
                                        axis (``Scan.points("sensor")``; does not turn)
``biris_pan``       ``biris_base``      yaw by the azimuth (each acquisition)
``biris_tilt``      ``biris_pan``       out along the azimuth by ``head_offset_m``, then
                                        pitch by the elevation (positive looks up)
``biris_sensor``    ``biris_tilt``      static identity: the optics (x along the optical
                                        axis, z up the laser sheet), where the fan lies
==================  ==================  ==================================================

**Topics**: ``/biris/points`` (``sensor_msgs/msg/PointCloud2``, one per completed scan, in
``vehicle`` or ``biris_base``), ``/biris/profile`` (``PointCloud2``, one per acquisition, in
``biris_sensor``: the fan is the x-z plane of that frame), ``/tf`` (``tf2_msgs/msg/TFMessage``:
pan and tilt at each acquisition's time), ``/tf_static`` (the two static transforms),
``/diagnostics`` (``diagnostic_msgs/msg/DiagnosticArray``, REP 107). The live view adds
``/biris/sweep``: the acquisitions since its previous message, so that a 3D panel that keeps
clouds for a while (its decay time) shows the sweep build up. The lossless channels the recorder
adds beside them, and the replay reads, are :data:`RAW_SCAN_TOPIC`, :data:`RAW_POINT_TOPIC`
and :data:`RAW_STATUS_TOPIC` (``biris_msgs`` types, :mod:`biris_hw.io.wire`).

Why a PointCloud2 for the profile and not a LaserScan: BIRIS measures depth along the optical
axis, not slant range, and its rows are not a ray fan about an axis a LaserScan could name
without converting every sample; a cloud keeps the points exactly where :mod:`biris_hw.geometry`
puts them, with the intensity and the same fields as the scan cloud.

Every cloud has the fields ``x, y, z`` (float32, m), ``intensity`` (float32, BIRIS's int16
value), ``time`` (float32, s after the header's stamp: the acquisition's time), ``azimuth``
(float32, rad: the acquisition's pan angle) and ``row`` (uint16: the sample's CCD row, top
first); no-return samples are left out (``is_dense`` true), in the order of ``Scan.points()``.
Stamps are the hardware clock's seconds.

:class:`SensorFeed` is the reading half both users share: it opens a DATA connection for every
acquisition, one for every completed scan, and polls the status, handing them over in batches
from one thread, out of step with the acquisitions (why: see the class).
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from biris_hw.data import ConnectionKind, DeliveryPolicy, Point, Scan
from biris_hw.errors import BirisError, ConnectionClosed, HardwareFault, RequestError
from biris_hw.geometry import DEFAULT_MOUNT, Frame, Mount, project_profiles
from regs.wiener_crate import CrateReading

__all__ = [
    "BASE_FRAME",
    "CLOUD_FIELDS",
    "DIAGNOSTIC_ARRAY",
    "PAN_FRAME",
    "POINT_CLOUD2",
    "RAW_POINT_TOPIC",
    "RAW_SCAN_TOPIC",
    "RAW_STATUS_TOPIC",
    "SENSOR_FRAME",
    "TF_MESSAGE",
    "TILT_FRAME",
    "TOPICS",
    "VEHICLE_FRAME",
    "Encoded",
    "SensorFeed",
    "SensorSource",
    "cloud_frame_id",
    "diagnostics",
    "point_rows",
    "profile_cloud",
    "profile_clouds",
    "scan_cloud",
    "schema_text",
    "sensor_time",
    "stamp_ns",
    "static_transforms",
    "sweep_cloud",
    "sweep_rows",
    "transforms",
    "typestore",
]

log = logging.getLogger(__name__)

POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

VEHICLE_FRAME = "vehicle"
BASE_FRAME = "biris_base"
PAN_FRAME = "biris_pan"
TILT_FRAME = "biris_tilt"
SENSOR_FRAME = "biris_sensor"

TOPICS: Mapping[str, str] = {
    "/biris/points": POINT_CLOUD2,
    "/biris/profile": POINT_CLOUD2,
    "/biris/sweep": POINT_CLOUD2,
    "/tf": TF_MESSAGE,
    "/tf_static": TF_MESSAGE,
    "/diagnostics": DIAGNOSTIC_ARRAY,
}
"""Every standard topic this module's messages go to, and its type."""

RAW_SCAN_TOPIC = "/biris/raw/scan"
RAW_POINT_TOPIC = "/biris/raw/point"
RAW_STATUS_TOPIC = "/biris/raw/status"
"""The lossless channels of a recording (:mod:`biris_hw.io.wire` payloads): written by
:mod:`biris_hw.io.record`, read by :mod:`biris_hw.io.record.replay`, named here, below both."""

_RAD_PER_COUNT = 2.0 * math.pi / 4096.0

_CLOUD_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "time", "azimuth", "row"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<f4", "<f4", "<u2"],
        "offsets": [0, 4, 8, 12, 16, 20, 24],
        "itemsize": 28,
    }
)
"""One cloud point as it lies in ``PointCloud2.data`` (little-endian, 28 bytes with padding)."""

CLOUD_FIELDS: tuple[tuple[str, int, int], ...] = (
    ("x", 0, 7),
    ("y", 4, 7),
    ("z", 8, 7),
    ("intensity", 12, 7),
    ("time", 16, 7),
    ("azimuth", 20, 7),
    ("row", 24, 4),
)
"""(name, offset, PointField datatype: 7 FLOAT32, 4 UINT16) of every cloud's fields."""


@cache
def typestore() -> Any:
    """rosbags' ROS 2 Jazzy typestore: the standard types, their CDR and schema text.

    Imported on first use so that ``import biris_hw.io.ros2`` costs nothing without the
    ``.[record]`` extra.
    """
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@cache
def schema_text(msgtype: str) -> str:
    """The ros2msg schema text of a standard type, dependencies included (see the module)."""
    text, _digest = typestore().generate_msgdef(msgtype, ros_version=2)
    return str(text)


@dataclass(frozen=True)
class Encoded:
    """One message ready to write or send: where it goes, its type, its CDR, its time (ns)."""

    topic: str
    msgtype: str
    data: bytes
    log_time_ns: int


def stamp_ns(t: float) -> int:
    """Hardware seconds as whole nanoseconds (never negative: MCAP times are unsigned)."""
    return max(0, round(t * 1e9))


def _header(t: float, frame_id: str) -> Any:
    types = typestore().types
    ns = stamp_ns(t)
    stamp = types["builtin_interfaces/msg/Time"](
        sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000
    )
    return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def _serialize(msg: Any, msgtype: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msgtype))


class _Cdr:
    """Little-endian CDR (XCDR1, the ROS 2 default) written by hand, for the two messages sent
    per acquisition: building rosbags message objects costs more than the encoding itself, and
    this runs at the acquisition rate. Alignment counts from the end of the 4-byte
    encapsulation header, as in rosbags and rmw. Tests compare the bytes with rosbags'."""

    __slots__ = ("parts", "size")

    def __init__(self) -> None:
        self.parts: list[bytes] = [b"\x00\x01\x00\x00"]
        self.size = 0

    def align(self, n: int) -> None:
        pad = -self.size % n
        if pad:
            self.parts.append(b"\x00" * pad)
            self.size += pad

    def raw(self, data: bytes) -> None:
        self.parts.append(data)
        self.size += len(data)

    def pack(self, fmt: str, *values: Any, align: int = 4) -> None:
        self.align(align)
        self.raw(struct.pack(fmt, *values))

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.pack("<I", len(data))
        self.raw(data)

    def stamp(self, ns: int) -> None:
        self.pack("<iI", ns // 1_000_000_000, ns % 1_000_000_000)

    def bytes(self) -> bytes:
        return b"".join(self.parts)


@cache
def _fields_cdr() -> bytes:
    """The PointField sequence of every cloud (position-independent: it starts 4-aligned and
    holds nothing wider than 4 bytes)."""
    out = _Cdr()
    out.pack("<I", len(CLOUD_FIELDS))
    for name, offset, datatype in CLOUD_FIELDS:
        out.string(name)
        out.pack("<IB", offset, datatype)
        out.pack("<I", 1)
    return out.bytes()[4:]


@cache
def _cloud_head(frame_id: str) -> bytes:
    """A cloud's bytes from the frame id to just before ``width`` (the stamp is 4-aligned and
    8 long, so what follows it starts 4-aligned too)."""
    out = _Cdr()
    out.size = 8  # after the stamp
    out.string(frame_id)
    out.pack("<I", 1)  # height
    return out.bytes()[4:]


def _padded(rows: NDArray[Any]) -> NDArray[Any]:
    """``rows`` as ``_CLOUD_DTYPE``, padding zeroed: numpy's concatenate packs a structured
    dtype's padding away (26-byte rows under a 28-byte point_step make a cloud no reader takes)."""
    if rows.dtype == _CLOUD_DTYPE:
        return rows
    out = np.zeros(rows.shape[0], dtype=_CLOUD_DTYPE)
    for name in _CLOUD_DTYPE.names or ():
        out[name] = rows[name]
    return out


def _cloud_message(t: float | int, frame_id: str, rows: NDArray[Any]) -> bytes:
    """``sensor_msgs/msg/PointCloud2`` CDR for ``rows`` (``_CLOUD_DTYPE``), stamped ``t``
    (seconds, or whole nanoseconds as an int)."""
    ns = t if isinstance(t, int) else stamp_ns(t)
    rows = _padded(rows)
    width = int(rows.shape[0])
    data = rows.tobytes()
    return b"".join(
        (
            struct.pack("<iiI", 0x100, ns // 1_000_000_000, ns % 1_000_000_000),
            _cloud_head(frame_id),
            struct.pack("<I", width),
            _fields_cdr(),
            struct.pack(
                "<?xxxIII", False, _CLOUD_DTYPE.itemsize, _CLOUD_DTYPE.itemsize * width, len(data)
            ),
            data,
            b"\x01",  # is_dense
        )
    )


def _rows(
    range_mm: NDArray[np.int16],
    intensity: NDArray[np.int16],
    azimuth: NDArray[np.int32],
    t: NDArray[np.float64],
    t0: float | NDArray[np.float64],
    elevation: int | NDArray[np.int32],
    frame: Frame | None,
    mount: Mount,
) -> tuple[NDArray[Any], NDArray[np.intp]]:
    """Cloud rows for profiles, and how many rows each profile gave; ``frame`` None is the
    head's own frame (``biris_sensor``). ``t0`` (a scalar or one per profile) is subtracted
    from each profile's time."""
    if frame is None:
        grid = project_profiles(range_mm, np.zeros(len(azimuth)), 0, "sensor", DEFAULT_MOUNT)
    else:
        grid = project_profiles(range_mm, azimuth, elevation, frame, mount)
    valid = np.asarray(range_mm) > 0
    n_acq, samples = valid.shape
    counts = valid.sum(axis=1)
    rows = np.zeros(int(counts.sum()), dtype=_CLOUD_DTYPE)
    xyz = grid[valid]
    rows["x"], rows["y"], rows["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rows["intensity"] = np.asarray(intensity, dtype=np.float32)[valid]
    per_acq = np.repeat(np.arange(n_acq), counts)
    rows["time"] = (np.asarray(t, dtype=np.float64) - t0)[per_acq]
    rows["azimuth"] = (np.asarray(azimuth, dtype=np.float64) * _RAD_PER_COUNT)[per_acq]
    rows["row"] = np.broadcast_to(np.arange(samples, dtype=np.uint16), (n_acq, samples))[valid]
    return rows, counts


def cloud_frame_id(frame: Frame) -> str:
    """The TF frame of ``Scan.points(frame)``: ``vehicle`` or ``biris_base``."""
    if frame == "vehicle":
        return VEHICLE_FRAME
    if frame == "sensor":
        return BASE_FRAME
    raise ValueError(f"frame must be 'vehicle' or 'sensor', not {frame!r}")


def scan_cloud(scan: Scan, frame: Frame = "vehicle", topic: str = "/biris/points") -> Encoded:
    """A completed scan as one PointCloud2 in ``frame``, stamped with its first acquisition.

    The points are ``scan.points(frame)`` in the same order, as float32.
    """
    frame_id = cloud_frame_id(frame)
    t0 = float(scan.t[0]) if scan.n_acq else (scan.t_delivered or 0.0)
    rows, _counts = _rows(
        scan.range_mm,
        scan.intensity,
        scan.azimuth,
        scan.t,
        t0,
        scan.elevation,
        frame,
        scan.mount or DEFAULT_MOUNT,
    )
    return Encoded(topic, POINT_CLOUD2, _cloud_message(t0, frame_id, rows), stamp_ns(t0))


def point_rows(
    points: Sequence[Point], frame: Frame | None, t0: float | Sequence[float]
) -> list[NDArray[Any]]:
    """Each acquisition's cloud rows, computed for the whole batch at once (numpy over every
    profile of the same mount and length: per-profile calls cost ten times more); ``frame``
    None is ``biris_sensor``, and ``t0`` (one, or one per point) the time the ``time`` field
    counts from."""
    if not points:
        return []
    starts = np.broadcast_to(np.asarray(t0, dtype=np.float64), (len(points),))
    out: list[NDArray[Any]] = [np.zeros(0, dtype=_CLOUD_DTYPE)] * len(points)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, p in enumerate(points):
        # the sensor frame ignores the mount: one group per profile length there
        key = (len(p.profile), 0 if frame is None else id(p.mount))
        groups.setdefault(key, []).append(i)
    for index in groups.values():
        group = [points[i] for i in index]
        rows, counts = _rows(
            np.stack([p.profile for p in group]),
            np.stack([p.intensity for p in group]),
            np.array([p.azimuth for p in group], dtype=np.int32),
            np.array([p.t for p in group], dtype=np.float64),
            starts[index],
            np.array([p.elevation for p in group], dtype=np.int32),
            frame,
            group[0].mount or DEFAULT_MOUNT,
        )
        for i, piece in zip(index, np.split(rows, np.cumsum(counts)[:-1]), strict=True):
            out[i] = piece
    return out


def profile_clouds(points: Sequence[Point], topic: str = "/biris/profile") -> list[Encoded]:
    """:func:`profile_cloud` for a batch of acquisitions, the projection done once for all."""
    return [
        Encoded(topic, POINT_CLOUD2, _cloud_message(p.t, SENSOR_FRAME, rows), stamp_ns(p.t))
        for p, rows in zip(points, point_rows(points, None, [p.t for p in points]), strict=True)
    ]


def profile_cloud(point: Point, topic: str = "/biris/profile") -> Encoded:
    """One acquisition's profile as a PointCloud2 in ``biris_sensor`` (the fan's own frame).

    x is the depth BIRIS measured, z the height up the sheet, y 0; :func:`transforms` at the
    same stamp places it.
    """
    return profile_clouds([point], topic)[0]


def sweep_cloud(points: Sequence[Point], topic: str = "/biris/sweep") -> Encoded:
    """Acquisitions as one cloud in ``vehicle``: the live view's ``/biris/sweep`` message, which
    carries those since the previous one. Stamped with the first acquisition (``time`` counts
    from it) and logged at the last; the rows are :func:`scan_cloud`'s for the same
    acquisitions, so the pieces of a sweep put together are its scan's cloud."""
    if not points:
        return Encoded(topic, POINT_CLOUD2, _cloud_message(0, VEHICLE_FRAME, _no_rows()), 0)
    t0 = points[0].t
    rows = _padded(np.concatenate(point_rows(points, "vehicle", t0)))
    data = _cloud_message(t0, VEHICLE_FRAME, rows)
    return Encoded(topic, POINT_CLOUD2, data, stamp_ns(points[-1].t))


def _no_rows() -> NDArray[Any]:
    return np.zeros(0, dtype=_CLOUD_DTYPE)


def sweep_rows(point: Point, t0: float) -> NDArray[Any]:
    """One acquisition's cloud rows in ``vehicle``, times relative to ``t0``."""
    return point_rows([point], "vehicle", t0)[0]


def _transform(
    t: float, parent: str, child: str, xyz: Sequence[float], quat: Sequence[float]
) -> Any:
    types = typestore().types
    vector = types["geometry_msgs/msg/Vector3"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))
    rotation = types["geometry_msgs/msg/Quaternion"](
        x=float(quat[0]), y=float(quat[1]), z=float(quat[2]), w=float(quat[3])
    )
    return types["geometry_msgs/msg/TransformStamped"](
        header=_header(t, parent),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](translation=vector, rotation=rotation),
    )


def _tf(t: float, items: list[Any], topic: str) -> Encoded:
    msg = typestore().types[TF_MESSAGE](transforms=items)
    return Encoded(topic, TF_MESSAGE, _serialize(msg, TF_MESSAGE), stamp_ns(t))


def static_transforms(mount: Mount | None, t: float = 0.0, topic: str = "/tf_static") -> Encoded:
    """``vehicle -> biris_base`` (the optical centre's height on the pan axis) and
    ``biris_tilt -> biris_sensor`` (identity), for ``/tf_static``."""
    m = mount or DEFAULT_MOUNT
    identity = (0.0, 0.0, 0.0, 1.0)
    return _tf(
        t,
        [
            _transform(t, VEHICLE_FRAME, BASE_FRAME, m.optical_centre_m, identity),
            _transform(t, TILT_FRAME, SENSOR_FRAME, (0.0, 0.0, 0.0), identity),
        ],
        topic,
    )


def _transform_cdr(
    out: _Cdr, ns: int, parent: str, child: str, xyz: Sequence[float], quat: Sequence[float]
) -> None:
    out.stamp(ns)
    out.string(parent)
    out.string(child)
    out.pack("<7d", *xyz, *quat, align=8)


def transforms(point: Point, topic: str = "/tf") -> Encoded:
    """``biris_base -> biris_pan`` (yaw = azimuth) and ``biris_pan -> biris_tilt`` (pitch:
    positive elevation looks up, a negative rotation about y) at the acquisition's time.

    Encoded by hand (``_Cdr``: one of these goes out per acquisition), to the same bytes as
    rosbags'."""
    m = point.mount or DEFAULT_MOUNT
    yaw = point.azimuth * _RAD_PER_COUNT
    pitch = -point.elevation * _RAD_PER_COUNT
    ns = stamp_ns(point.t)
    out = _Cdr()
    out.pack("<I", 2)
    _transform_cdr(
        out, ns, BASE_FRAME, PAN_FRAME, (0.0, 0.0, 0.0),
        (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)),
    )  # fmt: skip
    _transform_cdr(
        out, ns, PAN_FRAME, TILT_FRAME, (m.head_offset_m, 0.0, 0.0),
        (0.0, math.sin(pitch / 2.0), 0.0, math.cos(pitch / 2.0)),
    )  # fmt: skip
    return Encoded(topic, TF_MESSAGE, out.bytes(), ns)


_OK, _WARN, _ERROR = 0, 1, 2


def _value(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if hasattr(value, "value") and not isinstance(value, (int, str)):
        return str(value.value)  # an enum
    return str(value)


def diagnostics(
    status: Mapping[str, Any] | None,
    t: float,
    *,
    hardware_id: str = "biris",
    extra: Mapping[str, Mapping[str, object]] | None = None,
    error: str | None = None,
    topic: str = "/diagnostics",
) -> Encoded:
    """The sensor's status (and any ``extra`` components, e.g. the recorder's drops) as a
    DiagnosticArray, REP 107 style.

    One DiagnosticStatus named ``biris: server`` with ``hardware_id``: level ERROR in a fault
    (message ``fault:<kind>``), WARN while initialising, OK otherwise; its values are the state,
    the axes, the acquisition mode and every counter, as strings. ``error`` (the text of a fault
    a feed met) makes it ERROR when no status could be read. Each ``extra`` entry becomes a
    status ``biris: <name>``, WARN when a value whose key contains ``dropped`` is not ``0``.
    """
    types = typestore().types
    key_value = types["diagnostic_msgs/msg/KeyValue"]
    status_type = types["diagnostic_msgs/msg/DiagnosticStatus"]
    items = []
    if status is not None:
        state = str(status["state"])
        level = _ERROR if state.startswith("fault") else _WARN if state == "initialising" else _OK
        values = [key_value(key="state", value=state)]
        for key in ("azimuth", "elevation", "azimuth_live", "elevation_live", "acquisition"):
            if key in status:
                values.append(key_value(key=key, value=_value(status[key])))
        for key, count in dict(status.get("counters", {})).items():
            values.append(key_value(key=f"counters.{key}", value=_value(count)))
        down = status.get("tasks_down") or ()
        if down:
            values.append(key_value(key="tasks_down", value=",".join(down)))
        message = state if error is None else f"{state}: {error}"
        items.append(
            status_type(
                level=level,
                name="biris: server",
                message=message,
                hardware_id=hardware_id,
                values=values,
            )
        )
    elif error is not None:
        items.append(
            status_type(
                level=_ERROR,
                name="biris: server",
                message=error,
                hardware_id=hardware_id,
                values=[],
            )
        )
    if status is not None:
        crate = _crate_status(status, hardware_id)
        if crate is not None:
            items.append(crate)
    for name, fields in (extra or {}).items():
        values = [key_value(key=k, value=_value(v)) for k, v in fields.items()]
        warn = any("dropped" in k and _value(v) != "0" for k, v in fields.items())
        items.append(
            status_type(
                level=_WARN if warn else _OK,
                name=f"biris: {name}",
                message="dropped data" if warn else "ok",
                hardware_id=hardware_id,
                values=values,
            )
        )
    msg = types[DIAGNOSTIC_ARRAY](header=_header(t, ""), status=items)
    return Encoded(topic, DIAGNOSTIC_ARRAY, _serialize(msg, DIAGNOSTIC_ARRAY), stamp_ns(t))


def _crate_status(status: Mapping[str, Any], hardware_id: str) -> Any:
    """The VME crate's DiagnosticStatus (``biris: VME crate``), or None without a monitor:
    ERROR while the crate reports an alarm, WARN when its last poll failed (the values are
    then the last reading's), OK otherwise. The values: power, fans, temperatures and each
    fitted supply channel's voltage and current."""
    reading = status.get("crate")
    error = status.get("crate_error")
    if not isinstance(reading, CrateReading) and not error:
        return None
    types = typestore().types
    key_value = types["diagnostic_msgs/msg/KeyValue"]
    values = []
    level, message = (_WARN, str(error)) if error else (_OK, "ok")
    if isinstance(reading, CrateReading):
        alarms = reading.alarms()
        if alarms:
            level, message = _ERROR, "; ".join(alarms)
        values.append(key_value(key="crate_id", value=str(reading.crate_id)))
        values.append(key_value(key="power", value="on" if reading.power_on else "off"))
        for channel, volts, amps in reading.fitted():
            values.append(key_value(key=f"channel{channel}.volts", value=f"{volts:.2f}"))
            values.append(key_value(key=f"channel{channel}.amps", value=f"{amps:.2f}"))
        for fan, rps in enumerate(reading.fans_rps, start=1):
            values.append(key_value(key=f"fan{fan}.rpm", value=str(rps * 60)))
        for sensor, celsius in enumerate(reading.temperatures_c, start=1):
            values.append(key_value(key=f"temperature{sensor}.celsius", value=str(celsius)))
    return types["diagnostic_msgs/msg/DiagnosticStatus"](
        level=level,
        name="biris: VME crate",
        message=message,
        hardware_id=hardware_id,
        values=values,
    )


# -- reading a sensor ------------------------------------------------------------------------------


class SensorSource(Protocol):
    """What a feed reads: a BirisServer, a network client's sensor, a ReplayServer."""

    def open(self, kind: ConnectionKind = ..., *, policy: Any = ..., depth: Any = ...) -> Any: ...

    def status(self) -> Mapping[str, Any]: ...


def sensor_time(source: object, last_seen: float) -> float:
    """The time to stamp a status with: the sensor's hardware clock now (a local server's
    ``hardware.clock``), else ``last_seen``, the newest time the data carried (a network
    client's sensor or a replay has no clock here)."""
    clock = getattr(getattr(source, "hardware", None), "clock", None)
    return float(clock()) if clock is not None else last_seen


BATCH_S = 0.05
"""How often a feed collects what the sensor queued for it (real seconds)."""

DRAIN_MAX = 256
"""At most this many items are taken from one connection before they are handed over, so a
fast sensor's data are written in bounded batches while the rest waits in the server's queue."""


class SensorFeed:
    """Every acquisition, every completed scan and the status every ``status_period_s``, from a
    sensor, handed over in batches to callbacks that all run in the feed's one thread.

    Why batches, collected on a timer: a reader blocked in ``ready_for_data`` is woken at the
    very moment the acquisition reaches every other client, and whatever it then does (the CDR
    encoding, the file) holds the interpreter lock just when those clients should run; that
    is what a recorder or a live view added to the latency of the local data path. Here one
    thread wakes every ``batch_s`` (out of step with the acquisitions), takes what waits on
    its two DATA connections (EVERY_ACQUISITION with ``point_depth``, EVERY_BUFFER with
    ``scan_depth``) with polls, and hands each batch over: the encoding runs once per batch,
    vectorised, and mostly between acquisitions.

    The connections are opened by the feed's thread (their owner), before :meth:`start`
    returns, so nothing the sensor produces after that is missed; what the server dropped
    because the feed was too slow is counted in :attr:`dropped_points` /
    :attr:`dropped_scans` (the server's own count, so acquisitions the server lost are in it
    too). :meth:`stop` wakes the thread at once (an event), which collects what is already
    queued, hands it over and closes the connections. A callback that raises stops the feed;
    the error is kept in :attr:`error`. A hardware fault is handed to ``on_fault`` and reading
    goes on (a reset may clear it); while a reset initialises the sensor, nothing comes and
    reading goes on too.
    """

    def __init__(
        self,
        source: SensorSource,
        *,
        on_points: Callable[[list[Point]], None] | None = None,
        on_scans: Callable[[list[Scan]], None] | None = None,
        on_status: Callable[[Mapping[str, Any] | None, str | None], None] | None = None,
        on_fault: Callable[[BaseException], None] | None = None,
        status_period_s: float = 1.0,
        batch_s: float = BATCH_S,
        point_depth: int = 4096,
        scan_depth: int = 256,
    ) -> None:
        self._source = source
        self._on_points = on_points
        self._on_scans = on_scans
        self._on_status = on_status
        self._on_fault = on_fault
        self._period = status_period_s
        self._batch_s = batch_s
        self._point_depth = point_depth
        self._scan_depth = scan_depth
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.dropped_points = 0
        self.dropped_scans = 0
        self.error: BaseException | None = None
        self.failed = threading.Event()
        """Set when a callback (or the sensor) failed: :attr:`error` says how."""

    def start(self) -> SensorFeed:
        """Open the connections (in the feed's thread) and start reading; raises what opening
        raised (ConnectionClosed for a stopped server), with nothing left running."""
        opened = threading.Event()
        failure: list[BaseException] = []
        self._thread = threading.Thread(
            target=self._run, args=(opened, failure), name="biris-feed", daemon=True
        )
        self._thread.start()
        opened.wait()
        if failure:
            self._thread.join()
            self._thread = None
            raise failure[0]
        return self

    def stop(self) -> None:
        """Wake the thread, which hands over what waits and closes the connections; join it.
        Idempotent."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    def _fail(self, exc: BaseException) -> None:
        if self.error is None:
            self.error = exc
        self.failed.set()
        self._stop.set()

    def _open(self, policy: DeliveryPolicy, depth: int) -> Any:
        return self._source.open(ConnectionKind.DATA, policy=policy, depth=depth)

    def _run(self, opened: threading.Event, failure: list[BaseException]) -> None:
        conns: list[Any] = []
        try:
            points = scans = None
            if self._on_points is not None:
                points = self._open(DeliveryPolicy.EVERY_ACQUISITION, self._point_depth)
                conns.append(points)
            if self._on_scans is not None:
                scans = self._open(DeliveryPolicy.EVERY_BUFFER, self._scan_depth)
                conns.append(scans)
        except BaseException as exc:
            failure.append(exc)
            opened.set()
            self._close(conns)
            return
        opened.set()
        try:
            self._loop(points, scans)
        except BaseException as exc:
            log.exception("a sensor feed's callback failed")
            self._fail(exc)
        finally:
            self._close(conns)

    @staticmethod
    def _close(conns: list[Any]) -> None:
        for conn in conns:
            try:
                conn.close()
            except BirisError:
                pass

    def _loop(self, points: Any, scans: Any) -> None:
        next_status = time.monotonic()
        ended = [points is None, scans is None]
        while True:
            stopping = self._stop.is_set()
            begun = time.monotonic()
            if self._on_status is not None and (begun >= next_status or stopping):
                next_status = begun + self._period
                self._status()
            full = False
            if points is not None and not ended[0]:
                got, ended[0] = self._drain(points)
                self.dropped_points = int(points.dropped)
                full = len(got) >= DRAIN_MAX
                if got:
                    assert self._on_points is not None
                    self._on_points(got)
            if scans is not None and not ended[1]:
                got, ended[1] = self._drain(scans)
                self.dropped_scans = int(scans.dropped)
                full = full or len(got) >= DRAIN_MAX
                if got:
                    assert self._on_scans is not None
                    self._on_scans(got)
            if full:
                continue  # more waits: no pause
            if stopping or all(ended):
                return  # drained after the stop (or the sensor is gone)
            wait = self._batch_s - (time.monotonic() - begun)
            if self._on_status is not None:
                wait = min(wait, next_status - time.monotonic())
            self._stop.wait(max(0.0, wait))

    def _drain(self, conn: Any) -> tuple[list[Any], bool]:
        """What waits on ``conn`` (at most DRAIN_MAX), and whether the source has ended
        (closed: nothing more will come). A fault goes to ``on_fault``; the next batch tries
        again, as it does while the sensor initialises (a reset). Any other error of the
        source (a replay's ReplayError) stops the feed: it is kept in :attr:`error` and
        :attr:`failed` is set."""
        got: list[Any] = []
        while len(got) < DRAIN_MAX:
            try:
                got.append(conn.ready_for_data(timeout=0))
            except TimeoutError:
                return got, False
            except ConnectionClosed:
                return got, True  # the sensor stopped (or the replay ended)
            except HardwareFault as exc:
                if self._on_fault is not None:
                    self._on_fault(exc)
                return got, False
            except RequestError:  # the sensor is initialising (a reset): its data come back
                return got, False  # when it is done, on these same connections
            except BirisError as exc:  # the source cannot go on (a damaged recording): what
                # came before is handed over, the error kept for the owner to report
                log.info("sensor feed stopped: %s", exc)
                self._fail(exc)
                return got, True
        return got, False

    def _status(self) -> None:
        assert self._on_status is not None
        try:
            status = self._source.status()
        except ConnectionClosed:
            return
        except BirisError as exc:
            self._on_status(None, str(exc))
            return
        self._on_status(status, None)
