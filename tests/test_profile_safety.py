"""The profile's safety beside a person: hard bounds, the robot, acknowledged loosened values, docs/profile.md."""

from __future__ import annotations

import json
import logging
import math
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import msgspec
import msgspec.inspect as mi
import pytest

from nwr.common import config
from nwr.common.config import PROFILES_DIR, Profile, check_acknowledgements, check_against_robot
from nwr.common.errors import ConfigError
from nwr.common.guards import GUARDS, Guarded, Loosened, toml_value
from nwr.common.recordings import read_recording, session_metadata
from nwr.common.robot import load_description
from nwr.services.gain.core import continuous_gain, scaled_sigmoid, sigmoid
from nwr.services.planner.strategies.location import robot_settings
from nwr.services.profile import check_plugins, kinds, load_profile, loosened_safety

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "profile.md"
DEFAULT = Profile()
REASON = "bench test without a person in the cell, 2026-11-23, J. Doe"


DESC = load_description()
WEIGHTS = robot_settings(DESC)  # the location reflex's defaults on the default robot: its table


def plugin_guards(profile: Profile | None = None) -> list[Guarded]:
    """The plug-ins' safety-relevant fields as ``profile`` (default: the defaults) holds them."""
    return check_plugins(profile or Profile(), DESC)


def loosened(profile: Profile) -> list[Loosened]:
    """Every loosened value of ``profile``, its plug-ins' included."""
    return config.loosened(profile, plugin_guards(profile))


def safe_range(field: str) -> str:
    return config.safe_range({g.field: g for g in plugin_guards()}.get(field, field))


def write(tmp_path: Path, text: str, name: str = "p.toml") -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def acknowledge(*fields: str, reason: str = REASON) -> str:
    return f"[safety]\nacknowledge = {json.dumps(list(fields))}\nreason = {json.dumps(reason)}\n"


def toml_of(field: str, value: Any) -> str:
    """A profile table that sets the dotted ``field`` to ``value`` (a location-weights row: in its full table)."""
    table, _, key = field.rpartition(".")
    if table.startswith("planner.location."):
        rows = dict(msgspec.to_builtins(getattr(WEIGHTS, table.rsplit(".", 1)[1])))
        rows[key] = value
        return f"[{table}]\n" + "".join(f"{k} = {toml_value(v)}\n" for k, v in rows.items())
    return f"[{table}]\n{key} = {toml_value(value)}\n"


# A value past the default on the side that loosens it, for every safety-relevant
# field, each within its hard bounds and cross-checks.
LOOSENED: dict[str, Any] = {
    "gateway.contact_hpa": 1.5,
    "gateway.release_hpa": 0.8,
    "gateway.max_drift_hpa_s": 0.1,
    "gateway.max_contact_s": 60.0,
    "gain.thresholds_hpa": [2.0, 6.0, 12.0, 24.0],
    "gain.overrides.wrist_3.thresholds_hpa": [3.0, 8.0, 14.0, 24.0],
    "planner.update_margin": 0.1,
    "planner.restarts.gap_s": 0.05,
    "planner.restarts.escalate_at_once": 0.3,
    "planner.restarts.pad_burst": 8,
    "planner.restarts.pad_interval_s": 0.25,
    "planner.restarts.burst": 20,
    "planner.restarts.interval_s": 0.1,
    "gain.pl3_gain": 0.5,
    "gain.torque.on_nm": 8.0,
    "gain.torque.off_ratio": 0.5,
    "gain.torque.full_force_n": 40.0,
    "gain.torque.state_timeout_s": 0.2,
    "gain.effective_mass.floor": 0.8,
    "gain.effective_mass.rest_speed_m_s": 0.01,
    "gain.effective_mass.state_timeout_s": 0.2,
    "gain.effective_mass.regions.hand.k_n_m": 40_000.0,
    "gain.effective_mass.regions.hand.mass_kg": 0.6,
    "gain.effective_mass.regions.hand.transient_n": 300.0,
    "planner.q_max_deg": [40.0, 70.0, 146.0, 80.0, 0.0, 0.0],
    "planner.uniform.fraction": 0.6,
    **{f"planner.location.{level}.{region}": [min(1.0, w + 0.1) for w in row]
       for level in ("pl3", "pl4")
       for region, row in getattr(WEIGHTS, level).items()},
    "planner.v_max_m_s": 0.3,
    "planner.reflex_duration_s": 0.6,
    "planner.speed_fraction": 0.95,
    "planner.whole-arm.duration_s": 0.8,
    "planner.whole-arm.distance_m": 0.15,
    "planner.whole-arm.point_speed_m_s": 0.6,
    "planner.whole-arm.outward_speed_m_s": 0.1,
    "planner.sustained_contact": "paper",
    "planner.contacts": "strongest",
    "planner.release_s": 0.1,
    "planner.max_hold_s": 10.0,
    "planner.recent_contact_s": 1.0,
    "planner.contact_margin_m": 0.03,
    "planner.return_speed_m_s": 0.22,
    "planner.approach_speed_m_s": 0.1,
    "planner.approach_distance_m": 0.02,
    "planner.task.period_s": 11.0,
    "planner.task.amplitude_rad": [0.35, 0.10, -0.13, 0.0, 0.0, 0.0],
    "planner.task.double_frequency": [0, 1, 1, 1, 0, 0],
    "planner.task.ramp_s": 0.2,
    "bridge.command_timeout_s": 0.05,
    "bridge.skin_timeout_s": 5.0,
    "bridge.position_jump_rad": 0.2,
    "bridge.ur_rtde.watchdog_hz": 5.0,
    "gateway.ros2.scale_hpa": 0.01,
    "bridge.franky.collision_torque_nm": 30.0,
    "bridge.franky.collision_force_n": 40.0,
    "bridge.franky.state_timeout_s": 0.2,
    "bridge.franky.recover_rest_s": 0.5,
    "bridge.limits.speed_m_s": 0.3,
    "bridge.limits.withdrawal_speed_m_s": 0.6,
    "bridge.limits.momentum_kg_m_s": 12.0,
    "bridge.limits.power_w": 60.0,
    "bridge.limits.stopping_time_s": 0.3,
    "bridge.limits.stopping_distance_m": 0.1,
    "bridge.reduced.speed_m_s": 0.2,
    "bridge.reduced.withdrawal_speed_m_s": 0.3,
    "bridge.reduced.momentum_kg_m_s": 6.0,
    "bridge.reduced.power_w": 30.0,
    "bridge.reduced.stopping_time_s": 0.2,
    "bridge.reduced.stopping_distance_m": 0.05,
    "bridge.following_error_rad": 0.1,
    "bridge.following_lag_s": 0.1,
    "bridge.report_jump_rad": 0.02,
    "bridge.report_speed_jump_rad_s": 0.5,
    "bridge.report_frozen_s": 0.2,
    "bridge.blind_pad_s": 0.5,
}


def test_every_safety_relevant_field_has_a_loosened_case() -> None:
    patterns = {re.sub(r"^gain\.effective_mass\.regions\.[^.]+\.", "gain.effective_mass.regions.<region>.",
                       re.sub(r"^gain\.overrides\.[^.]+\.", "gain.overrides.<pad>.", f)) for f in LOOSENED}
    assert patterns == set(GUARDS) | {g.field for g in plugin_guards()}


@pytest.mark.parametrize("field", sorted(LOOSENED))
def test_a_loosened_value_without_acknowledgement_is_refused_naming_it(tmp_path: Path, field: str) -> None:
    path = write(tmp_path, toml_of(field, LOOSENED[field]))
    with pytest.raises(ConfigError) as caught:
        load_profile(path)
    message = str(caught.value)
    assert "\n" not in message
    assert f"{field} = {toml_value(LOOSENED[field])}" in message  # the field and its value
    assert f"safe range {safe_range(field)}" in message  # its default's side
    assert f'acknowledge = ["{field}"]' in message and "reason" in message  # how to acknowledge it


@pytest.mark.parametrize("field", sorted(LOOSENED))
def test_an_acknowledged_loosened_value_loads_warns_once_and_is_kept(tmp_path: Path, field: str,
                                                                    caplog: pytest.LogCaptureFixture) -> None:
    path = write(tmp_path, toml_of(field, LOOSENED[field]) + acknowledge(field))
    with caplog.at_level(logging.WARNING, logger="nwr.common.config"):
        profile = load_profile(path)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and warnings[0].startswith(f"safety: {field} = ") and REASON in warnings[0]
    assert loosened_safety(profile) == [{"field": field, "value": LOOSENED[field],
                                         "default": loosened(profile)[0].default, "reason": REASON}]


def test_several_loosened_values_need_each_its_acknowledgement(tmp_path: Path) -> None:
    text = toml_of("bridge.skin_timeout_s", 5.0) + "[planner]\nsustained_contact = \"paper\"\nrelease_s = 0.1\n"
    with pytest.raises(ConfigError, match=r'acknowledge = \["planner.sustained_contact", "planner.release_s", '
                                          r'"bridge.skin_timeout_s"\]'):
        load_profile(write(tmp_path, text))
    with pytest.raises(ConfigError) as caught:  # one of three acknowledged: the other two are named
        load_profile(write(tmp_path, text + acknowledge("bridge.skin_timeout_s")))
    assert "planner.release_s = 0.1" in str(caught.value) and "planner.sustained_contact" in str(caught.value)
    assert "bridge.skin_timeout_s = " not in str(caught.value)
    profile = load_profile(write(tmp_path, text + acknowledge("bridge.skin_timeout_s", "planner.release_s",
                                                              "planner.sustained_contact")))
    assert [item["field"] for item in loosened_safety(profile)] == [
        "planner.sustained_contact", "planner.release_s", "bridge.skin_timeout_s"]


def test_a_tightened_value_needs_no_acknowledgement(tmp_path: Path) -> None:
    text = ("[bridge]\nskin_timeout_s = 0.08\ncommand_timeout_s = 0.01\n[planner]\nv_max_m_s = 0.1\nq_max_deg = "
            "[20.0, 35.0, 73.0, 36.5, 0.0, 0.0]\n[planner.task]\nperiod_s = 20.0\n[gain]\nthresholds_hpa = "
            "[1.5, 5.0, 10.0, 18.0]\nk = 8.0\nmodel = \"discrete\"\n")
    assert loosened(load_profile(write(tmp_path, text))) == []


@pytest.mark.parametrize(("text", "match"), [
    # stale: acknowledged but at its default
    (acknowledge("bridge.skin_timeout_s"), r"safety.acknowledge names bridge.skin_timeout_s, which this profile "
                                           r"does not loosen \(bridge.skin_timeout_s = 0.12, safe range <= 0.12 s\)"),
    # stale: tightened, not loosened
    ("[bridge]\nskin_timeout_s = 0.1\n" + acknowledge("bridge.skin_timeout_s"), r"does not loosen .*= 0.1,"),
    (acknowledge("gain.overrides.wrist_3.thresholds_hpa"), r"gain.overrides.wrist_3.thresholds_hpa = unset"),
    (acknowledge("bridge.skin_timeout"), r"'bridge.skin_timeout', which is no safety-relevant field"),
    (acknowledge("gain.k"), r"'gain.k', which is no safety-relevant field"),
    ("[bridge]\nskin_timeout_s = 5.0\n" + acknowledge("bridge.skin_timeout_s", "bridge.skin_timeout_s"),
     r"more than once"),
    ("[bridge]\nskin_timeout_s = 5.0\n" + acknowledge("bridge.skin_timeout_s", reason="  "), r"safety.reason is empty"),
    ('[safety]\nreason = "left over"\n', r"safety.reason is set but safety.acknowledge names nothing"),
])
def test_stale_unknown_or_unexplained_acknowledgements_are_refused(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_profile(write(tmp_path, text))


# -- hard bounds: refused whatever [safety] says -------------------------------------------------------------------

@pytest.mark.parametrize(("text", "match"), [
    # the examples of the issue
    ("[planner.task]\nperiod_s = 1\n", r"planner.task.period_s = 1.0 s .* at 2.28 m/s, above robot 'ur10e''s "
                                       r"max_point_speed = 1.0 m/s"),
    ("[planner.task]\nperiod_s = 6\n", r"planner.task.period_s = 6.0 s .* at 0.381 m/s, above "
                                       r"bridge.limits.speed_m_s = 0.25 m/s"),
    ("[planner]\nv_max_m_s = 1.0\n", r"planner.v_max_m_s = 1.0 m/s is above bridge.limits.withdrawal_speed_m_s"),
    ("[planner]\nq_max_deg = [40.0, 70.0, 146.0, 73.0, 720.0, 0.0]\n", r"<= 180.0 - at `\$.planner.q_max_deg\[4\]`"),
    ("[gain]\nk = 1e4\n", r"<= 50.0 - at `\$.gain.k`"),
    ("[gain.overrides.wrist_3]\nk = 1e4\n", r"<= 50.0 - at `\$.gain.overrides\[...\].k`"),
    ("[gain]\nk = 0.01\n", r">= 0.1 - at `\$.gain.k`"),
    ("[bridge]\nskin_timeout_s = -1\n", r"\$.bridge.skin_timeout_s"),
    ("[bridge]\ncommand_timeout_s = 0\n", r"\$.bridge.command_timeout_s"),
    ("[planner]\nreflex_duration_s = 10\n", r"\$.planner.reflex_duration_s"),
    # cross-checks
    ("[planner]\nreturn_speed_m_s = 0.2\n[bridge.limits]\nspeed_m_s = 0.15\n",
     r"planner.return_speed_m_s = 0.2 m/s is above bridge.limits.speed_m_s = 0.15 m/s"),
    ("[planner]\napproach_speed_m_s = 0.2\nreturn_speed_m_s = 0.1\n",
     r"planner.approach_speed_m_s = 0.2 m/s is above planner.return_speed_m_s = 0.1 m/s"),
    ("[gateway]\ncontact_hpa = 2.0\n", r"gateway.contact_hpa = 2.0 hPa is not below gain.thresholds_hpa\[0\]"),
    ("[gateway]\ncontact_hpa = 1.5\n[gain.overrides.wrist_1]\nthresholds_hpa = [1.2, 6.0, 12.0, 20.0]\n",
     r"not below gain.overrides.wrist_1.thresholds_hpa\[0\] = 1.2 hPa"),
    ("[gateway]\nrate_hz = 5.0\n", r"gateway.rate_hz = 5 Hz .* bridge.skin_timeout_s = 0.12 s"),
    ("[planner]\nrate_hz = 40.0\ntask_ahead_cycles = 1\n", r"planner.rate_hz = 40 Hz .* bridge.command_timeout_s"),
    ("[gain]\nthresholds_hpa = [2.0, 6.0, 12.0, 3000.0]\n", r"up to 2000 hPa"),
    ("[planner]\ntarget_order = [\"wrist_9\"]\n", r"planner.target_order names \['wrist_9'\]"),
    ("[gain.overrides.wrist_9]\nk = 4.0\n", r"gain.overrides names \['wrist_9'\]"),
    ("[planner.location.pl3]\nwrist = [0.0, 0.3, 0.6, 0.8]\n",
     r"planner.location.pl3 has no row for \['elbow', 'forearm', 'shoulder', 'upper_arm'\]"),
    ("[planner.location.pl4]\n" + "".join(f"{r} = [0.0, 0.0, 0.0, 0.0]\n" for r in
                                          ("shoulder", "upper_arm", "elbow", "forearm", "wrist", "knee")),
     r"planner.location.pl4 has rows for \['knee'\]"),
    ("[planner.task]\namplitude_rad = [0.35, 0.10, -1.5, 0.0, 0.0, 0.0]\n",
     r"planner.task.amplitude_rad\[2\] = -1.5 swings elbow_joint .* beyond its limits"),
    ("[bridge]\nq_max = [1.0, 1.0, 9.0, 1.0, 1.0, 1.0]\n", r"bridge.q_max\[2\] = 9.0 is looser"),
    ("[bridge]\ninitial_q = [0.0, -1.15, 1.85, -2.27, -1.57, 7.0]\n", r"bridge.initial_q\[5\] = 7.0 is outside"),
    ("[bridge.limits]\nspeed_m_s = 1.5\n", r"bridge.limits.speed_m_s = 1.5 m/s is beyond what the robot"),
    ("[zenoh]\nrouter = [\"10.0.0.2:7447\"]\n", r"zenoh.router: '10.0.0.2:7447' is not a Zenoh endpoint"),
    ("[bridge.ur_rtde]\nreconnect_min_s = 10.0\nreconnect_max_s = 2.0\n",
     r"bridge.ur_rtde.reconnect_min_s = 10.0 s is above"),
    ("[bridge.ur_rtde]\nservo_gain = 50.0\n", r"bridge.ur_rtde: .* >= 100.0 - at `\$.servo_gain`"),
    ("[bridge.ur_rtd]\nservo_gain = 500.0\n",
     r"\[bridge.ur_rtd\] names no backend; the backends are franky, physics, sim, ur_rtde"),
    ("[bridge.franky]\nstiffness_nm_rad = [600.0, 600.0]\n", r"bridge.franky.stiffness_nm_rad has 2 values"),
    ("[bridge]\nbackend = \"franky\"\n", r"drives Franka's 7-joint arms: the robot ur10e has 6 joints"),
    ("[planner.whole-arm]\nramp_s = 0.6\n", r"planner.whole-arm.ramp_s = 0.6 s is more than half"),
    ("[gateway.ros1]\ntopc = \"/skin\"\n", r"gateway.ros1: Object contains unknown field `topc`"),
])
def test_values_never_safe_or_meaningful_are_refused_even_acknowledged(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_profile(write(tmp_path, text))
    # an acknowledgement does not pass a hard bound (whatever it names, the bound is checked first)
    acknowledged = text + acknowledge("bridge.skin_timeout_s", "planner.task.period_s", "planner.v_max_m_s")
    with pytest.raises(ConfigError, match=match):
        load_profile(write(tmp_path, acknowledged))


def test_a_faster_task_loads_once_its_speed_limit_and_its_period_are_acknowledged(tmp_path: Path) -> None:
    text = "[planner.task]\nperiod_s = 6.0\n[bridge.limits]\nspeed_m_s = 0.4\n"
    with pytest.raises(ConfigError, match=r"planner.task.period_s = 6.0 \(default 12.0, safe range >= 12.0 s\); "
                                          r"bridge.limits.speed_m_s = 0.4"):
        load_profile(write(tmp_path, text))
    profile = load_profile(write(tmp_path, text + acknowledge("planner.task.period_s", "bridge.limits.speed_m_s")))
    assert {item.field for item in loosened(profile)} == {"planner.task.period_s", "bridge.limits.speed_m_s"}


# -- lists of the wrong length: a ConfigError naming the field, never a traceback ----------------------------------

@pytest.mark.parametrize(("text", "field"), [
    ("[planner.task]\namplitude_rad = [0.35, 0.10, -0.12, 0.0, 0.0, 0.0, 0.0]\n", "planner.task.amplitude_rad"),
    ("[planner.task]\namplitude_rad = [0.35, 0.10, -0.12, 0.0, 0.0, 0.0, 0.0]\n"
     "double_frequency = [0, 1, 1, 0, 0, 0, 0]\n", "planner.task.amplitude_rad"),
    ("[planner.task]\ndouble_frequency = [0, 1, 1]\n", "planner.task.double_frequency"),
    ("[planner]\nq_max_deg = [40.0, 70.0, 146.0, 73.0, 0.0]\n", "planner.q_max_deg"),
    *[(f"[bridge]\n{name} = [1.0]\n", f"bridge.{name}") for name in ("q_min", "q_max", "v_max", "a_max", "j_max")],
    ("[bridge]\ninitial_q = [0.0, -1.15, 1.85, -2.27, -1.57, 0.0, 0.0]\n", "bridge.initial_q"),
])
def test_a_per_joint_list_of_the_wrong_length_names_the_field(tmp_path: Path, text: str, field: str) -> None:
    with pytest.raises(ConfigError, match=rf"^{re.escape(field)} has \d values, the robot 'ur10e' has 6 joints"):
        load_profile(write(tmp_path, text))


@pytest.mark.parametrize(("text", "match"), [
    ("[planner.location.pl3]\n" + "".join(f"{r} = [0.2, 0.8, 0.6]\n" for r in
                                          ("shoulder", "upper_arm", "elbow", "forearm", "wrist")),
     r"planner.location: Expected `array` of length >= 4 - at `\$.pl3"),
    ("[gain]\nthresholds_hpa = [2.0, 6.0, 12.0]\n", r"gain: thresholds_hpa must be four increasing"),
    ("[gain.overrides.wrist_3]\nthresholds_hpa = [2.0, 6.0, 12.0, 20.0, 30.0]\n",
     r"gain.overrides.wrist_3: thresholds_hpa must be four increasing"),
])
def test_rows_and_thresholds_of_the_wrong_length_name_the_field(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_profile(write(tmp_path, text))


def test_the_robot_checks_take_the_description_given() -> None:
    desc = load_description()
    check_against_robot(Profile(), desc)
    profile = Profile()
    profile.planner.q_max_deg = list(desc.reflex_range_deg) + [0.0]
    with pytest.raises(ConfigError, match=r"planner.q_max_deg has 7 values"):
        check_against_robot(profile, desc)


# -- the sigmoid at any steepness ----------------------------------------------------------------------------------

def test_the_sigmoid_is_the_papers_formula_bit_for_bit_for_normal_k() -> None:
    for k in (0.1, 1.0, 3.0, 10.0, 50.0):
        for x in [i / 40 for i in range(-40, 81)]:
            assert sigmoid(x, k) == 1.0 / (1.0 + math.exp(-k * (x - 0.5)))


@pytest.mark.parametrize("k", [1e3, 1e4, 1e6, 1e300])
def test_the_sigmoid_does_not_overflow_for_huge_k(k: float) -> None:
    assert 0.0 <= sigmoid(0.0, k) < 1e-200 and sigmoid(1.0, k) == 1.0 and sigmoid(0.5, k) == 0.5
    assert [scaled_sigmoid(x, k) for x in (0.0, 0.25, 0.5, 0.75, 1.0)] == pytest.approx([0, 0, 0.5, 1, 1], abs=1e-100)
    thresholds = (2.0, 6.0, 12.0, 20.0)
    gains = [continuous_gain(p, thresholds, k) for p in (7.0, 9.0, 11.0, 13.0, 19.0)]
    assert gains == pytest.approx([0.0, 0.175, 0.35, 0.35, 1.0], abs=1e-100)


# -- the packaged and deployed profiles load; session metadata --------------------------------------------------

def test_every_packaged_and_deployed_profile_loads_with_nothing_loosened() -> None:
    profiles = sorted(PROFILES_DIR.glob("*.toml")) + sorted((ROOT / "deploy" / "profiles").glob("*.toml"))
    assert PROFILES_DIR / "default.toml" in profiles
    for path in profiles:
        profile = load_profile(str(path))
        assert check_acknowledgements(profile, plugin_guards(profile)) == []


def test_the_session_metadata_keeps_the_loosened_values(tmp_path: Path) -> None:
    profile = load_profile(write(tmp_path, toml_of("bridge.skin_timeout_s", 5.0)
                                 + "[planner]\nsustained_contact = \"paper\"\n"
                                 + acknowledge("bridge.skin_timeout_s", "planner.sustained_contact")))

    def meta(**extra: Any) -> dict[str, str]:
        return session_metadata(robot="ur10e", session="s1", profile_json="{}", strategy="cartesian",
                                planner="cartesian", start_time_iso="2026-11-23T00:00:00+00:00",
                                start_monotonic_ns=0, labels={}, **extra)

    assert json.loads(meta(loosened_safety=loosened_safety(profile))["loosened_safety"]) == [
        {"field": "planner.sustained_contact", "value": "paper", "default": "hold", "reason": REASON},
        {"field": "bridge.skin_timeout_s", "value": 5.0, "default": 0.12, "reason": REASON},
    ]
    assert meta(loosened_safety=loosened_safety(Profile()))["loosened_safety"] == "[]"
    assert "loosened_safety" not in meta()


@pytest.mark.e2e
@pytest.mark.slow
def test_the_recorder_warns_and_records_the_loosened_values(tmp_path: Path) -> None:
    """`nwr record` with an acknowledged profile: one warning per loosened value, and the session's metadata."""
    profile = write(tmp_path, f"[zenoh]\nbase_port = 18530\n[recorder]\ndirectory = \"{tmp_path}\"\n"
                    + toml_of("bridge.skin_timeout_s", 5.0) + acknowledge("bridge.skin_timeout_s"))
    output = tmp_path / "s.mcap"
    proc = subprocess.Popen([sys.executable, "-m", "nwr.services.cli", "--profile", profile, "record", "-o",
                             str(output)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30.0
        while not output.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(1.0)
    finally:
        proc.send_signal(signal.SIGINT)
        log = proc.communicate(timeout=30)[0]
    assert proc.returncode == 0, log
    assert len([line for line in log.splitlines() if "WARNING" in line and "safety: " in line]) == 1, log
    _records, metadata = read_recording(output)
    assert json.loads(metadata["session"]["loosened_safety"]) == [
        {"field": "bridge.skin_timeout_s", "value": 5.0, "default": 0.12, "reason": REASON}]


# -- docs/profile.md is the code's --------------------------------------------------------------------------------

def _number(value: float | int) -> str:
    return repr(value) if isinstance(value, int) else f"{value:.6g}"


def _bound(t: Any) -> str:
    """The hard bound a field's type carries (msgspec.Meta), as docs/profile.md begins its cell."""
    if isinstance(t, mi.UnionType):
        inner = [x for x in t.types if not isinstance(x, mi.NoneType)]
        bound = _bound(inner[0]) if len(inner) == 1 else ""
        return f"{bound}, or unset" if bound else ""
    if isinstance(t, (mi.FloatType, mi.IntType)):
        return ", ".join(f"{symbol} {_number(getattr(t, attr))}"
                         for attr, symbol in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))
                         if getattr(t, attr) is not None)
    if isinstance(t, mi.ListType):
        parts = [f"{t.min_length} values"] if t.min_length is not None and t.min_length == t.max_length else []
        inner = _bound(t.item_type)
        return ", ".join(parts + ([f"each {inner}"] if inner else []))
    if isinstance(t, mi.LiteralType):
        return "one of " + ", ".join(toml_value(v) for v in t.values)
    if isinstance(t, mi.StrType) and t.pattern:
        return f"matches `{t.pattern}`"
    return ""


def _fields() -> dict[str, tuple[Any, str]]:
    """Every field of Profile by dotted name -> (default, hard bound); a table of pads' overrides as <pad>,
    the location weights' rows one by one."""
    found: dict[str, tuple[Any, str]] = {}

    def walk(prefix: str, struct: mi.StructType, default: Any) -> None:
        for field in struct.fields:
            if field.name == "plugins":  # the plug-ins' tables: each one's Settings below
                continue
            name, t, value = f"{prefix}{field.name}", field.type, getattr(default, field.name)
            if name in config.ROBOT_HELD:  # documented as the default robot's value
                value = config.robot_default(DEFAULT, name)
            if isinstance(t, mi.StructType):
                walk(f"{name}.", t, value)
            elif isinstance(t, mi.DictType) and isinstance(t.value_type, mi.StructType):
                walk(f"{name}.{'<region>' if field.name == 'regions' else '<pad>'}.", t.value_type,
                     t.value_type.cls())
            elif isinstance(t, mi.DictType) and not value:  # a table by pad name, empty by default: one row
                found[name] = (value, _bound(t.value_type))
            elif isinstance(t, mi.DictType):
                assert value, name  # a table of rows documents its default rows
                for key, row in value.items():
                    found[f"{name}.{key}"] = (row, _bound(t.value_type))
            else:
                found[name] = (value, _bound(t))

    info = mi.type_info(Profile)
    assert isinstance(info, mi.StructType)
    walk("", info, DEFAULT)
    for kind in kinds():
        for plugin in kind.names():
            cls = kind.settings_class(plugin)
            settings = mi.type_info(cls)
            assert isinstance(settings, mi.StructType)
            robot = getattr(kind.declared(plugin), "robot_settings", None)  # its defaults: the robot's
            walk(f"{kind.section}.{plugin}.", settings, robot(DESC) if robot else cls())
    return found


def _rows() -> dict[str, list[str]]:
    rows: dict[str, list[str]] = {}
    for line in DOC.read_text().splitlines():
        if line.startswith("| `"):
            cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
            assert len(cells) == 6, line
            name = cells[0].strip("`")
            assert name not in rows, f"{name} has two rows"
            rows[name] = cells
    return rows


def test_every_field_of_the_profile_has_one_row_in_docs_profile_md() -> None:
    assert set(_rows()) == set(_fields())


def test_the_documented_defaults_bounds_and_safe_ranges_are_the_codes() -> None:
    rows = _rows()
    for name, (default, bound) in _fields().items():
        _name, doc_default, hard, safe, unit, why = rows[name]
        assert doc_default == f"`{toml_value(default)}`", name
        assert hard.startswith(bound) and hard, name  # the Meta bound first, then the cross-checks
        pattern = name.replace(name.split(".")[2], "<pad>") if name.startswith("gain.overrides.") else name
        pattern = name if "<region>" in name else pattern
        plugins = {g.field: g for g in plugin_guards()}
        if pattern in GUARDS or name in plugins:
            assert safe == safe_range(name), name
            assert unit == (GUARDS[pattern] if pattern in GUARDS else plugins[name].guard).unit, name
        else:
            assert safe == "any", name
        assert why, name


def test_the_safe_range_is_the_side_of_the_default_that_does_not_loosen() -> None:
    assert safe_range("bridge.skin_timeout_s") == "<= 0.12 s"
    assert safe_range("planner.task.period_s") == ">= 12.0 s"
    assert safe_range("planner.sustained_contact") == '= "hold"'
    assert safe_range("planner.task.amplitude_rad") == "each magnitude <= [0.35, 0.1, 0.12, 0.0, 0.0, 0.0] rad"
    assert safe_range("gain.overrides.wrist_3.thresholds_hpa") == "each <= [2.0, 6.0, 12.0, 20.0] hPa"


# -- plug-in tables; profiles written before the tables moved ------------------------------------------------------

LEGACY = """[planner]
uniform_fraction = 0.4
smooth_ramp_s = 0.05
[planner.location_weights.pl3]
shoulder = [0.1, 0.8, 0.6, 0.0]
upper_arm = [0.2, 0.8, 0.6, 0.0]
elbow = [0.0, 0.6, 0.8, 0.2]
forearm = [0.0, 0.6, 0.8, 0.2]
wrist = [0.0, 0.3, 0.6, 0.8]
[planner.whole_arm]
duration_s = 0.8
[bridge]
servo_gain = 500.0
watchdog_hz = 5.0
"""
CURRENT = """[planner.uniform]
fraction = 0.4
[planner.cartesian-smooth]
ramp_s = 0.05
[planner.location.pl3]
shoulder = [0.1, 0.8, 0.6, 0.0]
upper_arm = [0.2, 0.8, 0.6, 0.0]
elbow = [0.0, 0.6, 0.8, 0.2]
forearm = [0.0, 0.6, 0.8, 0.2]
wrist = [0.0, 0.3, 0.6, 0.8]
[planner.whole-arm]
duration_s = 0.8
[bridge.ur_rtde]
servo_gain = 500.0
watchdog_hz = 5.0
"""


def test_a_profile_written_before_the_plug_in_tables_loads_as_its_current_form(tmp_path: Path) -> None:
    old = load_profile(write(tmp_path, LEGACY + acknowledge("bridge.watchdog_hz", "planner.whole_arm.duration_s"),
                             "old.toml"))
    new = load_profile(write(tmp_path, CURRENT + acknowledge("bridge.ur_rtde.watchdog_hz",
                                                             "planner.whole-arm.duration_s"), "new.toml"))
    assert old == new
    assert old.safety.acknowledge == ["bridge.ur_rtde.watchdog_hz", "planner.whole-arm.duration_s"]
    assert old.planner.plugins["uniform"]["fraction"] == 0.4
    assert old.planner.plugins["location"]["pl3"]["shoulder"] == [0.1, 0.8, 0.6, 0.0]
    assert old.planner.plugins["location"]["pl4"] == {}  # the rest: its default, the robot's table
    # a session's journaled profile (JSON, as a recording keeps it) decodes the same, either form
    journaled = json.loads(msgspec.json.encode(new))
    assert config.decode_profile(journaled, "journal") == new


def test_every_plug_in_table_is_resolved_in_full_for_the_journal() -> None:
    profile = load_profile(None)
    for kind in kinds():
        section = getattr(profile, kind.section)
        assert sorted(section.plugins) == sorted(kind.names())
        for name in kind.names():
            assert section.plugins[name] == msgspec.to_builtins(kind.settings_class(name)())


def test_a_service_checks_its_own_plug_ins_and_leaves_the_others_to_theirs(tmp_path: Path) -> None:
    loosened_bridge = "[bridge.ur_rtde]\nwatchdog_hz = 5.0\n"
    path = write(tmp_path, loosened_bridge + acknowledge("bridge.ur_rtde.watchdog_hz"))
    gain = load_profile(path, sections=())  # the gain runs no plug-in: the bridge's table as written
    assert gain.bridge.plugins["ur_rtde"] == {"watchdog_hz": 5.0}
    assert "whole-arm" not in gain.planner.plugins
    bridge = load_profile(path, sections=("bridge",))
    assert bridge.bridge.plugins["ur_rtde"]["servo_gain"] == 300.0  # resolved in full for its journal
    with pytest.raises(ConfigError, match=r"bridge.ur_rtde.watchdog_hz = 5.0 .* safe range >= 10.0 Hz"):
        load_profile(write(tmp_path, loosened_bridge, "bare.toml"), sections=("bridge",))
