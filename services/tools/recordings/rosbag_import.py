"""``nwr import BAG OUT.mcap``: a ROS 1 or ROS 2 bag of a touch session -> a project recording.

BAG is a ROS 1 bag (``.bag``) or a ROS 2 bag: a rosbag2 directory (its
``metadata.yaml`` and storage files) or one of its storage files alone
(``.mcap`` or SQLite ``.db3``). Both go through the same code: only the
reader, the type store (ROS 1 Noetic's or ROS 2's) and the deserializer
(ROS 1 serialization or CDR) differ.

The bag's skin topic (``gateway.ros1``: AIRSKIN's ``/bullet_ros/airskin_status``,
``float32[] pressures``) becomes ``skin/pressure``: each message mapped onto
the robot's pads by the same code as the live ROS 1 source
(:func:`nwr.common.skinmap.map_values`, ``gateway.ros1.pads``) and through the
gateway's baseline filter (:class:`nwr.services.gateway.core.Gateway`), as the
live gateway would have published it. ``sensor_msgs/JointState`` on the joint
topic becomes ``robot/state``, its joints put in the robot description's order
by name. Every message keeps the bag's time stamp (its record time, ns since
the epoch) as stamp and log time. The session metadata says where it came from
(``label.imported_from``, the topics, the mapping).

Unusable input ends the import with a non-zero exit and one line: no such bag,
a file that is no bag or a damaged one (a ROS 1 bag's index, headers or
chunks, a ROS 2 bag's metadata, MCAP records or SQLite pages unreadable: bit
flips, a cut), no skin topic, a skin topic of a type the bag does not define
and the type store does not know, a skin topic whose type has no
``values_field``, a joint topic that is not JointState. A message's own
problems (wrong length, non-finite or out-of-range values, a joint state
missing a joint, or with a position or velocity that is not finite or beyond
the robot description's limits, a message whose bytes do not deserialize as
its type) are counted and reported at the end (for
joint states: by topic, with the joint and the value of the first); a bad
value makes its pad invalid in that sample, such a joint state is skipped.
The exit code says what was lost: 0, every message imported (a bad value
only marks its pad invalid in its sample, as the live gateway does); 3,
imported, but joint states were left out (the lines above say which, how
many, the first): the recording lacks part of the arm's motion; 1, nothing
to import; 2, unusable input.

The recording replays like any other (``nwr replay --fast --reflex NAME``; a
real skin's recording has no touch ground truth: open loop only) and compares
with ``nwr compare``. ``rosbags`` (pure Python, no ROS needed) is imported only
when the command runs. ``nwr export --ros2`` (:mod:`.rosbag_export`) writes a
recording back as a ROS 2 bag.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import math
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.recordings import McapRecorder, new_file, session_metadata
from nwr.common.robot import RobotDescription, load_description
from nwr.common.ros2_msgs import field_names, numbers_field
from nwr.common.skinmap import PadMap, map_values, pad_map
from nwr.services.gateway.sources.ros1 import settings_of
from nwr.services.profile import profile_for

log = logging.getLogger(__name__)

JOINT_STATE = "sensor_msgs/msg/JointState"
BAG_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"


def rosbags_type(name: str) -> str:
    """``pkg/Name`` (ROS 1's spelling) -> ``pkg/msg/Name`` (rosbags' and ROS 2's)."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def ros1_type(name: str) -> str:
    parts = name.split("/")
    return f"{parts[0]}/{parts[2]}" if len(parts) == 3 and parts[1] == "msg" else name


@dataclass(frozen=True)
class BagKind:
    """What differs between a ROS 1 and a ROS 2 bag: its name in messages, the gateway source it stands for,
    how it spells types, and how its records deserialize."""

    name: str  # "ROS 1" / "ROS 2"
    source: str  # SkinPressure.source of its samples
    ros2: bool

    def type_name(self, msgtype: str) -> str:
        """``msgtype`` (rosbags' ``pkg/msg/Name``) as this ROS spells it."""
        return msgtype if self.ros2 else ros1_type(msgtype)

    def deserialize(self, typestore: Any, raw: bytes, msgtype: str) -> Any:
        if self.ros2:
            return typestore.deserialize_cdr(raw, msgtype)
        return typestore.deserialize_ros1(raw, msgtype)


ROS1 = BagKind("ROS 1", "ros1", ros2=False)
ROS2 = BagKind("ROS 2", "ros2", ros2=True)


def _head(path: Path, n: int) -> bytes:
    try:
        with path.open("rb") as head:
            return head.read(n)
    except OSError as exc:
        raise ConfigError(f"{path} cannot be read: {exc.strerror or exc}") from exc


def bag_kind(bag: Path) -> BagKind:
    """ROS 1 or ROS 2, from the path and the file's first bytes; ConfigError (one line) for anything else."""
    if bag.is_dir():
        if not (bag / "metadata.yaml").is_file():
            raise ConfigError(f"{bag} is a directory without metadata.yaml: no ROS 2 bag (give the rosbag2 "
                              "directory, or its .mcap or .db3 file)")
        return ROS2
    if not bag.is_file():
        raise ConfigError(f"{bag}: no such bag file")
    if bag.suffix in (".mcap", ".db3"):
        magic = MCAP_MAGIC if bag.suffix == ".mcap" else SQLITE_MAGIC
        if _head(bag, len(magic)) != magic:
            what = "an MCAP file" if bag.suffix == ".mcap" else "an SQLite database"
            raise ConfigError(f"{bag} is no ROS 2 bag: it is not {what} (it does not begin with {magic!r})")
        return ROS2
    magic = _head(bag, len(BAG_MAGIC))
    if magic == BAG_MAGIC:
        return ROS1
    raise ConfigError(f"{bag} is no ROS 1 bag: it does not begin with {BAG_MAGIC.decode().strip()!r} (a ROS 2 "
                      "bag is a rosbag2 directory or its .mcap or .db3 file; a compressed copy, another file?)")


@dataclass
class ImportReport:
    skin: int = 0
    states: int = 0
    skin_problems: Counter[str] = field(default_factory=Counter)  # messages with each kind of problem
    state_problems: Counter[str] = field(default_factory=Counter)
    state_examples: dict[str, str] = field(default_factory=dict)  # the first message of each kind of problem
    notes: list[str] = field(default_factory=list)  # the mapping's gaps, a missing joint topic
    first_ns: int = 0
    last_ns: int = 0

    def format(self, out: Path) -> str:
        span = (self.last_ns - self.first_ns) / 1e9 if self.skin else 0.0
        lines = [f"imported {self.skin} skin samples and {self.states} robot states ({span:.1f} s) into {out}"]
        lines += [f"  note: {n}" for n in self.notes]
        for kind, count in sorted(self.skin_problems.items()):
            lines.append(f"  {count} skin messages with a problem ({kind}): their bad pads are invalid")
        for kind, count in sorted(self.state_problems.items()):
            example = self.state_examples.get(kind)
            lines.append(f"  {count} joint states skipped ({kind})" + (f", the first {example}" if example else ""))
        return "\n".join(lines)


def _definition_types(connection: Any) -> dict[str, Any]:
    """The types a connection's own definition gives: ROS 1's or ROS 2's .msg text (with its dependencies),
    or ROS 2's IDL."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.typesys import get_types_from_idl, get_types_from_msg

    data = connection.msgdef.data
    if not data.strip():  # rosbags would parse it as a type without fields
        raise ValueError("the bag has no definition of it")
    if connection.msgdef.format != MessageDefinitionFormat.IDL:
        return dict(get_types_from_msg(data, connection.msgtype))
    types: dict[str, Any] = {}
    sep = "=" * 80 + "\n"
    for part in data.split(sep)[1:] if data.startswith(f"{sep}IDL: ") else [data]:
        types.update(get_types_from_idl(part.split("\n", 1)[1] if part.startswith("IDL: ") else part))
    return types


def _register(typestore: Any, connection: Any, fallback: tuple[str, str] | None, kind: BagKind = ROS1) -> None:
    """The connection's type in ``typestore``: from the bag's own definition, else ``fallback`` (name, .msg text)."""
    from rosbags.typesys import get_types_from_msg

    if connection.msgtype in typestore.fielddefs:
        return
    try:
        types = _definition_types(connection)
        if connection.msgtype not in types:
            raise ValueError("its definition does not define it")
        typestore.register(types)
        return
    except Exception as exc:  # rosbags raises assorted errors for a definition it cannot parse
        if fallback is None or rosbags_type(fallback[0]) != connection.msgtype or not fallback[1].strip():
            raise ConfigError(f"the bag's definition of {kind.type_name(connection.msgtype)} on {connection.topic} "
                              f"cannot be read ({_first_line(exc)}); the type is unknown: give its .msg text "
                              "(gateway.ros1.definition) and --message-type") from exc
    typestore.register(get_types_from_msg(fallback[1], connection.msgtype))


def _first_line(exc: BaseException) -> str:
    """An exception's message in one line of at most 200 characters (rosbags' parser errors span several)."""
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else type(exc).__name__


def _damaged(bag: Path, exc: BaseException, kind: BagKind = ROS1) -> ConfigError:
    """A one-line error for a bag the reader cannot read (rosbags raises assorted errors for damaged bytes)."""
    return ConfigError(f"{bag} is no readable {kind.name} bag, or a damaged one ({type(exc).__name__}: "
                       f"{_first_line(exc)}); check the file, or re-record it")


def _records(reader: Any, bag: Path, connections: list[Any], kind: BagKind = ROS1
             ) -> Iterator[tuple[Any, int, bytes]]:
    """The reader's messages on ``connections``; a damaged record ends the import with one line (ConfigError)."""
    try:
        records = iter(reader.messages(connections=connections))
    except Exception as exc:  # noqa: BLE001  the reader's errors on damaged bytes are of many types
        raise _damaged(bag, exc, kind) from exc
    while True:
        try:
            item = next(records)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001
            raise _damaged(bag, exc, kind) from exc
        yield item


def _open_reader(bag: Path, kind: BagKind) -> tuple[Any, Any]:
    """An open rosbags reader of ``bag`` and the type store its types start from; ConfigError (one line)."""
    from rosbags.rosbag1 import Reader as Reader1
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import Reader as Reader2
    from rosbags.rosbag2 import ReaderError as ReaderError2
    from rosbags.typesys import Stores, get_typestore

    store = Stores.ROS2_HUMBLE if kind.ros2 else Stores.ROS1_NOETIC
    try:
        reader = Reader2(bag) if kind.ros2 else Reader1(bag)
        reader.open()
    except (ReaderError1, ReaderError2, OSError) as exc:
        raise ConfigError(f"{bag} is no readable {kind.name} bag: {_first_line(exc)}") from exc
    except Exception as exc:  # noqa: BLE001  garbage bytes: the reader fails in assorted ways
        raise _damaged(bag, exc, kind) from exc
    return reader, get_typestore(store)


def import_bag(bag: Path, out: Path, profile: Profile, *, topic: str, joint_topic: str, pmap: PadMap,
               message_type: str, definition: str, values_field: str) -> ImportReport:
    """Convert ``bag`` into the recording ``out``; ConfigError (one line) for input that cannot be used."""
    from nwr.services.gateway.core import Gateway

    kind = bag_kind(bag)
    desc = load_description(profile.robot.description or None)
    report = ImportReport(notes=pmap.describe())
    reader, typestore = _open_reader(bag, kind)
    try:
        by_topic: dict[str, list[Any]] = {}
        for connection in reader.connections:
            by_topic.setdefault(connection.topic, []).append(connection)
        topics = sorted(f"{t} ({kind.type_name(c[0].msgtype)})" for t, c in by_topic.items())
        skin_connections = by_topic.get(topic, [])
        if not skin_connections:
            raise ConfigError(f"{bag} has no skin topic {topic}: its topics are {topics or 'none'}; name the skin's "
                              "with --topic")
        for connection in skin_connections:
            _register(typestore, connection, (message_type, definition), kind)
            fields = field_names(typestore, connection.msgtype)
            if values_field not in fields:
                raise ConfigError(f"{topic} in {bag} is of type {kind.type_name(connection.msgtype)}, which has no "
                                  f"field {values_field!r} (its fields: {fields}); give the type's field of pressures "
                                  "(gateway.ros1.values_field)")
            if (shape := numbers_field(typestore, connection.msgtype, values_field)) is not None:
                raise ConfigError(f"{topic} in {bag} is of type {kind.type_name(connection.msgtype)}, whose field "
                                  f"{values_field!r} is {shape}, not an array of numbers; give the type's field of "
                                  "pressures (gateway.ros1.values_field)")
            if connection.msgtype != rosbags_type(message_type):
                report.notes.append(f"{topic} is of type {kind.type_name(connection.msgtype)}, not {message_type}: "
                                    f"its field {values_field!r} is taken as the pressures")
        state_connections = by_topic.get(joint_topic, [])
        for connection in state_connections:
            if connection.msgtype != JOINT_STATE:
                raise ConfigError(f"{joint_topic} in {bag} is of type {kind.type_name(connection.msgtype)}, not "
                                  f"{kind.type_name(JOINT_STATE)}; name the joint states' topic with --joint-topic")
        if not state_connections:
            report.notes.append(f"the bag has no joint states on {joint_topic}: the recording has no robot/state "
                                f"(its topics: {topics})")
        if sum(c.msgcount for c in skin_connections) == 0:
            raise ConfigError(f"{bag} has no message on {topic}")

        gateway = Gateway(profile.gateway, pmap.n_pads, source=kind.source)
        robot = profile.robot.name
        wanted = [*skin_connections, *state_connections]
        with new_file(out, "the recording") as stream:
            recorder = McapRecorder(stream, robot, compression=profile.recorder.compression,
                                    chunk_size=profile.recorder.chunk_size)
            first_ns = min((t for _, t, _ in _records(reader, bag, skin_connections, kind)), default=0)
            recorder.metadata("session", session_metadata(
                robot=robot, session=out.stem, profile_json=msgspec.json.encode(profile).decode(), strategy="",
                planner="", start_time_iso=dt.datetime.fromtimestamp(first_ns / 1e9, dt.UTC).isoformat(),
                start_monotonic_ns=first_ns, timing="imported",
                labels={"imported_from": str(bag), "import_tool": "nwr import", "ros_version": kind.name,
                        "ros_skin_topic": topic, "ros_skin_type": message_type, "ros_joint_topic": joint_topic,
                        "pad_mapping": json.dumps(pmap.table())},
            ))
            report.first_ns = first_ns
            for connection, stamp, raw in _records(reader, bag, wanted, kind):
                try:
                    msg = kind.deserialize(typestore, raw, connection.msgtype)
                    values: Any = getattr(msg, values_field) if connection.topic == topic else ()
                except Exception as exc:  # a corrupt record: counted, never fatal
                    bucket = report.skin_problems if connection.topic == topic else report.state_problems
                    bucket[f"undecodable: {type(exc).__name__}"] += 1
                    continue
                if connection.topic == topic:
                    mapped = map_values(values, pmap)
                    for problem in mapped.problems:
                        report.skin_problems[problem] += 1
                    sample, _ = gateway.process((stamp - first_ns) / 1e9, stamp, mapped.absolute_hpa)
                    recorder.write(keys.key(robot, keys.SKIN_PRESSURE), sample, stamp)
                    report.skin += 1
                    report.last_ns = max(report.last_ns, stamp)
                else:
                    state, problem, example = robot_state(msg, desc, report.states, stamp)
                    if state is None:
                        what = f"{connection.topic}: {problem}"
                        report.state_problems[what] += 1
                        report.state_examples.setdefault(what, f"at {stamp / 1e9:.3f} s: {example}" if example
                                                         else f"at {stamp / 1e9:.3f} s")
                        continue
                    recorder.write(keys.key(robot, keys.ROBOT_STATE), state, stamp)
                    report.states += 1
            recorder.finish()
    finally:
        reader.close()
    return report


def robot_state(msg: Any, desc: RobotDescription, seq: int, stamp_ns: int
                ) -> tuple[m.RobotState | None, str, str]:
    """A JointState -> RobotState in the robot's joint order (by name), or None, the kind of problem and the
    first offending joint and value.

    Positions must be finite and within the robot description's joint limits, velocities finite and within its
    speed limits: anything else is a corrupt message, or another robot's.
    """
    joints = list(desc.joints)
    names = list(msg.name)
    index = {name: i for i, name in enumerate(names)}
    missing = [j for j in joints if j not in index]
    if missing:
        return None, f"missing joints {missing}", ""
    try:
        position = np.asarray(msg.position, dtype=float)
        velocity = np.asarray(msg.velocity, dtype=float)
    except (TypeError, ValueError):
        return None, "positions or velocities that are no numbers", ""
    if position.ndim != 1 or velocity.ndim != 1 or len(position) != len(names) or \
            (len(velocity) and len(velocity) != len(names)):
        return None, "positions or velocities not one per name", ""
    order = [index[j] for j in joints]
    q = position[order]
    dq = velocity[order] if len(velocity) else np.zeros(len(joints))
    for i, joint in enumerate(joints):
        if not math.isfinite(q[i]):
            return None, "non-finite positions", f"{joint} = {q[i]}"
        if not desc.q_min[i] <= q[i] <= desc.q_max[i]:
            return None, "positions beyond the joint limits", \
                f"{joint} = {q[i]:g} rad, its limits [{desc.q_min[i]:g}, {desc.q_max[i]:g}] rad"
    for i, joint in enumerate(joints):
        if not math.isfinite(dq[i]):
            return None, "non-finite velocities", f"{joint} = {dq[i]}"
        if abs(dq[i]) > desc.v_max[i]:
            return None, "velocities beyond the joint speed limits", \
                f"{joint} = {dq[i]:g} rad/s, its limit {desc.v_max[i]:g} rad/s"
    return m.RobotState(seq=seq, stamp_ns=stamp_ns, q=q.tolist(), dq=dq.tolist(), status="ok", owner="rosbag",
                        backend="rosbag", skin_age_s=-1.0), "", ""


def _run(args: argparse.Namespace) -> int:
    profile = profile_for(args)
    ros1 = settings_of(profile)
    desc = load_description(profile.robot.description or None)
    mapping = ros1.pads
    if args.mapping:
        mapping = [name.strip() for name in args.mapping.split(",")]
    pmap = pad_map(mapping, [p.name for p in desc.pads], scale_hpa=ros1.scale_hpa, offset_hpa=ros1.offset_hpa,
                   where="--mapping" if args.mapping else "gateway.ros1.pads")
    bag, out = Path(args.bag), Path(args.output)
    if out.suffix != ".mcap":
        raise ConfigError(f"{out}: the recording to write must end in .mcap")
    if out.exists() and not args.force:
        raise ConfigError(f"{out} exists: give another name, or --force to overwrite it")
    report = import_bag(bag, out, profile, topic=args.topic or ros1.topic, joint_topic=args.joint_topic,
                        pmap=pmap, message_type=args.message_type or ros1.message_type,
                        definition=ros1.definition, values_field=args.field or ros1.values_field)
    print(report.format(out))
    if report.skin_problems or report.state_problems:
        log.warning("some messages had problems (above); the recording marks the bad pads invalid and leaves out "
                    "the joint states skipped")
    if not report.skin:
        return 1
    return PARTIAL if report.state_problems else 0


# The exit code of an import that wrote its recording but left joint states out: a script that imports a lab's
# bags can tell a recording of the whole motion from a partial one.
PARTIAL = 3


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import",
        help="turn a ROS 1 or ROS 2 bag of a touch session (skin pressures, joint states) into a recording",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("bag", help="ROS 1 bag (.bag), or ROS 2 bag: a rosbag2 directory, or its .mcap or .db3 file")
    p.add_argument("output", help="recording to write (.mcap)")
    p.add_argument("--topic", help="the skin's topic (default: gateway.ros1.topic)")
    p.add_argument("--message-type",
                   help="the skin's message type, pkg/Name or pkg/msg/Name (default: gateway.ros1.message_type)")
    p.add_argument("--field", help="the message's field of pressures (default: gateway.ros1.values_field)")
    p.add_argument("--joint-topic", default="/joint_states",
                   help="sensor_msgs/(msg/)JointState topic (default: %(default)s)")
    p.add_argument("--mapping", metavar="PADS",
                   help="pad mapping: comma-separated pad names, the i-th for the message's value i, empty for an "
                        "unused one (default: gateway.ros1.pads of the profile, --profile)")
    p.add_argument("--force", action="store_true", help="overwrite OUTPUT if it exists")
    p.set_defaults(handler=_run)
