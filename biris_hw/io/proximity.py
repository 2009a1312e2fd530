"""The proximity alarm: the nearest return inside a zone on the vehicle's path, and how old it is.

The Slit server the report describes before BIRIS had one, and the report took it out of BIRIS;
a robot's reactive layer wants it back: is anything in the way, how far, and how fresh is that
news. :class:`ProximityAlarm` is fed like the certainty grid (:mod:`biris_hw.io.grid`): every
acquisition placed with the vehicle's pose at its own time, the profile's returns within a
height band grouped into surfaces along its ray (:func:`~biris_hw.io.grid.profile_rays`), so one
noisy row does not raise the alarm. It keeps the surfaces seen in the last
:attr:`ProximityZone.memory_s` in ``odom`` and, when asked (:meth:`ProximityAlarm.check`), puts
them in the vehicle's frame *at that moment* and looks inside the zone:

* **the zone** (:class:`ProximityZone`) is a rectangle ahead of the vehicle in its own frame: from
  ``front_m`` forward (the vehicle's front), ``width_m`` across (centred), ``length_m`` long
  standing still and longer by ``time_s`` times the forward speed (the distance covered before
  a stop takes effect); the speed is the vehicle's over the last ``speed_window_s`` (from the
  poses), or given;
* **the answer** (:class:`Proximity`) is the nearest surface inside it (the least distance
  ahead of the zone's start), its place in the vehicle frame and its **age** (the check's time
  minus the time of the acquisition that saw it), or none; and, either way, how long ago the
  head last looked *into* the zone (``looked_age_s``: the newest acquisition whose ray crossed
  it before its first surface), because "nothing in the zone" means little if the head has been
  looking elsewhere for two seconds.

A sweep of -90 to +90 degrees looks ahead about once a second and a half; a head that should
guard the path sweeps a narrower fan ahead. :meth:`Proximity.message` encodes the answer for the
network or a recording (``biris_msgs/msg/Proximity``, :mod:`biris_hw.io.codec`).

A live stream feeds it through a :class:`ProximityFeeder`, as a
:class:`~biris_hw.io.grid.GridFeeder` feeds the grid: each acquisition waits until the vehicle's
pose at its time is known, and the alarm is asked at the newest acquisition placed, at
:data:`RATE_HZ` of the data's hardware time (:class:`~biris_hw.io.moving_sink.MovingEncoder`
publishes the answers on ``/biris/proximity``).
docs/moving.md, "The proximity alarm", says more.
"""

from __future__ import annotations

import collections
import math
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from biris_hw.data import Point, PoseLookup, Scan, VehiclePoses
from biris_hw.geometry import Mount
from biris_hw.io import codec
from biris_hw.io.grid import GridParams, Placed, PoseWait, profile_rays

__all__ = [
    "DEFAULT_ZONE",
    "RATE_HZ",
    "Proximity",
    "ProximityAlarm",
    "ProximityFeeder",
    "ProximityZone",
]

FloatArray = NDArray[np.float64]


def _number(name: str, value: float, *, positive: bool = False) -> float:
    number = float(value)
    if not math.isfinite(number) or (number <= 0.0 if positive else number < 0.0):
        kind = "positive" if positive else "at least 0"
        raise ValueError(f"{name} must be a finite number {kind}, not {value!r}")
    return number


@dataclass(frozen=True)
class ProximityZone:
    """Where the alarm looks: a rectangle ahead of the vehicle, in its frame (module notes).
    The defaults suit a small indoor robot at walking pace."""

    width_m: float = 0.6
    """Across the vehicle, centred on its x axis: its width and a margin."""
    length_m: float = 0.5
    """Along x from ``front_m``, standing still."""
    time_s: float = 1.5
    """The zone grows by this times the forward speed: at 0.5 m/s, 0.75 m more."""
    front_m: float = 0.0
    """Where the zone starts on the vehicle frame's x axis: the vehicle's front."""
    band_m: tuple[float, float] = (0.1, 2.0)
    """Heights (vehicle frame) of the returns that count, as for the grid."""
    memory_s: float = 2.0
    """Surfaces older than this (hardware seconds) are forgotten: a sweep and a margin."""
    speed_window_s: float = 0.2
    """The speed is the vehicle's advance along its heading over this time before the check."""
    match_m: float = 0.1
    """Sightings this close to one another are one obstacle: the nearest one's age is that of
    the freshest sighting within this of it (the range noise puts a static obstacle's
    sightings centimetres apart, and the oldest would otherwise win as often as any)."""
    clear_m: float = 0.05
    """A surface is gone when a newer ray passed within this of it sideways and ended more
    than this beyond it: something that moved away, or a wrong return."""

    def __post_init__(self) -> None:
        names = ("width_m", "length_m", "memory_s", "speed_window_s", "match_m", "clear_m")
        for name in names:
            object.__setattr__(self, name, _number(name, getattr(self, name), positive=True))
        object.__setattr__(self, "time_s", _number("time_s", self.time_s))
        front = float(self.front_m)
        if not math.isfinite(front):
            raise ValueError(f"front_m must be a finite number, not {self.front_m!r}")
        object.__setattr__(self, "front_m", front)
        band = tuple(float(v) for v in self.band_m)
        if len(band) != 2 or not all(math.isfinite(v) for v in band) or not band[1] > band[0]:
            raise ValueError(f"band_m must be (low, high) with high > low, not {self.band_m!r}")
        object.__setattr__(self, "band_m", band)

    def length_at(self, speed_mps: float) -> float:
        """The zone's length at a forward speed (reversing or standing: ``length_m``)."""
        return self.length_m + self.time_s * max(float(speed_mps), 0.0)


DEFAULT_ZONE = ProximityZone()


class Proximity(NamedTuple):
    """What the alarm says at one moment (:meth:`ProximityAlarm.check`)."""

    t: float
    """The check's hardware time."""
    found: bool
    """Something lies inside the zone."""
    distance_m: float
    """How far ahead of the zone's start the nearest surface in it is (inf: none)."""
    x_m: float
    """Where that surface is in the vehicle frame at ``t`` (NaN: none)."""
    y_m: float
    age_s: float
    """``t`` minus the time of the acquisition that saw it (NaN: none)."""
    looked_age_s: float
    """``t`` minus the time of the newest acquisition whose ray crossed the zone (inf: none
    within the memory): how fresh "nothing there" is."""
    zone_length_m: float
    zone_width_m: float
    speed_mps: float
    """The forward speed the zone was sized for."""

    def message(self, topic: str = codec.PROXIMITY_TOPIC) -> codec.Encoded:
        """This answer as a ``biris_msgs/msg/Proximity`` (frame ``vehicle``), stamped ``t``."""
        return codec.proximity_message(
            self.t,
            found=self.found,
            distance_m=self.distance_m,
            x_m=self.x_m,
            y_m=self.y_m,
            age_s=self.age_s,
            looked_age_s=self.looked_age_s,
            zone_length_m=self.zone_length_m,
            zone_width_m=self.zone_width_m,
            speed_mps=self.speed_mps,
            topic=topic,
        )


class _Seen(NamedTuple):
    """One batch of acquisitions as the alarm keeps it, in ``odom``."""

    t: FloatArray  # (n,) each acquisition's time
    origin: FloatArray  # (n, 2) its optical centre
    end: FloatArray  # (n, 2) its nearest surface (NaN: none)
    surfaces: FloatArray  # (m, 2) every surface of the batch
    surface_t: FloatArray  # (m,) the time of the acquisition that saw each


class ProximityAlarm:
    """The nearest return inside a :class:`ProximityZone` (module notes). Thread-safe: a feed's
    thread adds acquisitions while another checks."""

    def __init__(self, zone: ProximityZone = DEFAULT_ZONE) -> None:
        if not isinstance(zone, ProximityZone):
            raise TypeError(f"zone must be a ProximityZone, not {type(zone).__name__}")
        self.zone = zone
        self._params = GridParams(band_m=zone.band_m)
        self._seen: collections.deque[_Seen] = collections.deque()
        self._lock = threading.Lock()
        self.acquisitions = 0
        """Acquisitions taken in."""
        self.unplaced = 0
        """Acquisitions left out: no vehicle pose at their time."""

    # -- feeding it ------------------------------------------------------------------------------

    def add_scan(self, scan: Scan, poses: PoseLookup) -> Placed:
        """Every acquisition of ``scan``, each placed with the pose at its own time."""
        return self.add_acquisitions(
            scan.range_mm, scan.azimuth, scan.elevation, scan.t, poses, scan.mount
        )

    def add_points(self, points: Sequence[Point], poses: PoseLookup) -> Placed:
        """Acquisitions as read (one profile length, the first's mount)."""
        if not points:
            return Placed(0, 0)
        return self.add_acquisitions(
            np.stack([p.profile for p in points]),
            np.array([p.azimuth for p in points], dtype=np.float64),
            np.array([p.elevation for p in points], dtype=np.float64),
            np.array([p.t for p in points], dtype=np.float64),
            poses,
            points[0].mount,
        )

    def add_acquisitions(
        self,
        range_mm: ArrayLike,
        azimuth_counts: ArrayLike,
        elevation_counts: ArrayLike,
        t: ArrayLike,
        poses: PoseLookup,
        mount: Mount | None = None,
    ) -> Placed:
        """Acquisitions as arrays (``range_mm`` (n, samples), the rest one per acquisition or
        one for all), placed with ``poses.poses_at(t)``; those without a pose are counted in
        :attr:`unplaced` and left out."""
        r = np.asarray(range_mm)
        times = np.asarray(t, dtype=np.float64).reshape(-1)
        if r.ndim != 2 or r.shape[0] != times.shape[0]:
            raise ValueError(f"range_mm must be (n, samples) for {times.shape[0]} times")
        n = times.shape[0]
        az = np.broadcast_to(np.asarray(azimuth_counts, dtype=np.float64).reshape(-1), (n,))
        el = np.broadcast_to(np.asarray(elevation_counts, dtype=np.float64).reshape(-1), (n,))
        at = poses.poses_at(times)
        ok = np.asarray(at.valid, dtype=bool)
        keep = np.flatnonzero(ok)
        missing = n - keep.shape[0]
        if keep.shape[0]:
            placed = VehiclePoses(
                at.t[keep], at.x_m[keep], at.y_m[keep], at.yaw_rad[keep], ok[keep]
            )
            rays = profile_rays(
                r[keep], az[keep], el[keep], np.zeros(keep.shape[0]), placed, mount,
                params=self._params,
            )  # fmt: skip
            c, s = np.cos(rays.heading), np.sin(rays.heading)
            d = rays.distance
            has = np.isfinite(d)
            nearest = d[:, 0] if d.shape[1] else np.full(keep.shape[0], np.nan)
            end = rays.origin + nearest[:, np.newaxis] * np.column_stack((c, s))
            row = np.nonzero(has)[0]
            surfaces = rays.origin[row] + d[has][:, np.newaxis] * np.column_stack((c[row], s[row]))
            seen = _Seen(rays.t, rays.origin, end, surfaces, rays.t[row])
        with self._lock:
            self.unplaced += missing
            if keep.shape[0]:
                self._seen.append(seen)
                self.acquisitions += int(keep.shape[0])
        return Placed(int(keep.shape[0]), missing)

    # -- asking it -------------------------------------------------------------------------------

    def speed_at(self, t_hw: float, poses: PoseLookup) -> float:
        """The vehicle's forward speed at ``t_hw``: its advance along its heading over the last
        :attr:`ProximityZone.speed_window_s` (0 when either pose is unknown)."""
        window = self.zone.speed_window_s
        at = poses.poses_at(np.array([t_hw - window, t_hw]))
        if not bool(np.all(at.valid)):
            return 0.0
        dx = float(at.x_m[1] - at.x_m[0])
        dy = float(at.y_m[1] - at.y_m[0])
        mean = float(at.yaw_rad[1])
        return (math.cos(mean) * dx + math.sin(mean) * dy) / window

    def check(
        self, t_hw: float, poses: PoseLookup, *, speed_mps: float | None = None
    ) -> Proximity | None:
        """The nearest surface inside the zone at hardware time ``t_hw`` (module notes), the
        vehicle's pose then from ``poses`` and its speed from them (or ``speed_mps``). None
        when the pose at ``t_hw`` is not known: the alarm cannot say where the zone is."""
        t = float(t_hw)
        at = poses.poses_at(np.array([t]))
        if not bool(at.valid[0]):
            return None
        speed = self.speed_at(t, poses) if speed_mps is None else float(speed_mps)
        zone = self.zone
        length = zone.length_at(speed)
        half = zone.width_m / 2.0
        x0, x1 = zone.front_m, zone.front_m + length
        with self._lock:
            while self._seen and self._seen[0].t[-1] < t - zone.memory_s:
                self._seen.popleft()
            batches = list(self._seen)
        if batches:
            t_acq = np.concatenate([b.t for b in batches])
            origin = np.concatenate([b.origin for b in batches])
            end = np.concatenate([b.end for b in batches])
            surfaces = np.concatenate([b.surfaces for b in batches])
            surface_t = np.concatenate([b.surface_t for b in batches])
        else:
            t_acq, surface_t = np.zeros(0), np.zeros(0)
            origin = end = surfaces = np.zeros((0, 2))
        to_vehicle = _ToVehicle(float(at.x_m[0]), float(at.y_m[0]), float(at.yaw_rad[0]))
        recent = (t_acq >= t - zone.memory_s) & (t_acq <= t) & np.isfinite(end[:, 0])
        a, b, t_ray = to_vehicle(origin[recent]), to_vehicle(end[recent]), t_acq[recent]
        crossed = _crosses(a, b, x0, x1, half)
        looked = t - float(t_ray[crossed].max()) if crossed.any() else math.inf
        fresh = (surface_t >= t - zone.memory_s) & (surface_t <= t)
        p, p_t = to_vehicle(surfaces[fresh]), surface_t[fresh]
        inside = np.flatnonzero((p[:, 0] >= x0) & (p[:, 0] <= x1) & (np.abs(p[:, 1]) <= half))
        if inside.size:
            gone = _passed(p[inside], p_t[inside], a, b, t_ray, zone.clear_m)
            inside = inside[~gone]
        if inside.size == 0:
            return Proximity(
                t, False, math.inf, math.nan, math.nan, math.nan, looked, length, zone.width_m,
                speed,
            )  # fmt: skip
        best = inside[np.argmin(p[inside, 0])]
        near = inside[np.hypot(*(p[inside] - p[best]).T) <= zone.match_m]
        seen_t = float(p_t[near].max())
        return Proximity(
            t, True, float(p[best, 0] - x0), float(p[best, 0]), float(p[best, 1]), t - seen_t,
            looked, length, zone.width_m, speed,
        )  # fmt: skip


RATE_HZ = 5.0
"""Answers a :class:`ProximityFeeder` owes per second of the data's hardware time: a message
is some 100 bytes, and a reactive layer wants its news fresh; a feed hands a sink its
acquisitions every 50 ms, so a sink cannot answer much more often."""


class _PoseSpan(Protocol):
    """A pose lookup that also says which times it holds: a
    :class:`~biris_hw.io.pose.PoseBuffer`."""

    def poses_at(self, times: ArrayLike) -> VehiclePoses: ...

    def span(self) -> tuple[float, float] | None: ...


class ProximityFeeder:
    """Feeds a :class:`ProximityAlarm` the acquisitions of a live stream and says when and where
    to ask it, as a feed's sink does.

    The acquisitions wait for their poses as the grid's do (:class:`~biris_hw.io.grid.PoseWait`:
    a base publishes at 50 Hz, BIRIS at 30 Hz): each until ``poses`` holds a sample at or after
    its time, or until it is ``wait_s`` hardware seconds behind the newest acquisition, when it
    is put in anyway and counted as unplaced if its pose is still unknown.

    The alarm is asked (:meth:`answer`) at the time of an acquisition taken in whose pose was
    known: every acquisition up to then has been fed, and the zone can be placed there.
    :meth:`due` names those times, one per ``1 / rate_hz`` hardware seconds of them, however
    the acquisitions were batched (a live feed hands them over every 50 ms, a replay as fast as
    it reads or a virtual clock a sweep at once): asked in order, each answer is what a check at
    that moment would have said, since the alarm leaves out what it saw later.
    """

    def __init__(
        self,
        alarm: ProximityAlarm,
        poses: _PoseSpan,
        *,
        wait_s: float = 0.5,
        rate_hz: float = RATE_HZ,
    ) -> None:
        if not isinstance(alarm, ProximityAlarm):
            raise TypeError(f"alarm must be a ProximityAlarm, not {type(alarm).__name__}")
        waiting = PoseWait(poses, wait_s)
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate_hz must be positive, not {rate_hz!r}")
        self.alarm = alarm
        self.poses = poses
        self.wait_s = waiting.wait_s
        self.period_s = 1.0 / float(rate_hz)
        self.known_t = -math.inf
        """The newest acquisition taken in whose pose was known (-inf: none yet)."""
        self._waiting = waiting
        self._known: list[float] = []
        """The times of the acquisitions taken in with a known pose since :meth:`due`."""
        self._next = -math.inf

    @property
    def pending(self) -> int:
        """Acquisitions waiting for the pose of their time."""
        return self._waiting.pending

    def add(self, points: Iterable[Point]) -> Placed:
        """Take acquisitions in; feed the alarm every waiting one whose pose can be known now."""
        return self._feed(*self._waiting.take(points))

    def flush(self) -> Placed:
        """Feed the alarm whatever waits, as it stands (at the end of a stream)."""
        return self._feed(*self._waiting.take((), flush=True))

    def _feed(self, ready: list[Point], newest_pose: float) -> Placed:
        """Feed the alarm the acquisitions ready; those up to ``newest_pose`` had a pose."""
        if not ready:
            return Placed(0, 0)
        known = [p.t for p in ready if p.t <= newest_pose]
        if known:
            self.known_t = max(self.known_t, *known)
            self._known.extend(known)
        return self.alarm.add_points(ready, self.poses)

    def due(self) -> list[float]:
        """The hardware times at which answers are owed, oldest first, among the acquisitions
        taken in with a known pose since the last call: the first at least ``1 / rate_hz``
        after the last answer owed, and so on. Each time is named once."""
        owed: list[float] = []
        for t in sorted(self._known):
            if t >= self._next:
                owed.append(t)
                self._next = t + self.period_s
        self._known.clear()
        return owed

    def answer(self, t_hw: float | None = None) -> Proximity | None:
        """The alarm's answer at ``t_hw`` (default :attr:`known_t`); None before any
        acquisition was placed, or when the pose then is not known (a gap in the stream)."""
        t = self.known_t if t_hw is None else float(t_hw)
        if t == -math.inf:
            return None
        return self.alarm.check(t, self.poses)


def _passed(
    p: FloatArray, p_t: FloatArray, a: FloatArray, b: FloatArray, t_ray: FloatArray, clear: float
) -> NDArray[np.bool_]:
    """(m,) whether a ray a -> b newer than each point p (taken at p_t) passed within ``clear``
    of it sideways and ended more than ``clear`` beyond it."""
    if a.shape[0] == 0:
        return np.zeros(p.shape[0], dtype=bool)
    d = b - a
    reach = np.hypot(d[:, 0], d[:, 1])
    unit = d / np.where(reach > 0.0, reach, 1.0)[:, np.newaxis]
    rel = p[:, np.newaxis, :] - a[np.newaxis, :, :]  # (m, k, 2)
    along = rel[..., 0] * unit[:, 0] + rel[..., 1] * unit[:, 1]
    side = np.abs(rel[..., 0] * unit[:, 1] - rel[..., 1] * unit[:, 0])
    newer = t_ray[np.newaxis, :] > p_t[:, np.newaxis]
    through = newer & (side <= clear) & (along >= 0.0) & (along < reach - clear)
    passed: NDArray[np.bool_] = np.any(through, axis=1)
    return passed


class _ToVehicle:
    """Points in ``odom`` into the vehicle frame of one pose."""

    def __init__(self, x: float, y: float, yaw: float) -> None:
        self.x, self.y = x, y
        self.c, self.s = math.cos(yaw), math.sin(yaw)

    def __call__(self, xy: FloatArray) -> FloatArray:
        dx, dy = xy[:, 0] - self.x, xy[:, 1] - self.y
        out: FloatArray = np.column_stack((self.c * dx + self.s * dy, -self.s * dx + self.c * dy))
        return out


def _crosses(a: FloatArray, b: FloatArray, x0: float, x1: float, half: float) -> NDArray[np.bool_]:
    """(n,) whether each segment a -> b passes through the rectangle [x0, x1] x [-half, half]
    (the slab test, for all segments at once)."""
    d = b - a
    lo = np.zeros(a.shape[0])
    hi = np.ones(a.shape[0])
    for axis, low, high in ((0, x0, x1), (1, -half, half)):
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (low - a[:, axis]) / d[:, axis]
            t1 = (high - a[:, axis]) / d[:, axis]
        flat = d[:, axis] == 0.0
        within = (a[:, axis] >= low) & (a[:, axis] <= high)
        enter = np.where(flat, np.where(within, -np.inf, np.inf), np.minimum(t0, t1))
        leave = np.where(flat, np.where(within, np.inf, -np.inf), np.maximum(t0, t1))
        lo = np.maximum(lo, enter)
        hi = np.minimum(hi, leave)
    crossed: NDArray[np.bool_] = lo <= hi
    return crossed
