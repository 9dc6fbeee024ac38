"""Does the touched pad retreat? A check from the kinematics, and a guard.

The paper's strongest criticism of its joint-space reflexes is that in some
postures part of the arm moves toward the person while another part
withdraws. For a planned reflex (joint positions sampled over its duration)
:func:`assess` computes:

- the speed of the touched pad's point along its outward normal n0 (taken
  at the onset) over the whole reflex: positive means toward the contact;
- ``toward_m``: how far the touched pad ever moves toward the contact,
  max_t (p(t) - p(0)) . n0 (0 when it only retreats);
- ``withdrawal_m``: where it ends, -(p(T) - p(0)) . n0;
- per other pad, how much closer it ever gets to the contact point (the
  touched pad's point at the onset, where the finger is).

:func:`guard_displacement` corrects a joint-space displacement whose path
would move the touched pad toward the contact: it removes the offending
component along the gradient of the pad's normal displacement, J_lin^T n0
(the smallest joint-space change that makes the pad retreat), checking the
whole path with the full kinematics, and as a last resort shortens the
motion to the part that retreats.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nwr.common import messages as m
from nwr.common.robot import RobotModel

TOLERANCE_M = 1e-3  # approaches below a millimetre are numerical noise, not a push
PATH_SAMPLES = 16


@dataclass(frozen=True)
class Assessment:
    normal_speed: np.ndarray  # m/s over the samples, + toward the contact
    dt: float
    toward_m: float
    withdrawal_m: float
    approach_m: np.ndarray  # per pad, >= 0
    furthest_m: float = 0.0  # the furthest the touched pad gets from the contact along the way, m
    furthest_at_s: float = 0.0  # when, from the path's first sample, s
    leaves_m: float = 0.0  # the furthest the touched pad's point gets from the contact point (any direction), m

    def to_message(self, pad: int, corrected: bool) -> m.Retreat:
        others = self.approach_m.copy()
        others[pad] = 0.0
        worst = int(np.argmax(others))
        return m.Retreat(
            sample_dt_s=self.dt,
            normal_speed_m_s=self.normal_speed.tolist(),
            toward_m=self.toward_m,
            withdrawal_m=self.withdrawal_m,
            approach_m=others.tolist(),
            worst_pad=worst,
            worst_approach_m=float(others[worst]),
            approached=self.toward_m > TOLERANCE_M,
            corrected=corrected,
        )


def assess(model: RobotModel, path: np.ndarray, dt: float, pad: int) -> Assessment:
    """Retreat figures of a sampled joint path (k x n, first row = the onset pose)."""
    q0 = path[0]
    p0 = model.pad_point(q0, pad)
    n0 = model.pad_normal(q0, pad)
    contact = p0
    d0 = np.linalg.norm(model.pad_points(q0) - contact, axis=1)
    along = np.empty(len(path))
    closest = d0.copy()
    leaves = 0.0
    for i, q in enumerate(path):
        points = model.pad_points(q)
        along[i] = (points[pad] - p0) @ n0
        leaves = max(leaves, float(np.linalg.norm(points[pad] - p0)))
        closest = np.minimum(closest, np.linalg.norm(points - contact, axis=1))
    speed = np.diff(along) / dt if len(path) > 1 else np.zeros(0)
    return Assessment(
        normal_speed=speed,
        dt=dt,
        toward_m=float(max(0.0, along.max())),
        withdrawal_m=float(-along[-1]),
        approach_m=np.maximum(0.0, d0 - closest),
        furthest_m=float(max(0.0, -along.min())),
        furthest_at_s=float(np.argmin(along)) * dt,
        leaves_m=leaves,
    )


def toward_along_path(model: RobotModel, q0: np.ndarray, delta: np.ndarray, pad: int) -> tuple[float, float]:
    """Worst approach toward the contact along q0 + s delta, and the s where it happens."""
    p0, n0 = model.pad_point(q0, pad), model.pad_normal(q0, pad)
    worst, at = 0.0, 0.0
    for s in np.linspace(0.0, 1.0, PATH_SAMPLES + 1)[1:]:
        toward = (model.pad_point(q0 + s * delta, pad) - p0) @ n0
        if toward > worst:
            worst, at = float(toward), float(s)
    return worst, at


def guard_displacement(
    model: RobotModel, q0: np.ndarray, delta: np.ndarray, pad: int, q_min: np.ndarray, q_max: np.ndarray
) -> tuple[np.ndarray, bool]:
    """A displacement along which the touched pad never approaches the contact; and whether it changed."""
    worst, _ = toward_along_path(model, q0, delta, pad)
    if worst <= TOLERANCE_M:
        return delta, False
    n0 = model.pad_normal(q0, pad)
    out = delta.copy()
    for _ in range(8):
        worst, at = toward_along_path(model, q0, out, pad)
        if worst <= TOLERANCE_M:
            return out, True
        # Gradient of the pad's normal displacement at the worst point of the path.
        q_at = q0 + at * out
        grad = model.pad_jacobian(q_at, pad)[:3].T @ n0
        norm2 = float(grad @ grad)
        if norm2 < 1e-12:  # no joint behind this pad moves it along its normal
            break
        # Remove what pushes the pad forward there, plus a small retreat margin.
        excess = worst / max(at, 1e-3) + 2 * TOLERANCE_M
        out = np.clip(q0 + out - excess * grad / norm2, q_min, q_max) - q0
    # Last resort: keep only the part of the motion before the pad turns toward the contact.
    for scale in np.linspace(1.0, 0.0, 21)[1:]:
        if toward_along_path(model, q0, scale * out, pad)[0] <= TOLERANCE_M:
            return scale * out, True
    return np.zeros_like(delta), True


def guard_velocity(jac_lin: np.ndarray, normal: np.ndarray, dq: np.ndarray) -> tuple[np.ndarray, bool]:
    """Remove the part of a joint velocity that moves the pad toward the contact."""
    grad = jac_lin.T @ normal
    toward = float(grad @ dq)
    norm2 = float(grad @ grad)
    if toward <= 0.0 or norm2 < 1e-12:
        return dq, False
    return dq - toward * grad / norm2, True
