"""The figures are drawn by the services' own code and show what they claim."""

from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib.colors import same_color, to_rgb

from nwr.common.config import Profile
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner import retreat
from nwr.services.tools import figures
from nwr.services.tools.recordings import analysis, compare
from nwr.services.tools.recordings.replay import simulate

DATA = Path(__file__).parent / "data"
DESC = load_description()
MODEL = RobotModel(DESC)


def pixels_of(image: np.ndarray, color: str, tol: float = 0.06) -> int:
    rgb = np.asarray(to_rgb(color))
    return int(np.sum(np.all(np.abs(image[..., :3] - rgb) < tol, axis=-1)))


def test_gain_figure(tmp_path):
    path = figures.gain_figure(tmp_path / "gain.png")
    assert path.stat().st_size > 20_000
    image = mpimg.imread(path)
    assert image.shape[0] >= 500 and image.shape[1] >= 900
    # Both curves are drawn, the continuous one longer (it rises smoothly).
    cont, disc = pixels_of(image, figures.CONTINUOUS_COLOR), pixels_of(image, figures.DISCRETE_COLOR)
    assert cont > 2000 and disc > 2000


@pytest.mark.slow
def test_reflexes_figure(tmp_path):
    path = figures.reflexes_figure(tmp_path / "reflexes.png")
    assert path.stat().st_size > 100_000
    image = mpimg.imread(path)
    assert image.shape[1] > 1.5 * image.shape[0]  # four columns side by side, three rows
    for color in figures.TOUCH_COLORS:
        assert pixels_of(image, color) > 300, color
    assert pixels_of(image, "0.55", tol=0.03) > 1000  # the initial pose


def test_reflex_end_poses_differ_as_the_paper_says():
    desc = load_description()
    model = RobotModel(desc)
    ends = {(s, p): figures.reflex_end_pose(s, desc, model, p)[1] for s in ("uniform", "location")
            for p in desc.figure_pads}
    # UR is stereotypical: the same end pose whatever was touched; LR depends on the region.
    np.testing.assert_allclose(ends[("uniform", "upper_arm_top")], ends[("uniform", "wrist_2")], atol=1e-6)
    assert np.abs(ends[("location", "upper_arm_top")] - ends[("location", "wrist_2")]).max() > 0.1


def texts(fig) -> list[str]:
    """Every title, axis label, text and legend entry of a figure (its subfigures' too)."""
    out = [t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text") and hasattr(a, "get_position"))]
    return [t for t in out if t]


def test_contact_motion_is_positive_away_from_the_contact_and_negative_toward_it():
    """The figures' measure of a touch: the retreat check's, signed so that a withdrawal goes up."""
    pad = DESC.pad("wrist_2").id
    q0 = DESC.home.copy()
    toward = np.linalg.pinv(MODEL.pad_jacobian(q0, pad)[:3]) @ MODEL.pad_normal(q0, pad)  # pad along +n0
    into = np.array([q0 + s * toward for s in np.linspace(0.0, 0.02, 11)])
    away, approach, _ = analysis.contact_motion(MODEL, into, pad, q0)
    assert away[0] == 0.0 and np.all(np.diff(away) < 0) and away[-1] == pytest.approx(-0.02, rel=0.05)
    check = retreat.assess(MODEL, into, 0.01, pad)
    assert -away.min() == pytest.approx(check.toward_m) and away[-1] == pytest.approx(check.withdrawal_m)
    others = np.delete(check.approach_m, pad)
    assert max(0.0, approach.max()) == pytest.approx(others.max())
    out = np.array([q0 - s * toward for s in np.linspace(0.0, 0.02, 11)])
    away, _, _ = analysis.contact_motion(MODEL, out, pad, q0)
    assert np.all(np.diff(away) > 0) and away[-1] == pytest.approx(0.02, rel=0.05)


def test_the_uniform_reflex_on_the_upper_arm_moves_its_pad_toward_the_contact():
    """The paper's criticism of UR, as the reflexes figure plots it: below zero, not as a distance."""
    run = figures.reflex_runs(("uniform",), DESC, MODEL, Profile().planner, Profile().bridge.limits)
    assert run[("uniform", "upper_arm_top")].away_mm.min() < -100.0
    assert run[("uniform", "wrist_2")].away_mm.min() > -1.0 and run[("uniform", "wrist_2")].away_mm[-1] > 100.0


def test_the_uniform_panel_says_its_end_poses_coincide():
    plt = figures._pyplot()
    fig = figures.draw_reflexes(("uniform", "location"))
    try:
        ur, lr = (ax for ax in fig.axes if ax.name == "3d")
        assert any("same end pose" in t.get_text() for t in ur.texts)
        assert not any("same end pose" in t.get_text() for t in lr.texts)
        # The three coinciding poses are drawn dashed, each in its colour, so that every colour shows.
        dashed = [line for line in ur.get_lines() if line.get_linestyle() != "-"]
        for color in figures.TOUCH_COLORS:
            assert any(same_color(line.get_color(), color) for line in dashed), color
    finally:
        plt.close(fig)
    assert figures.coinciding([np.zeros(6), np.ones(6), np.zeros(6) + 1e-6]) == [[0, 2], [1]]


def test_the_smoothed_cartesian_panel_shows_what_the_smoothing_changed():
    plt = figures._pyplot()
    fig = figures.draw_reflexes(("cartesian", "cartesian-smooth"))
    try:
        speed = [ax for ax in fig.axes if ax.get_title().startswith("its speed")]
        assert len(speed) == 2
        cr, smooth = speed
        assert "dashed: Cartesian (CR)" in smooth.get_title()
        pink = figures.TOUCH_COLORS[load_description().figure_pads.index("wrist_2")]

        def curve(ax, ls: str) -> np.ndarray:
            return next(line.get_ydata() for line in ax.get_lines()
                        if same_color(line.get_color(), pink) and line.get_linestyle() == ls)
        cr_v, smooth_v = curve(cr, "-"), curve(smooth, "-")
        np.testing.assert_array_equal(curve(smooth, "--"), cr_v)  # CR drawn under CR-smooth for comparison
        # CR steps up to its speed and is still at it at the end; CR-smooth ramps in and out.
        assert cr_v[-1] > 0.8 * cr_v.max() and smooth_v[-1] < 0.2 * smooth_v.max()
        assert np.argmax(smooth_v > 0.5 * smooth_v.max()) > np.argmax(cr_v > 0.5 * cr_v.max())
    finally:
        plt.close(fig)


@pytest.fixture(scope="module")
def short_sessions(tmp_path_factory) -> list[compare.Session]:
    """The short touch script in lockstep against UR and CR, recorded like ``nwr demo --fast``."""
    where = tmp_path_factory.mktemp("compare")
    paths = [simulate(Profile(), str(DATA / "short.toml"), s, where / f"short-{s}.mcap")[0]
             for s in ("uniform", "cartesian")]
    return [compare.load_session(p, DESC, MODEL) for p in paths]


def test_compare_figure_plots_the_table_s_withdrawal_signed(short_sessions):
    cr = short_sessions[1]
    touch = next(t for t in cr.touches if t.name == "wrist_2")
    motion = compare.touch_motion(cr, touch, MODEL)
    assert motion is not None and motion.onset_s is not None and motion.resumed_s is not None
    during = motion.t >= motion.onset_s
    # The table's withdrawal and toward, from the same contact point and normal: up and down, not a distance
    # (the table's toward covers the reflex and its hold; the figure goes on through the return).
    assert touch.toward_mm is not None and touch.withdrawal_mm is not None and touch.withdrawal_mm > 10.0
    assert motion.away_mm[during].min() <= -touch.toward_mm + 1e-9
    assert motion.away_mm[during].max() == pytest.approx(touch.withdrawal_mm)
    assert motion.t[0] == pytest.approx(-compare.FIGURE_BEFORE_S, abs=0.03)  # time from the touch's onset
    assert motion.t[-1] <= motion.resumed_s + 0.03  # the reflex and its return, not the task after it
    np.testing.assert_allclose(motion.dq[np.searchsorted(motion.t, motion.onset_s)], 0.0)


def test_a_touch_s_motion_ends_where_another_touch_s_reflex_begins(short_sessions):
    """UR's forearm_top reflex never resumes the task before wrist_2's touch: its withdrawal took in wrist_2's
    reflex to the end of the recording (550.8 mm in the table, 407 mm up to the next reflex)."""
    ur = short_sessions[0]
    forearm, wrist = (next(t for t in ur.touches if t.name == n) for n in ("forearm_top", "wrist_2"))
    assert forearm.resumed_after_s is None and wrist.reflex_seq  # the case: no resumption in between
    motion = compare.touch_motion(ur, forearm, MODEL)
    assert motion is not None
    before_next = (motion.t >= motion.onset_s) & (motion.t <= (wrist.start_ns - forearm.start_ns) / 1e9 + 0.1)
    assert forearm.withdrawal_mm == pytest.approx(motion.away_mm[before_next].max(), rel=0.02)


def test_compare_figure_names_the_joints_and_the_files(short_sessions):
    plt = figures._pyplot()
    rows = compare.line_up(short_sessions, 0.3)
    fig = compare.draw(short_sessions, rows, MODEL)
    try:
        words = texts(fig)
        for joint in DESC.joints:
            assert words.count(joint) == 2, joint  # one panel per joint, in each of the two reflex touches
        assert "short-uniform.mcap: Uniform (UR)" in words and "short-cartesian.mcap: Cartesian (CR)" in words
        assert any("withdrawal" in w and "toward the contact" in w and "(mm)" in w for w in words)
        assert any(w.startswith("time from the touch") and "(s)" in w for w in words)
        assert any("(rad)" in w for w in words)
        assert any(w.startswith("touch 3: wrist_2") for w in words)
    finally:
        plt.close(fig)


def visible(ax) -> list[float]:
    """Each curve's extent on ``ax`` as drawn, a fraction of the panel's height (lines, not marks or rules)."""
    out = []
    for line in ax.get_lines():
        x, y = np.asarray(line.get_xdata(), dtype=float), np.asarray(line.get_ydata(), dtype=float)
        if len(y) > 1 and np.nanmax(y) > np.nanmin(y) and np.nanmax(x) > np.nanmin(x):  # no rule
            shown = ax.transData.transform(np.c_[x, y])[:, 1]
            out.append(float((np.nanmax(shown) - np.nanmin(shown)) / ax.bbox.height))
    return out


def test_the_reflexes_figure_shares_its_scales_and_shows_every_curve():
    """Strategies compare by eye: one scale per row; UR's 900 mm beside CR's 20 mm on it still shows both."""
    plt = figures._pyplot()
    fig = figures.draw_reflexes(("uniform", "cartesian"))
    try:
        fig.canvas.draw()
        for title in ("touched pad", "its speed"):
            row = [ax for ax in fig.axes if ax.get_title().startswith(title)]
            assert len(row) == 2
            assert row[0].get_ylim() == row[1].get_ylim() and row[0].get_xlim() == row[1].get_xlim(), title
            assert [ax.get_yscale() for ax in row] == ["symlog", "symlog"], title
            for ax in row:
                assert len(visible(ax)) == 3 and min(visible(ax)) > 0.1, (title, visible(ax))
    finally:
        plt.close(fig)


def test_compare_s_figure_shows_every_file_s_curve(short_sessions):
    plt = figures._pyplot()
    fig = compare.draw(short_sessions, compare.line_up(short_sessions, 0.3), MODEL)
    try:
        fig.canvas.draw()
        forearm = next(ax for ax in fig.findobj(lambda a: hasattr(a, "get_title") and hasattr(a, "get_yscale"))
                       if ax.get_title().startswith("forearm_top: the touched pad"))
        assert forearm.get_yscale() == "symlog"  # UR's ~300 mm beside CR's few
        assert len(visible(forearm)) == 2 and min(visible(forearm)) > 0.2, visible(forearm)
        wrist = next(ax for ax in fig.findobj(lambda a: hasattr(a, "get_title") and hasattr(a, "get_yscale"))
                     if ax.get_title().startswith("wrist_2: the touched pad"))
        assert wrist.get_yscale() == "linear"  # 75 and 120 mm: one linear scale shows both
    finally:
        plt.close(fig)


# --------------------------------------------------------------------------- the reflex quality table

def _touch(pad, peak, gain, withdrawal, toward=0.0, other=0.0, jerk=None, withdraws=True):
    from nwr.services.tools.recordings.analysis import TouchSummary

    return TouchSummary(pad=pad, name=f"p{pad}", region="r", start_ns=0, end_ns=0, first_seq=0, last_seq=0,
                        peak_hpa=peak, gain=gain, reflex_seq=1, withdrawal_mm=withdrawal, toward_mm=toward,
                        other_approach_mm=other, peak_jerk_m_s3=jerk, withdraws=withdraws, strategy="s")


def test_the_quality_row_counts_approaches_repeats_and_the_gain_ranking():
    from nwr.services.tools.recordings.analysis import quality

    touches = [
        _touch(0, 6.0, 0.2, 10.0, toward=1.0, other=3.0, jerk=50.0),
        _touch(0, 12.0, 0.5, 30.0, toward=6.0, other=2.0, jerk=70.0),  # the pad came 6 mm toward the contact
        _touch(0, 20.0, 1.0, 60.0, other=8.5, jerk=90.0),
        _touch(0, 20.4, 0.99, 58.0),  # the same touch repeated: 2 mm apart
        _touch(1, 20.0, 1.0, 0.0, withdraws=False),  # a pad that cannot withdraw
        _touch(2, 9.0, 0.3, 40.0), _touch(2, 14.0, 0.6, 30.0), _touch(2, 22.0, 1.0, 20.0),  # backwards
    ]
    q = quality(touches)
    assert (q.strategy, q.reflexes, q.approached, q.worst_toward_mm, q.worst_other_mm) == ("s", 8, 1, 6.0, 8.5)
    assert q.withdrawal_min_mm == 10.0 and q.withdrawal_median_mm == 30.0
    assert (q.repeat_pairs, q.repeat_diff_mm) == (1, 2.0)
    assert q.gain_rank_corr == pytest.approx(0.0)  # pad 0: +1, pad 2: -1; the median
    assert q.peak_jerk_m_s3 == 70.0
    assert q.back_past == 0
    assert quality([]).reflexes == 0
    # Back past a recent touch: every touch the skin felt counts, a light one without a gain too.
    light = _touch(3, 1.2, 0.0, None)
    light.reflex_seq, light.past_after_mm = 0, 38.9
    assert quality([*touches, light]).back_past == 1
    light.past_after_mm = 9.7  # within the 10 mm margin
    assert quality([*touches, light]).back_past == 0


def test_the_gain_ranking_judges_each_withdrawal_by_what_the_joints_allowed_its_reflex():
    """A pad whose reach changes with the task's phase: full withdrawals (125 mm at G = 1) at one phase, short
    ones (a 20 mm reach) at another. In proportion within each reach; not across them."""
    import dataclasses

    from nwr.services.tools.recordings.analysis import quality, withdrawal_share

    def at(reach, gain, withdrawal):
        return dataclasses.replace(_touch(0, 4.0 + 20 * gain, gain, withdrawal), reach_mm=reach)

    touches = [at(125.0, 0.3, 37.0), at(20.0, 0.5, 11.5), at(125.0, 0.7, 86.0), at(20.0, 0.9, 18.0),
               at(125.0, 1.0, 121.0)]
    assert withdrawal_share(touches[1]) == pytest.approx(0.575)
    assert quality(touches).gain_rank_corr == pytest.approx(1.0)
    raw = [dataclasses.replace(t, reach_mm=None) for t in touches]  # a strategy that does not say
    assert quality(raw).gain_rank_corr == pytest.approx(0.5)
    assert withdrawal_share(dataclasses.replace(touches[0], withdrawal_mm=None)) is None


def test_peak_jerk_tells_a_velocity_step_from_a_ramp():
    from nwr.services.tools.recordings.analysis import peak_jerk

    t = np.arange(0, 21) * 20_000_000  # states at 50 Hz
    step = np.zeros((21, 3))
    step[10:, 0] = 0.25
    ramp = np.zeros((21, 3))
    ramp[:, 0] = 0.25 * np.clip((np.arange(21) - 5) / 10, 0, 1)
    assert peak_jerk(t, step) > 3 * peak_jerk(t, ramp) > 0
    assert peak_jerk(t[:2], step[:2]) is None


def test_a_recording_that_ends_as_a_reflex_begins_summarizes(short_sessions):
    """A session stopped in the arm's state that began a reflex (a study block's end) has no withdrawal to
    measure: its speeds are unknown, not an error; nor is a recording cut just before or after any reflex's
    first status or first state (a session ended by a crash) one."""
    cr = short_sessions[1]
    touch = next(t for t in cr.touches if t.name == "wrist_2")
    onset = next(r for r in cr.records if r.key == "robot/state" and r.message.reflex_seq == touch.reflex_seq
                 and r.message.accepted is not None)
    cut = [r for r in cr.records if r.log_time_ns <= onset.log_time_ns]
    last = next(t for t in analysis.summarize(cut, DESC, MODEL) if t.name == "wrist_2")
    assert last.reflex_seq == touch.reflex_seq and last.peak_speed_m_s is None and last.peak_jerk_m_s3 is None
    assert touch.peak_speed_m_s is not None  # the whole session's: measured
    for session in short_sessions:
        seen: set[tuple[str, int]] = set()
        for i, r in enumerate(session.records):
            seq = r.message.reflex_seq if r.key == "robot/state" else \
                r.message.reflex.reflex_seq if r.key.endswith("/status") and r.message.reflex is not None else 0
            if seq and (r.key, seq) not in seen:
                seen.add((r.key, seq))
                for end in (i, i + 1, i + 2):
                    analysis.quality(analysis.summarize(session.records[:end], DESC, MODEL))
        assert len(seen) > 4
