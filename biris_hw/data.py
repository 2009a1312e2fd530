"""What the client API hands out: scan directions, connection kinds, scans and points.

These are values, not handles: they never refer back to the server, so a client may keep them,
pass them to another thread or pickle them. Their arrays are read-only so that one scan handed to
several DATA connections cannot be changed by one of them under the others.
"""

from __future__ import annotations

import enum
import operator
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from biris_hw.geometry import Frame, Mount, point_points, project_profiles, scan_points
from regs.hctl1000 import COUNTS_PER_REV

__all__ = [
    "ACQUISITION_MODES",
    "ConnectionKind",
    "DeliveryPolicy",
    "Direction",
    "Point",
    "PoseLookup",
    "PoseSample",
    "Scan",
    "VehiclePoses",
]

_DEG_PER_COUNT = 360.0 / COUNTS_PER_REV

ACQUISITION_MODES = ("single", "continuous")
"""How BIRIS acquired a scan's or a point's data: ``"single"`` -- the report's mode, one
BI_ACQUIRE sequence per scan (240 ms start-up each time) -- or ``"continuous"`` -- Appendix D's
ring, BIRIS started once with BI_START_CONTINUOUS and acquiring for ever. The same words as
``server.status()["acquisition"]``, which says which mode is on now; the data say which one they
were taken in, so a client that did not switch the mode itself still knows."""


class Direction(enum.IntEnum):
    """The way a sweep turns, seen from above; the server keeps one scan buffer for each.

    CCW moves towards larger counts (positive is counter-clockwise, REP 103). The values are 0 and
    1, usable as indices; use :attr:`sign` for arithmetic.
    """

    CW = 0
    CCW = 1

    @property
    def sign(self) -> int:
        """+1 for CCW, -1 for CW: the sign of the change in counts along such a sweep."""
        return 1 if self is Direction.CCW else -1

    @classmethod
    def of_motion(cls, start_counts: int, end_counts: int) -> Direction:
        """The direction of a move from ``start_counts`` to ``end_counts``; ValueError if none."""
        if end_counts == start_counts:
            raise ValueError(f"a move from {start_counts} to itself has no direction")
        return cls.CCW if end_counts > start_counts else cls.CW


class ConnectionKind(enum.IntEnum):
    """NORMAL connections ask; DATA ("DAT") connections are also sent every completed buffer."""

    NORMAL = 0
    DATA = 1


class DeliveryPolicy(enum.Enum):
    """What a DATA connection is sent, and what happens when its client is slower than BIRIS.

    The report's server handed a slow client "the latest complete scan", which delays data by up
    to a sweep and loses the rest; these are the ways to choose. Whatever is thrown away is
    counted in the connection's ``dropped``: nothing is lost silently.

    * ``LATEST`` -- only the newest complete scan waits for the client; a newer one replaces it
      (and counts one drop). The report's behaviour and the default.
    * ``EVERY_BUFFER`` -- complete scans wait in a queue of ``depth``; when it is full the
      oldest is dropped (and counted).
    * ``EVERY_ACQUISITION`` -- every acquisition is sent as a :class:`Point` as soon as it is
      read, without waiting for the end of the sweep; a queue of ``depth`` points, oldest
      dropped (and counted) when full. Acquisitions the server itself lost count too.
    """

    LATEST = "latest"
    EVERY_BUFFER = "every_buffer"
    EVERY_ACQUISITION = "every_acquisition"

    @property
    def default_depth(self) -> int:
        """Queue length when ``open`` is given none: 1, 8 scans, 256 points (8.5 s at 30 Hz)."""
        return {"latest": 1, "every_buffer": 8, "every_acquisition": 256}[self.value]


def _frozen(name: str, value: Any, dtype: type[np.generic], ndim: int) -> NDArray[Any]:
    """``value`` as a read-only array of ``dtype``, copied unless it already is one.

    A writable input is copied, not frozen in place: freezing the caller's own array would break
    the caller, and sharing it would let the caller change a delivered scan.
    """
    array = np.asarray(value, dtype=dtype)
    if array.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), not shape {array.shape}")
    if array.flags.writeable:
        array = array.copy()
        array.flags.writeable = False
    return array


def _read_only(value: object) -> bool:
    """A 1-D int16 array that :func:`_frozen` would return unchanged."""
    return (
        type(value) is np.ndarray
        and value.dtype == np.int16
        and value.ndim == 1
        and not value.flags.writeable
    )


def _optional_time(name: str, value: float | None) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number or None, not {type(value).__name__}")
    return float(value)


@dataclass(frozen=True, eq=False)
class Scan:
    """One sweep's data, as the server buffered it (one buffer per direction).

    Row k is acquisition k of the sequence: ``azimuth[k]`` (counts), ``range_mm[k]`` (the samples
    along the laser line, top to bottom; 0 = no return or discarded beyond BIRIS_MAX_RANGE),
    ``closest_mm[k]`` (element 0 of the BIRIS frame), ``intensity[k]`` and ``t[k]`` (hardware
    clock seconds, the middle of the exposure: increasing, and re-timed when the scan completes
    from the promptest wake of the sequence, so a :class:`Point` streamed earlier may carry a
    slightly later time for the same acquisition). ``seq`` counts completed scans of this
    direction; ``dropped`` counts acquisitions lost (a slow DATA client, a coalesced interrupt the
    data path could not recover). ``elevation`` is the tilt axis position in counts and
    ``t_delivered`` the hardware time the scan was handed to the client, when known. ``mount`` is
    the head's place on the vehicle, as the server's init record gives it, so that
    :meth:`points` needs nothing else.

    ``acquisition`` is how BIRIS acquired the scan (:data:`ACQUISITION_MODES`): ``"single"``, a
    BI_ACQUIRE sequence of its own (the report's mode), or ``"continuous"``, cut out of
    Appendix D's ring. Clients are told through the data because the mode can change while they
    listen (``conn.start_continuous()`` / ``stop_continuous()`` from any connection), and the two
    differ in what a scan covers.

    ``span`` is the ``(start, destination)``, in counts, the scan was asked to cover: ``start``
    where the head stood when the scan began, ``destination`` the requested end (None when not
    known: data recorded before the field existed). ``partial`` is True when the scan does not cover
    its span -- it ended short of its destination, began away from its start or holds no acquisition
    at all (a motor that started late, an acquisition sequence cut short), or it is the first sweep
    of a continuous scan, begun from wherever the head stood rather than from the opposite limit, or
    a sweep whose ring STOP_CONTINUOUS stopped under it -- so that a client never mistakes it for a
    whole one; its ``azimuth`` says which part it holds. ``partial_reason`` says why, in words
    (``"ended 312 counts (27.4 deg) short of its destination 2048"``), and is ``""`` for a whole
    scan; a reason without ``partial`` is refused, since it would contradict itself.
    :func:`biris_hw.scancheck.coverage_shortfall` is the rule that decides "covers".

    Equality is identity: comparing array contents is the caller's choice (``np.array_equal``).
    """

    direction: Direction
    seq: int
    azimuth: NDArray[np.int32]
    range_mm: NDArray[np.int16]
    closest_mm: NDArray[np.int16]
    intensity: NDArray[np.int16]
    t: NDArray[np.float64]
    dropped: int = 0
    elevation: int = 0
    t_delivered: float | None = None
    mount: Mount | None = None
    acquisition: str = "single"
    partial: bool = False
    partial_reason: str = ""
    span: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        def put(key: str, value: object) -> None:
            object.__setattr__(self, key, value)

        put("direction", Direction(self.direction))
        put("seq", _count("seq", self.seq))
        put("dropped", _count("dropped", self.dropped))
        put("elevation", operator.index(self.elevation))
        put("t_delivered", _optional_time("t_delivered", self.t_delivered))
        _check_mount(self.mount)
        put("acquisition", _acquisition(self.acquisition))
        put("partial", _flag("partial", self.partial))
        put("partial_reason", _reason(self.partial_reason, self.partial))
        put("span", _span(self.span))
        azimuth = _frozen("azimuth", self.azimuth, np.int32, 1)
        range_mm = _frozen("range_mm", self.range_mm, np.int16, 2)
        closest = _frozen("closest_mm", self.closest_mm, np.int16, 1)
        intensity = _frozen("intensity", self.intensity, np.int16, 2)
        t = _frozen("t", self.t, np.float64, 1)
        n_acq = azimuth.shape[0]
        for key, array in (("closest_mm", closest), ("t", t)):
            if array.shape != (n_acq,):
                raise ValueError(f"{key} has shape {array.shape}, expected ({n_acq},)")
        if range_mm.shape[0] != n_acq:
            raise ValueError(f"range_mm has {range_mm.shape[0]} rows for {n_acq} acquisitions")
        if intensity.shape != range_mm.shape:
            raise ValueError(f"intensity has shape {intensity.shape}, range_mm {range_mm.shape}")
        for key, array in (
            ("azimuth", azimuth),
            ("range_mm", range_mm),
            ("closest_mm", closest),
            ("intensity", intensity),
            ("t", t),
        ):
            put(key, array)

    @property
    def n_acq(self) -> int:
        """Acquisitions in the scan."""
        return int(self.azimuth.shape[0])

    @property
    def samples(self) -> int:
        """Samples per acquisition along the laser line (64 or 128 on the real sensor)."""
        return int(self.range_mm.shape[1])

    @property
    def azimuth_deg(self) -> NDArray[np.float64]:
        """``azimuth`` in degrees (a new array on each call)."""
        return np.multiply(self.azimuth, _DEG_PER_COUNT, dtype=np.float64)

    def points(
        self, frame: Frame | Literal["odom"] = "vehicle", poses: PoseLookup | None = None
    ) -> NDArray[np.float64]:
        """Every return of the scan as an ``(m, 3)`` array in metres; no-return samples left out.

        ``frame`` is ``"vehicle"`` (the mount applied) or ``"sensor"`` (centred on the pan
        axis at the optical centre's height); see :mod:`biris_hw.geometry`. ``"odom"`` places
        each acquisition with the vehicle's pose at its own time ``t[k]``, which ``poses`` (a
        :class:`PoseLookup`: a :class:`biris_hw.io.pose.PoseBuffer`) gives: the scan stays
        sharp while the vehicle drives (docs/moving.md). A ValueError if ``poses`` is missing,
        or has no pose for some acquisition: such an acquisition is never placed by a guess,
        and :func:`biris_hw.io.deskew.deskewed` keeps the others and says which.
        """
        if frame != "odom":
            if poses is not None:
                raise ValueError(f"poses= places points in 'odom', not in {frame!r}")
            return scan_points(self, frame)
        if poses is None:
            raise ValueError("frame='odom' needs poses= (the vehicle's pose at each acquisition)")
        placed = poses.poses_at(self.t)
        if not placed.valid.all():
            missing = np.flatnonzero(~placed.valid)
            raise ValueError(
                f"{missing.size} of {self.n_acq} acquisitions have no vehicle pose within the "
                f"lookup's bounds (the first: acquisition {int(missing[0])}, "
                f"t={self.t[missing[0]]:.6f} s); biris_hw.io.deskew.deskewed() places the "
                "others and marks these"
            )
        grid = project_profiles(self.range_mm, self.azimuth, self.elevation, "vehicle", self.mount)
        return np.ascontiguousarray(placed.to_odom(grid)[self.range_mm > 0])

    def as_points(self) -> list[Point]:
        """The scan's acquisitions as the :class:`Point` s an ``EVERY_ACQUISITION`` connection
        hands over, in order (``t_delivered`` None: a scan does not say when each was), to give a
        recording's scans to what takes acquisitions (``add_points`` of a
        :class:`~biris_hw.io.grid.CertaintyGrid` or a :class:`~biris_hw.io.proximity.
        ProximityAlarm`). Each point's arrays are views of this scan's rows."""
        return [
            Point(
                azimuth=int(self.azimuth[k]),
                range_mm=int(self.closest_mm[k]),
                profile=self.range_mm[k],
                intensity=self.intensity[k],
                t=float(self.t[k]),
                acq=k,
                scan_seq=self.seq,
                elevation=self.elevation,
                mount=self.mount,
                acquisition=self.acquisition,
            )
            for k in range(self.n_acq)
        ]

    @property
    def ages(self) -> NDArray[np.float64] | None:
        """Per acquisition, how old it was when the scan was delivered (hardware seconds)."""
        if self.t_delivered is None:
            return None
        return self.t_delivered - self.t

    @property
    def age(self) -> float | None:
        """How old the scan's *newest* acquisition was when delivered (hardware seconds).

        The freshest data is what a collision-avoidance client acts on, so this is the delay
        the report worried about; :attr:`ages` has every acquisition's. None if not delivered
        or empty.
        """
        if self.t_delivered is None or self.t.size == 0:
            return None
        return self.t_delivered - float(self.t.max())


@dataclass(frozen=True, eq=False)
class Point:
    """One acquisition, as REQUEST_POINT returns it: the latest the server has.

    ``range_mm`` is the closest sample (what the report's initial server returned), ``profile``
    and ``intensity`` the full line. ``acq`` is its index in sequence ``scan_seq``; ``t`` its
    acquisition time and ``t_delivered`` the time it was handed over, both hardware seconds.
    ``elevation`` is the tilt axis position (counts) and ``mount`` the head's place on the
    vehicle, for :meth:`points`. ``acquisition`` is how BIRIS acquired it, ``"single"`` (a
    BI_ACQUIRE sequence) or ``"continuous"`` (Appendix D's ring), as for :class:`Scan`.
    """

    azimuth: int
    range_mm: int
    profile: NDArray[np.int16]
    intensity: NDArray[np.int16]
    t: float
    acq: int
    scan_seq: int
    elevation: int = 0
    t_delivered: float | None = None
    mount: Mount | None = None
    acquisition: str = "single"

    def __post_init__(self) -> None:
        if self._valid_as_given():
            return

        def put(key: str, value: object) -> None:
            object.__setattr__(self, key, value)

        put("azimuth", operator.index(self.azimuth))
        put("range_mm", operator.index(self.range_mm))
        put("acq", _count("acq", self.acq))
        put("scan_seq", _count("scan_seq", self.scan_seq))
        put("elevation", operator.index(self.elevation))
        t = _optional_time("t", self.t)
        if t is None:
            raise ValueError("t must be a number, not None")
        put("t", t)
        put("t_delivered", _optional_time("t_delivered", self.t_delivered))
        _check_mount(self.mount)
        put("acquisition", _acquisition(self.acquisition))
        profile = _frozen("profile", self.profile, np.int16, 1)
        intensity = _frozen("intensity", self.intensity, np.int16, 1)
        if intensity.shape != profile.shape:
            raise ValueError(f"intensity has shape {intensity.shape}, profile {profile.shape}")
        put("profile", profile)
        put("intensity", intensity)

    def _valid_as_given(self) -> bool:
        """True when every field already is what the checks below would make of it.

        The server builds a Point per acquisition from fields of exactly these types (its
        arrays already read-only), and the checks' dozen calls were a visible share of the
        administrator's time per acquisition; anything else takes the full path.
        """
        t_delivered = self.t_delivered
        profile, intensity = self.profile, self.intensity
        return (
            type(self.azimuth) is int
            and type(self.range_mm) is int
            and type(self.acq) is int
            and self.acq >= 0
            and type(self.scan_seq) is int
            and self.scan_seq >= 0
            and type(self.elevation) is int
            and type(self.t) is float
            and (t_delivered is None or type(t_delivered) is float)
            and (self.mount is None or isinstance(self.mount, Mount))
            and type(self.acquisition) is str
            and self.acquisition in ACQUISITION_MODES
            and _read_only(profile)
            and _read_only(intensity)
            and profile.shape == intensity.shape
        )

    @property
    def age(self) -> float | None:
        """How old the point was when delivered (hardware seconds), or None if not known."""
        return None if self.t_delivered is None else self.t_delivered - self.t

    @property
    def azimuth_deg(self) -> float:
        """``azimuth`` in degrees."""
        return self.azimuth * _DEG_PER_COUNT

    def points(self, frame: Frame = "vehicle") -> NDArray[np.float64]:
        """The profile's returns as an ``(m, 3)`` array in metres (see :meth:`Scan.points`)."""
        return point_points(self, frame)


class PoseSample(NamedTuple):
    """One pose of the vehicle in ``odom``, as its base reports it: planar, with its twist.

    What every pose source gives (the simulator's odometry, a ROS 2 base's
    ``nav_msgs/msg/Odometry`` or ``geometry_msgs/msg/TransformStamped`` on Zenoh, a recording's
    ``/tf``) and what :class:`biris_hw.io.pose.PoseBuffer` holds. A wheeled base drives in the
    plane and does not slip sideways, so (x, y, yaw) and a forward speed and yaw rate say all.
    """

    t: float
    """Stamp, seconds: on the hardware clock once in a buffer (the source's own clock before
    the buffer's ``clock_offset_s`` is added)."""
    x_m: float
    y_m: float
    yaw_rad: float
    """Counter-clockwise from ``odom``'s x axis, in [-pi, pi)."""
    v_mps: float
    """Forward speed in the vehicle frame; NaN when the source does not say (a transform)."""
    omega_rad_s: float
    """Yaw rate, counter-clockwise positive; NaN when the source does not say."""
    seq: int
    """Sample number: the source's own where it has one (consecutive: a gap shows samples
    missed), else the order of arrival."""


class VehiclePoses(NamedTuple):
    """The vehicle's pose at each of a list of hardware times (a :class:`PoseLookup`'s answer).

    ``valid[k]`` is False where no pose was known within the lookup's bounds: there x, y and yaw
    are NaN, so a point placed with them is NaN too, never a guess that looks right.
    """

    t: NDArray[np.float64]
    """The hardware times asked for."""
    x_m: NDArray[np.float64]
    y_m: NDArray[np.float64]
    yaw_rad: NDArray[np.float64]
    """In [-pi, pi)."""
    valid: NDArray[np.bool_]

    def to_odom(self, points: ArrayLike) -> NDArray[np.float64]:
        """``points`` in the vehicle frame, one row of points per time (``(n, samples, 3)``, or
        ``(n, 3)`` with one point per time), moved into ``odom`` by the pose of their own time:
        rotated by the yaw about z, shifted by (x, y). The vehicle drives in the plane, so z is
        kept. One array operation for the lot; rows without a valid pose come out NaN."""
        p = np.asarray(points, dtype=np.float64)
        n = self.t.shape[0]
        if p.ndim not in (2, 3) or p.shape[0] != n or p.shape[-1] != 3:
            raise ValueError(f"points must be ({n}, 3) or ({n}, samples, 3), not {p.shape}")
        shape = (n,) + (1,) * (p.ndim - 2)
        c = np.cos(self.yaw_rad).reshape(shape)
        s = np.sin(self.yaw_rad).reshape(shape)
        out = np.empty_like(p)
        out[..., 0] = self.x_m.reshape(shape) + c * p[..., 0] - s * p[..., 1]
        out[..., 1] = self.y_m.reshape(shape) + s * p[..., 0] + c * p[..., 1]
        out[..., 2] = np.where(self.valid.reshape(shape), p[..., 2], np.nan)
        return out


class PoseLookup(Protocol):
    """What places acquisitions in ``odom``: the vehicle's pose at any hardware times
    (:class:`biris_hw.io.pose.PoseBuffer` is one)."""

    def poses_at(self, times: ArrayLike) -> VehiclePoses: ...


def _check_mount(mount: object) -> None:
    if mount is not None and not isinstance(mount, Mount):
        raise ValueError(f"mount must be a geometry.Mount or None, not {type(mount).__name__}")


def _acquisition(value: object) -> str:
    """One of :data:`ACQUISITION_MODES`, as a plain str (a str subclass is taken as its text)."""
    if not isinstance(value, str) or value not in ACQUISITION_MODES:
        raise ValueError(f"acquisition must be one of {ACQUISITION_MODES}, not {value!r}")
    return str(value)


def _flag(name: str, value: object) -> bool:
    """A bool (numpy's too, as a file gives it back); a number or anything else is refused, since
    a truthy 2 or "no" there is a mistake in the caller, not a wish."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise ValueError(f"{name} must be True or False, not {value!r}")


def _reason(value: object, partial: bool) -> str:
    """``partial_reason`` as a plain str; a reason on a scan that is not partial is refused (one
    of the two fields would be wrong, and a client reading either must be able to trust it)."""
    if not isinstance(value, str):
        raise ValueError(f"partial_reason must be a str, not {type(value).__name__}")
    if value and not partial:
        raise ValueError(f"partial_reason {value!r} given for a scan that is not partial")
    return str(value)


def _span(value: object) -> tuple[int, int] | None:
    """``span`` as a tuple of two Python ints, or None. Whole numbers of any integer type (a
    numpy int from a file) are taken; floats and bools are refused: a count is exact."""
    if value is None:
        return None
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise ValueError(f"span must be (start, destination) in counts or None, not {value!r}")
    ends = []
    for end in value:
        if isinstance(end, (bool, np.bool_)):
            raise ValueError(f"span must hold two whole counts, not {value!r}")
        try:
            ends.append(operator.index(end))
        except TypeError:
            raise ValueError(f"span must hold two whole counts, not {value!r}") from None
    return ends[0], ends[1]


def _count(name: str, value: int) -> int:
    """A non-negative whole number (sequence numbers, indices, tallies)."""
    number = operator.index(value)
    if number < 0:
        raise ValueError(f"{name} must not be negative, not {number}")
    return number
