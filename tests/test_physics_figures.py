"""The physics world's force figures per touch: the measured peak force, pressure and energy on the person beside
ISO/TS 15066's limits, in the per-touch table, its CSV, the quality table and ``nwr compare``; a lockstep session
of a packaged multi-contact script in the physics world that ``nwr verify`` re-makes bit for bit."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.launch import load_script
from nwr.common.recordings import Recorded, read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.tools.recordings import analysis, compare, summary, table
from nwr.services.tools.recordings.replay import simulate
from nwr.services.tools.recordings.verify import verify
from nwr.services.view.core import encode_frame
from nwr.services.view.export import load_records, make_core
from nwr.services.worlds.hosted import finger_force
from nwr.services.worlds.people import ISO_TS_15066, load_limits
from nwr.services.worlds.settings import PhysicsSettings

DESC = load_description()
PAD = DESC.pad("forearm_top").id
OTHER = DESC.pad("upper_arm_top").id
S = 1_000_000_000


def person(touch: int, force: float, pressure: float, energy: float, pushed: float) -> m.WorldPerson:
    return m.WorldPerson(name=f"touch-{touch}", kind="finger", touch=touch, pads=[PAD], force_n=force,
                         peak_force_n=force, pressure_n_cm2=pressure, peak_pressure_n_cm2=pressure, energy_j=energy,
                         pushed_m=pushed, peak_pushed_m=pushed)


def touch_at(pad: int, start_s: float) -> analysis.TouchSummary:
    return analysis.TouchSummary(pad, DESC.pads[pad].name, DESC.pads[pad].region, round(start_s * S),
                                 round((start_s + 1) * S), 0, 10, 15.0)


def recorded(*people: list[m.WorldPerson], body_area: str = "") -> list[Recorded]:
    scripted = m.SkinTouch(seq=4, stamp_ns=S, pad=PAD, name="forearm_top", origin_ns=0, start_s=1.0,
                           duration_s=1.0, peak_hpa=15.0, shape="step", ramp_s=0.0, body_area=body_area)
    return [Recorded(keys.SKIN_TOUCH, S, scripted),
            *(Recorded(keys.WORLD_CONTACTS, S + i, m.WorldContacts(seq=i, stamp_ns=S + i, world_ns=i, people=p))
              for i, p in enumerate(people))]


def test_a_touch_gets_its_fingers_measured_peaks_and_the_limits_of_the_body_area_it_is_judged_by() -> None:
    records = recorded([person(4, 10.0, 50.0, 0.01, 0.001)], [person(4, 20.0, 120.0, 0.03, 0.004)],
                       [person(4, 15.0, 90.0, 0.05, -0.002)])
    mine, elsewhere, later = touch_at(PAD, 1.1), touch_at(OTHER, 1.1), touch_at(PAD, 5.0)
    analysis.world_figures([mine, elsewhere, later], records)

    assert (mine.peak_force_n, mine.peak_pressure_n_cm2, mine.energy_j) == (20.0, 120.0, 0.05)
    assert mine.into_finger_mm == pytest.approx(4.0)
    finger = ISO_TS_15066["forefinger_pad_d"]  # a touch script's finger: the dominant forefinger's pad
    assert mine.body_area == "forefinger_pad_d"
    assert (mine.force_limit_n, mine.pressure_limit_n_cm2) == (finger.force_n, finger.pressure_n_cm2) == (140, 300)
    assert (mine.transient_force_limit_n, mine.transient_pressure_limit_n_cm2) == (280, 600)
    assert mine.of_limit == pytest.approx(max(20.0 / 140.0, 120.0 / 300.0))
    # Another pad's touch, and one long after the finger met the pad, are not this finger's.
    for other in (elsewhere, later):
        assert other.peak_force_n is None and other.of_limit is None and other.body_area == ""


def test_a_touch_that_names_a_body_area_is_judged_by_that_areas_limits() -> None:
    mine = touch_at(PAD, 1.1)
    analysis.world_figures([mine], recorded([person(4, 20.0, 120.0, 0.03, 0.004)], body_area="forearm_muscle"))
    forearm = ISO_TS_15066["forearm_muscle"]
    assert mine.body_area == "forearm_muscle" and (forearm.region, forearm.label) == (
        "lower arms and wrist joints", "forearm muscle")
    assert (mine.force_limit_n, mine.pressure_limit_n_cm2) == (forearm.force_n, forearm.pressure_n_cm2) == (160, 180)
    assert (mine.transient_force_limit_n, mine.transient_pressure_limit_n_cm2) == (320, 360)
    assert mine.of_limit == pytest.approx(max(20.0 / 160.0, 120.0 / 180.0))


def test_iso_ts_15066s_values_come_from_their_data_file_each_row_compared_with_a_reproduction(tmp_path) -> None:
    assert len(ISO_TS_15066) == 29 and all(r.checked and r.label for r in ISO_TS_15066.values())
    assert load_limits() == ISO_TS_15066
    bad = tmp_path / "limits.toml"
    bad.write_text('[[area]]\nname = "palm_d"\nlabel = "palm"\nregion = "hands"\npressure_n_cm2 = -1\n'
                   'force_n = 140\n')
    with pytest.raises(ConfigError, match=r"limits.toml: Expected `float` >= 0|limits.toml: .*pressure_n_cm2"):
        load_limits(bad)
    twice = 'name = "palm_d"\nlabel = "palm"\nregion = "hands"\npressure_n_cm2 = 260\nforce_n = 140\n'
    bad.write_text(f"[[area]]\n{twice}\n[[area]]\n{twice}")
    with pytest.raises(ConfigError, match="body area 'palm_d' is given twice"):
        load_limits(bad)


def test_the_quality_table_gives_the_worst_force_and_counts_the_touches_beyond_the_limits() -> None:
    within, beyond = touch_at(PAD, 1.0), touch_at(PAD, 3.0)
    within.peak_force_n, within.peak_pressure_n_cm2, within.of_limit = 30.0, 150.0, 0.5
    beyond.peak_force_n, beyond.peak_pressure_n_cm2, beyond.of_limit = 45.0, 330.0, 1.1
    q = analysis.quality([within, beyond], "uniform")
    assert (q.worst_force_n, q.worst_pressure_n_cm2, q.worst_of_limit, q.over_limit) == (45.0, 330.0, 1.1, 1)
    row = analysis.world_quality_rows([q])[0]
    assert row == ["uniform", "45.0", "330.0", "110", "1"] and len(row) == len(analysis.WORLD_QUALITY_HEADER)
    # Without a physics world there is nothing to judge: "-", not 0.
    assert analysis.world_quality_rows([analysis.quality([touch_at(PAD, 1.0)], "uniform")])[0][1:] == ["-"] * 4


@pytest.fixture(scope="module")
def two_fingers(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The packaged two-finger touch in the physics world, in lockstep, recorded."""
    profile = Profile()
    profile.bridge.backend, profile.gateway.source = "physics", "physics"
    path = tmp_path_factory.mktemp("physics") / "two-fingers.mcap"
    simulate(profile, "two-fingers", "uniform", path)
    return path


@pytest.mark.slow
def test_a_lockstep_physics_session_of_two_fingers_verifies_and_measures_both(two_fingers: Path,
                                                                             capsys: pytest.CaptureFixture) -> None:
    results = verify(two_fingers)
    lines = [r.format() for r in results]
    assert all(r.verdict == "identical" for r in results) and len(results) == 4, lines
    bridge = next(r for r in results if r.service == "bridge")
    assert bridge.outputs[keys.WORLD_CONTACTS] > 10, bridge.format()

    assert print_summary(two_fingers) == 0
    out = capsys.readouterr().out
    assert "the physics world's fingers:" in out and "forefinger pad d (140 N, 300 N/cm^2" in out, out
    with table.csv_path(two_fingers).open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    script = load_script("two-fingers")
    for touch in script.touch:  # both fingers pressed with about the script's force, well within the limits
        row = next(r for r in rows if r["name"] == touch.pad and r["peak_force_n"])
        assert 10.0 < float(row["peak_force_n"]) < 40.0 and float(row["peak_pressure_n_cm2"]) > 0.0, row
        assert float(row["energy_j"]) >= 0.0 and 0.0 < float(row["of_limit"]) < 1.0, row
        assert row["body_area"] == "forefinger_pad_d" and row["force_limit_n"] == "140.0", row

    model = RobotModel(DESC)
    sessions = [compare.load_session(two_fingers, DESC, model), compare.load_session(two_fingers, DESC, model)]
    world = compare.world_table(sessions, compare.line_up(sessions, 0.3))
    assert world is not None and world.count("upper_arm_top") == 2 and "peak force (N)" in world


@pytest.mark.slow
def test_the_view_of_a_lockstep_physics_session_shows_both_fingers_and_the_force_on_them(two_fingers: Path) -> None:
    records, _ = load_records(two_fingers)
    core = make_core()
    seen: dict[str, float] = {}
    outputs = 0
    for record in records:
        core.apply(record.message)
        if isinstance(record.message, m.WorldContacts):
            frame = core.frame(record.log_time_ns)
            for mark in frame.people:
                name = DESC.pads[mark.pad].name
                seen[name] = max(seen.get(name, 0.0), mark.force_n)
                assert mark.arrow is not None and mark.arrow.length > 0.0
            outputs += sum(1 for o in encode_frame(frame) if o.topic == "/nwr/people")
    assert outputs > 10
    assert sorted(seen) == ["forearm_top", "upper_arm_top"], seen
    assert all(10.0 < force < 40.0 for force in seen.values()), seen


@pytest.mark.slow
def test_a_slow_press_whose_finger_follows_the_arm_is_felt_at_the_scripts_force_and_verifies(tmp_path) -> None:
    profile = Profile()
    profile.bridge.backend, profile.gateway.source = "physics", "physics"
    path = tmp_path / "slow-press.mcap"
    simulate(profile, "slow-press", "uniform", path)
    touch = load_script("slow-press").touch[0]
    assert touch.follow_m_s > 0.0
    records, _ = read_recording(path, only=analysis.summarized)
    touches = analysis.summarize(records, DESC, RobotModel(DESC))
    mine = [t for t in touches if t.pad == PAD]
    # Held where it met the pad, the task carried the pad away before the ramp's push built (1.2 N at most, no
    # touch felt); followed, the ramp is felt, answered by a reflex, at about the force the script asks for.
    assert mine and any(t.reflex_seq for t in mine), mine
    peak = max(t.peak_force_n or 0.0 for t in mine)
    assert 0.8 * finger_force(touch.peak_hpa, PhysicsSettings()) < peak < 30.0, peak
    assert max(t.into_finger_mm or 0.0 for t in mine) < 5.0
    results = verify(path)
    assert all(r.verdict == "identical" for r in results) and len(results) == 4, [r.format() for r in results]


def print_summary(path: Path) -> int:
    return summary.print_summary(path, None, Profile(), columns="t,pad,peak")


def test_compare_has_no_physics_table_without_a_physics_world() -> None:
    sessions = [compare.Session(Path(name), name, [], 0, [touch_at(PAD, 1.0)]) for name in ("a", "b")]
    assert compare.world_table(sessions, compare.line_up(sessions, 0.3)) is None
