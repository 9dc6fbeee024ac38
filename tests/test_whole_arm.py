"""The whole-arm withdrawal (services/planner/strategies/whole_arm.py): its QP each cycle, run alone.

Every pad, in poses along the task's figure-eight, at the survey's three
gains: the touched pad never moves toward the contact, no other pad and no
joint of the arm comes closer to the contact point than the budget, the pads
its joints can move along their normals withdraw in proportion to the gain,
the others withdraw sideways and say so, the same touch in the same pose gives
the same motion bit for bit, and what cannot be solved ends in a stand-still.
The stream is integrated at the planner's rate without the planner (the
session-level figures are in tests/test_whole_arm_session.py).
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from planner_support import running

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.robot import RobotModel, load_description
from nwr.common.task import FigureEight, TaskSection
from nwr.services.planner import strategies
from nwr.services.planner.core import Planner
from nwr.services.planner.strategies import whole_arm
from nwr.services.planner.strategies.whole_arm import (
    APPROACH_BUDGET_M,
    TOWARD_BUDGET_M,
    WholeArm,
    WholeArmSettings,
)

DESC = load_description()
MODEL = RobotModel(DESC)
NAMES = [pad.name for pad in DESC.pads]
TASK = FigureEight(TaskSection(), DESC)
POSES = {"home": DESC.home.copy(), "lap 1/4": TASK.position(3.0), "lap 5/8": TASK.position(7.5)}
GAINS = (0.175, 0.58, 1.0)  # the survey script's 9, 15 and 25 hPa
# Pads whose joints move them along their normals with nothing coming toward the contact: they withdraw
# straight back, in proportion to the gain. The shoulder pads' normals are tangent to everything their two
# joints do: they withdraw sideways. The elbow's and wrist_1's (sideways, toward the base) need the base to
# turn, which swings the shoulder toward the contact point: they withdraw along their normals only a few
# millimetres, the gain's share of that reach ("short").
STRAIGHT = ("upper_arm_top", "upper_arm_bottom", "forearm_top", "forearm_bottom", "wrist_2", "wrist_3")
SIDEWAYS = ("shoulder_back", "shoulder_outer")
SHORT = ("elbow_outer", "wrist_1")
DT = 0.004  # s: every second control cycle of the planner's 500 Hz (the figures agree within 0.1 mm)


def contact(pad: int, gain: float) -> m.Contact:
    return m.Contact(pad=pad, name=NAMES[pad], region=DESC.pads[pad].region, change_hpa=20.0, level=4, gain=gain)


def build(**overrides: float) -> WholeArm:
    cfg = PlannerSection(strategy="whole-arm", plugins={"whole-arm": dict(overrides)})
    strategy = strategies.build(cfg, DESC, MODEL, cfg.speed_fraction * DESC.v_max)
    assert isinstance(strategy, WholeArm)
    return strategy


def withdraw(pad: int, gain: float, q0: np.ndarray, strategy: WholeArm | None = None) -> dict:
    """The stream integrated from ``q0``: the touched pad's motion along its normal (+ away), the largest
    approach of every other pad and joint to the contact point, the path."""
    s = strategy or build()
    onset = s.start(q0.copy(), contact(pad, gain))
    p0, n0 = MODEL.pad_point(q0, pad), MODEL.pad_normal(q0, pad)
    pads0 = np.linalg.norm(MODEL.pad_points(q0) - p0, axis=1)
    joints0 = np.linalg.norm(MODEL.joint_positions(q0) - p0, axis=1)
    q, path, away = q0.copy(), [q0.copy()], []
    pads_closest, joints_closest = pads0.copy(), joints0.copy()
    for k in range(int(round(s.duration_s / DT)) + 1):
        q = q + s.velocity(q, k * DT) * DT
        path.append(q.copy())
        points = MODEL.pad_points(q)
        away.append(-float((points[pad] - p0) @ n0))
        pads_closest = np.minimum(pads_closest, np.linalg.norm(points - p0, axis=1))
        joints_closest = np.minimum(joints_closest, np.linalg.norm(MODEL.joint_positions(q) - p0, axis=1))
    pads_approach = pads0 - pads_closest
    pads_approach[pad] = 0.0
    far = joints0 > whole_arm.NEAR_M
    return {
        "onset": onset, "away_m": np.array(away), "pad_approach_m": float(pads_approach.max()),
        "joint_approach_m": float((joints0 - joints_closest)[far].max(initial=0.0)), "path": np.array(path),
        "leaves_m": float(np.linalg.norm(MODEL.pad_point(q, pad) - p0)),
    }


@pytest.mark.parametrize("pose", POSES)
@pytest.mark.parametrize("pad", NAMES)
def test_the_touched_pad_never_comes_toward_the_contact_and_nothing_else_does(pad: str, pose: str) -> None:
    run = withdraw(NAMES.index(pad), 1.0, POSES[pose])
    tol = 2e-4  # the stream integrated in cycles: second-order motion within a cycle
    assert -run["away_m"].min() <= TOWARD_BUDGET_M + tol
    assert run["pad_approach_m"] <= APPROACH_BUDGET_M + tol
    assert run["joint_approach_m"] <= APPROACH_BUDGET_M + tol


@pytest.mark.parametrize("pose", POSES)
@pytest.mark.parametrize("pad", STRAIGHT)
def test_a_pad_its_joints_can_move_withdraws_in_proportion_to_the_gain(pad: str, pose: str) -> None:
    distance = build().distance_m
    runs = [withdraw(NAMES.index(pad), g, POSES[pose]) for g in GAINS]
    assert all(r["onset"].reach_m == distance for r in runs)  # ReflexInfo.reach_m: all of distance_m at G = 1
    away = [r["away_m"].max() for r in runs]
    assert away[-1] >= 0.07, f"{pad} withdrew only {1e3 * away[-1]:.1f} mm at G = 1"
    assert away[0] < away[1] < away[2]
    for g, a in zip(GAINS[:2], away[:2]):  # below the speed caps: the gain's share of the distance (less what
        assert 0.85 * g * distance <= a <= g * distance + 1e-4  # keeping the rest of the arm still costs)


@pytest.mark.parametrize("pose", POSES)
@pytest.mark.parametrize("pad", ("upper_arm_top", "upper_arm_bottom", "forearm_top", "wrist_2"))
def test_no_other_pad_moves_out_along_its_normal_faster_than_the_cap_and_the_distance_stays(pad: str,
                                                                                            pose: str) -> None:
    s = build()
    touched = NAMES.index(pad)
    q = POSES[pose].copy()
    s.start(q.copy(), contact(touched, 1.0))
    assert s.configured_s <= s.duration_s <= whole_arm.STRETCH_MAX * s.configured_s
    fastest = 0.0
    for k in range(int(round(s.duration_s / DT)) + 1):
        dq = s.velocity(q, k * DT)
        out = np.einsum("ij,ijk,k->i", MODEL.pad_normals(q), MODEL.speed_jacobians(q)[: len(NAMES)], dq)
        out[touched] = 0.0
        fastest = max(fastest, float(out.max()))
        q = q + dq * DT
    assert fastest <= s.outward_speed + 1e-6
    # The touched pad withdraws (nearly) its full distance: the cap makes it take longer, up to STRETCH_MAX.
    assert withdraw(touched, 1.0, POSES[pose])["away_m"].max() >= 0.8 * s.distance_m


def test_the_reach_is_no_further_than_the_joints_range_lets_the_motion_go() -> None:
    """Near a joint limit the speed the QP allows says nothing of how far the pad may go: the reach stops where
    the first joint the withdrawal moves reaches its range (less the margin)."""
    s = build()
    q = DESC.home.copy()
    q[2] = DESC.q_max[2] - whole_arm.MARGIN_RAD - 0.01  # the elbow 0.01 rad inside its range's margin
    dq = np.zeros_like(q)
    assert s._room_s(q, dq) == np.inf
    dq[2], dq[1] = 0.5, -0.1  # the elbow toward its limit: 0.02 s
    assert s._room_s(q, dq) == pytest.approx(0.02)
    dq[2] = -0.5  # away from it: the room toward its other end, or the shoulder's
    lo = DESC.q_min + whole_arm.MARGIN_RAD
    assert s._room_s(q, dq) == pytest.approx(min((q[2] - lo[2]) / 0.5, (q[1] - lo[1]) / 0.1))
    for name in SHORT:  # at home, nothing near a limit: the reach is the QP's
        s.start(DESC.home.copy(), contact(NAMES.index(name), 1.0))
        assert whole_arm.REACH_MIN_M <= s.reach_m < whole_arm.SHORT_SHARE * s.distance_m


# How far each leaves the contact point at G = 1 at least, m: shoulder_back only by turning the base, which
# swings the pads farther out along their normals, each no faster than outward_speed_m_s.
LEAVES_M = {"shoulder_back": 0.005, "shoulder_outer": 0.02}


@pytest.mark.parametrize("pose", POSES)
@pytest.mark.parametrize("pad", SHORT)
def test_a_pad_its_joints_move_only_a_little_along_its_normal_withdraws_the_gains_share_of_that(
        pad: str, pose: str) -> None:
    runs = [withdraw(NAMES.index(pad), g, POSES[pose]) for g in (0.03, *GAINS)]
    reach = build()
    reach.start(POSES[pose].copy(), contact(NAMES.index(pad), 1.0))
    assert whole_arm.REACH_MIN_M <= reach.reach_m < whole_arm.SHORT_SHARE * reach.distance_m
    assert all(r["onset"].reason == "short" and not r["onset"].sideways for r in runs)
    assert all(r["onset"].reach_m == reach.reach_m for r in runs)  # ReflexInfo.reach_m: the reach, at any gain
    away = [r["away_m"].max() for r in runs]
    assert away == sorted(away) and away[0] < away[-1]  # in proportion: a rank correlation of 1
    assert away[-1] >= 0.7 * reach.reach_m  # most of its reach at G = 1; never toward, nothing else closer
    assert away[-1] <= reach.reach_m + 1e-3
    for r in runs:
        assert -r["away_m"].min() <= TOWARD_BUDGET_M + 2e-4
        assert r["pad_approach_m"] <= APPROACH_BUDGET_M + 2e-4


@pytest.mark.parametrize("pad", SIDEWAYS)
def test_a_pad_that_cannot_move_along_its_normal_withdraws_sideways_and_says_so(pad: str) -> None:
    run = withdraw(NAMES.index(pad), 1.0, POSES["home"])
    assert run["onset"].sideways and run["onset"].reason == "sideways"
    assert run["leaves_m"] >= LEAVES_M[pad]  # away from the contact point, across the normal
    assert -run["away_m"].min() <= TOWARD_BUDGET_M + 2e-4


def test_the_same_touch_in_the_same_pose_gives_the_same_motion_bit_for_bit() -> None:
    first = withdraw(NAMES.index("forearm_top"), 0.58, POSES["lap 1/4"])["path"]
    again = withdraw(NAMES.index("forearm_top"), 0.58, POSES["lap 1/4"])["path"]
    reused = build()
    withdraw(NAMES.index("wrist_3"), 1.0, POSES["home"], reused)  # a strategy that ran another reflex before
    third = withdraw(NAMES.index("forearm_top"), 0.58, POSES["lap 1/4"], reused)["path"]
    assert np.array_equal(first, again) and np.array_equal(first, third)


def test_the_motion_ramps_in_and_out_and_lasts_long_enough_to_be_seen() -> None:
    s = build()
    q = POSES["home"]
    s.start(q.copy(), contact(NAMES.index("forearm_top"), 1.0))
    assert s.duration_s >= 1.0
    speeds = [float(np.linalg.norm(MODEL.pad_jacobian(q, s.pad)[:3] @ s.velocity(q, t, count=False)))
              for t in np.arange(0.0, s.duration_s + 0.01, 0.01)]
    assert speeds[0] == pytest.approx(0.0, abs=1e-6) and speeds[-1] == 0.0
    peak = int(np.argmax(speeds))
    assert 0.3 <= peak * 0.01 <= 0.7
    rise = np.diff(speeds[: int(s.ramp_s / 0.01)])
    assert np.all(rise >= -1e-9) and rise.max() < 0.2 * max(speeds)  # no step: a ramp over ramp_s


def test_a_zero_gain_commands_nothing() -> None:
    s = build()
    s.start(POSES["home"].copy(), contact(NAMES.index("forearm_top"), 0.0))
    assert not s.velocity(POSES["home"], 0.5).any()


def test_a_pose_where_nothing_can_withdraw_holds_still_and_reports_why(caplog: pytest.LogCaptureFixture,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    # No approach at all allowed: the elbow's side can be withdrawn only by turning the base, which swings the
    # shoulder toward the contact point; across its normal, the upper arm or forearm come closer.
    monkeypatch.setattr(whole_arm, "APPROACH_BUDGET_M", 0.0)
    s = build()
    with caplog.at_level(logging.INFO, logger="nwr"):
        run = withdraw(NAMES.index("elbow_outer"), 1.0, POSES["home"], s)
    assert run["onset"].reason == "blocked" and not run["onset"].sideways
    assert np.abs(run["path"] - POSES["home"]).max() == 0.0  # held still
    assert [n[:2] for n in s.notes] == [("info", "whole_arm_blocked")]
    assert "holding still" in caplog.text


@pytest.mark.parametrize("failure", ["none", "nan", "raises"])
def test_a_solver_failure_commands_a_stand_still_and_is_reported_once(failure: str,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    s = build()
    s.start(POSES["home"].copy(), contact(NAMES.index("forearm_top"), 1.0))

    def broken(*_args: object, **_kwargs: object) -> tuple[object, ...]:
        if failure == "raises":
            raise ValueError("constraints are inconsistent, no solution")
        return (None if failure == "none" else np.full(6, np.nan), 0.0)

    monkeypatch.setattr(whole_arm.quadprog, "solve_qp", broken)
    for k in range(5):
        assert not s.velocity(POSES["home"], 0.3 + k * 0.002).any()
    assert s.failures == 5
    assert [n[:2] for n in s.notes] == [("warning", "whole_arm_failed")]


def test_a_ramp_longer_than_half_the_withdrawal_is_refused() -> None:
    from nwr.common.errors import ConfigError

    with pytest.raises(ConfigError, match="ramp_s"):
        build(duration_s=0.5, ramp_s=0.3)


def touched(cfg: PlannerSection, pad: str, gain: float) -> tuple[Planner, int, m.Command | None]:
    """A planner of ``cfg`` in its task, the touch on ``pad`` at ``gain`` given to it: the planner, the time (ns)
    and its answer."""
    planner, t = running(cfg, DESC, MODEL)
    index = NAMES.index(pad)
    gains = [0.0] * len(NAMES)
    gains[index] = gain
    pain = m.SkinPain(seq=1, stamp_ns=t, trace=m.Trace(1, t - 1000), model="continuous", level=[1] * len(NAMES),
                      gain=gains, strongest=contact(index, gain))
    return planner, t, planner.on_pain(pain, t)


def test_the_planner_streams_it_for_its_own_duration_and_the_status_says_sideways() -> None:
    cfg = PlannerSection(strategy="whole-arm", name="whole-arm")
    planner, t, command = touched(cfg, "shoulder_outer", 1.0)
    assert isinstance(command, m.VelocityCommand)
    assert planner.mode == "REFLEX"
    status = planner.status(t)
    assert status.reflex is not None and status.reflex.reason == "sideways"
    # Its sideways withdrawal is held to the outward speed cap: it lasts longer than duration_s, at most twice.
    duration = status.reflex.duration_s
    assert WholeArmSettings().duration_s < duration <= whole_arm.STRETCH_MAX * WholeArmSettings().duration_s
    cycles = 0
    while planner.mode == "REFLEX":
        t += 2_000_000
        planner.step(t)
        cycles += 1
    assert cycles == pytest.approx(duration * cfg.rate_hz, abs=2)


def _reflex_and_return(pad: str, gain: float) -> np.ndarray:
    """The planner's commanded poses from a touch on ``pad`` until its task resumes (the paper's immediate
    return: no hold)."""
    cfg = PlannerSection(strategy="whole-arm", name="whole-arm", sustained_contact="paper")
    planner, t, _ = touched(cfg, pad, gain)
    path = [planner.q.copy()]
    while planner.mode != "TASK":
        t += 2_000_000
        planner.step(t)
        path.append(planner.q.copy())
    return np.array(path)


@pytest.mark.parametrize("retraces", [True, False], ids=["retraced", "straight"])
def test_the_return_retraces_the_withdrawal_so_that_nothing_comes_closer_on_the_way_back(
        retraces: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(WholeArm, "retraces", retraces)
    path = _reflex_and_return("upper_arm_bottom", 1.0)
    pad = NAMES.index("upper_arm_bottom")
    p0 = MODEL.pad_point(path[0], pad)
    d0 = np.linalg.norm(MODEL.pad_points(path[0]) - p0, axis=1)
    closest = np.min([np.linalg.norm(MODEL.pad_points(q) - p0, axis=1) for q in path], axis=0)
    approach = d0 - closest
    approach[pad] = 0.0
    assert np.abs(path[-1] - path[0]).max() < 0.05  # back at the task, where it paused
    if retraces:
        assert approach.max() <= APPROACH_BUDGET_M + 1e-3
    else:  # the straight line in joint space swings wrist_2 closer than the withdrawal ever brought it
        assert approach.max() > 2 * APPROACH_BUDGET_M


@pytest.mark.parametrize(("pad", "gain"), [("wrist_3", 0.6), ("wrist_3", 1.0), ("forearm_top", 0.6),
                                           ("upper_arm_bottom", 1.0)])
def test_the_retraced_return_approaches_the_touched_place_no_faster_than_the_approach_speed(pad: str,
                                                                                              gain: float) -> None:
    # The return's legs through the withdrawal's poses: a leg that ends short of the slow stretch near the place
    # must not hand over at a speed it cannot brake from in time (it would run into the stretch fast and back).
    cfg = PlannerSection(strategy="whole-arm", name="whole-arm")
    planner, t, _ = touched(cfg, pad, gain)
    index = NAMES.index(pad)
    place = MODEL.pad_point(planner.q, index)
    lifted = m.SkinPain(seq=2, stamp_ns=t + 40_000_000, trace=m.Trace(2, t), model="continuous",
                        level=[1] * len(NAMES), gain=[0.0] * len(NAMES), strongest=None)
    previous, fastest, returned = place, 0.0, False
    for k in range(6000):
        t += 2_000_000
        if k == 20:
            planner.on_pain(lifted, t)
        planner.step(t)
        at = MODEL.pad_point(planner.q, index)
        if planner.mode == "RETURNING":
            returned = True
            to = place - at
            dist = float(np.linalg.norm(to))
            if 0.002 < dist <= cfg.approach_distance_m:
                fastest = max(fastest, float((at - previous) @ to) / dist / 0.002)
        previous = at
        if returned and planner.mode == "TASK":
            break
    assert returned and planner.mode == "TASK"
    assert fastest <= cfg.approach_speed_m_s * 1.05
