"""Safety beside a person: the profile's safety-relevant fields (:data:`GUARDS`) and which side of a default
loosens each (:func:`loosens`), what a field holds (:class:`Guarded`) and a loosened value (:class:`Loosened`).

Plug-ins declare their own fields with :class:`Guard` too. The profile's defaults, and the acknowledgement a
loosened value needs in ``[safety]``, are :mod:`nwr.common.config`'s (``guarded``, ``check_acknowledgements``:
the third step of checking a profile).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import msgspec


@dataclass(frozen=True)
class Guard:
    """A safety-relevant field: the side of its default that loosens it, and its unit.

    ``above``: a larger value (for a list: any element larger than the
    default's); ``below``: a smaller one; ``wider``: a larger magnitude,
    either sign; ``other``: any value but the default.
    """

    loosens: Literal["above", "below", "wider", "other"]
    unit: str = ""


# The safety-relevant fields beside a person, by dotted name (<pad>: a pad's
# name): a value past the default on the side named must be acknowledged in
# [safety]. docs/profile.md says why, one by one (tests/test_profile_safety.py
# loosens each).
GUARDS: dict[str, Guard] = {
    # When a touch is felt and a press stays felt.
    "gateway.contact_hpa": Guard("above", "hPa"),
    "gateway.release_hpa": Guard("above", "hPa"),
    "gateway.max_drift_hpa_s": Guard("above", "hPa/s"),
    "gateway.max_contact_s": Guard("below", "s"),
    "gain.thresholds_hpa": Guard("above", "hPa"),
    "gain.overrides.<pad>.thresholds_hpa": Guard("above", "hPa"),
    "planner.update_margin": Guard("above"),
    # Reflex storms: how often a touch, or a forged skin stream, may restart a reflex.
    "planner.restarts.gap_s": Guard("below", "s"),
    "planner.restarts.escalate_at_once": Guard("above"),
    "planner.restarts.pad_burst": Guard("above"),
    "planner.restarts.pad_interval_s": Guard("below", "s"),
    "planner.restarts.burst": Guard("above"),
    "planner.restarts.interval_s": Guard("below", "s"),
    # How far and how fast a reflex moves the arm.
    "gain.pl3_gain": Guard("above"),
    "gain.torque.on_nm": Guard("above", "N m"),
    "gain.torque.off_ratio": Guard("below"),
    "gain.torque.full_force_n": Guard("above", "N"),
    "gain.torque.state_timeout_s": Guard("above", "s"),
    # The effective-mass model: how much more sensitive a moving pad becomes, and what it predicts.
    "gain.effective_mass.floor": Guard("above"),
    "gain.effective_mass.rest_speed_m_s": Guard("above", "m/s"),
    "gain.effective_mass.state_timeout_s": Guard("above", "s"),
    "gain.effective_mass.regions.<region>.k_n_m": Guard("below", "N/m"),
    "gain.effective_mass.regions.<region>.mass_kg": Guard("below", "kg"),
    "gain.effective_mass.regions.<region>.transient_n": Guard("above", "N"),
    "planner.q_max_deg": Guard("above", "deg"),
    "planner.v_max_m_s": Guard("above", "m/s"),
    "planner.reflex_duration_s": Guard("above", "s"),
    "planner.speed_fraction": Guard("above"),
    # Sustained contact: when and how the arm comes back.
    "planner.sustained_contact": Guard("other"),
    "planner.contacts": Guard("other"),
    "planner.release_s": Guard("below", "s"),
    "planner.max_hold_s": Guard("below", "s"),
    "planner.recent_contact_s": Guard("below", "s"),
    "planner.contact_margin_m": Guard("above", "m"),
    "planner.return_speed_m_s": Guard("above", "m/s"),
    "planner.approach_speed_m_s": Guard("above", "m/s"),
    "planner.approach_distance_m": Guard("below", "m"),
    # The task.
    "planner.task.period_s": Guard("below", "s"),
    "planner.task.amplitude_rad": Guard("wider", "rad"),
    "planner.task.double_frequency": Guard("above"),
    "planner.task.ramp_s": Guard("below", "s"),
    # The bridge: its timeouts and limits.
    "bridge.command_timeout_s": Guard("above", "s"),
    "bridge.skin_timeout_s": Guard("above", "s"),
    "bridge.position_jump_rad": Guard("above", "rad"),
    "bridge.following_error_rad": Guard("above", "rad"),
    "bridge.following_lag_s": Guard("above", "s"),
    "bridge.report_jump_rad": Guard("above", "rad"),
    "bridge.report_speed_jump_rad_s": Guard("above", "rad/s"),
    "bridge.report_frozen_s": Guard("above", "s"),
    "bridge.blind_pad_s": Guard("above", "s"),
    **{f"bridge.{mode}.{field}": Guard("above", unit)
       for mode in ("limits", "reduced")
       for field, unit in (("speed_m_s", "m/s"), ("withdrawal_speed_m_s", "m/s"), ("momentum_kg_m_s", "kg m/s"),
                           ("power_w", "W"), ("stopping_time_s", "s"), ("stopping_distance_m", "m"))},
}


def pattern_of(name: str) -> str | None:
    """The key of GUARDS that the dotted ``name`` stands for (None: no safety-relevant field)."""
    if name in GUARDS:
        return name
    parts = name.split(".")
    if len(parts) == 4 and parts[:2] == ["gain", "overrides"] and parts[3] == "thresholds_hpa" and parts[2]:
        return "gain.overrides.<pad>.thresholds_hpa"
    if len(parts) == 5 and parts[:3] == ["gain", "effective_mass", "regions"] and parts[3] and \
            f"gain.effective_mass.regions.<region>.{parts[4]}" in GUARDS:
        return f"gain.effective_mass.regions.<region>.{parts[4]}"
    return None


def toml_value(value: Any) -> str:
    """A value as a profile writes it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + "}"
    if value is None:
        return "unset"
    return repr(value)


def loosens(guard: Guard, value: Any, default: Any) -> bool:
    if guard.loosens == "other":
        return bool(value != default)
    if not isinstance(value, list):
        value, default = [value], [default]
    # A robot with more joints than the UR10e: its extra joints' default is 0.
    pairs = zip(value, list(default) + [0] * max(0, len(value) - len(default)))
    if guard.loosens == "above":
        return any(v > d for v, d in pairs)
    if guard.loosens == "below":
        return any(v < d for v, d in pairs)
    return any(abs(v) > abs(d) for v, d in pairs)


class Loosened(msgspec.Struct, frozen=True):
    """A safety-relevant value past its default on the side that loosens it, as the session's metadata keeps it."""

    field: str
    value: Any
    default: Any
    reason: str


class Guarded(NamedTuple):
    """A safety-relevant field as a profile holds it: its dotted name, value, documented default and guard."""

    field: str
    value: Any
    default: Any
    guard: Guard
