"""The key-expression registry: every key, its message type and its QoS.

Everything lives under ``nwr/<robot>/`` so that two arms can share one LAN.

===========================  =====================================  ==========  =========  =======
key (under nwr/<robot>/)     message                                priority    express    on congestion
===========================  =====================================  ==========  =========  =======
skin/pressure                SkinPressure                           real-time   yes        block
skin/touch                   SkinTouch                              data        no         block
skin/pain                    SkinPain                               real-time   yes        block
world/skin                   WorldSkin                              real-time   yes        block
world/contacts               WorldContacts                          data        no         block
robot/command/<name>         PositionCommand | VelocityCommand      real-time   yes        block
robot/state                  RobotState                             interactive no         drop
reflex/<name>/status         PlannerStatus                          data        no         drop
reflex/<name>/decision       PlannerDecision                        data        no         block
control/active               SwitchRequest                          interactive yes        block
control/safety               SafetyModeRequest                      interactive yes        block
diag/<service>               Diagnostic                             data-low    no         drop
journal/<service>            Journal                                data        no         block
alive/<service>              (liveliness token, no payload)
===========================  =====================================  ==========  =========  =======

Each planner commands on its own key, ``robot/command/<name>``: the
router's access control lets only the certificate ``planner:<name>`` put
there, and the bridge obeys a command only if its owner field is the name in
the key and the active planner's. A stolen standby planner's key therefore
cannot pose as the active planner.

The reflex path (skin -> pain -> command) travels at Zenoh's real-time
priority with ``express`` (no batching) and never drops; telemetry may drop
under congestion rather than slow the reflex path down. A planner's
decisions (one per pain message, published after any command it caused)
are batched (not express) at data priority but never dropped: they are the
measurement of the sample latency (``nwr bench``), and a dropped one would
bias it. The simulated skin's touch ground truth (``skin/touch``, one
message per touch) is not on the reflex path and is batched the same way,
never dropped: a re-simulation of the session needs every touch.

A physics world (the bridge's ``physics`` backend) puts its skin samples on
``world/skin``, on the reflex path like the pressure they become (the
gateway's ``physics`` source reads them), and its body parts' contact
figures on ``world/contacts`` (batched, never dropped: the per-touch
force figures come from them).
"""

from __future__ import annotations

import fnmatch
import re
import time
from dataclasses import dataclass
from typing import Any

import msgspec

from nwr.common import messages as m
from nwr.common.errors import DecodeError

PREFIX_ROOT = "nwr"
DEFAULT_ROBOT = "ur10e"


@dataclass(frozen=True)
class Topic:
    """One key of the registry: a pattern relative to the robot prefix."""

    pattern: str  # may contain one '*' chunk, e.g. "reflex/*/status"
    type: Any
    priority: str  # a zenoh.Priority's name (the transport maps it: this module does not import Zenoh)
    express: bool
    drop: bool
    doc: str
    # Who puts on the key: the pipeline's services (the graph in
    # nwr.services.pipeline.graph), "operator" (nwr switch, nwr study),
    # "replay" (nwr replay), "status" (nwr status); ANY_SERVICE for a key
    # every service has its own instance of. Who subscribes to it, besides
    # the services with a wiring (gateway, gain, planner, bridge), whose
    # declared inputs say what they read (nwr.services.wiring.Input): the
    # recorder, the view and the tools.
    producers: tuple[str, ...]
    consumers: tuple[str, ...]


ANY_SERVICE = "*"


TOPICS: tuple[Topic, ...] = (
    Topic("skin/pressure", m.SkinPressure, "REAL_TIME", True, False,
          "per-pad absolute pressure, change from baseline, contact flags",
          ("gateway", "replay"), ("recorder", "view")),
    Topic("skin/touch", m.SkinTouch, "DATA", False, False,
          "simulated skin: one touch's ground truth (pad, profile, contact point), when it starts",
          ("gateway",), ("recorder",)),
    Topic("world/skin", m.WorldSkin, "REAL_TIME", True, False,
          "a physics world's skin samples (absolute hPa per pad), from the bridge's physics backend",
          ("bridge",), ("recorder",)),
    Topic("world/contacts", m.WorldContacts, "DATA", False, False,
          "a physics world's body parts: contact force, pressure, energy, how far each was pushed back",
          ("bridge",), ("recorder",)),
    Topic("skin/pain", m.SkinPain, "REAL_TIME", True, False,
          "per-pad gain and pain level, strongest contact",
          ("gain",), ("recorder", "view", "status")),
    Topic("robot/command/*", m.PositionCommand | m.VelocityCommand, "REAL_TIME", True, False,
          "a planner's joint position or velocity target, on its own key",
          ("planner",), ("recorder",)),
    Topic("robot/state", m.RobotState, "INTERACTIVE_HIGH", False, True,
          "joint positions and velocities, status, command owner, reflex onsets",
          ("bridge",), ("recorder", "view", "operator", "status")),
    Topic("reflex/*/status", m.PlannerStatus, "DATA", False, True,
          "a planner's state machine: mode, strategy, saved pose, reflex",
          ("planner",), ("recorder", "view", "status")),
    Topic("reflex/*/decision", m.PlannerDecision, "DATA", False, False,
          "when a planner acted on each pain message (the sample latency's end)",
          ("planner",), ("recorder",)),
    Topic("control/active", m.SwitchRequest, "INTERACTIVE_HIGH", True, False,
          "which planner should be active (the bridge carries the switch out)",
          ("operator",), ("recorder",)),
    Topic("control/safety", m.SafetyModeRequest, "INTERACTIVE_HIGH", True, False,
          "the bridge's Cartesian limits: the normal or the reduced set (the operator's role only)",
          ("operator",), ("recorder",)),
    Topic("diag/*", m.Diagnostic, "DATA_LOW", False, True,
          "warnings and errors with a code and a readable message",
          (ANY_SERVICE,), ("recorder",)),
    Topic("journal/*", m.Journal, "DATA", False, False,
          "what a service received, in order, with its clock readings: enough to re-run it exactly (nwr verify)",
          ("gateway", "gain", "planner", "bridge"), ("recorder",)),
)

SKIN_PRESSURE = "skin/pressure"
SKIN_TOUCH = "skin/touch"
SKIN_PAIN = "skin/pain"
WORLD_SKIN = "world/skin"
WORLD_CONTACTS = "world/contacts"
ROBOT_COMMANDS = "robot/command/*"  # every planner's commands (what the bridge and the recorder take)
ROBOT_STATE = "robot/state"
CONTROL_ACTIVE = "control/active"
CONTROL_SAFETY = "control/safety"


def prefix(robot: str) -> str:
    return f"{PREFIX_ROOT}/{robot}"


def key(robot: str, relative: str) -> str:
    """Full key expression of a relative key, e.g. ``key("ur10e", "skin/pain")``."""
    return f"{prefix(robot)}/{relative}"


def robot_command(name: str) -> str:
    """The key a planner commands on: ``robot/command/<name>``."""
    return f"robot/command/{name}"


def command_publisher(relative: str) -> str | None:
    """The planner a command key belongs to (``robot/command/cartesian`` -> ``cartesian``), else None."""
    head, sep, name = relative.rpartition("/")
    return name if sep and head == "robot/command" and name else None


def is_command(relative: str) -> bool:
    return command_publisher(relative) is not None


def planner_status(name: str) -> str:
    return f"reflex/{name}/status"


def planner_decision(name: str) -> str:
    return f"reflex/{name}/decision"


def diag(service: str) -> str:
    return f"diag/{service}"


# Each planner instance is its own service, ``planner-<name>``: its liveliness
# token, diagnostics and journal carry that name (the bridge watches the tokens).
PLANNER_SERVICE_PREFIX = "planner-"


def planner_service(name: str) -> str:
    return f"{PLANNER_SERVICE_PREFIX}{name}"


def journal(service: str) -> str:
    return f"journal/{service}"


def alive(service: str) -> str:
    return f"alive/{service}"


# ------------------------------------------------------------------------------ who owns the robot's keys

_CHUNK = re.compile(r"[^A-Za-z0-9_.-]")
NO_INSTANCE = "-"  # a process started alone (nwr run), not by a launcher


def key_chunk(text: str) -> str:
    """``text`` as one chunk of a key (letters, digits, '_', '.', '-'; anything else '_'; empty: '-')."""
    return _CHUNK.sub("_", text) or NO_INSTANCE


def owner(service: str, instance: str, host: str, pid: int, since_s: int) -> str:
    """The liveliness token a pipeline's service holds while it drives the robot's keys:
    ``owner/<service>/<instance>/<host>/<pid>/<since>`` (``since``: Unix time, s)."""
    return f"owner/{key_chunk(service)}/{key_chunk(instance)}/{key_chunk(host)}/{int(pid)}/{int(since_s)}"


@dataclass(frozen=True)
class Owner:
    """A live service of some pipeline instance, from its owner token."""

    service: str
    instance: str  # NO_INSTANCE: started alone
    host: str
    pid: int
    since_s: int

    def describe(self) -> str:
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.since_s))
        run = "started alone" if self.instance == NO_INSTANCE else f"pipeline {self.instance}"
        return f"{self.service} ({run}, host {self.host}, pid {self.pid}, since {since})"


def parse_owner(relative: str) -> Owner | None:
    """The owner a token's relative key names; None for anything else."""
    parts = relative.split("/")
    if len(parts) != 6 or parts[0] != "owner" or not (parts[4].isdigit() and parts[5].isdigit()):
        return None
    return Owner(parts[1], parts[2], parts[3], int(parts[4]), int(parts[5]))


def matches(relative: str, pattern: str) -> bool:
    """Whether a relative key is one of a pattern's (a '*' stands for one chunk)."""
    return fnmatch.fnmatchcase(relative, pattern) and relative.count("/") == pattern.count("/")


def topic_for(relative: str) -> Topic:
    """The registry entry matching a relative key; DecodeError if none does."""
    for topic in TOPICS:
        if matches(relative, topic.pattern):
            return topic
    raise DecodeError(f"key {relative!r} is not in the key registry (known: {[t.pattern for t in TOPICS]})")


def relative_key(robot: str, full_key: str) -> str:
    head = prefix(robot) + "/"
    if not full_key.startswith(head):
        raise DecodeError(f"key {full_key!r} is not under the robot prefix {head!r}")
    return full_key[len(head):]


class Codec:
    """Encoder and strict typed decoder for one key, built once at start-up."""

    def __init__(self, topic: Topic) -> None:
        self.topic = topic
        self._encoder = msgspec.msgpack.Encoder()
        self._decoder = msgspec.msgpack.Decoder(topic.type)

    def encode(self, message: Any) -> bytes:
        return self._encoder.encode(message)

    def decode(self, payload: bytes | bytearray | memoryview) -> Any:
        try:
            return self._decoder.decode(payload)
        except (msgspec.ValidationError, msgspec.DecodeError, UnicodeDecodeError) as exc:
            reason = str(exc)
            if str(m.FINITE_BOUND) in reason:
                reason = f"a number is NaN, infinite or beyond +-{m.FINITE_BOUND:g} ({reason})"
            raise DecodeError(f"{self.topic.pattern}: {reason}") from exc


_CODECS: dict[str, Codec] = {}


def codec(relative: str) -> Codec:
    """The codec of a relative key (shared per registry entry)."""
    topic = topic_for(relative)
    found = _CODECS.get(topic.pattern)
    if found is None:
        found = _CODECS[topic.pattern] = Codec(topic)
    return found
