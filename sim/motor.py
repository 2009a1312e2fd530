"""The pan axis as the HCTL-1000 sees it: amplifier, DC motor, head inertia, friction, encoder.

The model exists so that the filter registers matter: Appendix B's defaults must give a stable,
well-damped loop and a bad gain written later must behave like a bad gain. Everything is referred
to the head (the gearbox is folded into the torque constant and the inertia), positions are in
encoder counts (4096 per head revolution, binary degrees) and time is hardware seconds.

Model::

    V        = command / 128 * 10 V                      linear amplifier, +-10 V full scale
    L di/dt  = V - R i - k w                              winding; back emf k w (k_e = k_t = k)
    J dw/dt  = k i - b w - T_c sgn(w)                     stiction: stuck while |k i| <= T_c

The winding inductance matters: without it the loop is so well damped that no gain makes it
oscillate, whereas a real servo does. Each ``step`` is split into ``substeps``; within a sub-step
the drive and the Coulomb torque are constant and the linear part is integrated exactly (a
zero-order-hold discretisation computed once per step length), so the integration is stable for
any step. When the velocity would change sign and the torque cannot beat friction, the head
stops and sticks.

Chosen constants (``PlantParams`` defaults), found by closing the chip's filter around the plant
in a scratch script and iterating on them::

    R = 4.0 ohm, L = 24 mH, k = 2.5 N m/A (at the head), J = 0.01 kg m^2,
    b = 0.05 N m s/rad, T_c = 0.12 N m

so the electrical time constant is 6 ms, the mechanical one 6.2 ms, the head's top speed at
10 V is 3.8 rad/s (2480 counts/s, 3.5 counts per 1.408 ms sample; Appendix B asks for 2) and a
command of +-3 units of R08H breaks it away from rest.

Measured closed loop, Appendix B defaults (sample 0xAF = 1.408 ms, A = 0x7F, B = 0xEF, K = 0x3F,
maximum velocity 2 counts/sample, acceleration 0x3322), trapezoids from rest of 3 to 4096 counts
either way from several sub-count starting positions:

    +1024 counts                512 samples (0.721 s) of profile
    motor command at speed      about +74 (of 127)
    following error at speed    18 counts
    overshoot                   0 counts for long moves, at most 2 counts (20-count moves)
    settled to +-2 counts       at most 9 samples (12.7 ms) after the last setpoint
    final error                 0 counts (the head sticks on target)

The tests hold the model to: overshoot <= 2 counts, settled within 20 ms of the profile's end,
final error 0.

Bad filters oscillate for ever (a limit cycle bounded by the amplifier's saturation), measured
over the second half-second after the same move: ``K = 0xFF, A = 0x00`` hunts +-19 counts around
the target, the error changing sign 19 times (about 19 Hz); ``K = 0xFF, B = 0x00`` hunts
+-16 counts with 25 sign changes. The tests require at least 10 sign changes and an amplitude of
at least 10 counts. Over 450 random filters and profiles (any sample timer, A, B, K, maximum
velocity and acceleration), a move to +4096 from rest followed by a hold of 1.5 to 5 s took the
head at most 21 counts past it (``K = 0xFF, A = 0x00``, a limit cycle; the reliability review's
random runs saw 18.7): the audit's allowance for overshoot
(:data:`sim.hctl1000.HEAD_OVERSHOOT_COUNTS`) rests on this.

Hard stops (beyond the report): the pan head's cable allows a little more than the +-0x1000
counts (+-360 degrees) the driver must keep to, and mechanical stops end the travel at
``PlantParams.stop_counts`` (+-(4096 + 256) counts from true zero by default, ``None`` for a
head that turns freely). A head that reaches a stop stops dead there: velocity 0, position held
at the stop for as long as the drive pushes into it (the winding current then settles as in a
held shaft), free to move away again when the drive reverses. Each impact counts in
:attr:`MotorPlant.stop_hits` (a head that arrives faster than its steady speed carries a
reversed winding current, which pulls it off the stop once more: a bounce is a second impact).
256 counts (22.5 degrees) is far beyond anything a driver that keeps to its envelope can
produce (21 counts, above), so touching a stop always means the head has been wound round,
which on the robot tears the cable.

Dead amplifier (a fault): the amplifier's output stays at 0 V whatever the command, so no
torque reaches the shaft; a moving head coasts to rest, braked by friction and by the back emf
through the winding, and then stays put. The chip cannot tell: its profile runs and ends as
usual.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from regs.hctl1000 import COUNTS_PER_REV

__all__ = ["COUNTS_PER_REV", "MotorPlant", "PlantParams"]


@dataclass(frozen=True)
class PlantParams:
    """Physical constants of the pan axis, referred to the head (gearbox folded in).

    The defaults are tuned so that Appendix B's filter gives a well-damped loop; the module
    docstring lists the step response they produce.
    """

    full_scale_volts: float = 10.0
    """Amplifier output for a motor command of -128 (and 127/128 of it for +127)."""
    resistance_ohm: float = 4.0
    inductance_h: float = 0.024
    torque_constant: float = 2.5
    """N m per A at the head; also the back-emf constant in V s/rad."""
    inertia: float = 0.01
    """Head, gearbox and rotor inertia seen at the head, kg m^2."""
    viscous_friction: float = 0.05
    """N m s/rad."""
    coulomb_friction: float = 0.12
    """N m; also the break-away (static) torque."""
    counts_per_rev: int = COUNTS_PER_REV
    substeps: int = 4
    """Integration sub-steps per ``step`` call (friction stops and index crossings)."""
    stop_counts: float | None = COUNTS_PER_REV + 256
    """Mechanical stops at +-this many counts from true azimuth 0; None turns freely.

    The default lets the cable 256 counts (22.5 degrees) beyond the driver's +-0x1000 envelope:
    an axis that keeps to its envelope never gets there (the worst overshoot measured is 21
    counts, see the module docstring), one wound round by a revolution always does."""

    def __post_init__(self) -> None:
        positive = ("full_scale_volts", "resistance_ohm", "inductance_h", "torque_constant")
        for name in (*positive, "inertia"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be positive")
        if self.viscous_friction < 0.0 or self.coulomb_friction < 0.0:
            raise ValueError("friction cannot be negative")
        if self.counts_per_rev < 1 or self.substeps < 1:
            raise ValueError("counts_per_rev and substeps must be at least 1")
        if self.stop_counts is not None and not self.stop_counts > 0.0:
            raise ValueError("stop_counts must be positive (or None for no stops)")


def _expm(m: np.ndarray) -> np.ndarray:
    """Matrix exponential by scaling and squaring a Taylor series (small, tame matrices only)."""
    norm = float(np.abs(m).sum(axis=1).max())
    squarings = max(0, math.ceil(math.log2(norm)) + 1) if norm > 0.5 else 0
    scaled = m / float(2**squarings)
    result = np.eye(m.shape[0])
    term = np.eye(m.shape[0])
    for k in range(1, 20):
        term = term @ scaled / k
        result = result + term
    for _ in range(squarings):
        result = result @ result
    return result


@dataclass(frozen=True)
class _Discrete:
    """Exact one-sub-step update of (theta counts, omega rad/s, current A) while moving."""

    h: float
    phi: tuple[tuple[float, float], ...]  # rows: theta (counts), omega, current; cols: omega, i
    volt: tuple[float, float, float]  # response to 1 V held over the sub-step
    fric: tuple[float, float, float]  # response to 1 N m of friction torque
    stuck_decay: float  # current decay while the shaft is held: exp(-R h / L)


class MotorPlant:
    """One servo axis: integrates the head's motion and counts encoder edges.

    The encoder counter is relative to power-up (it starts at 0 wherever the head happens to be);
    the head's absolute azimuth is only visible through the index latch, which is set whenever the
    head crosses true azimuth 0 (modulo one revolution) -- that is why homing must look for it.
    Not thread-safe: the board steps it under its lock.
    """

    def __init__(
        self,
        rng: np.random.Generator,
        params: PlantParams = PlantParams(),  # frozen, so sharing the default is harmless
        initial_azimuth_counts: float | None = None,
    ) -> None:
        self.params = params
        cpr = params.counts_per_rev
        if initial_azimuth_counts is None:
            initial_azimuth_counts = float(rng.uniform(-cpr / 2, cpr / 2))
        stop = math.inf if params.stop_counts is None else float(params.stop_counts)
        if not -stop <= initial_azimuth_counts <= stop:
            raise ValueError(
                f"initial azimuth {initial_azimuth_counts} counts lies beyond the stops at +-{stop}"
            )
        # (low, high): where the stops are, +-inf without them
        self._stops = (-stop, stop)
        self._stop_hits = 0
        self._theta = float(initial_azimuth_counts)
        self._omega = 0.0
        self._current = 0.0
        self._origin = math.floor(self._theta)
        self._index_seen = False
        self._stalled = False
        self._counts_per_rad = cpr / (2.0 * math.pi)
        self._volts_per_unit = params.full_scale_volts / 128.0
        # volts per command unit reaching the winding: _volts_per_unit, or 0.0 with a dead
        # amplifier (so the fault costs the hot path nothing)
        self._drive = self._volts_per_unit
        self._disc: _Discrete | None = None
        self._disc_dt = -1.0
        # constants of the hot paths, looked up once (every value is exactly what the
        # expressions over ``params`` give, so the arithmetic is unchanged)
        self._rest_limit = params.coulomb_friction / params.torque_constant
        self._coef: tuple[float, ...] = ()
        self._consts = (
            params.substeps,
            params.resistance_ohm,
            params.torque_constant,
            params.coulomb_friction,
            params.counts_per_rev,
        )

    # -- state -----------------------------------------------------------------------------------
    @property
    def encoder_counts(self) -> int:
        """Edges counted since power-up (B leads A = positive)."""
        return math.floor(self._theta) - self._origin

    @property
    def true_azimuth_counts(self) -> float:
        """Where the head really points, in counts from true azimuth 0 (backdoor)."""
        return self._theta

    @property
    def velocity_counts_per_s(self) -> float:
        return self._omega * self._counts_per_rad

    @property
    def current_a(self) -> float:
        """Winding current (backdoor, for plots and tests)."""
        return self._current

    @property
    def index_seen(self) -> bool:
        """Latched when the head crosses true azimuth 0 (mod one revolution)."""
        return self._index_seen

    def clear_index(self) -> None:
        self._index_seen = False

    @property
    def stalled(self) -> bool:
        """The shaft is locked (a fault): it neither moves nor counts, whatever the drive."""
        return self._stalled

    @stalled.setter
    def stalled(self, value: bool) -> None:
        self._stalled = bool(value)
        if self._stalled:
            self._omega = 0.0

    @property
    def amplifier_dead(self) -> bool:
        """The amplifier outputs 0 V whatever the command (a fault): no torque reaches the shaft."""
        return self._drive == 0.0

    @amplifier_dead.setter
    def amplifier_dead(self, value: bool) -> None:
        self._drive = 0.0 if value else self._volts_per_unit

    @property
    def stop_hits(self) -> int:
        """How many times the head has struck a mechanical stop, bounces included (backdoor)."""
        return self._stop_hits

    @property
    def at_stop(self) -> bool:
        """The head stands at one of its mechanical stops (backdoor)."""
        low, high = self._stops
        return self._theta <= low or self._theta >= high

    def holds_at_rest(self, motor_command_signed: int) -> bool:
        """True if the head is still and would stay still under this command for ever.

        While stuck the current moves monotonically from its present value towards V/R, so if
        neither end can beat friction nothing will ever move. At a stop, torque into the stop
        moves nothing either: there only torque away from it counts. The chip uses this to skip
        idle sample periods without changing what happens.
        """
        if self._stalled:
            return True
        if self._omega != 0.0:
            return False
        limit = self._rest_limit
        current = self._current
        drive = motor_command_signed * self._drive / self.params.resistance_ohm
        low, high = self._stops
        if self._theta >= high:  # pressed into the upper stop: only pulling back can move it
            return current >= -limit and drive >= -limit
        if self._theta <= low:
            return current <= limit and drive <= limit
        if not -limit <= current <= limit:
            return False
        return -limit <= drive <= limit

    # -- integration -----------------------------------------------------------------------------
    def _discretise(self, dt: float) -> _Discrete:
        p = self.params
        h = dt / p.substeps
        k, r, ind, j, b = (
            p.torque_constant,
            p.resistance_ohm,
            p.inductance_h,
            p.inertia,
            p.viscous_friction,
        )
        # state (theta rad, omega, i); inputs (V, friction torque); augmented for the integral
        aug = np.zeros((5, 5))
        aug[0, 1] = 1.0
        aug[1, 1], aug[1, 2], aug[1, 4] = -b / j, k / j, -1.0 / j
        aug[2, 1], aug[2, 2], aug[2, 3] = -k / ind, -r / ind, 1.0 / ind
        full = _expm(aug * h)
        scale = (self._counts_per_rad, 1.0, 1.0)
        # plain Python floats: the same IEEE doubles as numpy's, at a fraction of the cost of
        # numpy scalars in the per-sample arithmetic
        phi = tuple(
            (float(scale[row] * full[row, 1]), float(scale[row] * full[row, 2])) for row in range(3)
        )
        volt = (float(scale[0] * full[0, 3]), float(full[1, 3]), float(full[2, 3]))
        fric = (float(scale[0] * full[0, 4]), float(full[1, 4]), float(full[2, 4]))
        return _Discrete(h, phi, volt, fric, math.exp(-r * h / ind))

    def step(self, motor_command_signed: int, dt: float) -> None:
        """Apply a constant motor command for ``dt`` seconds.

        The hot path of the simulator (every sample of both axes). The stops cost nothing per
        sub-step: the bounds the index check compares against are narrowed to them, so only a
        sub-step that crosses an index or reaches a stop does any more work; holding against a
        stop is tested only when a still head's torque beats friction.
        """
        if dt != self._disc_dt or self._disc is None:
            d = self._disc = self._discretise(dt)
            self._disc_dt = dt
            (p0w, p0i), (p1w, p1i), (p2w, p2i) = d.phi
            # friction torque is +-T_c (against the motion), and f * -T_c is exactly -(f * T_c)
            coulomb = self.params.coulomb_friction
            friction = tuple(f * coulomb for f in d.fric)
            self._coef = (p0w, p0i, p1w, p1i, p2w, p2i, *d.volt, *friction, d.stuck_decay)
        p0w, p0i, p1w, p1i, p2w, p2i, u0, u1, u2, c0, c1, c2, decay = self._coef
        substeps, resistance, k, coulomb, cpr = self._consts
        volts = motor_command_signed * self._drive
        target = volts / resistance
        cur = self._current
        if self._stalled:
            # the shaft is held: only the current settles towards V/R
            for _ in range(substeps):
                cur = target + (cur - target) * decay
            self._current = cur
            return
        theta, omega = self._theta, self._omega
        v0, v1, v2 = u0 * volts, u1 * volts, u2 * volts
        low = math.floor(theta / cpr) * cpr  # the revolution the head is in: [low, low + cpr)
        high = low + cpr
        stop_low, stop_high = self._stops
        # one comparison per sub-step covers both: leaving [edge_low, edge_high) means an index
        # crossing or a stop
        edge_low = low if low > stop_low else stop_low
        edge_high = high if high < stop_high else stop_high
        for _ in range(substeps):
            if omega == 0.0:
                torque = k * cur
                if -coulomb <= torque <= coulomb:
                    cur = target + (cur - target) * decay  # stiction holds the head
                    continue
                forward = torque > 0.0
                if theta >= stop_high if forward else theta <= stop_low:
                    cur = target + (cur - target) * decay  # pushed into a stop: held there
                    continue
            else:
                forward = omega > 0.0
            # kinetic friction opposes the motion; the head stops (it cannot reverse) when the
            # velocity would change sign and the torque cannot beat friction
            if forward:
                theta += p0w * omega + p0i * cur + v0 + c0
                new_omega = p1w * omega + p1i * cur + v1 + c1
                cur = p2w * omega + p2i * cur + v2 + c2
                if not new_omega > 0.0 and -coulomb <= k * cur <= coulomb:
                    new_omega = 0.0
            else:
                theta += p0w * omega + p0i * cur + v0 - c0
                new_omega = p1w * omega + p1i * cur + v1 - c1
                cur = p2w * omega + p2i * cur + v2 - c2
                if new_omega > 0.0 and -coulomb <= k * cur <= coulomb:
                    new_omega = 0.0
            omega = new_omega
            if theta < edge_low or theta >= edge_high:
                if theta >= stop_high or theta <= stop_low:  # ran into a stop: dead still
                    theta = stop_high if theta >= stop_high else stop_low
                    omega = 0.0
                    self._stop_hits += 1
                if theta < low or theta >= high:  # crossed a multiple of one revolution: index
                    self._index_seen = True
                    low = math.floor(theta / cpr) * cpr
                    high = low + cpr
                edge_low = low if low > stop_low else stop_low
                edge_high = high if high < stop_high else stop_high
        self._theta, self._omega, self._current = theta, omega, cur
