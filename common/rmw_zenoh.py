"""What a ROS 2 node on rmw_zenoh (ROS 2's Zenoh middleware, ``rmw_zenoh_cpp``) puts on Zenoh, as pure functions.

The names and bytes the live ROS 2 side (:mod:`nwr.common.ros2`: the services' ROS 2 topics and the gateway's
``ros2`` skin source) puts on Zenoh, and its profile section ``[ros2]`` (:class:`Ros2Section`). No Zenoh import
here; the message bytes themselves are CDR, which ``rosbags`` serializes (``typestore.serialize_cdr``).

What rmw_zenoh_cpp does (its ``liveliness_utils.cpp`` and ``attachment_helpers.cpp``, 1.x for Jazzy and later):

- **Data key**: ``<domain id>/<topic without its leading and trailing slash>/<DDS type name>/<type hash>``,
  e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74...``: the topic keeps its inner slashes; the DDS
  type name of ``pkg/msg/Name`` is ``pkg::msg::dds_::Name_``; the type hash is the type's REP-2016 hash
  (``RIHS01_`` and 64 hex digits; Humble, which has none, sends ``TypeHashNotSupported``).
- **Attachment** of every sample (a subscriber drops a sample without one): Zenoh's own serialization
  (``zenoh::ext::Serializer``) of the publisher's sequence number (int64), the source timestamp (int64, ns
  since the epoch) and its 16-byte GID: little-endian int64, int64, then the GID as a byte sequence (its
  length as a LEB128 varint, 16, then the bytes): 33 bytes.
- **Liveliness tokens** for the graph (``ros2 node list``, ``ros2 topic list``): ``@ros2_lv/<domain>/<zenoh
  session id>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node name>`` for a node (kind ``NN``, its
  entity id equal to its node id), and for a publisher (``MP``) or subscription (``MS``) the same followed by
  ``/<topic>/<DDS type name>/<type hash>/<QoS>``. Every name is *mangled*: each ``/`` becomes ``%`` (the
  empty namespace ``/`` is ``%``); the QoS part lists, separated by ``:`` and ``,``, only what differs from
  the default profile (:func:`qos_keyexpr`).
- A publisher's GID is, in rmw_zenoh_cpp, the XXH3-128 hash of its liveliness token; subscribers only
  carry it along (``rmw_message_info_t.publisher_gid``), so :func:`gid_of` uses BLAKE2b-128 of the token
  instead (no xxhash dependency): unique per publisher, but not the value rmw_zenoh_cpp would compute.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import msgspec

from nwr.common.section import Section

ADMIN_SPACE = "@ros2_lv"
TYPE_HASH_NOT_SUPPORTED = "TypeHashNotSupported"  # what Humble's rmw_zenoh sends: it has no type hashes
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE since Iron
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
_ATTACHMENT = struct.Struct(f"<qqB{GID_SIZE}s")

# rmw's QoS enums (rmw/types.h) and the profile rmw_zenoh_cpp's QoS part is relative to (rmw_qos_profile_default).
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2


@dataclass(frozen=True)
class Qos:
    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10
    deadline: tuple[int, int] = (0, 0)  # s, ns
    lifespan: tuple[int, int] = (0, 0)
    liveliness: int = 0  # SYSTEM_DEFAULT
    liveliness_lease: tuple[int, int] = (0, 0)


DEFAULT_QOS = Qos()


class Ros2Section(Section):
    """``[ros2]``: the pipeline's side on a ROS 2 graph of rmw_zenoh nodes (docs/lab.md, "ROS 2 live topics")."""

    # Publish the robot's joint states, the skin and the reflex as ROS 2
    # topics (as `nwr export --ros2` names them), each from the service that
    # makes it (bridge, gateway, active planner): rmw_zenoh's keys, CDR, the
    # attachment on every sample and the graph's liveliness tokens.
    enabled: bool = False
    # rmw_zenoh's router (`ros2 run rmw_zenoh_cpp rmw_zenohd`, port 7447),
    # which each process's ROS 2 side joins as a client, on a Zenoh session of
    # its own (the ROS 2 graph never reaches the pipeline's keys). Beyond
    # loopback only with NWR_INSECURE=1: rmw_zenohd has no TLS here.
    router: list[str] = msgspec.field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    # ROS_DOMAIN_ID of the lab's ROS 2 graph.
    domain_id: Annotated[int, msgspec.Meta(ge=0, le=232)] = 0
    # The ROS 2 nodes' namespace: the topics are joint_states, nwr/skin/...
    # in it ("/": /joint_states, as robot_state_publisher reads it).
    namespace: Annotated[str, msgspec.Meta(pattern=r"^/([A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*)?$")] = "/"
    # The ROS 2 distribution's message definitions and type hashes: "jazzy"
    # (and later: RIHS01 hashes in the keys) or "humble" (no type hashes).
    distro: Literal["jazzy", "humble"] = "jazzy"


def dds_type_name(msgtype: str) -> str:
    """``pkg/msg/Name`` (or ``pkg/Name``) -> ``pkg::msg::dds_::Name_``, the type name in keys and tokens."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"{msgtype!r} is no ROS 2 type name (pkg/msg/Name)")
    package, kind, name = parts
    return f"{package}::{kind}::dds_::{name}_"


def type_hash(typestore: Any, msgtype: str, *, humble: bool = False) -> str:
    """The type's RIHS01 hash as rmw_zenoh puts it in keys (computed by ``rosbags``), or Humble's placeholder."""
    return TYPE_HASH_NOT_SUPPORTED if humble else str(typestore.hash_rihs01(msgtype))


def topic_keyexpr(domain_id: int, topic: str, msgtype: str, hash_: str) -> str:
    """The Zenoh key of a topic's samples."""
    if not 0 <= domain_id <= 232:
        raise ValueError(f"ROS_DOMAIN_ID {domain_id} is outside 0..232")
    name = topic.strip("/") if topic not in ("", "/") else ""
    if not name or "//" in name or any(c in name for c in "*$?#"):
        raise ValueError(f"{topic!r} is no ROS 2 topic name")
    return f"{domain_id}/{name}/{dds_type_name(msgtype)}/{hash_}"


def mangle(name: str) -> str:
    return name.replace("/", "%")


def demangle(name: str) -> str:
    return name.replace("%", "/")


def _part(value: int, default: int) -> str:
    return "" if value == default else str(value)


def qos_keyexpr(qos: Qos = DEFAULT_QOS) -> str:
    """The QoS part of a publisher's or subscription's token: only what differs from the default profile."""
    d = DEFAULT_QOS
    return ":".join([
        _part(qos.reliability, d.reliability),
        _part(qos.durability, d.durability),
        f"{_part(qos.history, d.history)},{_part(qos.depth, d.depth)}",
        f"{_part(qos.deadline[0], d.deadline[0])},{_part(qos.deadline[1], d.deadline[1])}",
        f"{_part(qos.lifespan[0], d.lifespan[0])},{_part(qos.lifespan[1], d.lifespan[1])}",
        f"{_part(qos.liveliness, d.liveliness)},{_part(qos.liveliness_lease[0], d.liveliness_lease[0])},"
        f"{_part(qos.liveliness_lease[1], d.liveliness_lease[1])}",
    ])


@dataclass(frozen=True)
class Node:
    """A ROS 2 node as the graph sees it."""

    domain_id: int
    zid: str  # the Zenoh session's id, as Zenoh prints it (hex)
    node_id: int
    name: str
    namespace: str = "/"
    enclave: str = "/"

    def token(self) -> str:
        """The node's liveliness token (``NN``)."""
        return self._prefix(self.node_id, "NN")

    def _prefix(self, entity_id: int, kind: str) -> str:
        if not self.name or "/" in self.name:
            raise ValueError(f"{self.name!r} is no ROS 2 node name")
        return "/".join([ADMIN_SPACE, str(self.domain_id), self.zid, str(self.node_id), str(entity_id), kind,
                         mangle(self.enclave), mangle(self.namespace), mangle(self.name)])

    def endpoint_token(self, entity_id: int, kind: Literal["MP", "MS"], topic: str, msgtype: str, hash_: str,
                       qos: Qos = DEFAULT_QOS) -> str:
        """A publisher's (``MP``) or subscription's (``MS``) liveliness token."""
        fq = topic if topic.startswith("/") else f"{self.namespace.rstrip('/')}/{topic}"
        return "/".join([self._prefix(entity_id, kind), mangle(fq), mangle(dds_type_name(msgtype)), mangle(hash_),
                         qos_keyexpr(qos)])


def gid_of(token: str) -> bytes:
    """A publisher's 16-byte GID, from its liveliness token (see the module's note on XXH3)."""
    return hashlib.blake2b(token.encode(), digest_size=GID_SIZE).digest()


@dataclass(frozen=True)
class Attachment:
    """The 33 bytes rmw_zenoh attaches to every sample."""

    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"a GID is {GID_SIZE} bytes, not {len(self.gid)}")
        return _ATTACHMENT.pack(self.sequence_number, self.source_timestamp_ns, GID_SIZE, self.gid)

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        """ValueError for anything but rmw_zenoh's 33 bytes (a sample without it is dropped, as rmw_zenoh does)."""
        if len(data) != ATTACHMENT_SIZE:
            raise ValueError(f"an rmw_zenoh attachment is {ATTACHMENT_SIZE} bytes, not {len(data)}")
        seq, stamp, size, gid = _ATTACHMENT.unpack(data)
        if size != GID_SIZE:
            raise ValueError(f"the attachment's GID is {size} bytes long, not {GID_SIZE}")
        return cls(seq, stamp, gid)
