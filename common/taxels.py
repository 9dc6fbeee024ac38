"""A taxel skin: hundreds of small sensing elements over the links, instead of ten air pads.

An AIRSKIN pad reports one pressure change for a whole pad, so a contact's location is the pad's point. A
taxel skin reports one pressure per element (a *taxel*: position, outward normal, area, link), so a contact
is where the pressing taxels are: the touched cluster's pressure-weighted centroid and mean normal.

The skin file
-------------
A taxel skin file (``skin-taxels.toml`` beside a robot's ``robot.toml``) has one ``[skin]`` table and its
taxels as ``[[patch]]`` tables (a grid of taxels over a section of a cylinder around a link, expanded at load)
and/or ``[[taxel]]`` tables (one element each)::

    [skin]
    unit = "kPa"                              # what a taxel reports: pressure over its no-touch baseline
    neighbour_m = 0.03                        # taxels of one link closer than this press in one contact
    force_thresholds_n = [0.5, 2.0, 5.0, 10.0]  # a contact's pain levels by its force, N

    [[patch]]
    name = "upper_arm_top"; region = "upper_arm"; link = "upper_arm_link"
    axis_point = [0.0, 0.0, 0.176]  # a point on the cylinder's axis, link frame (m)
    axis = [1.0, 0.0, 0.0]          # the axis' unit direction
    ref = [0.0, 1.0, 0.0]           # the unit direction of angle 0, perpendicular to the axis
    radius = 0.065                  # the skin's surface, m
    along_m = [-0.10, -0.50]        # the patch's extent along the axis from axis_point
    angles_deg = [0.0, 180.0]       # its extent around the axis, from ref toward axis x ref
    pitch_m = 0.02                  # taxel spacing (rounded so the taxels tile the section evenly)

    [[taxel]]
    patch = "lid"; region = "shoulder"; link = "shoulder_link"
    point = [0.0, 0.11, 0.0]; normal = [0.0, 1.0, 0.0]; area_m2 = 4e-4

Taxel ids are their order: the patches' taxels first (each patch along its axis, then around it), then the
``[[taxel]]`` tables in file order. Checks (each a :class:`ConfigError` naming the file, the element and the
value): links of the URDF, unit normals (within 1e-6: a normal is never silently normalised), normals
perpendicular to a patch's axis, every taxel within :data:`~nwr.common.robot.MAX_PAD_OFFSET_M` of its link's
skeleton (the test the AIRSKIN pads pass), positive areas, no two taxels of one link at one point.

Levels
------
The paper's thresholds (2/6/12/20 hPa) are an AIRSKIN pad's air pressure: they mean nothing for a taxel.
A taxel contact's pain level and gain come from the same functions of :mod:`nwr.services.gain.core` applied
to its *force* (the sum of pressure x area over its cluster, N) and the skin file's ``force_thresholds_n``
(:attr:`TaxelSkin.level_thresholds_n`: a billionth under them, for the sum's rounding):
a force is what a person feels and what a skin of any pitch measures alike. The AIRSKIN skin keeps the
paper's values to the digit.

The simulated finger
--------------------
:func:`finger_pressure` presses a round fingertip of radius R with a force F at a point of a link: each
taxel at distance d < R from the centre reads p0 sqrt(1 - (d/R)^2) (Hertz's elliptic profile), p0 chosen so
that the taxels' pressure times area sums to F; a taxel farther than R, or on another link, reads 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nwr.common.errors import ConfigError
from nwr.common.robot import (
    _NAME_PATTERN,
    _UNIT_TOLERANCE,
    MAX_PAD_OFFSET_M,
    REGIONS,
    RobotDescription,
    _build_model,
    _check_keys,
    _is_number,
    _read_toml,
    _readonly,
    _string,
    _vector,
    link_offset,
)

UNITS: tuple[str, ...] = ("kPa", "hPa", "Pa")
_PA_PER_UNIT = {"kPa": 1e3, "hPa": 1e2, "Pa": 1.0}
_SKIN_KEYS = frozenset({"unit", "neighbour_m", "force_thresholds_n"})
_PATCH_KEYS = frozenset({"name", "region", "link", "axis_point", "axis", "ref", "radius", "along_m",
                         "angles_deg", "pitch_m"})
_TAXEL_KEYS = frozenset({"patch", "region", "link", "point", "normal", "area_m2"})
# The relative rounding of a contact's force (a sum of pressure x area over its taxels) that still reaches a
# threshold.
FORCE_ROUNDING = 1e-9
# Two taxels of one link nearer than this are one taxel entered twice.
_SAME_POINT_M = 1e-4
# A skin of more taxels than this is a unit slip (a pitch in mm); the neighbour graph is an N x N matrix
# (25 MB at this size).
MAX_TAXELS = 5000


@dataclass(frozen=True, eq=False)
class TaxelSkin:
    """A taxel skin, expanded and checked; arrays have one row per taxel, in id order, and are read-only.

    ``points`` (m) and ``normals`` (unit) are in the frame of each taxel's link (``links[link_index[i]]``),
    ``areas`` in m^2; ``patch_index[i]`` indexes ``patches`` and ``patch_regions`` (its body region).
    """

    path: Path
    unit: str
    neighbour_m: float
    force_thresholds_n: tuple[float, float, float, float]
    links: tuple[str, ...]
    patches: tuple[str, ...]
    patch_regions: tuple[str, ...]
    link_index: np.ndarray
    patch_index: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    # The neighbour graph (taxels of one link nearer than neighbour_m), a symmetric boolean N x N matrix.
    neighbours: np.ndarray

    def __len__(self) -> int:
        return len(self.areas)

    @property
    def pa_per_unit(self) -> float:
        return _PA_PER_UNIT[self.unit]

    @property
    def level_thresholds_n(self) -> tuple[float, ...]:
        """The force thresholds a contact's level and gain are computed against: ``force_thresholds_n`` less
        :data:`FORCE_ROUNDING` of each (a contact's force is a sum over its taxels: a finger pressing exactly
        a threshold's force sums to within a few ulps either side of it, and must reach its level)."""
        return tuple(t * (1.0 - FORCE_ROUNDING) for t in self.force_thresholds_n)


@dataclass(frozen=True, eq=False)
class TaxelContact:
    """One touched cluster: its taxels, force, peak, pressure-weighted centroid and mean outward normal in
    the frame of its link; ``peak_taxel`` is the id of its most pressed taxel. Compared by identity, as
    :class:`~nwr.common.robot.Pad` (numpy fields)."""

    link: str
    patch: str
    region: str
    taxels: tuple[int, ...]
    force_n: float
    peak: float
    peak_taxel: int
    point: np.ndarray
    normal: np.ndarray


def load_taxel_skin(path: str | Path, robot: RobotDescription) -> TaxelSkin:
    """Read, expand and check a taxel skin file for ``robot`` (its URDF's links); ConfigError otherwise."""
    path = Path(path)
    doc = _read_toml(path)
    _check_keys(doc, frozenset({"skin"}), frozenset({"skin", "patch", "taxel"}), path, "taxel skin")
    skin = doc["skin"]
    if not isinstance(skin, dict):
        raise ConfigError(f"{path}: [skin] must be a table")
    _check_keys(skin, _SKIN_KEYS, _SKIN_KEYS, path, "[skin]")
    unit = skin["unit"]
    if unit not in UNITS:
        raise ConfigError(f"{path}: [skin] unit = {unit!r}; expected one of {', '.join(UNITS)}")
    neighbour_m = _positive(skin["neighbour_m"], path, "[skin] neighbour_m")
    thresholds = _vector(skin["force_thresholds_n"], 4, path, "[skin] force_thresholds_n", positive=True)
    if not np.all(np.diff(thresholds) > 0):
        raise ConfigError(f"{path}: [skin] force_thresholds_n = {thresholds.tolist()}; expected four rising "
                          "forces (PL 2, PL 3, PL 4 start and full gain), N")

    model = _build_model(robot.urdf_path, path)
    urdf_links = {frame.name for frame in model.frames if frame.type.name == "BODY"}
    links: list[str] = []
    patches: list[str] = []
    regions: list[str] = []
    rows: list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]] = []  # link, patch, points, normals, areas

    def patch_id(name: str, region: str, where: str) -> int:
        if name in patches:
            if regions[patches.index(name)] != region:
                raise ConfigError(f"{path}: {where}: patch {name!r} is in region {regions[patches.index(name)]!r} "
                                  f"elsewhere, here in {region!r}: one patch, one region")
            return patches.index(name)
        patches.append(name)
        regions.append(region)
        return len(patches) - 1

    def link_id(link: str, where: str) -> int:
        if link not in urdf_links:
            raise ConfigError(f"{path}: {where}: link = {link!r} is not a link of {robot.urdf_path.name}; "
                              f"expected one of: {', '.join(sorted(urdf_links))}")
        if link not in links:
            links.append(link)
        return links.index(link)

    for number, table in enumerate(_tables(doc, "patch", path)):
        where = f"[[patch]] #{number + 1}"
        _check_keys(table, _PATCH_KEYS, _PATCH_KEYS, path, where)
        name, region = _name(table["name"], path, where), _region(table["region"], path, where)
        if name in patches:
            raise ConfigError(f"{path}: {where}: patch name {name!r} is used by more than one [[patch]]")
        points, normals, areas = _expand_patch(table, path, where)
        link = link_id(_string(table["link"], path, f"{where}: link"), where)
        rows.append((link, patch_id(name, region, where), points, normals, areas))
    for number, table in enumerate(_tables(doc, "taxel", path)):
        where = f"[[taxel]] #{number + 1}"
        _check_keys(table, _TAXEL_KEYS, _TAXEL_KEYS, path, where)
        point = _vector(table["point"], 3, path, f"{where}: point")
        normal = _unit(table["normal"], path, f"{where}: normal")
        area = _positive(table["area_m2"], path, f"{where}: area_m2")
        link = link_id(_string(table["link"], path, f"{where}: link"), where)
        patch = patch_id(_name(table["patch"], path, where), _region(table["region"], path, where), where)
        rows.append((link, patch, point[None, :], normal[None, :], np.array([area])))
    if not rows:
        raise ConfigError(f"{path}: expected one or more [[patch]] or [[taxel]] tables")

    link_index = np.concatenate([np.full(len(r[4]), r[0]) for r in rows])
    patch_index = np.concatenate([np.full(len(r[4]), r[1]) for r in rows])
    points = np.concatenate([r[2] for r in rows])
    normals = np.concatenate([r[3] for r in rows])
    areas = np.concatenate([r[4] for r in rows])
    if len(areas) > MAX_TAXELS:
        raise ConfigError(f"{path}: {len(areas)} taxels; expected at most {MAX_TAXELS}: is a pitch in mm?")
    for taxel in range(len(areas)):
        link = links[link_index[taxel]]
        offset = link_offset(model, link, points[taxel])
        if offset > MAX_PAD_OFFSET_M:
            raise ConfigError(
                f"{path}: taxel {taxel} (patch {patches[patch_index[taxel]]!r}): point = "
                f"{np.round(points[taxel], 4).tolist()} is {offset:.3f} m from link {link!r} (its origin and the "
                f"joints it carries); expected at most {MAX_PAD_OFFSET_M} m: is it in another link's frame, or mm?")
    neighbours = _neighbour_graph(points, link_index, neighbour_m, path, patches, patch_index)
    return TaxelSkin(
        path=path, unit=unit, neighbour_m=neighbour_m,
        force_thresholds_n=tuple(float(t) for t in thresholds),  # type: ignore[arg-type]
        links=tuple(links), patches=tuple(patches), patch_regions=tuple(regions),
        link_index=_readonly_int(link_index), patch_index=_readonly_int(patch_index),
        points=_readonly(points), normals=_readonly(normals), areas=_readonly(areas), neighbours=neighbours)


def contacts(skin: TaxelSkin, pressure: np.ndarray, threshold: float) -> list[TaxelContact]:
    """The touched clusters of one sample, strongest (force) first.

    ``pressure`` has one reading per taxel in the skin's unit; a taxel presses when its reading is at least
    ``threshold`` (> 0) and finite (a non-finite reading never makes or joins a contact). A cluster is a
    connected set of pressing taxels in the neighbour graph; its centroid and normal are weighted by pressure.
    """
    if pressure.shape != (len(skin),):
        raise ValueError(f"taxel sample has shape {pressure.shape}; the skin has {len(skin)} taxels")
    if not threshold > 0:
        raise ValueError(f"contact threshold {threshold!r}; expected > 0")
    with np.errstate(invalid="ignore"):
        pressing = np.flatnonzero(np.isfinite(pressure) & (pressure >= threshold))
    if pressing.size == 0:
        return []
    labels = _components(skin.neighbours[np.ix_(pressing, pressing)])
    count = int(labels.max()) + 1
    p = pressure[pressing]
    # Sequential sums (bincount), not a matrix product: the same bits on every machine, for nwr verify.
    weights = np.bincount(labels, weights=p, minlength=count)
    force = np.bincount(labels, weights=p * skin.areas[pressing], minlength=count) * skin.pa_per_unit
    points = np.stack([np.bincount(labels, weights=p * skin.points[pressing, d], minlength=count)
                       for d in range(3)], axis=1) / weights[:, None]
    normals = np.stack([np.bincount(labels, weights=p * skin.normals[pressing, d], minlength=count)
                        for d in range(3)], axis=1)
    lengths = np.linalg.norm(normals, axis=1)
    found = []
    for cluster in np.argsort(-force, kind="stable"):
        members = pressing[labels == cluster]
        peak = int(members[np.argmax(pressure[members])])
        patch = skin.patch_index[peak]
        found.append(TaxelContact(
            link=skin.links[skin.link_index[peak]], patch=skin.patches[patch], region=skin.patch_regions[patch],
            taxels=tuple(members.tolist()), force_n=float(force[cluster]), peak=float(pressure[peak]),
            peak_taxel=peak, point=points[cluster],
            # Opposite normals cancel only on a cluster wrapped around a link thinner than neighbour_m: then
            # the peak taxel's normal.
            normal=normals[cluster] / lengths[cluster] if lengths[cluster] > 1e-9 else skin.normals[peak].copy()))
    return found


def _components(adjacent: np.ndarray) -> np.ndarray:
    """Connected components of a symmetric boolean adjacency matrix: each node's label is the least index of
    its component, relabelled 0..count-1 in order of those least indices (min-label propagation with pointer
    jumping: a few numpy passes for a cluster under a finger)."""
    k = len(adjacent)
    labels = np.arange(k)
    while True:
        spread = np.where(adjacent, labels[None, :], k).min(axis=1)
        new = np.minimum(labels, spread)
        new = new[new]  # pointer jumping: a node takes its label's label
        if np.array_equal(new, labels):
            break
        labels = new
    roots = labels == np.arange(k)  # each component's least index labels it
    return (np.cumsum(roots) - 1)[labels]


def in_base(contact: TaxelContact, link_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A contact's point and normal in the base frame, given its link's 4x4 pose there
    (:meth:`nwr.common.robot.RobotModel.frame_pose`)."""
    rotation = link_pose[:3, :3]
    return rotation @ contact.point + link_pose[:3, 3], rotation @ contact.normal


def finger_pressure(skin: TaxelSkin, link: str, centre: np.ndarray, radius_m: float, force_n: float) -> np.ndarray:
    """Each taxel's reading (the skin's unit) under a round fingertip of ``radius_m`` pressing with ``force_n``
    at ``centre`` (m, in the frame of ``link``): Hertz's elliptic profile, scaled so that the readings times
    the areas sum to the force; all zero when no taxel of the link lies within the radius."""
    if not (radius_m > 0 and math.isfinite(radius_m)) or not (force_n >= 0 and math.isfinite(force_n)):
        raise ValueError(f"finger radius {radius_m!r} m and force {force_n!r} N; expected > 0 and >= 0")
    if link not in skin.links:
        raise ValueError(f"the taxel skin has no taxel on link {link!r}; its links: {', '.join(skin.links)}")
    on_link = skin.link_index == skin.links.index(link)
    d2 = np.sum((skin.points - np.asarray(centre, dtype=float)) ** 2, axis=1) / (radius_m * radius_m)
    shape = np.where(on_link & (d2 < 1.0), np.sqrt(np.clip(1.0 - d2, 0.0, None)), 0.0)
    carried = float(shape @ skin.areas) * skin.pa_per_unit
    return shape * (force_n / carried) if carried > 0 else shape


def nearest_taxel(skin: TaxelSkin, link: str, point: np.ndarray) -> int:
    """The id of ``link``'s taxel nearest ``point`` (link frame): where a touch scripted on a pad presses a
    taxel skin."""
    if link not in skin.links:
        raise ValueError(f"the taxel skin has no taxel on link {link!r}; its links: {', '.join(skin.links)}")
    candidates = np.flatnonzero(skin.link_index == skin.links.index(link))
    distances = np.linalg.norm(skin.points[candidates] - np.asarray(point, dtype=float), axis=1)
    return int(candidates[int(np.argmin(distances))])


# --------------------------------------------------------------------------- loading helpers


def _tables(doc: dict[str, Any], key: str, path: Path) -> list[dict[str, Any]]:
    tables = doc.get(key, [])
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise ConfigError(f"{path}: {key} must be [[{key}]] tables")
    return tables


def _name(value: Any, path: Path, where: str) -> str:
    name = _string(value, path, f"{where}: name")
    if not _NAME_PATTERN.match(name):
        raise ConfigError(f"{path}: {where}: name = {name!r}; expected letters, digits, '_' or '-' only")
    return name


def _region(value: Any, path: Path, where: str) -> str:
    if value not in REGIONS:
        raise ConfigError(f"{path}: {where}: region = {value!r}; expected one of {', '.join(REGIONS)}")
    return str(value)


def _positive(value: Any, path: Path, field: str) -> float:
    if not (_is_number(value) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{path}: {field} = {value!r}; expected a number > 0")
    return float(value)


def _unit(value: Any, path: Path, field: str) -> np.ndarray:
    vector = _vector(value, 3, path, field)
    length = float(np.linalg.norm(vector))
    if abs(length - 1.0) > _UNIT_TOLERANCE:
        raise ConfigError(f"{path}: {field} = {value!r} has length {length:.9g}; expected a unit vector "
                          f"(length 1 within {_UNIT_TOLERANCE})")
    return vector


def _expand_patch(table: dict[str, Any], path: Path, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    axis_point = _vector(table["axis_point"], 3, path, f"{where}: axis_point")
    axis = _unit(table["axis"], path, f"{where}: axis")
    ref = _unit(table["ref"], path, f"{where}: ref")
    if abs(float(axis @ ref)) > 1e-6:
        raise ConfigError(f"{path}: {where}: ref = {table['ref']!r} is not perpendicular to axis = "
                          f"{table['axis']!r} (dot {float(axis @ ref):.3g}); expected the direction of angle 0")
    radius = _positive(table["radius"], path, f"{where}: radius")
    pitch = _positive(table["pitch_m"], path, f"{where}: pitch_m")
    along = _vector(table["along_m"], 2, path, f"{where}: along_m")
    angles = np.radians(_vector(table["angles_deg"], 2, path, f"{where}: angles_deg"))
    length, sweep = abs(along[1] - along[0]), abs(angles[1] - angles[0])
    if length == 0 or sweep == 0 or sweep > 2 * math.pi + 1e-9:
        raise ConfigError(f"{path}: {where}: along_m = {table['along_m']!r}, angles_deg = {table['angles_deg']!r};"
                          " expected a section of non-zero length and a sweep in (0, 360] degrees")
    n_along = max(1, round(length / pitch))
    n_around = max(1, round(radius * sweep / pitch))
    if n_along * n_around > MAX_TAXELS:
        raise ConfigError(f"{path}: {where}: {n_along * n_around} taxels at pitch_m = {pitch}; expected at most "
                          f"{MAX_TAXELS}: is the pitch in mm?")
    s = along[0] + (np.arange(n_along) + 0.5) * (along[1] - along[0]) / n_along
    theta = angles[0] + (np.arange(n_around) + 0.5) * (angles[1] - angles[0]) / n_around
    side = np.cross(axis, ref)
    s_grid, t_grid = np.meshgrid(s, theta, indexing="ij")
    normals = np.cos(t_grid.ravel())[:, None] * ref + np.sin(t_grid.ravel())[:, None] * side
    points = axis_point + s_grid.ravel()[:, None] * axis + radius * normals
    areas = np.full(len(points), (length / n_along) * (radius * sweep / n_around))
    return points, normals, areas


def _neighbour_graph(points: np.ndarray, link_index: np.ndarray, neighbour_m: float, path: Path,
                     patches: list[str], patch_index: np.ndarray) -> np.ndarray:
    graph = np.zeros((len(points), len(points)), dtype=bool)
    for link in np.unique(link_index):
        ids = np.flatnonzero(link_index == link)
        d = np.linalg.norm(points[ids, None, :] - points[None, ids, :], axis=2)
        np.fill_diagonal(d, np.inf)
        twins = np.argwhere(d < _SAME_POINT_M)
        if twins.size:
            a, b = ids[twins[0]]
            raise ConfigError(f"{path}: taxels {a} (patch {patches[patch_index[a]]!r}) and {b} (patch "
                              f"{patches[patch_index[b]]!r}) are at one point {np.round(points[a], 4).tolist()}: "
                              "expected each taxel once")
        graph[np.ix_(ids, ids)] = d < neighbour_m
    graph.flags.writeable = False
    return graph


def _readonly_int(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=np.intp)
    out.flags.writeable = False
    return out
