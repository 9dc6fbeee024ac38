"""A taxel skin in the physics world: the world's contact forces on the arm, read by taxels.

The world's arm carries the AIRSKIN pads' cushions (:mod:`nwr.services.worlds.mjcf`); a taxel skin here is
a reading of the same contacts, not a geometry of its own. Each contact between a body part and the arm
(:meth:`PhysicsWorld.touches`) on a link that has taxels presses them as :func:`nwr.common.taxels.finger_pressure`
presses a finger: its normal force (N) spread over the taxels within ``radius_m`` of the contact point, which
is first brought into the link's frame and onto the taxel skin's surface (the tangent plane of the taxel
nearest it: the cushions lie ~0.03 m above the taxels). A contact with a link without taxels reads nothing,
and a contact that pulls (a normal force <= 0) presses nothing. The readings' force sums to the contacts'
normal forces on the taxel links.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from nwr.common.robot import RobotModel
from nwr.common.taxels import TaxelSkin, finger_pressure, nearest_taxel
from nwr.services.worlds.physics import PhysicsWorld


class WorldTaxels:
    """Reads a physics world's contacts on a taxel skin; built once per world."""

    def __init__(self, world: PhysicsWorld, skin: TaxelSkin, model: RobotModel, radius_m: float) -> None:
        self.world, self.skin, self.model, self.radius_m = world, skin, model, radius_m
        # The world's bodies are named after the joints that move them (fixed links merged in): each taxel
        # link by the joint that moves it.
        pinocchio = model.model
        self._link_of_body: dict[str, str] = {}
        for link in skin.links:
            frame = pinocchio.frames[pinocchio.getFrameId(link, pin.FrameType.BODY)]
            self._link_of_body[pinocchio.names[frame.parentJoint]] = link

    def link_of(self, geom: str) -> str | None:
        """The taxel link an arm geom belongs to, or None."""
        mj = self.world.model
        body = mj.body(int(mj.geom_bodyid[mj.geom(geom).id])).name
        return self._link_of_body.get(body)

    def readings(self) -> np.ndarray:
        """Every taxel's reading (the skin's unit) from the contacts of the world's last step."""
        out = np.zeros(len(self.skin))
        q = self.world.arm().q
        for touch in self.world.touches():
            force = float(touch.force @ touch.normal)
            link = self.link_of(touch.geom)
            if link is None or not force > 0.0:
                continue
            pose = self.model.frame_pose(q, link)
            point = pose[:3, :3].T @ (touch.point - pose[:3, 3])
            taxel = nearest_taxel(self.skin, link, point)
            normal = self.skin.normals[taxel]
            centre = point - float((point - self.skin.points[taxel]) @ normal) * normal
            out += finger_pressure(self.skin, link, centre, self.radius_m, force)
        return out
