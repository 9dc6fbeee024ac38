"""The whole-arm withdrawal over the survey session, as a lab would measure it.

The survey script (every pad at 9, 15 and 25 hPa, twice each, across the
figure-eight) in lockstep against the whole-arm planner, the services' own
wirings and the simulated arm, then the per-touch table's figures from the
recording: the touched pad never comes toward the contact (beyond the few
millimetres the arm takes to brake from the task's own motion into the
finger), no other pad comes more than 5 mm closer to the contact point, every
pad its joints can move withdraws centimetres at full gain and in proportion
to the gain, the others withdraw sideways and the status says so, and the
same touch repeated gives the same withdrawal.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nwr.common.config import Profile
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.replay import simulate

pytestmark = pytest.mark.slow

DESC = load_description()
MODEL = RobotModel(DESC)
STRAIGHT = ("upper_arm_top", "upper_arm_bottom", "forearm_top", "forearm_bottom", "wrist_2", "wrist_3")
SIDEWAYS = ("shoulder_back", "shoulder_outer")
SHORT = ("elbow_outer", "wrist_1")


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> tuple[list, list]:
    path = simulate(Profile(), "survey", "whole-arm", tmp_path_factory.mktemp("survey") / "whole-arm.mcap")[0]
    records, _ = read_recording(path)
    return records, analysis.summarize(records, DESC, MODEL)


def test_every_touch_started_a_reflex_and_none_approached(session: tuple[list, list]) -> None:
    _, touches = session
    assert len(touches) == 60 and all(t.reflex_seq for t in touches)
    quality = analysis.quality(touches)
    assert quality.strategy == "whole-arm" and quality.reflexes == 60
    assert quality.approached == 0
    assert quality.worst_toward_mm is not None and quality.worst_toward_mm <= analysis.APPROACH_MM
    assert quality.worst_other_mm is not None and quality.worst_other_mm <= 5.0


def test_pads_its_joints_can_move_withdraw_in_proportion_to_the_gain(session: tuple[list, list]) -> None:
    _, touches = session
    for pad in STRAIGHT:
        mine = sorted((t.gain, t.withdrawal_mm) for t in touches if t.name == pad)
        assert len(mine) == 6
        full = [w for g, w in mine if g > 0.9]
        assert min(full) >= 70.0, (pad, mine)  # centimetres at full gain
        low = [w for g, w in mine if g < 0.3]
        assert max(low) < min(full) / 2, (pad, mine)  # a light touch, a small withdrawal
    assert analysis.quality(touches).gain_rank_corr >= 0.9


def test_the_same_touch_repeated_gives_the_same_withdrawal(session: tuple[list, list]) -> None:
    _, touches = session
    quality = analysis.quality(touches)
    assert quality.repeat_pairs == 30
    assert quality.repeat_diff_mm is not None and quality.repeat_diff_mm <= 2.0


def test_the_shoulder_pads_withdraw_sideways_the_elbow_short_and_the_status_says_so(session: tuple[list, list]) -> None:
    records, touches = session
    reasons = {r.message.reflex.reflex_seq: r.message.reflex.reason for r in records
               if r.key == "reflex/whole-arm/status" and r.message.reflex is not None}
    for touch in touches:
        if touch.name in SIDEWAYS:
            assert reasons[touch.reflex_seq] == "sideways", touch.name
        if touch.name in STRAIGHT:
            assert reasons[touch.reflex_seq] == "", touch.name
        if touch.name in SHORT:
            assert reasons[touch.reflex_seq] == "short", touch.name
    assert np.isfinite([t.peak_jerk_m_s3 for t in touches if t.peak_jerk_m_s3 is not None]).all()


def test_the_survey_is_the_packaged_script(tmp_path: Path) -> None:
    from nwr.common.launch import load_script

    script = load_script("survey")
    pads = {t.pad for t in script.touch}
    assert pads == {p.name for p in DESC.pads}
    assert sorted({t.peak_hpa for t in script.touch}) == [9.0, 15.0, 25.0]
    assert all(b.start_s - a.start_s >= 6.0 for a, b in zip(script.touch, script.touch[1:]))
