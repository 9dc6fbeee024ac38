"""The pipeline's messages as ROS 2's standard messages (``rosbags``' classes): one conversion for ``nwr export
--ros2`` (:mod:`nwr.services.tools.recordings.rosbag_export`) and the live ROS 2 topics (:mod:`nwr.common.ros2`).

Pure: numbers and Structs in, message objects of a ``rosbags`` type store out
(its ``serialize_cdr`` makes the bytes). The topics, relative to a namespace
(the bag's and the default live one: ``/``):

- ``joint_states`` (``sensor_msgs/msg/JointState``): a ``robot/state``, the
  joints named and ordered as in the robot description, positions,
  velocities and, where the controller estimates them (a Franka's
  ``tau_ext``), the estimated external torques as efforts (N m; empty
  otherwise, as ROS leaves a field it does not know);
- ``nwr/skin/absolute_hpa``, ``nwr/skin/change_hpa``
  (``std_msgs/msg/Float64MultiArray``): a ``skin/pressure``, one value per pad
  in the skin file's order (one dimension, label ``pads``), NaN where the pad
  is invalid in that sample;
- ``nwr/reflex`` (``visualization_msgs/msg/MarkerArray``): the active
  planner's status when its mode or reflex changes, as a text above the base.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from nwr.common import messages as m

JOINT_STATES = "/joint_states"
SKIN_ABSOLUTE = "/nwr/skin/absolute_hpa"
SKIN_CHANGE = "/nwr/skin/change_hpa"
REFLEX = "/nwr/reflex"
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
ARRAY_TYPE = "std_msgs/msg/Float64MultiArray"
MARKERS_TYPE = "visualization_msgs/msg/MarkerArray"
ARROW, TEXT_VIEW_FACING, DELETEALL = 0, 9, 3  # visualization_msgs/Marker's type and action constants
ADD = 0
NUMBERS = {"bool", "byte", "char", "float32", "float64", "int8", "int16", "int32", "int64", "uint8", "uint16",
           "uint32", "uint64"}


def field_names(typestore: Any, msgtype: str) -> list[str]:
    """The fields of ``msgtype`` in ``typestore``."""
    return [name for name, _ in typestore.fielddefs[msgtype][1]]


def numbers_field(typestore: Any, msgtype: str, name: str) -> str | None:
    """None if field ``name`` of ``msgtype`` is an array or sequence of numbers, else what it is."""
    from rosbags.interfaces import Nodetype

    (kind, detail), = [t for n, t in typestore.fielddefs[msgtype][1] if n == name]
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        (inner, inner_detail), _count = detail
        if inner == Nodetype.BASE and inner_detail[0] in NUMBERS:
            return None
        return f"an array of {inner_detail[0] if inner == Nodetype.BASE else inner_detail}"
    return detail[0] if kind == Nodetype.BASE else str(detail)


class Ros2Builder:
    """Messages of the type store ``types`` (Jazzy's or Humble's definitions) for one robot, stamps moved by
    ``offset_ns`` (monotonic -> UTC)."""

    def __init__(self, types: Any, joints: Iterable[str], offset_ns: int = 0) -> None:
        self.types = types
        self.joints = list(joints)
        self.offset_ns = offset_ns
        self._last_mode: tuple[Any, ...] | None = None
        self._classes = types.types

    def t(self, msgtype: str, /, **kwargs: Any) -> Any:
        return self._classes[msgtype](**kwargs)

    def time(self, ns: int) -> Any:
        ns = max(0, ns)
        return self.t("builtin_interfaces/msg/Time", sec=ns // 10**9, nanosec=ns % 10**9)

    def header(self, ns: int, frame: str = "") -> Any:
        return self.t("std_msgs/msg/Header", stamp=self.time(ns), frame_id=frame)

    def joint_state(self, state: m.RobotState) -> Any:
        return self.t(JOINT_STATE_TYPE, header=self.header(state.stamp_ns + self.offset_ns), name=self.joints,
                      position=np.array(state.q, dtype=np.float64), velocity=np.array(state.dq, dtype=np.float64),
                      effort=np.array(state.tau_ext, dtype=np.float64))

    def pad_array(self, values: Iterable[float], valid: list[bool]) -> Any:
        data = np.array([v if ok else math.nan for v, ok in zip(values, valid, strict=True)], dtype=np.float64)
        n = len(data)
        layout = self.t("std_msgs/msg/MultiArrayLayout", dim=[
            self.t("std_msgs/msg/MultiArrayDimension", label="pads", size=n, stride=n)], data_offset=0)
        return self.t(ARRAY_TYPE, layout=layout, data=data)

    def skin(self, sample: m.SkinPressure) -> tuple[Any, Any]:
        """The sample's absolute pressures and changes, hPa (NaN: invalid)."""
        valid = list(sample.valid) or [True] * len(sample.absolute_hpa)
        return self.pad_array(sample.absolute_hpa, valid), self.pad_array(sample.change_hpa, valid)

    def marker(self, ns: int, frame: str, namespace: str, ident: int, kind: int, action: int, **kw: Any) -> Any:
        """A Marker of this type store's definition (Jazzy's has texture and mesh-file fields Humble's lacks)."""
        t = self.t
        defaults: dict[str, Any] = {
            "pose": lambda: t("geometry_msgs/msg/Pose", position=t("geometry_msgs/msg/Point", x=0.0, y=0.0, z=0.0),
                              orientation=t("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0)),
            "scale": lambda: t("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0),
            "color": lambda: t("std_msgs/msg/ColorRGBA", r=0.0, g=0.0, b=0.0, a=0.0),
            "lifetime": lambda: t("builtin_interfaces/msg/Duration", sec=0, nanosec=0),
            "frame_locked": lambda: True, "points": list, "colors": list, "texture_resource": str,
            "texture": lambda: t("sensor_msgs/msg/CompressedImage", header=self.header(0), format="",
                                 data=np.array([], dtype=np.uint8)),
            "uv_coordinates": list, "text": str, "mesh_resource": str,
            "mesh_file": lambda: t("visualization_msgs/msg/MeshFile", filename="", data=np.array([], dtype=np.uint8)),
            "mesh_use_embedded_materials": lambda: False,
        }
        fields: dict[str, Any] = {"header": self.header(ns, frame), "ns": namespace, "id": ident, "type": kind,
                                  "action": action}
        for name in field_names(self.types, "visualization_msgs/msg/Marker"):
            if name not in fields:
                fields[name] = kw[name] if name in kw else defaults[name]()
        return t("visualization_msgs/msg/Marker", **fields)

    def reflex(self, status: m.PlannerStatus, frame: str) -> Any | None:
        """The active planner's mode (and its reflex's strategy, pad, gain) as a text marker above the base in
        ``frame``, when it changes; None for another planner's status or no change."""
        if not status.active:
            return None
        reflex = status.reflex
        key = (status.name, status.mode, reflex and (reflex.reflex_seq, reflex.contact.pad))
        if key == self._last_mode:
            return None
        self._last_mode = key
        text = f"{status.name}: {status.mode}"
        if reflex is not None:
            contact = reflex.contact
            text += f" ({reflex.strategy}, {contact.name}, gain {contact.gain:.2f})"
        pose = self.t("geometry_msgs/msg/Pose", position=self.t("geometry_msgs/msg/Point", x=0.0, y=0.0, z=1.6),
                      orientation=self.t("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0))
        marker = self.marker(status.stamp_ns + self.offset_ns, frame, "reflex", 0, TEXT_VIEW_FACING, ADD, pose=pose,
                             text=text, scale=self.t("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.08),
                             color=self.t("std_msgs/msg/ColorRGBA", r=1.0, g=1.0, b=1.0, a=1.0))
        return self.t(MARKERS_TYPE, markers=[marker])
