"""View core: the pipeline's messages -> Foxglove's well-known scene messages.

Pure: no Zenoh, no clock, no server. Messages go in through :meth:`ViewCore.apply`
(which only keeps the newest of each kind, as the live subscribers do), and
:meth:`ViewCore.frame` turns what is held at a given time into a :class:`Frame`
of plain numbers (what the tests check); :func:`encode_frame` turns a frame
into encoded channel messages (:class:`Output`), the same bytes for the live
WebSocket server, ``nwr view FILE`` and ``nwr export --foxglove``.

Channels (see :func:`channel_specs`):

- ``/robot_description``: the URDF with simple visual geometry (cylinders
  derived from the kinematics and the pad layout), as ``std_msgs/String``
  JSON, the name the 3D panel looks for;
- ``/tf``: ``foxglove.FrameTransforms``, one transform per URDF joint (fixed
  ones included) from its parent link to its child link at the newest joint
  state, computed with :class:`nwr.common.robot.RobotModel`;
- ``/nwr/pads``, ``/nwr/contact``, ``/nwr/reflex``: ``foxglove.SceneUpdate``
  of the pads (a patch per pad coloured by its gain, ringed by its LEDs), the
  contact arrow and the reflex's ghost;
- ``/nwr/people``: ``foxglove.SceneUpdate`` of a physics world's body parts
  on the arm (``world/contacts``): per body part and pad it touches, a
  sphere at the contact and an arrow of the force on the person (from the
  arm into them, :data:`FORCE_ARROW_M_PER_N`). The message names the pads a
  part touches, not where on them: the contact is drawn at the pad's point,
  where the world's touch-script fingers press; a part across several pads
  has its force split evenly among them. Contacts older than
  :data:`PEOPLE_STALE_NS` are gone (the world publishes them only while a
  body part is in it);
- ``/nwr/skin``, ``/nwr/planner``, ``/nwr/robot``, ``/nwr/onset``: JSON with a
  JSON Schema, for plots and state-transition panels. Each schema is in the
  form Foxglove's and Lichtblick's loader takes (every property typed, objects
  with their properties listed: see :func:`nwr.common.messages.json_schema`),
  so ``/nwr/skin``'s per-pad values, keyed by pad name, have a property per
  pad of the robot description.

Every stamp is the pipeline's clock (``time.monotonic_ns()`` live, log time
in a recording): a frame's header stamps equal its log time, so the 3D panel
looks transforms up on the same clock the entities carry.
"""

from __future__ import annotations

import bisect
import json
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CubePrimitive,
    FrameTransform,
    FrameTransforms,
    KeyValuePair,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    Vector3,
)

from nwr.common import messages as m
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.skin import contact_point

RGBA = tuple[float, float, float, float]

# -- colours ------------------------------------------------------------------
NEUTRAL: RGBA = (0.72, 0.74, 0.77, 1.0)  # a pad with G = 0
LED_IDLE: RGBA = (0.10, 0.35, 1.00, 1.0)  # AIRSKIN LEDs in the study: blue...
LED_TARGET: RGBA = (1.00, 0.05, 0.05, 1.0)  # ...and red on the pad to touch
GHOST: RGBA = (0.20, 0.85, 1.00, 0.35)
PERSON: RGBA = (0.95, 0.75, 0.60, 1.0)  # a body part's contact
FORCE: RGBA = (0.85, 0.10, 0.75, 1.0)  # the force on it
TUBE_RGBA = "0.80 0.82 0.85 1"
HOUSING_RGBA = "0.35 0.38 0.42 1"

# -- geometry (m) ---------------------------------------------------------------
PAD_SIZE_M = 0.12  # edge of a pad's square patch
PAD_THICKNESS_M = 0.01
LED_OFFSET_M = 0.004  # the LED ring floats this far above the patch, so it is never hidden
LED_THICKNESS_M = 0.008
ARROW_MAX_M = 0.25  # contact arrow length at G = 1 (it scales with G)
ARROW_HEAD_FRACTION = 0.3
ARROW_SHAFT_DIAMETER_M = 0.015
ARROW_HEAD_DIAMETER_M = 0.04
GHOST_LINE_M = 0.05
FORCE_ARROW_M_PER_N = 0.004  # a force arrow's length per newton on the person (a finger's 25 N: 10 cm)...
FORCE_ARROW_MAX_M = 0.3  # ...at most (75 N and more)
PERSON_SPHERE_M = 0.018  # a contact's sphere: a fingertip's width
PEOPLE_STALE_NS = 200_000_000  # world/contacts older than this show nobody (they come at the skin's rate)
GHOST_JOINT_M = 0.09
# Visual geometry of the generated URDF: every pad sits on an air cushion
# this thick; a link with no pad on its side gets this radius.
PAD_STANDOFF_M = 0.03
DEFAULT_LINK_RADIUS_M = 0.05

DEFAULT_RATE_HZ = 30.0
MODE_INDEX = {mode: index for index, mode in enumerate(m.MODES)}


def gain_color(gain: float) -> RGBA:
    """A pad's colour for its gain: neutral grey at G = 0 (no reflex), and from the
    first G > 0 on (a reflex fires) yellow, turning red as G rises to 1."""
    if not gain > 0.0:  # 0, negative or NaN: nothing to see
        return NEUTRAL
    g = min(float(gain), 1.0)
    return (1.0, 1.0 - g, 0.0, 1.0)


def led_color(pad: int, target_pad: int) -> RGBA:
    """The pad's LED ring: red on the study's target pad (the one to touch), blue elsewhere."""
    return LED_TARGET if pad == target_pad else LED_IDLE


def rotation_with_z(z: np.ndarray) -> np.ndarray:
    """A rotation matrix whose third column is the unit vector ``z``."""
    z = np.asarray(z, dtype=float) / np.linalg.norm(z)
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(z)))] = 1.0  # the axis least aligned with z: well conditioned
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack((x, np.cross(z, x), z))


def quaternion(rotation: np.ndarray) -> np.ndarray:
    """(x, y, z, w) of a rotation matrix, w >= 0."""
    q = pin.Quaternion(np.asarray(rotation, dtype=float)).coeffs()  # x, y, z, w
    return np.array(-q if q[3] < 0 else q)


# -- pads -----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PadPatch:
    """A pad drawn as a thin square patch in its link's frame.

    The patch's outer face passes through the pad's point, its z axis is the
    pad's outward normal; ``ring`` holds the four corners of its LED ring.
    """

    pad: int
    name: str
    region: str
    link: str
    point: np.ndarray  # on the surface, link frame
    normal: np.ndarray  # outward, link frame
    rotation: np.ndarray  # 3x3, z = normal
    center: np.ndarray  # of the box: half a thickness below the surface
    size: np.ndarray  # (edge, edge, thickness)
    ring: np.ndarray  # (4, 3) corners, link frame


def pad_patches(desc: RobotDescription, edge_m: float = PAD_SIZE_M,
                thickness_m: float = PAD_THICKNESS_M) -> tuple[PadPatch, ...]:
    patches = []
    half = edge_m / 2
    for pad in desc.pads:
        point = np.array(pad.point, dtype=float)
        normal = np.array(pad.normal, dtype=float)
        rotation = rotation_with_z(normal)
        corners = np.array([[half, half], [-half, half], [-half, -half], [half, -half]])
        ring = point + corners @ rotation[:, :2].T + LED_OFFSET_M * normal
        patches.append(PadPatch(
            pad=pad.id, name=pad.name, region=pad.region, link=pad.link, point=point, normal=normal,
            rotation=rotation, center=point - normal * thickness_m / 2,
            size=np.array([edge_m, edge_m, thickness_m]), ring=ring,
        ))
    return tuple(patches)


@dataclass(frozen=True)
class Arrow:
    """An arrow in ``frame``: from ``tail`` along the unit vector ``direction``, ``length`` long."""

    frame: str
    tail: np.ndarray
    direction: np.ndarray
    length: float
    color: RGBA

    @property
    def tip(self) -> np.ndarray:
        return self.tail + self.length * self.direction


def contact_arrow(patch: PadPatch, gain: float, max_length_m: float = ARROW_MAX_M) -> Arrow | None:
    """The touch on a pad: an arrow pressing on the pad along its inward normal, its
    tip on the surface, its length ``max_length_m * G``; None at G = 0."""
    if not gain > 0.0:
        return None
    length = max_length_m * min(float(gain), 1.0)
    return Arrow(patch.link, patch.point + length * patch.normal, -patch.normal, length, gain_color(gain))


@dataclass(frozen=True)
class PersonMark:
    """A body part on a pad: where it touches (the pad's point, link frame) and the force on it (N), as an arrow
    from the contact out along the pad's normal (from the arm into the person)."""

    name: str
    kind: str
    pad: int
    force_n: float
    point: np.ndarray
    arrow: Arrow | None


def person_marks(patches: Sequence[PadPatch], contacts: m.WorldContacts) -> list[PersonMark]:
    """The body parts of ``contacts`` on the pads they touch (a part touching none is not drawn)."""
    marks = []
    for person in contacts.people:
        pads = [p for p in person.pads if 0 <= p < len(patches)]
        for pad in pads:
            patch = patches[pad]
            force = float(person.force_n) / len(pads)
            length = min(FORCE_ARROW_M_PER_N * force, FORCE_ARROW_MAX_M)
            arrow = Arrow(patch.link, patch.point.copy(), patch.normal.copy(), length, FORCE) if length > 0 else None
            marks.append(PersonMark(person.name, person.kind, pad, force, patch.point.copy(), arrow))
    return marks


# -- URDF and transforms -----------------------------------------------------------


@dataclass(frozen=True)
class UrdfJoint:
    name: str
    type: str
    parent: str
    child: str
    xyz: np.ndarray  # joint origin in the parent link's frame


def urdf_joints(root: ET.Element) -> tuple[UrdfJoint, ...]:
    joints = []
    for joint in root.findall("joint"):
        origin = joint.find("origin")
        xyz = np.array([float(v) for v in origin.get("xyz", "0 0 0").split()]) if origin is not None else np.zeros(3)
        parent, child = joint.find("parent"), joint.find("child")
        if parent is None or child is None:
            raise ConfigError(f"URDF joint {joint.get('name')!r} lacks a <parent> or <child> link")
        joints.append(UrdfJoint(joint.get("name", ""), joint.get("type", ""), parent.get("link", ""),
                                child.get("link", ""), xyz))
    return tuple(joints)


def _cylinder(link: ET.Element, a: np.ndarray, b: np.ndarray, radius: float, material: str, rgba: str) -> None:
    """Append a <visual> cylinder from ``a`` to ``b`` (link frame) to ``link``."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    if length < 1e-6:
        return
    rpy = pin.rpy.matrixToRpy(rotation_with_z(axis / length))
    visual = ET.SubElement(link, "visual", name=f"nwr_{material}")
    ET.SubElement(visual, "origin", xyz=" ".join(f"{v:.6g}" for v in (a + b) / 2),
                  rpy=" ".join(f"{v:.9g}" for v in rpy))
    geometry = ET.SubElement(visual, "geometry")
    ET.SubElement(geometry, "cylinder", radius=f"{radius:.6g}", length=f"{length:.6g}")
    mat = ET.SubElement(visual, "material", name=f"nwr_{material}")
    ET.SubElement(mat, "color", rgba=rgba)


def visual_urdf(desc: RobotDescription) -> str:
    """The robot's URDF with simple visual geometry added (the file is not changed).

    Each moving link gets a housing along its joint axis (its z) and a tube to
    each child joint. Where pads sit on the side of a link (normal across the
    axis), the tube runs at the pads' height along the axis and with their
    distance to it less the air cushion (``PAD_STANDOFF_M``), so pads and
    tubes meet; elsewhere it is a straight stick of ``DEFAULT_LINK_RADIUS_M``.
    Links that already have visuals are left alone.
    """
    root = ET.parse(desc.urdf_path).getroot()
    joints = urdf_joints(root)
    moving = {j.child for j in joints if j.type != "fixed"}
    for link in root.findall("link"):
        name = link.get("name", "")
        if link.find("visual") is not None:
            continue
        children = [j for j in joints if j.parent == name]
        side = [p for p in desc.pads if p.link == name and abs(p.normal[2]) < 0.5]
        height = float(np.median([p.point[2] for p in side])) if side else 0.0
        radius = DEFAULT_LINK_RADIUS_M
        if side:
            # Distance of each pad from the tube's axis (the z = height plane's
            # line towards the child joints), less the cushion.
            radius = max(DEFAULT_LINK_RADIUS_M / 2,
                         float(np.median([math.hypot(*p.point[:2]) if not children else
                                          _distance_to_axis(p.point, children, height) for p in side]))
                         - PAD_STANDOFF_M)
        if name in moving:
            half = radius
            _cylinder(link, np.array([0.0, 0.0, min(0.0, height) - half]),
                      np.array([0.0, 0.0, max(0.0, height) + half]), radius, "housing", HOUSING_RGBA)
        for joint in children:
            end = joint.xyz
            if side and np.linalg.norm(end[:2]) > 1e-6:
                _cylinder(link, np.array([0.0, 0.0, height]), np.array([end[0], end[1], height]), radius,
                          "tube", TUBE_RGBA)
                if abs(end[2] - height) > 1e-6:
                    _cylinder(link, np.array([end[0], end[1], height]), end, radius, "tube", TUBE_RGBA)
            elif np.linalg.norm(end) > 1e-6:
                _cylinder(link, np.zeros(3), end, radius, "tube", TUBE_RGBA)
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _distance_to_axis(point: np.ndarray, children: list[UrdfJoint], height: float) -> float:
    end = children[0].xyz
    direction = np.array([end[0], end[1], 0.0])
    norm = np.linalg.norm(direction)
    offset = point - np.array([0.0, 0.0, height])
    if norm < 1e-9:
        return float(np.linalg.norm(offset[:2]))
    direction /= norm
    return float(np.linalg.norm(offset - direction * float(offset @ direction)))


@dataclass(frozen=True)
class Transform:
    """Pose of ``child`` in ``parent``: translation (m) and rotation (x, y, z, w)."""

    parent: str
    child: str
    translation: np.ndarray
    rotation: np.ndarray

    def matrix(self) -> np.ndarray:
        x, y, z, w = self.rotation
        out = np.eye(4)
        out[:3, :3] = pin.Quaternion(w, x, y, z).toRotationMatrix()
        out[:3, 3] = self.translation
        return out


def link_transforms(model: RobotModel, joints: Iterable[UrdfJoint], q: np.ndarray) -> list[Transform]:
    """One transform per URDF joint, parent link -> child link, at ``q``, from the model's FK."""
    poses: dict[str, np.ndarray] = {}

    def pose(link: str) -> np.ndarray:
        found = poses.get(link)
        if found is None:
            found = poses[link] = model.frame_pose(q, link)
        return found

    out = []
    for joint in joints:
        relative = np.linalg.solve(pose(joint.parent), pose(joint.child))
        out.append(Transform(joint.parent, joint.child, relative[:3, 3].copy(), quaternion(relative[:3, :3])))
    return out


def compose(transforms: Iterable[Transform], root: str) -> dict[str, np.ndarray]:
    """Every frame's 4x4 pose in ``root`` from a set of parent -> child transforms."""
    by_child = {t.child: t for t in transforms}
    out: dict[str, np.ndarray] = {root: np.eye(4)}

    def resolve(frame: str, depth: int = 0) -> np.ndarray:
        if frame in out:
            return out[frame]
        if frame not in by_child or depth > len(by_child):
            raise KeyError(f"frame {frame!r} is not connected to {root!r}")
        t = by_child[frame]
        out[frame] = resolve(t.parent, depth + 1) @ t.matrix()
        return out[frame]

    for child in by_child:
        resolve(child)
    return out


# -- the reflex's ghost ---------------------------------------------------------------


@dataclass(frozen=True)
class Ghost:
    """The planned end of a reflex, in the base frame: the arm's polyline at a joint
    target (joint-space reflexes), or the touched pad's planned displacement
    (Cartesian reflexes)."""

    frame: str
    strategy: str
    reflex_seq: int
    polyline: np.ndarray | None = None  # (n, 3): joints then tool, at the target
    arrow: Arrow | None = None


def reflex_ghost(model: RobotModel, status: m.PlannerStatus, q: np.ndarray | None) -> Ghost | None:
    reflex = status.reflex
    if status.mode != "REFLEX" or reflex is None:
        return None
    base = model.desc.base_frame
    if reflex.target and len(reflex.target) == model.nq:
        return Ghost(base, reflex.strategy, reflex.reflex_seq, polyline=model.joint_positions(np.array(reflex.target)))
    if len(reflex.direction) == 3:
        velocity = np.array(reflex.direction, dtype=float)
        speed = float(np.linalg.norm(velocity))
        start_q = status.saved_pose if status.saved_pose and len(status.saved_pose) == model.nq else q
        if speed <= 0 or start_q is None or not 0 <= reflex.contact.pad < len(model.desc.pads):
            return None
        tail = contact_point(model, np.asarray(start_q, dtype=float), reflex.contact)
        arrow = Arrow(base, tail, velocity / speed, speed * float(reflex.duration_s), GHOST)
        return Ghost(base, reflex.strategy, reflex.reflex_seq, arrow=arrow)
    return None


# -- frames ---------------------------------------------------------------------------


@dataclass
class PadState:
    patch: PadPatch
    gain: float
    level: int
    change_hpa: float
    color: RGBA
    led: RGBA


@dataclass
class Frame:
    """Everything one scene update shows, as plain numbers."""

    stamp_ns: int
    q: np.ndarray | None
    transforms: list[Transform]
    pads: list[PadState]
    contact: Arrow | None
    contact_pad: int
    ghost: Ghost | None
    # Plottable JSON messages due with this frame: (topic, message).
    signals: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    # A physics world's body parts on the arm.
    people: list[PersonMark] = field(default_factory=list)


@dataclass(frozen=True)
class Output:
    """One encoded message on one of the view's channels (:func:`channel_specs`)."""

    topic: str
    log_time_ns: int
    data: bytes


class ViewCore:
    """Holds the newest message of each kind and builds frames from them.

    ``apply`` only stores (it is what the live subscribers call, on Zenoh's
    threads); ``frame`` does the work (on the view's own paced thread).
    """

    def __init__(self, desc: RobotDescription, model: RobotModel) -> None:
        self.desc = desc
        self.model = model
        self.urdf = visual_urdf(desc)
        self.joints = urdf_joints(ET.fromstring(self.urdf))
        self.patches = pad_patches(desc)
        self.names = [p.name for p in desc.pads]
        self.channels = channel_specs(self.names)
        self.state: m.RobotState | None = None
        self.pressure: m.SkinPressure | None = None
        self.pain: m.SkinPain | None = None
        self.statuses: dict[str, m.PlannerStatus] = {}
        self.contacts: m.WorldContacts | None = None
        # What was already published, so that event-like signals go out once.
        self._skin_sent: tuple[int, int] | None = None
        self._status_sent: dict[str, int] = {}
        self._onset_sent: int | None = None

    def apply(self, message: Any) -> None:
        """Keep ``message`` as the newest of its kind (other kinds are ignored)."""
        match message:
            case m.RobotState():
                self.state = message
            case m.SkinPressure():
                self.pressure = message
            case m.SkinPain():
                self.pain = message
            case m.PlannerStatus():
                self.statuses[message.name] = message
            case m.WorldContacts():
                self.contacts = message
            case _:
                pass

    def active_status(self) -> m.PlannerStatus | None:
        """The status of the planner the bridge follows (else the newest one)."""
        statuses = dict(self.statuses)  # a copy: subscribers may add to it meanwhile
        state = self.state
        if state is not None and state.owner in statuses:
            return statuses[state.owner]
        return max(statuses.values(), key=lambda s: s.stamp_ns, default=None)

    def frame(self, now_ns: int) -> Frame:
        state, pain, pressure = self.state, self.pain, self.pressure
        status = self.active_status()
        n = len(self.patches)
        q = None
        transforms: list[Transform] = []
        if state is not None and len(state.q) == self.model.nq:
            q = m.as_array(state.q)
            transforms = link_transforms(self.model, self.joints, q)
        gains = list(pain.gain) if pain is not None and len(pain.gain) == n else [0.0] * n
        levels = list(pain.level) if pain is not None and len(pain.level) == n else [1] * n
        changes = list(pressure.change_hpa) if pressure is not None and len(pressure.change_hpa) == n else [0.0] * n
        target = status.target_pad if status is not None else -1
        pads = [PadState(p, float(gains[i]), int(levels[i]), float(changes[i]), gain_color(gains[i]),
                         led_color(i, target)) for i, p in enumerate(self.patches)]
        contact, contact_pad = None, -1
        strongest = pain.strongest if pain is not None else None
        if strongest is not None and 0 <= strongest.pad < n:
            contact = contact_arrow(self.patches[strongest.pad], strongest.gain)
            contact_pad = strongest.pad if contact is not None else -1
        ghost = reflex_ghost(self.model, status, q) if status is not None else None
        frame = Frame(now_ns, q, transforms, pads, contact, contact_pad, ghost)
        contacts = self.contacts
        if contacts is not None and now_ns - contacts.stamp_ns <= PEOPLE_STALE_NS:
            frame.people = person_marks(self.patches, contacts)
        self._signals(frame, state, pressure, pain, status)
        return frame

    def _signals(self, frame: Frame, state: m.RobotState | None, pressure: m.SkinPressure | None,
                 pain: m.SkinPain | None, status: m.PlannerStatus | None) -> None:
        out = frame.signals
        if state is not None:
            out.append(("/nwr/robot", {
                "stamp_ns": state.stamp_ns, "seq": state.seq, "q": list(state.q), "status": state.status,
                "active_planner": state.owner, "command_mode": state.command_mode, "reflex_seq": state.reflex_seq,
            }))
            # One per onset the bridge accepted: its states name the last one until the next (with reflex_seq 0
            # once the arm is back in its task), so the onset is its acceptance time, not the state's reflex.
            onset = state.accepted_ns
            if state.accepted is not None and state.accepted_ns > 0 and onset != self._onset_sent:
                self._onset_sent = onset
                reflex = status.reflex if status is not None else None
                out.append(("/nwr/onset", {
                    "reflex_seq": state.reflex_seq, "skin_seq": state.accepted.seq,
                    "skin_stamp_ns": state.accepted.stamp_ns, "accepted_ns": state.accepted_ns,
                    "latency_ms": (state.accepted_ns - state.accepted.stamp_ns) / 1e6,
                    "pad": reflex.contact.name if reflex is not None else "",
                    "gain": reflex.contact.gain if reflex is not None else 0.0,
                    "strategy": reflex.strategy if reflex is not None else "",
                }))
        if pain is not None or pressure is not None:
            key = (pressure.seq if pressure is not None else -1, pain.seq if pain is not None else -1)
            if key != self._skin_sent:
                self._skin_sent = key
                strongest = pain.strongest if pain is not None else None
                out.append(("/nwr/skin", {
                    "pressure_seq": key[0], "pain_seq": key[1],
                    "stamp_ns": pain.stamp_ns if pain is not None else pressure.stamp_ns,  # type: ignore[union-attr]
                    "change_hpa": {p.patch.name: p.change_hpa for p in frame.pads},
                    "level": {p.patch.name: p.level for p in frame.pads},
                    "gain": {p.patch.name: p.gain for p in frame.pads},
                    "strongest": {"pad": strongest.name if strongest else "",
                                  "gain": strongest.gain if strongest else 0.0,
                                  "level": strongest.level if strongest else 1},
                }))
        active = self.state.owner if self.state is not None else ""
        for name, s in sorted(self.statuses.items()):
            if self._status_sent.get(name) == s.seq:
                continue
            self._status_sent[name] = s.seq
            target, reflex = s.target_pad, s.reflex
            retreat = reflex.retreat if reflex is not None else None
            out.append(("/nwr/planner", {
                "stamp_ns": s.stamp_ns, "seq": s.seq, "name": s.name, "strategy": s.strategy, "mode": s.mode,
                "mode_index": MODE_INDEX.get(s.mode, -1), "active": s.name == active, "active_planner": active,
                "target_pad": target, "target_name": self._name(target),
                "reflex_seq": reflex.reflex_seq if reflex is not None else 0,
                "task_time_s": s.task_time_s,
                # Why the reflex's motion is not its strategy's plain one, what the joints allow it at full gain,
                # and how far its retreat check found each other touched pad moves toward its own contact.
                "reason": reflex.reason if reflex is not None else "",
                "reach_m": reflex.reach_m if reflex is not None else 0.0,
                "others": [] if retreat is None else [
                    {"pad": self._name(pad), "toward_m": toward}
                    for pad, toward in zip(retreat.contacts, retreat.contacts_toward_m)],
            }))

    def _name(self, pad: int) -> str:
        """A pad's name ("" for none, -1)."""
        return self.names[pad] if 0 <= pad < len(self.names) else ""

    def description(self, now_ns: int) -> Output:
        return Output(ROBOT_DESCRIPTION, now_ns, json.dumps({"data": self.urdf}).encode())


# -- encoding --------------------------------------------------------------------------

ROBOT_DESCRIPTION = "/robot_description"


def _object(properties: dict[str, Any], title: str) -> bytes:
    return json.dumps({"title": title, "type": "object", "properties": properties}).encode()


def _per_pad(pad_names: Sequence[str], value_type: str) -> dict[str, Any]:
    """An object with one property per pad, by name (the loader needs an object's properties listed)."""
    return {"type": "object", "properties": {name: {"type": value_type} for name in pad_names}}


@dataclass(frozen=True)
class ChannelSpec:
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema: bytes
    doc: str


def _protobuf(topic: str, message_type: Any, doc: str) -> ChannelSpec:
    schema = message_type.get_schema()
    return ChannelSpec(topic, "protobuf", schema.name, schema.encoding, bytes(schema.data), doc)


def channel_specs(pad_names: Sequence[str]) -> tuple[ChannelSpec, ...]:
    """The view's channels for a robot whose pads are ``pad_names`` (in pad id order)."""
    return (
        ChannelSpec(ROBOT_DESCRIPTION, "json", "std_msgs/String", "jsonschema",
                    _object({"data": {"type": "string"}}, "std_msgs/String"),
                    "the URDF with simple visual geometry (the 3D panel loads it from this topic)"),
        _protobuf("/tf", FrameTransforms, "every URDF joint's transform, parent link -> child link"),
        _protobuf("/nwr/pads", SceneUpdate, "pads coloured by gain, LED rings (red: the study's target)"),
        _protobuf("/nwr/contact", SceneUpdate, "the strongest contact: an arrow into the pad, length ~ gain"),
        _protobuf("/nwr/reflex", SceneUpdate, "the reflex's planned end (ghost arm or Cartesian displacement)"),
        _protobuf("/nwr/people", SceneUpdate,
                  "a physics world's body parts on the arm: a sphere per contact, an arrow of the force on the person"),
        ChannelSpec("/nwr/skin", "json", "nwr.view.Skin", "jsonschema", _object({
            "pressure_seq": {"type": "integer"}, "pain_seq": {"type": "integer"}, "stamp_ns": {"type": "integer"},
            "change_hpa": _per_pad(pad_names, "number"), "level": _per_pad(pad_names, "integer"),
            "gain": _per_pad(pad_names, "number"),
            "strongest": {"type": "object", "properties": {"pad": {"type": "string"}, "gain": {"type": "number"},
                                                           "level": {"type": "integer"}}},
        }, "nwr.view.Skin"), "per pad (a property per pad name): pressure change (hPa), pain level, gain"),
        ChannelSpec("/nwr/planner", "json", "nwr.view.Planner", "jsonschema", _object({
            "stamp_ns": {"type": "integer"}, "seq": {"type": "integer"}, "name": {"type": "string"},
            "strategy": {"type": "string"}, "mode": {"type": "string", "enum": list(m.MODES)},
            "mode_index": {"type": "integer"}, "active": {"type": "boolean"}, "active_planner": {"type": "string"},
            "target_pad": {"type": "integer"}, "target_name": {"type": "string"}, "reflex_seq": {"type": "integer"},
            "task_time_s": {"type": "number"}, "reason": {"type": "string"}, "reach_m": {"type": "number"},
            "others": {"type": "array", "items": {"type": "object", "properties": {
                "pad": {"type": "string"}, "toward_m": {"type": "number"}}}},
        }, "nwr.view.Planner"),
            "each planner's mode (TASK 0, REFLEX 1, RETURNING 2, HOLDING 3), strategy, target pad; its reflex's "
            "reason, reach (m) and each other touched pad's planned motion toward its own contact (m)"),
        ChannelSpec("/nwr/robot", "json", "nwr.view.Robot", "jsonschema", _object({
            "stamp_ns": {"type": "integer"}, "seq": {"type": "integer"},
            "q": {"type": "array", "items": {"type": "number"}}, "status": {"type": "string"},
            "active_planner": {"type": "string"}, "command_mode": {"type": "string"},
            "reflex_seq": {"type": "integer"},
        }, "nwr.view.Robot"), "the joint state the frame's /tf was computed from; the active planner"),
        ChannelSpec("/nwr/onset", "json", "nwr.view.Onset", "jsonschema", _object({
            "reflex_seq": {"type": "integer"}, "skin_seq": {"type": "integer"}, "skin_stamp_ns": {"type": "integer"},
            "accepted_ns": {"type": "integer"}, "latency_ms": {"type": "number"}, "pad": {"type": "string"},
            "gain": {"type": "number"}, "strategy": {"type": "string"},
        }, "nwr.view.Onset"), "each reflex's onset latency: skin sample stamped -> first command accepted"),
    )


# The view's topics, whatever the robot (an exported file that has one was exported already).
VIEW_TOPICS = frozenset(spec.topic for spec in channel_specs(()))


def _ts(ns: int) -> Timestamp:
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _v(p: np.ndarray) -> Vector3:
    return Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _pose(position: np.ndarray, rotation_xyzw: np.ndarray) -> Pose:
    x, y, z, w = (float(v) for v in rotation_xyzw)
    return Pose(position=_v(position), orientation=Quaternion(x=x, y=y, z=z, w=w))


def _c(rgba: RGBA) -> Color:
    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


_IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def _arrow(arrow: Arrow) -> ArrowPrimitive:
    # A Foxglove arrow points along +x of its pose.
    rotation = rotation_with_z(arrow.direction)[:, [2, 0, 1]]  # columns x = direction, y, z
    head = ARROW_HEAD_FRACTION * arrow.length
    return ArrowPrimitive(
        pose=_pose(arrow.tail, quaternion(rotation)), shaft_length=arrow.length - head,
        shaft_diameter=ARROW_SHAFT_DIAMETER_M, head_length=head, head_diameter=ARROW_HEAD_DIAMETER_M,
        color=_c(arrow.color),
    )


def _delete_all(stamp: Timestamp) -> SceneUpdate:
    return SceneUpdate(deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)])


def encode_frame(frame: Frame) -> list[Output]:
    """A frame as encoded messages, in a fixed order: signals, /tf, then the scene."""
    t = frame.stamp_ns
    stamp = _ts(t)
    out = [Output(topic, t, json.dumps(msg).encode()) for topic, msg in frame.signals]
    if frame.transforms:
        tf = FrameTransforms(transforms=[
            FrameTransform(timestamp=stamp, parent_frame_id=x.parent, child_frame_id=x.child,
                           translation=_v(x.translation),
                           rotation=Quaternion(x=float(x.rotation[0]), y=float(x.rotation[1]),
                                               z=float(x.rotation[2]), w=float(x.rotation[3])))
            for x in frame.transforms])
        out.append(Output("/tf", t, tf.encode()))
    entities = []
    for pad in frame.pads:
        p = pad.patch
        entities.append(SceneEntity(
            timestamp=stamp, frame_id=p.link, id=f"pad/{p.name}", frame_locked=True,
            metadata=[KeyValuePair(key="pad", value=p.name), KeyValuePair(key="region", value=p.region),
                      KeyValuePair(key="gain", value=repr(pad.gain)), KeyValuePair(key="level", value=str(pad.level)),
                      KeyValuePair(key="change_hpa", value=f"{pad.change_hpa:.2f}")],
            cubes=[CubePrimitive(pose=_pose(p.center, quaternion(p.rotation)), size=_v(p.size), color=_c(pad.color))],
            lines=[LinePrimitive(type=LinePrimitiveLineType.LineLoop, pose=_pose(np.zeros(3), _IDENTITY),
                                 thickness=LED_THICKNESS_M, points=[Point3(x=float(c[0]), y=float(c[1]), z=float(c[2]))
                                                                    for c in p.ring], color=_c(pad.led))],
        ))
    out.append(Output("/nwr/pads", t, SceneUpdate(entities=entities).encode()))
    if frame.contact is not None:
        pad_name = frame.pads[frame.contact_pad].patch.name
        gain = frame.pads[frame.contact_pad].gain
        contact = SceneUpdate(entities=[SceneEntity(
            timestamp=stamp, frame_id=frame.contact.frame, id="contact", frame_locked=True,
            metadata=[KeyValuePair(key="pad", value=pad_name), KeyValuePair(key="gain", value=repr(gain))],
            arrows=[_arrow(frame.contact)])])
    else:
        contact = _delete_all(stamp)
    out.append(Output("/nwr/contact", t, contact.encode()))
    ghost = frame.ghost
    if ghost is not None:
        meta = [KeyValuePair(key="strategy", value=ghost.strategy),
                KeyValuePair(key="reflex_seq", value=str(ghost.reflex_seq))]
        if ghost.polyline is not None:
            entity = SceneEntity(
                timestamp=stamp, frame_id=ghost.frame, id="reflex", metadata=meta,
                lines=[LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=_pose(np.zeros(3), _IDENTITY),
                                     thickness=GHOST_LINE_M, points=[Point3(x=float(a), y=float(b), z=float(c))
                                                                     for a, b, c in ghost.polyline], color=_c(GHOST))],
                spheres=[SpherePrimitive(pose=_pose(p, _IDENTITY), size=_v(np.full(3, GHOST_JOINT_M)), color=_c(GHOST))
                         for p in ghost.polyline],
            )
        else:
            assert ghost.arrow is not None
            entity = SceneEntity(timestamp=stamp, frame_id=ghost.frame, id="reflex", metadata=meta,
                                 arrows=[_arrow(ghost.arrow)])
        out.append(Output("/nwr/reflex", t, SceneUpdate(entities=[entity]).encode()))
    else:
        out.append(Output("/nwr/reflex", t, _delete_all(stamp).encode()))
    people = [SceneEntity(
        timestamp=stamp, frame_id=frame.pads[mark.pad].patch.link,
        id=f"person/{mark.name}/{frame.pads[mark.pad].patch.name}", frame_locked=True,
        metadata=[KeyValuePair(key="person", value=mark.name), KeyValuePair(key="kind", value=mark.kind),
                  KeyValuePair(key="pad", value=frame.pads[mark.pad].patch.name),
                  KeyValuePair(key="force_n", value=f"{mark.force_n:.2f}")],
        spheres=[SpherePrimitive(pose=_pose(mark.point, _IDENTITY), size=_v(np.full(3, PERSON_SPHERE_M)),
                                 color=_c(PERSON))],
        arrows=[_arrow(mark.arrow)] if mark.arrow is not None else [],
    ) for mark in frame.people]
    # Each frame replaces the last one's people (deletions apply before entities: a part that left is gone).
    update = SceneUpdate(deletions=[SceneEntityDeletion(timestamp=stamp, type=SceneEntityDeletionType.All)],
                         entities=people)
    out.append(Output("/nwr/people", t, update.encode()))
    return out


# -- pacing ----------------------------------------------------------------------------


class SceneClock:
    """Caps the scene rate on any clock: ``due(t)`` is True at most once per period.

    Deadlines sit on a fixed grid (no drift); after a gap longer than a period
    the grid restarts at the late call, so a stall is never followed by a burst.
    """

    def __init__(self, rate_hz: float = DEFAULT_RATE_HZ) -> None:
        if not rate_hz > 0:
            raise ConfigError(f"scene rate {rate_hz!r} Hz: expected a positive rate, e.g. 30")
        self.period_ns = round(1e9 / rate_hz)
        self.next_ns: int | None = None

    def due(self, now_ns: int) -> bool:
        if self.next_ns is not None and now_ns < self.next_ns:
            return False
        if self.next_ns is None or now_ns - self.next_ns >= self.period_ns:
            self.next_ns = now_ns + self.period_ns
        else:
            self.next_ns += self.period_ns
        return True


def timeline(records: Iterable[Any], core: ViewCore, rate_hz: float = DEFAULT_RATE_HZ) -> Iterator[Output]:
    """The view's output for a recording, in log-time order (``records``: ``Recorded``,
    sorted by log time). Frames fall on a fixed grid from the first message at
    ``rate_hz``, each from the messages logged up to it, as the live view would."""
    clock = SceneClock(rate_hz)
    t_next: int | None = None
    last = 0
    for record in records:
        t = record.log_time_ns
        if t_next is None:
            yield core.description(t)
            t_next = t
        while t_next <= t:
            if clock.due(t_next):
                yield from encode_frame(core.frame(t_next))
            t_next += clock.period_ns
        core.apply(record.message)
        last = t
    if t_next is not None and clock.due(max(t_next, last)):
        yield from encode_frame(core.frame(max(t_next, last)))


def index_at(times: list[int], t_ns: int) -> int:
    """How many of the sorted ``times`` are at or before ``t_ns``."""
    return bisect.bisect_right(times, t_ns)
