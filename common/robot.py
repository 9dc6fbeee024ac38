"""Robot description (URDF + TOML) and pure forward kinematics.

This module only reads files and computes: no network, no clock, no global state.

Frames
------
* The URDF root link (``base_link`` for the UR10e) is pinocchio's *universe* frame.
* Everything :class:`RobotModel` returns "in the base frame" (positions, normals,
  4x4 poses, Jacobians) is expressed in ``RobotDescription.base_frame``, a frame
  named in ``robot.toml`` that must be rigidly attached to the URDF root.  For the
  packaged UR10e it is ``base_link`` (ROS convention: the UR controller's DH base
  turned by pi about z, so at q = 0 the arm points along +x).  Choosing ``base``
  instead gives the coordinates shown on the UR pendant.
* Each skin pad gets an extra pinocchio frame ``pad_<name>`` rigidly attached to
  its link: origin at the pad's surface point, z axis along its outward normal.
  Pad Jacobians are the Jacobians of these frames' origins.
* Joint vectors ``q`` are in radians, in the order of ``RobotDescription.joints``,
  which is also the URDF chain order (pinocchio's q order).

:class:`RobotModel` keeps one pinocchio ``Data`` and caches the last
configuration, so it is cheap to call several accessors for the same ``q`` but it
is not thread-safe: give each thread its own instance.

Bounds that hold in every configuration
---------------------------------------
:class:`ChainBounds` (``RobotModel.bounds``) bounds, without kinematics, how
fast the speed-limited points and the centres of mass can move, how fast
their Jacobians change with ``q``, and the power of a motion: from the norms
of the URDF's fixed placements (the triangle inequality; rotations keep
norms). The bridge's Cartesian limiter uses them to skip the exact
computation in the cycles where they prove it cannot bind.
"""

from __future__ import annotations

import logging
import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from nwr.common.errors import ConfigError

log = logging.getLogger(__name__)

REGIONS: tuple[str, ...] = ("shoulder", "upper_arm", "elbow", "forearm", "wrist")
# The paper's joint groups of its joint-space reflexes (Table II's columns): every joint of a robot belongs to one
# (robot.toml's reflex_group); a joint's location weight is its group's.
JOINT_GROUPS: tuple[str, ...] = ("base", "shoulder", "elbow", "wrist")

#: The description shipped with the package.
# The packaged robots, one folder each (robots/<name>/robot.toml, its URDF and its skin file): a profile names one
# by its folder's name (robot.description = "ur10e"), or any robot.toml by its path. Adding a robot is adding a
# folder.
ROBOTS_DIR: Path = Path(__file__).resolve().parent / "robots"
DEFAULT_DESCRIPTION: Path = ROBOTS_DIR / "ur10e" / "robot.toml"


def packaged_robots() -> list[str]:
    """The names of the packaged robots (the folders of robots/ with a robot.toml)."""
    return sorted(folder.name for folder in ROBOTS_DIR.iterdir() if (folder / "robot.toml").is_file())


def resolve_description(name_or_path: str | Path | None) -> Path:
    """The robot.toml a profile's ``robot.description`` names: empty, the packaged UR10e; a packaged robot's
    name (a folder of robots/); else a path. ConfigError for a name that is no packaged robot."""
    if not name_or_path:
        return DEFAULT_DESCRIPTION
    text = str(name_or_path)
    if "/" in text or text.endswith(".toml") or Path(text).exists():
        return Path(text)
    if text not in packaged_robots():
        raise ConfigError(f"robot.description = {text!r} is no packaged robot ({', '.join(packaged_robots())}) "
                          "and no path: give a robot's name or the path of its robot.toml")
    return ROBOTS_DIR / text / "robot.toml"

# A normal whose length is off by more than this is a typo, not rounding.
_UNIT_TOLERANCE = 1e-6
# Pad names end up in frame names and, elsewhere, in Zenoh key expressions,
# where '/', '*', '$', '?' and '#' have meanings of their own.
_NAME_PATTERN = re.compile(r"^[A-Za-z0-9_-]+$")

_ROBOT_KEYS: frozenset[str] = frozenset(
    {"name", "urdf", "skin", "base_frame", "tool_frame", "joints", "max_acceleration", "max_jerk", "home",
     "reflex_direction"}
)
_OPTIONAL_ROBOT_KEYS: frozenset[str] = frozenset(
    {"elbow_frame", "max_point_speed", "reflex_range_deg", "reflex_group", "location", "task", "figure_pads"})
_TASK_KEYS: frozenset[str] = frozenset({"amplitude_rad", "double_frequency"})
_LEVELS: tuple[str, ...] = ("pl3", "pl4")
_PAD_KEYS: frozenset[str] = frozenset({"id", "name", "region", "link", "point", "normal"})


@dataclass(frozen=True, eq=False)
class Pad:
    """One skin pad, fixed to ``link``.

    ``point`` (m) is a point on the pad surface and ``normal`` its outward unit
    normal, both expressed in the frame of ``link``.  ``eq=False`` because the
    numpy fields make field-wise ``==`` ambiguous; pads compare by identity.
    """

    id: int
    name: str
    region: str
    link: str
    point: np.ndarray
    normal: np.ndarray


@dataclass(frozen=True, eq=False)
class RobotDescription:
    """Everything the pipeline needs to know about one robot, validated.

    Arrays have one entry per joint, in ``joints`` order, and are read-only:
    ``q_min``/``q_max`` (rad) and ``v_max`` (rad/s) come from the URDF,
    ``a_max`` (rad/s^2), ``j_max`` (rad/s^3), ``home`` (rad) and
    ``reflex_direction`` (+1/-1 per joint: the sign that makes a positive
    joint-space reflex displacement a withdrawal) from robot.toml.
    ``pads`` is sorted by id, and ids are 0..n-1, so ``pads[i].id == i``.
    """

    name: str
    urdf_path: Path
    skin_path: Path
    base_frame: str
    tool_frame: str
    joints: tuple[str, ...]
    q_min: np.ndarray
    q_max: np.ndarray
    v_max: np.ndarray
    a_max: np.ndarray
    j_max: np.ndarray
    home: np.ndarray
    pads: tuple[Pad, ...]
    reflex_direction: np.ndarray
    elbow_frame: str | None = None  # the frame whose origin is the elbow (a speed-limited point), if named
    max_point_speed: float = 1.0  # m/s: the fastest any point of the arm moves (a Cartesian limit never exceeds it)
    # The joint-space reflexes' range q_max per joint, degrees (planner.q_max_deg when the profile gives none).
    reflex_range_deg: tuple[float, ...] = ()
    # Per joint, the index in JOINT_GROUPS of the location weight it takes.
    reflex_group: tuple[int, ...] = ()
    # The location reflex's weight table: "pl3"/"pl4" -> region -> [w_base, w_shoulder, w_elbow, w_wrist]
    # (planner.location when the profile gives none).
    location: dict[str, dict[str, list[float]]] | None = None
    # The task's figure-eight around home (planner.task.amplitude_rad / double_frequency when the profile gives
    # none), one per joint.
    task_amplitude_rad: tuple[float, ...] = ()
    task_double_frequency: tuple[int, ...] = ()
    # Three pads on three regions that the figures and the benchmark touch, by name.
    figure_pads: tuple[str, ...] = ()

    def joint_weights(self, weights: list[float]) -> np.ndarray:
        """A location weight row [w_base, w_shoulder, w_elbow, w_wrist] as one weight per joint (its group's)."""
        return np.array([weights[group] for group in self.reflex_group], dtype=float)

    def pad(self, key: int | str) -> Pad:
        """Return a pad by id (int) or by name (str); raise ConfigError otherwise."""
        if isinstance(key, (int, np.integer)) and not isinstance(key, (bool, np.bool_)):
            if 0 <= key < len(self.pads):
                return self.pads[int(key)]
        elif isinstance(key, str):
            for pad in self.pads:
                if pad.name == key:
                    return pad
        names = ", ".join(p.name for p in self.pads)
        raise ConfigError(
            f"{self.skin_path}: robot {self.name!r} has no pad {key!r}; "
            f"expected an id in 0..{len(self.pads) - 1} or one of: {names}"
        )


# --------------------------------------------------------------------------- loading


def load_description(path: str | Path | None = None) -> RobotDescription:
    """Read and validate ``robot.toml``, its URDF and its skin file.

    ``path`` is the robot.toml file, or a packaged robot's name (:func:`resolve_description`); ``None`` selects
    the packaged UR10e.  The ``urdf`` and ``skin`` entries are resolved relative to robot.toml's folder.
    Any inconsistency raises :class:`ConfigError` naming the file, the field, the
    offending value and what was expected.
    """
    robot_path = resolve_description(path)
    doc = _read_toml(robot_path)
    _check_keys(doc, _ROBOT_KEYS, _ROBOT_KEYS | _OPTIONAL_ROBOT_KEYS, robot_path, "robot description")

    name = _string(doc["name"], robot_path, "name")
    urdf_path = (robot_path.parent / _string(doc["urdf"], robot_path, "urdf")).resolve()
    skin_path = (robot_path.parent / _string(doc["skin"], robot_path, "skin")).resolve()
    base_frame = _string(doc["base_frame"], robot_path, "base_frame")
    tool_frame = _string(doc["tool_frame"], robot_path, "tool_frame")
    elbow_frame = _string(doc["elbow_frame"], robot_path, "elbow_frame") if "elbow_frame" in doc else None
    max_point_speed = doc.get("max_point_speed", 1.0)
    if not (_is_number(max_point_speed) and math.isfinite(max_point_speed) and max_point_speed > 0):
        raise ConfigError(f"{robot_path}: max_point_speed = {max_point_speed!r}; expected a speed > 0 in m/s")

    model = _build_model(urdf_path, robot_path)
    urdf_joints = tuple(model.names[1:])
    joints = _joint_names(doc["joints"], urdf_joints, robot_path, urdf_path)
    for index in range(1, model.njoints):
        if model.joints[index].nq != 1:
            raise ConfigError(
                f"{urdf_path}: joint {model.names[index]!r} has {model.joints[index].nq} "
                "configuration variables; only revolute and prismatic joints are supported"
            )
    frames = {frame.name for frame in model.frames}
    links = {frame.name for frame in model.frames if frame.type == pin.FrameType.BODY}
    for field, frame_name in (("base_frame", base_frame), ("tool_frame", tool_frame), ("elbow_frame", elbow_frame)):
        if frame_name is not None and frame_name not in frames:
            raise ConfigError(
                f"{robot_path}: {field} = {frame_name!r} is not a frame of {urdf_path.name}; "
                f"expected one of its links: {', '.join(sorted(links))}"
            )

    n = len(joints)
    q_min = _readonly(model.lowerPositionLimit)
    q_max = _readonly(model.upperPositionLimit)
    v_max = _readonly(model.velocityLimit)
    for i, joint in enumerate(joints):
        if not (math.isfinite(q_min[i]) and math.isfinite(q_max[i]) and q_min[i] < q_max[i]):
            raise ConfigError(
                f"{urdf_path}: joint {joint!r} has position limits [{q_min[i]}, {q_max[i]}]; "
                "expected finite lower < upper"
            )
        if not (math.isfinite(v_max[i]) and v_max[i] > 0.0):
            raise ConfigError(
                f"{urdf_path}: joint {joint!r} has velocity limit {v_max[i]}; expected a finite value > 0"
            )

    a_max = _vector(doc["max_acceleration"], n, robot_path, "max_acceleration", positive=True)
    j_max = _vector(doc["max_jerk"], n, robot_path, "max_jerk", positive=True)
    home = _vector(doc["home"], n, robot_path, "home")
    direction = _vector(doc.get("reflex_direction", [1.0] * n), n, robot_path, "reflex_direction")
    if not np.all(np.isin(direction, (-1.0, 1.0))):
        raise ConfigError(f"{robot_path}: reflex_direction must hold +1 or -1 per joint, got {direction.tolist()}")
    outside = [i for i in range(n) if not q_min[i] <= home[i] <= q_max[i]]
    if outside:
        details = "; ".join(
            f"{joints[i]} = {home[i]} not in [{q_min[i]}, {q_max[i]}]" for i in outside
        )
        raise ConfigError(f"{robot_path}: home is outside the URDF joint limits: {details}")

    if not skin_path.is_file():
        raise ConfigError(f"{robot_path}: skin file {skin_path} does not exist")
    pads = _load_pads(skin_path, links, urdf_path)
    _check_pads_on_links(model, pads, skin_path)
    reflex_range = _vector(doc.get("reflex_range_deg", [0.0] * n), n, robot_path, "reflex_range_deg")
    if not np.all((reflex_range >= 0.0) & (reflex_range <= 180.0)):
        raise ConfigError(f"{robot_path}: reflex_range_deg = {reflex_range.tolist()}; expected 0 to 180 deg per joint")
    group = _groups(doc.get("reflex_group", list(JOINT_GROUPS[:3]) + ["wrist"] * max(0, n - 3)), n, robot_path)
    location = _location(doc["location"], robot_path, {pad.region for pad in pads}) if "location" in doc else None
    task = doc.get("task", {})
    if not isinstance(task, dict):
        raise ConfigError(f"{robot_path}: task = {task!r}; expected a table [task]")
    _check_keys(task, frozenset(), _TASK_KEYS, robot_path, "[task]")
    amplitude = _vector(task.get("amplitude_rad", [0.0] * n), n, robot_path, "task.amplitude_rad")
    double = _vector(task.get("double_frequency", [0] * n), n, robot_path, "task.double_frequency")
    if not np.all(np.isin(double, (0.0, 1.0))):
        raise ConfigError(f"{robot_path}: task.double_frequency = {double.tolist()}; expected 0 or 1 per joint")
    figure_pads = doc.get("figure_pads", [pad.name for pad in pads[:3]])
    names = {pad.name for pad in pads}
    if not isinstance(figure_pads, list) or len(figure_pads) != 3 or any(p not in names for p in figure_pads):
        raise ConfigError(f"{robot_path}: figure_pads = {figure_pads!r}; expected three of its pads' names "
                          f"({', '.join(sorted(names))})")
    log.debug("loaded robot %r: %d joints, %d pads", name, n, len(pads))
    return RobotDescription(
        name=name,
        urdf_path=urdf_path,
        skin_path=skin_path,
        base_frame=base_frame,
        tool_frame=tool_frame,
        joints=joints,
        q_min=q_min,
        q_max=q_max,
        v_max=v_max,
        a_max=a_max,
        j_max=j_max,
        home=home,
        pads=pads,
        reflex_direction=direction,
        elbow_frame=elbow_frame,
        max_point_speed=float(max_point_speed),
        reflex_range_deg=tuple(float(v) for v in reflex_range),
        reflex_group=group,
        location=location,
        task_amplitude_rad=tuple(float(v) for v in amplitude),
        task_double_frequency=tuple(int(v) for v in double),
        figure_pads=tuple(figure_pads),
    )


def _groups(value: Any, n: int, path: Path) -> tuple[int, ...]:
    if not isinstance(value, list) or len(value) != n or any(v not in JOINT_GROUPS for v in value):
        raise ConfigError(f"{path}: reflex_group = {value!r}; expected one of {', '.join(JOINT_GROUPS)} per joint "
                          f"({n} joints)")
    return tuple(JOINT_GROUPS.index(v) for v in value)


def _location(value: Any, path: Path, regions: set[str]) -> dict[str, dict[str, list[float]]]:
    """The location reflex's table [location.pl3] / [location.pl4]: a row of four weights in [0, 1] per body
    region, every region of the skin's pads with its row."""
    if not isinstance(value, dict):
        raise ConfigError(f"{path}: location = {value!r}; expected the tables [location.pl3] and [location.pl4]")
    _check_keys(value, frozenset(_LEVELS), frozenset(_LEVELS), path, "[location]")
    table: dict[str, dict[str, list[float]]] = {}
    for level in _LEVELS:
        rows = value[level]
        if not isinstance(rows, dict):
            raise ConfigError(f"{path}: location.{level} = {rows!r}; expected a table of body regions")
        unknown = sorted(set(rows) - set(REGIONS))
        missing = sorted(regions - set(rows))
        if unknown or missing:
            raise ConfigError(f"{path}: location.{level} has rows {sorted(rows)}; expected one per region of the "
                              f"skin's pads {sorted(regions)}, each one of {', '.join(REGIONS)}")
        table[level] = {}
        for region, row in rows.items():
            weights = _vector(row, len(JOINT_GROUPS), path, f"location.{level}.{region}")
            if not np.all((weights >= 0.0) & (weights <= 1.0)):
                raise ConfigError(f"{path}: location.{level}.{region} = {row!r}; expected four weights in [0, 1] "
                                  f"[{', '.join(JOINT_GROUPS)}]")
            table[level][region] = [float(w) for w in weights]
    return table


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as stream:
            return tomllib.load(stream)
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc}") from exc


def _build_model(urdf_path: Path, referenced_from: Path) -> pin.Model:
    if not urdf_path.is_file():
        raise ConfigError(f"{referenced_from}: urdf file {urdf_path} does not exist")
    try:
        return pin.buildModelFromUrdf(str(urdf_path))
    except (ValueError, RuntimeError) as exc:
        raise ConfigError(f"{urdf_path}: pinocchio cannot parse this URDF: {exc}") from exc


def _check_keys(
    table: dict[str, Any], required: frozenset[str], allowed: frozenset[str], path: Path, what: str
) -> None:
    missing = sorted(required - table.keys())
    if missing:
        raise ConfigError(f"{path}: {what} is missing {', '.join(missing)}")
    # Unknown keys are almost always typos ("max_accel"); silently ignoring them
    # would run the robot with a default the user thinks they changed.
    unknown = sorted(table.keys() - allowed)
    if unknown:
        raise ConfigError(
            f"{path}: {what} has unknown key(s) {', '.join(unknown)}; expected only {', '.join(sorted(allowed))}"
        )


def _string(value: Any, path: Path, field: str) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{path}: {field} = {value!r}; expected a non-empty string")
    return value


def _joint_names(value: Any, urdf_joints: tuple[str, ...], path: Path, urdf_path: Path) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f"{path}: joints = {value!r}; expected a list of joint names")
    unknown = [v for v in value if v not in urdf_joints]
    if unknown:
        raise ConfigError(
            f"{path}: joints {unknown} are not movable joints of {urdf_path.name}; "
            f"expected {list(urdf_joints)}"
        )
    # q vectors are handed to pinocchio as they are, so the order must be the URDF's.
    if tuple(value) != urdf_joints:
        raise ConfigError(
            f"{path}: joints = {value}; expected every movable joint of {urdf_path.name} "
            f"in chain order: {list(urdf_joints)}"
        )
    return tuple(value)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _vector(value: Any, n: int, path: Path, field: str, *, positive: bool = False) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n or not all(_is_number(v) for v in value):
        raise ConfigError(f"{path}: {field} = {value!r}; expected a list of {n} numbers")
    out = np.array(value, dtype=float)
    if not np.all(np.isfinite(out)):
        raise ConfigError(f"{path}: {field} = {value!r}; expected finite numbers")
    if positive and not np.all(out > 0.0):
        raise ConfigError(f"{path}: {field} = {value!r}; expected numbers > 0")
    return _readonly(out)


def _readonly(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=float)  # copy: never alias pinocchio's or the caller's memory
    out.flags.writeable = False
    return out


def _load_pads(skin_path: Path, links: set[str], urdf_path: Path) -> tuple[Pad, ...]:
    doc = _read_toml(skin_path)
    _check_keys(doc, frozenset({"pad"}), frozenset({"pad"}), skin_path, "skin description")
    tables = doc["pad"]
    if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
        raise ConfigError(f"{skin_path}: expected one or more [[pad]] tables")

    pads: list[Pad] = []
    for index, table in enumerate(tables):
        where = f"[[pad]] #{index + 1}"
        if "name" in table:
            where += f" ({table['name']!r})"
        _check_keys(table, _PAD_KEYS, _PAD_KEYS, skin_path, where)
        pad_id = table["id"]
        if not isinstance(pad_id, int) or isinstance(pad_id, bool):
            raise ConfigError(f"{skin_path}: {where}: id = {pad_id!r}; expected an integer")
        name = _string(table["name"], skin_path, f"{where}: name")
        if not _NAME_PATTERN.match(name):
            raise ConfigError(
                f"{skin_path}: {where}: name = {name!r}; expected letters, digits, '_' or '-' only"
            )
        region = table["region"]
        if region not in REGIONS:
            raise ConfigError(
                f"{skin_path}: {where}: region = {region!r}; expected one of {', '.join(REGIONS)}"
            )
        link = table["link"]
        if link not in links:
            raise ConfigError(
                f"{skin_path}: {where}: link = {link!r} is not a link of {urdf_path.name}; "
                f"expected one of {', '.join(sorted(links))}"
            )
        point = _vector(table["point"], 3, skin_path, f"{where}: point")
        normal = np.array(_vector(table["normal"], 3, skin_path, f"{where}: normal"))
        length = float(np.linalg.norm(normal))
        if abs(length - 1.0) > _UNIT_TOLERANCE:
            raise ConfigError(
                f"{skin_path}: {where}: normal = {table['normal']!r} has length {length:.9g}; "
                f"expected a unit vector (length 1 within {_UNIT_TOLERANCE:g})"
            )
        pads.append(
            Pad(id=pad_id, name=name, region=region, link=link, point=point, normal=_readonly(normal / length))
        )

    for attribute in ("id", "name"):
        first: dict[Any, int] = {}
        for index, pad in enumerate(pads):
            value = getattr(pad, attribute)
            if value in first:
                raise ConfigError(
                    f"{skin_path}: pad {attribute} {value!r} is used by more than one [[pad]] "
                    f"(#{first[value] + 1} and #{index + 1}); expected unique {attribute}s"
                )
            first[value] = index
    ids = sorted(pad.id for pad in pads)
    if ids != list(range(len(pads))):
        raise ConfigError(
            f"{skin_path}: pad ids are {ids}; expected exactly 0..{len(pads) - 1} "
            "(ids index arrays of pad readings)"
        )
    return tuple(sorted(pads, key=lambda pad: pad.id))


# A pad's point is on its link's body: within this distance of the link's skeleton (the segments from the
# link's origin to the joints and links it carries). The UR10e's farthest pad (elbow_outer, on the elbow
# housing's lid) is 0.266 m off its link's skeleton: past 0.3 m a point is on another link or a typo.
MAX_PAD_OFFSET_M = 0.3


def _segment_distance(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    length2 = float(ab @ ab)
    t = 0.0 if length2 == 0.0 else min(1.0, max(0.0, float((point - a) @ ab) / length2))
    return float(np.linalg.norm(point - (a + t * ab)))


def link_offset(model: pin.Model, link: str, point: np.ndarray) -> float:
    """How far ``point`` (m, in the frame of ``link``) is from the link's skeleton: the segments from the
    link's origin to the joints it carries and the links fixed to it."""
    frame = model.frames[model.getFrameId(link)]
    joint = frame.parentJoint
    # In the frame of the joint that moves the link: the link's origin, the joints it carries and the
    # links fixed to it.
    ends = [model.jointPlacements[child].translation for child in range(1, model.njoints)
            if model.parents[child] == joint]
    ends += [other.placement.translation for other in model.frames
             if other.parentJoint == joint and other.type == pin.FrameType.BODY]
    origin = frame.placement.translation
    at = frame.placement.act(np.asarray(point, dtype=float))
    return min([_segment_distance(at, origin, end) for end in ends], default=float(np.linalg.norm(at - origin)))


def _check_pads_on_links(model: pin.Model, pads: tuple[Pad, ...], skin_path: Path) -> None:
    """Every pad's point within :data:`MAX_PAD_OFFSET_M` of its link's skeleton; else ConfigError naming it."""
    for pad in pads:
        offset = link_offset(model, pad.link, pad.point)
        if offset > MAX_PAD_OFFSET_M:
            raise ConfigError(
                f"{skin_path}: pad {pad.name!r}: point = {pad.point.tolist()} is {offset:.3f} m from link "
                f"{pad.link!r} (its origin and the joints it carries); expected at most {MAX_PAD_OFFSET_M} m: "
                "is the point in the frame of another link, or in mm?"
            )


# --------------------------------------------------------------------------- kinematics


def _rotation_with_z(z: np.ndarray) -> np.ndarray:
    """A rotation matrix whose third column is the unit vector ``z``."""
    # Cross with the world axis least aligned with z so the result is well conditioned.
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(z)))] = 1.0
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack((x, y, z))


_REVOLUTE: frozenset[str] = frozenset(
    {"JointModelRX", "JointModelRY", "JointModelRZ", "JointModelRevoluteUnaligned"})
_PRISMATIC: frozenset[str] = frozenset(
    {"JointModelPX", "JointModelPY", "JointModelPZ", "JointModelPrismaticUnaligned"})


@dataclass(frozen=True, eq=False)
class ChainBounds:
    """Configuration-independent bounds on the motion of points fixed to the arm's links (see below).

    For a chain of revolute and prismatic joints, column ``i`` of a point
    ``p``'s linear Jacobian is ``z_i x (p - o_i)`` for a revolute joint ``i``
    upstream of ``p`` (axis ``z_i``, a unit vector, through its origin
    ``o_i``), ``z_i`` for a prismatic one, and zero for a joint not upstream
    of ``p``. ``p - o_i`` is a sum of fixed vectors each turned by some
    rotation (the placements between ``o_i`` and ``p``) and of prismatic
    travels ``q_k z_k``; by the triangle inequality its norm is at most
    ``reach[p, i]``, the sum of those placements' norms and of the travels'
    bounds ``max(|q_min_k|, |q_max_k|)``. So, wherever the prismatic joints are
    within their limits (no bound on their travel otherwise), every
    configuration ``q`` and velocity ``dq``:

    - ``|J_p(q) dq| <= reach[p] . |dq|`` (``reach[p, i]`` is 1 for a prismatic ``i``);
    - ``|d/dq_k (J_p(q) dq)| <= sum_i |dq_i| bend[p, i, k]``, hence, along the
      segment between two such configurations,
      ``|J_p(q) dq - J_p(q0) dq| <= |dq| . bend[p] . |q - q0|``. Turning about an
      upstream joint ``k`` (or ``k = i``) turns column ``i`` (or moves ``p``
      about ``z_i``): at most ``reach[p, i]``; turning about a downstream ``k``
      moves ``p`` at most ``reach[p, k]`` across the fixed ``z_i``; a prismatic
      ``k`` downstream of a revolute ``i``, or a revolute ``k`` upstream of a
      prismatic ``i``, at most 1; a prismatic ``k`` turns nothing (0);
    - the power of a motion (``RobotModel.motion_power``, the rate of change of
      the kinetic energy: sum over the links of ``m v_c . a_c + w . I a_w``, the
      gyroscopic term being orthogonal to ``w``) is at most
      ``|dq| . power_rate . |ddq| + power_cubic(|dq|, |dq|, |dq|)``: ``|v_c|``
      and ``|a_c| <= J_c ddq + |dq| . bend . |dq|`` as above, ``|w| <=`` the
      sum of the upstream revolute joints' ``|dq_i|``, ``|a_w| <=`` that of
      their ``|ddq_i|`` plus ``|dq_i|`` times the turn of their axes (the sum of
      the ``|dq_k|`` upstream of ``i``), ``|I w| <= `` its largest principal
      moment times ``|w|``; the joints' armature is counted as a diagonal
      ``power_rate``.

    Rows of ``speed_*`` follow :attr:`RobotModel.speed_points`, rows of ``com_*``
    :attr:`RobotModel.link_masses`. ``gravity[i]``: the gravity torque's bound
    at joint ``i`` (the magnitude of the terms the exact power subtracts).
    ``travel``: the prismatic joints whose travel the bounds count, with
    ``travel_min``/``travel_max`` the limits it was counted within.
    """

    speed_reach: np.ndarray  # (P, n)
    speed_bend: np.ndarray  # (P, n, n)
    com_reach: np.ndarray  # (L, n)
    com_bend: np.ndarray  # (L, n, n)
    power_rate: np.ndarray  # (n, n)
    power_cubic: np.ndarray  # (n, n, n)
    gravity: np.ndarray  # (n,)
    travel: np.ndarray  # joint indices (int)
    travel_min: np.ndarray
    travel_max: np.ndarray


def _chain_bounds(model: pin.Model, speed_ids: tuple[int, ...], com_joints: tuple[int, ...]) -> ChainBounds | None:
    """:class:`ChainBounds` of a pinocchio model; None if a joint is neither revolute nor prismatic."""
    n = model.nv
    kinds: dict[int, str] = {}
    for joint in range(1, model.njoints):
        name = model.joints[joint].shortname()
        if name in _REVOLUTE:
            kinds[joint] = "R"
        elif name in _PRISMATIC:
            kinds[joint] = "P"
        else:
            return None
    column = {joint: model.joints[joint].idx_v for joint in kinds}
    travel = {joint: max(abs(model.lowerPositionLimit[model.joints[joint].idx_q]),
                         abs(model.upperPositionLimit[model.joints[joint].idx_q]))
              for joint, kind in kinds.items() if kind == "P"}

    def path(joint: int) -> list[int]:
        """The joints from ``joint`` up to the root, ``joint`` first (its upstream chain)."""
        out = []
        while joint > 0:
            out.append(joint)
            joint = model.parents[joint]
        return out

    def point(joint: int, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``reach`` (n) and ``bend`` (n, n) of the point ``offset`` in ``joint``'s frame."""
        reach = np.zeros(n)
        distance: dict[int, float] = {}
        d = float(np.linalg.norm(offset))
        chain = path(joint)
        for k in chain:  # d: from o_k (after its own motion) to the point
            distance[k] = d
            reach[column[k]] = d if kinds[k] == "R" else 1.0
            d += float(np.linalg.norm(model.jointPlacements[k].translation)) + travel.get(k, 0.0)
        bend = np.zeros((n, n))
        for position_i, i in enumerate(chain):
            for position_k, k in enumerate(chain):
                upstream = position_k >= position_i  # k upstream of i, or k = i
                if kinds[i] == "R":
                    if kinds[k] == "R":
                        value = distance[i] if upstream else distance[k]
                    else:
                        value = 0.0 if upstream else 1.0
                else:
                    value = 1.0 if kinds[k] == "R" and position_k > position_i else 0.0
                bend[column[i], column[k]] = value
        return reach, bend

    def stacked(points: list[tuple[np.ndarray, np.ndarray]], rows: int) -> tuple[np.ndarray, np.ndarray]:
        reach = np.array([r for r, _ in points]).reshape(rows, n)
        bend = np.array([b for _, b in points]).reshape(rows, n, n)
        return _readonly(reach), _readonly(bend)

    speed_reach, speed_bend = stacked(
        [point(model.frames[f].parentJoint, model.frames[f].placement.translation) for f in speed_ids], len(speed_ids))
    com_reach, com_bend = stacked([point(j, model.inertias[j].lever) for j in com_joints], len(com_joints))

    # The power: every moving body, its mass at its centre of mass and its largest principal moment there.
    rate = np.diag(np.abs(np.asarray(model.armature, dtype=float)))
    cubic = np.zeros((n, n, n))
    gravity = np.zeros(n)
    g = float(np.linalg.norm(model.gravity.linear))
    for joint in range(1, model.njoints):
        inertia = model.inertias[joint]
        mass = float(inertia.mass)
        moment = float(np.linalg.eigvalsh(np.asarray(inertia.inertia)).max(initial=0.0))
        reach, bend = point(joint, inertia.lever)
        spin = np.zeros(n)  # |w| <= spin . |dq|
        turn = np.zeros((n, n))  # |a_w| <= spin . |ddq| + |dq| . turn . |dq|
        chain = path(joint)
        for position_i, i in enumerate(chain):
            if kinds[i] == "R":
                spin[column[i]] = 1.0
                for k in chain[position_i + 1:]:
                    if kinds[k] == "R":
                        turn[column[i], column[k]] = 1.0
        rate += mass * np.outer(reach, reach) + max(moment, 0.0) * np.outer(spin, spin)
        cubic += mass * reach[:, None, None] * bend[None] + max(moment, 0.0) * spin[:, None, None] * turn[None]
        gravity += g * mass * reach
    joints = sorted(travel)
    return ChainBounds(
        speed_reach=speed_reach, speed_bend=speed_bend, com_reach=com_reach, com_bend=com_bend,
        power_rate=_readonly(rate), power_cubic=_readonly(cubic), gravity=_readonly(gravity),
        travel=np.array([column[j] for j in joints], dtype=int),
        travel_min=_readonly(np.array([-travel[j] for j in joints])),
        travel_max=_readonly(np.array([travel[j] for j in joints])),
    )


class RobotModel:
    """Forward kinematics of a :class:`RobotDescription` with pinocchio.

    The URDF is parsed once and one ``pinocchio.Data`` is reused for every call.
    All results are expressed in ``desc.base_frame`` (see the module docstring)
    and are fresh arrays the caller may keep or modify.
    """

    def __init__(self, desc: RobotDescription) -> None:
        self.desc = desc
        model = _build_model(desc.urdf_path, desc.urdf_path)
        if tuple(model.names[1:]) != desc.joints:
            raise ConfigError(
                f"{desc.urdf_path}: movable joints {list(model.names[1:])} do not match the "
                f"description's joints {list(desc.joints)}"
            )
        base_id = self._existing_frame(model, desc.base_frame, desc.urdf_path)
        if model.frames[base_id].parentJoint != 0:
            raise ConfigError(
                f"{desc.urdf_path}: base_frame {desc.base_frame!r} moves with joint "
                f"{model.names[model.frames[base_id].parentJoint]!r}; it must be fixed to the URDF root"
            )
        self._tool_id = self._existing_frame(model, desc.tool_frame, desc.urdf_path)

        pad_ids: list[int] = []
        for pad in desc.pads:
            link_id = model.getFrameId(pad.link, pin.FrameType.BODY)
            if link_id >= model.nframes:
                raise ConfigError(f"{desc.urdf_path}: pad {pad.name!r} is on unknown link {pad.link!r}")
            frame_name = f"pad_{pad.name}"
            if model.existFrame(frame_name):
                raise ConfigError(f"{desc.urdf_path}: a frame named {frame_name!r} already exists")
            link = model.frames[link_id]
            on_link = pin.SE3(_rotation_with_z(np.array(pad.normal)), np.array(pad.point))
            frame = pin.Frame(frame_name, link.parentJoint, link_id, link.placement * on_link, pin.FrameType.OP_FRAME)
            pad_ids.append(model.addFrame(frame))

        # The points a Cartesian speed limit applies to: every pad's reference
        # point, the elbow and the flange (the tool frame's origin), as a UR's
        # safety system limits the elbow's and the flange's speed.
        speed_ids = list(pad_ids)
        names = [pad.name for pad in desc.pads]
        if desc.elbow_frame is not None:
            speed_ids.append(self._existing_frame(model, desc.elbow_frame, desc.urdf_path))
            names.append("elbow")
        speed_ids.append(self._tool_id)
        names.append("flange")
        # One frame at each moving body's centre of mass, for its momentum.
        com_ids: list[int] = []
        com_joints: list[int] = []
        masses: list[float] = []
        for joint in range(1, model.njoints):
            inertia = model.inertias[joint]
            if inertia.mass > 0.0:
                parent = model.getFrameId(model.names[joint])
                com = pin.Frame(f"com_{model.names[joint]}", joint, parent, pin.SE3(np.eye(3), inertia.lever),
                                pin.FrameType.OP_FRAME)
                com_ids.append(model.addFrame(com))
                com_joints.append(joint)
                masses.append(float(inertia.mass))
        self.speed_points: tuple[str, ...] = tuple(names)
        self._speed_ids: tuple[int, ...] = tuple(speed_ids)
        self._com_ids: tuple[int, ...] = tuple(com_ids)
        self.link_masses: np.ndarray = _readonly(np.array(masses))
        # Bounds that hold in every configuration (None: a joint type they do not cover).
        self.bounds: ChainBounds | None = _chain_bounds(model, self._speed_ids, tuple(com_joints))

        self.model: pin.Model = model
        # Created after the pad and centre-of-mass frames were added, so data.oMf has room for them.
        self.data: pin.Data = model.createData()
        self._dynamics: pin.Data = model.createData()  # inverse dynamics, apart from the kinematics cache
        self.nq: int = model.nq
        self._pad_ids: tuple[int, ...] = tuple(pad_ids)
        self._frame_ids: dict[str, int] = {}
        for frame_id, frame in enumerate(model.frames):
            self._frame_ids.setdefault(frame.name, frame_id)

        # base_frame is fixed to the root, so its pose is a constant of the model.
        base = model.frames[base_id].placement
        self._base_rotation_t: np.ndarray = np.array(base.rotation).T
        self._base_translation: np.ndarray = np.array(base.translation)
        self._base_inverse: pin.SE3 = base.inverse()
        self._base_is_root: bool = bool(np.allclose(base.homogeneous, np.eye(4), rtol=0.0, atol=1e-15))

        self._q = np.zeros(self.nq)
        self._fk_valid = False
        self._jacobians_valid = False
        self._stacked: dict[tuple[int, ...], np.ndarray] = {}  # speed and COM Jacobians at self._q

    @staticmethod
    def _existing_frame(model: pin.Model, name: str, urdf_path: Path) -> int:
        if not model.existFrame(name):
            raise ConfigError(f"{urdf_path}: no frame {name!r}; the description expects one")
        return model.getFrameId(name)

    # ------------------------------------------------------------------ caching

    def _as_q(self, q: Any) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.shape != (self.nq,):
            raise ValueError(f"q has shape {q.shape}; expected ({self.nq},) joint angles in rad")
        if not np.isfinite(q).all():
            raise ValueError(f"q = {q} contains non-finite values")
        return q

    def _posed(self, q: Any) -> np.ndarray:
        """``_update(_as_q(q))``, returning the checked ``q``: the bridge asks several times per control cycle
        at one pose, and a ``q`` equal to the cached pose (finite; NaN equals nothing) needs no more checks."""
        q = np.asarray(q, dtype=float)
        if self._fk_valid and q.shape == self._q.shape and (q == self._q).all():
            return q
        q = self._as_q(q)
        self._update(q)
        return q

    def _update(self, q: np.ndarray) -> None:
        if self._fk_valid and (q == self._q).all():  # np.array_equal's test, for arrays of one shape
            return
        pin.forwardKinematics(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        self._q[:] = q  # a copy: callers may reuse and modify their q array
        self._fk_valid = True
        self._jacobians_valid = False
        self._stacked.clear()

    def fk(self, q: Any) -> None:
        """Update joint and frame placements for ``q``; a no-op if ``q`` is unchanged."""
        self._posed(q)

    # ------------------------------------------------------------------ helpers

    def _pad_frame(self, pad: int) -> int:
        if not 0 <= pad < len(self._pad_ids):
            raise IndexError(f"pad index {pad} out of range; expected 0..{len(self._pad_ids) - 1}")
        return self._pad_ids[pad]

    def _to_base(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3) from the root frame into base_frame."""
        if self._base_is_root:
            return np.array(points, dtype=float)
        return (points - self._base_translation) @ self._base_rotation_t.T

    def _rotate_to_base(self, vectors: np.ndarray) -> np.ndarray:
        """Free vectors (..., 3) from the root frame into base_frame."""
        if self._base_is_root:
            return np.array(vectors, dtype=float)
        return vectors @ self._base_rotation_t.T

    # ------------------------------------------------------------------ queries

    def frame_pose(self, q: Any, frame: str) -> np.ndarray:
        """4x4 homogeneous transform of model frame ``frame`` in base_frame.

        ``frame`` is any URDF link or joint name, or a pad frame ``pad_<name>``.
        """
        frame_id = self._frame_ids.get(frame)
        if frame_id is None:
            raise ConfigError(
                f"{self.desc.urdf_path}: no frame {frame!r}; expected one of {', '.join(self._frame_ids)}"
            )
        self._posed(q)
        return (self._base_inverse * self.data.oMf[frame_id]).homogeneous

    def tool_position(self, q: Any) -> np.ndarray:
        """Origin of the tool frame (m), shape (3,), in base_frame."""
        self._posed(q)
        return self._to_base(self.data.oMf[self._tool_id].translation)

    def pad_point(self, q: Any, pad: int) -> np.ndarray:
        """Surface point of pad ``pad`` (its id) in base_frame, shape (3,)."""
        frame_id = self._pad_frame(pad)
        self._posed(q)
        return self._to_base(self.data.oMf[frame_id].translation)

    def pad_normal(self, q: Any, pad: int) -> np.ndarray:
        """Outward unit normal of pad ``pad`` in base_frame, shape (3,)."""
        frame_id = self._pad_frame(pad)
        self._posed(q)
        return self._rotate_to_base(self.data.oMf[frame_id].rotation[:, 2])

    def pad_points(self, q: Any) -> np.ndarray:
        """All pad points in base_frame, shape (n_pads, 3), row i = pad id i."""
        self._posed(q)
        points = np.empty((len(self._pad_ids), 3))
        for row, frame_id in enumerate(self._pad_ids):
            points[row] = self.data.oMf[frame_id].translation
        return self._to_base(points)

    def pad_normals(self, q: Any) -> np.ndarray:
        """All outward pad normals in base_frame, shape (n_pads, 3), row i = pad id i."""
        self._posed(q)
        normals = np.empty((len(self._pad_ids), 3))
        for row, frame_id in enumerate(self._pad_ids):
            normals[row] = self.data.oMf[frame_id].rotation[:, 2]
        return self._rotate_to_base(normals)

    def pad_jacobian(self, q: Any, pad: int) -> np.ndarray:
        """Jacobian (6, nq) of the pad point: rows 0-2 linear velocity (m/s per rad/s),
        rows 3-5 angular velocity, both with base_frame axes (pinocchio's
        LOCAL_WORLD_ALIGNED, i.e. the velocity of the pad point itself)."""
        frame_id = self._pad_frame(pad)
        q = self._posed(q)
        if not self._jacobians_valid:
            # Also redoes forward kinematics for the same q; harmless, and then all
            # pads share one Jacobian computation per configuration.
            pin.computeJointJacobians(self.model, self.data, q)
            self._jacobians_valid = True
        jacobian = pin.getFrameJacobian(self.model, self.data, frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        if not self._base_is_root:
            jacobian[:3] = self._base_rotation_t @ jacobian[:3]
            jacobian[3:] = self._base_rotation_t @ jacobian[3:]
        return jacobian

    def _linear_jacobians(self, q: Any, frame_ids: tuple[int, ...]) -> np.ndarray:
        q = self._posed(q)
        if not self._jacobians_valid:
            pin.computeJointJacobians(self.model, self.data, q)
            self._jacobians_valid = True
        cached = self._stacked.get(frame_ids)
        if cached is not None:  # the bridge asks for them several times per control cycle, at one pose
            return cached
        out = np.empty((len(frame_ids), 3, self.nq))
        for row, frame_id in enumerate(frame_ids):
            out[row] = pin.getFrameJacobian(self.model, self.data, frame_id, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:3]
        if not self._base_is_root:
            out = np.einsum("ij,pjk->pik", self._base_rotation_t, out)
        out.setflags(write=False)
        self._stacked[frame_ids] = out
        return out

    def speed_jacobians(self, q: Any) -> np.ndarray:
        """Linear Jacobians (P, 3, nq) of the speed-limited points (:attr:`speed_points`: pads, elbow, flange):
        row p times q_dot is point p's velocity (m/s) in base_frame. Read-only, computed once per pose."""
        return self._linear_jacobians(q, self._speed_ids)

    def com_jacobians(self, q: Any) -> np.ndarray:
        """Linear Jacobians (L, 3, nq) of the moving links' centres of mass (masses in :attr:`link_masses`)."""
        return self._linear_jacobians(q, self._com_ids)

    def motion_power(self, q: Any, dq: Any, ddq: Any) -> float:
        """The power the joints put into the arm's motion at ``q``, ``dq``, ``ddq``, W.

        ``dq . (tau - g(q))`` with ``tau`` the inverse dynamics (RNEA, the
        URDF's inertias) and ``g`` its gravity part: the rate of change of the
        arm's kinetic energy (lifting against gravity is not counted; that
        energy is not in the motion). Negative while braking.
        """
        q = self._as_q(q)
        v = np.asarray(dq, dtype=float)
        a = np.asarray(ddq, dtype=float)
        data = self._dynamics
        tau = pin.rnea(self.model, data, q, v, a) - pin.computeGeneralizedGravity(self.model, data, q)
        return float(v @ tau)

    def inverse_dynamics(self, q: Any, dq: Any, ddq: Any) -> np.ndarray:
        """The joint torques that move the arm with ``dq``, ``ddq`` at ``q`` against gravity, N m (RNEA, the URDF's
        inertias)."""
        return np.array(pin.rnea(self.model, self._dynamics, self._as_q(q), np.asarray(dq, dtype=float),
                                 np.asarray(ddq, dtype=float)))

    def gravity_torques(self, q: Any) -> np.ndarray:
        """The joint torques that hold the arm still against gravity at ``q``, N m (the URDF's inertias, gravity
        along the URDF root's -z)."""
        return np.array(pin.computeGeneralizedGravity(self.model, self._dynamics, self._as_q(q)))

    def mass_matrix(self, q: Any) -> np.ndarray:
        """The joint-space mass matrix M(q) (nq, nq), kg m^2, symmetric (the URDF's inertias; CRBA)."""
        upper = pin.crba(self.model, self._dynamics, self._as_q(q))
        return np.triu(upper) + np.triu(upper, 1).T  # CRBA fills the upper triangle only

    def pad_jacobians(self, q: Any) -> np.ndarray:
        """Linear Jacobians (n_pads, 3, nq) of the pad points, base_frame axes (the first rows of
        :meth:`speed_jacobians`). Read-only, computed once per pose."""
        return self.speed_jacobians(q)[:len(self._pad_ids)]

    def kinetic_energy(self, q: Any, dq: Any) -> float:
        """The arm's kinetic energy at ``q`` moving at ``dq``, J."""
        return float(pin.computeKineticEnergy(self.model, self._dynamics, self._as_q(q), np.asarray(dq, dtype=float)))

    def joint_positions(self, q: Any) -> np.ndarray:
        """Origins of every movable joint in chain order, then the tool frame origin,
        in base_frame, shape (nq + 1, 3): the polyline used for drawing and for
        distance checks."""
        self._posed(q)
        points = np.empty((self.model.njoints, 3))
        for row in range(self.model.njoints - 1):
            points[row] = self.data.oMi[row + 1].translation
        points[-1] = self.data.oMf[self._tool_id].translation
        return self._to_base(points)
