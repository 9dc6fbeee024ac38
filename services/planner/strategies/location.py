"""Location-dependent reflex (LR) of the paper: q_ref = G(p) W(PL, region) q_max.

W = diag(w_b, w_s, w_e, w_w, w_w, w_w): the weights are the paper's Table II (``planner.location_weights``), one
table per pain level 3 and 4 (PL 1-2: no motion); the displacement is added
to the pose as every joint-space reflex's
(:class:`~nwr.services.planner.reflexes.JointReflex`).
"""

from __future__ import annotations

import numpy as np

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner.reflexes import JointReflex


class Location(JointReflex):
    name = "location"
    rank = 20

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> None:
        super().__init__(cfg, desc, model, v_limit)
        n = len(desc.joints)
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
        table = self.weights.get(contact.level)
        if table is None:  # PL 1-2: no motion
            return np.zeros_like(self.q_max)
        w = table.get(contact.region)
        if w is None:
            raise ConfigError(f"planner.location_weights.pl{contact.level} has no weights "
                              f"for region {contact.region!r}")
        return contact.gain * w * self.q_max


STRATEGY = Location
