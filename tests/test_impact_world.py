"""The effective-mass model's predicted impact force beside the force the physics world measures: the arm runs
into a finger held in its way (``in_the_way``), in lockstep, re-run bit for bit by ``nwr verify``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import GainSection, Profile
from nwr.common.launch import load_script
from nwr.common.recordings import Recorded, read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.tools.recordings.impact_check import ImpactRow, format_rows, impact_rows, world_free_collision_n
from nwr.services.worlds.hosted import check_script, finger_force
from nwr.services.worlds.people import KINDS
from nwr.services.worlds.settings import PhysicsSettings

DESC = load_description()
ROBOT = RobotModel(DESC)
SETTINGS = PhysicsSettings()


def test_the_world_free_collision_by_hand():
    # 0.1 m/s, m = 8 kg against the world's finger (500 N/m, 0.6 kg): 0.1 * 22.36 / sqrt(0.125 + 1.667) = 1.670 N
    assert world_free_collision_n(0.1, 8.0, 500.0, 0.6) == pytest.approx(1.670, abs=1e-3)
    assert world_free_collision_n(0.1, 0.0, 500.0, 0.6) == pytest.approx(0.1 * math.sqrt(500.0 * 0.6))
    assert world_free_collision_n(-0.1, 8.0, 500.0, 0.6) == 0.0  # moving away: no collision


def test_the_ratio_of_a_row():
    row = ImpactRow(touch=0, pad="wrist_1", kind="finger", t_s=0.0, speed_m_s=0.1, into_m_s=0.1, basis="state",
                    mass_kg=8.0, predicted_n=50.0, measured_n=5.0, pushed_mm=1.0)
    assert row.ratio == pytest.approx(0.1)
    assert row.ran_into
    assert not ImpactRow(**{**row.__dict__, "pushed_mm": 0.5}).ran_into  # a press on a pad that barely moved
    assert not ImpactRow(**{**row.__dict__, "into_m_s": -0.1}).ran_into  # the pad moving away from the part
    assert ImpactRow(**{**row.__dict__, "predicted_n": 0.0}).ratio == math.inf
    assert ImpactRow(**{**row.__dict__, "predicted_n": 0.0, "measured_n": 0.0}).ratio == 0.0


def _person(force: float, peak: float, pushed: float, pads: list[int]) -> m.WorldPerson:
    return m.WorldPerson(name="touch-4", kind="finger", touch=4, pads=pads, force_n=force, peak_force_n=peak,
                         pressure_n_cm2=0.0, peak_pressure_n_cm2=0.0, energy_j=0.0, pushed_m=pushed,
                         peak_pushed_m=pushed)


def test_the_prediction_is_the_first_pain_message_after_first_contact_and_the_measurement_the_parts_peak():
    pad = DESC.pad("wrist_1").id
    q, dq = np.asarray(DESC.home, dtype=float), np.array([0.0, 0.0, 0.0, 0.4, 0.0, 0.0])
    n = len(DESC.pads)
    ms = 1_000_000

    def state(t: int, speed: np.ndarray) -> Recorded:
        return Recorded("robot/state", t, m.RobotState(seq=t, stamp_ns=t, q=list(q), dq=list(speed), status="ok",
                                                        owner="", backend="physics"))

    def pain(t: int, force: float) -> Recorded:
        impact = [0.0] * n
        impact[pad] = force
        return Recorded("skin/pain", t, m.SkinPain(seq=t, stamp_ns=t, trace=m.Trace(seq=t, stamp_ns=t),
                                                   model="effective-mass", level=[1] * n, gain=[0.0] * n,
                                                   effective_mass_kg=[7.0] * n, impact_n=impact,
                                                   threshold_scale=[1.0] * n, impact_basis="state"))

    def contacts(t: int, person: m.WorldPerson) -> Recorded:
        return Recorded("world/contacts", t, m.WorldContacts(seq=t, stamp_ns=t, world_ns=t, people=[person]))

    records = [state(0, np.zeros(6)), pain(5 * ms, 50.0), contacts(8 * ms, _person(0.0, 0.0, 0.0, [])),
               state(10 * ms, np.zeros(6)), contacts(12 * ms, _person(3.0, 3.0, 0.0, [pad])), pain(15 * ms, 70.0),
               state(20 * ms, dq), contacts(30 * ms, _person(9.0, 9.0, 0.004, [pad])),
               contacts(40 * ms, _person(1.0, 9.0, 0.002, [pad]))]
    rows = impact_rows(records, DESC, ROBOT)
    assert len(rows) == 1
    row = rows[0]
    velocity = ROBOT.pad_jacobians(q)[pad] @ dq  # the first state at or after first contact (12 ms): 20 ms
    assert (row.pad, row.touch, row.kind, row.basis) == ("wrist_1", 4, "finger", "state")
    assert row.t_s == pytest.approx(0.012)
    assert (row.predicted_n, row.mass_kg, row.measured_n) == (70.0, 7.0, 9.0)
    assert row.pushed_mm == pytest.approx(4.0)
    assert row.speed_m_s == pytest.approx(np.linalg.norm(velocity))
    assert row.into_m_s == pytest.approx(velocity @ ROBOT.pad_normal(q, pad))
    assert "wrist_1" in format_rows(rows, 500.0, {"finger": 0.6})
    # The paper's models predict nothing: no rows.
    assert impact_rows([r for r in records if r.key != "skin/pain"], DESC, ROBOT) == []


def test_the_packaged_script_puts_a_finger_on_wrist_1_at_the_start_below_every_threshold():
    script = load_script("in_the_way")
    assert [t.pad for t in script.touch] == ["wrist_1"] and script.touch[0].peak_hpa < 2.0
    check_script(script, SETTINGS, DESC, np.asarray(DESC.home, dtype=float))


@pytest.mark.slow
def test_the_arm_running_into_a_finger_measures_less_than_predicted_and_more_than_a_free_collision(tmp_path: Path):
    """The task drives wrist_1 along its outward normal into a finger resting on it (0.6 N). The prediction (ISO/TS
    15066: a hand's 75,000 N/m and 5.6 kg, a free collision) is an upper bound on what the world measures: its
    finger is a 0.6 kg sphere on a 500 N/m critically damped spring against a compliant cushion, so the same
    energy gives a far smaller force. The arm is servo-driven and goes on pushing until the planner stops it: the
    measurement exceeds the free collision with the world's own finger (the same formula with its k and mass)."""
    from nwr.services.tools.recordings.replay import simulate
    from nwr.services.tools.recordings.verify import verify

    profile = Profile(gain=GainSection(model="effective-mass"))
    profile.bridge.backend, profile.gateway.source = "physics", "physics"
    path = simulate(profile, "in_the_way", "cartesian", tmp_path / "in_the_way.mcap")[0]
    records, _ = read_recording(path)
    rows = impact_rows(records, DESC, ROBOT)
    assert len(rows) == 1, rows
    row = rows[0]
    assert row.pad == "wrist_1" and row.kind == "finger" and row.basis == "state" and row.ran_into
    assert row.into_m_s > 0.08  # the task drives the pad into the finger
    preload = finger_force(load_script("in_the_way").touch[0].peak_hpa, SETTINGS)
    assert row.measured_n > 3.0 * preload and row.pushed_mm > 2.0  # the arm's motion made the press, not the finger
    free = world_free_collision_n(row.into_m_s, row.mass_kg, SETTINGS.person_stiffness_n_m, KINDS["finger"].mass_kg)
    assert free < row.measured_n < row.predicted_n, format_rows(rows, SETTINGS.person_stiffness_n_m, {"finger": 0.6})
    assert row.predicted_n < 280.0  # the default task stays below the hand's transient limit
    assert {r.service: r.verdict for r in verify(path)} == {
        "gateway": "identical", "gain": "identical", "planner-cartesian": "identical", "bridge": "identical"}
