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
  stays within ``momentum_kg_m_s``.

Which bound binds is reported (:class:`Scaling`): the point, its speed and
the limit. The limits themselves (:class:`Limits`) come from the profile's
``bridge.limits`` and ``bridge.reduced`` (the reduced mode), checked against
the robot description: a profile may tighten them, never loosen them past
``max_point_speed`` or the momentum of the whole arm at that speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nwr.common.config import CartesianLimits
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotModel

# A factor this close to 1 is no scaling (rounding).
SCALE_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Limits:
    """One set of Cartesian limits, checked against the robot."""

    speed_m_s: float
    withdrawal_speed_m_s: float
    momentum_kg_m_s: float

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
        return cls(section.speed_m_s, section.withdrawal_speed_m_s, section.momentum_kg_m_s)


@dataclass(frozen=True)
class Scaling:
    """What bound a cycle's joint velocity, and by how much."""

    factor: float  # the joint velocity is multiplied by this (<= 1)
    what: str  # "speed", "speed toward the contact" or "momentum"
    point: str  # the point (or "arm" for the momentum)
    value: float  # its speed (m/s) or momentum (kg m/s) before scaling
    limit: float

    def describe(self) -> str:
        unit = "kg m/s" if self.what == "momentum" else "m/s"
        where = "the arm's momentum" if self.what == "momentum" else f"{self.point} {self.what}"
        return f"{where} {self.value:.3f} {unit} above {self.limit:.3f} {unit}: scaled by {self.factor:.3f}"


class CartesianLimiter:
    """The per-cycle check of a joint velocity against a set of :class:`Limits` (see the module docstring)."""

    def __init__(self, model: RobotModel, limits: Limits) -> None:
        self.model = model
        self.limits = limits
        self.points = model.speed_points
        self.masses = model.link_masses

    def speeds(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """The speed (m/s) of every speed-limited point at ``q`` moving at ``dq``."""
        return np.linalg.norm(self.model.speed_jacobians(q) @ dq, axis=1)

    def momentum(self, q: np.ndarray, dq: np.ndarray) -> float:
        """Sum over the moving links of mass times centre-of-mass speed, kg m/s."""
        return float(self.masses @ np.linalg.norm(self.model.com_jacobians(q) @ dq, axis=1))

    def scale(self, q: np.ndarray, dq: np.ndarray, *, withdrawal: bool = False,
              toward: np.ndarray | None = None, speed_cap: float | None = None) -> Scaling | None:
        """The scaling ``dq`` needs at ``q`` (None: within every limit).

        ``withdrawal``: the motion is a withdrawal (its own speed limit);
        ``toward``: the unit direction toward the contact, whose component is
        held to the collaborative speed; ``speed_cap``: a lower speed limit
        for now (rejoining a stream after a hold: the stream's own peak).
        """
        limits = self.limits
        velocities = self.model.speed_jacobians(q) @ dq  # (P, 3)
        speeds = np.linalg.norm(velocities, axis=1)
        worst: Scaling | None = None
        limit = limits.withdrawal_speed_m_s if withdrawal else limits.speed_m_s
        what = "speed"
        if speed_cap is not None and speed_cap < limit:
            limit, what = speed_cap, "rejoin speed"
        k = int(np.argmax(speeds))
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
        if worst is not None and worst.factor >= 1.0 - SCALE_TOLERANCE:
            return None
        return worst
