"""Cartesian reflex (CR) of the paper: the touched pad withdraws along its normal.

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
- Guarded mode removes, every cycle, any component of q_dot that pushes the
  pad toward the contact (:func:`~nwr.services.planner.retreat.guard_velocity`).

Other active contacts (this project's; the paper has one): each other pad
touched with a gain G_i when the reflex (re)starts adds the rows the paper
asks of one pad (6 with ``hold_orientation``, else the 3 linear ones),
asking [v_i; 0], v_i = -v_max G_i n_i (n_i its pad's outward normal then,
kept like the reflex's own), and the stacked system is solved with the same
damped least-squares inverse over the joints that move any of the pads. The
same row set as the reflex's own: with the linear rows only, a forearm pad
that is not the strongest withdraws several times farther than it would as
the reflex's own and folds the wrist toward the other hand (on the project's
``contacts`` script, another pad up to 67 mm closer to the strongest's
contact, against 25 mm). The rows are not weighted: each asks a velocity in
m/s (or rad/s), so where the joints cannot serve every pad at once each
pad's shortfall counts by its size, the reflex's own included. In guarded
mode no touched pad moves toward its contact: q_dot becomes the nearest
joint velocity that moves none of them toward it. One contact gives exactly
the paper's stream.
"""

from __future__ import annotations

import copy

import numpy as np

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.skin import contact_normal
from nwr.services.planner.reflexes import damped_pinv, scale_to_limits
from nwr.services.planner.retreat import guard_velocity
from nwr.services.planner.strategies import Onset, ReflexStrategy


class Cartesian(ReflexStrategy):
    """Resolved-rate withdrawal of the touched pad along its normal."""

    name = "cartesian"
    rank = 30
    mode = "velocity"

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> None:
        super().__init__(cfg, desc, model, v_limit)
        self.v_max = cfg.v_max_m_s
        self.damping_max = cfg.damping_max
        self.threshold = cfg.singular_threshold
        self.v_limit = v_limit
        self.rows = 6 if cfg.hold_orientation else 3
        self.guarded = cfg.guarded
        self._twist = np.zeros(6)
        self._normal = np.zeros(3)
        self.pad = -1
        # The other active contacts at the (re)start: (pad, its outward normal then, its twist [v_i; 0]).
        self._extra: tuple[tuple[int, np.ndarray, np.ndarray], ...] = ()

    def start(self, q: np.ndarray, contact: m.Contact) -> Onset:
        """Begin (or update) a reflex; its direction is the contact's normal (the pad's, or the taxels')."""
        self.pad = contact.pad
        self.corrections = 0
        normal = self._normal = contact_normal(self.model, q, contact)
        self._twist[:3] = -self.v_max * contact.gain * normal
        self._twist[3:] = 0.0
        extra = []
        for other in self.other_contacts:
            normal_i = self.model.pad_normal(q, other.pad)
            extra.append((other.pad, normal_i, np.concatenate([-self.v_max * other.gain * normal_i, np.zeros(3)])))
        self._extra = tuple(extra)
        return Onset(direction=self._twist[:3].tolist())

    def velocity(self, q: np.ndarray, t: float, *, count: bool = True) -> np.ndarray:
        """q_dot at the current pose (every control cycle; the plain stream does not depend on ``t``)."""
        full = self.model.pad_jacobian(q, self.pad)
        jac, twist = full[: self.rows], self._twist[: self.rows]
        fulls = [self.model.pad_jacobian(q, pad) for pad, _, _ in self._extra]
        if fulls:  # every other touched pad's rows below the reflex's own
            jac = np.vstack([jac, *(full_i[: self.rows] for full_i in fulls)])
            twist = np.concatenate([twist, *(twist_i[: self.rows] for _, _, twist_i in self._extra)])
        moving = np.any(jac != 0.0, axis=0)
        dq = np.zeros(jac.shape[1])
        dq[moving] = damped_pinv(jac[:, moving], self.damping_max, self.threshold) @ twist
        if self.guarded:
            others = [(full_i[:3], normal_i) for full_i, (_, normal_i, _) in zip(fulls, self._extra, strict=True)]
            dq, corrected = guard_velocity(full[:3], self._normal, dq, others)
            if corrected and count:
                self.corrections += 1
        return scale_to_limits(dq, self.v_limit)

    def snapshot(self) -> Cartesian:
        stream = copy.copy(self)
        stream._twist = self._twist.copy()
        stream._normal = self._normal.copy()
        return stream


STRATEGY = Cartesian
