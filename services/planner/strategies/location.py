"""Location-dependent reflex (LR) of the paper: q_ref = G(p) W(PL, region) q_max.

W = diag(w per joint, its group's: on the UR10e w_b, w_s, w_e, w_w, w_w, w_w): the weights are the robot's
table (robot.toml [location]; the UR10e's is the paper's Table II) or the profile's ``[planner.location]``, one
table per pain level 3 and 4 (PL 1-2: no motion); the displacement is added
to the pose as every joint-space reflex's
(:class:`~nwr.services.planner.reflexes.JointReflex`).

With other active contacts (each with its gain G_i, pain level PL_i and its
pad's region) q_ref is the joint-space sum sum_i G_i W(PL_i, region_i) q_max
over every contact, the reflex's own included, each joint at most its q_max:
two hands on the forearm swing the elbow no farther than one at full gain.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

import msgspec
import numpy as np

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.errors import ConfigError
from nwr.common.guards import Guard
from nwr.common.robot import REGIONS, RobotDescription, RobotModel
from nwr.common.section import Section
from nwr.services.planner.reflexes import JointReflex
from nwr.services.planner.strategies import KIND

if TYPE_CHECKING:
    from nwr.common.config import Profile

# Four weights in [0, 1]: [w_base, w_shoulder, w_elbow, w_wrist].
Weights = Annotated[list[Annotated[float, msgspec.Meta(ge=0, le=1)]], msgspec.Meta(min_length=4, max_length=4)]


class LocationSettings(Section):
    """``[planner.location]``: the weights W."""

    # [w_base, w_shoulder, w_elbow, w_wrist] per body region, for pain level 3
    # and 4 (PL 1-2: all zero, no motion); empty = the robot's table
    # (robot.toml [location]: the UR10e's is the paper's Table II). A joint
    # takes its group's weight (robot.toml reflex_group: the UR10e's wrist
    # weight applies to all three wrist joints). Every region of the robot's
    # pads needs its row.
    pl3: dict[str, Weights] = {}
    pl4: dict[str, Weights] = {}


def robot_settings(desc: RobotDescription) -> LocationSettings:
    """The robot's own table (robot.toml [location]) as the strategy's settings: the defaults on that robot."""
    table = desc.location or {}
    return LocationSettings(pl3=dict(table.get("pl3", {})), pl4=dict(table.get("pl4", {})))


def resolved(weights: LocationSettings, desc: RobotDescription) -> LocationSettings:
    """The profile's table, each level the robot's where the profile leaves it empty."""
    own = robot_settings(desc)
    return LocationSettings(pl3=weights.pl3 or own.pl3, pl4=weights.pl4 or own.pl4)


class Location(JointReflex):
    name = "location"
    rank = 20
    Settings = LocationSettings
    robot_settings = staticmethod(robot_settings)
    GUARDS = {f"{level}.{region}": Guard("above") for level in ("pl3", "pl4") for region in REGIONS}

    @staticmethod
    def check_settings(weights: LocationSettings, profile: Profile | None, desc: RobotDescription) -> None:
        """Every row a body region's, every region of the robot's pads with its row."""
        weights = resolved(weights, desc)
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
        self.weights: dict[int, dict[str, np.ndarray]] = {}
        self.regions = [pad.region for pad in desc.pads]
        weights = resolved(KIND.settings(cfg, self.name, LocationSettings), desc)
        for level, table in ((3, weights.pl3), (4, weights.pl4)):
            self.weights[level] = {}
            for region, w in table.items():
                if len(w) != 4 or not all(0.0 <= x <= 1.0 for x in w):
                    raise ConfigError(
                        f"planner.location.pl{level}.{region} must be four weights in [0, 1] "
                        f"[base, shoulder, elbow, wrist], got {w}"
                    )
                # One weight per joint: its group's (robot.toml reflex_group).
                self.weights[level][region] = desc.joint_weights(w)

    def displacement(self, contact: m.Contact) -> np.ndarray:
        own = self._share(contact.level, contact.region, contact.gain)
        if not self.other_contacts:
            return own
        total = own + sum(self._share(other.level, self.regions[other.pad], other.gain)
                          for other in self.other_contacts)
        return np.minimum(total, self.q_max)

    def _share(self, level: int, region: str, gain: float) -> np.ndarray:
        """One contact's G W(PL, region) q_max."""
        table = self.weights.get(level)
        if table is None:  # PL 1-2: no motion
            return np.zeros_like(self.q_max)
        w = table.get(region)
        if w is None:
            raise ConfigError(f"planner.location.pl{level} has no weights for region {region!r}")
        return gain * w * self.q_max


STRATEGY = Location
