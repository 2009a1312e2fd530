"""On a moving robot: what a recording and the live view add once the vehicle's poses are known.

The recorder and the live view are sinks of the sensor's feed (:mod:`biris_hw.io.feed`); the
feed knows nothing of the vehicle. Given the vehicle's poses (a
:class:`~biris_hw.io.pose.PoseBuffer`, or any :class:`PoseFeed`) and, if asked, a certainty grid,
a :class:`MovingEncoder` turns each batch the sink is handed into the messages of a moving
robot (docs/moving.md), written once here for both sinks:

- **``/odom``** (``nav_msgs/msg/Odometry``) and **``odom -> vehicle`` on ``/tf``**: every pose
  sample once, in stamp order, each in a message of its own logged at its stamp, from
  :data:`LEAD_S` before the first data (or status) the sink is handed (the first acquisitions
  need a pose before them; what the pose buffer held from long before is not the sink's). A
  sample is handed on once the sink has seen data (or a status) at least as new -- a replay's
  poses come out at the pace of its data -- and at the end every sample left;
- **``/biris/points`` in ``odom``**: each completed scan deskewed
  (:func:`~biris_hw.io.deskew.deskewed`: every acquisition placed with the pose at its own
  time). A scan waits until the poses reach its last acquisition, or until the sink has seen
  data ``wait_s`` newer than it (a pose stream with a gap); an acquisition still without a
  pose then is left out of the cloud and counted (:attr:`MovingEncoder.unplaced_points`), never
  placed by a guess, and a scan none of whose acquisitions has a pose gives no cloud
  (:attr:`MovingEncoder.unplaced_scans`);
- **``/biris/grid``** (``nav_msgs/msg/OccupancyGrid`` in ``odom``) with a grid: every
  acquisition of the feed goes into a :class:`~biris_hw.io.grid.CertaintyGrid` through a
  :class:`~biris_hw.io.grid.GridFeeder` (which holds each until its pose is known), and the grid
  goes out when the feeder says one is due (a few Hz, on the data's hardware time) and once more
  at the end;
- **``/biris/proximity``** (``biris_msgs/msg/Proximity`` in ``vehicle``) with a proximity
  alarm: every acquisition goes into a :class:`~biris_hw.io.proximity.ProximityAlarm` through a
  :class:`~biris_hw.io.proximity.ProximityFeeder` (the same holding rule as the grid's), and
  the alarm's answer goes out :data:`~biris_hw.io.proximity.RATE_HZ` times a second of the
  data's hardware time, each at an acquisition's time whose pose is known (so as often however
  the batches come), and once more at the end, at the newest.

Only the topics the sink wants are built (``wanted``: the live view builds only what a viewer
subscribed to), but the poses are taken and the grid and the alarm are fed whatever is watched,
so that a viewer who subscribes late sees the grid whole, the alarm's memory full and the poses
from then on.

**Reading the poses.** Each sample is taken once, by ``since(t)`` where the pose object has one
(a :class:`~biris_hw.io.pose.PoseBuffer`, :class:`RecordedPoses`, the simulator's odometry: a
bisection, whatever the number held), else by ``samples()``, which copies every sample held
(about 10 ms for 3000): a pose object with only that is looked at no more often than every
``poll_s`` real seconds, so ``/odom`` then comes in bursts of half a second.
"""

from __future__ import annotations

import bisect
import math
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol, TypeAlias, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from biris_hw.data import PoseSample, Scan, VehiclePoses
from biris_hw.io import codec
from biris_hw.io.deskew import deskewed
from biris_hw.io.feed import Batch
from biris_hw.io.grid import CertaintyGrid, GridFeeder, GridParams
from biris_hw.io.proximity import ProximityAlarm, ProximityFeeder, ProximityZone

__all__ = [
    "LEAD_S",
    "POSE_POLL_S",
    "WAIT_S",
    "GridOption",
    "MovingEncoder",
    "PoseFeed",
    "ProximityOption",
    "RecordedPoses",
    "moving_encoder",
]

POSE_POLL_S = 0.5
"""Real seconds between two copies of a pose object that has no ``since`` (see the module)."""

LEAD_S = 1.0
"""Hardware seconds of poses handed on from before the first data a sink is handed."""

WAIT_S = 0.5
"""Hardware seconds a completed scan waits for the poses of its acquisitions, counted on the
newest data the sink has seen."""


class PoseFeed(Protocol):
    """What ``poses=`` takes: a pose lookup that says which times it holds and gives its samples
    (:class:`~biris_hw.io.pose.PoseBuffer` is one; :class:`RecordedPoses` another). An object
    that also has ``since(t)`` (the samples stamped after ``t``) is read through it."""

    def poses_at(self, times: ArrayLike) -> VehiclePoses: ...

    def span(self) -> tuple[float, float] | None: ...

    def samples(self) -> list[PoseSample]: ...


@runtime_checkable
class _Since(Protocol):
    def since(self, t_hw: float, /) -> Sequence[PoseSample]: ...


GridOption: TypeAlias = GridParams | CertaintyGrid | GridFeeder
"""What ``grid=`` takes: the grid's settings, a grid, or a feeder of a grid (its own poses)."""

ProximityOption: TypeAlias = ProximityZone | ProximityAlarm | ProximityFeeder
"""What ``proximity=`` takes: the alarm's zone, an alarm, or a feeder of an alarm (its own poses
and rate)."""


class RecordedPoses:
    """A recording's poses (:func:`~biris_hw.io.pose.read_poses`) as a :class:`PoseFeed`: a
    :class:`~biris_hw.io.pose.PoseBuffer` holding all of them for the lookups, and
    :meth:`since` by bisection, so handing them on costs nothing per batch however many there
    are. ``options`` are the buffer's (``max_gap_s``, ``max_extrapolation_s``)."""

    def __init__(self, samples: Sequence[PoseSample], **options: Any) -> None:
        from biris_hw.io.pose import PoseBuffer

        ordered = sorted(samples, key=lambda s: s.t)
        self.buffer = PoseBuffer(capacity=max(2, len(ordered)), **options)
        self.buffer.extend(ordered)
        self._samples = self.buffer.samples()  # what the buffer took: in order, finite
        self._times = [s.t for s in self._samples]

    def __len__(self) -> int:
        return len(self._samples)

    def poses_at(self, times: ArrayLike) -> VehiclePoses:
        return self.buffer.poses_at(times)

    def span(self) -> tuple[float, float] | None:
        return self.buffer.span()

    def samples(self) -> list[PoseSample]:
        return list(self._samples)

    def since(self, t_hw: float, /) -> list[PoseSample]:
        """The samples stamped after ``t_hw``, oldest first."""
        return self._samples[bisect.bisect_right(self._times, t_hw) :]


def moving_encoder(
    poses: PoseFeed | None,
    grid: GridOption | None = None,
    proximity: ProximityOption | None = None,
) -> MovingEncoder | None:
    """What a sink's ``poses=``, ``grid=`` and ``proximity=`` make: a :class:`MovingEncoder`, or
    None without poses. The recorder, the live view and the service take these options alike.

    Raises:
        ValueError: ``grid`` or ``proximity`` without ``poses`` (each places every acquisition
            with its pose).
        TypeError: as :class:`MovingEncoder`.
    """
    if grid is not None and poses is None:
        raise ValueError("grid= needs poses=: the grid places each acquisition with its pose")
    if proximity is not None and poses is None:
        raise ValueError("proximity= needs poses=: the alarm places each acquisition with its pose")
    return None if poses is None else MovingEncoder(poses, grid, proximity=proximity)


def _feeder(grid: GridOption, poses: PoseFeed) -> GridFeeder:
    if isinstance(grid, GridFeeder):
        return grid
    if isinstance(grid, GridParams):
        return GridFeeder(CertaintyGrid(grid), poses)
    if isinstance(grid, CertaintyGrid):
        return GridFeeder(grid, poses)
    raise TypeError(
        f"grid= takes a GridParams, a CertaintyGrid or a GridFeeder, not {type(grid).__name__}"
    )


def _proximity_feeder(proximity: ProximityOption, poses: PoseFeed) -> ProximityFeeder:
    if isinstance(proximity, ProximityFeeder):
        return proximity
    if isinstance(proximity, ProximityZone):
        return ProximityFeeder(ProximityAlarm(proximity), poses)
    if isinstance(proximity, ProximityAlarm):
        return ProximityFeeder(proximity, poses)
    raise TypeError(
        "proximity= takes a ProximityZone, a ProximityAlarm or a ProximityFeeder, not "
        f"{type(proximity).__name__}"
    )


def _everything(topic: str) -> bool:
    return True


class MovingEncoder:
    """The messages of a moving robot for one sink, batch by batch (see the module).

    ``poses`` is the vehicle's pose (a :class:`PoseFeed`, on the sensor's hardware clock);
    ``grid`` (None: no grid) what :data:`GridOption` says, ``proximity`` (None: no alarm) what
    :data:`ProximityOption` says. ``wait_s`` is how long a scan waits
    for its poses (:data:`WAIT_S`), ``poll_s`` how often a pose object without ``since`` is
    copied (:data:`POSE_POLL_S`). Used from one thread (the sink's); the counts may be read
    from any.

    Raises:
        TypeError: ``poses`` lacks ``poses_at``, ``span`` or a way to give its samples, or
            ``grid`` or ``proximity`` is none of its kinds.
        ValueError: ``wait_s`` or ``poll_s`` is not a number of seconds >= 0.
    """

    def __init__(
        self,
        poses: PoseFeed,
        grid: GridOption | None = None,
        *,
        proximity: ProximityOption | None = None,
        wait_s: float = WAIT_S,
        poll_s: float = POSE_POLL_S,
    ) -> None:
        for name in ("poses_at", "span"):
            if not callable(getattr(poses, name, None)):
                raise TypeError(
                    f"poses= takes a pose buffer (biris_hw.io.pose.PoseBuffer), not "
                    f"{type(poses).__name__}: it has no {name}()"
                )
        if not isinstance(poses, _Since) and not callable(getattr(poses, "samples", None)):
            raise TypeError(
                f"poses= must give its samples (samples() or since(t)); "
                f"{type(poses).__name__} does not"
            )
        for name, value in (("wait_s", wait_s), ("poll_s", poll_s)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a number of seconds >= 0, not {value!r}")
        self.poses = poses
        self.feeder: GridFeeder | None = None if grid is None else _feeder(grid, poses)
        self.proximity_feeder: ProximityFeeder | None = (
            None if proximity is None else _proximity_feeder(proximity, poses)
        )
        self.wait_s = float(wait_s)
        self.poll_s = float(poll_s)
        self._since = poses if isinstance(poses, _Since) else None
        self._next_poll = -math.inf
        self._last_pose = -math.inf
        self._seen = -math.inf
        """The newest hardware time the sink has been handed (data or a status)."""
        self._first = math.inf
        """The oldest such time."""
        self._pending: list[Scan] = []
        self.poses_out = 0
        """Pose samples handed on (each once, on ``/odom`` and ``/tf``)."""
        self.placed_scans = 0
        """Scans put on ``/biris/points`` in ``odom`` (all or some of their acquisitions)."""
        self.unplaced_scans = 0
        """Completed scans none of whose acquisitions had a pose: no cloud."""
        self.unplaced_points = 0
        """Acquisitions of completed scans left out of their cloud for want of a pose."""
        self.grid_messages = 0
        self.proximity_messages = 0
        """Answers of the proximity alarm made (on ``/biris/proximity``)."""
        self._answered = -math.inf
        """The stamp of the last of them."""

    # -- what it adds ----------------------------------------------------------------------------
    @property
    def grid(self) -> CertaintyGrid | None:
        return None if self.feeder is None else self.feeder.grid

    @property
    def alarm(self) -> ProximityAlarm | None:
        return None if self.proximity_feeder is None else self.proximity_feeder.alarm

    @property
    def topics(self) -> dict[str, str]:
        """The topics it adds beside :data:`~biris_hw.io.codec.TOPICS` (whose ``/tf`` and
        ``/biris/points`` it also writes to), and their types."""
        topics = {codec.ODOM_TOPIC: codec.ODOMETRY}
        if self.feeder is not None:
            topics[codec.GRID_TOPIC] = codec.OCCUPANCY_GRID
        if self.proximity_feeder is not None:
            topics[codec.PROXIMITY_TOPIC] = codec.PROXIMITY
        return topics

    def describe(self) -> dict[str, object]:
        """What a recording's ``biris`` metadata says of it."""
        out: dict[str, object] = {
            "frame": codec.ODOM_FRAME,
            "poses": f"{codec.ODOM_TOPIC}; {codec.ODOM_FRAME} -> {codec.VEHICLE_FRAME} on "
            f"{codec.TF_TOPIC}",
        }
        grid = self.grid
        if grid is not None:
            params = grid.params
            out["grid"] = {
                "topic": codec.GRID_TOPIC,
                "resolution_m": params.resolution_m,
                "extent_m": list(params.extent_m),
                "band_m": list(params.band_m),
                "half_life_s": params.half_life_s,
            }
        feeder = self.proximity_feeder
        if feeder is not None:
            zone = feeder.alarm.zone
            out["proximity"] = {
                "topic": codec.PROXIMITY_TOPIC,
                "rate_hz": 1.0 / feeder.period_s,
                "front_m": zone.front_m,
                "width_m": zone.width_m,
                "length_m": zone.length_m,
                "time_s": zone.time_s,
                "band_m": list(zone.band_m),
                "memory_s": zone.memory_s,
            }
        return out

    def counts(self) -> dict[str, object]:
        """The counts a recording's diagnostics and end record carry."""
        counts: dict[str, object] = {
            "poses": self.poses_out,
            "placed_scans": self.placed_scans,
            "unplaced_scans": self.unplaced_scans,
            "unplaced_points": self.unplaced_points,
        }
        grid = self.grid
        if grid is not None:
            counts["grid_messages"] = self.grid_messages
            counts["grid_acquisitions"] = grid.acquisitions
            counts["grid_unplaced"] = grid.unplaced
        alarm = self.alarm
        if alarm is not None:
            counts["proximity_messages"] = self.proximity_messages
            counts["proximity_acquisitions"] = alarm.acquisitions
            counts["proximity_unplaced"] = alarm.unplaced
        return counts

    @staticmethod
    def warm() -> None:
        """Pay the one-time costs of its message types now (the typestore, the schema texts,
        rosbags' generated OccupancyGrid and Proximity encoders), not on the first batch."""
        for msgtype in (codec.ODOMETRY, codec.OCCUPANCY_GRID, codec.PROXIMITY):
            codec.warm(msgtype)
        codec.encode_occupancy_grid(np.zeros((1, 1), dtype=np.int8), 1.0, (0.0, 0.0), 0.0)
        nan = math.nan
        codec.encode_proximity(
            0.0, found=False, distance_m=math.inf, x_m=nan, y_m=nan, age_s=nan,
            looked_age_s=math.inf, zone_length_m=1.0, zone_width_m=1.0, speed_mps=0.0,
        )  # fmt: skip

    # -- a batch ---------------------------------------------------------------------------------
    def messages(
        self, batch: Batch, wanted: Callable[[str], bool] = _everything
    ) -> list[codec.Encoded]:
        """The messages ``batch`` gives on the topics ``wanted`` says yes to, in log-time order;
        a ``final`` batch hands on everything left."""
        times = [p.t for p in batch.points] + [codec.scan_time(s) for s in batch.scans]
        if batch.status is not None:
            times.append(batch.status.t)
        if times:
            self._seen = max(self._seen, *times)
            self._first = min(self._first, *times)
        out: list[codec.Encoded] = []
        samples = self._new_samples(batch.final)
        if samples:
            self.poses_out += len(samples)
            if wanted(codec.ODOM_TOPIC):
                out.extend(codec.odometry_messages(samples))
            if wanted(codec.TF_TOPIC):
                out.extend(codec.odom_transform_messages(samples))
        if wanted(codec.POINTS_TOPIC):
            self._pending.extend(batch.scans)
        out.extend(self._placed(batch.final))
        grid = self._grid(batch, wanted)
        if grid is not None:
            out.append(grid)
        out.extend(self._proximity(batch, wanted))
        out.sort(key=lambda m: m.log_time_ns)
        return out

    def _new_samples(self, final: bool) -> list[PoseSample]:
        """The samples not handed on yet, up to the newest time seen (all of them at the end)."""
        if self._since is not None:
            fresh = list(self._since.since(self._last_pose))
        else:
            now = time.monotonic()
            if not final and now < self._next_poll:
                return []
            self._next_poll = now + self.poll_s
            span = self.poses.span()
            if span is None or span[1] <= self._last_pose:
                return []
            fresh = [s for s in self.poses.samples() if s.t > self._last_pose]
        if self._last_pose == -math.inf:  # the first: from LEAD_S before the first data
            fresh = [s for s in fresh if s.t >= self._first - LEAD_S]
        if not final:
            fresh = [s for s in fresh if s.t <= self._seen]
        if fresh:
            self._last_pose = fresh[-1].t
        return fresh

    def _placed(self, final: bool) -> list[codec.Encoded]:
        """The clouds of the waiting scans whose poses are known now (or never will be)."""
        if not self._pending:
            return []
        span = self.poses.span()
        newest_pose = -math.inf if span is None else span[1]
        out: list[codec.Encoded] = []
        waiting: list[Scan] = []
        for scan in self._pending:
            last = float(scan.t[-1]) if scan.n_acq else -math.inf
            if not (final or last <= newest_pose or self._seen - last > self.wait_s):
                waiting.append(scan)
                continue
            placed = deskewed(scan, self.poses)
            missing = int(placed.unplaced.size)
            self.unplaced_points += missing
            if scan.n_acq and missing == scan.n_acq:
                self.unplaced_scans += 1
                continue
            self.placed_scans += 1
            out.append(codec.placed_cloud(scan, placed.grid))
        self._pending = waiting
        return out

    def _grid(self, batch: Batch, wanted: Callable[[str], bool]) -> codec.Encoded | None:
        """Feed the grid the batch's acquisitions; its message when one is due (or at the
        end), if wanted."""
        feeder = self.feeder
        if feeder is None:
            return None
        if batch.points:
            feeder.add(batch.points)
        if batch.final:
            feeder.flush()
        if not wanted(codec.GRID_TOPIC):
            return None
        if not batch.final and not (batch.points and feeder.due(batch.points[-1].t)):
            return None
        grid = feeder.grid
        if grid.acquisitions == 0:
            return None
        self.grid_messages += 1
        return grid.message()

    def _proximity(self, batch: Batch, wanted: Callable[[str], bool]) -> list[codec.Encoded]:
        """Feed the alarm the batch's acquisitions; its answers at the times they are owed
        (and at the end, unless the last one was at the same time), if wanted."""
        feeder = self.proximity_feeder
        if feeder is None:
            return []
        if batch.points:
            feeder.add(batch.points)
        if batch.final:
            feeder.flush()
        owed = feeder.due()  # named once: an unwatched topic owes nothing afterwards
        if not wanted(codec.PROXIMITY_TOPIC):
            return []
        if batch.final and feeder.known_t > max(self._answered, *owed, -math.inf):
            owed.append(feeder.known_t)
        out: list[codec.Encoded] = []
        for t in owed:
            answer = feeder.answer(t)
            if answer is None:
                continue
            self._answered = answer.t
            self.proximity_messages += 1
            out.append(answer.message())
        return out
