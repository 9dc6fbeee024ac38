"""Uniform reflex (UR) of the paper: q_ref = 1/2 q_max, q_max = [40, 70, 146, 73, 0, 0] deg, whatever G(p) > 0.

The fraction is ``planner.uniform_fraction``; the displacement is added to
the pose as every joint-space reflex's (:class:`~nwr.services.planner.reflexes.JointReflex`).
"""

from __future__ import annotations

import numpy as np

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner.reflexes import JointReflex


class Uniform(JointReflex):
    name = "uniform"
    rank = 10

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> None:
        super().__init__(cfg, desc, model, v_limit)
        self.fraction = cfg.uniform_fraction

    def displacement(self, contact: m.Contact) -> np.ndarray:
        return self.fraction * self.q_max


STRATEGY = Uniform
