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
  touched pad's point at the onset, where the finger is);
- per other active contact (another pad touched at the onset), how far that
  pad ever moves toward its own contact, along its own normal at the onset.

:func:`guard_displacement` corrects a joint-space displacement whose path
would move the touched pad (or any other touched pad) toward its contact: it
removes the offending component along the gradient of each such pad's normal
displacement, J_lin^T n0 (the smallest joint-space change that makes every
one of them retreat: a small quadratic programme, quadprog, when two or more
push at once, so that the correction for one does not undo another's),
checking the whole path with the full kinematics, and as a last resort
shortens the motion to the part that retreats (as when no joint change
retreats them all). :func:`guard_velocity` does the same for one control
cycle's joint velocity: the nearest velocity that moves no touched pad
toward its contact (a non-negative least-squares fit, scipy's ``nnls``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import quadprog
from scipy.optimize import nnls

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
    # The other active contacts' pads, and how far each ever moves toward its own contact (>= 0), m.
    contacts: tuple[int, ...] = ()
    contacts_toward_m: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def to_message(self, pad: int, corrected: bool) -> m.Retreat:
        others = self.approach_m.copy()
        others[pad] = 0.0
        worst = int(np.argmax(others))
        return m.Retreat(
            contacts=list(self.contacts),
            contacts_toward_m=self.contacts_toward_m.tolist(),
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


def assess(model: RobotModel, path: np.ndarray, dt: float, pad: int, others: Sequence[int] = ()) -> Assessment:
    """Retreat figures of a sampled joint path (k x n, first row = the onset pose); ``others``: the pads of the
    other active contacts, each judged against its own contact (its point and normal at the onset)."""
    q0 = path[0]
    others = tuple(p for p in others if p != pad)
    p0 = model.pad_point(q0, pad)
    n0 = model.pad_normal(q0, pad)
    contact = p0
    d0 = np.linalg.norm(model.pad_points(q0) - contact, axis=1)
    along = np.empty(len(path))
    closest = d0.copy()
    leaves = 0.0
    ahead = np.zeros(len(others))
    if others:
        first, normals = model.pad_points(q0)[list(others)], model.pad_normals(q0)[list(others)]
    for i, q in enumerate(path):
        points = model.pad_points(q)
        along[i] = (points[pad] - p0) @ n0
        if others:
            ahead = np.maximum(ahead, np.einsum("ij,ij->i", points[list(others)] - first, normals))
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
        contacts=others,
        contacts_toward_m=ahead,
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


def _pushing(model: RobotModel, q0: np.ndarray, delta: np.ndarray,
             pads: Sequence[int]) -> list[tuple[int, float, float]]:
    """The pads that ``delta``'s path moves toward their contacts: (pad, worst approach, where)."""
    found = []
    for pad in pads:
        worst, at = toward_along_path(model, q0, delta, pad)
        if worst > TOLERANCE_M:
            found.append((pad, worst, at))
    return found


def guard_displacement(
    model: RobotModel, q0: np.ndarray, delta: np.ndarray, pad: int, q_min: np.ndarray, q_max: np.ndarray,
    others: Sequence[int] = (),
) -> tuple[np.ndarray, bool]:
    """A displacement along which the touched pad, and the pad of each other active contact (``others``), never
    approaches its contact (the pad's point and normal at ``q0``); and whether it changed."""
    pads = [pad, *(p for p in others if p != pad)]
    if not _pushing(model, q0, delta, pads):
        return delta, False
    normals = {p: model.pad_normal(q0, p) for p in pads}
    out = delta.copy()
    for _ in range(8):
        pushing = _pushing(model, q0, out, pads)
        if not pushing:
            return out, True
        # Gradient of each pushing pad's normal displacement at the worst point of its path, and how much of
        # it to remove there (plus a small retreat margin).
        grads, excess = [], []
        for p, worst, at in pushing:
            grad = model.pad_jacobian(q0 + at * out, p)[:3].T @ normals[p]
            if float(grad @ grad) >= 1e-12:  # else no joint behind this pad moves it along its normal
                grads.append(grad)
                excess.append(worst / max(at, 1e-3) + 2 * TOLERANCE_M)
        if not grads:
            break
        step = _least_change(np.array(grads), np.array(excess))
        if step is None:  # the pads ask for opposite changes: no joint change retreats them all
            break
        out = np.clip(q0 + out + step, q_min, q_max) - q0
    # Last resort: keep only the part of the motion before any of the pads turns toward its contact.
    for scale in np.linspace(1.0, 0.0, 21)[1:]:
        if not _pushing(model, q0, scale * out, pads):
            return scale * out, True
    return np.zeros_like(delta), True


def _least_change(grads: np.ndarray, excess: np.ndarray) -> np.ndarray | None:
    """The smallest joint change c with grads[i] . c <= -excess[i] for every row (None if there is none)."""
    if len(grads) == 1:  # the closed form of the one-row case
        grad = grads[0]
        return -excess[0] * grad / float(grad @ grad)
    # quadprog: minimise 1/2 c'c subject to (-grads) c >= excess.
    try:
        return np.asarray(quadprog.solve_qp(np.eye(grads.shape[1]), np.zeros(grads.shape[1]), -grads.T, excess)[0])
    except ValueError:  # "constraints are inconsistent"
        return None


def guard_velocity(jac_lin: np.ndarray, normal: np.ndarray, dq: np.ndarray,
                   others: Sequence[tuple[np.ndarray, np.ndarray]] = ()) -> tuple[np.ndarray, bool]:
    """Remove the part of a joint velocity that moves the pad toward the contact (``jac_lin``: the pad's linear
    Jacobian, ``normal``: its contact's normal) and, with ``others`` (each other active contact's pad's linear
    Jacobian and its contact's normal), the nearest joint velocity that moves none of them toward its contact."""
    rows = [jac.T @ n for jac, n in ((jac_lin, normal), *others)]
    rows = [g for g in rows if float(g @ g) >= 1e-12]  # pads no joint moves along their normal
    pushing = [g for g in rows if float(g @ dq) > 0.0]
    if not pushing:
        return dq, False
    if len(rows) == 1:  # the closed form of the one-pad case
        grad = rows[0]
        return dq - float(grad @ dq) * grad / float(grad @ grad), True
    # The nearest dq' with every row g . dq' <= 0 is dq's projection on that cone: dq less its projection on the
    # polar cone {G' l, l >= 0} (Moreau), whose l is a non-negative least-squares fit of dq (scipy's nnls, sound
    # however many rows and however dependent, where an active-set QP can fail on degenerate ones).
    grads = np.array(rows)
    weights = nnls(grads.T, np.asarray(dq, dtype=float))[0]
    return dq - grads.T @ weights, True
