"""Smoothed Cartesian reflex (CR-smooth): the Cartesian stream ramped in and out.

The stream of :mod:`.cartesian` multiplied by a raised-cosine ramp of
``[planner.cartesian-smooth] ramp_s`` at both ends, its plateau raised by T/(T - ramp)
so that the displacement equals the plain reflex's
(:func:`~nwr.services.planner.reflexes.smooth_profile`).
"""

from __future__ import annotations

from typing import Annotated

import msgspec
import numpy as np

from nwr.common.config import PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.section import Section
from nwr.services.planner.reflexes import smooth_profile
from nwr.services.planner.strategies import KIND
from nwr.services.planner.strategies.cartesian import Cartesian


class SmoothSettings(Section):
    """``[planner.cartesian-smooth]``."""

    # Rise and fall time of its velocity (a raised cosine), s; the plateau is
    # raised so the displacement equals the plain reflex's.
    ramp_s: Annotated[float, msgspec.Meta(gt=0, le=0.25)] = 0.1


class CartesianSmooth(Cartesian):
    name = "cartesian-smooth"
    rank = 40
    Settings = SmoothSettings

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> None:
        super().__init__(cfg, desc, model, v_limit)
        self.duration_s = cfg.reflex_duration_s
        self.ramp_s = KIND.settings(cfg, self.name, SmoothSettings).ramp_s

    def velocity(self, q: np.ndarray, t: float, *, count: bool = True) -> np.ndarray:
        return super().velocity(q, t, count=count) * smooth_profile(t, self.duration_s, self.ramp_s)


STRATEGY = CartesianSmooth
