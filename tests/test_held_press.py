"""A finger held on a pad: the arm withdraws once, stays away while the touch lasts, returns at a person's speed.

The planner's state machine on its own (HOLDING, the release, the stop of a
return that feels a touch ahead, max_hold_s, a pad that cannot withdraw),
then whole sessions in lockstep (`nwr press`): a 3 s press on every pad, in
open and closed loop.
"""

from __future__ import annotations

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import CartesianLimits, PlannerSection, Profile, load_profile
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner.core import Planner
from nwr.services.tools.press import held_press, held_presses

DESC = load_description(None)
MODEL = RobotModel(DESC)
MS = 1_000_000
LIMITS = CartesianLimits()


def pain(pad: str | None, level: int, gain: float, seq: int, t: int) -> m.SkinPain:
    levels, gains = [1] * len(DESC.pads), [0.0] * len(DESC.pads)
    contact = None
    if pad is not None:
        info = DESC.pad(pad)
        levels[info.id], gains[info.id] = level, gain
        contact = m.Contact(pad=info.id, name=info.name, region=info.region, change_hpa=14.0, level=level, gain=gain)
    return m.SkinPain(seq=seq, stamp_ns=t, trace=m.Trace(seq, 0), model="continuous", level=levels, gain=gains,
                      strongest=contact)


class Run:
    """A planner on its own, stepped every 2 ms, fed pain every 40 ms (the skin's 25 Hz)."""

    def __init__(self, strategy: str = "cartesian", **cfg: object) -> None:
        self.p = Planner(PlannerSection(strategy=strategy, **cfg), DESC, MODEL, limits=LIMITS)
        self.p.on_state(DESC.home.copy(), following=True)
        self.t = 0
        self.seq = 0
        self.commands: list[m.Command] = []
        while self.p.mode != "TASK":
            self.step()
        for _ in range(500):  # the task under way, 1 s
            self.step()

    def step(self) -> None:
        self.t += 2 * MS
        cmd = self.p.step(self.t)
        if cmd is not None:
            self.commands.append(cmd)

    def feel(self, pad: str | None, level: int = 4, gain: float = 1.0) -> None:
        self.seq += 1
        cmd = self.p.on_pain(pain(pad, level, gain, self.seq, self.t), self.t)
        if cmd is not None:
            self.commands.append(cmd)

    def run(self, seconds: float, pad: str | None = None, level: int = 4, gain: float = 1.0) -> None:
        """``seconds`` of control cycles, with pain (``pad`` at ``level``, else nothing) every 20 cycles."""
        for i in range(round(seconds / 0.002)):
            if i % 20 == 0:
                self.feel(pad, level, gain)
            self.step()


def test_the_arm_stays_away_while_the_touch_lasts_and_returns_once_it_has_ended():
    r = Run()
    r.run(3.0, "wrist_3")  # a 3 s press, at the top pain level all along
    assert r.p.started == 1 and r.p.restarted == 0
    assert r.p.mode == "HOLDING"
    held = r.commands[-100:]
    assert all(c.phase == "HOLDING" for c in held)
    assert np.ptp(np.array([c.q for c in held]), axis=0).max() == 0.0  # at rest
    r.run(0.2)  # released, for less than release_s (0.3 s)
    assert r.p.mode == "HOLDING"
    r.run(0.2)
    assert r.p.mode == "RETURNING"
    r.run(8.0)
    assert r.p.mode == "TASK" and r.p.started == 1


def test_the_papers_behaviour_returns_as_soon_as_the_withdrawal_ends():
    r = Run(sustained_contact="paper")
    r.run(0.6, "wrist_3")
    assert r.p.mode == "RETURNING"


def test_a_return_that_feels_a_touch_ahead_stops_there_jerk_limited():
    r = Run()
    r.run(0.6, "wrist_3")
    r.run(0.5)  # released: the return begins
    assert r.p.mode == "RETURNING"
    r.run(0.3)
    before = len(r.commands)
    r.run(0.5, "wrist_3", level=2, gain=0.0)  # felt again (PL 2, no pain): the finger is still there
    assert r.p.mode == "HOLDING" and r.p.started == 1 and r.p.restarted == 0
    q = np.array([c.q for c in r.commands[before - 3:]])
    dt = 0.002
    acc = np.diff(q, n=2, axis=0) / dt**2
    jerk = np.diff(acc, axis=0) / dt
    assert np.all(np.abs(acc) <= r.p.a_limit * 1.01)
    assert np.all(np.abs(jerk) <= 0.9 * DESC.j_max * 1.01)  # the planner's speed_fraction of the jerk limit
    assert np.ptp(q[-50:], axis=0).max() == 0.0  # at rest


def test_returns_and_approaches_keep_to_a_persons_speed():
    r = Run()
    r.run(0.6, "wrist_3")
    saved = r.p.saved.copy()
    contact = MODEL.pad_point(saved, DESC.pad("wrist_3").id)
    start = len(r.commands)
    r.run(6.0)
    assert r.p.mode == "TASK"
    back = [c for c in r.commands[start:] if c.phase == "RETURNING"]
    q = np.array([c.q for c in back])
    dq = np.diff(q, axis=0) / 0.002
    cfg = PlannerSection()
    pad = DESC.pad("wrist_3").id
    for qi, dqi in zip(q[1:], dq):
        speeds = np.linalg.norm(MODEL.speed_jacobians(qi) @ dqi, axis=1)
        assert speeds.max() <= cfg.return_speed_m_s * 1.02
        if np.linalg.norm(MODEL.pad_point(qi, pad) - contact) < 0.8 * cfg.approach_distance_m:
            assert speeds[pad] <= cfg.approach_speed_m_s * 1.05


def test_a_touch_still_felt_after_max_hold_gets_only_a_return_that_approaches_no_touch():
    r = Run(max_hold_s=1.0)
    r.run(2.0, "wrist_3")
    notes = r.p.drain_notes()
    assert [code for _, code, _ in notes] == ["max_hold"] and "wrist_3" in notes[0][2]
    r.run(1.0, "wrist_3")
    assert r.p.mode == "HOLDING" and r.p.restarted == 0  # it never went back into the finger
    assert not r.p.drain_notes()  # said once per hold


def test_a_pad_that_cannot_withdraw_holds_still_and_says_so():
    r = Run("cartesian")
    r.feel("shoulder_back")
    assert r.p.mode == "REFLEX"
    assessment = r.p.assess()
    assert assessment is not None and assessment.withdrawal_m < 0.002
    assert r.p.mode == "HOLDING"
    status = r.p.status(r.t)
    assert status.reflex is not None and status.reflex.withdraws is False


# -- whole sessions in lockstep ------------------------------------------------------------

def check(press) -> None:
    t = press.touch
    assert t is not None, f"{press}: the press was not seen"
    where = f"{press.strategy}, {'closed' if press.closed_loop else 'open'} loop, {press.pad}"
    assert press.reflexes == 1, f"{where}: {press.reflexes} reflexes"
    assert t.returns_into == 0, f"{where}: {t.returns_into} returns into the finger"
    if t.return_speed_m_s is not None:
        assert t.return_speed_m_s <= LIMITS.speed_m_s, f"{where}: returned at {t.return_speed_m_s:.3f} m/s"
    assert t.resumed_after_s is None or t.resumed_after_s > 3.0, f"{where}: the task resumed during the press"


@pytest.mark.parametrize("closed", [False, True])
@pytest.mark.parametrize("pad", ["wrist_3", "shoulder_back", "forearm_top"])
def test_a_held_press_gets_one_reflex_and_no_return_into_it(pad, closed):
    check(held_press(load_profile(), "cartesian", pad, closed_loop=closed))


def test_the_papers_behaviour_returns_into_a_finger_still_pressing():
    profile = load_profile()
    profile.planner.sustained_contact = "paper"
    press = held_press(profile, "cartesian", "wrist_3", closed_loop=False)
    assert press.touch is not None and press.touch.returns_into >= 1 and press.reflexes >= 2


@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["cartesian", "cartesian-smooth", "uniform", "location", "whole-arm"])
def test_a_3s_press_on_every_pad_in_open_and_closed_loop(strategy):
    for press in held_presses(Profile(), [strategy]):
        check(press)


def test_the_first_approach_to_the_task_keeps_to_a_persons_speed_from_far_away():
    p = Planner(PlannerSection(), DESC, MODEL, limits=LIMITS)
    start = DESC.home + np.array([1.5, -0.8, 1.0, 1.2, 1.5, 3.0])  # 3 rad away on the wrist
    p.on_state(start, following=True)
    q = [p.q.copy()]
    t = 0
    while p.mode != "TASK":
        t += 2 * MS
        p.step(t)
        q.append(p.q.copy())
    q = np.array(q)
    dq = np.diff(q, axis=0) / 0.002
    peak = max(float(np.linalg.norm(MODEL.speed_jacobians(qi) @ v, axis=1).max()) for qi, v in zip(q[1:], dq))
    assert PlannerSection().return_speed_m_s * 0.5 < peak <= PlannerSection().return_speed_m_s * 1.02
