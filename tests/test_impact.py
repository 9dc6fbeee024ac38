"""Effective mass, predicted impact force and the effective-mass gain model, against hand computations."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nwr.common import messages as m
from nwr.common.config import BodyRegion, EffectiveMassSection, GainSection, Profile
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotModel, load_description
from nwr.services.gain.core import GainEstimator, continuous_gain
from nwr.services.gain.impact import (
    ILL_CONDITIONED,
    MASS_CAP_KG,
    MEASURED,
    NO_STATE,
    NON_FINITE_STATE,
    STALE_STATE,
    ImpactModel,
    impact_forces,
    inverse_masses,
    speed_scale_allowed,
)
from nwr.services.profile import load_profile

DESC = load_description()
ROBOT = RobotModel(DESC)
N = len(DESC.pads)
K, MH, LIMIT = 75_000.0, 5.6, 280.0


def model(**cfg: object) -> ImpactModel:
    return ImpactModel(EffectiveMassSection(**cfg), RobotModel(DESC))  # type: ignore[arg-type]


# -- the formulas, by hand ---------------------------------------------------------------------------------------

def test_a_point_on_a_single_rotor_has_the_effective_mass_i_over_r_squared():
    inertia, r = 2.4, 0.3  # kg m^2, m: a point 0.3 m from the axis, moving along y
    jacobian = np.array([[[0.0], [r], [0.0]]])
    inverse = inverse_masses(np.array([[inertia]]), jacobian, np.array([[0.0, 1.0, 0.0]]))
    assert 1.0 / inverse[0] == pytest.approx(inertia / r**2)  # 26.67 kg


def test_two_decoupled_axes_give_each_its_mass_and_a_diagonal_their_harmonic_mean():
    m1, m2 = 3.0, 12.0
    jacobians = np.array([np.eye(3)[:, :2]] * 2)  # a point driven along x by joint 1 and along y by joint 2
    diagonal = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    inverse = inverse_masses(np.diag([m1, m2]), jacobians, np.array([[1.0, 0.0, 0.0], diagonal]))
    assert 1.0 / inverse[0] == pytest.approx(m1)
    assert 1.0 / inverse[1] == pytest.approx(2.0 / (1.0 / m1 + 1.0 / m2))  # 4.8 kg


def test_the_impact_force_by_hand():
    # 0.25 m/s, m = 2 kg against k = 75 N/mm, m_H = 5.6 kg: 0.25 * 273.861 / sqrt(0.5 + 0.178571) = 83.11 N
    force = impact_forces(np.array([0.25]), np.array([1 / 2.0]), np.array([K]), np.array([MH]))
    assert force[0] == pytest.approx(83.11, abs=0.01)
    # An infinite effective mass (1/m = 0): the person's own mass alone, v sqrt(k m_H).
    assert impact_forces(np.array([0.25]), np.array([0.0]), np.array([K]), np.array([MH]))[0] == \
        pytest.approx(0.25 * math.sqrt(K * MH))


@pytest.mark.parametrize("q", [DESC.home, np.array([0.4, -1.2, 1.1, -1.5, -1.2, 0.3])])
def test_a_shoulder_pad_turned_by_the_pan_joint_alone(q):
    """shoulder_back sits on the shoulder link: only the pan joint moves it. Its velocity is w x r (r its
    distance from the pan axis, the base's z), its Jacobian one column, and so m = 1 / (r^2 [M^-1]_00), at most
    the locked arm's I/r^2 = M_00 / r^2 (the other joints free to move give way: their Schur complement)."""
    pad = DESC.pad("shoulder_back").id
    w = 0.5
    point = ROBOT.pad_point(q, pad)
    r = math.hypot(point[0], point[1])
    mass_matrix = ROBOT.mass_matrix(q)
    expected = 1.0 / (r**2 * np.linalg.inv(mass_matrix)[0, 0])
    impact = model().at(q, np.array([w, 0, 0, 0, 0, 0]))
    assert impact.basis == MEASURED
    assert impact.speed_m_s[pad] == pytest.approx(w * r)
    assert impact.mass_kg[pad] == pytest.approx(expected, rel=1e-9)
    assert expected <= mass_matrix[0, 0] / r**2
    speed = w * r
    assert impact.force_n[pad] == pytest.approx(speed * math.sqrt(K) / math.sqrt(1 / expected + 1 / MH), rel=1e-9)
    assert impact.ratio[pad] == pytest.approx(impact.force_n[pad] / LIMIT)


def test_the_wrist_3_pad_turned_by_its_own_joint_alone_is_light():
    q = DESC.home
    pad = DESC.pad("wrist_3").id
    jacobian = ROBOT.pad_jacobians(q)[pad]
    impact = model().at(q, np.array([0, 0, 0, 0, 0, 1.0]))
    u = jacobian[:, 5] / np.linalg.norm(jacobian[:, 5])
    lever = float(u @ jacobian[:, 5])  # the pad's distance from the wrist 3 axis, m
    by_hand = 1.0 / (np.linalg.inv(ROBOT.mass_matrix(q)) @ (jacobian.T @ u) @ (jacobian.T @ u))
    assert impact.mass_kg[pad] == pytest.approx(by_hand)
    assert impact.speed_m_s[pad] == pytest.approx(lever)
    assert impact.mass_kg[pad] < 5.0  # a tool flange, not the arm


def test_a_pad_at_rest_predicts_no_force_and_its_mass_along_its_normal():
    q = DESC.home
    impact = model().at(q, np.zeros(6))
    assert impact.basis == MEASURED
    assert (impact.force_n == 0).all() and (impact.ratio == 0).all() and (impact.speed_m_s == 0).all()
    pad = DESC.pad("forearm_top").id
    n = ROBOT.pad_normal(q, pad)
    jacobian = ROBOT.pad_jacobians(q)[pad]
    by_hand = 1.0 / (n @ jacobian @ np.linalg.inv(ROBOT.mass_matrix(q)) @ jacobian.T @ n)
    assert impact.mass_kg[pad] == pytest.approx(by_hand)


def test_a_direction_the_arm_cannot_be_pushed_in_reports_the_mass_cap():
    # shoulder_back's normal is radial from the pan axis, which no joint moves it along.
    impact = model().at(DESC.home, np.zeros(6))
    assert impact.mass_kg[DESC.pad("shoulder_back").id] == MASS_CAP_KG


def test_a_planar_two_link_arm_by_hand():
    """Two links of 0.5 m with 2 kg at each end, the elbow at 90 degrees (link 1 along x, link 2 along y):
    M = [[m1 l1^2 + m2 (l1^2 + l2^2), m2 l2^2], [m2 l2^2, m2 l2^2]] = [[1.5, 0.5], [0.5, 0.5]] (cos q2 = 0);
    the tip's Jacobian [[-l2, -l2], [l1, 0]]; J M^-1 J^T = diag(0.5, 0.25): 2 kg across link 2 (x), 4 kg along it
    (y, the whole arm turning about the base with the elbow free), 1 / ((0.5 + 0.25) / 2) = 2.67 kg at 45 deg."""
    mass_matrix = np.array([[1.5, 0.5], [0.5, 0.5]])
    jacobian = np.array([[-0.5, -0.5], [0.5, 0.0], [0.0, 0.0]])
    diagonal = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    inverse = inverse_masses(mass_matrix, np.array([jacobian] * 3),
                             np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], diagonal]))
    assert 1.0 / inverse == pytest.approx([2.0, 4.0, 8.0 / 3.0])
    # 0.3 m/s across link 2 into a hand: 82.158 / sqrt(1/2 + 1/5.6) = 82.158 / 0.82376 = 99.74 N
    assert impact_forces(np.array([0.3]), inverse[:1], np.array([K]), np.array([MH]))[0] == pytest.approx(99.74,
                                                                                                           abs=0.01)


def _mass_matrix_from_link_inertias(q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """M = sum over links of m J_c^T J_c + J_w^T (R I R^T) J_w from the URDF's inertias, each link's centre-of-mass
    and angular Jacobians by central differences of its placement: forward kinematics only, none of pinocchio's
    dynamics or Jacobians."""
    import pinocchio as pin

    model, data = ROBOT.model, ROBOT.model.createData()

    def placements(x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        pin.forwardKinematics(model, data, x)
        return [(data.oMi[i].translation + data.oMi[i].rotation @ model.inertias[i].lever, data.oMi[i].rotation.copy())
                for i in range(1, model.njoints)]

    n = len(q)
    jc = np.zeros((model.njoints - 1, 3, n))
    jw = np.zeros((model.njoints - 1, 3, n))
    for j in range(n):
        step = np.zeros(n)
        step[j] = h
        for link, ((c_plus, r_plus), (c_minus, r_minus)) in enumerate(zip(placements(q + step), placements(q - step))):
            jc[link, :, j] = (c_plus - c_minus) / (2 * h)
            turn = r_plus @ r_minus.T
            jw[link, :, j] = np.array([turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0], turn[1, 0] - turn[0, 1]]) / (
                4 * h)
    rotations = [r for _, r in placements(q)]
    out = np.diag(np.asarray(model.armature, dtype=float))
    for link in range(model.njoints - 1):
        inertia = model.inertias[link + 1]
        world = rotations[link] @ inertia.inertia @ rotations[link].T
        out += inertia.mass * jc[link].T @ jc[link] + jw[link].T @ world @ jw[link]
    return out


@pytest.mark.parametrize(("q", "dq"), [
    (DESC.home, np.array([0.3, -0.2, 0.4, 0.5, -0.6, 0.8])),
    (np.array([0.4, -1.2, 1.1, -1.5, -1.2, 0.3]), np.array([-0.5, 0.3, 0.2, -0.4, 0.7, 0.1])),
])
def test_the_ur10e_at_two_poses_against_an_independent_computation(q, dq):
    """Every pad's speed, effective mass and force against numpy alone: the mass matrix from the link inertias
    (above), the pads' Jacobians by central differences of their points."""
    h = 1e-6
    mass_matrix = _mass_matrix_from_link_inertias(q)
    assert mass_matrix == pytest.approx(ROBOT.mass_matrix(q), rel=1e-6, abs=1e-7)
    jacobians = np.zeros((N, 3, 6))
    for j in range(6):
        step = np.zeros(6)
        step[j] = h
        jacobians[:, :, j] = (ROBOT.pad_points(q + step) - ROBOT.pad_points(q - step)) / (2 * h)
    impact = model().at(q, dq)
    assert impact.basis == MEASURED
    for pad in range(N):
        v = jacobians[pad] @ dq
        speed = float(np.linalg.norm(v))
        assert impact.speed_m_s[pad] == pytest.approx(speed, rel=1e-6, abs=1e-9)
        u = v / speed
        mass = 1.0 / float(u @ jacobians[pad] @ np.linalg.inv(mass_matrix) @ jacobians[pad].T @ u)
        assert impact.mass_kg[pad] == pytest.approx(mass, rel=1e-5)
        force = speed * math.sqrt(K) / math.sqrt(1.0 / mass + 1.0 / MH)
        assert impact.force_n[pad] == pytest.approx(force, rel=1e-5)

# -- bad input: a defined, conservative answer, never a NaN ----------------------------------------------------

@pytest.mark.parametrize(("q", "dq"), [
    (np.full(6, np.nan), np.zeros(6)),
    (DESC.home, np.array([0, np.inf, 0, 0, 0, 0])),
    (DESC.home[:5], np.zeros(5)),
])
def test_a_non_finite_or_wrong_sized_state_makes_every_pad_most_sensitive(q, dq):
    impact = model().at(q, dq)
    assert impact.basis == NON_FINITE_STATE
    assert (impact.ratio == 1).all() and (impact.force_n == LIMIT).all() and (impact.mass_kg == 0).all()


@pytest.mark.parametrize("bad", [np.diag([1.0, 1, 1, 1, 1, 1e-12]), np.diag([1.0, 1, 1, 1, 1, -1]),
                                 np.full((6, 6), np.nan)])
def test_an_ill_conditioned_mass_matrix_makes_every_pad_most_sensitive(bad):
    impacts = model()
    impacts.robot.mass_matrix = lambda q: bad  # type: ignore[method-assign]
    impact = impacts.at(DESC.home, np.ones(6))
    assert impact.basis == ILL_CONDITIONED
    assert (impact.ratio == 1).all() and np.isfinite(impact.force_n).all()


def state(stamp_ns: int, stale: bool = False) -> m.RobotState:
    return m.RobotState(seq=0, stamp_ns=stamp_ns, q=list(DESC.home), dq=[0.0] * 6, status="ok", owner="", backend="sim",
                        pose_stale=stale)


def test_no_state_a_stale_one_and_one_not_measured_are_unknown():
    impacts = model(state_timeout_s=0.1)
    assert impacts.predict(0).basis == NO_STATE
    impacts.update(state(1_000_000_000))
    assert impacts.predict(1_100_000_000).basis == MEASURED
    assert impacts.predict(1_100_000_001).basis == STALE_STATE
    impacts.update(state(1_200_000_000, stale=True))
    assert impacts.predict(1_200_000_000).basis == STALE_STATE


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6), st.lists(st.floats(-1.0, 1.0), min_size=6,
                                                                      max_size=6),
       st.floats(0.01, 3.0))
def test_every_pose_and_speed_within_the_limits_gives_finite_forces_in_proportion_to_the_speed(x, y, scale):
    impacts = PROPERTY_MODEL
    q = DESC.q_min + (np.array(x) + 1) / 2 * (DESC.q_max - DESC.q_min)
    dq = np.array(y) * DESC.v_max
    impact = impacts.at(q, dq)
    assert impact.basis == MEASURED
    for values in (impact.mass_kg, impact.speed_m_s, impact.force_n, impact.ratio):
        assert np.isfinite(values).all() and (values >= 0).all()
    assert (impact.mass_kg > 0).all() and (impact.ratio <= 1).all()
    faster = impacts.at(q, dq * scale)
    moving = (impact.speed_m_s > 0) & (faster.speed_m_s > 0)
    assert faster.force_n[moving] == pytest.approx(impact.force_n[moving] * scale, rel=1e-9)
    assert faster.mass_kg[moving] == pytest.approx(impact.mass_kg[moving], rel=1e-9)


PROPERTY_MODEL = model()


def test_the_allowed_speed_scale_is_the_limit_over_the_largest_force():
    q = np.array([DESC.home, DESC.home])
    dq = np.array([[0.2, 0, 0, 0, 0, 0], [0.4, 0.1, 0, 0, 0, 0]])
    impacts = model()
    scale, sample, pad = speed_scale_allowed(impacts, q, dq)
    forces = np.array([impacts.at(a, b).force_n for a, b in zip(q, dq)])
    assert scale == pytest.approx(LIMIT / forces.max())
    assert forces[sample, pad] == forces.max()
    assert speed_scale_allowed(impacts, q, np.zeros((2, 6)))[0] == math.inf


# -- regions: per pad, unknown ones refused at start -----------------------------------------------------------

def test_a_pad_meets_its_own_region():
    soft = BodyRegion(k_n_m=25_000.0, mass_kg=40.0, transient_n=220.0)
    impacts = model(pad_regions={"wrist_3": "chest"}, regions={"hand": BodyRegion(), "chest": soft})
    pad = DESC.pad("wrist_3").id
    assert impacts.regions[pad] == "chest" and impacts.regions[0] == "hand"
    dq = np.array([0, 0, 0, 0, 0, 1.0])
    impact = impacts.at(DESC.home, dq)
    by_hand = impact.speed_m_s[pad] * math.sqrt(25_000.0) / math.sqrt(1 / impact.mass_kg[pad] + 1 / 40.0)
    assert impact.force_n[pad] == pytest.approx(by_hand)
    assert impact.ratio[pad] == pytest.approx(by_hand / 220.0)


@pytest.mark.parametrize(("cfg", "match"), [
    ({"pad_regions": {"nope": "hand"}}, "pad_regions names pads \\['nope'\\]"),
    ({"pad_regions": {"wrist_3": "knee"}}, "meets body region 'knee'"),
    ({"default_region": "knee"}, "meets body region 'knee'"),
])
def test_an_unknown_pad_or_region_is_refused_at_start(cfg, match):
    with pytest.raises(ConfigError, match=match):
        model(**cfg)


@pytest.mark.parametrize(("text", "match"), [
    ('[gain]\nmodel = "effective-mass"\n[gain.effective_mass]\ndefault_region = "knee"\n',
     "default_region = 'knee' is no body region"),
    ('[gain]\nmodel = "effective-mass"\n[gain.effective_mass]\npad_regions = {wrist_3 = "knee"}\n',
     "pad_regions.wrist_3 = 'knee' is no body region"),
    ('[gain]\nmodel = "effective-mass"\n[gain.effective_mass]\npad_regions = {nope = "hand"}\n',
     "pad_regions names \\['nope'\\]"),
    ('[gain]\nmodel = "effective-mass"\n[gateway]\ncontact_hpa = 1.2\nrelease_hpa = 0.5\n',
     "not below gain.effective_mass.floor x gain.thresholds_hpa\\[0\\] = 1.2 hPa"),
])
def test_the_profile_refuses_unknown_regions_and_a_floor_below_the_contact_level(tmp_path: Path, text, match):
    path = tmp_path / "p.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_profile(str(path))


# -- the gain model ----------------------------------------------------------------------------------------------

def pressure(change: list[float], seq: int = 3) -> m.SkinPressure:
    n = len(change)
    return m.SkinPressure(seq=seq, stamp_ns=10, absolute_hpa=[0.0] * n, baseline_hpa=[0.0] * n, change_hpa=change,
                          contact=[c > 1 for c in change])


EM = GainSection(model="effective-mass")


def test_at_rest_the_effective_mass_model_is_the_papers_continuous_one_bit_for_bit():
    impact = model().at(DESC.home, np.zeros(6))
    change = [0.0, 1.9, 2.5, 5.9, 6.0, 7.3, 12.0, 15.5, 20.0, 31.0]
    em = GainEstimator(EM, DESC.pads).process(pressure(change), 7, impact)
    paper = GainEstimator(GainSection(), DESC.pads).process(pressure(change), 7)
    assert em.gain == paper.gain and em.level == paper.level and em.strongest == paper.strongest
    assert em.threshold_scale == [1.0] * N and em.impact_n == [0.0] * N and em.impact_basis == MEASURED
    assert paper.effective_mass_kg == [] and paper.impact_n == [] and paper.impact_basis == ""


def test_a_pad_at_its_regions_limit_feels_with_its_thresholds_at_the_floor():
    impacts = model()
    dq = np.array([0, 0, 0, 0, 0, 1.0])
    impact = impacts.at(DESC.home, dq)
    pad = DESC.pad("wrist_3").id
    # Find the speed at which wrist_3's predicted force is half its limit, then at and past the limit.
    half = impacts.at(DESC.home, dq * (0.5 * LIMIT / impact.force_n[pad]))
    est = GainEstimator(EM, DESC.pads)
    assert est.scales(half)[pad] == pytest.approx(1 - 0.4 * 0.5)  # 0.8
    full = impacts.at(DESC.home, dq * (1.5 * LIMIT / impact.force_n[pad]))
    assert est.scales(full)[pad] == pytest.approx(0.6)
    change = [0.0] * N
    change[pad] = 4.0  # PL 2 at the paper's thresholds (no gain); PL 3 at 0.6 x (2, 6, 12, 20) = (1.2, 3.6, 7.2, 12)
    pain = est.process(pressure(change), 0, full)
    assert pain.level[pad] == 3
    assert pain.gain[pad] == pytest.approx(continuous_gain(4.0, (1.2, 3.6, 7.2, 12.0)))
    assert pain.gain[pad] > 0 and pain.strongest is not None and pain.strongest.pad == pad
    assert pain.impact_n[pad] == pytest.approx(1.5 * LIMIT)


@pytest.mark.parametrize("basis", [NO_STATE, STALE_STATE, NON_FINITE_STATE, ILL_CONDITIONED])
def test_without_a_prediction_every_pad_is_at_the_floor(basis):
    est = GainEstimator(EM, DESC.pads)
    pain = est.process(pressure([4.0] * N), 0, model().unknown(basis))
    assert pain.threshold_scale == [pytest.approx(0.6)] * N
    assert pain.level == [3] * N and all(g > 0 for g in pain.gain)
    assert pain.impact_basis == basis and pain.impact_n == [LIMIT] * N


def test_the_effective_mass_model_never_gives_less_gain_than_the_papers():
    est, paper = GainEstimator(EM, DESC.pads), GainEstimator(GainSection(), DESC.pads)
    rng = np.random.default_rng(0)
    impacts = model()
    for _ in range(50):
        q = DESC.q_min + rng.random(6) * (DESC.q_max - DESC.q_min)
        impact = impacts.at(q, (rng.random(6) * 2 - 1) * DESC.v_max)
        change = list(rng.random(N) * 25)
        assert all(a >= b for a, b in zip(est.process(pressure(change), 0, impact).gain,
                                          paper.process(pressure(change), 0).gain))


def test_the_model_needs_a_prediction():
    with pytest.raises(ValueError, match="needs an impact prediction"):
        GainEstimator(EM, DESC.pads).process(pressure([0.0] * N), 0)


def test_a_pain_message_recorded_before_the_prediction_fields_still_decodes():
    old = {"kind": "skin_pain", "seq": 1, "stamp_ns": 2, "trace": {"seq": 1, "stamp_ns": 1}, "model": "continuous",
           "level": [1], "gain": [0.0], "strongest": None}
    pain = msgspec.msgpack.decode(msgspec.msgpack.encode(old), type=m.SkinPain)
    assert pain.impact_n == [] and pain.effective_mass_kg == [] and pain.impact_basis == ""


def test_the_gain_wiring_reads_the_robot_state_only_for_the_effective_mass_model():
    from nwr.common.clock import ManualClock
    from nwr.common.journal import Recording
    from nwr.services.gain.wiring import GainWiring

    def wiring(profile: Profile) -> GainWiring:
        return GainWiring(profile, journal=Recording(ManualClock()), out=lambda k, v: None,
                          diag=lambda *a, **k: None)

    assert [i.name for i in wiring(Profile()).subscriptions()] == ["pressure"]
    em = Profile(gain=GainSection(model="effective-mass"))
    assert sorted(i.name for i in wiring(em).subscriptions()) == ["pressure", "state"]


def test_a_prediction_lost_and_regained_is_said_once_each_time():
    """No state yet, a state, then none for longer than the timeout: one warning per loss, one note per return,
    not one per skin sample; every pain message meanwhile at the floor, none NaN."""
    from nwr.common.clock import ManualClock
    from nwr.common.journal import Recording
    from nwr.services.gain.wiring import GainWiring

    clock = ManualClock(1_000_000_000)
    said: list[tuple[str, str]] = []
    pains: list[m.SkinPain] = []
    wiring = GainWiring(Profile(gain=GainSection(model="effective-mass")), journal=Recording(clock),
                        out=lambda key, msg: pains.append(msg), diag=lambda level, code, *a, **k: said.append(
                            (level, code)))

    def samples(count: int) -> None:
        for _ in range(count):
            clock.advance(0.04)
            wiring.on_pressure(pressure([4.0] * N, seq=len(pains)))

    samples(3)  # no robot state yet
    wiring.on_state(state(clock.now_ns()))
    samples(2)  # 40 and 80 ms after the state: within the 0.1 s timeout
    samples(3)  # the state is now 120 ms and more old: stale
    wiring.on_state(state(clock.now_ns()))
    samples(1)
    assert said == [("warning", "impact_unknown"), ("info", "impact_predicted"), ("warning", "impact_unknown"),
                    ("info", "impact_predicted")]
    assert [p.impact_basis for p in pains] == [NO_STATE] * 3 + [MEASURED] * 2 + [STALE_STATE] * 3 + [MEASURED]
    assert all(p.threshold_scale == [pytest.approx(0.6)] * N for p in pains if p.impact_basis != MEASURED)
    assert all(math.isfinite(x) for p in pains for x in [*p.impact_n, *p.effective_mass_kg, *p.gain])

# -- a lockstep session with the model: recorded, summarised, re-run bit for bit -------------------------------

@pytest.mark.slow
def test_a_lockstep_session_with_the_model_records_its_predictions_and_re_runs_bit_for_bit(tmp_path: Path, capsys):
    from nwr.services.tools.recordings.analysis import summarize
    from nwr.services.tools.recordings.compare import load_session, table
    from nwr.services.tools.recordings.replay import simulate
    from nwr.services.tools.recordings.summary import print_summary
    from nwr.services.tools.recordings.verify import verify

    profile = Profile(gain=GainSection(model="effective-mass"))
    path = simulate(profile, str(Path(__file__).parent / "data" / "short.toml"), "cartesian", tmp_path / "em.mcap")[0]
    assert {r.service: r.verdict for r in verify(path)} == {
        "gateway": "identical", "gain": "identical", "planner-cartesian": "identical", "bridge": "identical"}
    from nwr.common.recordings import read_recording

    records, _ = read_recording(path)
    pains = [r.message for r in records if r.key == "skin/pain"]
    assert all(p.model == "effective-mass" and len(p.impact_n) == N for p in pains)
    assert sum(p.impact_basis == MEASURED for p in pains) >= len(pains) - 1  # the first sample may precede a state
    touches = summarize(records, DESC)
    reflexes = [t for t in touches if t.reflex_seq]
    assert reflexes and all(t.impact_n is not None and t.effective_mass_kg is not None for t in touches)
    assert all(0.0 <= t.impact_n <= LIMIT for t in touches if t.impact_n is not None)
    assert print_summary(path, None, profile, columns="t,pad,impact,mass") == 0
    out = capsys.readouterr().out
    assert "impact" in out and "mass" in out and "predicted impact force at the onset" in out
    session = load_session(path, DESC, ROBOT, profile)
    assert "force (N)" in table([session], [[t] for t in session.touches]).splitlines()[0]
