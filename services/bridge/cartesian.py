"""The bridge's Cartesian limits: speed of every point of the arm, speed toward a contact, momentum; pure.

A UR controller's safety system limits the speed of the elbow and the flange
and the arm's momentum; ISO/TS 15066 frames contact with a person through
the speed and the energy of the part that meets them. The bridge does the
same on every point the skin covers: every control cycle,
:meth:`CartesianLimiter.scale` computes the velocity of each pad's reference
point, of the elbow and of the flange (the robot model's Jacobians) and the
momentum of the moving links (their masses and centres of mass, from the
URDF), and returns the factor in (0, 1] by which the joint velocity must be
scaled, direction kept, so that:

- no point moves faster than the motion's speed limit: the collaborative
  speed (``speed_m_s``) for the task, the return and anything that is not a
  withdrawal; ``withdrawal_speed_m_s`` during a withdrawal (phase REFLEX);
- during a withdrawal, no point moves *toward the contact* (along the
  touched pad's outward normal at the onset: toward the finger) faster than the
  collaborative speed: a withdrawal may move away faster than it approaches;
- the momentum, the sum over the moving links of mass times the speed of the
  link's centre of mass (a bound on the momentum of any part of the arm),
  stays within ``momentum_kg_m_s``;
- the stop the bridge would make from this velocity (jerk-limited, at the
  envelope's acceleration and jerk limits, every joint ending together) ends
  within ``stopping_time_s`` and moves no point farther than
  ``stopping_distance_m`` (:meth:`CartesianLimiter.stopping`).

After the acceleration limit, :meth:`CartesianLimiter.power_scale` bounds the
power the joints put into the motion (``power_w``: the rate of change of the
kinetic energy, the robot model's inverse dynamics) by easing the cycle's
acceleration.

Most cycles are far from every limit, and proving it costs a fraction of
computing it: :meth:`CartesianLimiter.scale` and :meth:`CartesianLimiter.power_scale`
first try bounds that need no kinematics (the robot model's
:class:`~nwr.common.robot.ChainBounds`: the triangle inequality along the
chain). Every point's speed is bounded from the last exact computation of
the fastest one, at ``q0`` and ``dq0``: ``|J(q) dq| <= |J(q0) dq0| + reach .
|dq - dq0| + |dq| . bend . |q - q0|`` (the cycles move ``q`` and ``dq``
little); the speed toward the contact by the speed, the stopping distance by
the speed times half the stopping time (computed: no kinematics); the
momentum from ``|dq|`` alone, the power from ``|dq|`` and ``|ddq|``. Only
where these bounds, inflated well past the exact computation's rounding
(:data:`BOUND_MARGIN`), hold every limit is the exact computation skipped:
it would have returned None too, so the result is the same bit for bit (the
tracker's own uses of the speeds, :meth:`CartesianLimiter.within_speed`,
likewise).

Which bound binds is reported (:class:`Scaling`): the point, its speed and
the limit. The limits themselves (:class:`Limits`) come from the profile's
``bridge.limits`` and ``bridge.reduced`` (the reduced mode), checked against
the robot description: a profile may tighten them, never loosen them past
``max_point_speed`` or the momentum of the whole arm at that speed.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from nwr.common.config import CartesianLimits
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotModel

# A factor this close to 1 is no scaling (rounding).
SCALE_TOLERANCE = 1e-9
# The bounds that skip the exact computation are inflated by this share of the magnitudes involved: the exact
# computation's rounding is of the order of 1e-16 of them (a few dozen operations in double precision).
BOUND_MARGIN = 1e-9


@dataclass(frozen=True)
class Limits:
    """One set of Cartesian limits, checked against the robot."""

    speed_m_s: float
    withdrawal_speed_m_s: float
    momentum_kg_m_s: float
    power_w: float = 50.0
    stopping_time_s: float = 0.25
    stopping_distance_m: float = 0.08

    @classmethod
    def of(cls, section: CartesianLimits, model: RobotModel, where: str) -> Limits:
        """The limits of a profile section; ConfigError naming the field if the robot cannot allow them."""
        top = model.desc.max_point_speed
        momentum_top = float(model.link_masses.sum()) * top
        for field, value, bound, unit in (
            ("speed_m_s", section.speed_m_s, top, "m/s"),
            ("withdrawal_speed_m_s", section.withdrawal_speed_m_s, top, "m/s"),
            ("momentum_kg_m_s", section.momentum_kg_m_s, momentum_top, "kg m/s"),
        ):
            if not 0.0 < value <= bound:
                raise ConfigError(
                    f"{where}.{field} = {value} {unit} is beyond what the robot description allows "
                    f"({bound:.3g} {unit}: max_point_speed {top} m/s"
                    f"{f' times the moving links {model.link_masses.sum():.3g} kg' if unit == 'kg m/s' else ''})"
                )
        return cls(section.speed_m_s, section.withdrawal_speed_m_s, section.momentum_kg_m_s, section.power_w,
                   section.stopping_time_s, section.stopping_distance_m)

    def describe(self) -> str:
        return CartesianLimits(**dataclasses.asdict(self)).describe()


@dataclass(frozen=True)
class Scaling:
    """What bound a cycle's joint velocity, and by how much."""

    factor: float  # the joint velocity is multiplied by this (<= 1)
    what: str  # "speed", "speed toward the contact", "rejoin speed", "momentum", "power", "stopping time",
    # "stopping distance"
    point: str  # the point (or "arm" for the momentum, the power and the stopping time)
    value: float  # its value before scaling, in UNITS[what]
    limit: float

    def describe(self) -> str:
        unit = UNITS.get(self.what, "m/s")
        where = f"the arm's {self.what}" if self.point == "arm" else f"{self.point} {self.what}"
        scaled = "acceleration eased" if self.what == "power" else "scaled"
        return f"{where} {self.value:.3f} {unit} above {self.limit:.3f} {unit}: {scaled} by {self.factor:.3f}"


UNITS = {"momentum": "kg m/s", "power": "W", "stopping time": "s", "stopping distance": "m"}
# Bisection steps for the factors that have no closed form (stopping distance, power): 2^-12 of the range.
BISECTION_STEPS = 12


def row_norms(x: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(x, axis=1)`` of a real array, bit for bit: the same ufuncs in the same order
    (its own path for one axis), without its dispatch, several times per control cycle."""
    return np.sqrt(np.add.reduce(x * x, axis=1))


class CartesianLimiter:
    """The per-cycle check of a joint velocity against a set of :class:`Limits` (see the module docstring)."""

    def __init__(self, model: RobotModel, limits: Limits, *, a_max: np.ndarray | None = None,
                 j_max: np.ndarray | None = None, bounded: bool = True) -> None:
        """``bounded``: skip the exact computation where the bounds prove it cannot bind (the module docstring;
        False: always compute it, as the tests compare)."""
        self.model = model
        self.limits = limits
        self.points = model.speed_points
        self.masses = model.link_masses
        # The envelope's acceleration and jerk limits, for the stop (None: no stopping limits).
        self.a_max = None if a_max is None else np.asarray(a_max, dtype=float)
        self.j_max = None if j_max is None else np.asarray(j_max, dtype=float)
        # The bounds that skip the exact computation (module docstring; None: the robot model has none): the
        # fastest point's reach and bend (each joint's largest over the points), the momentum's reach (the
        # masses times the centres of mass').
        self.bounds = model.bounds if bounded else None
        self._reach: np.ndarray | None = None  # (n,)
        self._bend: np.ndarray | None = None  # (n, n)
        self._momentum_reach: np.ndarray | None = None  # (n,)
        self._gravity_margin: np.ndarray | None = None  # (n,): the exact power's rounding scales with gravity
        if self.bounds is not None:
            bounds = self.bounds
            self._reach = bounds.speed_reach.max(axis=0)
            self._bend = bounds.speed_bend.max(axis=0)
            self._momentum_reach = self.masses @ bounds.com_reach
            self._gravity_margin = BOUND_MARGIN * bounds.gravity
        # The last exact computation of the fastest point's speed: q0, dq0, that speed, and reach . |dq0| (the
        # magnitude its rounding scales with); None: none yet.
        self._reference: tuple[np.ndarray, np.ndarray, float, float] | None = None

    def stop_time(self, dq: np.ndarray) -> float:
        """Duration of the jerk-limited stop from ``dq`` (at rest in acceleration), s: the slowest joint's.

        Per joint from speed v: ``v / a + a / j`` when the deceleration reaches
        ``a`` (``v >= a^2 / j``), else ``2 sqrt(v / j)``; every joint ends together.
        """
        assert self.a_max is not None and self.j_max is not None
        a, j, v = self.a_max, self.j_max, np.abs(dq)
        t = np.where(v >= a * a / j, v / a + a / j, 2.0 * np.sqrt(v / j))
        return float(t.max())

    def stopping(self, q: np.ndarray, dq: np.ndarray, speeds: np.ndarray | None = None) -> tuple[float, float, int]:
        """The stop from ``dq`` at ``q``: its time (s), the farthest any point moves (m), and that point.

        Every joint ends together, so each slows along the same normalised
        profile, symmetric in time: a point moving at ``s`` covers ``s T / 2``
        (to first order in the motion). ``speeds``: :meth:`speeds` of ``q`` and ``dq``, if the caller has them.
        """
        t = self.stop_time(dq)
        if speeds is None:
            speeds = self.speeds(q, dq)
        k = int(np.argmax(speeds))
        return t, float(speeds[k]) * t / 2.0, k

    def _stopping_scale(self, q: np.ndarray, dq: np.ndarray, speeds: np.ndarray | None = None) -> Scaling | None:
        """The factor that brings the stop from ``dq`` within the stopping time and distance."""
        limits = self.limits
        t, distance, k = self.stopping(q, dq, speeds)
        if t <= limits.stopping_time_s and distance <= limits.stopping_distance_m:
            return None
        assert self.a_max is not None and self.j_max is not None
        a, j = self.a_max, self.j_max
        # The fastest each joint may move and still stop in time (stop_time inverted), then bisection
        # for the distance, which grows with the factor.
        limit_t = limits.stopping_time_s
        v_top = np.where(limit_t >= 2.0 * a / j, a * (limit_t - a / j), j * (limit_t / 2.0) ** 2)
        v = np.abs(dq)
        moving = v > 0.0
        hi = min(1.0, float(np.min(v_top[moving] / v[moving]))) if moving.any() else 1.0
        worst: Scaling | None = None
        if t > limit_t:
            worst = Scaling(hi, "stopping time", "arm", t, limit_t)
        if self.stopping(q, hi * dq)[1] > limits.stopping_distance_m:
            lo = 0.0
            for _ in range(BISECTION_STEPS):
                mid = 0.5 * (lo + hi)
                if self.stopping(q, mid * dq)[1] > limits.stopping_distance_m:
                    hi = mid
                else:
                    lo = mid
            worst = Scaling(lo, "stopping distance", self.points[k], distance, limits.stopping_distance_m)
        return worst

    def power_scale(self, q: np.ndarray, dq0: np.ndarray, dq1: np.ndarray, h: float) -> Scaling | None:
        """How much of the cycle's change of velocity, ``dq0`` to ``dq1`` in ``h`` s, keeps the power within limit.

        The factor ``s`` makes the velocity ``dq0 + s (dq1 - dq0)``: the
        acceleration eased, never reversed (at ``s = 0`` the arm coasts, whose
        power is the small Coriolis share). None: within the limit, the
        inverse dynamics skipped where the robot model's bound on the power
        (:class:`~nwr.common.robot.ChainBounds`) proves it.
        """
        limit = self.limits.power_w
        change = dq1 - dq0
        ddq = change / h
        if self._power_within(q, dq1, ddq, limit):
            return None
        power = self.model.motion_power(q, dq1, ddq)
        if power <= limit:
            return None
        lo, hi = 0.0, 1.0
        for _ in range(BISECTION_STEPS):
            mid = 0.5 * (lo + hi)
            if self.model.motion_power(q, dq0 + mid * change, mid * change / h) > limit:
                hi = mid
            else:
                lo = mid
        return Scaling(lo, "power", "arm", power, limit)

    def _power_within(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, limit: float) -> bool:
        """True if the power at ``q``, ``dq``, ``ddq`` provably is within ``limit`` (:meth:`power_scale` would
        return None); False: unknown. The exact computation's ``q`` checks are kept (a ``q`` it would refuse is
        left to it), and the prismatic joints' travel must be within the limits the bound counted."""
        bounds = self.bounds
        if bounds is None or self._gravity_margin is None:
            return False
        if not isinstance(q, np.ndarray) or not isinstance(dq, np.ndarray):
            return False
        if not (q.shape == dq.shape == ddq.shape == (self.model.nq,) and np.isfinite(q).all()
                and self._travelling(q)):
            return False
        a, b = np.abs(dq), np.abs(ddq)
        # The gravity term: the exact power subtracts the gravity torques, whose rounding is not in the bound.
        power = float(a @ (bounds.power_rate @ b + self._gravity_margin)) + float((bounds.power_cubic @ a) @ a @ a)
        return power * (1.0 + BOUND_MARGIN) <= limit

    def _travelling(self, q: np.ndarray) -> bool:
        """``q``'s prismatic joints are within the travel the bounds counted (always, without prismatic joints)."""
        bounds = self.bounds
        assert bounds is not None
        if not bounds.travel.size:
            return True
        x = q[bounds.travel]
        return bool(((x >= bounds.travel_min) & (x <= bounds.travel_max)).all())

    def _bound(self, q: np.ndarray, dq: np.ndarray) -> tuple[float, float] | None:
        """Upper bounds on the fastest point's speed and on the momentum at ``q`` moving at ``dq``; None: none
        (no exact computation of the speeds yet, or arguments the exact computation must judge).

        With the fastest point's speed ``s0`` at ``q0``, ``dq0`` (the last exact
        computation): every point's ``|J(q) dq| <= |J(q0) dq0| + |J(q0) (dq -
        dq0)| + |(J(q) - J(q0)) dq| <= s0 + reach . |dq - dq0| + |dq| . bend .
        |q - q0|`` (:class:`~nwr.common.robot.ChainBounds`). The momentum, the
        masses times their centres' ``|J_c(q) dq| <= reach_c . |dq|``, is far
        from its limit at the speeds the limits allow: its configuration-free
        bound does. Both inflated by :data:`BOUND_MARGIN` of themselves and of
        ``reach . |dq|`` (at most ``reach . |dq - dq0| + reach . |dq0|``), which
        the rounding of the exact speeds and momentum scales with.
        """
        reference = self._reference
        if reference is None or not isinstance(q, np.ndarray) or not isinstance(dq, np.ndarray):
            return None
        q0, dq0, top0, scale0 = reference
        if q.shape != q0.shape or dq.shape != dq0.shape or not self._travelling(q):
            return None
        assert self._reach is not None and self._bend is not None and self._momentum_reach is not None
        a = np.abs(dq)
        spread = float(self._reach @ np.abs(dq - dq0))
        top = top0 + spread + float((self._bend @ np.abs(q - q0)) @ a)
        momentum = float(self._momentum_reach @ a)
        return top + BOUND_MARGIN * (top + spread + scale0), momentum * (1.0 + 2.0 * BOUND_MARGIN)

    def _refer(self, q: np.ndarray, dq: np.ndarray, top: float) -> None:
        """Keep an exact computation of the fastest point's speed ``top`` at ``q``, ``dq`` for the bounds."""
        if self._reach is not None:
            dq = np.array(dq, dtype=float)
            self._reference = (np.array(q, dtype=float), dq, top, float(self._reach @ np.abs(dq)))

    def within_speed(self, q: np.ndarray, dq: np.ndarray, limit: float) -> bool:
        """True if no point is provably faster than ``limit`` at ``q`` moving at ``dq`` (``speeds(q, dq).max() <=
        limit``) without computing it; False: unknown."""
        bound = self._bound(q, dq)
        return bound is not None and bound[0] <= limit

    def _limit(self, withdrawal: bool, speed_cap: float | None) -> tuple[float, str]:
        """The speed limit of :meth:`scale` and what it is."""
        limits = self.limits
        limit = limits.withdrawal_speed_m_s if withdrawal else limits.speed_m_s
        if speed_cap is not None and speed_cap < limit:
            return speed_cap, "rejoin speed"
        return limit, "speed"

    def _within(self, q: np.ndarray, dq: np.ndarray, limit: float, toward: np.ndarray | None) -> bool:
        """True if :meth:`scale` provably returns None for ``dq`` at ``q`` under the speed limit ``limit``;
        False: unknown.

        The bounds on the fastest point's speed and the momentum (:meth:`_bound`)
        are within their limits; so is the speed toward the contact (a point's
        velocity along ``toward`` is at most its speed times ``|toward|``); the
        stop's time (computed, as the exact computation does) and its distance
        (the fastest point's speed times half the time: at most the bound's).
        """
        bound = self._bound(q, dq)
        if bound is None:
            return False
        top, momentum = bound
        limits = self.limits
        if not (top <= limit and momentum <= limits.momentum_kg_m_s):
            return False
        if toward is not None and not top * math.sqrt(float(np.dot(toward, toward))) <= limits.speed_m_s:
            return False
        if self.a_max is None:
            return True
        t = self.stop_time(dq)
        return t <= limits.stopping_time_s and top * t / 2.0 <= limits.stopping_distance_m

    def speeds(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """The speed (m/s) of every speed-limited point at ``q`` moving at ``dq``."""
        return row_norms(self.model.speed_jacobians(q) @ dq)

    def top_speed(self, q: np.ndarray, dq: np.ndarray) -> float:
        """``speeds(q, dq).max()``, kept for the bounds (:meth:`within_speed`, :meth:`scale`)."""
        top = float(self.speeds(q, dq).max())
        self._refer(q, dq, top)
        return top

    def momentum(self, q: np.ndarray, dq: np.ndarray) -> float:
        """Sum over the moving links of mass times centre-of-mass speed, kg m/s."""
        return float(self.masses @ row_norms(self.model.com_jacobians(q) @ dq))

    def scale(self, q: np.ndarray, dq: np.ndarray, *, withdrawal: bool = False,
              toward: np.ndarray | None = None, speed_cap: float | None = None) -> Scaling | None:
        """The scaling ``dq`` needs at ``q`` (None: within every limit).

        ``withdrawal``: the motion is a withdrawal (its own speed limit);
        ``toward``: the unit direction toward the contact, whose component is
        held to the collaborative speed; ``speed_cap``: a lower speed limit
        for now (rejoining a stream after a hold: the stream's own peak).
        """
        limit, what = self._limit(withdrawal, speed_cap)
        if self._within(q, dq, limit, toward):  # the bounds hold every limit: the exact computation returns None
            return None
        return self._scale(q, dq, limit, what, toward)

    def _scale(self, q: np.ndarray, dq: np.ndarray, limit: float, what: str,
               toward: np.ndarray | None) -> Scaling | None:
        """:meth:`scale`, computed: the exact computation (its reference for the bounds kept)."""
        limits = self.limits
        velocities = self.model.speed_jacobians(q) @ dq  # (P, 3)
        speeds = row_norms(velocities)
        worst: Scaling | None = None
        k = int(np.argmax(speeds))
        self._refer(q, dq, float(speeds[k]))
        if speeds[k] > limit:
            worst = Scaling(limit / float(speeds[k]), what, self.points[k], float(speeds[k]), limit)
        if toward is not None:
            approach = velocities @ toward
            k = int(np.argmax(approach))
            if approach[k] > limits.speed_m_s:
                factor = limits.speed_m_s / float(approach[k])
                if worst is None or factor < worst.factor:
                    worst = Scaling(factor, "speed toward the contact", self.points[k], float(approach[k]),
                                    limits.speed_m_s)
        momentum = self.momentum(q, dq)
        if momentum > limits.momentum_kg_m_s:
            factor = limits.momentum_kg_m_s / momentum
            if worst is None or factor < worst.factor:
                worst = Scaling(factor, "momentum", "arm", momentum, limits.momentum_kg_m_s)
        if self.a_max is not None:
            # Unscaled, the speeds of the stop's start are those above (the same product, not computed twice).
            stopping = self._stopping_scale(q, dq, speeds) if worst is None else \
                self._stopping_scale(q, worst.factor * dq)
            if stopping is not None:
                factor = stopping.factor * (1.0 if worst is None else worst.factor)
                worst = Scaling(factor, stopping.what, stopping.point, stopping.value, stopping.limit)
        if worst is not None and worst.factor >= 1.0 - SCALE_TOLERANCE:
            return None
        return worst
