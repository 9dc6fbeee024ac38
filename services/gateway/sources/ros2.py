"""The gateway's ROS 2 skin source (``gateway.source = "ros2"``): a real skin's pressures from a ROS 2 topic on
rmw_zenoh, no ROS 2 installation needed.

The gateway's ROS 2 node (``nwr_gateway``, :class:`nwr.common.ros2.Ros2Link`:
a session of its own, a client of ``[ros2] router``, domain ``[ros2]
domain_id``) subscribes to ``gateway.ros2.topic`` under rmw_zenoh's keys,
any type hash (or only ``type_hash``); each sample's CDR is decoded with
``rosbags``' type store (the ``[ros2] distro``'s standard types, or
``message_type`` generated from ``definition``), and its values field is
mapped and checked by the code the ROS 1 source uses
(:class:`~nwr.services.gateway.sources._feed.SkinFeed`,
:func:`nwr.common.skinmap.map_values`): the same pad mapping, scale and
offset, per-pad invalid marks and units check.

Bad input, each counted and reported on ``diag/gateway``, never a stop:

- a sample without rmw_zenoh's 33-byte attachment: dropped, as rmw_zenoh
  drops it (``ros2_no_attachment``);
- a sample of another type than ``message_type``, or of another type hash
  than ``type_hash`` when one is set, or whose CDR does not decode:
  dropped (``ros2_bad_message``);
- the wrong number of values, non-finite or out-of-range values: those pads
  invalid in that sample (``ros2_bad_message``), every value out of range the
  wrong units (``ros2_units``);
- no sample for ``timeout_s``: ``ros2_no_messages`` (the skin goes stale and
  the bridge stops the arm); no router: ``ros2_router_unreachable``.

A type the type store does not have and ``definition`` does not give, a
``values_field`` that is no field of it or no array of numbers: a one-line
error at start.
"""

from __future__ import annotations

import argparse
import logging
import threading
from typing import TYPE_CHECKING, Annotated, Any

import msgspec

from nwr.common import rmw_zenoh as rz
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.guards import Guard
from nwr.common.ros2_msgs import field_names, numbers_field
from nwr.common.section import Section
from nwr.common.skinmap import PadMap, pad_map
from nwr.services.gateway.sources import KIND
from nwr.services.gateway.sources._feed import SkinFeed, gateway_node
from nwr.services.gateway.sources.ros1 import ROS1_DEFAULT_PADS
from nwr.services.gateway.wiring import GatewayWiring

if TYPE_CHECKING:
    from nwr.common.robot import RobotDescription
    from nwr.common.ros2 import Ros2Sample

log = logging.getLogger(__name__)

NAME = "ros2"


class Settings(Section):
    """The ROS 2 skin source's settings: ``[gateway.ros2]`` (the graph it joins: ``[ros2]``)."""

    # The ROS 2 topic that carries the skin's pressures (relative names are
    # in [ros2] namespace).
    topic: str = "/bullet_ros/airskin_status"
    # Its message type, package/msg/Name as `ros2 topic type TOPIC` prints it.
    message_type: str = "airskin_msgs/msg/AirskinStatus"
    # The type's definition (its .msg text), for a type that is not one of
    # ROS 2's standard ones; empty: a standard type (e.g.
    # std_msgs/msg/Float32MultiArray with values_field = "data").
    definition: str = "float32[] pressures"
    # The message's field holding the pressures (an array of numbers).
    values_field: str = "pressures"
    # Only samples of this type hash (RIHS01_..., as `ros2 topic info -v`
    # shows it); empty: any (a Humble publisher sends none).
    type_hash: Annotated[str, msgspec.Meta(pattern=r"^(RIHS01_[0-9a-f]{64})?$")] = ""
    # The pad mapping: entry i names the robot's pad that the message's value
    # i is; "" = a value no pad takes. A message must carry this many values.
    pads: list[str] = msgspec.field(default_factory=lambda: list(ROS1_DEFAULT_PADS))
    # A value v is the absolute pressure v * scale_hpa + offset_hpa, hPa
    # (the gateway takes each pad's change from its own baseline).
    scale_hpa: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 1.0
    offset_hpa: Annotated[float, msgspec.Meta(ge=-5000, le=5000)] = 0.0
    # No sample for this long: a diagnostic (the skin is stale; the bridge
    # stops the arm after bridge.skin_timeout_s).
    timeout_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 0.5


# A smaller scale makes every press feel smaller: the gain's thresholds are crossed later, or never.
GUARDS = {"scale_hpa": Guard("below", "hPa")}


def settings_of(profile: Profile) -> Settings:
    """The profile's ``[gateway.ros2]``."""
    return KIND.settings(profile.gateway, NAME, Settings)


def check_settings(cfg: Settings, profile: Profile, desc: RobotDescription) -> None:
    """The pad mapping names the robot's pads and the type is one the gateway can decode, when this is the
    gateway's source."""
    if profile.gateway.source == NAME:
        pad_map(cfg.pads, [pad.name for pad in desc.pads], scale_hpa=cfg.scale_hpa, offset_hpa=cfg.offset_hpa,
                where="gateway.ros2.pads")
        skin_types(cfg, profile.ros2.distro)


def skin_types(cfg: Settings, distro: str) -> Any:
    """``rosbags``' type store of ``distro`` with ``cfg.message_type`` in it, its values field checked;
    ConfigError naming the field to fix."""
    from rosbags.typesys import get_types_from_msg

    from nwr.common.ros2 import typestore

    parts = cfg.message_type.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise ConfigError(f"gateway.ros2.message_type = {cfg.message_type!r}: write package/msg/Name, e.g. "
                          "std_msgs/msg/Float32MultiArray")
    types = typestore(distro)
    if cfg.definition.strip():
        try:
            types.register(get_types_from_msg(cfg.definition, cfg.message_type))
        except Exception as exc:  # rosbags raises assorted errors for a definition it cannot parse
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
            raise ConfigError(f"gateway.ros2.definition is no valid message definition of {cfg.message_type}: "
                              f"{first}") from exc
    elif cfg.message_type not in types.fielddefs:
        raise ConfigError(f"gateway.ros2.message_type = {cfg.message_type!r} is no standard ROS 2 type of "
                          f"{distro}: give its .msg text as gateway.ros2.definition")
    fields = field_names(types, cfg.message_type)
    if cfg.values_field not in fields:
        raise ConfigError(f"gateway.ros2.values_field = {cfg.values_field!r} is no field of {cfg.message_type} "
                          f"(its fields: {fields})")
    if (shape := numbers_field(types, cfg.message_type, cfg.values_field)) is not None:
        raise ConfigError(f"gateway.ros2.values_field = {cfg.values_field!r} of {cfg.message_type} is {shape}, "
                          "not an array of numbers")
    return types


class Ros2Skin(SkinFeed):
    """The subscription's callback: a ROS 2 sample's type and CDR checked, then the ROS 1 source's mapping."""

    source = NAME

    def __init__(self, cfg: Settings, types: Any, pmap: PadMap, wiring: GatewayWiring, lock: threading.Lock,
                 diag: Any) -> None:
        super().__init__(cfg, pmap, wiring, lock, diag)
        self.types = types
        self.dds_type = rz.dds_type_name(cfg.message_type)
        self.dropped = 0  # samples without rmw_zenoh's attachment

    def on_dropped(self, key: str, why: str) -> None:
        self.dropped += 1
        self.diag("warning", "ros2_no_attachment",
                  f"dropped a sample on {key} without rmw_zenoh's attachment ({why}): no ROS 2 publisher sends "
                  f"one ({self.dropped} so far)")

    def on_sample(self, sample: Ros2Sample) -> None:
        if sample.dds_type != self.dds_type:
            self.reject(f"its type is {sample.dds_type}, not {self.dds_type} (gateway.ros2.message_type)")
            return
        if self.cfg.type_hash and sample.type_hash != self.cfg.type_hash:
            self.reject(f"its type hash is {sample.type_hash}, not {self.cfg.type_hash} (gateway.ros2.type_hash): "
                        "another definition of the type")
            return
        try:
            msg = self.types.deserialize_cdr(sample.payload, self.cfg.message_type)
        except Exception as exc:  # rosbags raises assorted errors for bytes that are no such message
            self.reject(f"its CDR does not decode as {self.cfg.message_type} ({type(exc).__name__}: {exc})")
            return
        self.on_message(msg)


def run(profile: Profile, args: argparse.Namespace) -> int:
    """The gateway with the ROS 2 source, until stopped."""
    from nwr.common.robot import load_description

    cfg = settings_of(profile)
    types = skin_types(cfg, profile.ros2.distro)
    desc = load_description(profile.robot.description or None)
    pmap = pad_map(cfg.pads, [p.name for p in desc.pads], scale_hpa=cfg.scale_hpa, offset_hpa=cfg.offset_hpa,
                   where="gateway.ros2.pads")
    with gateway_node(profile, pmap, "ros2") as (node, wiring, lock):
        skin = Ros2Skin(cfg, types, pmap, wiring, lock, node.diag)
        link = node.ros2(profile.ros2)
        hash_ = cfg.type_hash or rz.type_hash(types, cfg.message_type, humble=profile.ros2.distro == "humble")
        key = link.subscribe(cfg.topic, cfg.message_type, hash_, skin.on_sample, skin.on_dropped)
        log.info("skin from ROS 2: %s (%s, field %s) on %s, %d values onto %d pads", cfg.topic, cfg.message_type,
                 cfg.values_field, key, pmap.n_values, pmap.n_pads)
        try:
            while not node.stop.wait(min(0.5, cfg.timeout_s / 2)):
                skin.check_quiet("is the skin's node publishing, on [ros2] domain_id and router?")
        finally:
            log.info("%d skin samples, %d with problems, %d without rmw_zenoh's attachment", skin.count, skin.bad,
                     skin.dropped)
    return 0
