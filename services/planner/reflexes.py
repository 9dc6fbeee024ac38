"""Reflex strategies: what the arm does when it is touched.

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

from nwr.common.robot import RobotModel


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
    ) -> None:
        self.model = model
        self.v_max = v_max
        self.duration_s = duration_s
        self.damping_max = damping_max
        self.threshold = singular_threshold
        self.v_limit = v_limit
        self.rows = 6 if hold_orientation else 3
        self._twist = np.zeros(6)
        self.pad = -1

    def start(self, q: np.ndarray, pad: int, gain: float) -> np.ndarray:
        """Begin (or update) a reflex; returns the pad's Cartesian velocity v_c."""
        self.pad = pad
        normal = self.model.pad_normal(q, pad)
        self._twist[:3] = -self.v_max * gain * normal
        self._twist[3:] = 0.0
        return self._twist[:3].copy()

    def joint_velocity(self, q: np.ndarray) -> np.ndarray:
        """q_dot for the current pose (call every control cycle)."""
        jac = self.model.pad_jacobian(q, self.pad)[: self.rows]
        moving = np.any(jac != 0.0, axis=0)
        dq = np.zeros(jac.shape[1])
        dq[moving] = damped_pinv(jac[:, moving], self.damping_max, self.threshold) @ self._twist[: self.rows]
        return scale_to_limits(dq, self.v_limit)
