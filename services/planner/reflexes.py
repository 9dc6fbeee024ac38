"""Reflex strategies: what the arm does when it is touched.

Joint-space reflexes of the paper, under joint position control; the
displacement is added to the current pose, signed by the robot
description's ``reflex_direction`` (shoulder internal rotation, shoulder
adduction, elbow flexion, wrist flexion: the arm draws in toward the base)
and clipped to the joint limits:

    uniform (UR):           q_ref = 1/2 q_max,  q_max = [40, 70, 146, 73, 0, 0] deg, whatever G(p) > 0
    location-dependent (LR): q_ref = G(p) W(PL, region) q_max, W = diag(w_b, w_s, w_e, w_w, w_w, w_w)

The planner moves to the target with a jerk-limited trajectory (ruckig).

Cartesian reflex (CR) of the paper:

    v_c = -v_max G(p) n                       (n: the pad's outward normal in the base frame)
    q_dot = J^+(q) [v_c; 0]                   (J: 6 x n Jacobian of the pad, base orientation)

streamed for ``reflex_duration_s`` (0.5 s) under joint velocity control.
Choices where the paper is silent (documented in the profile as well):

- n is taken at the onset and kept for the whole reflex, so the pad moves
  along one straight line away from the contact; J is re-evaluated every
  control cycle at the current pose (resolved-rate control).
- J has one column per joint that moves the pad (the joints beyond the pad's
  link are structurally zero and left out, so a pad on the forearm is not
  treated as if it sat at a singularity).
- ``hold_orientation`` (the paper's formula, default) asks for a zero angular
  velocity of the pad: with fewer than six joints behind a pad this is a
  least-squares compromise that withdraws proximal pads (shoulder, upper arm,
  forearm) much more slowly than v_c. With it off, only the three linear rows
  are used and the pad moves at v_c whenever the arm can.
- J^+ is a damped least-squares inverse, V diag(s / (s^2 + l^2)) U^T, whose
  damping l^2 grows smoothly from 0 to ``damping_max^2`` as the smallest
  singular value s_min falls below ``singular_threshold`` (Maciejewski and
  Klein). Far from singularities it is the exact pseudo-inverse; near them
  joint speeds stay bounded.
- If a joint would still exceed ``speed_fraction`` of its speed limit, the
  whole q_dot is scaled down uniformly (the pad keeps its direction).
"""

from __future__ import annotations

import numpy as np

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner.retreat import guard_velocity


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


class JointReflex:
    """UR and LR: a joint displacement added to the current pose, clipped to the limits."""

    mode = "position"

    def __init__(self, strategy: str, cfg: PlannerSection, desc: RobotDescription) -> None:
        n = len(desc.joints)
        if len(cfg.q_max_deg) != n:
            raise ConfigError(f"planner.q_max_deg has {len(cfg.q_max_deg)} values, the robot has {n} joints")
        self.strategy = strategy
        self.q_max = np.radians(cfg.q_max_deg)
        self.fraction = cfg.uniform_fraction
        self.sign = desc.reflex_direction
        self.q_min, self.q_lim = desc.q_min, desc.q_max
        self.weights: dict[int, dict[str, np.ndarray]] = {}
        for level, table in ((3, cfg.location_weights.pl3), (4, cfg.location_weights.pl4)):
            self.weights[level] = {}
            for region, w in table.items():
                if len(w) != 4 or not all(0.0 <= x <= 1.0 for x in w):
                    raise ConfigError(
                        f"planner.location_weights.pl{level}.{region} must be four weights in [0, 1] "
                        f"[base, shoulder, elbow, wrist], got {w}"
                    )
                # One weight per base, shoulder, elbow; the wrist's for every wrist joint.
                self.weights[level][region] = np.array([w[0], w[1], w[2]] + [w[3]] * (n - 3))

    def displacement(self, contact: m.Contact) -> np.ndarray:
        """q_ref, rad, before the direction signs and clipping."""
        if self.strategy == "uniform":
            return self.fraction * self.q_max
        table = self.weights.get(contact.level)
        if table is None:  # PL 1-2: no motion
            return np.zeros_like(self.q_max)
        w = table.get(contact.region)
        if w is None:
            raise ConfigError(f"planner.location_weights.pl{contact.level} has no weights "
                              f"for region {contact.region!r}")
        return contact.gain * w * self.q_max

    def target(self, q: np.ndarray, contact: m.Contact) -> np.ndarray:
        return np.clip(q + self.sign * self.displacement(contact), self.q_min, self.q_lim)


class CartesianReflex:
    """Resolved-rate withdrawal of the touched pad along its normal."""

    strategy = "cartesian"
    mode = "velocity"

    def __init__(
        self,
        model: RobotModel,
        v_max: float,
        duration_s: float,
        damping_max: float,
        singular_threshold: float,
        v_limit: np.ndarray,
        hold_orientation: bool = True,
        guarded: bool = False,
    ) -> None:
        self.model = model
        self.v_max = v_max
        self.duration_s = duration_s
        self.damping_max = damping_max
        self.threshold = singular_threshold
        self.v_limit = v_limit
        self.rows = 6 if hold_orientation else 3
        self.guarded = guarded
        self.corrections = 0
        self._twist = np.zeros(6)
        self._normal = np.zeros(3)
        self.pad = -1

    def start(self, q: np.ndarray, pad: int, gain: float) -> np.ndarray:
        """Begin (or update) a reflex; returns the pad's Cartesian velocity v_c."""
        self.pad = pad
        self.corrections = 0
        normal = self._normal = self.model.pad_normal(q, pad)
        self._twist[:3] = -self.v_max * gain * normal
        self._twist[3:] = 0.0
        return self._twist[:3].copy()

    def joint_velocity(self, q: np.ndarray, *, count: bool = True) -> np.ndarray:
        """q_dot for the current pose (call every control cycle)."""
        full = self.model.pad_jacobian(q, self.pad)
        jac = full[: self.rows]
        moving = np.any(jac != 0.0, axis=0)
        dq = np.zeros(jac.shape[1])
        dq[moving] = damped_pinv(jac[:, moving], self.damping_max, self.threshold) @ self._twist[: self.rows]
        if self.guarded:
            dq, corrected = guard_velocity(full[:3], self._normal, dq)
            if corrected and count:
                self.corrections += 1
        return scale_to_limits(dq, self.v_limit)


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
