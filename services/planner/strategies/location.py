"""Location-dependent reflex (LR) of the paper: q_ref = G(p) W(PL, region) q_max.

W = diag(w_b, w_s, w_e, w_w, w_w, w_w): the weights are the paper's Table II (``[planner.location]``), one
table per pain level 3 and 4 (PL 1-2: no motion); the displacement is added
to the pose as every joint-space reflex's
(:class:`~nwr.services.planner.reflexes.JointReflex`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

import msgspec
import numpy as np

from nwr.common import messages as m
from nwr.common.config import Guard, PlannerSection
from nwr.common.errors import ConfigError
from nwr.common.robot import REGIONS, RobotDescription, RobotModel
from nwr.common.section import Section
from nwr.services.planner.reflexes import JointReflex
from nwr.services.planner.strategies import KIND

if TYPE_CHECKING:
    from nwr.common.config import Profile

# Four weights in [0, 1]: [w_base, w_shoulder, w_elbow, w_wrist].
Weights = Annotated[list[Annotated[float, msgspec.Meta(ge=0, le=1)]], msgspec.Meta(min_length=4, max_length=4)]


def _w(*rows: list[float]) -> dict[str, list[float]]:
    return dict(zip(REGIONS, rows))


class LocationSettings(Section):
    """``[planner.location]``: the weights W."""

    # The paper's Table II: [w_base, w_shoulder, w_elbow, w_wrist] per body
    # region, for pain level 3 and 4 (PL 1-2: all zero, no motion). The wrist
    # weight applies to all three wrist joints. Every region of the robot's
    # pads needs its row.
    pl3: dict[str, Weights] = msgspec.field(default_factory=lambda: _w(
        [0.2, 0.8, 0.6, 0.0], [0.2, 0.8, 0.6, 0.0], [0.0, 0.6, 0.8, 0.2], [0.0, 0.6, 0.8, 0.2], [0.0, 0.3, 0.6, 0.8]))
    pl4: dict[str, Weights] = msgspec.field(default_factory=lambda: _w(
        [0.5, 1.0, 0.7, 0.1], [0.5, 1.0, 0.7, 0.1], [0.0, 0.8, 1.0, 0.4], [0.0, 0.8, 1.0, 0.4], [0.0, 0.6, 0.8, 1.0]))


class Location(JointReflex):
    name = "location"
    rank = 20
    Settings = LocationSettings
    GUARDS = {f"{level}.{region}": Guard("above") for level in ("pl3", "pl4") for region in REGIONS}

    @staticmethod
    def check_settings(weights: LocationSettings, profile: Profile | None, desc: RobotDescription) -> None:
        """Every row a body region's, every region of the robot's pads with its row."""
        regions = sorted({pad.region for pad in desc.pads})
        for level in ("pl3", "pl4"):
            table = getattr(weights, level)
            unknown = sorted(set(table) - set(REGIONS))
            if unknown:
                raise ConfigError(f"planner.location.{level} has rows for {unknown}, which are no body regions; "
                                  f"the regions are {list(REGIONS)}")
            missing = [r for r in regions if r not in table]
            if missing:
                raise ConfigError(f"planner.location.{level} has no row for {missing}, regions of robot "
                                  f"{desc.name!r}'s pads: give [w_base, w_shoulder, w_elbow, w_wrist] for each")

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> None:
        super().__init__(cfg, desc, model, v_limit)
        n = len(desc.joints)
        self.weights: dict[int, dict[str, np.ndarray]] = {}
        weights = KIND.settings(cfg, self.name, LocationSettings)
        for level, table in ((3, weights.pl3), (4, weights.pl4)):
            self.weights[level] = {}
            for region, w in table.items():
                if len(w) != 4 or not all(0.0 <= x <= 1.0 for x in w):
                    raise ConfigError(
                        f"planner.location.pl{level}.{region} must be four weights in [0, 1] "
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
            raise ConfigError(f"planner.location.pl{contact.level} has no weights "
                              f"for region {contact.region!r}")
        return contact.gain * w * self.q_max


STRATEGY = Location
