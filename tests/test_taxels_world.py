"""The physics world's contacts read by the UR10e's taxel skin (services/worlds/taxels.py): a finger pressing
a pad of a taxel link presses the taxels under it with the world's own contact force; elsewhere, nothing."""

from __future__ import annotations

import numpy as np
import pytest

from nwr.common.robot import ROBOTS_DIR, RobotModel, load_description
from nwr.common.taxels import contacts, load_taxel_skin
from nwr.services.worlds.physics import PhysicsWorld
from nwr.services.worlds.taxels import WorldTaxels

DESC = load_description(None)
MODEL = RobotModel(DESC)
SKIN = load_taxel_skin(ROBOTS_DIR / "ur10e" / "skin-taxels.toml", DESC)


@pytest.mark.parametrize(("pad", "force", "surface"), [
    ("upper_arm_top", 8.0, (-0.30, 0.065, 0.176)),
    ("upper_arm_bottom", 14.0, (-0.30, -0.065, 0.176)),
    ("forearm_top", 5.0, (-0.28, 0.06, 0.04)),
    ("forearm_bottom", 8.0, (-0.28, -0.06, 0.04)),
])
def test_a_finger_in_the_world_presses_the_taxels_under_its_pad(pad: str, force: float,
                                                                 surface: tuple[float, ...]) -> None:
    world = PhysicsWorld(DESC)
    world.press("finger", pad, force)
    world.run(DESC.home, 1.0)
    readings = WorldTaxels(world, SKIN, MODEL, 0.03).readings()
    # The world's normal force on the pad's cushion, all of it on the taxels, as one contact.
    pad_force = float(world.pad_force_n()[DESC.pad(pad).id])
    assert pad_force == pytest.approx(force, rel=0.1)
    (contact,) = contacts(SKIN, readings, 1e-9)
    assert contact.force_n == pytest.approx(pad_force, rel=1e-9)
    assert contact.patch == pad and contact.link == DESC.pad(pad).link
    # Under the pad's point, on the taxel surface, facing as the pad does.
    assert np.linalg.norm(contact.point - surface) < 0.01
    assert contact.normal @ DESC.pad(pad).normal > 0.99


def test_contacts_off_the_taxels_read_nothing() -> None:
    # A finger on the wrist (a link without taxels) and a palm on the elbow's lid (the upper arm's link, 0.1 m
    # past its last taxels): the world feels both, no taxel does.
    world = PhysicsWorld(DESC)
    world.press("finger", "wrist_1", 8.0)
    world.press("palm", "elbow_outer", 10.0, kind="palm")
    world.run(DESC.home, 1.0)
    felt = world.pad_force_n()
    assert felt[DESC.pad("wrist_1").id] > 5.0 and felt[DESC.pad("elbow_outer").id] > 5.0
    taxels = WorldTaxels(world, SKIN, MODEL, 0.03)
    links = {taxels.link_of(t.geom) for t in world.touches()}
    assert links == {None, "upper_arm_link"}
    assert not taxels.readings().any()
