"""The gateway's ROS 1 skin source (``gateway.source = "ros1"``): a real skin's pressures from a ROS 1 topic.

A thin adapter: rospy subscribes to ``gateway.ros1.topic``; each message's
values field is mapped onto the robot's pads by
:func:`nwr.common.skinmap.map_values` (the same code ``nwr import`` uses)
and fed to the gateway's wiring (:meth:`GatewayWiring.on_sample`) by
:class:`~nwr.services.gateway.sources._feed.SkinFeed`, which the ROS 2 source
shares: the same baseline filter and ``skin/pressure`` as the simulated skin.

- the mapping's own gaps (unused device indices, pads no index feeds) are
  reported once at start (log and diagnostic ``ros1_mapping``);
- a message of the wrong length, with non-finite or out-of-range values:
  a diagnostic (``ros1_bad_message``, rate limited) and those pads invalid in
  that sample; nothing a message carries stops the gateway; every value out
  of range is the wrong units or scale (``ros1_units``, an error);
- no message for ``timeout_s``, or the ROS master unreachable: diagnostics
  ``ros1_no_messages`` / ``ros1_master_unreachable``. The gateway publishes
  nothing without messages: the skin goes stale and the bridge stops the arm
  (``bridge.skin_timeout_s``).

rospy is imported only here, only when the source is chosen: the project
installs and runs without ROS. On Debian/Ubuntu the packages are
``python3-rospy`` (with ``python3-rosgraph``, ``python3-genpy``) and, for a
type imported from ROS, its message package (e.g. ``python3-std-msgs``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import socket
import sys
import threading
from typing import TYPE_CHECKING, Annotated, Any
from urllib.parse import urlparse

import msgspec

from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.section import Section
from nwr.common.skinmap import PadMap, pad_map
from nwr.services.gateway.sources import KIND
from nwr.services.gateway.sources._feed import SkinFeed, gateway_node
from nwr.services.gateway.wiring import GatewayWiring

if TYPE_CHECKING:
    from nwr.common.robot import RobotDescription

log = logging.getLogger(__name__)

NAME = "ros1"

# The default pad mapping of gateway.ros1.pads: device index i -> the UR10e's pad i, the 11th index unused.
# A placeholder: check it on the lab's skin (docs/lab.md) and write the real one in the lab's profile.
ROS1_DEFAULT_PADS = ["shoulder_back", "shoulder_outer", "upper_arm_top", "upper_arm_bottom", "elbow_outer",
                     "forearm_top", "forearm_bottom", "wrist_1", "wrist_2", "wrist_3", ""]


class Settings(Section):
    """The ROS 1 skin source's settings: ``[gateway.ros1]``."""

    # The ROS 1 topic that carries the skin's pressures (AIRSKIN: ~30 Hz).
    topic: str = "/bullet_ros/airskin_status"
    # Its message type, package/Name as `rostopic type TOPIC` prints it.
    message_type: str = "airskin_msgs/AirskinStatus"
    # The type's definition (its .msg text), for a type this machine has no
    # ROS package of: generated at start. Empty: import the type from ROS
    # (e.g. std_msgs/Float32MultiArray with values_field = "data").
    definition: str = "float32[] pressures"
    # The message's field holding the pressures (an array of numbers).
    values_field: str = "pressures"
    # The pad mapping: entry i names the robot's pad that the message's value
    # i is; "" = a value no pad takes. A message must carry this many values.
    pads: list[str] = msgspec.field(default_factory=lambda: list(ROS1_DEFAULT_PADS))
    # A value v is the absolute pressure v * scale_hpa + offset_hpa, hPa
    # (the gateway takes each pad's change from its own baseline).
    scale_hpa: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 1.0
    offset_hpa: Annotated[float, msgspec.Meta(ge=-5000, le=5000)] = 0.0
    # No message for this long, or the ROS master unreachable: a diagnostic
    # (the skin is stale; the bridge stops the arm after bridge.skin_timeout_s).
    timeout_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 0.5


def settings_of(profile: Profile) -> Settings:
    """The profile's ``[gateway.ros1]``."""
    return KIND.settings(profile.gateway, NAME, Settings)


def check_settings(cfg: Settings, profile: Profile, desc: RobotDescription) -> None:
    """The pad mapping names the robot's pads, when this is the gateway's source (the simulated skin needs none)."""
    if profile.gateway.source == NAME:
        pad_map(cfg.pads, [pad.name for pad in desc.pads], scale_hpa=cfg.scale_hpa, offset_hpa=cfg.offset_hpa)

# Where Debian's and ROS's own Python packages live; appended (never prepended) to sys.path when rospy is not
# importable as is, so that this environment's own packages (numpy, ...) win.
ROS_PYTHON_DIRS = ("/usr/lib/python3/dist-packages", "/opt/ros/noetic/lib/python3/dist-packages")
NO_ROSPY = ("gateway.source = \"ros1\" needs rospy, which cannot be imported ({error}); on Debian/Ubuntu: "
            "apt install python3-rospy python3-rosgraph python3-genpy (and the message package of "
            "gateway.ros1.message_type if its definition is empty, e.g. python3-std-msgs), or source a ROS 1 "
            "installation's setup.bash")


def import_ros(module: str = "rospy") -> Any:
    """``module`` of ROS 1 (rospy, genpy, ...), from this environment or the system's; ConfigError if absent."""
    try:
        return importlib.import_module(module)
    except ImportError:
        pass
    for path in ROS_PYTHON_DIRS:
        if path not in sys.path:
            sys.path.append(path)
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ConfigError(NO_ROSPY.format(error=exc)) from exc


def message_class(cfg: Settings) -> Any:
    """The ROS message class of ``cfg.message_type``: generated from ``cfg.definition``, or imported from ROS."""
    package, _, name = cfg.message_type.partition("/")
    if not package or not name:
        raise ConfigError(f"gateway.ros1.message_type = {cfg.message_type!r}: write package/Name, e.g. "
                          "std_msgs/Float32MultiArray")
    if cfg.definition.strip():
        dynamic = import_ros("genpy.dynamic")
        try:
            return dynamic.generate_dynamic(cfg.message_type, cfg.definition)[cfg.message_type]
        except Exception as exc:  # genpy raises its own and assorted errors for a bad definition
            raise ConfigError(f"gateway.ros1.definition is no valid message definition of "
                              f"{cfg.message_type}: {exc}") from exc
    import_ros("genpy")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError) as exc:
        raise ConfigError(f"gateway.ros1.message_type = {cfg.message_type!r} cannot be imported from ROS ({exc}): "
                          "install its message package, or give its .msg text as gateway.ros1.definition") from exc


def check_field(cls: Any, cfg: Settings) -> None:
    slots = list(getattr(cls, "__slots__", ()))
    if cfg.values_field not in slots:
        raise ConfigError(f"gateway.ros1.values_field = {cfg.values_field!r} is no field of {cfg.message_type} "
                          f"(its fields: {slots})")


class Ros1Skin(SkinFeed):
    """The subscriber's callback and the watchdog's checks (messages coming, master reachable)."""

    source = NAME

    def __init__(self, cfg: Settings, pmap: PadMap, wiring: GatewayWiring, lock: threading.Lock,
                 diag: Any) -> None:
        super().__init__(cfg, pmap, wiring, lock, diag)
        self.master_down = False

    def check(self, master_uri: str) -> None:
        """The watchdog: messages coming, master reachable."""
        self.check_quiet("is the skin's node running, the topic and ROS_MASTER_URI right?")
        up = master_reachable(master_uri)
        if not up:
            self.master_down = True
            self.diag("error", "ros1_master_unreachable",
                      f"the ROS master at {master_uri} does not answer; skin messages already flowing may go on, "
                      "but a restarted skin node will not be found")
        elif self.master_down:
            self.master_down = False
            log.info("the ROS master at %s answers again", master_uri)


def master_reachable(uri: str, timeout_s: float = 0.5) -> bool:
    parsed = urlparse(uri)
    try:
        with socket.create_connection((parsed.hostname or "localhost", parsed.port or 11311), timeout=timeout_s):
            return True
    except OSError:
        return False


def init_node(rospy: Any, name: str) -> None:
    """``rospy.init_node``, keeping this process's logging as it was (rospy's configuration would send it all
    to a file under ~/.ros/log) and its signal handlers (the Node's)."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    try:
        rospy.init_node(name, anonymous=True, disable_signals=True)
    finally:
        for handler in root.handlers[:]:
            if handler not in handlers:
                root.removeHandler(handler)
        for handler in handlers:
            if handler not in root.handlers:
                root.addHandler(handler)
        root.setLevel(level)


def run(profile: Profile, args: argparse.Namespace) -> int:
    """The gateway with the ROS 1 source, until stopped."""
    from nwr.common.robot import load_description

    cfg = settings_of(profile)
    rospy = import_ros("rospy")
    rosgraph = import_ros("rosgraph")
    cls = message_class(cfg)
    check_field(cls, cfg)
    desc = load_description(profile.robot.description or None)
    pmap = pad_map(cfg.pads, [p.name for p in desc.pads], scale_hpa=cfg.scale_hpa, offset_hpa=cfg.offset_hpa)
    master_uri = rosgraph.get_master_uri()
    with gateway_node(profile, pmap, "ros1") as (node, wiring, lock):
        skin = Ros1Skin(cfg, pmap, wiring, lock, node.diag)

        def connect() -> None:  # rospy waits for its master to register: not on the main thread
            try:
                init_node(rospy, "nwr_gateway")
                rospy.Subscriber(cfg.topic, cls, skin.on_message, queue_size=10)
            except Exception as exc:  # rospy.ROSException, OSError, ...: the watchdog goes on reporting
                node.diag("error", "ros1_init_failed", f"could not join ROS 1 at {master_uri}: {exc!r}")
                return
            if not rospy.is_shutdown():
                log.info("skin from ROS 1: %s (%s, field %s) at master %s, %d values onto %d pads",
                         cfg.topic, cfg.message_type, cfg.values_field, master_uri, pmap.n_values, pmap.n_pads)

        threading.Thread(target=connect, name="ros1", daemon=True).start()
        period = min(0.5, cfg.timeout_s / 2)
        try:
            while not node.stop.wait(period):
                skin.check(master_uri)
        finally:
            rospy.signal_shutdown("nwr gateway stopping")  # also ends a wait for the master
            log.info("%d skin messages, %d with problems", skin.count, skin.bad)
    return 0
