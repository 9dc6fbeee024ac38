"""The reflex strategies' shared pieces: the joint-space family and the math of the Cartesian stream.

Joint-space reflexes of the paper (:mod:`.strategies.uniform`,
:mod:`.strategies.location`), under joint position control: a displacement
q_ref is added to the current pose, signed by the robot description's
``reflex_direction`` (shoulder internal rotation, shoulder adduction, elbow
flexion, wrist flexion: the arm draws in toward the base) and clipped to the
joint limits less :data:`JOINT_MARGIN_RAD` (a target on the limit itself
would have the bridge brake the arm short of it, off the plan); the planner
moves to the target with a jerk-limited trajectory (ruckig). In guarded mode
the displacement is corrected when its path would move the touched pad toward
the contact (:func:`.retreat.guard_displacement`).

The Cartesian stream (:mod:`.strategies.cartesian`) inverts the pad Jacobian
with :func:`damped_pinv` and scales the result into the speed limits with
:func:`scale_to_limits`; its smoothed variant
(:mod:`.strategies.cartesian_smooth`) ramps it with :func:`smooth_profile`.
"""

from __future__ import annotations

from abc import abstractmethod

import numpy as np

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner.retreat import guard_displacement
from nwr.services.planner.strategies import Onset, ReflexStrategy

# A joint-space target stays this far inside each joint's range (a joint already closer stays where it is).
JOINT_MARGIN_RAD = 0.01


def damped_pinv(jac: np.ndarray, damping_max: float, threshold: float) -> np.ndarray:
    """Damped least-squares inverse of ``jac`` (m x n) -> (n x m)."""
    u, s, vt = np.linalg.svd(jac, full_matrices=False)
    s_min = s[-1] if s.size else 0.0
    lam2 = 0.0 if s_min >= threshold else (1.0 - (s_min / threshold) ** 2) * damping_max**2
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(s > 1e-12, s / (s * s + lam2), 0.0)
    return (vt.T * inv) @ u.T


def scale_to_limits(dq: np.ndarray, v_limit: np.ndarray) -> np.ndarray:
    """Scale ``dq`` uniformly so that no joint exceeds its speed limit."""
    ratio = float(np.max(np.abs(dq) / v_limit))
    return dq / ratio if ratio > 1.0 else dq


def smooth_profile(t: float, duration: float, ramp: float) -> float:
    """Raised-cosine ramps in and out, scaled so its integral equals ``duration``."""
    if t < 0.0 or t >= duration:
        return 0.0
    if t < ramp:
        shape = 0.5 - 0.5 * np.cos(np.pi * t / ramp)
    elif t > duration - ramp:
        shape = 0.5 - 0.5 * np.cos(np.pi * (duration - t) / ramp)
    else:
        shape = 1.0
    return float(shape * duration / (duration - ramp))


class JointReflex(ReflexStrategy):
    """A joint displacement added to the current pose, clipped to the limits (guarded: corrected)."""

    mode = "position"

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> None:
        super().__init__(cfg, desc, model, v_limit)
        n = len(desc.joints)
        q_max_deg = cfg.q_max_deg or list(desc.reflex_range_deg)  # empty: the robot's (robot.toml)
        if len(q_max_deg) != n:
            raise ConfigError(f"planner.q_max_deg has {len(q_max_deg)} values, the robot has {n} joints")
        self.q_max = np.radians(q_max_deg)
        self.sign = desc.reflex_direction
        self.q_min, self.q_lim = desc.q_min + JOINT_MARGIN_RAD, desc.q_max - JOINT_MARGIN_RAD
        self.guarded = cfg.guarded

    @abstractmethod
    def displacement(self, contact: m.Contact) -> np.ndarray:
        """q_ref, rad, before the direction signs and clipping (the other active contacts' included:
        :attr:`other_contacts`)."""

    def bounds(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where a target from ``q`` may go: the joint ranges less the margin, widened to ``q`` itself."""
        return np.minimum(self.q_min, q), np.maximum(self.q_lim, q)

    def target(self, q: np.ndarray, contact: m.Contact) -> np.ndarray:
        return np.clip(q + self.sign * self.displacement(contact), *self.bounds(q))

    def start(self, q: np.ndarray, contact: m.Contact) -> Onset:
        target = self.target(q, contact)
        corrected = False
        if self.guarded:
            delta, corrected = guard_displacement(self.model, q, target - q, contact.pad, *self.bounds(q),
                                                  others=[other.pad for other in self.other_contacts])
            target = q + delta
        return Onset(target=target, corrected=corrected)
