"""The simulated robot base's odometry: the vehicle's pose as its wheels and gyro report it.

A robot base publishes where it believes it is, at a fixed rate, stamped with its clock: here
sample k is stamped ``k / rate_hz`` hardware seconds (50 Hz by default), from hardware time 0.
It believes what it integrates, so its errors accumulate the way a real base's do: each sample's
motion since the previous one (the true motion, in the vehicle's frame, from the
:class:`~sim.trajectory.Trajectory`) is scaled by ``1 + scale_error`` (wheels of the wrong size)
and by ``1 + distance_noise n1``, its turn gets ``(yaw_rate_bias_rad_s + yaw_rate_noise_rad_s
n2) dt`` added (a gyro's bias and white noise), n1 and n2 being standard normal draws, and the
increments are summed from the true pose at time 0. With no drift and no noise the samples are
the truth at their stamps (the sum of the true increments; rounding aside), so ``odom`` is the
scene's frame. The reported velocities are the true twist at the stamp with the same errors.

There is no thread: samples are made when someone asks, from the trajectory and the seeded
generator, and handed out once the time base's ``now()`` reaches their stamps. They are made in
fixed blocks of :data:`BLOCK` stamps (two draws per sample, in stamp order), whenever and in
whatever pieces they are asked for, so the same seed gives the same samples to the last bit, and
on virtual time they are exact. A consumer polls :meth:`Odometry.since` with the stamp of
the last sample it has, or waits for the next one with :meth:`Odometry.wait` (a sleep through the
time base until its stamp: time can jump to it). The newest ``history`` samples are held; a
consumer that polls less often loses the oldest, and the gap in ``seq`` says so.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from biris_hw.data import PoseSample
from biris_hw.timebase import TimeBase, timebase_of
from sim.trajectory import Trajectory

__all__ = ["DEFAULT_ODOMETRY", "Odometry", "OdometryParams", "OdometrySample"]

_STREAM_KEY = 0x0D0E
"""Mixed into the seed, so that odometry noise is independent of the rig's other generators."""

BLOCK = 256
"""Samples made per vectorised step, from a multiple of it: the sums that integrate the motion
then run over the same stamps however the samples are asked for, so they round the same."""


@dataclass(frozen=True)
class OdometryParams:
    """How the simulated base reports its motion; the defaults are a perfect base at 50 Hz."""

    rate_hz: float = 50.0
    scale_error: float = 0.0
    """Reported distance = (1 + scale_error) x true distance (e.g. 0.02: wheels 2 % too big)."""
    yaw_rate_bias_rad_s: float = 0.0
    """Added to every yaw rate: the reported heading drifts by this much per second."""
    distance_noise: float = 0.0
    """1 sigma of each sample's distance error, as a fraction of that sample's distance."""
    yaw_rate_noise_rad_s: float = 0.0
    """1 sigma of the white noise on each sample's yaw rate (its turn gets this times 1/rate)."""
    history: int = 3000
    """Samples held for consumers (60 s at 50 Hz)."""
    seed: int | None = None
    """Seed of the noise; None: the rig's seed."""

    def __post_init__(self) -> None:
        for name in ("rate_hz", "scale_error", "yaw_rate_bias_rad_s"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite, not {getattr(self, name)!r}")
        if not self.rate_hz > 0.0:
            raise ValueError(f"rate_hz must be positive, not {self.rate_hz!r}")
        if not self.scale_error > -1.0:
            raise ValueError(f"scale_error must be above -1, not {self.scale_error!r}")
        for name in ("distance_noise", "yaw_rate_noise_rad_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, not {value!r}")
        if isinstance(self.history, bool) or not isinstance(self.history, int) or self.history < 1:
            raise ValueError(f"history must be a positive whole number, not {self.history!r}")

    @property
    def noisy(self) -> bool:
        return self.distance_noise > 0.0 or self.yaw_rate_noise_rad_s > 0.0


DEFAULT_ODOMETRY = OdometryParams()


OdometrySample = PoseSample
"""One odometry message: pose in ``odom`` and twist in the vehicle frame, at stamp ``t`` (the
driver's :class:`~biris_hw.data.PoseSample`, so a pose buffer takes it as it is): ``t`` is
``seq / rate_hz`` hardware seconds, yaw in [-pi, pi), ``v_mps`` the forward speed (the vehicle
does not move sideways), ``omega_rad_s`` the yaw rate, and ``seq`` counts from hardware time 0,
consecutive, so a gap shows samples a consumer missed."""


class Odometry:
    """The base's odometry stream over ``trajectory``, on the clock ``clock`` (hardware seconds).

    Thread-safe. ``timebase`` is what :meth:`wait` sleeps through (default: the one ``clock``
    belongs to, :func:`~biris_hw.timebase.timebase_of`).
    """

    def __init__(
        self,
        trajectory: Trajectory,
        params: OdometryParams = DEFAULT_ODOMETRY,
        *,
        seed: int = 0,
        clock: Callable[[], float],
        timebase: TimeBase | None = None,
    ) -> None:
        self._trajectory = trajectory
        self._params = params
        self._clock = clock
        self._timebase = timebase if timebase is not None else timebase_of(clock)
        self._rate = float(params.rate_hz)
        entropy = [params.seed if params.seed is not None else seed, _STREAM_KEY]
        self._rng = np.random.default_rng(np.random.SeedSequence(entropy))
        self._lock = threading.Lock()
        self._held: list[OdometrySample] = []  # made, oldest first: the due ones and a few more
        self._next = 0  # the first sample not yet made
        x, y, yaw = (float(a) for a in trajectory.poses(0.0, unwrapped=True))
        self._true_prev = (x, y, yaw)  # the truth at the last stamp made (at 0 before any)
        self._odom_prev = (x, y, yaw)  # what the base believed then

    @property
    def params(self) -> OdometryParams:
        return self._params

    @property
    def trajectory(self) -> Trajectory:
        return self._trajectory

    @property
    def period_s(self) -> float:
        return 1.0 / self._rate

    def stamp(self, seq: int) -> float:
        """Hardware time of sample ``seq``."""
        return seq / self._rate

    def _first_after(self, t_hw: float) -> int:
        """The first sample whose stamp is later than ``t_hw``."""
        if t_hw < 0.0:
            return 0
        k = math.floor(t_hw * self._rate)
        while self.stamp(k) > t_hw:  # the product rounds: settle on the stamps themselves
            k -= 1
        while self.stamp(k + 1) <= t_hw:
            k += 1
        return k + 1

    # --- what consumers call ----------------------------------------------------------------

    def latest(self) -> OdometrySample:
        """The newest sample (stamp at or before now)."""
        with self._lock:
            due = self._catch_up()
            return self._held[due - 1 - self._held[0].seq]

    def since(self, t_hw: float) -> list[OdometrySample]:
        """Every held sample stamped after ``t_hw`` and at or before now, oldest first (empty if
        none is due yet). Pass the ``t`` of the last sample you have; ``-1.0`` for all held."""
        with self._lock:
            due = self._catch_up()
            first = self._held[0].seq
            start = max(due - self._params.history, self._first_after(t_hw))
            return self._held[max(0, start - first) : max(0, due - first)]

    def wait(self, after_t_hw: float, timeout_hw: float | None = None) -> list[OdometrySample]:
        """:meth:`since` once the first sample after ``after_t_hw`` is due, sleeping through the
        time base until its stamp (or for ``timeout_hw`` hardware seconds, then whatever is
        due: possibly nothing)."""
        due = self.stamp(self._first_after(after_t_hw))
        if timeout_hw is not None:
            due = min(due, self._clock() + max(0.0, timeout_hw))
        self._timebase.sleep_until(due, what="the next odometry sample")
        return self.since(after_t_hw)

    # --- making samples -----------------------------------------------------------------------

    def _catch_up(self) -> int:
        """Make every sample due by now (under the lock); return how many are due."""
        due = max(1, self._first_after(self._clock()))  # sample 0 is the start: always there
        keep = self._params.history
        while self._next < due:
            self._make(self._next, self._next + BLOCK, due - keep)
        if self._held and self._held[0].seq < due - 2 * keep:  # trim now and then
            del self._held[: due - keep - self._held[0].seq]
        return due

    def _make(self, k0: int, k1: int, wanted: int) -> None:
        """Make samples k0 .. k1 - 1; hold those from ``wanted`` on."""
        p = self._params
        seq = np.arange(k0, k1)
        t = seq / self._rate
        x, y, yaw = self._trajectory.poses(t, unwrapped=True)
        v, w = self._trajectory.twists(t)
        px = np.concatenate(([self._true_prev[0]], x[:-1]))
        py = np.concatenate(([self._true_prev[1]], y[:-1]))
        pyaw = np.concatenate(([self._true_prev[2]], yaw[:-1]))
        # the true motion since the previous stamp, in the vehicle's frame then
        dx, dy = x - px, y - py
        c, s = np.cos(pyaw), np.sin(pyaw)
        forward = c * dx + s * dy
        left = c * dy - s * dx
        dt = np.where(seq == 0, 0.0, 1.0 / self._rate)  # sample 0 is the start itself
        if p.noisy:
            n = self._rng.standard_normal((seq.size, 2))
            gain = (1.0 + p.scale_error) * (1.0 + p.distance_noise * n[:, 0])
            rate_error = p.yaw_rate_bias_rad_s + p.yaw_rate_noise_rad_s * n[:, 1]
        else:
            gain = np.full(seq.size, 1.0 + p.scale_error)
            rate_error = np.full(seq.size, p.yaw_rate_bias_rad_s)
        # what the base believes: its own increments, summed from where it believed it was
        ox0, oy0, oyaw0 = self._odom_prev
        oyaw = oyaw0 + np.cumsum((yaw - pyaw) + rate_error * dt)
        oyaw_prev = np.concatenate(([oyaw0], oyaw[:-1]))
        oc, os_ = np.cos(oyaw_prev), np.sin(oyaw_prev)
        ox = ox0 + np.cumsum(gain * (oc * forward - os_ * left))
        oy = oy0 + np.cumsum(gain * (os_ * forward + oc * left))
        self._true_prev = (float(x[-1]), float(y[-1]), float(yaw[-1]))
        self._odom_prev = (float(ox[-1]), float(oy[-1]), float(oyaw[-1]))
        self._next = k1
        tail = slice(min(seq.size, max(0, wanted - k0)), None)  # only what can still be held
        wrapped = (oyaw[tail] + math.pi) % (2.0 * math.pi) - math.pi
        self._held.extend(
            OdometrySample(*row)
            for row in zip(
                t[tail].tolist(),
                ox[tail].tolist(),
                oy[tail].tolist(),
                wrapped.tolist(),
                (v * gain)[tail].tolist(),
                (w + rate_error)[tail].tolist(),
                seq[tail].tolist(),
                strict=True,
            )
        )
