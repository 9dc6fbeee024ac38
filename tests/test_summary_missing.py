"""A summary says what its recording cannot tell: no pain data (a real skin's imported recording), no planner, no
latency on simulated time. It never shows such a touch as "PL 1, gain 0, no reflex"."""

from __future__ import annotations

from pathlib import Path

import pytest

from nwr.common.config import load_profile
from nwr.common.recordings import McapRecorder, read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.tools.recordings import compare, summary, table
from nwr.services.tools.recordings.replay import simulate

DATA = Path(__file__).parent / "data"
DESC = load_description()
PROFILE = load_profile()


@pytest.fixture(scope="module")
def lockstep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("lockstep") / "short.mcap"
    return simulate(PROFILE, str(DATA / "short.toml"), "cartesian", out)[0]


@pytest.fixture(scope="module")
def imported(lockstep: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """What ``nwr import`` makes of a lab's bag: the skin's pressures and the joint states, nothing else."""
    records, _ = read_recording(lockstep)
    out = tmp_path_factory.mktemp("imported") / "imported.mcap"
    with out.open("wb") as f:
        recorder = McapRecorder(f, "ur10e")
        recorder.metadata("session", {"robot": "ur10e", "timing": "imported"})
        for r in records:
            if r.key in ("skin/pressure", "robot/state"):
                recorder.write(f"nwr/ur10e/{r.key}", r.message, r.log_time_ns)
        recorder.finish()
    return out


def test_without_pain_data_the_levels_come_from_the_pressures_and_the_reflexes_are_unknown(
        imported: Path, capsys: pytest.CaptureFixture) -> None:
    assert summary.print_summary(imported, str(DATA / "short.toml"), PROFILE) == 0
    out = capsys.readouterr().out
    words = " ".join(out.split())
    assert max(map(len, out.splitlines())) <= 120, out
    assert "no pain data (skin/pain) in this recording: PL and gain computed from each touch's peak pressure " \
           "through the profile's continuous gain model (thresholds 2/6/12/20 hPa)" in words, out
    assert "no planner in this recording" in words and "cannot be judged" in words, out
    assert "all 4 scripted touches seen (their reflexes cannot be judged: no planner)" in out, out
    rows = {line.split()[1]: line.split() for line in out.splitlines()
            if line.split()[1:2] and line.split()[1] in ("upper_arm_top", "forearm_top", "wrist_2", "elbow_outer")}
    # 9 hPa on forearm_top: PL 3 with a gain, 18 hPa on wrist_2: PL 4; whether either moved the arm: "?".
    assert rows["forearm_top"][3:6] == ["3", "0.182", "?"], out
    assert rows["wrist_2"][3] == "4" and float(rows["wrist_2"][4]) > 0.8 and rows["wrist_2"][5] == "?", out
    assert rows["elbow_outer"][3:6] == ["1", "0.000", "?"], out
    csv_text = table.csv_path(imported).read_text(encoding="utf-8")
    assert "pain_computed" in csv_text and "reflex_known" in csv_text


def test_a_recording_with_pain_and_a_planner_has_no_such_note(lockstep: Path, capsys: pytest.CaptureFixture) -> None:
    assert summary.print_summary(lockstep, str(DATA / "short.toml"), PROFILE) == 0
    out = capsys.readouterr().out
    assert "no pain data" not in out and "no planner" not in out and "all 4 scripted touches as expected" in out


def test_compare_shows_no_latency_of_a_lockstep_recording(lockstep: Path, capsys: pytest.CaptureFixture) -> None:
    model = RobotModel(DESC)
    session = compare.load_session(lockstep, DESC, model, PROFILE)
    reflexes = [t for t in session.touches if t.reflex_seq]
    assert len(reflexes) == 2 and all(t.onset_latency_ms is None for t in reflexes)
    assert any("lockstep" in n and "no onset latency is measured" in n for n in session.notes)
    text = compare.table([session], compare.line_up([session], 0.3))
    onset = text.splitlines()[0].index("onset (ms)")
    assert {line[onset:onset + len("onset (ms)")].strip() for line in text.splitlines()[2:]} == {"-"}, text
