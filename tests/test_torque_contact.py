"""The external-torque contact detector (services/gain/torque.py): the residual after a baseline model and a learnt
offset, per-joint thresholds with hysteresis, and the pad whose push explains the residual, on the FR3's model."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile
from nwr.common.journal import Recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.gain.torque import TorqueDetector
from nwr.services.gain.wiring import GainWiring

DESC = load_description("fr3")
MODEL = RobotModel(DESC)
HOME = np.asarray(DESC.home, dtype=float)
ON = np.array([6.0, 6.0, 3.0, 6.0, 2.0, 2.0, 1.0])
OFF = np.array([4.0, 4.0, 1.5, 4.0, 1.0, 1.0, 0.5])
# What a controller that reports its applied torque shows at rest beyond the URDF's gravity (franky-sim's at home).
OFFSET = np.array([0.0, -2.84, 0.0, 3.28, 0.01, 0.58, 0.0])


def push(q: np.ndarray, pad: int, force_n: float) -> np.ndarray:
    """The joint torque of ``force_n`` N at the pad's point along minus its outward normal."""
    return -force_n * (MODEL.pad_normals(q)[pad] @ MODEL.pad_jacobians(q)[pad])


def applied(q: np.ndarray, external: np.ndarray) -> np.ndarray:
    """A controller's own torque holding the arm still at ``q`` against gravity and ``external``."""
    return MODEL.gravity_torques(q) - external - OFFSET


def detector(**kw: object) -> TorqueDetector:
    return TorqueDetector(MODEL, ON, OFF, **kw)  # type: ignore[arg-type]


def tared(det: TorqueDetector, q: np.ndarray = HOME) -> TorqueDetector:
    for _ in range(det.tare_samples):
        verdict = det.update(q, applied(q, np.zeros(7)))
        assert not verdict.tared and not verdict.detected
    return det


def test_the_arms_weight_and_a_constant_offset_are_no_contact() -> None:
    det = tared(detector())
    for k in range(200):
        q = HOME + 0.2 * np.sin(np.arange(7) + 0.05 * k)  # anywhere on the way: gravity is the model's
        verdict = det.update(q, applied(q, np.zeros(7)))
        assert verdict.tared and not verdict.detected and max(map(abs, verdict.residual_nm)) < 1e-9


@pytest.mark.parametrize("pad", ["forearm_top", "wrist_side", "elbow_outer", "upper_arm_back"])
def test_a_push_is_detected_at_its_first_state_over_the_threshold_located_and_weighed(pad: str) -> None:
    index = [p.name for p in DESC.pads].index(pad)
    det = tared(detector())
    unit = push(HOME, index, 1.0)
    first = float(np.min(ON[np.abs(unit) > 0] / np.abs(unit[np.abs(unit) > 0])))  # the force that first crosses
    seen = []
    for force in np.linspace(0.0, 2.0 * first, 41):
        verdict = det.update(HOME, applied(HOME, push(HOME, index, force)))
        seen.append((force, verdict))
    onset = [(f, v) for f, v in seen if v.onset]
    assert len(onset) == 1 and onset[0][0] >= first - 1e-9 and onset[0][0] < first + 2 * first / 40 + 1e-9
    assert all(v.detected for f, v in seen if f >= onset[0][0]) and not any(v.detected for f, v in seen
                                                                           if f < onset[0][0])
    last = seen[-1][1]
    assert DESC.pads[last.pad].name == pad
    # The offset followed the push a little while it was below the threshold (1 %).
    assert last.force_n == pytest.approx(2.0 * first, rel=0.02) and last.unexplained < 0.01


def test_the_pad_is_told_from_the_one_on_the_opposite_side() -> None:
    names = [p.name for p in DESC.pads]
    top, bottom = names.index("forearm_top"), names.index("forearm_bottom")
    for pad in (top, bottom):
        det = tared(detector())
        verdict = det.update(HOME, applied(HOME, push(HOME, pad, 40.0)))
        assert verdict.detected and verdict.pad == pad and verdict.force_n == pytest.approx(40.0)


def test_hysteresis_holds_between_the_thresholds_and_ends_below_the_lower_on_every_joint() -> None:
    det = tared(detector())
    r = np.zeros(7)
    r[3] = 7.0
    assert det.update(HOME, applied(HOME, r)).onset
    r[3] = 4.5  # below on, above off: still in contact
    assert det.update(HOME, applied(HOME, r)).detected
    r[3], r[1] = 3.0, 4.2  # joint 4 below off, joint 2 above it: still
    verdict = det.update(HOME, applied(HOME, r))
    assert verdict.detected and not verdict.onset
    r[1] = 3.9
    assert not det.update(HOME, applied(HOME, r)).detected
    r[:] = 0.0
    r[6] = -1.2  # a small joint's own threshold (1 N m), either sign
    assert det.update(HOME, applied(HOME, r)).onset


def test_a_sustained_push_never_becomes_the_baseline_and_slow_drift_does() -> None:
    det = tared(detector())
    r = np.zeros(7)
    r[1] = 8.0
    for _ in range(20_000):
        verdict = det.update(HOME, applied(HOME, r))
    assert verdict.detected and verdict.residual_nm[1] == pytest.approx(8.0)
    det = tared(detector())
    drift = np.zeros(7)
    for k in range(20_000):  # 3 N m over 20,000 states: followed, never a contact
        drift[1] = 3.0 * k / 20_000
        assert not det.update(HOME, applied(HOME, drift)).detected
    assert abs(det.update(HOME, applied(HOME, drift)).residual_nm[1]) < 0.1  # the lag: slope / follow, 0.075


def test_the_none_baseline_takes_the_estimate_as_external_and_reset_tares_again() -> None:
    det = detector(baseline="none")
    for _ in range(det.tare_samples):
        det.update(HOME, np.full(7, 0.3))  # a real Franka's estimate at rest: small, not zero
    assert not det.update(HOME, np.full(7, 0.3)).detected
    external = push(HOME, [p.name for p in DESC.pads].index("wrist_top"), 30.0)
    verdict = det.update(HOME, 0.3 + external)
    assert verdict.detected and DESC.pads[verdict.pad].name == "wrist_top" and verdict.force_n == pytest.approx(30.0)
    det.reset()
    assert not det.active and not det.update(HOME, 0.3 + external).tared


def test_bad_input_and_settings_are_clear_errors() -> None:
    det = tared(detector())
    with pytest.raises(ValueError, match="7 finite values"):
        det.update(HOME, np.array([0.0] * 6 + [np.nan]))
    with pytest.raises(ValueError, match="7 finite values"):
        det.update(HOME, np.zeros(6))
    assert not det.update(HOME, applied(HOME, np.zeros(7))).detected  # nothing lost: it goes on
    with pytest.raises(ValueError, match="one per joint"):
        TorqueDetector(MODEL, ON[:6], OFF)
    with pytest.raises(ValueError, match="off_nm <= on_nm"):
        TorqueDetector(MODEL, OFF, ON)
    with pytest.raises(ValueError, match="baseline"):
        TorqueDetector(MODEL, ON, OFF, baseline="rnea")


def wiring_with(enabled: bool, clock: ManualClock, pains: list[m.SkinPain], said: list[str]) -> GainWiring:
    profile = msgspec.convert({"robot": {"name": "fr3", "description": "fr3"},
                               "gain": {"torque": {"enabled": enabled, "baseline": "gravity"}}}, Profile)
    return GainWiring(profile, journal=Recording(clock), out=lambda key, msg: pains.append(msg),
                      diag=lambda level, code, *a, **k: said.append(code))


def robot_state(clock: ManualClock, seq: int, external: np.ndarray, *, stale: bool = False) -> m.RobotState:
    return m.RobotState(seq=seq, stamp_ns=clock.now_ns(), q=HOME.tolist(), dq=[0.0] * 7, status="ok",
                        owner="cartesian", backend="franky", pose_stale=stale,
                        tau_ext=applied(HOME, external).tolist())


def skin(clock: ManualClock, seq: int, blind: int = -1) -> m.SkinPressure:
    n = len(DESC.pads)
    return m.SkinPressure(seq=seq, stamp_ns=clock.now_ns(), absolute_hpa=[1000.0] * n, baseline_hpa=[1000.0] * n,
                          change_hpa=[0.0] * n, contact=[False] * n, valid=[i != blind for i in range(n)])


def test_the_fallback_gives_a_blind_pad_the_gain_of_the_push_the_torques_locate_on_it() -> None:
    clock = ManualClock(10**9)
    pains: list[m.SkinPain] = []
    said: list[str] = []
    wiring = wiring_with(True, clock, pains, said)
    assert sorted(i.name for i in wiring.subscriptions()) == ["pressure", "state"]
    top = [p.name for p in DESC.pads].index("wrist_top")  # 24 N there: 10 N m on joint 4 at home
    for seq in range(30):  # at rest: the offset learnt
        clock.advance(0.02)
        wiring.on_state(robot_state(clock, seq, np.zeros(7)))
    wiring.on_pressure(skin(clock, 1, blind=top))
    assert pains[-1].gain[top] == 0.0 and pains[-1].strongest is None and not pains[-1].torque_pads
    clock.advance(0.02)
    wiring.on_state(robot_state(clock, 30, push(HOME, top, 24.0)))  # 24 N of 30 N for gain 1
    wiring.on_pressure(skin(clock, 2))  # the skin sees the pad (and no press there): the skin decides
    assert pains[-1].gain[top] == 0.0 and not pains[-1].torque_pads
    wiring.on_pressure(skin(clock, 3, blind=top))
    pain = pains[-1]
    assert pain.torque_pads == [top] and pain.gain[top] == pytest.approx(0.8) and pain.level[top] == 4
    assert pain.strongest is not None and pain.strongest.pad == top and pain.strongest.gain == pytest.approx(0.8)
    assert said == ["torque_contact"]
    clock.advance(0.5)  # the state went quiet: too old to use
    wiring.on_pressure(skin(clock, 4, blind=top))
    assert not pains[-1].torque_pads and pains[-1].gain[top] == 0.0
    wiring.on_state(robot_state(clock, 31, push(HOME, top, 24.0), stale=True))  # not measured: taring again
    clock.advance(0.01)
    wiring.on_state(robot_state(clock, 32, push(HOME, top, 24.0)))
    wiring.on_pressure(skin(clock, 5, blind=top))
    assert not pains[-1].torque_pads


def test_off_by_default_the_gain_estimator_takes_no_robot_state() -> None:
    clock = ManualClock(10**9)
    pains: list[m.SkinPain] = []
    wiring = wiring_with(False, clock, pains, [])
    assert [i.name for i in wiring.subscriptions()] == ["pressure"] and wiring.torque is None
    assert Profile().gain.torque.enabled is False


def test_the_dynamics_baseline_tells_the_arms_own_acceleration_from_a_push() -> None:
    """A controller that reports its applied torque while the arm accelerates hard (a withdrawal's 3 rad/s²):
    the gravity baseline takes the motion's torque for a push, the dynamics baseline does not, and still feels one."""
    acc = np.array([3.0, -3.0, 0.0, 3.0, 0.0, 0.0, 0.0])
    wrist = [p.name for p in DESC.pads].index("wrist_top")
    found = {}
    for baseline in ("gravity", "dynamics"):
        det = detector(baseline=baseline)
        verdicts = []
        for k in range(det.tare_samples + 10):
            t = 0.02 * k
            moving = k >= det.tare_samples
            dq = acc * (t - 0.02 * det.tare_samples) if moving else np.zeros(7)
            q = HOME + (0.5 * acc * (t - 0.02 * det.tare_samples) ** 2 if moving else 0.0)
            a = acc if moving else np.zeros(7)
            external = push(q, wrist, 25.0) if k == det.tare_samples + 9 else np.zeros(7)
            tau = MODEL.inverse_dynamics(q, dq, a) - external - OFFSET
            verdicts.append(det.update(q, tau, dq, 10**9 + round(t * 1e9)))
        found[baseline] = verdicts
    assert any(v.detected for v in found["gravity"][:-1])  # the motion alone, taken for a contact
    # The first moving state's acceleration is unknown (the previous state was at rest): it lags one state.
    assert not any(v.detected for v in found["dynamics"][26:-1])
    last = found["dynamics"][-1]
    assert last.detected and DESC.pads[last.pad].name == "wrist_top" and last.force_n == pytest.approx(25.0, rel=0.02)
