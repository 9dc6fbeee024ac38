"""A real skin's pressure array -> the robot's pads: the pad mapping and each message's checks.

One piece of code for the live ROS 1 source (:mod:`nwr.services.gateway.sources.ros1`)
and ``nwr import`` of ROS 1 and ROS 2 bags (:mod:`nwr.services.tools.recordings.rosbag_import`).
Pure: no ROS, no clock, no I/O.

A device reports ``n`` values (AIRSKIN: 11); the mapping (``gateway.ros1.pads``)
names, for each device index, the robot's pad it is, or ``""`` for an index
that is not used. Each of the robot's pads is named at most once. A value
becomes an absolute pressure ``value * scale_hpa + offset_hpa``, hPa (the
gateway's baseline filter takes the change from it, as for the simulated skin).

A pad is invalid in a sample (NaN here, ``valid`` false and change 0 in the
SkinPressure, so it can never trigger a reflex) when it has no device index,
when the message is too short to hold its index, when its value is not a
finite number, or when its absolute pressure is outside what the pipeline
accepts (:data:`nwr.common.door.ABSOLUTE_HPA`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from nwr.common.errors import ConfigError

# The absolute pressures the pipeline accepts (as nwr.common.door.ABSOLUTE_HPA), hPa.
ABSOLUTE_RANGE_HPA = (0.0, 5000.0)


@dataclass(frozen=True)
class PadMap:
    """Device index -> pad id, checked against the robot's pad names."""

    pad_names: tuple[str, ...]  # the robot's pads, in id order
    pad_of_index: tuple[int | None, ...]  # per device index: the pad id, None = not used
    scale_hpa: float = 1.0
    offset_hpa: float = 0.0

    @property
    def n_values(self) -> int:
        """How many values a message must carry."""
        return len(self.pad_of_index)

    @property
    def n_pads(self) -> int:
        return len(self.pad_names)

    def unused_indices(self) -> list[int]:
        """Device indices no pad is mapped from."""
        return [i for i, pad in enumerate(self.pad_of_index) if pad is None]

    def unmapped_pads(self) -> list[str]:
        """The robot's pads no device index feeds: always invalid."""
        fed = {pad for pad in self.pad_of_index if pad is not None}
        return [name for i, name in enumerate(self.pad_names) if i not in fed]

    def describe(self) -> list[str]:
        """The mapping's own problems, once (not per message): unused indices, pads with no index."""
        out = []
        if unused := self.unused_indices():
            out.append(f"device indices {unused} are mapped to no pad (their values are ignored)")
        if unmapped := self.unmapped_pads():
            out.append(f"pads {unmapped} have no device index: they are always invalid (never trigger a reflex)")
        return out

    def table(self) -> list[tuple[int, str]]:
        """(device index, pad name or "") rows, as docs/lab.md shows them."""
        return [(i, "" if pad is None else self.pad_names[pad]) for i, pad in enumerate(self.pad_of_index)]


def pad_map(mapping: Sequence[str], pad_names: Sequence[str], *, scale_hpa: float = 1.0,
            offset_hpa: float = 0.0, where: str = "gateway.ros1.pads") -> PadMap:
    """The mapping ``mapping[i]`` = pad name of device index ``i`` ("" = unused); ConfigError naming ``where``
    for an unknown or repeated pad name, an empty mapping or a non-finite or non-positive scale."""
    if not mapping:
        raise ConfigError(f"{where} is empty: name the robot's pad of each device index (\"\" for an unused one)")
    if not (math.isfinite(scale_hpa) and scale_hpa > 0):
        raise ConfigError(f"the pressure scale must be a positive number of hPa per unit, got {scale_hpa}")
    if not math.isfinite(offset_hpa):
        raise ConfigError(f"the pressure offset must be a finite number of hPa, got {offset_hpa}")
    ids = {name: i for i, name in enumerate(pad_names)}
    seen: dict[str, int] = {}
    out: list[int | None] = []
    for index, name in enumerate(mapping):
        if not name:
            out.append(None)
            continue
        if name not in ids:
            raise ConfigError(f"{where}[{index}] = {name!r} is no pad of the robot; its pads are {list(pad_names)}")
        if name in seen:
            raise ConfigError(f"{where} names pad {name!r} twice (indices {seen[name]} and {index}): each pad "
                              "takes one device index")
        seen[name] = index
        out.append(ids[name])
    return PadMap(tuple(pad_names), tuple(out), float(scale_hpa), float(offset_hpa))


@dataclass
class Mapped:
    """One message's values mapped onto the pads."""

    absolute_hpa: np.ndarray  # one per pad, NaN where the pad is invalid in this sample
    # This message's problems, by kind: "length", "non_finite", "range" (readable text each).
    problems: dict[str, str] = field(default_factory=dict)

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.absolute_hpa)


def map_values(values: Sequence[float] | np.ndarray, pmap: PadMap) -> Mapped:
    """A message's values -> each pad's absolute pressure (NaN: invalid in this sample), with its problems.

    Never raises for what a message carries: a wrong length, non-numbers,
    non-finite or out-of-range values make only the pads concerned invalid.
    """
    problems: dict[str, str] = {}
    try:
        raw = np.asarray(values, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raw = np.array([_number(v) for v in values], dtype=float) if _iterable(values) else np.array([], dtype=float)
        problems["non_finite"] = "the message's values are not all numbers"
    n = pmap.n_values
    if raw.size != n:
        lost = [pmap.pad_names[p] for p in pmap.pad_of_index[raw.size:] if p is not None]
        problems["length"] = (f"the message carries {raw.size} values, the pad mapping {n}"
                              + (f": pads {lost} are invalid" if lost else "")
                              + (f"; values past index {n - 1} are ignored" if raw.size > n else ""))
    out = np.full(pmap.n_pads, np.nan)
    bad_value: list[str] = []
    out_of_range: list[str] = []
    lo, hi = ABSOLUTE_RANGE_HPA
    with np.errstate(over="ignore", invalid="ignore"):
        for index, pad in enumerate(pmap.pad_of_index[:raw.size]):
            if pad is None:
                continue
            value = raw[index]
            name = pmap.pad_names[pad]
            if not math.isfinite(value):
                bad_value.append(f"{name} (index {index}: {value})")
                continue
            absolute = value * pmap.scale_hpa + pmap.offset_hpa
            if not (math.isfinite(absolute) and lo <= absolute <= hi):
                out_of_range.append(f"{name} (index {index}: {absolute:g} hPa)")
                continue
            out[pad] = absolute
    if bad_value:
        problems["non_finite"] = "non-finite values, pads invalid: " + ", ".join(bad_value)
    if out_of_range:
        problems["range"] = (f"absolute pressures outside {lo:g}..{hi:g} hPa (check scale_hpa / offset_hpa), "
                             "pads invalid: " + ", ".join(out_of_range))
    return Mapped(out, problems)


def _iterable(values: object) -> bool:
    try:
        iter(values)  # type: ignore[call-overload]
    except TypeError:
        return False
    return True


def _number(value: object) -> float:
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        return math.nan
