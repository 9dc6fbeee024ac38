"""The skin a profile selects (``robot.skin``), and where a contact lies on the arm.

``robot.skin = "pads"`` (the default) is the robot description's pad file, the paper's AIRSKIN; ``"taxels"`` is
the taxel skin file ``skin-taxels.toml`` beside the description's robot.toml (:mod:`nwr.common.taxels`,
docs/skins.md). On a taxel skin every per-element list of ``skin/pressure`` has one entry per taxel, in hPa
(the file's unit converted: 1 kPa = 10 hPa), and ``skin/pain`` stays per pad: each patch is named after the
pad it replaces.

:func:`contact_point` and :func:`contact_normal` give a :class:`~nwr.common.messages.Contact`'s location in the
base frame: its own (a taxel contact's point and normal in its link's frame) when it carries one, else its
pad's, so that every strategy reads a contact's location through one call.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.robot import Pad, RobotDescription, RobotModel, load_description, resolve_description
from nwr.common.taxels import TaxelSkin, load_taxel_skin

TAXELS = "taxels"
TAXEL_FILE = "skin-taxels.toml"
HPA_PER_PA = 0.01


def load_skin(profile: Profile, desc: RobotDescription | None = None) -> TaxelSkin | None:
    """The taxel skin the profile selects, checked against its robot; None for the pads."""
    if profile.robot.skin != TAXELS:
        return None
    desc = desc if desc is not None else load_description(profile.robot.description or None)
    path = resolve_description(profile.robot.description or None).parent / TAXEL_FILE
    if not path.is_file():
        raise ConfigError(f"robot.skin = \"taxels\": robot {desc.name!r} has no taxel skin ({path} does not "
                          f"exist); use robot.skin = \"pads\" or write one (docs/skins.md)")
    return load_taxel_skin(path, desc)


def hpa_per_unit(skin: TaxelSkin) -> float:
    """hPa per unit of the skin's readings."""
    return skin.pa_per_unit * HPA_PER_PA


def patch_pads(skin: TaxelSkin, pads: tuple[Pad, ...]) -> dict[str, int]:
    """Each patch's pad id (the pad of its name); ConfigError for a patch named after no pad."""
    ids = {pad.name: pad.id for pad in pads}
    unknown = sorted(set(skin.patches) - set(ids))
    if unknown:
        raise ConfigError(f"{skin.path}: patches {unknown} are named after no pad of the robot (pads: "
                          f"{sorted(ids)}); a patch takes the name of the pad it replaces")
    return {patch: ids[patch] for patch in skin.patches}


def entry_pads(skin: TaxelSkin, pads: tuple[Pad, ...]) -> np.ndarray:
    """Each taxel's pad id (its patch's pad), -1 where its patch is named after no pad."""
    ids = {pad.name: pad.id for pad in pads}
    per_patch = np.array([ids.get(patch, -1) for patch in skin.patches], dtype=int)
    return per_patch[skin.patch_index]


def contact_point(model: RobotModel, q: Any, contact: m.Contact) -> np.ndarray:
    """The contact's point in the base frame at ``q``: its own where it carries one, else its pad's."""
    if contact.link and contact.point:
        pose = model.frame_pose(q, contact.link)
        return pose[:3, :3] @ np.asarray(contact.point, dtype=float) + pose[:3, 3]
    return model.pad_point(q, contact.pad)


def contact_normal(model: RobotModel, q: Any, contact: m.Contact) -> np.ndarray:
    """The contact's outward unit normal in the base frame at ``q``: its own where it carries one, else its
    pad's."""
    if contact.link and contact.normal:
        return model.frame_pose(q, contact.link)[:3, :3] @ np.asarray(contact.normal, dtype=float)
    return model.pad_normal(q, contact.pad)
