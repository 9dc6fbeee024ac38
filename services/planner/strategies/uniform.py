"""Uniform reflex (UR) of the paper: q_ref = 1/2 q_max, q_max = [40, 70, 146, 73, 0, 0] deg, whatever G(p) > 0.

The fraction is ``[planner.uniform] fraction``; the displacement is added to
the pose as every joint-space reflex's (:class:`~nwr.services.planner.reflexes.JointReflex`).
It does not depend on the contact, so two contacts give the same motion as
one; only guarded mode differs, which keeps every touched pad from its contact.
"""

from __future__ import annotations

import numpy as np

from nwr.common import messages as m
from nwr.common.config import Fraction, PlannerSection
from nwr.common.guards import Guard
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.section import Section
from nwr.services.planner.reflexes import JointReflex
from nwr.services.planner.strategies import KIND


class UniformSettings(Section):
    """``[planner.uniform]``."""

    # UR adds this fraction of planner.q_max_deg (the paper's 1/2).
    fraction: Fraction = 0.5


class Uniform(JointReflex):
    name = "uniform"
    rank = 10
    Settings = UniformSettings
    GUARDS = {"fraction": Guard("above")}

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> None:
        super().__init__(cfg, desc, model, v_limit)
        self.fraction = KIND.settings(cfg, self.name, UniformSettings).fraction

    def displacement(self, contact: m.Contact) -> np.ndarray:
        return self.fraction * self.q_max


STRATEGY = Uniform
