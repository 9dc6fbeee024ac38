"""A process's side on a ROS 2 graph of rmw_zenoh nodes: its own Zenoh session, a client of ``rmw_zenohd``.

Two uses, one link per process (:meth:`nwr.common.node.Node.ros2`):

- **the services' ROS 2 topics** (``[ros2] enabled``): what a service
  publishes on a key of :data:`MIRRORED` is also published, after the
  pipeline's own put, as a ROS 2 message (:mod:`nwr.common.ros2_msgs`, CDR by
  ``rosbags``' type store) on the service's ROS 2 node: the bridge's
  ``robot/state`` as ``joint_states``, the gateway's ``skin/pressure`` as
  ``nwr/skin/absolute_hpa`` and ``nwr/skin/change_hpa``, the active planner's
  status as ``nwr/reflex``. No other process is involved.
- **the gateway's ``ros2`` skin source** subscribes to a ROS 2 topic
  (:meth:`Ros2Link.subscribe`).

What rmw_zenoh does and this does too (:mod:`nwr.common.rmw_zenoh`): the
data key ``<domain>/<topic>/<DDS type>/<type hash>``, the 33-byte attachment
on every sample (a subscriber drops a sample without one, and so does
:meth:`Ros2Link.subscribe`), the liveliness tokens of the node and of each
publisher and subscription (``ros2 node list``, ``ros2 topic list``).

The link's session is not the pipeline's: it connects to the configured
router only (``[ros2] router``, client mode, multicast scouting off), so
nothing on the ROS 2 graph reaches the pipeline's keys, and nothing of the
pipeline but these topics reaches the graph. A router that is not there is a
diagnostic (``ros2_router_unreachable``), tried again every
:data:`RETRY_S`; the service runs on meanwhile and its ROS 2 samples are
counted as dropped. A put never blocks the service (congestion control
DROP).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from nwr.common import keys
from nwr.common import messages as m
from nwr.common import rmw_zenoh as rz
from nwr.common.rmw_zenoh import Ros2Section
from nwr.common.ros2_msgs import (
    ARRAY_TYPE,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    MARKERS_TYPE,
    REFLEX,
    SKIN_ABSOLUTE,
    SKIN_CHANGE,
    Ros2Builder,
)

log = logging.getLogger(__name__)

# How often a link whose router did not answer tries again, s; how long one try waits for it, ms.
RETRY_S = 2.0
CONNECT_TIMEOUT_MS = 1000

Diag = Callable[..., None]  # Node.diag: (level, code, message, *, every_s)


def typestore(distro: str) -> Any:
    """``rosbags``' type store of the ROS 2 distribution ``distro`` ("jazzy", "humble")."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE if distro == "humble" else Stores.ROS2_JAZZY)


def node_name(service: str) -> str:
    """A service's ROS 2 node name (letters, digits and ``_``): ``nwr_gateway``, ``nwr_planner_cartesian``."""
    return "nwr_" + "".join(c if c.isalnum() else "_" for c in service)


def session_config(cfg: Ros2Section) -> zenoh.Config:
    """A client of the configured router, multicast scouting off, one try of :data:`CONNECT_TIMEOUT_MS`."""
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps(cfg.router))
    conf.insert_json5("connect/timeout_ms", json.dumps({"client": CONNECT_TIMEOUT_MS}))
    return conf


@dataclass
class Ros2Publisher:
    """One ROS 2 topic of the link's node: ``publish(message)`` serializes it and puts it with its attachment."""

    topic: str  # fully qualified
    msgtype: str
    type_hash: str
    key: str
    entity: int
    serialize: Callable[[Any, str], Any] = field(repr=False)
    token: str = ""  # set when the session is open (it names the session)
    gid: bytes = b""
    sent: int = 0
    dropped: int = 0  # while the router was not there
    _pub: Any = field(default=None, repr=False)

    def declare(self, session: zenoh.Session, node: rz.Node) -> list[Any]:
        self.token = node.endpoint_token(self.entity, "MP", self.topic, self.msgtype, self.type_hash)
        self.gid = rz.gid_of(self.token)
        token = session.liveliness().declare_token(self.token)
        self._pub = session.declare_publisher(self.key, priority=zenoh.Priority.DATA,
                                              congestion_control=zenoh.CongestionControl.DROP)
        return [token, self._pub]

    def publish(self, message: Any) -> None:
        pub = self._pub
        if pub is None:
            self.dropped += 1
            return
        payload = self.serialize(message, self.msgtype)
        self.sent += 1
        pub.put(bytes(payload), attachment=rz.Attachment(self.sent, time.time_ns(), self.gid).encode())


@dataclass(frozen=True)
class Ros2Sample:
    """A ROS 2 sample as the link received it: its key's DDS type and type hash, CDR bytes, attachment."""

    key: str
    dds_type: str
    type_hash: str
    payload: bytes
    attachment: rz.Attachment


@dataclass
class _Subscription:
    topic: str
    key: str
    entity: int
    token_type: str  # the type its token announces
    token_hash: str
    callback: Callable[[zenoh.Sample], None]

    def declare(self, session: zenoh.Session, node: rz.Node) -> list[Any]:
        token = node.endpoint_token(self.entity, "MS", self.topic, self.token_type, self.token_hash)
        return [session.liveliness().declare_token(token), session.declare_subscriber(self.key, self.callback)]


class Ros2Link:
    """One process's ROS 2 node (``node_name(service)`` in ``[ros2] namespace``) on a session of its own."""

    def __init__(self, cfg: Ros2Section, service: str, diag: Diag) -> None:
        self.cfg = cfg
        self.name = node_name(service)
        self.diag = diag
        self.types = typestore(cfg.distro)
        self.session: zenoh.Session | None = None
        self.node: rz.Node | None = None
        self._entities = 0
        self._endpoints: list[Ros2Publisher | _Subscription] = []
        self._declared: list[Any] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.no_attachment = 0  # samples dropped for want of rmw_zenoh's attachment
        if not self._connect():
            self._thread = threading.Thread(target=self._connect_loop, name="ros2", daemon=True)
            self._thread.start()

    # -- names -----------------------------------------------------------------------------------------------
    def fq(self, topic: str) -> str:
        """A topic relative to the namespace (``joint_states``, or ``/joint_states`` as the bag names it) as a
        fully qualified name."""
        return "/".join([self.cfg.namespace.rstrip("/"), topic.strip("/")])

    def type_hash(self, msgtype: str) -> str:
        return rz.type_hash(self.types, msgtype, humble=self.cfg.distro == "humble")

    # -- the session -----------------------------------------------------------------------------------------
    def _connect(self) -> bool:
        try:
            session = zenoh.open(session_config(self.cfg))
        except zenoh.ZError as exc:
            self.diag("error", "ros2_router_unreachable",
                      f"no rmw_zenoh router at {', '.join(self.cfg.router)} ({exc}): this process's ROS 2 side "
                      f"waits for it (tried every {RETRY_S:g} s); start it with `ros2 run rmw_zenoh_cpp rmw_zenohd` "
                      "or set [ros2] router", every_s=30.0)
            return False
        with self._lock:
            if self._stop.is_set():
                session.close()
                return True
            node = rz.Node(self.cfg.domain_id, str(session.info.zid()), 0, self.name, namespace=self.cfg.namespace)
            self._declared.append(session.liveliness().declare_token(node.token()))
            for endpoint in self._endpoints:
                self._declared.extend(endpoint.declare(session, node))
            self.session, self.node = session, node
        log.info("ROS 2 node %s on rmw_zenoh's router %s (domain %d)", self.fq(self.name),
                 ", ".join(self.cfg.router), self.cfg.domain_id)
        return True

    def _connect_loop(self) -> None:
        while not self._stop.wait(RETRY_S):
            if self._connect():
                return

    def _add(self, endpoint: Ros2Publisher | _Subscription) -> None:
        with self._lock:
            self._endpoints.append(endpoint)
            if self.session is not None and self.node is not None:
                self._declared.extend(endpoint.declare(self.session, self.node))

    def _entity(self) -> int:
        with self._lock:
            self._entities += 1
            return self._entities

    # -- publishing and subscribing --------------------------------------------------------------------------
    def publisher(self, topic: str, msgtype: str) -> Ros2Publisher:
        """A publisher of ``msgtype`` on ``topic`` (relative to the namespace), declared once the router is there."""
        fq, hash_ = self.fq(topic), self.type_hash(msgtype)
        pub = Ros2Publisher(fq, msgtype, hash_, rz.topic_keyexpr(self.cfg.domain_id, fq, msgtype, hash_),
                            self._entity(), self.types.serialize_cdr)
        self._add(pub)
        return pub

    def subscribe(self, topic: str, msgtype: str, type_hash: str, handler: Callable[[Ros2Sample], None],
                  on_dropped: Callable[[str, str], None]) -> str:
        """Call ``handler`` with every sample on ``topic`` (relative to the namespace), of any type and type hash
        (the handler checks them: a publisher of another type is a diagnostic, not silence); the subscription's
        token announces ``msgtype`` and ``type_hash``. A sample without rmw_zenoh's attachment is dropped, as
        rmw_zenoh drops it, and ``on_dropped(key, why)`` called. Returns the key expression subscribed to."""
        fq = self.fq(topic)
        head = rz.topic_keyexpr(self.cfg.domain_id, fq, msgtype, type_hash).rsplit("/", 2)[0]
        key = f"{head}/*/*"

        def on_sample(sample: zenoh.Sample) -> None:
            name = str(sample.key_expr)
            raw = sample.attachment.to_bytes() if sample.attachment is not None else b""
            try:
                attachment = rz.Attachment.decode(raw)
            except ValueError as exc:
                self.no_attachment += 1
                on_dropped(name, str(exc))
                return
            _, dds_type, hash_ = name.rsplit("/", 2)
            handler(Ros2Sample(name, dds_type, hash_, sample.payload.to_bytes(), attachment))

        self._add(_Subscription(fq, key, self._entity(), msgtype, type_hash, on_sample))
        return key

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            session, self.session = self.session, None
            self._declared.clear()
        if session is not None:
            session.close()
        publishers = [e for e in self._endpoints if isinstance(e, Ros2Publisher)]
        if publishers:
            log.info("ROS 2 node %s: %d samples published, %d dropped while its router was not there",
                     self.fq(self.name), sum(p.sent for p in publishers), sum(p.dropped for p in publishers))


# -- the services' ROS 2 topics ----------------------------------------------------------------------------------

def mirrored(relative: str) -> bool:
    """Whether a service's output on ``relative`` is also a ROS 2 topic (:class:`Mirror`)."""
    return relative in (keys.ROBOT_STATE, keys.SKIN_PRESSURE) or (
        relative.startswith("reflex/") and relative.endswith("/status"))


class Mirror:
    """A service's outputs of :func:`mirrored` keys, also published as ROS 2 topics on ``link``."""

    def __init__(self, link: Ros2Link, joints: list[str], base_frame: str) -> None:
        self.link = link
        self.base_frame = base_frame
        # Stamps are the machine's monotonic clock; ROS 2's are UTC.
        self.build = Ros2Builder(link.types, joints, time.time_ns() - time.monotonic_ns())
        self._joints: Ros2Publisher | None = None
        self._skin: tuple[Ros2Publisher, Ros2Publisher] | None = None
        self._reflex: Ros2Publisher | None = None
        self.failed = 0

    def _guarded(self, publish: Callable[[Any], None], also: Callable[[Any], None]) -> Callable[[Any], None]:
        """``publish``, then ``also``, whose failure is a diagnostic: the ROS 2 side never fails the service."""
        def both(message: Any) -> None:
            publish(message)
            try:
                also(message)
            except Exception as exc:  # a ROS 2 topic is a view: report and go on
                self.failed += 1
                self.link.diag("error", "ros2_publish_failed", f"a ROS 2 sample could not be published: {exc!r}",
                               every_s=10.0)
        return both

    def tee(self, relative: str, publish: Callable[[Any], None]) -> Callable[[Any], None]:
        """``publish`` followed by this key's ROS 2 topics (``publish`` itself for a key of no topic)."""
        if relative == keys.ROBOT_STATE:
            joints = self._joints = self.link.publisher(JOINT_STATES, JOINT_STATE_TYPE)

            def state(message: m.RobotState) -> None:
                joints.publish(self.build.joint_state(message))
            return self._guarded(publish, state)
        if relative == keys.SKIN_PRESSURE:
            absolute, change = self._skin = (self.link.publisher(SKIN_ABSOLUTE, ARRAY_TYPE),
                                             self.link.publisher(SKIN_CHANGE, ARRAY_TYPE))

            def skin(message: m.SkinPressure) -> None:
                a, c = self.build.skin(message)
                absolute.publish(a)
                change.publish(c)
            return self._guarded(publish, skin)
        if mirrored(relative):
            reflex = self._reflex = self.link.publisher(REFLEX, MARKERS_TYPE)

            def status(message: m.PlannerStatus) -> None:
                markers = self.build.reflex(message, self.base_frame)
                if markers is not None:
                    reflex.publish(markers)
            return self._guarded(publish, status)
        return publish


def mirror(link: Ros2Link, profile: Any) -> Mirror:
    """The mirror of a service of ``profile``'s robot on ``link``."""
    from nwr.common.robot import load_description

    desc = load_description(profile.robot.description or None)
    return Mirror(link, list(desc.joints), desc.base_frame)
