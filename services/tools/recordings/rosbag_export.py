"""``nwr export --ros2 IN OUT``: a recording -> a ROS 2 bag (rosbag2, MCAP storage) of standard messages.

OUT is a rosbag2 directory (``metadata.yaml`` and ``OUT.mcap``, written by
``rosbags``' rosbag2 writer, format version 9) that ``ros2 bag play`` plays
and Foxglove opens with its ROS 2 decoders. Its topics, all of standard ROS 2
types (CDR, their ``.msg`` definitions in the file):

- ``/joint_states`` (``sensor_msgs/msg/JointState``): every ``robot/state``,
  the joints named and ordered as in the robot description, positions,
  velocities and, where the controller estimates them (a Franka's
  ``tau_ext``), the estimated external torques as efforts (N m; empty
  otherwise);
- ``/nwr/skin/absolute_hpa`` and ``/nwr/skin/change_hpa``
  (``std_msgs/msg/Float64MultiArray``): every ``skin/pressure``, one value
  per pad in the skin file's pad order (one dimension, label ``pads``, size
  and stride the number of pads, the names in the bag's custom data
  ``nwr.pads``), hPa, NaN where the pad is invalid in that sample. Float64,
  not Float32 as AIRSKIN publishes: the recording's values are doubles, and
  so an export imported again (``nwr import``) gives the same samples;
- ``/tf`` (``tf2_msgs/msg/TFMessage``): the robot model's link transforms
  (the view's visual URDF, parent link -> child link) at the robot's state,
  at most ``--rate`` per second; ``/tf_static``: one frame per pad
  (``pad/<name>``, child of its link, at its point, z along its outward
  normal); ``/robot_description`` (``std_msgs/msg/String``): that URDF.
  The last two are offered transient-local, as robot_state_publisher's;
- ``/nwr/contacts`` (``visualization_msgs/msg/MarkerArray``): on every
  ``skin/pain``, a DELETEALL and one arrow per pad with a gain above 0,
  pressing on the pad along its normal (in the pad's frame), 5 cm plus 10 cm
  times the gain long, yellow to red with the gain;
- ``/nwr/reflex`` (``visualization_msgs/msg/MarkerArray``): on every status
  of the active planner whose mode or reflex changes, a text above the base:
  the mode, and in a reflex its strategy, pad and gain.

Time: each message's bag time is its record's log time, its header stamp the
message's own stamp, both moved onto UTC by the session's (``start_time``,
``start_monotonic_ns``) pair for a live recording; an imported recording's
times are UTC already, a lockstep one's simulated time is kept as it is.
"""

from __future__ import annotations

import datetime as dt
import logging
import shutil
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nwr.common import messages as m
from nwr.common.errors import ConfigError
from nwr.common.recordings import Recorded, read_recording
from nwr.common.robot import RobotDescription, RobotModel, load_description
from nwr.common.ros2_msgs import (
    ADD,
    ARRAY_TYPE,
    ARROW,
    DELETEALL,
    JOINT_STATE_TYPE,
    JOINT_STATES,
    MARKERS_TYPE,
    REFLEX,
    SKIN_ABSOLUTE,
    SKIN_CHANGE,
    Ros2Builder,
)
from nwr.services.view.core import link_transforms, quaternion, urdf_joints, visual_urdf

log = logging.getLogger(__name__)

TF, TF_STATIC, DESCRIPTION = "/tf", "/tf_static", "/robot_description"
CONTACTS = "/nwr/contacts"
TOPICS: dict[str, str] = {
    JOINT_STATES: JOINT_STATE_TYPE,
    SKIN_ABSOLUTE: ARRAY_TYPE,
    SKIN_CHANGE: ARRAY_TYPE,
    TF: "tf2_msgs/msg/TFMessage",
    TF_STATIC: "tf2_msgs/msg/TFMessage",
    DESCRIPTION: "std_msgs/msg/String",
    CONTACTS: MARKERS_TYPE,
    REFLEX: MARKERS_TYPE,
}
LATCHED = (TF_STATIC, DESCRIPTION)


def pad_frame(name: str) -> str:
    return f"pad/{name}"


def wall_offset_ns(metadata: dict[str, dict[str, str]]) -> int:
    """What moves a recording's stamps onto UTC: a live session's (start_time - start_monotonic_ns), else 0."""
    session = metadata.get("session", {})
    if session.get("timing", "live") != "live":
        return 0
    try:
        start = dt.datetime.fromisoformat(session["start_time"])
        monotonic = int(session["start_monotonic_ns"])
    except (KeyError, ValueError):
        return 0
    if start.tzinfo is None:
        start = start.replace(tzinfo=dt.UTC)
    since = start - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)  # exact: a float timestamp loses microseconds
    return ((since.days * 86_400 + since.seconds) * 10**6 + since.microseconds) * 1000 - monotonic


@dataclass
class Ros2Messages:
    """A recording's records -> (topic, bag time, message) of ROS 2's standard types; pure (rosbags' classes)."""

    desc: RobotDescription
    model: RobotModel
    types: Any  # rosbags typestore
    offset_ns: int = 0
    rate_hz: float = 30.0
    counts: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.urdf = visual_urdf(self.desc)
        self.joints = urdf_joints(ET.fromstring(self.urdf))
        self.pads = [p.name for p in self.desc.pads]
        self._last_tf = -(2**62)
        self.build = Ros2Builder(self.types, self.desc.joints, self.offset_ns)
        self._t = self.build.t

    def _transform(self, ns: int, parent: str, child: str, translation: Iterable[float],
                   rotation: Iterable[float]) -> Any:
        x, y, z = (float(v) for v in translation)
        qx, qy, qz, qw = (float(v) for v in rotation)
        return self._t("geometry_msgs/msg/TransformStamped", header=self.build.header(ns, parent),
                       child_frame_id=child,
                       transform=self._t("geometry_msgs/msg/Transform",
                                         translation=self._t("geometry_msgs/msg/Vector3", x=x, y=y, z=z),
                                         rotation=self._t("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw)))

    def static(self, ns: int) -> Iterator[tuple[str, int, Any]]:
        """The robot description and the pads' frames, once at the start."""
        yield DESCRIPTION, ns, self._t("std_msgs/msg/String", data=self.urdf)
        transforms = []
        for pad in self.desc.pads:
            normal = np.asarray(pad.normal, dtype=float) / np.linalg.norm(pad.normal)
            x = np.cross([0.0, 0.0, 1.0], normal) if abs(normal[2]) < 0.9 else np.cross([1.0, 0.0, 0.0], normal)
            x /= np.linalg.norm(x)
            rotation = np.column_stack([x, np.cross(normal, x), normal])
            transforms.append(self._transform(ns, pad.link, pad_frame(pad.name), pad.point, quaternion(rotation)))
        yield TF_STATIC, ns, self._t("tf2_msgs/msg/TFMessage", transforms=transforms)

    def convert(self, record: Recorded) -> Iterator[tuple[str, int, Any]]:
        """The ROS 2 messages of one record (none for a record of no exported kind)."""
        msg, t = record.message, record.log_time_ns + self.offset_ns
        if isinstance(msg, m.RobotState):
            stamp = msg.stamp_ns + self.offset_ns
            yield JOINT_STATES, t, self.build.joint_state(msg)
            if t - self._last_tf >= 1e9 / self.rate_hz:
                self._last_tf = t
                transforms = [self._transform(stamp, tr.parent, tr.child, tr.translation, tr.rotation)
                              for tr in link_transforms(self.model, self.joints, np.asarray(msg.q, dtype=float))]
                yield TF, t, self._t("tf2_msgs/msg/TFMessage", transforms=transforms)
        elif isinstance(msg, m.SkinPressure):
            absolute, change = self.build.skin(msg)
            yield SKIN_ABSOLUTE, t, absolute
            yield SKIN_CHANGE, t, change
        elif isinstance(msg, m.SkinPain):
            yield CONTACTS, t, self._t(MARKERS_TYPE, markers=self._contacts(msg, msg.stamp_ns + self.offset_ns))
        elif isinstance(msg, m.PlannerStatus):
            markers = self.build.reflex(msg, self.joints[0].parent if self.joints else "base_link")
            if markers is not None:
                yield REFLEX, t, markers

    def _contacts(self, pain: m.SkinPain, ns: int) -> list[Any]:
        out = [self.build.marker(ns, "", "contacts", 0, ARROW, DELETEALL)]
        for pad, gain in enumerate(pain.gain):
            if not gain > 0 or pad >= len(self.pads):
                continue
            length = 0.05 + 0.10 * float(gain)
            tail = self._t("geometry_msgs/msg/Point", x=0.0, y=0.0, z=length)
            tip = self._t("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0)
            out.append(self.build.marker(
                ns, pad_frame(self.pads[pad]), "contacts", pad, ARROW, ADD, points=[tail, tip],
                scale=self._t("geometry_msgs/msg/Vector3", x=0.01, y=0.02, z=0.02),
                color=self._t("std_msgs/msg/ColorRGBA", r=1.0, g=float(1.0 - gain), b=0.0, a=1.0)))
        return out


@dataclass
class ExportReport:
    counts: dict[str, int]

    def format(self, out: Path) -> str:
        rows = ", ".join(f"{topic} {n}" for topic, n in self.counts.items() if n)
        return f"wrote the ROS 2 bag {out} (MCAP storage): {rows}"


def _qos(latched: bool) -> list[Any]:
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 1 if latched else 10, QosReliability.RELIABLE,
                QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE, zero, zero,
                QosLiveliness.AUTOMATIC, zero, False)]


def export_ros2(src: Path, out: Path, *, description: str | None = None, rate_hz: float = 30.0) -> ExportReport:
    """Write the recording ``src`` as the ROS 2 bag directory ``out``; ConfigError / RecordingError (one line)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    if out.exists():
        raise ConfigError(f"{out} exists: a ROS 2 bag is a new directory; give another name")
    records, metadata = read_recording(src)
    if not any(isinstance(r.message, (m.RobotState, m.SkinPressure)) for r in records):
        raise ConfigError(f"{src} has no robot state and no skin sample: nothing to export")
    desc = load_description(description)
    store = get_typestore(Stores.ROS2_JAZZY)
    convert = Ros2Messages(desc, RobotModel(desc), store, wall_offset_ns(metadata), rate_hz)
    records.sort(key=lambda r: r.log_time_ns)
    counts = dict.fromkeys(TOPICS, 0)
    partial = out.with_name(out.name + ".part")
    if partial.exists():
        raise ConfigError(f"{partial} exists (an export cut short?): remove it first")
    try:
        with Writer(partial, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            writer.set_custom_data("nwr.pads", ",".join(convert.pads))
            writer.set_custom_data("nwr.joints", ",".join(desc.joints))
            writer.set_custom_data("nwr.source", str(src))
            writer.set_custom_data("nwr.session", metadata.get("session", {}).get("session", ""))
            connections = {topic: writer.add_connection(topic, msgtype, typestore=store,
                                                        offered_qos_profiles=_qos(topic in LATCHED))
                           for topic, msgtype in TOPICS.items()}

            def write(items: Iterable[tuple[str, int, Any]]) -> None:
                for topic, t, msg in items:
                    writer.write(connections[topic], max(0, t), store.serialize_cdr(msg, TOPICS[topic]))
                    counts[topic] += 1

            write(convert.static(records[0].log_time_ns + convert.offset_ns))
            for record in records:
                write(convert.convert(record))
    except OSError as exc:
        shutil.rmtree(partial, ignore_errors=True)
        raise ConfigError(f"{out} cannot be written: {exc.strerror or exc}") from exc
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)  # nothing half-written is left behind
        raise
    # rosbags names the storage file after the directory: name both after OUT.
    (partial / f"{partial.name}.mcap").rename(partial / f"{out.name}.mcap")
    meta = partial / "metadata.yaml"
    meta.write_text(meta.read_text().replace(f"{partial.name}.mcap", f"{out.name}.mcap"))
    partial.rename(out)
    return ExportReport(counts)
