"""The one ROS 2 codec of the outside world: every message the sensor's data become, in CDR.

Two families of messages leave this package, and both are made here, on one typestore, with one
header and one serialiser:

* **biris_msgs** (:data:`MSG_DEFINITIONS`): the lossless payloads of the network service and of
  a recording's raw channels. A scan that crosses the network or lands in a file must come back
  *equal*: the same ``seq``, the same int16 samples, the same float64 hardware times, the same
  drop count. ROS 2 message types serialised as CDR (the encoding of every ROS 2 transport and
  of ``ros2 bag``'s MCAP files) do that and are self-describing through their ``.msg`` text, so
  a C++ or Rust client, Foxglove, Lichtblick or ``ros2 bag`` decodes them with nothing from this
  package. ``docs/wire-format.md`` writes them down field for field.
* **standard views** (``sensor_msgs/PointCloud2``, ``tf2_msgs/TFMessage``,
  ``diagnostic_msgs/DiagnosticArray``): what robotics tools understand without our types,
  derived from the lossless data and shared by the recorder and the live view, so that a file
  and a live stream carry the same bytes.

Why custom types beside the standard ones, and not ``sensor_msgs/LaserScan``: a LaserScan holds
float32 metres of one profile; a BIRIS scan is an int16 ``(n_acq, samples)`` grid with
per-acquisition azimuths and times, and converting would lose exactly what a lossless recording
must keep. Why a PointCloud2 for the profile and not a LaserScan: BIRIS measures depth along the
optical axis, not slant range, and its rows are not a ray fan about an axis a LaserScan could
name without converting every sample; a cloud keeps the points exactly where
:mod:`biris_hw.geometry` puts them.

**One distribution: ROS 2 Jazzy** (:data:`DISTRIBUTION`). Jazzy is the long-term-support release
current while this is written (supported to 2029; Humble ends in 2027), so a reader that looks a
type up by name on a current install finds the definitions we write. The choice changes no byte
for anyone else: every type used here -- ``std_msgs/Header``, ``builtin_interfaces/Time``,
``PointCloud2``/``PointField``, ``TFMessage``/``TransformStamped``, ``DiagnosticArray`` and its
parts -- has the same definition in Humble and in Jazzy, so the schema texts we write, and the
CDR of every message, are those of either (``tests/test_codec.py`` compares the two
distributions' texts). Files written before, when the lossless half used Humble's store and the
standard half Jazzy's, hold these same texts and replay as they did.

Schema text: what :meth:`rosbags.typesys.store.Typestore.generate_msgdef` gives -- the type's
definition followed by those of its dependencies, each after a line of 80 ``=`` and ``MSG:
pkg/Type``, the layout ``ros2 bag`` (rosbag2_storage_mcap) writes, without the comments of the
``.msg`` files of the standard types (which a ROS install would add, and which no reader needs).

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

The biris_msgs payloads carry frame ``biris`` (:data:`FRAME_ID`): the sensor's own frame.

**Topics** (:data:`TOPICS`): ``/biris/points`` (``PointCloud2``, one per completed scan, in
``vehicle`` or ``biris_base``), ``/biris/profile`` (``PointCloud2``, one per acquisition, in
``biris_sensor``: the fan is the x-z plane of that frame), ``/biris/sweep`` (``PointCloud2`` in
``vehicle``: the acquisitions since its previous message, for a 3D panel that keeps clouds a
while), ``/tf`` (pan and tilt at each acquisition's time), ``/tf_static`` (the two static
transforms), ``/diagnostics`` (REP 107). The lossless channels of a recording are
:data:`RAW_SCAN_TOPIC`, :data:`RAW_POINT_TOPIC` and :data:`RAW_STATUS_TOPIC`. On a moving robot a
recording and the live view add :data:`MOVING_TOPICS` (``/odom``, ``/biris/grid``), ``odom ->
vehicle`` on ``/tf`` and ``/biris/points`` in ``odom`` (:func:`placed_cloud`), and with a
proximity alarm :data:`PROXIMITY_TOPIC`.

Every cloud has the fields ``x, y, z`` (float32, m), ``intensity`` (float32, BIRIS's int16
value), ``time`` (float32, s after the header's stamp: the acquisition's time), ``azimuth``
(float32, rad: the acquisition's pan angle) and ``row`` (uint16: the sample's CCD row, top
first); no-return samples are left out (``is_dense`` true), in the order of ``Scan.points()``.

**Stamps** are the hardware clock's seconds (since the target's clock started), as whole
nanoseconds by :func:`stamp_ns`, the one rule for every header and every log time as encoded. A
recording or the live view may log on the host's wall clock instead (:class:`LogTimes`): the log
time moves, the headers keep the hardware time.

Conventions of biris_msgs: optional values travel as a value plus a ``has_*`` flag (CDR has no
null); a 2-D array is flattened row-major with its row and column counts beside it.

Every decoding failure -- truncated, garbage, a wrong type, values a ``Scan`` refuses, an
oversized payload -- is a :class:`WireError`: bytes from the network are never trusted, and a
caller must be able to catch one error, not whatever the CDR parser happened to trip over.

The messages sent once per acquisition (the lossless ``Point``, the profile cloud, the
transforms) and the scan cloud are written by hand (:class:`_Cdr`, :func:`_point_layout`):
building rosbags message objects costs more than the encoding itself at the acquisition rate.
Tests compare those bytes with rosbags'.

rosbags is imported on first use, so that importing this module costs nothing without it.
"""

from __future__ import annotations

import functools
import logging
import math
import struct
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, NamedTuple, Protocol, get_args

import numpy as np
from numpy.typing import NDArray

from biris_hw.data import Direction, Point, PoseSample, Scan
from biris_hw.errors import BirisError, HardwareFault
from biris_hw.geometry import DEFAULT_MOUNT, Frame, Mount, project_profiles
from biris_hw.status import ConnectionStatus, ServerState, ServerStatus
from regs.wiener_crate import CrateReading

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

__all__ = [
    "BASE_FRAME",
    "CLOUD_FIELDS",
    "CONNECTION",
    "COUNTER",
    "CRATE",
    "DIAGNOSTICS_TOPIC",
    "DIAGNOSTIC_ARRAY",
    "DISTRIBUTION",
    "FAULT",
    "FRAME_ID",
    "GRID_TOPIC",
    "GRID_UNKNOWN",
    "LATENCY",
    "MAX_PAYLOAD",
    "MOUNT",
    "MOVING_TOPICS",
    "MSG_DEFINITIONS",
    "OCCUPANCY_GRID",
    "ODOMETRY",
    "ODOM_FRAME",
    "ODOM_TOPIC",
    "PAN_FRAME",
    "POINT",
    "POINTS_TOPIC",
    "POINT_CLOUD2",
    "POSE_TYPES",
    "PROFILE_TOPIC",
    "PROXIMITY",
    "PROXIMITY_TOPIC",
    "RAW_FAULT_TOPIC",
    "RAW_POINT_TOPIC",
    "RAW_SCAN_TOPIC",
    "RAW_STATUS_TOPIC",
    "SCAN",
    "SENSOR_FRAME",
    "STAMPS",
    "STATUS",
    "SWEEP_TOPIC",
    "TF_MESSAGE",
    "TF_STATIC_TOPIC",
    "TF_TOPIC",
    "TILT_FRAME",
    "TOPICS",
    "TRANSFORM_STAMPED",
    "VEHICLE_FRAME",
    "Encoded",
    "LogTimes",
    "OccupancyGridMessage",
    "PoseMessage",
    "ProximityMessage",
    "Stamp",
    "WireError",
    "cloud_frame_id",
    "decode_crate",
    "decode_fault",
    "decode_occupancy_grid",
    "decode_point",
    "decode_pose",
    "decode_proximity",
    "decode_scan",
    "decode_status",
    "decode_tf_poses",
    "diagnostics",
    "encode_crate",
    "encode_fault",
    "encode_occupancy_grid",
    "encode_odometry",
    "encode_point",
    "encode_proximity",
    "encode_scan",
    "encode_status",
    "encode_transform_stamped",
    "full_definition",
    "occupancy_grid_message",
    "odom_transform_messages",
    "odom_transforms",
    "odometry_message",
    "odometry_messages",
    "placed_cloud",
    "point_rows",
    "profile_cloud",
    "profile_clouds",
    "proximity_message",
    "scan_cloud",
    "scan_time",
    "schema_text",
    "stamp_ns",
    "static_transforms",
    "sweep_cloud",
    "sweep_rows",
    "transforms",
    "typestore",
    "warm",
]

DISTRIBUTION = "ros2_jazzy"
"""The ROS 2 distribution whose standard types the typestore holds (a rosbags ``Stores``
value); why Jazzy: see the module."""


class WireError(BirisError, ValueError):
    """Bytes that are not a valid payload of the type asked for (or a value that cannot be
    encoded); nothing was delivered. A ``ValueError`` too, as for any malformed input."""


MAX_PAYLOAD = 64 * 1024 * 1024
"""Largest payload :func:`decode_scan` and friends accept (bytes). A 128-sample scan of 4096
acquisitions is about 2.2 MB; anything near this limit is an attack or a bug, and refusing it
before parsing keeps a bad sender from making us allocate what it claims."""

FRAME_ID = "biris"
"""``header.frame_id`` of every biris_msgs message: the sensor frame (:mod:`biris_hw.geometry`)."""

# -- message types ---------------------------------------------------------------------------------

MOUNT = "biris_msgs/msg/Mount"
SCAN = "biris_msgs/msg/Scan"
POINT = "biris_msgs/msg/Point"
LATENCY = "biris_msgs/msg/Latency"
COUNTER = "biris_msgs/msg/Counter"
CONNECTION = "biris_msgs/msg/ConnectionStatus"
CRATE = "biris_msgs/msg/CrateStatus"
STATUS = "biris_msgs/msg/Status"
FAULT = "biris_msgs/msg/Fault"
PROXIMITY = "biris_msgs/msg/Proximity"

POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

# -- frames and topics -----------------------------------------------------------------------------

VEHICLE_FRAME = "vehicle"
BASE_FRAME = "biris_base"
PAN_FRAME = "biris_pan"
TILT_FRAME = "biris_tilt"
SENSOR_FRAME = "biris_sensor"

POINTS_TOPIC = "/biris/points"
PROFILE_TOPIC = "/biris/profile"
SWEEP_TOPIC = "/biris/sweep"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
DIAGNOSTICS_TOPIC = "/diagnostics"

TOPICS: Mapping[str, str] = {
    POINTS_TOPIC: POINT_CLOUD2,
    PROFILE_TOPIC: POINT_CLOUD2,
    SWEEP_TOPIC: POINT_CLOUD2,
    TF_TOPIC: TF_MESSAGE,
    TF_STATIC_TOPIC: TF_MESSAGE,
    DIAGNOSTICS_TOPIC: DIAGNOSTIC_ARRAY,
}
"""Every standard topic, and its type."""

RAW_SCAN_TOPIC = "/biris/raw/scan"
RAW_POINT_TOPIC = "/biris/raw/point"
RAW_STATUS_TOPIC = "/biris/raw/status"
"""The lossless channels of a recording (biris_msgs payloads): written by
:mod:`biris_hw.io.record`, read by :mod:`biris_hw.io.record.replay`."""

RAW_FAULT_TOPIC = "/biris/raw/fault"
"""``biris_msgs/msg/Fault`` when the sensor enters a fault: what the network service publishes
(:mod:`biris_hw.io.feed` makes it; a recording does not hold it)."""

# -- biris_msgs ------------------------------------------------------------------------------------

MSG_DEFINITIONS: dict[str, str] = {
    MOUNT: """\
# Where the head sits on the vehicle (biris_hw.geometry.Mount).
float64[3] offset_m
float64 head_height_m
float64 head_offset_m
""",
    SCAN: """\
# One sweep's data, as the server buffered it (biris_hw.data.Scan), losslessly.
# header.stamp: hardware time of the newest acquisition (the last of t), or 0 when empty.
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
    PROXIMITY: """\
# The proximity alarm's answer (biris_hw.io.proximity): the nearest return inside the zone
# ahead of the vehicle. header.stamp: hardware time of the check; frame_id: vehicle.
std_msgs/Header header
# true when a return lies inside the zone; the next four are then known
bool found
# how far ahead of the zone's start the nearest return is, metres (inf when not found)
float64 distance_m
# where it is in the vehicle frame at the stamp, metres (NaN when not found)
float64 x_m
float64 y_m
# the stamp minus the time of the acquisition that saw it, seconds (NaN when not found)
float64 age_s
# the stamp minus the time the head last looked into the zone, seconds (inf: not lately)
float64 looked_age_s
# the zone: its length at the speed below, its width, and that forward speed (m/s)
float64 zone_length_m
float64 zone_width_m
float64 speed_mps
""",
}
"""msgtype -> its ``.msg`` text (what a ROS 2 package holds). Each text names its own fields
only; :func:`schema_text` appends the types it uses."""

_V1_END = "bool partial\n"
_SCAN_V1 = MSG_DEFINITIONS[SCAN][: MSG_DEFINITIONS[SCAN].index(_V1_END) + len(_V1_END)]
"""``biris_msgs/msg/Scan`` as written before ``partial_reason`` and ``span`` were appended: the
current definition up to ``bool partial``, its last field then. Recordings made before hold it,
and :func:`decode_scan` still reads them. Fields are only ever appended, so that the old layout
stays a prefix of the new one and a payload tells which it is by where it ends."""

_FAULT_KINDS = ("timeout", "bus", "parity", "motor_stall", "protocol", "internal")


# -- the typestore ---------------------------------------------------------------------------------


def _store(definitions: Mapping[str, str]) -> Typestore:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores(DISTRIBUTION))
    types: dict[str, Any] = {}
    for name, text in definitions.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


@functools.cache
def typestore() -> Typestore:
    """rosbags' typestore of :data:`DISTRIBUTION`'s standard types with the biris_msgs types
    registered: every message of this module is built and serialised in it.

    Cached: building it parses every standard definition, which costs tens of milliseconds
    (:mod:`biris_hw.io.net.warm` pays it before anything is served).
    """
    return _store(MSG_DEFINITIONS)


@functools.cache
def _legacy_typestore() -> Typestore:
    """A typestore in which ``biris_msgs/msg/Scan`` has its first definition (:data:`_SCAN_V1`):
    a store of its own, since one store holds one definition per name."""
    return _store({MOUNT: MSG_DEFINITIONS[MOUNT], SCAN: _SCAN_V1})


@functools.cache
def schema_text(msgtype: str) -> str:
    """``msgtype``'s definition with those of every type it uses appended (``=====`` and
    ``MSG: pkg/msg/Type`` separators): what an MCAP ``ros2msg`` schema's data, or a Foxglove
    channel's schema, must be. Any type of the store: biris_msgs or standard."""
    text, _digest = typestore().generate_msgdef(msgtype, ros_version=2)
    return str(text)


full_definition = schema_text
"""The name :mod:`biris_hw.io.wire` gave :func:`schema_text` (``docs/wire-format.md`` uses it)."""


@dataclass(frozen=True)
class Encoded:
    """One message ready to write or send: where it goes, its type, its CDR, its time (ns)."""

    topic: str
    msgtype: str
    data: bytes
    log_time_ns: int


# -- the one header --------------------------------------------------------------------------------

MAX_STAMP_NS = (2**31 - 1) * 1_000_000_000 + 999_999_999
"""The latest ``builtin_interfaces/Time`` (int32 seconds: 68 years of hardware clock)."""


def stamp_ns(t: float) -> int:
    """Hardware seconds as whole nanoseconds, the one rule of every stamp and log time.

    Clamped into what ``builtin_interfaces/Time`` holds (and MCAP's unsigned log times): below
    zero or NaN is 0, beyond 68 years saturates. Only the stamp is clamped: the biris_msgs
    payloads carry the exact float64 time beside it.
    """
    if math.isnan(t) or t <= 0:
        return 0
    if t >= MAX_STAMP_NS / 1e9:
        return MAX_STAMP_NS
    return min(round(t * 1e9), MAX_STAMP_NS)


class _Clocked(Protocol):
    """What :meth:`LogTimes.anchor_to` needs of a sensor (:class:`biris_hw.sensor.Sensor`)."""

    def status(self) -> object: ...

    def clock(self) -> float: ...


Stamp = Literal["hardware", "wall"]
"""What a sink logs its messages at (:class:`LogTimes`)."""

STAMPS: tuple[Stamp, ...] = get_args(Stamp)

_log = logging.getLogger(__name__)


class LogTimes:
    """The log times a sink (a recording, the live view) gives its messages.

    ``"hardware"``: the header's stamp (:func:`stamp_ns`), as every message is encoded. A
    timeline then reads seconds since the target's clock started (1970 in a viewer).

    ``"wall"``: that stamp moved onto the host's wall clock by one offset, measured by
    :meth:`anchor` (the host's time now minus the sensor's) or, without one, at the first
    message, so that a file or a live view lines up with everything else the robot logs. The
    messages keep their hardware stamps (``header.stamp``, the biris_msgs times): only the log
    time moves, and by the same amount for every message, so intervals are the hardware's
    exactly. A hardware time more than :attr:`RESTART_S` before the latest seen (the
    sensor's clock restarted: its host rebooted) is anchored afresh. The offset is as exact as
    the reading of the sensor's clock: a status round trip for a network sensor, and up to a
    batch of the feed late when the first message measures it. A real target's clock is its
    host's monotonic clock, which keeps pace with the wall clock (until the wall clock is
    stepped, by hand or by NTP); a service on another host keeps pace with that host's.

    Raises:
        ValueError: ``stamp`` is not one of :data:`STAMPS`.
    """

    RESTART_S = 60.0
    """A hardware time this far before the latest seen is a restarted clock, not a late
    message: a sink's messages come in their stamps' order up to the depth of its queue in the
    feed (seconds), while a host's clock restarts from its boot."""

    def __init__(self, stamp: Stamp = "hardware", *, wall_ns: Callable[[], int] = time.time_ns):
        if stamp not in STAMPS:
            raise ValueError(f"stamp must be one of {', '.join(STAMPS)}, not {stamp!r}")
        self.stamp: Stamp = stamp
        self._wall_ns = wall_ns
        self._lock = threading.Lock()
        self.offset_ns: int | None = 0 if stamp == "hardware" else None
        """Log time minus hardware time (ns); None until the first anchor."""
        self.anchors = 0
        """How often the offset was measured (1 normally; more after clock restarts)."""
        self._latest = 0

    def anchor(self, hardware_s: float) -> None:
        """The sensor's clock reads ``hardware_s`` now: measure the offset (wall only)."""
        if self.stamp == "wall":
            with self._lock:
                self._anchor(stamp_ns(hardware_s))

    def anchor_to(self, sensor: _Clocked) -> None:
        """Measure the offset on ``sensor``'s clock now (wall only). A status is asked first:
        it brings a network sensor's clock up to date (its ``clock()`` is the newest time it has
        seen); a sensor that cannot say yet (0.0: a replay not begun) leaves it to the first
        message."""
        if self.stamp != "wall":
            return
        try:
            sensor.status()
        except BirisError:
            pass
        clock = float(sensor.clock())
        if clock > 0:
            self.anchor(clock)

    def _anchor(self, hardware_ns: int) -> None:
        self.offset_ns = self._wall_ns() - hardware_ns
        self._latest = hardware_ns
        self.anchors += 1

    def __call__(self, hardware_ns: int) -> int:
        """The log time of a message stamped ``hardware_ns``."""
        if self.stamp == "hardware":
            return hardware_ns
        with self._lock:
            if self.offset_ns is None:
                self._anchor(hardware_ns)
            elif hardware_ns < self._latest - round(self.RESTART_S * 1e9):
                _log.info("the sensor's clock went back: its log times measured afresh")
                self._anchor(hardware_ns)
            self._latest = max(self._latest, hardware_ns)
            assert self.offset_ns is not None
            return max(0, hardware_ns + self.offset_ns)


def _cls(name: str) -> Any:
    return typestore().types[name]


@functools.cache
def _header_types() -> tuple[Any, Any]:
    """The classes of a header and its stamp, looked up once: every message has a header."""
    types = typestore().types
    return types["builtin_interfaces/msg/Time"], types["std_msgs/msg/Header"]


def _header(t: float | int, frame_id: str) -> Any:
    """A ``std_msgs/Header`` stamped ``t`` (seconds, or whole nanoseconds as an int)."""
    time_type, header_type = _header_types()
    ns = t if isinstance(t, int) else stamp_ns(t)
    sec, nanosec = divmod(ns, 1_000_000_000)
    return header_type(stamp=time_type(sec=sec, nanosec=nanosec), frame_id=frame_id)


def _serialize(msg: Any, msgtype: str) -> bytes:
    """CDR of a message object; :class:`WireError` for a value outside its CDR type."""
    try:
        return bytes(typestore().serialize_cdr(msg, msgtype))
    except (OverflowError, ValueError, TypeError, struct.error) as exc:
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


@functools.cache
def _no_mount() -> Any:
    """The ``Mount`` of an item without one (``has_mount`` false), made once: every
    acquisition of a head without a mount carries it, and serialising only reads it."""
    offset = np.zeros(3)
    offset.flags.writeable = False
    return _cls(MOUNT)(offset_m=offset, head_height_m=0.0, head_offset_m=0.0)


def _mount(mount: Mount | None) -> Any:
    if mount is None:
        return _no_mount()
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


# -- Scan and Point --------------------------------------------------------------------------------


def encode_scan(scan: Scan) -> bytes:
    """``scan`` as a CDR ``biris_msgs/msg/Scan`` (little-endian)."""
    if not isinstance(scan, Scan):
        raise WireError(f"encode_scan takes a Scan, not {type(scan).__name__}")
    n_acq, samples = scan.range_mm.shape
    msg = _cls(SCAN)(
        header=_header(float(scan.t[-1]) if n_acq else 0.0, FRAME_ID),
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
    """``point`` as a CDR ``biris_msgs/msg/Point`` (little-endian).

    Written by hand around the bytes its shape has in common with every acquisition of that
    shape (:func:`_point_layout`), not through rosbags' message objects: this runs once per
    acquisition on the service's path to every remote reader, and rosbags' objects and generic
    serialiser cost several times the writing itself (``net.throughput_128`` in
    docs/benchmarks.md). Tests compare the bytes with rosbags'."""
    if not isinstance(point, Point):
        raise WireError(f"encode_point takes a Point, not {type(point).__name__}")
    mount = point.mount
    t_delivered = point.t_delivered
    try:
        profile, intensity = _little16(point.profile), _little16(point.intensity)
        if intensity.shape != profile.shape:
            raise ValueError(f"intensity has shape {intensity.shape}, profile {profile.shape}")
        layout = _point_layout(profile.shape[0], point.acquisition)
        sec, nanosec = divmod(stamp_ns(point.t), 1_000_000_000)
        offset, height, sideways = (
            (mount.offset_m, mount.head_height_m, mount.head_offset_m)
            if mount is not None
            else ((0.0, 0.0, 0.0), 0.0, 0.0)
        )
        return b"".join(
            (
                _POINT_HEAD.pack(_CDR_LE, sec, nanosec),
                layout.frame_id,
                _POINT_FIELDS.pack(point.azimuth, point.range_mm),
                layout.profile_length,
                profile.tobytes(),
                layout.intensity_length,
                intensity.tobytes(),
                layout.tail_padding,
                _POINT_TAIL.pack(
                    point.t,
                    point.acq,
                    point.scan_seq,
                    point.elevation,
                    t_delivered is not None,
                    _nan_none(t_delivered),
                    mount is not None,
                    *offset,
                    height,
                    sideways,
                ),
                layout.acquisition,
            )
        )
    except (OverflowError, ValueError, TypeError, struct.error) as exc:
        raise WireError(f"cannot encode {POINT}: {exc}") from exc


_CDR_LE = b"\x00\x01\x00\x00"
"""The encapsulation header of little-endian plain CDR (what rosbags and rmw write)."""

_POINT_HEAD = struct.Struct("<4siI")
"""The encapsulation header, then ``header.stamp``: sec, nanosec."""

_POINT_FIELDS = struct.Struct("<ii")
"""``azimuth``, ``range_mm`` (4-aligned after the frame id)."""

_POINT_TAIL = struct.Struct("<dQQi?3xd?7x3ddd")
"""From ``t`` to the end of ``mount``, starting 8-aligned: t, acq, scan_seq, elevation,
has_t_delivered, (padding to 8), t_delivered, has_mount, (padding to 8), mount.offset_m,
mount.head_height_m, mount.head_offset_m. CDR's padding is zero, as struct's ``x`` writes it."""


class _PointLayout(NamedTuple):
    """What a Point's CDR has in common with every acquisition of its shape (samples and
    acquisition mode), between the fields that change: the frame id, the sequence lengths, the
    alignment padding, the mode's name."""

    frame_id: bytes
    """``header.frame_id``, and the padding to ``azimuth``."""
    profile_length: bytes
    intensity_length: bytes
    """The padding after the profile, and the intensity's length."""
    tail_padding: bytes
    """The padding after the intensity, to ``t``."""
    acquisition: bytes


@functools.lru_cache(maxsize=64)
def _point_layout(samples: int, acquisition: str) -> _PointLayout:
    """The layout of a Point of ``samples`` samples taken in mode ``acquisition``, worked out
    once per shape (a sensor makes one or two) by writing one with :class:`_Cdr`."""
    out = _Cdr()
    out.stamp(0)
    marks = [out.size]
    out.string(FRAME_ID)
    out.align(4)
    marks.append(out.size)
    out.raw(bytes(_POINT_FIELDS.size))
    marks.append(out.size)
    out.pack("<I", samples)
    marks.append(out.size)
    out.raw(bytes(2 * samples))
    marks.append(out.size)
    out.pack("<I", samples)
    marks.append(out.size)
    out.raw(bytes(2 * samples))
    marks.append(out.size)
    out.align(8)
    marks.append(out.size)
    out.raw(bytes(_POINT_TAIL.size))
    marks.append(out.size)
    out.string(acquisition)
    marks.append(out.size)
    data = out.bytes()[len(_CDR_LE) :]
    pieces = [data[a:b] for a, b in zip(marks[0::2], marks[1::2], strict=True)]
    return _PointLayout(*pieces)


def _little16(values: NDArray[np.int16]) -> NDArray[np.int16]:
    """``values`` as little-endian int16 (as they are, on a little-endian host)."""
    return values if values.dtype == _LITTLE16 else values.astype(_LITTLE16)


_LITTLE16 = np.dtype("<i2")


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


def scan_time(scan: Scan) -> float:
    """When a scan was complete -- its hand-over, else its newest acquisition, else 0 -- in
    hardware seconds: the log time of every message made from it."""
    if scan.t_delivered is not None:
        return scan.t_delivered
    return float(scan.t[-1]) if scan.n_acq else 0.0


# -- status, crate readings and faults -------------------------------------------------------------


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
    """A reading as a ``biris_msgs/msg/CrateStatus`` object (zeros for none: the status's
    ``has_crate`` says which)."""
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
    """The reading :func:`_crate` made into a message object."""
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


def encode_crate(reading: CrateReading) -> bytes:
    """A crate reading alone as a CDR ``biris_msgs/msg/CrateStatus`` (a status carries one
    inside; this is the same message on its own)."""
    if not isinstance(reading, CrateReading):
        raise WireError(f"encode_crate takes a CrateReading, not {type(reading).__name__}")
    return _serialize(_crate(reading), CRATE)


def decode_crate(data: bytes | bytearray | memoryview) -> CrateReading:
    """The :class:`~regs.wiener_crate.CrateReading` that :func:`encode_crate` encoded."""
    msg = _deserialize(data, CRATE)
    try:
        return _uncrate(msg)
    except (ValueError, TypeError) as exc:
        raise WireError(f"{CRATE}: not a valid crate reading: {exc}") from exc


def encode_status(status: ServerStatus, t: float = 0.0) -> bytes:
    """``status`` as a CDR ``biris_msgs/msg/Status``; ``t`` stamps the header (hardware s)."""
    if not isinstance(status, ServerStatus):
        raise WireError(f"encode_status takes a ServerStatus, not {type(status).__name__}")
    connection = _cls(CONNECTION)
    msg = _cls(STATUS)(
        header=_header(t, FRAME_ID),
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
    msg = _cls(FAULT)(header=_header(t, FRAME_ID), kind=fault.kind, message=fault.message)
    return _serialize(msg, FAULT)


def decode_fault(data: bytes | bytearray | memoryview) -> HardwareFault:
    """The :class:`~biris_hw.errors.HardwareFault` that :func:`encode_fault` encoded."""
    msg = _deserialize(data, FAULT)
    kind = str(msg.kind)
    if kind not in _FAULT_KINDS:
        raise WireError(f"{FAULT}: unknown fault kind {kind!r}")
    return HardwareFault(kind, str(msg.message))  # type: ignore[arg-type]  # checked above


# -- paying the one-time costs ---------------------------------------------------------------------


def _sample_status() -> ServerStatus:
    return ServerStatus(
        state=ServerState.IDLE,
        fault=None,
        azimuth=0,
        elevation=0,
        calibration=None,
        continuous=False,
        acquisition="single",
        ring="off",
        counters={"scans": 0},
        connections={},
    )


@functools.cache
def warm(msgtype: str) -> None:
    """Pay ``msgtype``'s one-time costs in this process now: the typestore (about 0.1 s of pure
    Python), its schema text, and rosbags' generated (de)serialiser (10-20 ms a type), by
    encoding and decoding one sample. All of it holds the interpreter lock: paid lazily, it
    lands on the first acquisition (see :mod:`biris_hw.io.net.warm`). Cached: free the
    second time.

    Raises:
        KeyError: not a type of the store.
    """
    if msgtype not in typestore().types:
        raise KeyError(f"no message type {msgtype!r} in the codec's typestore")
    schema_text(msgtype)
    profile = np.zeros(2, dtype=np.int16)
    if msgtype == POINT:
        decode_point(encode_point(Point(0, 0, profile, profile, 0.0, 0, 0)))
    elif msgtype == SCAN:
        grid = np.zeros((1, 2), dtype=np.int16)
        scan = Scan(
            direction=Direction.CW,
            seq=0,
            azimuth=np.zeros(1, dtype=np.int32),
            range_mm=grid,
            closest_mm=np.zeros(1, dtype=np.int16),
            intensity=grid,
            t=np.zeros(1),
        )
        decode_scan(encode_scan(scan))
    elif msgtype == STATUS:
        decode_status(encode_status(_sample_status()))
    elif msgtype == FAULT:
        decode_fault(encode_fault(HardwareFault("internal", "warm-up")))
    elif msgtype == DIAGNOSTIC_ARRAY:
        diagnostics(None, 0.0, error="warm-up")
    # PointCloud2 and TFMessage are written by hand (_Cdr): nothing is generated for them


# -- standard views: hand-written CDR --------------------------------------------------------------

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


class _Cdr:
    """Little-endian CDR (XCDR1, the ROS 2 default) written by hand, for the messages sent per
    acquisition: building rosbags message objects costs more than the encoding itself, and this
    runs at the acquisition rate. Alignment counts from the end of the 4-byte encapsulation
    header, as in rosbags and rmw. Tests compare the bytes with rosbags'."""

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
        """A ``builtin_interfaces/Time`` of ``ns`` (already clamped by :func:`stamp_ns`)."""
        self.pack("<iI", ns // 1_000_000_000, ns % 1_000_000_000)

    def bytes(self) -> bytes:
        return b"".join(self.parts)


@functools.cache
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


@functools.cache
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


def scan_cloud(scan: Scan, frame: Frame = "vehicle", topic: str = POINTS_TOPIC) -> Encoded:
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


def profile_clouds(points: Sequence[Point], topic: str = PROFILE_TOPIC) -> list[Encoded]:
    """:func:`profile_cloud` for a batch of acquisitions, the projection done once for all."""
    return [
        Encoded(topic, POINT_CLOUD2, _cloud_message(p.t, SENSOR_FRAME, rows), stamp_ns(p.t))
        for p, rows in zip(points, point_rows(points, None, [p.t for p in points]), strict=True)
    ]


def profile_cloud(point: Point, topic: str = PROFILE_TOPIC) -> Encoded:
    """One acquisition's profile as a PointCloud2 in ``biris_sensor`` (the fan's own frame).

    x is the depth BIRIS measured, z the height up the sheet, y 0; :func:`transforms` at the
    same stamp places it.
    """
    return profile_clouds([point], topic)[0]


def sweep_cloud(points: Sequence[Point], topic: str = SWEEP_TOPIC) -> Encoded:
    """Acquisitions as one cloud in ``vehicle``: a ``/biris/sweep`` message, which carries those
    since the previous one. Stamped with the first acquisition (``time`` counts from it) and
    logged at the last; the rows are :func:`scan_cloud`'s for the same acquisitions, so the
    pieces of a sweep put together are its scan's cloud."""
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


def _transform_cdr(
    out: _Cdr, ns: int, parent: str, child: str, xyz: Sequence[float], quat: Sequence[float]
) -> None:
    out.stamp(ns)
    out.string(parent)
    out.string(child)
    out.pack("<7d", *xyz, *quat, align=8)


def _transforms_message(
    ns: int, items: Sequence[tuple[str, str, Sequence[float], Sequence[float]]], topic: str
) -> Encoded:
    """A ``tf2_msgs/msg/TFMessage`` of ``(parent, child, xyz, quaternion)`` all stamped ``ns``."""
    out = _Cdr()
    out.pack("<I", len(items))
    for parent, child, xyz, quat in items:
        _transform_cdr(out, ns, parent, child, xyz, quat)
    return Encoded(topic, TF_MESSAGE, out.bytes(), ns)


_IDENTITY = (0.0, 0.0, 0.0, 1.0)


def static_transforms(mount: Mount | None, t: float = 0.0, topic: str = TF_STATIC_TOPIC) -> Encoded:
    """``vehicle -> biris_base`` (the optical centre's height on the pan axis) and
    ``biris_tilt -> biris_sensor`` (identity), for ``/tf_static``."""
    m = mount or DEFAULT_MOUNT
    return _transforms_message(
        stamp_ns(t),
        [
            (VEHICLE_FRAME, BASE_FRAME, m.optical_centre_m, _IDENTITY),
            (TILT_FRAME, SENSOR_FRAME, (0.0, 0.0, 0.0), _IDENTITY),
        ],
        topic,
    )


def transforms(point: Point, topic: str = TF_TOPIC) -> Encoded:
    """``biris_base -> biris_pan`` (yaw = azimuth) and ``biris_pan -> biris_tilt`` (pitch:
    positive elevation looks up, a negative rotation about y) at the acquisition's time."""
    m = point.mount or DEFAULT_MOUNT
    yaw = point.azimuth * _RAD_PER_COUNT
    pitch = -point.elevation * _RAD_PER_COUNT
    return _transforms_message(
        stamp_ns(point.t),
        [
            (BASE_FRAME, PAN_FRAME, (0.0, 0.0, 0.0),
             (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))),
            (PAN_FRAME, TILT_FRAME, (m.head_offset_m, 0.0, 0.0),
             (0.0, math.sin(pitch / 2.0), 0.0, math.cos(pitch / 2.0))),
        ],
        topic,
    )  # fmt: skip


# -- the vehicle's pose: odom -> vehicle ----------------------------------------------------------

ODOMETRY = "nav_msgs/msg/Odometry"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
POSE_TYPES = (ODOMETRY, TRANSFORM_STAMPED)
"""The messages a pose source takes from a robot base (docs/moving.md, "The pose input")."""

ODOM_FRAME = "odom"
"""The frame the vehicle's odometry is in (REP 105): ``odom -> vehicle`` is its pose."""

ODOM_TOPIC = "/odom"
"""Where a base publishes ``nav_msgs/msg/Odometry`` (and a recording carries it)."""


class PoseMessage(NamedTuple):
    """A decoded pose message: its frames and the pose, stamped on the sender's clock."""

    frame_id: str
    """The parent frame (``odom`` by convention)."""
    child_frame_id: str
    """The frame whose pose it is (the vehicle: ``vehicle`` here, ``base_link`` on many bases)."""
    sample: PoseSample


def _yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def _quaternion_yaw(q: Any) -> float:
    """The heading of a rotation (the yaw of its z-y-x Euler angles), in [-pi, pi): what a
    planar base's pose means, whatever small roll and pitch its message carries."""
    x, y, z, w = float(q.x), float(q.y), float(q.z), float(q.w)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return yaw if yaw < math.pi else -math.pi


def _seconds(stamp: Any) -> float:
    return int(stamp.sec) + int(stamp.nanosec) * 1e-9


def _pose_types(sample: PoseSample) -> tuple[Any, Any]:
    """(position, orientation) of ``sample`` as geometry_msgs objects."""
    types = typestore().types
    position = types["geometry_msgs/msg/Point"](x=float(sample.x_m), y=float(sample.y_m), z=0.0)
    qx, qy, qz, qw = _yaw_quaternion(float(sample.yaw_rad))
    orientation = types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
    return position, orientation


def encode_odometry(
    sample: PoseSample, frame_id: str = ODOM_FRAME, child_frame_id: str = VEHICLE_FRAME
) -> bytes:
    """``sample`` as a ``nav_msgs/msg/Odometry`` in CDR: the pose in ``frame_id``, the twist
    (forward speed, yaw rate) in ``child_frame_id``, stamped ``sample.t`` (:func:`stamp_ns`);
    covariances 0 (not known). What a ROS 2 base publishes on ``/odom``."""
    types = typestore().types
    vector = types["geometry_msgs/msg/Vector3"]
    position, orientation = _pose_types(sample)
    no_covariance = np.zeros(36, dtype=np.float64)
    msg = types[ODOMETRY](
        header=_header(float(sample.t), frame_id),
        child_frame_id=child_frame_id,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](position=position, orientation=orientation),
            covariance=no_covariance,
        ),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](
                linear=vector(x=float(sample.v_mps), y=0.0, z=0.0),
                angular=vector(x=0.0, y=0.0, z=float(sample.omega_rad_s)),
            ),
            covariance=no_covariance,
        ),
    )
    return _serialize(msg, ODOMETRY)


def _transform(sample: PoseSample, parent: str, child: str) -> Any:
    types = typestore().types
    position, orientation = _pose_types(sample)
    translation = types["geometry_msgs/msg/Vector3"](x=position.x, y=position.y, z=0.0)
    return types[TRANSFORM_STAMPED](
        header=_header(float(sample.t), parent),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=translation, rotation=orientation
        ),
    )


def encode_transform_stamped(
    sample: PoseSample, frame_id: str = ODOM_FRAME, child_frame_id: str = VEHICLE_FRAME
) -> bytes:
    """``sample``'s pose as a ``geometry_msgs/msg/TransformStamped`` ``frame_id ->
    child_frame_id`` in CDR (no twist: a transform has none)."""
    return _serialize(_transform(sample, frame_id, child_frame_id), TRANSFORM_STAMPED)


def odometry_message(sample: PoseSample, topic: str = ODOM_TOPIC) -> Encoded:
    """:func:`encode_odometry` ready to write: on ``/odom``, logged at the sample's stamp."""
    return Encoded(topic, ODOMETRY, encode_odometry(sample), stamp_ns(float(sample.t)))


def odom_transforms(samples: Sequence[PoseSample], topic: str = TF_TOPIC) -> Encoded:
    """``odom -> vehicle`` at each of ``samples`` as one ``tf2_msgs/msg/TFMessage`` (for
    ``/tf``), logged at the newest stamp."""
    if not samples:
        raise WireError("odom_transforms needs at least one pose")
    msg = typestore().types[TF_MESSAGE](
        transforms=[_transform(s, ODOM_FRAME, VEHICLE_FRAME) for s in samples]
    )
    return Encoded(topic, TF_MESSAGE, _serialize(msg, TF_MESSAGE), stamp_ns(float(samples[-1].t)))


_NO_COVARIANCE = bytes(36 * 8)
"""A 6 x 6 float64 covariance of zeros (not known), as CDR."""


def _odometry_cdr(sample: PoseSample, frame_id: str, child_frame_id: str) -> bytes:
    """:func:`encode_odometry`'s bytes, written by hand (:class:`_Cdr`): a sink writes one per
    pose sample (50 Hz), and building rosbags' message objects costs ten times the encoding."""
    out = _Cdr()
    out.stamp(stamp_ns(float(sample.t)))
    out.string(frame_id)
    out.string(child_frame_id)
    qx, qy, qz, qw = _yaw_quaternion(float(sample.yaw_rad))
    out.pack("<7d", float(sample.x_m), float(sample.y_m), 0.0, qx, qy, qz, qw, align=8)
    out.raw(_NO_COVARIANCE)  # 8-aligned after seven float64s: no padding
    v, w = float(sample.v_mps), float(sample.omega_rad_s)
    out.pack("<6d", v, 0.0, 0.0, 0.0, 0.0, w, align=8)
    out.raw(_NO_COVARIANCE)
    return out.bytes()


def odometry_messages(samples: Sequence[PoseSample], topic: str = ODOM_TOPIC) -> list[Encoded]:
    """One ``nav_msgs/msg/Odometry`` per sample (``odom -> vehicle``, the twist in
    ``vehicle``), each logged at its stamp: what a recording and the live view carry on
    ``/odom``. The bytes are :func:`encode_odometry`'s, written by hand for the pose rate."""
    return [
        Encoded(
            topic,
            ODOMETRY,
            _odometry_cdr(s, ODOM_FRAME, VEHICLE_FRAME),
            stamp_ns(float(s.t)),
        )
        for s in samples
    ]


def odom_transform_messages(samples: Sequence[PoseSample], topic: str = TF_TOPIC) -> list[Encoded]:
    """One ``tf2_msgs/msg/TFMessage`` per sample holding its ``odom -> vehicle`` transform,
    each logged at its stamp: what a recording and the live view carry on ``/tf`` beside the
    head's own transforms. Each message is :func:`odom_transforms` of that one sample, written
    by hand for the pose rate."""
    out = []
    for s in samples:
        xyz = (float(s.x_m), float(s.y_m), 0.0)
        quat = _yaw_quaternion(float(s.yaw_rad))
        ns = stamp_ns(float(s.t))
        out.append(_transforms_message(ns, [(ODOM_FRAME, VEHICLE_FRAME, xyz, quat)], topic))
    return out


def placed_cloud(
    scan: Scan,
    placed: NDArray[np.float64],
    topic: str = POINTS_TOPIC,
    frame_id: str = ODOM_FRAME,
) -> Encoded:
    """A scan whose acquisitions were each placed with the vehicle's pose at its own time
    (``placed``: the ``(n_acq, samples, 3)`` grid of :func:`biris_hw.io.deskew.deskewed`, NaN
    for an acquisition without a pose) as one PointCloud2 in ``frame_id`` (``odom``): the
    fields of :func:`scan_cloud`, the returns of the placed acquisitions in the order of
    ``scan.points()``, stamped with the scan's first acquisition and logged when the scan was
    complete (:func:`scan_time`), as the feed logs a scan's cloud.

    Raises:
        ValueError: ``placed`` is not ``(n_acq, samples, 3)`` for ``scan``.
    """
    grid = np.asarray(placed, dtype=np.float64)
    if grid.shape != (*scan.range_mm.shape, 3):
        raise ValueError(
            f"placed must be {(*scan.range_mm.shape, 3)} for this scan, not {grid.shape}"
        )
    t0 = float(scan.t[0]) if scan.n_acq else (scan.t_delivered or 0.0)
    keep = (np.asarray(scan.range_mm) > 0) & np.isfinite(grid).all(axis=2)
    n_acq, samples = keep.shape
    counts = keep.sum(axis=1)
    rows = np.zeros(int(counts.sum()), dtype=_CLOUD_DTYPE)
    xyz = grid[keep]
    rows["x"], rows["y"], rows["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rows["intensity"] = np.asarray(scan.intensity, dtype=np.float32)[keep]
    per_acq = np.repeat(np.arange(n_acq), counts)
    rows["time"] = (np.asarray(scan.t, dtype=np.float64) - t0)[per_acq]
    rows["azimuth"] = (np.asarray(scan.azimuth, dtype=np.float64) * _RAD_PER_COUNT)[per_acq]
    rows["row"] = np.broadcast_to(np.arange(samples, dtype=np.uint16), (n_acq, samples))[keep]
    data = _cloud_message(t0, frame_id, rows)
    return Encoded(topic, POINT_CLOUD2, data, stamp_ns(scan_time(scan)))


def _pose_sample(
    t: float, position: Any, rotation: Any, v: float, w: float, seq: int
) -> PoseSample:
    x, y = float(position.x), float(position.y)
    yaw = _quaternion_yaw(rotation)
    if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y) and math.isfinite(yaw)):
        raise WireError(f"a pose with a value that is not a finite number (t={t}, x={x}, y={y})")
    return PoseSample(t, x, y, yaw, v, w, seq)


def decode_pose(
    data: bytes | bytearray | memoryview, msgtype: str | None = None, *, seq: int = 0
) -> PoseMessage:
    """A ``nav_msgs/msg/Odometry`` or a ``geometry_msgs/msg/TransformStamped`` (``msgtype``;
    None: whichever of the two the bytes are) as a :class:`PoseMessage` whose sample is
    numbered ``seq`` (ROS 2 headers have no sequence number). The stamp stays on the sender's
    clock; a transform's twist is NaN (not known). :class:`WireError` for anything else."""
    if msgtype is not None and msgtype not in POSE_TYPES:
        raise WireError(f"{msgtype} is not a pose message (one of {', '.join(POSE_TYPES)})")
    tried = (msgtype,) if msgtype is not None else POSE_TYPES
    error: WireError | None = None
    for name in tried:
        try:
            msg = _deserialize(data, name)
        except WireError as exc:
            error = exc
            continue
        t = _seconds(msg.header.stamp)
        if name == ODOMETRY:
            pose, twist = msg.pose.pose, msg.twist.twist
            sample = _pose_sample(
                t,
                pose.position,
                pose.orientation,
                float(twist.linear.x),
                float(twist.angular.z),
                seq,
            )
        else:
            tf = msg.transform
            sample = _pose_sample(t, tf.translation, tf.rotation, math.nan, math.nan, seq)
        return PoseMessage(str(msg.header.frame_id), str(msg.child_frame_id), sample)
    assert error is not None
    if msgtype is None:
        raise WireError(f"neither {ODOMETRY} nor {TRANSFORM_STAMPED}: {error}") from error
    raise error


def decode_tf_poses(
    data: bytes | bytearray | memoryview,
    frame_id: str = ODOM_FRAME,
    child_frame_id: str = VEHICLE_FRAME,
    *,
    seq: int = 0,
) -> list[PoseSample]:
    """The ``frame_id -> child_frame_id`` transforms of a ``tf2_msgs/msg/TFMessage`` (a ``/tf``
    message, which also carries the head's own transforms) as pose samples numbered from
    ``seq``, in the message's order; [] when it has none. :class:`WireError` for bytes that are
    not a TFMessage."""
    msg = _deserialize(data, TF_MESSAGE)
    out: list[PoseSample] = []
    for tf in msg.transforms:
        if tf.header.frame_id == frame_id and tf.child_frame_id == child_frame_id:
            t = _seconds(tf.header.stamp)
            out.append(
                _pose_sample(
                    t, tf.transform.translation, tf.transform.rotation, math.nan, math.nan,
                    seq + len(out),
                )
            )  # fmt: skip
    return out


# -- the certainty grid: nav_msgs/msg/OccupancyGrid ------------------------------------------------

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
GRID_TOPIC = "/biris/grid"
"""Where the certainty grid goes (:mod:`biris_hw.io.grid`): an ``OccupancyGrid`` in ``odom``."""

GRID_UNKNOWN = -1
"""A cell of an ``OccupancyGrid`` about which nothing is known (ROS's convention); the others
hold the probability of occupancy in percent, 0..100."""


class OccupancyGridMessage(NamedTuple):
    """A decoded ``nav_msgs/msg/OccupancyGrid``."""

    t: float
    """``header.stamp``, seconds (the hardware clock, in ours)."""
    frame_id: str
    resolution_m: float
    """Side of a cell (a float32 on the wire: 0.05 comes back as 0.0500000007...)."""
    origin_m: tuple[float, float]
    """``info.origin``'s position: the lower-left corner of cell (0, 0) in ``frame_id``."""
    origin_yaw_rad: float
    """``info.origin``'s heading (0 in ours: the grid's rows run along ``frame_id``'s x)."""
    data: NDArray[np.int8]
    """(height, width): row r is ``data[r * width : (r + 1) * width]`` on the wire, from the
    lower-left cell, x along a row; -1 unknown, else 0..100."""


def _grid_values(values: Any) -> NDArray[np.int8]:
    """``values`` as a 2-D int8 array of -1..100; :class:`WireError` otherwise."""
    grid = np.asarray(values)
    if grid.ndim != 2 or 0 in grid.shape:
        raise WireError(f"an occupancy grid must be a non-empty 2-D array, not shape {grid.shape}")
    if grid.dtype.kind not in "iu" or grid.min() < GRID_UNKNOWN or grid.max() > 100:
        raise WireError("an occupancy grid holds whole numbers from -1 (unknown) to 100")
    return np.ascontiguousarray(grid, dtype=np.int8)


def encode_occupancy_grid(
    values: Any,
    resolution_m: float,
    origin_m: tuple[float, float],
    t: float,
    frame_id: str = ODOM_FRAME,
) -> bytes:
    """``values`` ((height, width) of -1..100, row 0 the bottom row) as a
    ``nav_msgs/msg/OccupancyGrid`` in CDR: stamped ``t`` (:func:`stamp_ns`, also the map's
    load time), cells of ``resolution_m``, cell (0, 0)'s lower-left corner at ``origin_m`` in
    ``frame_id`` (no rotation). :class:`WireError` for values outside ROS's convention."""
    grid = _grid_values(values)
    res = float(resolution_m)
    if not (math.isfinite(res) and res > 0.0):
        raise WireError(f"resolution_m must be a positive number, not {resolution_m!r}")
    ox, oy = (float(v) for v in origin_m)
    if not (math.isfinite(ox) and math.isfinite(oy)):
        raise WireError(f"origin_m must be two finite numbers, not {origin_m!r}")
    types = typestore().types
    header = _header(float(t), frame_id)
    info = types["nav_msgs/msg/MapMetaData"](
        map_load_time=header.stamp,
        resolution=res,
        width=grid.shape[1],
        height=grid.shape[0],
        origin=types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=ox, y=oy, z=0.0),
            orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        ),
    )
    msg = types[OCCUPANCY_GRID](header=header, info=info, data=grid.reshape(-1))
    return _serialize(msg, OCCUPANCY_GRID)


def decode_occupancy_grid(data: bytes | bytearray | memoryview) -> OccupancyGridMessage:
    """A ``nav_msgs/msg/OccupancyGrid`` (from us or any ROS 2 node); :class:`WireError` for
    bytes that are not one, a data length that is not width x height, or a cell outside
    -1..100."""
    msg = _deserialize(data, OCCUPANCY_GRID)
    info = msg.info
    width, height = int(info.width), int(info.height)
    cells = np.asarray(msg.data, dtype=np.int8)
    if width * height != cells.shape[0] or cells.shape[0] == 0:
        raise WireError(
            f"{OCCUPANCY_GRID}: {cells.shape[0]} cells for a grid of {width} x {height}"
        )
    grid = _grid_values(cells.reshape(height, width))
    res = float(info.resolution)
    if not (math.isfinite(res) and res > 0.0):
        raise WireError(f"{OCCUPANCY_GRID}: resolution {res!r} is not a positive number")
    position = info.origin.position
    return OccupancyGridMessage(
        _seconds(msg.header.stamp),
        str(msg.header.frame_id),
        res,
        (float(position.x), float(position.y)),
        _quaternion_yaw(info.origin.orientation),
        grid,
    )


def occupancy_grid_message(
    values: Any,
    resolution_m: float,
    origin_m: tuple[float, float],
    t: float,
    topic: str = GRID_TOPIC,
) -> Encoded:
    """:func:`encode_occupancy_grid` in ``odom`` ready to publish or record: on
    ``/biris/grid``, logged at ``t``."""
    data = encode_occupancy_grid(values, resolution_m, origin_m, t)
    return Encoded(topic, OCCUPANCY_GRID, data, stamp_ns(float(t)))


MOVING_TOPICS: Mapping[str, str] = {
    ODOM_TOPIC: ODOMETRY,
    GRID_TOPIC: OCCUPANCY_GRID,
}
"""The topics a recording or the live view adds on a moving robot, beside :data:`TOPICS`:
``/odom`` when the vehicle's poses are known (which also put ``odom -> vehicle`` on ``/tf`` and
``/biris/points`` in ``odom``), ``/biris/grid`` with the certainty grid. Only there when asked
for (:mod:`biris_hw.io.moving_sink`)."""


# -- the proximity alarm: biris_msgs/msg/Proximity ------------------------------------------------

PROXIMITY_TOPIC = "/biris/proximity"
"""Where the proximity alarm's answers go (:mod:`biris_hw.io.proximity`): in a recording and the
live view given ``proximity=`` (beside :data:`MOVING_TOPICS`), and on the service's
``biris/<name>/proximity``."""


class ProximityMessage(NamedTuple):
    """A decoded ``biris_msgs/msg/Proximity`` (fields as in :data:`MSG_DEFINITIONS`)."""

    t: float
    frame_id: str
    found: bool
    distance_m: float
    x_m: float
    y_m: float
    age_s: float
    looked_age_s: float
    zone_length_m: float
    zone_width_m: float
    speed_mps: float


def encode_proximity(
    t: float,
    *,
    found: bool,
    distance_m: float,
    x_m: float,
    y_m: float,
    age_s: float,
    looked_age_s: float,
    zone_length_m: float,
    zone_width_m: float,
    speed_mps: float,
    frame_id: str = VEHICLE_FRAME,
) -> bytes:
    """One answer of the proximity alarm as a ``biris_msgs/msg/Proximity`` in CDR, stamped
    ``t`` (the check's hardware time); the values not known when nothing is found travel as
    inf or NaN, as the definition says."""
    msg = _cls(PROXIMITY)(
        header=_header(float(t), frame_id),
        found=bool(found),
        distance_m=float(distance_m),
        x_m=float(x_m),
        y_m=float(y_m),
        age_s=float(age_s),
        looked_age_s=float(looked_age_s),
        zone_length_m=float(zone_length_m),
        zone_width_m=float(zone_width_m),
        speed_mps=float(speed_mps),
    )
    return _serialize(msg, PROXIMITY)


def decode_proximity(data: bytes | bytearray | memoryview) -> ProximityMessage:
    """A ``biris_msgs/msg/Proximity``; :class:`WireError` for anything else."""
    msg = _deserialize(data, PROXIMITY)
    return ProximityMessage(
        _seconds(msg.header.stamp),
        str(msg.header.frame_id),
        bool(msg.found),
        float(msg.distance_m),
        float(msg.x_m),
        float(msg.y_m),
        float(msg.age_s),
        float(msg.looked_age_s),
        float(msg.zone_length_m),
        float(msg.zone_width_m),
        float(msg.speed_mps),
    )


def proximity_message(t: float, *, topic: str = PROXIMITY_TOPIC, **fields: Any) -> Encoded:
    """:func:`encode_proximity` ready to publish or record: on ``/biris/proximity``, logged
    at ``t``."""
    return Encoded(topic, PROXIMITY, encode_proximity(t, **fields), stamp_ns(float(t)))


# -- standard views: diagnostics -------------------------------------------------------------------

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
    topic: str = DIAGNOSTICS_TOPIC,
) -> Encoded:
    """The sensor's status (and any ``extra`` components, e.g. the recorder's drops) as a
    DiagnosticArray, REP 107 style.

    One DiagnosticStatus named ``server`` with ``hardware_id``: level ERROR in a fault
    (message ``fault:<kind>``), WARN while initialising, OK otherwise; its values are the state,
    the axes, the acquisition mode and every counter, as strings. ``error`` (the text of a fault
    a feed met) makes it ERROR when no status could be read. A sensor with a crate monitor adds
    ``VME crate``. Each ``extra`` entry becomes a status named ``<name>``, WARN when a value
    whose key contains ``dropped`` is not ``0``.

    The names leave the device out: viewers (Foxglove, Lichtblick, ``rqt_runtime_monitor``)
    show a status as ``hardware_id: name``, which reads ``biris: server``.
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
                name="server",
                message=message,
                hardware_id=hardware_id,
                values=values,
            )
        )
    elif error is not None:
        items.append(
            status_type(
                level=_ERROR,
                name="server",
                message=error,
                hardware_id=hardware_id,
                values=[],
            )
        )
    if status is not None:
        crate = _crate_diagnostic(status, hardware_id)
        if crate is not None:
            items.append(crate)
    for name, fields in (extra or {}).items():
        values = [key_value(key=k, value=_value(v)) for k, v in fields.items()]
        warn = any("dropped" in k and _value(v) != "0" for k, v in fields.items())
        items.append(
            status_type(
                level=_WARN if warn else _OK,
                name=str(name),
                message="dropped data" if warn else "ok",
                hardware_id=hardware_id,
                values=values,
            )
        )
    msg = types[DIAGNOSTIC_ARRAY](header=_header(t, ""), status=items)
    return Encoded(topic, DIAGNOSTIC_ARRAY, _serialize(msg, DIAGNOSTIC_ARRAY), stamp_ns(t))


def _crate_diagnostic(status: Mapping[str, Any], hardware_id: str) -> Any:
    """The VME crate's DiagnosticStatus (``VME crate``), or None without a monitor:
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
        name="VME crate",
        message=message,
        hardware_id=hardware_id,
        values=values,
    )
