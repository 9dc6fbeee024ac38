"""People's body parts in a physics world: their shapes, masses, how hard they can push, and ISO/TS 15066's limits.

A body part is a rigid shape (a finger's tip, a palm, a forearm) that a
person moves: a spring-damper pulls it toward a target, and its pull
saturates at the part's push force (a person pushes no harder than their
muscles let them). The world refuses a push beyond what a person can
plausibly make with that part (:data:`KINDS`' ``plausible_push_n``).

Sizes (adult anthropometry, rounded): an index fingertip is about 18 mm
wide (a sphere of 9 mm radius); a palm about 9 cm x 10 cm and 3 cm thick; a
forearm about 7 cm across and, where it can lean on an arm, 24 cm long.
Masses are ISO/TS 15066's effective masses of the body regions (its Table
A.3, from memory like the limits below: hands and fingers 0.6 kg, lower arms
and wrist joints 2 kg): the mass that takes part in a transient contact.

Plausible pushes: an index finger presses at most about 40-50 N (maximum
voluntary fingertip force); one hand or forearm pushes an obstacle with a
few hundred newtons at most. These are chosen bounds, not measurements: a
push beyond them is a script error, not a strong person.

ISO/TS 15066 (2016), Annex A, Table A.2 gives, per body region, the
maximum permissible quasi-static force and, per specific body area, the
maximum permissible quasi-static pressure; transient contact (the body part
can recoil) may reach twice both, except on the skull, forehead and face,
where transient contact is not permitted. :data:`ISO_TS_15066` holds the
table's values from the data file ``data/iso_ts_15066.toml`` beside this module:
written down as widely reproduced, each row compared with one or two public
reproductions of the table (the file says which; all agree), but not with
the standard's own text. Check them against the standard before quoting them
in a risk assessment. The energy figure
``energy_j = F_T**2 / (2 k)`` is derived from the transient force limit and
the region's effective spring constant (Table A.3), as ISO/TS 15066's
transfer-energy relation does; it is not a quoted value.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import msgspec
import msgspec.toml

from nwr.common.errors import ConfigError

Kind = Literal["finger", "palm", "forearm"]


@dataclass(frozen=True)
class Region:
    """ISO/TS 15066 Table A.2 limits for one specific body area (and its body region's force).

    Pressures in N/cm^2, forces in N. ``transient_factor`` multiplies both for
    transient contact (0: transient contact not permitted). ``spring_n_mm``
    and ``mass_kg`` are the region's effective spring constant and mass
    (Table A.3), where a body part of this world uses them.
    """

    region: str
    area: str
    pressure_n_cm2: float
    force_n: float
    transient_factor: float = 2.0
    spring_n_mm: float = 0.0
    mass_kg: float = 0.0
    label: str = ""
    # The public reproductions of the table its values were compared with (the data file's header).
    checked: tuple[str, ...] = ()

    @property
    def transient_pressure_n_cm2(self) -> float:
        return self.pressure_n_cm2 * self.transient_factor

    @property
    def transient_force_n(self) -> float:
        return self.force_n * self.transient_factor

    @property
    def transient_energy_j(self) -> float:
        """``F_T**2 / (2 k)``: the energy a transient contact at the transient force limit stores in the region's
        effective spring (derived, see the module docstring); 0 without a spring constant."""
        if self.spring_n_mm <= 0.0:
            return 0.0
        return self.transient_force_n ** 2 / (2.0 * self.spring_n_mm * 1000.0)


#: The data file of ISO/TS 15066's limits: a row per specific body area, each with the reproductions its values
#: were compared with (its header says which).
ISO_TS_15066_FILE = Path(__file__).with_name("data") / "iso_ts_15066.toml"


class _Area(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    label: str
    region: str
    pressure_n_cm2: Annotated[float, msgspec.Meta(gt=0)]
    force_n: Annotated[float, msgspec.Meta(gt=0)]
    transient_factor: Annotated[float, msgspec.Meta(ge=0)] = 2.0
    spring_n_mm: Annotated[float, msgspec.Meta(ge=0)] = 0.0
    mass_kg: Annotated[float, msgspec.Meta(ge=0)] = 0.0
    checked: list[str] = []


class _Table(msgspec.Struct, forbid_unknown_fields=True):
    area: list[_Area]


def load_limits(path: Path = ISO_TS_15066_FILE) -> dict[str, Region]:
    """ISO/TS 15066's limits per specific body area, keyed by its short name, from the data file. ConfigError
    naming the file for one that does not decode or names an area twice."""
    try:
        table = msgspec.toml.decode(path.read_bytes(), type=_Table)
    except (OSError, msgspec.DecodeError) as exc:
        raise ConfigError(f"{path}: {exc}") from None
    out: dict[str, Region] = {}
    for a in table.area:
        if a.name in out:
            raise ConfigError(f"{path}: body area {a.name!r} is given twice")
        out[a.name] = Region(a.region, a.name, a.pressure_n_cm2, a.force_n, a.transient_factor, a.spring_n_mm,
                             a.mass_kg, a.label, tuple(a.checked))
    return out


#: ISO/TS 15066:2016 Table A.2 (and A.3 where a body part uses it), one row per specific body area, keyed by a
#: short name (:data:`ISO_TS_15066_FILE`). D / ND: dominant / non-dominant hand.
ISO_TS_15066: dict[str, Region] = load_limits()


@dataclass(frozen=True)
class KindSpec:
    """One kind of body part: its shape (a MuJoCo geom), mass, the most a person pushes with it, and the
    ISO/TS 15066 body area it is judged by.

    ``size`` is MuJoCo's: a sphere's radius; a box's half sizes (x, y, z; its
    contact face is the -z face, so +z points away from what it presses); a
    capsule's radius and half length (its axis along z).
    """

    geom: Literal["sphere", "box", "capsule"]
    size: tuple[float, ...]
    mass_kg: float
    plausible_push_n: float
    area: str

    @property
    def extent_m(self) -> float:
        """How far the shape reaches from its centre toward what it presses (along its contact direction)."""
        if self.geom == "box":
            return self.size[2]
        return self.size[0]

    def contact_area_cm2(self, depth_m: float) -> float:
        """The area (cm^2) over which the part meets a surface it is pressed ``depth_m`` into (its geometric cut
        at that depth), at least a square millimetre: a sphere's cap ``pi (2 R d - d^2)``, a capsule's side
        ``2 sqrt(2 R d - d^2) x its length``, a box's whole face."""
        if self.geom == "box":
            area_m2 = 4.0 * self.size[0] * self.size[1]
        else:
            radius = self.size[0]
            d = min(max(depth_m, 0.0), radius)
            chord2 = 2.0 * radius * d - d * d
            if self.geom == "sphere":
                area_m2 = 3.141592653589793 * chord2
            else:
                area_m2 = 2.0 * chord2 ** 0.5 * 2.0 * self.size[1]
        return max(area_m2 * 1e4, 0.01)


#: The kinds of body part, their shapes and masses (see the module docstring for the sources).
KINDS: dict[str, KindSpec] = {
    "finger": KindSpec("sphere", (0.009,), 0.6, 50.0, "forefinger_pad_d"),
    "palm": KindSpec("box", (0.045, 0.05, 0.015), 0.6, 250.0, "palm_d"),
    "forearm": KindSpec("capsule", (0.035, 0.12), 2.0, 250.0, "forearm_muscle"),
}


def region_of(kind: str) -> Region:
    """The ISO/TS 15066 body area a kind of body part is judged by."""
    return ISO_TS_15066[KINDS[kind].area]
