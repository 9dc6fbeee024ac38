"""The paper's strategies with every active contact (docs/reflexes.md "Every contact counts").

One contact gives exactly the published motion; with two, LR sums its
joint-space displacements (each joint at most q_max), UR keeps its own, CR
and CR-smooth stack the other pad's rows, guarded mode keeps every
touched pad from moving toward its contact (checked with the full
kinematics over the planned path), and the retreat check reports every
other touched pad. In lockstep, the second touched pad of two hands is no
longer pushed into its hand.
"""

from __future__ import annotations

from pathlib import Path

import msgspec
import numpy as np
import pytest
from planner_support import running
from scipy.optimize import minimize

from nwr.common import messages as m
from nwr.common.config import PlannerSection, Profile
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner import strategies
from nwr.services.planner.contacts import ContactPoint
from nwr.services.planner.reflex import integrate_stream
from nwr.services.planner.reflexes import damped_pinv
from nwr.services.planner.retreat import TOLERANCE_M, assess, guard_velocity
from nwr.services.planner.strategies.cartesian import Cartesian
from nwr.services.planner.strategies.location import Location
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.replay import simulate

DESC = load_description()
MODEL = RobotModel(DESC)
NAMES = [pad.name for pad in DESC.pads]
HOME = DESC.home.copy()


def pad(name: str) -> int:
    return NAMES.index(name)


def contact(name: str, gain: float = 1.0, level: int = 4) -> m.Contact:
    i = pad(name)
    return m.Contact(pad=i, name=name, region=DESC.pads[i].region, change_hpa=20.0, level=level, gain=gain)


def touch(name: str, gain: float, level: int = 4, q: np.ndarray = HOME) -> ContactPoint:
    i = pad(name)
    return ContactPoint(i, MODEL.pad_point(q, i), MODEL.pad_normal(q, i), gain, 0, 0, level)


def build(strategy: str, **cfg: object) -> strategies.ReflexStrategy:
    section = msgspec.convert({"strategy": strategy, **cfg}, PlannerSection)
    return strategies.build(section, DESC, MODEL, section.speed_fraction * DESC.v_max)


def planned(strategy: strategies.ReflexStrategy, main: str, others: list[ContactPoint],
            gain: float = 1.0) -> np.ndarray:
    """The reflex's planned joint path from home: the straight way to its target (position mode: the way the
    guard checks) or its integrated stream."""
    strategy.set_contacts(HOME, others, pad(main))
    onset = strategy.start(HOME, contact(main, gain))
    if strategy.mode == "position":
        assert onset.target is not None
        return np.array([HOME + s * (onset.target - HOME) for s in np.linspace(0.0, 1.0, 41)])
    return integrate_stream(strategy, HOME, 0.0, strategy.duration_s, DESC.q_min, DESC.q_max, 100)[0]


def toward(path: np.ndarray, name: str) -> tuple[float, float]:
    """How far pad ``name`` ever moves toward where it is at the path's start, along its normal there, and where
    it ends away from it, m (full kinematics at every sample)."""
    i = pad(name)
    p0, n0 = MODEL.pad_point(path[0], i), MODEL.pad_normal(path[0], i)
    along = np.array([(MODEL.pad_point(q, i) - p0) @ n0 for q in path])
    return float(along.max()), float(-along[-1])


# -- one contact: the published motion, bit for bit ------------------------------------------------------------

@pytest.mark.parametrize("name", ["uniform", "location", "cartesian", "cartesian-smooth"])
def test_one_contact_gives_exactly_the_published_motion(name: str) -> None:
    alone, given = build(name), build(name)
    idle = [touch("forearm_bottom", 0.0, level=0), touch("upper_arm_top", 0.0, level=2)]  # recent, not active
    a = planned(alone, "forearm_top", [], gain=0.7)
    b = planned(given, "forearm_top", [touch("forearm_top", 0.7), *idle], gain=0.7)
    np.testing.assert_array_equal(a, b)


def test_the_cartesian_stream_of_one_contact_is_the_papers_formula() -> None:
    stream = build("cartesian")
    stream.set_contacts(HOME, [touch("wrist_1", 0.0, level=0)], pad("forearm_top"))
    stream.start(HOME, contact("forearm_top", 0.6))
    jac = MODEL.pad_jacobian(HOME, pad("forearm_top"))
    moving = np.any(jac != 0.0, axis=0)
    twist = np.concatenate([-0.25 * 0.6 * MODEL.pad_normal(HOME, pad("forearm_top")), np.zeros(3)])
    expected = np.zeros(6)
    expected[moving] = damped_pinv(jac[:, moving], 0.05, 0.05) @ twist
    np.testing.assert_array_equal(stream.velocity(HOME, 0.0), expected)


# -- LR: the joint-space sum -------------------------------------------------------------------------------------

def test_location_sums_every_contacts_displacement_and_clips_each_joint_at_q_max() -> None:
    lr = build("location")
    assert isinstance(lr, Location)
    forearm, wrist = lr.weights[4]["forearm"], lr.weights[3]["wrist"]
    lr.set_contacts(HOME, [touch("wrist_1", 0.5, level=3)], pad("forearm_top"))
    expected = np.minimum(0.6 * forearm * lr.q_max + 0.5 * wrist * lr.q_max, lr.q_max)
    np.testing.assert_allclose(lr.displacement(contact("forearm_top", 0.6)), expected, rtol=1e-12)
    assert np.all(0.6 * forearm * lr.q_max + 0.5 * wrist * lr.q_max <= lr.q_max)  # no clip needed here
    # Two hands at full gain on the forearm: the elbow no farther than q_max (1 + 1 would double it).
    lr.set_contacts(HOME, [touch("forearm_bottom", 1.0)], pad("forearm_top"))
    both = lr.displacement(contact("forearm_top", 1.0))
    np.testing.assert_allclose(both, np.minimum(2 * forearm * lr.q_max, lr.q_max), rtol=1e-12)
    assert np.any(2 * forearm * lr.q_max > lr.q_max) and np.all(both <= lr.q_max)
    # A felt touch below a reflex's level (PL 2, no gain) adds nothing.
    lr.set_contacts(HOME, [touch("forearm_bottom", 0.0, level=2)], pad("forearm_top"))
    np.testing.assert_array_equal(lr.displacement(contact("forearm_top", 0.6)), 0.6 * forearm * lr.q_max)


def test_uniform_moves_the_same_with_two_contacts() -> None:
    ur = build("uniform")
    one = planned(ur, "forearm_top", [])
    two = planned(ur, "forearm_top", [touch("upper_arm_top", 0.8)])
    np.testing.assert_array_equal(one, two)


# -- CR: the stacked rows --------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["cartesian", "cartesian-smooth"])
def test_the_cartesian_stream_withdraws_both_touched_pads(name: str) -> None:
    # upper_arm_bottom's reflex alone pushes forearm_top 2.8 mm into its hand at home.
    pushed, _ = toward(planned(build(name), "upper_arm_bottom", []), "forearm_top")
    assert pushed > 0.002
    path = planned(build(name), "upper_arm_bottom", [touch("forearm_top", 0.6)])
    for touched in ("upper_arm_bottom", "forearm_top"):
        ahead, away = toward(path, touched)
        assert ahead <= TOLERANCE_M and away >= 0.008, (touched, ahead, away)  # both about 12 mm


def test_the_other_pads_normal_is_taken_at_the_restart_and_kept() -> None:
    cr = build("cartesian")
    assert isinstance(cr, Cartesian)
    cr.set_contacts(HOME, [touch("upper_arm_bottom", 0.6)], pad("forearm_bottom"))
    cr.start(HOME, contact("forearm_bottom"))
    before = cr.velocity(HOME, 0.0)
    cr.set_contacts(HOME, [], pad("forearm_bottom"))  # the other hand lifts during the reflex: kept until a restart
    np.testing.assert_array_equal(cr.velocity(HOME, 0.1), before)
    cr.start(HOME, contact("forearm_bottom"))  # restarted: the paper's stream again
    alone = build("cartesian")
    alone.start(HOME, contact("forearm_bottom"))
    np.testing.assert_array_equal(cr.velocity(HOME, 0.0), alone.velocity(HOME, 0.0))


# -- guarded mode: every touched pad ---------------------------------------------------------------------------

@pytest.mark.parametrize(("name", "main", "other"), [
    ("uniform", "forearm_top", "upper_arm_top"),
    ("location", "forearm_top", "upper_arm_top"),
    ("location", "forearm_bottom", "upper_arm_top"),
    ("cartesian", "wrist_2", "forearm_bottom"),
    ("cartesian-smooth", "wrist_2", "upper_arm_top"),
])
def test_guarded_mode_keeps_every_touched_pad_from_its_contact(name: str, main: str, other: str) -> None:
    plain = planned(build(name), main, [touch(other, 0.6)])
    guarded = planned(build(name, guarded=True), main, [touch(other, 0.6)])
    assert toward(plain, other)[0] > 0.005
    for touched in (main, other):
        assert toward(guarded, touched)[0] <= TOLERANCE_M, touched
    assert max(toward(guarded, main)[1], toward(guarded, other)[1]) >= 0.02  # and the arm still withdraws


def test_the_velocity_guard_meets_every_pad_where_one_projection_after_another_would_not() -> None:
    # Two pads whose gradients are 120 degrees apart: removing the first one's push, then the second's, pushes
    # the first again.
    g1, g2 = np.array([1.0, 0.0, 0.0]), np.array([-0.5, np.sqrt(3) / 2, 0.0])
    dq = np.array([1.0, 1.0, 0.3])
    sequential = dq - (g1 @ dq) * g1
    sequential = sequential - (g2 @ sequential) * g2
    assert g1 @ sequential > 0.1  # the first pad pushed again
    out, corrected = guard_velocity(np.eye(3), g1, dq, [(np.eye(3), g2)])
    assert corrected and g1 @ out <= 1e-9 and g2 @ out <= 1e-9
    # The nearest such velocity: both constraints bind; the rest of dq stays.
    np.testing.assert_allclose(out, [0.0, 0.0, 0.3], atol=1e-9)


@pytest.mark.parametrize("rows", [3, 9])  # 9: more touched pads than joints, the cone may be the origin
def test_the_velocity_guard_is_the_nearest_velocity_that_pushes_no_pad(rows: int) -> None:
    rng = np.random.default_rng(7)
    for _ in range(50):
        grads = rng.normal(size=(rows, 6))
        grads[-1] = 2.0 * grads[0]  # two pads asking the same: dependent rows
        dq = rng.normal(size=6)
        out, corrected = guard_velocity(np.eye(6), grads[0], dq, [(np.eye(6), g) for g in grads[1:]])
        assert np.all(grads @ out <= 1e-9), grads @ out
        assert corrected == bool(np.any(grads @ dq > 0.0))
        # The nearest such velocity, checked against a general solver (SLSQP) from its own start, and the
        # projection's orthogonality: what is removed is orthogonal to what is kept.
        reference = minimize(lambda x, dq=dq: float((x - dq) @ (x - dq)), np.zeros(6), method="SLSQP",
                             constraints=[{"type": "ineq", "fun": lambda x, g=grads: -(g @ x)}]).x
        assert np.all(grads @ reference <= 1e-6)
        assert np.linalg.norm(dq - out) <= np.linalg.norm(dq - reference) + 1e-6
        assert abs((dq - out) @ out) <= 1e-9


# -- the retreat check -----------------------------------------------------------------------------------------

def test_the_retreat_check_judges_the_other_touched_pad() -> None:
    path = planned(build("cartesian"), "wrist_2", [touch("forearm_bottom", 0.6)])
    check = assess(MODEL, path, 0.005, pad("wrist_2"), [pad("forearm_bottom")])
    assert check.contacts == (pad("forearm_bottom"),)
    assert check.contacts_toward_m[0] == pytest.approx(toward(path, "forearm_bottom")[0], abs=1e-12)
    assert check.contacts_toward_m[0] > 0.01  # plain CR: the stacked rows cannot serve both pads here
    message = check.to_message(pad("wrist_2"), corrected=False)
    assert message.contacts == [pad("forearm_bottom")] and message.contacts_toward_m[0] > 0.01
    # One contact: the fields stay empty and off the wire (a single touch's message encodes as before).
    alone = assess(MODEL, path, 0.005, pad("wrist_2")).to_message(pad("wrist_2"), corrected=False)
    assert alone.contacts == [] and b"contacts" not in msgspec.msgpack.encode(alone)
    assert msgspec.msgpack.decode(msgspec.msgpack.encode(message), type=m.Retreat) == message


def pain(t: int, seq: int, levels: dict[str, int], gains: dict[str, float]) -> m.SkinPain:
    level = [levels.get(name, 1) for name in NAMES]
    gain = [gains.get(name, 0.0) for name in NAMES]
    strongest = max(gains, key=lambda name: gains[name])
    return m.SkinPain(seq=seq, stamp_ns=t, trace=m.Trace(seq, t - 1000), model="continuous", level=level,
                      gain=gain, strongest=contact(strongest, gains[strongest], levels[strongest]))


@pytest.mark.parametrize("every", [True, False])
def test_the_planner_gives_every_contact_to_the_strategy_and_its_retreat_check(every: bool) -> None:
    cfg = PlannerSection(strategy="cartesian", guarded=True, contacts="every" if every else "strongest")
    planner, t = running(cfg, DESC, MODEL)
    two = pain(t, 1, {"wrist_2": 4, "forearm_bottom": 3}, {"wrist_2": 1.0, "forearm_bottom": 0.4})
    assert planner.on_pain(two, t) is not None
    assert planner.reflex is not None and planner.reflex.contact.pad == pad("wrist_2")
    retreat = planner.assess()
    assert retreat is not None
    others = [c.pad for c in planner.strategy.other_contacts]
    if every:
        assert others == [pad("forearm_bottom")] and retreat.contacts == [pad("forearm_bottom")]
        assert retreat.contacts_toward_m[0] <= TOLERANCE_M and retreat.corrected
    else:  # the paper's: the strongest contact only
        assert others == [] and retreat.contacts == []


# -- in lockstep: two hands at once ----------------------------------------------------------------------------

TWO_HANDS = """duration_s = 3.0

[[touch]]
pad = "wrist_2"
start_s = 0.5
duration_s = 1.5
peak_hpa = 20.0

[[touch]]
pad = "forearm_bottom"
start_s = 0.5
duration_s = 1.5
peak_hpa = 12.0
"""


@pytest.mark.slow
def test_two_hands_in_lockstep_the_second_pad_is_no_longer_pushed_into_its_hand(tmp_path: Path) -> None:
    script = tmp_path / "two_hands.toml"
    script.write_text(TWO_HANDS)
    pushed = {}
    for mode in ("strongest", "every"):
        profile = msgspec.convert({"planner": {"contacts": mode, "guarded": True}}, Profile)
        path = simulate(profile, str(script), "cartesian", tmp_path / f"{mode}.mcap")[0]
        records, _ = read_recording(path)
        touches = {t.name: t for t in analysis.summarize(records, DESC, MODEL) if t.gain > 0.0}
        assert set(touches) == {"wrist_2", "forearm_bottom"}
        assert (touches["wrist_2"].pressed_toward_mm or 0.0) <= 1.0
        pushed[mode] = touches["forearm_bottom"].pressed_toward_mm or 0.0
    # The strongest contact only (guarded on its own pad): forearm_bottom is carried 55 mm into its hand.
    assert pushed["strongest"] > 20.0
    assert pushed["every"] <= 2.0
