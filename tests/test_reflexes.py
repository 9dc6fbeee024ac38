"""The paper's joint-space reflexes at hand-computed values, the retreat check and the guard."""

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.robot import RobotModel, load_description
from nwr.services.gain.core import continuous_gain
from nwr.services.planner import strategies
from nwr.services.planner.core import Planner
from nwr.services.planner.reflexes import JOINT_MARGIN_RAD, smooth_profile
from nwr.services.planner.retreat import assess

DESC = load_description()
MODEL = RobotModel(DESC)
SIGN = np.array([1, -1, 1, 1, 1, 1])
T = (2.0, 6.0, 12.0, 20.0)


def joint_reflex(name):
    return strategies.build(PlannerSection(strategy=name), DESC, MODEL, 0.9 * DESC.v_max)


def contact(pad_name, p_hpa, level):
    pad = DESC.pad(pad_name)
    return m.Contact(pad=pad.id, name=pad.name, region=pad.region, change_hpa=p_hpa, level=level,
                     gain=continuous_gain(p_hpa, T))


def test_reflex_directions_are_robot_data():
    np.testing.assert_array_equal(DESC.reflex_direction, SIGN)


def test_joint_targets_stay_inside_the_joint_ranges_by_the_margin():
    """A target on the limit itself had the bridge brake the arm short of it (joint_limit), off the plan."""
    ur = joint_reflex("uniform")
    q = DESC.home.copy()
    q[2] = DESC.q_max[2] - 0.5  # the elbow's 73 deg of flexion would pass its limit
    target = ur.target(q, contact("forearm_top", 25.0, 4))
    assert target[2] == pytest.approx(DESC.q_max[2] - JOINT_MARGIN_RAD)
    q[2] = DESC.q_max[2] - JOINT_MARGIN_RAD / 2  # already inside the margin: it stays, never pulled back
    assert ur.target(q, contact("forearm_top", 25.0, 4))[2] == q[2]


def test_uniform_adds_half_q_max_whatever_the_gain():
    ur = joint_reflex("uniform")
    q = DESC.home.copy()
    expected = q + SIGN * np.radians([20, 35, 73, 36.5, 0, 0])
    for p, level in ((6.5, 3), (25.0, 4)):
        np.testing.assert_allclose(ur.target(q, contact("forearm_top", p, level)), expected, atol=1e-12)


def test_uniform_clips_to_the_joint_limits():
    ur = joint_reflex("uniform")
    q = np.array([0.0, -1.0, 2.5, -2.0, -1.57, 0.0])  # elbow at 2.5 rad: +73 deg passes pi
    target = ur.target(q, contact("wrist_1", 16.0, 4))
    assert target[2] == pytest.approx(np.pi - JOINT_MARGIN_RAD)  # inside the URDF's elbow limit
    np.testing.assert_allclose(target[[0, 1, 3]], q[[0, 1, 3]] + SIGN[[0, 1, 3]] * np.radians([20, 35, 36.5]))


def test_location_pl3_upper_arm_by_hand():
    lr = joint_reflex("location")
    q = DESC.home.copy()
    c = contact("upper_arm_top", 9.0, 3)
    assert c.gain == pytest.approx(0.175)
    expected = q + SIGN * np.radians(0.175 * np.array([0.2 * 40, 0.8 * 70, 0.6 * 146, 0, 0, 0]))
    np.testing.assert_allclose(lr.target(q, c), expected, atol=1e-12)


@pytest.mark.parametrize(
    ("pad", "level", "p", "weights"),
    [
        ("shoulder_outer", 3, 9.0, [0.2, 0.8, 0.6, 0.0]),
        ("upper_arm_bottom", 3, 9.0, [0.2, 0.8, 0.6, 0.0]),
        ("elbow_outer", 3, 9.0, [0.0, 0.6, 0.8, 0.2]),
        ("forearm_top", 3, 9.0, [0.0, 0.6, 0.8, 0.2]),
        ("wrist_2", 3, 9.0, [0.0, 0.3, 0.6, 0.8]),
        ("shoulder_back", 4, 16.0, [0.5, 1.0, 0.7, 0.1]),
        ("upper_arm_top", 4, 16.0, [0.5, 1.0, 0.7, 0.1]),
        ("elbow_outer", 4, 16.0, [0.0, 0.8, 1.0, 0.4]),
        ("forearm_bottom", 4, 16.0, [0.0, 0.8, 1.0, 0.4]),
        ("wrist_3", 4, 16.0, [0.0, 0.6, 0.8, 1.0]),
    ],
)
def test_location_table_ii(pad, level, p, weights):
    lr = joint_reflex("location")
    c = contact(pad, p, level)
    g = 0.175 if level == 3 else 0.675
    assert c.gain == pytest.approx(g)
    w = np.array(weights[:3] + [weights[3]] * 3)
    expected = np.radians(g * w * np.array([40, 70, 146, 73, 0, 0]))
    np.testing.assert_allclose(lr.displacement(c), expected, atol=1e-12)


def test_location_pl1_2_does_not_move():
    lr = joint_reflex("location")
    np.testing.assert_array_equal(lr.displacement(contact("wrist_1", 4.0, 2)), np.zeros(6))


def test_smooth_profile_keeps_the_displacement_and_ramps():
    t = np.arange(0, 0.5, 1e-4)
    s = np.array([smooth_profile(x, 0.5, 0.1) for x in t])
    assert s.sum() * 1e-4 == pytest.approx(0.5, rel=1e-3)
    assert s[0] == pytest.approx(0.0) and s[-1] == pytest.approx(0.0, abs=1e-3)
    assert np.max(np.abs(np.diff(s))) < 0.01  # no step


def start(strategy, pad, gain=1.0, guarded=False, level=4, sustained="hold"):
    planner = Planner(PlannerSection(strategy=strategy, guarded=guarded, sustained_contact=sustained), DESC, MODEL)
    planner.on_state(DESC.home.copy(), following=True)
    while planner.mode != "TASK":
        planner.step(0)
    info = DESC.pad(pad)
    c = m.Contact(pad=info.id, name=info.name, region=info.region, change_hpa=25.0, level=level, gain=gain)
    gains = [0.0] * len(DESC.pads)
    gains[info.id] = gain
    pain = m.SkinPain(seq=1, stamp_ns=0, trace=m.Trace(1, 0), model="continuous", level=[1] * len(gains),
                      gain=gains, strongest=c)
    first = planner.on_pain(pain, 0)
    return planner, first


@pytest.mark.parametrize("sustained", ["hold", "paper"])
@pytest.mark.parametrize("strategy", ["uniform", "location"])
def test_joint_reflexes_are_position_controlled_and_reach_their_target(strategy, sustained):
    planner, first = start(strategy, "wrist_2", sustained=sustained)
    assert isinstance(first, m.PositionCommand) and first.phase == "REFLEX"
    target = planner.reflex.target.copy()
    while planner.mode == "REFLEX":
        planner.step(0)
    # The paper returns at once; hold mode holds first, while the touch may last.
    assert planner.mode == ("HOLDING" if sustained == "hold" else "RETURNING")
    np.testing.assert_allclose(planner.q, target, atol=1e-6)


def test_retreat_check_finds_the_uniform_reflex_pushing_into_the_person():
    # At home the upper arm's top pad faces back and up; the uniform reflex
    # lifts the upper arm back over the base: the pad goes toward the hand.
    planner, _ = start("uniform", "upper_arm_top")
    r = planner.assess()
    assert r.approached and r.toward_m > 0.1
    assert max(r.normal_speed_m_s) > 0.1  # m/s toward the contact at some point
    assert not r.corrected
    assert r.withdrawal_m < 0


def test_guarded_mode_corrects_it():
    planner, _ = start("uniform", "upper_arm_top", guarded=True)
    r = planner.assess()
    assert r.corrected and not r.approached
    assert r.toward_m <= 1e-3 and r.withdrawal_m > 0.05
    # and the arm then follows the corrected motion
    path = []
    while planner.mode == "REFLEX":
        planner.step(0)
        path.append(planner.q.copy())
    measured = assess(MODEL, np.array(path), 0.002, DESC.pad("upper_arm_top").id)
    assert measured.toward_m <= 1e-3


def test_guarded_mode_leaves_retreating_reflexes_alone():
    plain, _ = start("uniform", "forearm_top")
    guarded, _ = start("uniform", "forearm_top", guarded=True)
    np.testing.assert_allclose(plain.reflex.target, guarded.reflex.target)
    assert not guarded.assess().corrected


@pytest.mark.parametrize("strategy", ["cartesian", "cartesian-smooth"])
def test_cartesian_reflexes_retreat(strategy):
    planner, first = start(strategy, "wrist_3", gain=0.8)
    assert isinstance(first, m.VelocityCommand)
    r = planner.assess()
    assert not r.approached
    assert r.withdrawal_m == pytest.approx(0.25 * 0.8 * 0.5, rel=0.05)
    assert len(r.approach_m) == len(DESC.pads) and r.approach_m[DESC.pad("wrist_3").id] == 0.0


def test_smooth_cartesian_has_no_velocity_step():
    planner, first = start("cartesian-smooth", "wrist_3")
    speeds = [np.abs(first.dq).max()]
    while planner.mode == "REFLEX":
        cmd = planner.step(0)
        if isinstance(cmd, m.VelocityCommand):
            speeds.append(np.abs(cmd.dq).max())
    assert speeds[0] < 0.01 and speeds[-1] < 0.05
    assert max(speeds) > 0.3


def test_target_pad_moves_on_after_each_touch_in_a_reproducible_order():
    a = Planner(PlannerSection(), DESC, MODEL)
    b = Planner(PlannerSection(), DESC, MODEL)
    assert a.targets == b.targets and sorted(a.targets) == list(range(len(DESC.pads)))
    first = a.target_pad
    levels = [1] * len(DESC.pads)
    levels[first] = 2
    touch = m.SkinPain(seq=1, stamp_ns=0, trace=m.Trace(1, 0), model="c", level=levels, gain=[0.0] * 10)
    a.on_pain(touch, 0)
    assert a.target_pad == a.targets[1]
    a.on_pain(touch, 0)  # still the same touch: no change
    assert a.target_pad == a.targets[1]
    assert a.status(0).target_pad == a.targets[1]
