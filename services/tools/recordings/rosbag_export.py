"""``nwr export --ros2 IN OUT``: a recording -> a ROS 2 bag (rosbag2, MCAP storage) of standard messages.

OUT is a rosbag2 directory (``metadata.yaml`` and ``OUT.mcap``, written by
``rosbags``' rosbag2 writer, format version 9) that ``ros2 bag play`` plays
and Foxglove opens with its ROS 2 decoders. Its topics, all of standard ROS 2
types (CDR, their ``.msg`` definitions in the file):

- ``/joint_states`` (``sensor_msgs/msg/JointState``): every ``robot/state``,
  the joints named and ordered as in the robot description, positions and
  velocities, no efforts;
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
import math
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
from nwr.services.view.core import link_transforms, quaternion, urdf_joints, visual_urdf

log = logging.getLogger(__name__)

JOINT_STATES = "/joint_states"
SKIN_ABSOLUTE = "/nwr/skin/absolute_hpa"
SKIN_CHANGE = "/nwr/skin/change_hpa"
TF, TF_STATIC, DESCRIPTION = "/tf", "/tf_static", "/robot_description"
CONTACTS, REFLEX = "/nwr/contacts", "/nwr/reflex"
TOPICS: dict[str, str] = {
    JOINT_STATES: "sensor_msgs/msg/JointState",
    SKIN_ABSOLUTE: "std_msgs/msg/Float64MultiArray",
    SKIN_CHANGE: "std_msgs/msg/Float64MultiArray",
    TF: "tf2_msgs/msg/TFMessage",
    TF_STATIC: "tf2_msgs/msg/TFMessage",
    DESCRIPTION: "std_msgs/msg/String",
    CONTACTS: "visualization_msgs/msg/MarkerArray",
    REFLEX: "visualization_msgs/msg/MarkerArray",
}
LATCHED = (TF_STATIC, DESCRIPTION)
ARROW, TEXT_VIEW_FACING, DELETEALL = 0, 9, 3  # visualization_msgs/Marker's type and action constants
ADD = 0


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
        self._last_mode: tuple[Any, ...] | None = None

    def _t(self, msgtype: str, /, **kwargs: Any) -> Any:
        return self.types.types[msgtype](**kwargs)

    def _time(self, ns: int) -> Any:
        ns = max(0, ns)
        return self._t("builtin_interfaces/msg/Time", sec=ns // 10**9, nanosec=ns % 10**9)

    def _header(self, ns: int, frame: str = "") -> Any:
        return self._t("std_msgs/msg/Header", stamp=self._time(ns), frame_id=frame)

    def _transform(self, ns: int, parent: str, child: str, translation: Iterable[float],
                   rotation: Iterable[float]) -> Any:
        x, y, z = (float(v) for v in translation)
        qx, qy, qz, qw = (float(v) for v in rotation)
        return self._t("geometry_msgs/msg/TransformStamped", header=self._header(ns, parent), child_frame_id=child,
                       transform=self._t("geometry_msgs/msg/Transform",
                                         translation=self._t("geometry_msgs/msg/Vector3", x=x, y=y, z=z),
                                         rotation=self._t("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw)))

    def _array(self, values: Iterable[float], valid: list[bool]) -> Any:
        data = np.array([v if ok else math.nan for v, ok in zip(values, valid, strict=True)], dtype=np.float64)
        n = len(data)
        layout = self._t("std_msgs/msg/MultiArrayLayout", dim=[
            self._t("std_msgs/msg/MultiArrayDimension", label="pads", size=n, stride=n)], data_offset=0)
        return self._t("std_msgs/msg/Float64MultiArray", layout=layout, data=data)

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
            yield JOINT_STATES, t, self._t(
                "sensor_msgs/msg/JointState", header=self._header(stamp), name=list(self.desc.joints),
                position=np.array(msg.q, dtype=np.float64), velocity=np.array(msg.dq, dtype=np.float64),
                effort=np.array([], dtype=np.float64))
            if t - self._last_tf >= 1e9 / self.rate_hz:
                self._last_tf = t
                transforms = [self._transform(stamp, tr.parent, tr.child, tr.translation, tr.rotation)
                              for tr in link_transforms(self.model, self.joints, np.asarray(msg.q, dtype=float))]
                yield TF, t, self._t("tf2_msgs/msg/TFMessage", transforms=transforms)
        elif isinstance(msg, m.SkinPressure):
            valid = list(msg.valid) or [True] * len(msg.absolute_hpa)
            yield SKIN_ABSOLUTE, t, self._array(msg.absolute_hpa, valid)
            yield SKIN_CHANGE, t, self._array(msg.change_hpa, valid)
        elif isinstance(msg, m.SkinPain):
            yield CONTACTS, t, self._t("visualization_msgs/msg/MarkerArray",
                                       markers=self._contacts(msg, msg.stamp_ns + self.offset_ns))
        elif isinstance(msg, m.PlannerStatus) and msg.active:
            reflex = msg.reflex
            key = (msg.name, msg.mode, reflex and (reflex.reflex_seq, reflex.contact.pad))
            if key != self._last_mode:
                self._last_mode = key
                yield REFLEX, t, self._t("visualization_msgs/msg/MarkerArray",
                                         markers=[self._reflex(msg, msg.stamp_ns + self.offset_ns)])

    def _marker(self, ns: int, frame: str, namespace: str, ident: int, kind: int, action: int, **kw: Any) -> Any:
        """A Marker of this type store's definition (Jazzy's has texture and mesh-file fields Humble's lacks)."""
        t = self._t
        defaults: dict[str, Any] = {
            "pose": lambda: t("geometry_msgs/msg/Pose", position=t("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0),
                              orientation=t("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0)),
            "scale": lambda: t("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0),
            "color": lambda: t("std_msgs/msg/ColorRGBA", r=0.0, g=0.0, b=0.0, a=0.0),
            "lifetime": lambda: t("builtin_interfaces/msg/Duration", sec=0, nanosec=0),
            "frame_locked": lambda: True, "points": list, "colors": list, "texture_resource": str,
            "texture": lambda: t("sensor_msgs/msg/CompressedImage", header=self._header(0), format="",
                                 data=np.array([], dtype=np.uint8)),
            "uv_coordinates": list, "text": str, "mesh_resource": str,
            "mesh_file": lambda: t("visualization_msgs/msg/MeshFile", filename="", data=np.array([], dtype=np.uint8)),
            "mesh_use_embedded_materials": lambda: False,
        }
        fields: dict[str, Any] = {"header": self._header(ns, frame), "ns": namespace, "id": ident, "type": kind,
                                  "action": action}
        for name in self._fields("visualization_msgs/msg/Marker"):
            if name not in fields:
                fields[name] = kw[name] if name in kw else defaults[name]()
        return t("visualization_msgs/msg/Marker", **fields)

    def _fields(self, msgtype: str) -> list[str]:
        return [name for name, _ in self.types.fielddefs[msgtype][1]]

    def _contacts(self, pain: m.SkinPain, ns: int) -> list[Any]:
        out = [self._marker(ns, "", "contacts", 0, ARROW, DELETEALL)]
        for pad, gain in enumerate(pain.gain):
            if not gain > 0 or pad >= len(self.pads):
                continue
            length = 0.05 + 0.10 * float(gain)
            tail = self._t("geometry_msgs/msg/Point", x=0.0, y=0.0, z=length)
            tip = self._t("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0)
            out.append(self._marker(
                ns, pad_frame(self.pads[pad]), "contacts", pad, ARROW, ADD, points=[tail, tip],
                scale=self._t("geometry_msgs/msg/Vector3", x=0.01, y=0.02, z=0.02),
                color=self._t("std_msgs/msg/ColorRGBA", r=1.0, g=float(1.0 - gain), b=0.0, a=1.0)))
        return out

    def _reflex(self, status: m.PlannerStatus, ns: int) -> Any:
        text = f"{status.name}: {status.mode}"
        if status.reflex is not None:
            contact = status.reflex.contact
            text += f" ({status.reflex.strategy}, {contact.name}, gain {contact.gain:.2f})"
        pose = self._t("geometry_msgs/msg/Pose", position=self._t("geometry_msgs/msg/Point", x=0.0, y=0.0, z=1.6),
                       orientation=self._t("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0))
        return self._marker(ns, self.joints[0].parent if self.joints else "base_link", "reflex", 0,
                            TEXT_VIEW_FACING, ADD, pose=pose, text=text,
                            scale=self._t("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.08),
                            color=self._t("std_msgs/msg/ColorRGBA", r=1.0, g=1.0, b=1.0, a=1.0))


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
