"""The physics world's MuJoCo model, generated from the robot description (MJCF text, compiled once).

What goes in
------------
- **The arm**: one MuJoCo body per movable joint of the URDF (as pinocchio
  reads it: fixed links merged into their joint's body, their inertias
  included), placed by the URDF's joint placements, with the URDF's
  inertias, joint ranges and effort limits. The MuJoCo world frame is the
  description's ``base_frame`` (every position this world takes or gives is
  in the frame :class:`nwr.common.robot.RobotModel` uses).
- **Collision shapes**: the URDF has none. Each link gets capsules (or
  cylinders) between the points where its joint axes cross its housing
  (:class:`LinkShape`, in the link's own frame). The UR10e's are packaged
  here (:data:`PACKAGED_SHAPES`, from its outline drawing, the same sizes the
  skin file's pad points assume: housings of radius 0.075 m at the
  shoulder, 0.06 m at the elbow and on both tubes, 0.045 m at the wrists;
  the upper-arm tube 0.176 m and the forearm tube 0.04 m out along their
  joint axes; every pad 0.03 m of air cushion above its housing). A robot
  without packaged shapes gets capsules between consecutive joint origins
  (the kinematic skeleton) of one radius.
- **The pads' cushions**: one box per pad on its link, its outer face on the
  pad's surface point, square to the pad's outward normal, ``thickness``
  deep. The skin covers the whole arm (the paper: ten pads "cover the whole
  surface of the robot"), so every arm geom, cushion or housing, has the
  skin's soft contact (``solref``/``solimp``: it yields like the pads' air),
  and its priority makes that softness the one a contact with it uses.
- **The joint controller**: per joint a position servo and a velocity servo
  (MuJoCo's ``position`` and ``velocity`` actuators, together ``kp (q_c -
  q) + kv (dq_c - dq)``), the arm's weight compensated through the
  actuators (``gravcomp`` / ``actuatorgravcomp``), their sum clipped at the
  joint's effort limit (``actuatorfrcrange``), a rotor inertia
  (``armature``) on every joint: a stiff position-controlled arm like a
  UR's, whose joints still yield to a push in proportion to ``1 / kp``.
- **People**: a fixed number of slots per kind of body part, each a body on
  three slide joints (a body part keeps its orientation; the spring-damper
  that moves it acts on its position), parked far away with contacts off
  until a body part takes it. Arm geoms collide with people's geoms only:
  never with each other (the arm's self-collision is the bridge's concern,
  not the skin's) and people never with people.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import msgspec
import numpy as np
import pinocchio as pin

from nwr.common.errors import ConfigError
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.section import Section
from nwr.services.worlds.people import KINDS

# Contact filtering (MuJoCo: two geoms collide if either's contype shares a bit with the other's conaffinity).
ARM_CONTYPE, ARM_CONAFFINITY = 1, 0
PERSON_CONTYPE, PERSON_CONAFFINITY = 0, 1
# The cushion's impedance (MuJoCo solimp): 0.9 at first touch, 0.95 from 1 mm of yield on. With the default
# solref (20 ms, critically damped) a finger sinks about 0.5 mm into it under 15 N, as the pad's air would
# let it (see nwr.services.worlds.physics).
CUSHION_SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)
# Where free slots wait: far below the floor, a metre apart.
PARK_Z = -20.0


class LinkShape(Section):
    """One collision shape of the arm, in the frame of the URDF link ``link``."""

    # The URDF link the shape moves with (the root link: fixed to the base).
    link: str
    # The segment's ends (m), in the link's frame.
    start_m: Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]
    end_m: Annotated[list[float], msgspec.Meta(min_length=3, max_length=3)]
    # Its radius (m).
    radius_m: Annotated[float, msgspec.Meta(gt=0, le=0.5)]
    # Capsule: a segment swept by a sphere; cylinder: a flat-ended cylinder.
    kind: Literal["capsule", "cylinder"] = "capsule"


def _shape(link: str, start: tuple[float, float, float], end: tuple[float, float, float], radius: float,
           kind: Literal["capsule", "cylinder"] = "capsule") -> LinkShape:
    return LinkShape(link=link, kind=kind, start_m=list(start), end_m=list(end), radius_m=radius)


#: The UR10e's housings and tubes (see the module docstring), in its URDF's link frames.
PACKAGED_SHAPES: dict[str, tuple[LinkShape, ...]] = {
    "ur10e": (
        # The base: a 0.19 m drum under the shoulder.
        _shape("base_link", (0.0, 0.0, 0.0), (0.0, 0.0, 0.1), 0.095, "cylinder"),
        # Shoulder: the pan drive under the lift axis, the lift drive along -y (toward the upper arm); its lid
        # on +y carries the shoulder_back pad.
        _shape("shoulder_link", (0.0, 0.0, -0.08), (0.0, 0.0, 0.0), 0.075),
        _shape("shoulder_link", (0.0, 0.005, 0.0), (0.0, -0.10, 0.0), 0.075),
        # Upper arm: the shoulder-end housing along the lift axis (+z, to the shoulder_outer pad), the tube
        # 0.176 m out along it, the elbow-end housing along the elbow axis (to the elbow_outer pad).
        _shape("upper_arm_link", (0.0, 0.0, 0.0), (0.0, 0.0, 0.161), 0.075),
        _shape("upper_arm_link", (0.0, 0.0, 0.176), (-0.6127, 0.0, 0.176), 0.06),
        _shape("upper_arm_link", (-0.6127, 0.0, 0.02), (-0.6127, 0.0, 0.176), 0.06),
        # Forearm: the tube 0.04 m out along the elbow axis, to wrist 1.
        _shape("forearm_link", (0.0, 0.0, 0.04), (-0.57155, 0.0, 0.04), 0.06),
        # Wrist 1: its drive along its axis (down to the forearm tube), then toward wrist 2 (-y).
        _shape("wrist_1_link", (0.0, 0.0, -0.134), (0.0, 0.0, 0.0), 0.045),
        _shape("wrist_1_link", (0.0, 0.0, 0.0), (0.0, -0.075, 0.0), 0.045),
        # Wrist 2: its drive along its axis, then toward wrist 3 (+y).
        _shape("wrist_2_link", (0.0, 0.0, -0.045), (0.0, 0.0, 0.0), 0.045),
        _shape("wrist_2_link", (0.0, 0.0, 0.0), (0.0, 0.07, 0.0), 0.045),
        # Wrist 3: the flange ring, up to the flange face (z = 0).
        _shape("wrist_3_link", (0.0, 0.0, -0.047), (0.0, 0.0, 0.0), 0.045, "cylinder"),
    ),
}


@dataclass(frozen=True)
class ModelParams:
    """What the model needs besides the robot description (the world's settings, resolved)."""

    timestep_s: float
    shapes: tuple[LinkShape, ...]
    skeleton_radius_m: float
    armature_kg_m2: float
    servo_error_rad: float
    servo_damping_s: float
    cushion_thickness_m: float
    cushion_half_width_m: float
    cushion_solref: tuple[float, float]
    cushion_solimp: tuple[float, float, float, float, float]
    friction: float
    slots: dict[str, int]  # kind -> number of slots


@dataclass(frozen=True)
class Layout:
    """Names in the compiled model, in the order the world indexes them."""

    joints: tuple[str, ...]  # the arm's joints, description order
    arm_geoms: tuple[str, ...]  # every collision shape of the arm
    pad_geoms: tuple[str, ...]  # one cushion per pad, pad id order
    slots: tuple[tuple[str, str], ...]  # (slot body name, kind), slot order
    kp: np.ndarray  # the position servo's gain per joint, N m / rad
    kv: np.ndarray  # the velocity servo's gain per joint, N m s / rad
    effort: np.ndarray  # the effort limit per joint, N m


def _f(x: float) -> str:
    return repr(float(x))  # shortest exact text of a double: the compiled model is the description's, bit for bit


def _v(values: Sequence[float] | np.ndarray) -> str:
    return " ".join(_f(v) for v in np.asarray(values, dtype=float).ravel())


def _quat(rotation: np.ndarray) -> str:
    x, y, z, w = pin.Quaternion(np.asarray(rotation, dtype=float)).coeffs()
    return _v((w, x, y, z))


def rotation_with_z(z: np.ndarray, x_hint: np.ndarray | None = None) -> np.ndarray:
    """A rotation matrix whose third column is the unit vector ``z`` (its first as close to ``x_hint`` as allowed,
    else a fixed choice), deterministic."""
    z = np.asarray(z, dtype=float)
    z = z / np.linalg.norm(z)
    hint = np.asarray(x_hint, dtype=float) if x_hint is not None else None
    if hint is None or np.linalg.norm(np.cross(z, hint)) < 1e-6:
        hint = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = hint - z * float(hint @ z)
    x /= np.linalg.norm(x)
    return np.column_stack((x, np.cross(z, x), z))


def _axis(joint: Any) -> tuple[str, np.ndarray]:
    """MuJoCo joint type and axis of a pinocchio joint model, or ConfigError."""
    name = joint.shortname()
    fixed: dict[str, tuple[str, tuple[float, float, float]]] = {
        "JointModelRX": ("hinge", (1.0, 0.0, 0.0)), "JointModelRY": ("hinge", (0.0, 1.0, 0.0)),
        "JointModelRZ": ("hinge", (0.0, 0.0, 1.0)), "JointModelPX": ("slide", (1.0, 0.0, 0.0)),
        "JointModelPY": ("slide", (0.0, 1.0, 0.0)), "JointModelPZ": ("slide", (0.0, 0.0, 1.0))}
    if name in fixed:
        kind, axis = fixed[name]
        return kind, np.array(axis)
    if name in ("JointModelRevoluteUnaligned", "JointModelPrismaticUnaligned"):
        return ("hinge" if "Revolute" in name else "slide"), np.array(joint.extract().axis, dtype=float)
    raise ConfigError(f"joint type {name} has no MuJoCo counterpart here; expected revolute or prismatic joints")


def _skeleton(model: pin.Model, radius: float) -> tuple[LinkShape, ...]:
    """Capsules from each joint's origin to each child joint's origin (the kinematic skeleton), on the parent's
    link (the root link for the first joint); joints that share an origin add none."""
    link_of_joint: dict[int, str] = {}
    for frame in model.frames:
        if frame.type == pin.FrameType.BODY:
            link_of_joint.setdefault(frame.parentJoint, frame.name)
    out = []
    for child in range(1, model.njoints):
        end = np.asarray(model.jointPlacements[child].translation, dtype=float)
        if float(np.linalg.norm(end)) > 1e-6:
            out.append(_shape(link_of_joint[model.parents[child]], (0.0, 0.0, 0.0),
                              (float(end[0]), float(end[1]), float(end[2])), radius))
    return tuple(out)


def build(desc: RobotDescription, params: ModelParams) -> tuple[str, Layout]:
    """The MJCF text of the world and the names the world indexes; ConfigError for what cannot be built."""
    robot = RobotModel(desc)
    model = robot.model
    frames = {f.name: f for f in model.frames if f.type == pin.FrameType.BODY}
    shapes = params.shapes or PACKAGED_SHAPES.get(desc.name) or _skeleton(model, params.skeleton_radius_m)

    # Everything that moves with joint j, in joint j's frame: shapes, then pads.
    geoms: dict[int, list[str]] = {j: [] for j in range(model.njoints)}
    arm_geoms: list[str] = []
    for index, shape in enumerate(shapes):
        frame = frames.get(shape.link)
        if frame is None:
            raise ConfigError(f"physics world: shape #{index + 1} is on link {shape.link!r}, which "
                              f"{desc.urdf_path.name} does not have; expected one of {', '.join(sorted(frames))}")
        a = frame.placement.act(np.array(shape.start_m, dtype=float))
        b = frame.placement.act(np.array(shape.end_m, dtype=float))
        if shape.kind == "cylinder" and float(np.linalg.norm(b - a)) < 1e-9:
            raise ConfigError(f"physics world: cylinder #{index + 1} on {shape.link!r} has no length")
        name = f"shape{index}_{shape.link}"
        arm_geoms.append(name)
        geoms[frame.parentJoint].append(
            f'<geom name="{name}" class="arm" type="{shape.kind}" fromto="{_v(a)} {_v(b)}" '
            f'size="{_f(shape.radius_m)}"/>')
    pad_geoms: list[str] = []
    half = params.cushion_thickness_m / 2.0
    for pad in desc.pads:
        frame = frames[pad.link]
        rotation = frame.placement.rotation @ rotation_with_z(pad.normal)
        centre = frame.placement.act(np.array(pad.point, dtype=float)) - rotation[:, 2] * half
        name = f"pad{pad.id}_{pad.name}"
        pad_geoms.append(name)
        geoms[frame.parentJoint].append(
            f'<geom name="{name}" class="arm" type="box" pos="{_v(centre)}" quat="{_quat(rotation)}" '
            f'size="{_f(params.cushion_half_width_m)} {_f(params.cushion_half_width_m)} {_f(half)}"/>')

    kp = np.empty(len(desc.joints))
    kv = np.empty(len(desc.joints))
    effort = np.empty(len(desc.joints))
    bodies: dict[int, list[str]] = {j: [] for j in range(model.njoints)}
    for j in range(model.njoints - 1, 0, -1):  # children first, so each body's text holds its subtree
        kind, axis = _axis(model.joints[j])
        i = model.joints[j].idx_v
        limit = float(model.effortLimit[i])
        if not (math.isfinite(limit) and limit > 0.0):
            raise ConfigError(f"{desc.urdf_path}: joint {model.names[j]!r} has effort limit {limit}; "
                              "the physics world's servos need a finite limit > 0")
        effort[i] = limit
        kp[i] = limit / params.servo_error_rad
        kv[i] = kp[i] * params.servo_damping_s
        inertia = model.inertias[j]
        full = np.asarray(inertia.inertia, dtype=float)
        placement = model.jointPlacements[j]
        name = model.names[j]
        text = (
            f'<body name="{name}" pos="{_v(placement.translation)}" quat="{_quat(placement.rotation)}" gravcomp="1">'
            f'<inertial pos="{_v(inertia.lever)}" mass="{_f(inertia.mass)}" '
            f'fullinertia="{_v((full[0, 0], full[1, 1], full[2, 2], full[0, 1], full[0, 2], full[1, 2]))}"/>'
            f'<joint name="{name}" type="{kind}" axis="{_v(axis)}" range="{_f(desc.q_min[i])} {_f(desc.q_max[i])}" '
            f'armature="{_f(params.armature_kg_m2)}" actuatorfrcrange="{_f(-limit)} {_f(limit)}" '
            f'actuatorgravcomp="true"/>'
            + "".join(geoms[j]) + "".join(bodies[j]) + "</body>"
        )
        bodies[model.parents[j]].insert(0, text)
    names = [model.names[j] for j in range(1, model.njoints)]
    # Position servos first, then velocity servos: ctrl[:n] is q_c, ctrl[n:] dq_c.
    actuators = [f'<position name="{n}_position" joint="{n}" kp="{_f(kp[i])}" '
                 f'ctrlrange="{_f(desc.q_min[i])} {_f(desc.q_max[i])}"/>' for i, n in enumerate(names)]
    actuators += [f'<velocity name="{n}_velocity" joint="{n}" kv="{_f(kv[i])}" '
                  f'ctrlrange="{_f(-desc.v_max[i])} {_f(desc.v_max[i])}"/>' for i, n in enumerate(names)]

    # The base frame is the MuJoCo world: the URDF root sits at the base frame's inverse.
    base = model.frames[model.getFrameId(desc.base_frame)].placement.inverse()
    root = (f'<body name="robot" pos="{_v(base.translation)}" quat="{_quat(base.rotation)}">'
            + "".join(geoms[0]) + "".join(bodies[0]) + "</body>")

    slots: list[tuple[str, str]] = []
    people: list[str] = []
    for kind, count in params.slots.items():
        spec = KINDS[kind]
        size = _v(spec.size)
        for k in range(count):
            name = f"{kind}{k}"
            slots.append((name, kind))
            park = _v((float(len(slots)), 0.0, PARK_Z))
            people.append(
                f'<body name="{name}" pos="{park}" gravcomp="1">'
                + "".join(f'<joint name="{name}_{a}" type="slide" axis="{axis}"/>'
                          for a, axis in (("x", "1 0 0"), ("y", "0 1 0"), ("z", "0 0 1")))
                + f'<geom name="{name}" class="person" type="{spec.geom}" size="{size}" mass="{_f(spec.mass_kg)}"/>'
                + "</body>")

    solref = _v(params.cushion_solref)
    solimp = _v(params.cushion_solimp)
    xml = f"""<mujoco model="nwr-physics-{desc.name}">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{_f(params.timestep_s)}" integrator="implicitfast" cone="pyramidal"/>
  <default>
    <default class="arm">
      <geom contype="{ARM_CONTYPE}" conaffinity="{ARM_CONAFFINITY}" priority="1" solref="{solref}"
            solimp="{solimp}" friction="{_f(params.friction)} 0.005 0.0001"/>
    </default>
    <default class="person">
      <geom contype="0" conaffinity="0" friction="{_f(params.friction)} 0.005 0.0001"/>
    </default>
  </default>
  <worldbody>
    {root}
    {"".join(people)}
  </worldbody>
  <actuator>
    {"".join(actuators)}
  </actuator>
</mujoco>
"""
    for array in (kp, kv, effort):
        array.flags.writeable = False
    return xml, Layout(joints=tuple(desc.joints), arm_geoms=tuple(arm_geoms), pad_geoms=tuple(pad_geoms),
                       slots=tuple(slots), kp=kp, kv=kv, effort=effort)
