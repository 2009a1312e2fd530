"""The vehicle's recent poses, and the pose at any acquisition's time (interpolated, or marked).

A scan is taken over most of a second while the vehicle drives; to place each acquisition where
it was taken, a client needs the vehicle's pose at that acquisition's own time ``scan.t[k]``,
which no pose source sends: a base reports its pose at its own instants (50 Hz for the
simulator's). :class:`PoseBuffer` holds the newest samples (bounded) and answers
:meth:`~PoseBuffer.poses_at` for any hardware times, one array operation for a whole scan:

* **between two samples** no more than ``max_gap_s`` apart, the pose is interpolated: x and y
  linearly, yaw along the *unwrapped* difference (the short way round: a heading crossing pi
  goes on through it, not back round the circle);
* **beyond the newest sample** (or before the oldest) by no more than ``max_extrapolation_s``,
  it is carried on with that sample's twist (forward speed and yaw rate; a source without a
  twist, a transform, gets the one of its last two samples);
* **anywhere else** (a gap in the stream, a time not yet reached, a time older than the buffer
  holds) there is no pose, and the answer says so (``valid`` False, NaN in the pose): an
  acquisition is never placed by a guess that looks right.

**Clocks.** Acquisition times are on the sensor's hardware clock; a pose source stamps its
samples with its own. ``clock_offset_s`` is what turns one into the other, added to every
stamp as it enters: ``t_hw = t_source + clock_offset_s``. For the simulator it is 0 (its
odometry is stamped on the hardware clock). For a real base publishing ROS time (the system's
real-time clock, synchronised across the robot by NTP or PTP) beside a real target (whose
hardware clock is the host's ``time.monotonic()``), it is ``monotonic() - time()`` read on the
BIRIS host: :func:`clock_offset` reads it. docs/moving.md says more.

**Waiting.** Everything that waits here waits through a :class:`~biris_hw.timebase.TimeBase`:
the pump's sleeps between polls and a consumer's :meth:`PoseBuffer.wait_for`, so the buffer
runs unchanged on scaled real time and on a simulator's virtual time (where the pump wakes at
exactly each sample's stamp).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from types import TracebackType
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from biris_hw.data import PoseSample, VehiclePoses
from biris_hw.timebase import HwThread, ScaledTime, TimeBase

__all__ = [
    "DEFAULT_CAPACITY",
    "DEFAULT_MAX_EXTRAPOLATION_S",
    "DEFAULT_MAX_GAP_S",
    "PoseBuffer",
    "PosePump",
    "PoseSource",
    "clock_offset",
    "follow",
]

FloatArray = NDArray[np.float64]

DEFAULT_CAPACITY = 3000
"""Samples a buffer holds by default: 60 s at 50 Hz, far more than a scan lasts."""

DEFAULT_MAX_GAP_S = 0.1
"""Longest interval (hardware s) across which a pose is interpolated: five samples of a 50 Hz
base lost in a row. At 0.5 m/s and 90 deg/s a linear interpolation across 0.1 s errs by under
a millimetre sideways (the chord of an arc), so a gap this long is still safe to bridge."""

DEFAULT_MAX_EXTRAPOLATION_S = 0.05
"""Longest time (hardware s) beyond the newest (or before the oldest) sample a pose is carried
on with its twist: the last acquisitions of a scan handed over before the base's next sample
arrives. A base that changes speed or yaw rate within 50 ms errs by millimetres."""

_TWO_PI = 2.0 * math.pi


def _wrap(angle: FloatArray) -> FloatArray:
    wrapped: FloatArray = (angle + math.pi) % _TWO_PI - math.pi
    return wrapped


def _seconds(name: str, value: float, *, least: float | None = None, above: bool = False) -> float:
    """``value`` as float seconds: a finite number, at least (or, ``above``, more than)
    ``least`` when given; TypeError for a non-number, ValueError for a number out of range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name} must be a number of seconds, not {type(value).__name__}")
    number = float(value)
    low = least is not None and (number <= least if above else number < least)
    if not math.isfinite(number) or low:
        bound = "" if least is None else f" {'above' if above else 'at least'} {least:g}"
        raise ValueError(f"{name} must be a finite number{bound}, not {value!r}")
    return number


class PoseSource(Protocol):
    """What a :class:`PosePump` polls: the simulator's odometry (``rig.odometry``) is one.

    ``since(t)`` returns every sample the source holds stamped after ``t`` (on its own clock;
    ``-1.0`` for all it holds), oldest first, and never blocks; ``period_s`` is how often the
    source makes a sample, which sets when the pump looks again.
    """

    @property
    def period_s(self) -> float: ...

    def since(self, t_hw: float, /) -> Sequence[PoseSample]: ...


class PoseBuffer:
    """The newest ``capacity`` pose samples of one source, on the hardware clock.

    ``max_gap_s`` and ``max_extrapolation_s`` are the bounds within which a pose is given
    (module notes); ``clock_offset_s`` is added to every stamp as it enters. ``timebase`` is
    what :meth:`wait_for` waits through (the rig's or the server's, on a simulator; a real-time
    one by default). Thread-safe: sources add from their own threads (a pump, Zenoh's callbacks)
    while clients look poses up.

    Samples must arrive in stamp order. One not newer than the newest held is refused and
    counted in :attr:`refused` (a repeat, or a sample overtaken on the network), so the buffer
    stays ordered; a gap in ``seq`` is counted in :attr:`missed`.
    """

    def __init__(
        self,
        capacity: int = DEFAULT_CAPACITY,
        *,
        max_gap_s: float = DEFAULT_MAX_GAP_S,
        max_extrapolation_s: float = DEFAULT_MAX_EXTRAPOLATION_S,
        clock_offset_s: float = 0.0,
        timebase: TimeBase | None = None,
    ) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 2:
            raise ValueError(f"capacity must be a whole number of samples >= 2, not {capacity!r}")
        self.capacity = capacity
        self.max_gap_s = _seconds("max_gap_s", max_gap_s, least=0.0, above=True)
        self.max_extrapolation_s = _seconds("max_extrapolation_s", max_extrapolation_s, least=0.0)
        self._offset = _seconds("clock_offset_s", clock_offset_s)
        self.timebase: TimeBase = (
            timebase if timebase is not None else ScaledTime(1.0, clock=time.monotonic)
        )
        self._cond = self.timebase.Condition(threading.Lock())
        # columns t, x, y, yaw (unwrapped), v, omega; rows [start, end) hold the samples, in a
        # store twice the capacity so that appending moves the rows only once per capacity
        self._store = np.full((2 * capacity, 6), np.nan, dtype=np.float64)
        self._start = 0
        self._end = 0
        self._last_yaw = 0.0  # the newest sample's yaw as the source gave it (wrapped)
        self._last_seq: int | None = None
        self.added = 0
        """Samples taken in since the buffer was made."""
        self.refused = 0
        """Samples refused: stamped at or before the newest held, or not finite."""
        self.missed = 0
        """Samples the source numbered but never handed over (gaps in ``seq``)."""

    # -- the clock offset --------------------------------------------------------------------------

    @property
    def clock_offset_s(self) -> float:
        """Hardware seconds added to a source stamp: ``t_hw = t_source + clock_offset_s``.

        Setting it applies to samples added from then on (those held keep the offset they came
        in with): re-measure it now and then when the two clocks drift apart."""
        return self._offset

    @clock_offset_s.setter
    def clock_offset_s(self, value: float) -> None:
        self._offset = _seconds("clock_offset_s", value)

    # -- taking samples in ---------------------------------------------------------------------

    def add(self, sample: PoseSample) -> bool:
        """Take one sample in; False (and counted in :attr:`refused`) if it is not newer than
        the newest held or has a value that is not a finite number."""
        return self.extend((sample,)) == 1

    def extend(self, samples: Iterable[PoseSample]) -> int:
        """Take samples in, oldest first; how many were taken (see :meth:`add`)."""
        taken = 0
        with self._cond:
            for sample in samples:
                taken += self._add_locked(sample)
            if taken:
                self._cond.notify_all()
        return taken

    def _add_locked(self, sample: PoseSample) -> int:
        t = float(sample.t) + self._offset
        x, y, yaw = float(sample.x_m), float(sample.y_m), float(sample.yaw_rad)
        v, w = float(sample.v_mps), float(sample.omega_rad_s)
        if not all(math.isfinite(value) for value in (t, x, y, yaw)):
            self.refused += 1
            return 0
        n = self._end - self._start
        if n and t <= self._store[self._end - 1, 0]:
            self.refused += 1
            return 0
        if n:
            last = self._store[self._end - 1]
            unwrapped = last[3] + float(_wrap(np.float64(yaw - self._last_yaw)))
            dt = t - last[0]
            if not (math.isfinite(v) and math.isfinite(w)):
                # a transform says no twist: the one of the last interval, if it is short
                if dt <= self.max_gap_s:
                    w = (unwrapped - last[3]) / dt
                    mean = 0.5 * (last[3] + unwrapped)
                    v = (math.cos(mean) * (x - last[1]) + math.sin(mean) * (y - last[2])) / dt
                else:
                    v = w = math.nan
        else:
            unwrapped = yaw
        if self._end == self._store.shape[0]:
            keep = self.capacity - 1
            self._store[:keep] = self._store[self._end - keep : self._end]
            self._start, self._end = 0, keep
        elif n == self.capacity:
            self._start += 1
        self._store[self._end] = (t, x, y, unwrapped, v, w)
        self._end += 1
        self._last_yaw = yaw
        seq = int(sample.seq)
        if self._last_seq is not None and seq > self._last_seq + 1:
            self.missed += seq - self._last_seq - 1
        self._last_seq = seq
        self.added += 1
        return 1

    # -- what is held --------------------------------------------------------------------------

    def __len__(self) -> int:
        with self._cond:
            return self._end - self._start

    def span(self) -> tuple[float, float] | None:
        """(oldest, newest) stamp held, hardware seconds; None while empty."""
        with self._cond:
            if self._end == self._start:
                return None
            return float(self._store[self._start, 0]), float(self._store[self._end - 1, 0])

    def samples(self) -> list[PoseSample]:
        """The samples held, oldest first, on the hardware clock (yaw wrapped; the twist as
        held: derived for a source without one, NaN where it could not be). ``seq`` counts
        the held samples from 0."""
        with self._cond:
            rows = self._store[self._start : self._end].copy()
        yaw = _wrap(rows[:, 3])
        return [
            PoseSample(float(r[0]), float(r[1]), float(r[2]), float(a), float(r[4]), float(r[5]), i)
            for i, (r, a) in enumerate(zip(rows, yaw, strict=True))
        ]

    def since(self, t_hw: float, /) -> list[PoseSample]:
        """The samples held stamped after ``t_hw`` (hardware seconds), oldest first, as
        :meth:`samples` gives them (``seq`` their place among the held): a reader that hands
        each sample on once (the recorder's, the live view's, the service's ``/odom``) takes
        only the new ones by bisection, instead of copying the whole buffer each time.

        Raises:
            ValueError: ``t_hw`` is not a number (NaN included); ``-math.inf`` gives them all.
        """
        if isinstance(t_hw, bool) or not isinstance(t_hw, (int, float, np.integer, np.floating)):
            raise ValueError(f"since: t_hw must be a number of hardware seconds, not {t_hw!r}")
        after = float(t_hw)
        if math.isnan(after):
            raise ValueError("since: t_hw must be a number of hardware seconds, not nan")
        with self._cond:
            held = self._store[self._start : self._end, 0]
            first = int(np.searchsorted(held, after, side="right"))
            rows = self._store[self._start + first : self._end].copy()
        yaw = _wrap(rows[:, 3])
        return [
            PoseSample(
                float(r[0]), float(r[1]), float(r[2]), float(a), float(r[4]), float(r[5]), first + i
            )
            for i, (r, a) in enumerate(zip(rows, yaw, strict=True))
        ]

    def wait_for(self, t_hw: float, timeout_hw: float | None = None) -> bool:
        """Wait until a sample stamped at or after ``t_hw`` is held (so every time up to
        ``t_hw`` is between two samples), at most ``timeout_hw`` hardware seconds; True if one
        is. What a client calls before placing a scan whose newest acquisition is at ``t_hw``."""
        with self._cond:
            return bool(
                self._cond.wait_for(
                    lambda: self._end > self._start and self._store[self._end - 1, 0] >= t_hw,
                    timeout_hw,
                    what=f"a vehicle pose at t={t_hw:.6f}",
                )
            )

    # -- looking poses up ----------------------------------------------------------------------

    def pose_at(self, t_hw: float) -> tuple[float, float, float] | None:
        """(x_m, y_m, yaw_rad) of the vehicle in ``odom`` at hardware time ``t_hw``, yaw in
        [-pi, pi); None when no pose is known within the bounds (module notes)."""
        got = self.poses_at([t_hw])
        if not got.valid[0]:
            return None
        return (float(got.x_m[0]), float(got.y_m[0]), float(got.yaw_rad[0]))

    def poses_at(self, times: ArrayLike) -> VehiclePoses:
        """The vehicle's pose at each of ``times`` (hardware seconds, any order, 1-D), with
        ``valid`` False (and NaN) where none is known within the bounds: one array operation
        for a whole scan (``buffer.poses_at(scan.t)``)."""
        q = np.asarray(times, dtype=np.float64)
        if q.ndim != 1:
            raise ValueError(f"times must be a 1-D array of hardware seconds, not shape {q.shape}")
        with self._cond:
            rows = self._store[self._start : self._end]
            return self._lookup(q, rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4:6])

    def _lookup(
        self,
        q: FloatArray,
        t: FloatArray,
        x: FloatArray,
        y: FloatArray,
        yaw: FloatArray,
        twist: FloatArray,
    ) -> VehiclePoses:
        m = q.shape[0]
        n = t.shape[0]
        px = np.full(m, np.nan)
        py = np.full(m, np.nan)
        pyaw = np.full(m, np.nan)
        if n == 0:
            return VehiclePoses(q.copy(), px, py, pyaw, np.zeros(m, dtype=bool))
        finite = np.isfinite(q)
        right = np.searchsorted(t, q, side="right")  # the first sample after each time
        # between two samples (a time equal to a stamp is between it and the next, or at the
        # newest: then its own twist carries it on by 0 s, which is the sample itself)
        inner = finite & (right > 0) & (right < n)
        lo = np.clip(right - 1, 0, n - 1)
        hi = np.clip(right, 0, n - 1)
        gap = t[hi] - t[lo]
        inner &= gap <= self.max_gap_s
        inner |= finite & (right > 0) & (right < n) & (t[lo] == q)  # on a stamp: that sample
        with np.errstate(invalid="ignore", divide="ignore"):
            f = np.where(inner, (q - t[lo]) / np.where(gap > 0.0, gap, 1.0), 0.0)
        px = np.where(inner, x[lo] + f * (x[hi] - x[lo]), px)
        py = np.where(inner, y[lo] + f * (y[hi] - y[lo]), py)
        pyaw = np.where(inner, yaw[lo] + f * (yaw[hi] - yaw[lo]), pyaw)
        # beyond either end: carried on from the end sample with its twist
        after = finite & (right == n)
        before = finite & (right == 0)
        end = np.where(after, n - 1, 0)
        dt = np.where(after | before, q - t[end], 0.0)
        v, w = twist[end, 0], twist[end, 1]
        outer = (after | before) & (np.abs(dt) <= self.max_extrapolation_s)
        outer &= (dt == 0.0) | (np.isfinite(v) & np.isfinite(w))
        v0 = np.where(dt == 0.0, 0.0, v)
        w0 = np.where(dt == 0.0, 0.0, w)
        half = 0.5 * w0 * dt
        chord = v0 * dt * np.sinc(half / math.pi)  # the exact arc of a constant twist
        mean = yaw[end] + half
        px = np.where(outer, x[end] + chord * np.cos(mean), px)
        py = np.where(outer, y[end] + chord * np.sin(mean), py)
        pyaw = np.where(outer, yaw[end] + w0 * dt, pyaw)
        valid = inner | outer
        return VehiclePoses(q.copy(), px, py, np.where(valid, _wrap(pyaw), np.nan), valid)


def clock_offset(
    hardware_clock: Callable[[], float] = time.monotonic,
    source_clock: Callable[[], float] = time.time,
) -> float:
    """``hardware_clock() - source_clock()``, read as one instant (the source clock read on
    either side of the hardware clock, and averaged): the ``clock_offset_s`` of a real target
    (hardware clock: the host's monotonic clock) and a base stamping ROS time (the real-time
    clock), both on this host's time."""
    before = source_clock()
    hardware = hardware_clock()
    after = source_clock()
    return hardware - 0.5 * (before + after)


class PosePump:
    """A thread that moves samples from a :class:`PoseSource` into a :class:`PoseBuffer`.

    It polls the source once per source period, at the expected stamp of its next sample,
    sleeping through ``timebase`` (a participant of it: on virtual time it wakes exactly at
    each stamp, and the rig's time waits for it). ``stop()`` ends it at once. Use it as a
    context manager, or :func:`follow`.
    """

    def __init__(
        self,
        source: PoseSource,
        buffer: PoseBuffer,
        timebase: TimeBase | None = None,
        *,
        name: str = "biris-poses",
    ) -> None:
        period = float(source.period_s)
        if not (math.isfinite(period) and period > 0.0):
            raise ValueError(f"the source's period_s must be positive, not {period!r}")
        self.source = source
        self.buffer = buffer
        self.timebase = timebase if timebase is not None else buffer.timebase
        self._period = period
        self._stop = self.timebase.Event()
        self._thread: HwThread | None = None
        self._name = name
        self.error: BaseException | None = None
        """What ended the pump, if the source raised."""

    def start(self) -> PosePump:
        """Start pumping (once)."""
        if self._thread is not None:
            raise RuntimeError("the pose pump has already been started")
        self._thread = self.timebase.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop and join the thread (idempotent)."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            self.timebase.join_thread(thread)

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._thread.finished

    def __enter__(self) -> PosePump:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def _run(self) -> None:
        last = -math.inf
        # a hair past the next stamp: a stamp computed as k / rate may round a little late
        slack = self._period * 1e-6
        try:
            while not self._stop.is_set():
                got = self.source.since(last if math.isfinite(last) else -1.0)
                if got:
                    self.buffer.extend(got)
                    last = float(got[-1].t)
                now = self.timebase.now()
                due = last + self._period + slack if math.isfinite(last) else now + self._period
                if due <= now:  # nothing new when expected: look again a period on
                    due = now + self._period
                self._stop.wait(due - now, what="the next vehicle pose")
        except BaseException as exc:  # recorded for the owner; the thread ends quietly
            self.error = exc


@contextlib.contextmanager
def follow(
    source: PoseSource,
    timebase: TimeBase | None = None,
    **options: float | int,
) -> Iterator[PoseBuffer]:
    """``with follow(rig.odometry, rig.timebase) as poses: ...``: a :class:`PoseBuffer` (made
    with ``options``: ``capacity``, ``max_gap_s``, ``max_extrapolation_s``,
    ``clock_offset_s``) that a :class:`PosePump` keeps fed from ``source`` while the block
    runs."""
    buffer = PoseBuffer(timebase=timebase, **options)  # type: ignore[arg-type]
    with PosePump(source, buffer, timebase):
        yield buffer
