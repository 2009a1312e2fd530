"""Where the simulated vehicle is at every hardware instant: a path made of constant-twist pieces.

A robot base drives in the plane, so its pose is (x, y, yaw) in the scene's frame and its motion
at any instant is a twist: a forward speed ``v`` and a yaw rate ``w`` (a wheeled base does not
slip sideways). Every path the simulator offers is a sequence of pieces of constant twist:
standing (v = w = 0), a straight run (w = 0), an arc (w = v / r) and a turn on the spot (v = 0).
Over a piece that starts at (x0, y0, yaw0) at time t0, after tau = t - t0::

    yaw = yaw0 + w tau
    (x, y) = (x0, y0) + v tau sinc(w tau / 2) (cos, sin)(yaw0 + w tau / 2)

which is exact for every piece (the chord of an arc, at the mean heading; a straight run when
w = 0) and needs no special case. So any pose is exact and costs a bisection and a few
trigonometric calls: the optics ask for one per acquisition, on the simulator's hot path, and the
odometry asks for arrays of them (:meth:`Trajectory.poses`).

The vehicle starts at the scene's origin facing +x (a :meth:`Trajectory.line` faces its heading
from the start), stands there until ``start_s`` (hardware seconds), then drives. A line and an arc
go on for ever; a path of waypoints ends standing on its last waypoint. Yaw is reported in
[-pi, pi).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["DEFAULT_TURN_RATE_DEG_S", "Pose", "Trajectory", "wrap_angle"]

FloatArray = NDArray[np.float64]
Pose = tuple[float, float, float]
"""(x_m, y_m, yaw_rad) of the vehicle in the scene's frame."""

DEFAULT_TURN_RATE_DEG_S = 90.0
"""How fast a vehicle following waypoints turns on the spot to face its next leg: a slow,
deliberate turn for a small indoor base."""

_TWO_PI = 2.0 * math.pi


def wrap_angle(angle: float) -> float:
    """``angle`` (radians) brought into [-pi, pi)."""
    return (angle + math.pi) % _TWO_PI - math.pi


def _finite(name: str, value: float) -> float:
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite number, not {value!r}")
    return number


def _positive(name: str, value: float) -> float:
    number = _finite(name, value)
    if not number > 0.0:
        raise ValueError(f"{name} must be positive, not {value!r}")
    return number


@dataclass(frozen=True)
class _Piece:
    """One piece of constant twist: where and when it starts, and its twist."""

    t0: float
    x0: float
    y0: float
    yaw0: float
    v: float
    w: float


def _advance(x0: float, y0: float, yaw0: float, v: float, w: float, tau: float) -> Pose:
    turn = w * tau
    half = 0.5 * turn
    chord = v * tau * (math.sin(half) / half if half != 0.0 else 1.0)
    mean = yaw0 + half
    return (x0 + chord * math.cos(mean), y0 + chord * math.sin(mean), yaw0 + turn)


class Trajectory:
    """The vehicle's path through the scene: exact pose and twist at any hardware time.

    Make one with :meth:`line`, :meth:`arc`, :meth:`waypoints` or :meth:`standing`; it is an
    immutable value, safe to share between threads.
    """

    def __init__(self, pieces: Sequence[_Piece], end_s: float, name: str) -> None:
        self._pieces = tuple(pieces)
        self._starts = [p.t0 for p in self._pieces]
        self._end_s = end_s
        self._name = name
        cols = np.array(
            [(p.t0, p.x0, p.y0, p.yaw0, p.v, p.w) for p in self._pieces], dtype=np.float64
        )
        self._cols = tuple(np.ascontiguousarray(cols[:, i]) for i in range(6))

    # --- the paths ---------------------------------------------------------------------------

    @classmethod
    def standing(cls) -> Trajectory:
        """A vehicle that never moves: at the origin, facing +x (the simulator's default)."""
        return cls([_Piece(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)], 0.0, "standing()")

    @classmethod
    def line(
        cls, speed_mps: float, heading_deg: float = 0.0, *, start_s: float = 0.0
    ) -> Trajectory:
        """Straight on for ever at ``speed_mps`` along ``heading_deg`` (counter-clockwise from
        +x), facing that way from the start."""
        v = _positive("speed_mps", speed_mps)
        yaw = math.radians(_finite("heading_deg", heading_deg))
        t0 = _finite("start_s", start_s)
        return cls(
            [_Piece(t0, 0.0, 0.0, yaw, v, 0.0)],
            math.inf,
            f"line(speed_mps={v:g}, heading_deg={heading_deg:g}, start_s={t0:g})",
        )

    @classmethod
    def arc(cls, speed_mps: float, radius_m: float, *, start_s: float = 0.0) -> Trajectory:
        """Round a circle for ever at ``speed_mps``: a positive ``radius_m`` turns left
        (counter-clockwise, centre at (0, r)), a negative one right (centre at (0, r) too)."""
        v = _positive("speed_mps", speed_mps)
        r = _finite("radius_m", radius_m)
        if r == 0.0:
            raise ValueError("radius_m must not be 0 (a turn on the spot is not an arc)")
        t0 = _finite("start_s", start_s)
        return cls(
            [_Piece(t0, 0.0, 0.0, 0.0, v, v / r)],
            math.inf,
            f"arc(speed_mps={v:g}, radius_m={r:g}, start_s={t0:g})",
        )

    @classmethod
    def waypoints(
        cls,
        points: Iterable[tuple[float, float, float]],
        *,
        start_s: float = 0.0,
        turn_rate_deg_s: float = DEFAULT_TURN_RATE_DEG_S,
    ) -> Trajectory:
        """Through each ``(x_m, y_m, speed_mps)`` in turn, straight from the previous point (the
        origin first) at that speed; before each leg the vehicle turns on the spot, the short
        way, at ``turn_rate_deg_s`` to face it. It ends standing on the last point."""
        rate = math.radians(_positive("turn_rate_deg_s", turn_rate_deg_s))
        t = _finite("start_s", start_s)
        x, y, yaw = 0.0, 0.0, 0.0
        pieces: list[_Piece] = []
        given = list(points)
        if not given:
            raise ValueError("waypoints needs at least one (x_m, y_m, speed_mps)")
        for i, point in enumerate(given):
            if len(point) != 3:
                raise ValueError(f"waypoint {i} must be (x_m, y_m, speed_mps), not {point!r}")
            px = _finite(f"waypoint {i} x_m", point[0])
            py = _finite(f"waypoint {i} y_m", point[1])
            v = _positive(f"waypoint {i} speed_mps", point[2])
            length = math.hypot(px - x, py - y)
            if length == 0.0:
                raise ValueError(f"waypoint {i} ({px:g}, {py:g}) is where the vehicle already is")
            turn = wrap_angle(math.atan2(py - y, px - x) - yaw)
            if turn != 0.0:
                duration = abs(turn) / rate
                pieces.append(_Piece(t, x, y, yaw, 0.0, math.copysign(rate, turn)))
                t += duration
                yaw += turn
            pieces.append(_Piece(t, x, y, yaw, v, 0.0))
            t += length / v
            x, y = px, py  # the point itself, not the sum of the pieces: no drift of rounding
        pieces.append(_Piece(t, x, y, yaw, 0.0, 0.0))
        return cls(pieces, t, f"waypoints({len(given)} points, start_s={start_s:g})")

    # --- what it says --------------------------------------------------------------------------

    @property
    def end_s(self) -> float:
        """Hardware time from which the vehicle stands still for good (inf: never)."""
        return self._end_s

    @property
    def moves(self) -> bool:
        """False for :meth:`standing`: no piece has any twist."""
        return any(p.v != 0.0 or p.w != 0.0 for p in self._pieces)

    def __repr__(self) -> str:
        return f"Trajectory.{self._name}"

    def _piece(self, t: float) -> _Piece | None:
        i = bisect.bisect_right(self._starts, t) - 1
        return self._pieces[i] if i >= 0 else None

    def pose(self, t_hw: float) -> Pose:
        """(x_m, y_m, yaw_rad) at hardware time ``t_hw``; yaw in [-pi, pi)."""
        piece = self._piece(t_hw)
        if piece is None:  # before the first piece: at the start, facing the first heading
            first = self._pieces[0]
            return (first.x0, first.y0, wrap_angle(first.yaw0))
        x, y, yaw = _advance(piece.x0, piece.y0, piece.yaw0, piece.v, piece.w, t_hw - piece.t0)
        return (x, y, wrap_angle(yaw))

    def twist(self, t_hw: float) -> tuple[float, float]:
        """(forward speed m/s, yaw rate rad/s) at ``t_hw``: the piece's that starts at or before
        it (at a corner, the new piece's)."""
        piece = self._piece(t_hw)
        return (0.0, 0.0) if piece is None else (piece.v, piece.w)

    def poses(self, t_hw: ArrayLike, *, unwrapped: bool = False) -> tuple[FloatArray, ...]:
        """:meth:`pose` at every time of ``t_hw``: three arrays (x, y, yaw) of its shape.

        ``unwrapped`` leaves yaw continuous (it grows without bound on an arc), which is what a
        consumer differencing yaws wants."""
        t = np.asarray(t_hw, dtype=np.float64)
        t0, x0, y0, yaw0, v, w = self._cols
        i = np.searchsorted(t0, t, side="right") - 1
        before = i < 0
        i = np.maximum(i, 0)
        tau = np.where(before, 0.0, t - t0[i])
        vi, wi = v[i], w[i]
        half = 0.5 * wi * tau
        chord = vi * tau * np.sinc(half / math.pi)  # numpy's sinc is sin(pi x) / (pi x)
        mean = yaw0[i] + half
        x = x0[i] + chord * np.cos(mean)
        y = y0[i] + chord * np.sin(mean)
        yaw = yaw0[i] + wi * tau
        if not unwrapped:
            yaw = (yaw + math.pi) % _TWO_PI - math.pi
        return x, y, yaw

    def twists(self, t_hw: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """:meth:`twist` at every time of ``t_hw``: (speed, yaw rate) arrays of its shape."""
        t = np.asarray(t_hw, dtype=np.float64)
        t0, _, _, _, v, w = self._cols
        i = np.searchsorted(t0, t, side="right") - 1
        before = i < 0
        i = np.maximum(i, 0)
        return np.where(before, 0.0, v[i]), np.where(before, 0.0, w[i])
