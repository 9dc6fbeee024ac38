"""Returns near recent contacts (services/planner/returning.py): no pad nor the flange within approach_distance_m
of a touch felt in the last recent_contact_s moves toward it faster than approach_speed_m_s.

Synthetic contacts are placed on the way of a return (the first approach to the task's start, which is one), and
the planner's commanded stream, integrated cycle by cycle, is measured against each of them; in lockstep, the
`contacts` script's touch on the way back, at home and at a second pose.
"""

from __future__ import annotations

from pathlib import Path

import msgspec
import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import PlannerSection, Profile
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner.contacts import ContactPoint
from nwr.services.planner.core import Planner
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.replay import simulate

DESC = load_description()
MODEL = RobotModel(DESC)
NAMES = [pad.name for pad in DESC.pads]
DT_NS = 2_000_000  # the planner's 500 Hz cycle
CFG = PlannerSection(strategy="cartesian")
# A start away from the task's: the base and the shoulder turned, so that every pad sweeps across the room.
AWAY = np.array([0.9, -0.35, 0.0, 0.3, 0.0, 0.0])


def points(q: np.ndarray) -> np.ndarray:
    """The points the rule keeps slow: every pad and the flange."""
    return np.vstack([MODEL.pad_points(q), MODEL.tool_position(q)])


def approach(contacts: list[tuple[str, float]]) -> tuple[list[np.ndarray], list[ContactPoint], Planner]:
    """The commanded poses of the first approach from DESC.home + AWAY to the task's start, with a recent touch
    on each (pad, fraction of the straight way) of ``contacts``, where that pad passes at that fraction."""
    planner = Planner(CFG, DESC, MODEL)
    q0 = DESC.home + AWAY
    target = planner.task.position(0.0)
    places = []
    for name, x in contacts:
        i = NAMES.index(name)
        q = q0 + x * (target - q0)
        places.append(ContactPoint(i, MODEL.pad_point(q, i), MODEL.pad_normal(q, i), 0.0, 0, 0))
        planner.contacts.touches[i] = places[-1]
    planner.on_state(q0.copy(), following=True)
    poses, t = [q0.copy()], 0
    while planner.mode != "TASK":
        t += DT_NS
        planner.step(t)
        poses.append(planner.q.copy())
        assert t < 60e9, "the approach arrives"
    return poses, places, planner


def fastest_toward(poses: list[np.ndarray], place: np.ndarray, within: float) -> float:
    """The fastest any pad or the flange moved toward ``place`` while within ``within`` of it, m/s."""
    worst = 0.0
    for a, b in zip(poses, poses[1:]):
        xa, xb = points(a), points(b)
        to = place - xa
        dist = np.linalg.norm(to, axis=1)
        close = (dist <= within) & (dist > 1e-9)
        if close.any():
            speed = np.einsum("pk,pk->p", xb - xa, to) / np.where(close, dist, 1.0) / (DT_NS / 1e9)
            worst = max(worst, float(np.max(np.where(close, speed, 0.0))))
    return worst


def test_without_a_recent_contact_the_way_sweeps_fast_through_where_one_would_be() -> None:
    poses, _, _ = approach([])
    q0, target = poses[0], poses[-1]
    for name, x in [("wrist_1", 0.15), ("wrist_2", 0.5), ("wrist_3", 0.85)]:
        i = NAMES.index(name)
        place = MODEL.pad_point(q0 + x * (target - q0), i)
        assert fastest_toward(poses, place, CFG.approach_distance_m) > 2.5 * CFG.approach_speed_m_s


@pytest.mark.parametrize("contacts", [[("wrist_2", 0.5)], [("wrist_3", 0.3), ("forearm_top", 0.7)],
                                      [("wrist_1", 0.15), ("elbow_outer", 0.6), ("upper_arm_bottom", 0.85)]])
def test_no_point_approaches_a_recent_contact_faster_than_the_approach_speed(contacts: list[tuple[str, float]]
                                                                              ) -> None:
    poses, places, planner = approach(contacts)
    assert np.allclose(poses[-1], planner.task.position(0.0), atol=1e-6)  # it still arrives where the task starts
    for place in places:
        assert fastest_toward(poses, place.point, CFG.approach_distance_m) <= CFG.approach_speed_m_s * 1.001
    # Away from the contacts it keeps the return's pace: every point within return_speed_m_s, the fastest near it.
    fastest_away = 0.0
    for a, b in zip(poses, poses[1:]):
        speeds = np.linalg.norm(points(b) - points(a), axis=1) / (DT_NS / 1e9)
        assert speeds.max() <= CFG.return_speed_m_s * 1.001
        if min(np.linalg.norm(points(a) - p.point, axis=1).min() for p in places) > 2 * CFG.approach_distance_m:
            fastest_away = max(fastest_away, float(speeds.max()))
    assert fastest_away >= 0.8 * CFG.return_speed_m_s


def test_a_touch_that_begins_during_a_return_slows_the_rest_of_it_near_every_recent_contact() -> None:
    """A touch felt during a return (PL 2, no reflex) has the rest of the return planned again: near it, and near
    every other recent contact, no point moves toward the place faster than the approach speed."""

    def run(felt: bool) -> float:
        planner = Planner(CFG, DESC, MODEL)
        q0 = DESC.home + AWAY
        target = planner.task.position(0.0)
        planner.on_state(q0.copy(), following=True)
        poses, t = [q0.copy()], 0
        for _ in range(300):  # under way
            t += DT_NS
            planner.step(t)
            poses.append(planner.q.copy())
        assert planner.mode == "RETURNING"
        i = NAMES.index("wrist_2")  # a place ahead on its way, known since now
        ahead = q0 + 0.6 * (target - q0)
        place = ContactPoint(i, MODEL.pad_point(ahead, i), MODEL.pad_normal(ahead, i), 0.0, t, t)
        planner.contacts.touches[i] = place
        if felt:  # a touch on the shoulder, felt now: the return is planned again
            level = [1] * len(NAMES)
            level[NAMES.index("shoulder_back")] = 2
            pain = m.SkinPain(seq=1, stamp_ns=t, trace=m.Trace(1, t), model="continuous", level=level,
                              gain=[0.0] * len(NAMES), strongest=None)
            assert planner.on_pain(pain, t) is None and planner.mode == "RETURNING"
            assert planner.contacts.touches[i] is place  # still recent
        while planner.mode != "TASK":
            t += DT_NS
            planner.step(t)
            poses.append(planner.q.copy())
        assert np.allclose(poses[-1], target, atol=1e-6)
        return fastest_toward(poses[301:], place.point, CFG.approach_distance_m)

    assert run(felt=False) > 2.5 * CFG.approach_speed_m_s  # planned before the place was known: through it fast
    assert run(felt=True) <= CFG.approach_speed_m_s * 1.001


# -- a touch on the way back, in lockstep -------------------------------------------------------------------------

# The `contacts` script's reflex on wrist_2 and a touch on forearm_bottom while the arm returns from it (the
# script's own touch at 12 s comes during the hold before the return; here it comes after the return began).
ON_THE_WAY_BACK = """duration_s = {end}

[[touch]]
pad = "wrist_2"
start_s = 10.0
duration_s = 0.3
peak_hpa = 20.0

[[touch]]
pad = "forearm_bottom"
start_s = {touch_s}
duration_s = 0.3
peak_hpa = 12.0
"""


@pytest.mark.slow
@pytest.mark.parametrize(("home", "touch_s"), [(None, 11.2), ([0.6, -1.4, 0.6, -1.2, -1.57, 0.8], 11.2)],
                         ids=["home", "pose-2"])
def test_a_touch_on_the_way_back_withdraws_from_where_the_arm_is_and_the_return_keeps_clear_of_it(
        tmp_path: Path, home: list[float] | None, touch_s: float) -> None:
    """A touch on forearm_bottom while the arm returns from wrist_2's reflex: a fresh reflex from where the arm
    is (not from where the first began), the task's saved pose kept, and a way back to it that neither goes past
    the new touch's place nor approaches either place faster than the approach speed (the commanded stream)."""
    profile = Profile() if home is None else msgspec.convert(
        {"planner": {"task": {"home_rad": home}}, "bridge": {"initial_q": home}}, Profile)
    script = tmp_path / "on-the-way-back.toml"
    script.write_text(ON_THE_WAY_BACK.format(end=touch_s + 8.0, touch_s=touch_s), encoding="utf-8")
    path = simulate(profile, str(script), "cartesian", tmp_path / "contacts.mcap")[0]
    records, _ = read_recording(path)
    pains = [r.message for r in records if r.key == "skin/pain"]
    states = [r.message for r in records if r.key == "robot/state"]
    statuses = [r.message for r in records if r.key.endswith("/status")]
    commands = [r.message for r in records if r.key.startswith("robot/command")]
    t0 = pains[0].stamp_ns
    first, second = NAMES.index("wrist_2"), NAMES.index("forearm_bottom")

    def reflex_of(pad: int, after_s: float) -> m.ReflexInfo:
        return next(s.reflex for s in statuses if s.reflex is not None and s.reflex.contact.pad == pad
                    and s.stamp_ns - t0 > after_s * 1e9)

    one, two = reflex_of(first, 9.0), reflex_of(second, touch_s - 1.0)
    onsets = {seq: next(s for s in states if s.reflex_seq == seq and s.accepted is not None)
              for seq in (one.reflex_seq, two.reflex_seq)}
    onset = onsets[two.reflex_seq]
    before = [s for s in states if s.stamp_ns < onset.stamp_ns][-1]
    assert before.phase == "RETURNING"  # the touch came on the way back
    # From where the arm is: the reflex's first state is a cycle on from the return's last, far from where the
    # first reflex began.
    assert np.max(np.abs(np.asarray(onset.q) - np.asarray(before.q))) < 0.01
    assert np.max(np.abs(np.asarray(before.q) - np.asarray(onsets[one.reflex_seq].q))) > 0.05
    saved = {tuple(s.saved_pose) for s in statuses if s.saved_pose is not None and s.reflex is not None
             and s.reflex.reflex_seq in (one.reflex_seq, two.reflex_seq)}
    assert len(saved) == 1  # the pose the task paused at, kept through the second reflex
    touches = [t for t in analysis.summarize(records, DESC, MODEL) if t.pad == second and t.gain > 0.0]
    assert len(touches) == 1 and (touches[0].past_after_mm or 0.0) <= analysis.PAST_MM
    resumed = next(s for s in statuses if s.stamp_ns > onset.stamp_ns and s.mode == "TASK")
    back = [c for c in commands if isinstance(c, m.PositionCommand) and c.phase == "RETURNING"
            and onset.stamp_ns < c.stamp_ns < resumed.stamp_ns]
    assert np.max(np.abs(np.asarray(next(iter(saved))) - np.asarray(back[-1].q))) < 1e-3  # where the task paused
    # The commanded way back: near each of the two places (where the pad was at the first felt pain sample), while
    # it is recent, no point toward it faster than the approach speed.
    cfg = profile.planner
    for pad in (first, second):
        felt = [p.stamp_ns for p in pains if p.stamp_ns - t0 > 9.0e9 and p.level[pad] >= 2]
        place = MODEL.pad_point(np.asarray([s for s in states if s.stamp_ns <= felt[0]][-1].q), pad)
        poses = [np.asarray(c.q) for c in back if c.stamp_ns < felt[-1] + cfg.recent_contact_s * 1e9]
        assert fastest_toward(poses, place, cfg.approach_distance_m) <= cfg.approach_speed_m_s * 1.001
