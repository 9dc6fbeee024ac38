"""The study's statistics at small N, with ties and zero differences, against independent computations."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from study_synthetic import condition_forms, final_forms, ratings_of

from nwr.common.questionnaire import load_questionnaire
from nwr.common.recordings import Recorded
from nwr.common.robot import RobotModel, load_description
from nwr.services.tools.recordings import analysis
from nwr.services.tools.study import analysis as sa
from nwr.services.tools.study.store import ConditionForm, FinalAnswer, FinalForm, Rating

Q, _ = load_questionnaire()
CONDITIONS = ("uniform", "location", "cartesian")
DATA = Path(__file__).parent / "data"
DESC = load_description()


def _brute_force_p(d: np.ndarray) -> float:
    """Every sign pattern of the non-zero differences, one by one."""
    ranks = stats.rankdata(np.abs(d))
    centre = ranks.sum() / 2
    observed = abs(ranks[d > 0].sum() - centre)
    far = sum(1 for signs in itertools.product((False, True), repeat=d.size)
              if abs(ranks[np.array(signs)].sum() - centre) >= observed - 1e-9)
    return far / 2 ** d.size


def _permutation_p(d: np.ndarray) -> float:
    """scipy's permutation test of T+ on the differences (one sample: each one's sign flipped)."""
    ranks = stats.rankdata(np.abs(d))

    def t_plus(x: np.ndarray, axis: int) -> np.ndarray:
        return np.sum(np.where(x > 0, ranks, 0.0), axis=axis)

    return float(stats.permutation_test((d,), t_plus, permutation_type="samples", n_resamples=np.inf,
                                        vectorized=True, alternative="two-sided").pvalue)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 12, 16, 20])
def test_the_exact_p_without_ties_is_scipys_exact_wilcoxon(n):
    rng = np.random.default_rng(n)
    for _ in range(5):
        d = rng.permutation(np.arange(1, n + 1)) * rng.choice([-1.0, 1.0], n) + rng.normal(0, 0.01, n)
        expected = stats.wilcoxon(d, method="exact").pvalue
        assert sa.signed_rank_exact_p(d) == pytest.approx(expected, rel=1e-12, abs=1e-15), d


@pytest.mark.parametrize("seed", range(8))
def test_the_exact_p_with_ties_counts_every_sign_pattern(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 12))
    d = rng.choice([-1.0, -2 / 3, -1 / 3, 1 / 3, 2 / 3, 1.0, 4 / 3], n)  # subscale means' differences: ties
    p = sa.signed_rank_exact_p(d)
    assert p == pytest.approx(_brute_force_p(d), rel=1e-12)
    assert p == pytest.approx(_permutation_p(d), rel=1e-9)


def test_the_issues_examples_exact_not_the_normal_approximation():
    twelve = np.array([1.0, 1, 1, 2, 2, 2, 0.5, 0.5, 1, 2, 1, 0.5])  # every participant higher, ties
    assert sa.signed_rank_exact_p(twelve) == pytest.approx(2 / 2 ** 12)  # 0.00049, the approximation 0.002
    assert stats.wilcoxon(twelve, method="approx").pvalue == pytest.approx(0.002, abs=1e-4)
    three = np.array([1.0, 1.0, 2.0])
    assert sa.signed_rank_exact_p(three) == pytest.approx(0.25)  # the approximation: 0.102
    assert stats.wilcoxon(three, method="approx").pvalue == pytest.approx(0.102, abs=5e-4)
    with pytest.raises(ValueError, match="non-zero"):
        sa.signed_rank_exact_p(np.array([1.0, 0.0]))


def _forms(levels: dict[str, list[int]]) -> list[Rating]:
    """Participant i rates every item of condition c ``levels[c][i]`` (reversed items stored reversed)."""
    forms = []
    reversed_items = {i for s in Q.scales() for i in s.reversed}
    n = len(next(iter(levels.values())))
    for i in range(n):
        for block, c in enumerate(levels, start=1):
            v = levels[c][i]
            ratings = {item: Q.points + 1 - v if item in reversed_items else v for item in Q.rated_items()}
            forms.append(ConditionForm(participant=f"P{i + 1:02d}", condition=c, order=1, block=block,
                                       ratings=ratings))
    return ratings_of(forms)


def test_three_participants_get_exact_p_values():
    result = sa.analyze(_forms({"uniform": [5, 5, 4], "location": [3, 4, 3], "cartesian": [1, 2, 1]}), [], Q)
    s = result.scales[0]
    # Every participant ranks the conditions alike: 6 of the 6^3 orderings do (chi2 = 6; its approximation 0.0498).
    assert stats.friedmanchisquare([5, 5, 4], [3, 4, 3], [1, 2, 1]).pvalue == pytest.approx(0.0498, abs=1e-4)
    assert (s.p, s.p_method) == (pytest.approx(6 / 216), "exact")
    assert [(pt.n, pt.zeros, pt.method) for pt in s.pairs] == [(3, 0, "exact")] * 3
    assert [pt.p for pt in s.pairs] == pytest.approx([0.25] * 3)  # the normal approximation said 0.102
    text = sa.report(result, "s", [])
    assert "| Anthropomorphism | 3 | 6.00 | 0.0278 * | exact |" in text
    assert "| Anthropomorphism | UR vs LR | 3 | 0 | 0.0 | 0.25 | exact | 0.75 |" in text


def _friedman_permutation_p(data: np.ndarray) -> float:
    """scipy's permutation test of the Friedman statistic (each participant's ratings reordered)."""
    def chi2(*samples: np.ndarray, axis: int) -> np.ndarray:
        x = np.moveaxis(np.stack(samples), 0, -1)  # ... x participants x conditions
        r = stats.rankdata(x, axis=-1)
        return np.sum(r.sum(axis=-2) ** 2, axis=-1)

    return float(stats.permutation_test(tuple(data.T), chi2, permutation_type="samples", n_resamples=np.inf,
                                        vectorized=True, alternative="greater").pvalue)


@pytest.mark.parametrize("seed", range(6))
def test_the_exact_friedman_p_with_ties_counts_every_ordering(seed):
    rng = np.random.default_rng(seed)
    n, k = (3, 3) if seed < 2 else (5, 3) if seed < 4 else (3, 4)
    data = rng.integers(1, 4, size=(n, k)).astype(float) + rng.choice([0, 1 / 3], size=(n, k))
    p = sa.friedman_exact_p(data)
    assert p == pytest.approx(_friedman_permutation_p(data), rel=1e-9)
    brute = [sum(r ** 2 for r in np.sum(rows, axis=0))
             for rows in itertools.product(*(itertools.permutations(stats.rankdata(row)) for row in data))]
    observed = sum(r ** 2 for r in stats.rankdata(data, axis=1).sum(axis=0))
    assert p == pytest.approx(np.mean(np.array(brute) >= observed - 1e-9), rel=1e-12)


def test_a_larger_study_takes_the_friedman_p_from_chi2():
    rng = np.random.default_rng(41)
    result = sa.analyze(ratings_of(condition_forms(Q, rng, 12, {"uniform": 1.2})), [], Q)
    for s in result.scales:
        assert s.p_method == "chi2"
        data = np.array([[s.scores[c][p] for c in result.conditions] for p in result.complete])
        assert s.p == pytest.approx(stats.friedmanchisquare(*data.T).pvalue)
    seven = sa.analyze(ratings_of(condition_forms(Q, rng, 7, {"uniform": 1.2})), [], Q)
    assert {s.p_method for s in seven.scales} == {"exact"}  # 6^7 orderings; 6^8 > 2^20


def test_zero_differences_are_dropped_and_counted():
    # P01 and P02 rate uniform and location alike: 4 of 6 pairs tested.
    levels = {"uniform": [4, 3, 5, 5, 4, 5], "location": [4, 3, 2, 3, 1, 2], "cartesian": [1, 1, 1, 1, 1, 1]}
    result = sa.analyze(_forms(levels), [], Q)
    s = result.scales[0]
    assert s.p is not None and s.p < 0.05
    pair = next(pt for pt in s.pairs if (pt.a, pt.b) == ("uniform", "location"))
    assert (pair.n, pair.zeros, pair.method) == (4, 2, "exact")
    assert pair.p == pytest.approx(stats.wilcoxon([3, 2, 3, 3], method="exact").pvalue)  # 0.125
    assert "| Anthropomorphism | UR vs LR | 4 | 2 |" in sa.report(result, "s", [])


@pytest.mark.parametrize(("n", "method"), [(12, "exact"), (24, "normal")])
def test_every_pair_of_a_synthetic_study_matches_an_independent_computation(n, method):
    rng = np.random.default_rng(41)
    result = sa.analyze(ratings_of(condition_forms(Q, rng, n, {"uniform": 1.2})), [], Q)
    tested = 0
    for s in result.scales:
        for pt in s.pairs:
            a = np.array([s.scores[pt.a][p] for p in result.complete])
            b = np.array([s.scores[pt.b][p] for p in result.complete])
            d = np.round(a - b, 9)
            nonzero = d[d != 0]
            assert (pt.n, pt.zeros) == (nonzero.size, n - nonzero.size)
            if nonzero.size <= sa.EXACT_MAX_N:
                assert pt.method == "exact"
                if nonzero.size <= 14:  # scipy's permutation test takes seconds beyond 2^14 patterns
                    assert pt.p == pytest.approx(_permutation_p(nonzero), rel=1e-9)
            else:
                assert pt.method == "normal"
                assert pt.p == pytest.approx(stats.wilcoxon(nonzero, method="approx").pvalue, rel=1e-9)
            tested += pt.method == method
    assert tested > 0


def test_a_friedman_p_just_below_005_keeps_its_digits():
    result = sa.analyze(_forms({"uniform": [5, 5, 4], "location": [3, 4, 3], "cartesian": [1, 2, 1]}), [], Q)
    result.scales[0].p = 0.0498  # the chi2 approximation's at this N
    assert "| 0.0498 * |" in sa.report(result, "s", []) and "0.050 *" not in sa.report(result, "s", [])


@pytest.mark.parametrize(("p", "text"), [(0.0498, "0.0498"), (0.04996, "0.04996"), (0.05, "0.05"),
                                         (0.00049, "0.00049"), (0.00999, "0.00999"), (0.25, "0.25"), (1.0, "1")])
def test_p_is_printed_with_the_digits_that_keep_its_star(p, text):
    assert sa._p(p) == text
    assert sa.stars(float(sa._p(p))) == sa.stars(p)


# -- small N: reliability, figures -----------------------------------------------------


def test_cronbachs_alpha_of_few_participants_or_negative_is_marked_not_interpretable():
    assert sa.alpha_text(-10.5, 3) == "-10.50 (not interpretable: N = 3 < 5)"
    assert sa.alpha_text(0.9, 4).endswith("(not interpretable: N = 4 < 5)")
    assert sa.alpha_text(-0.2, 12) == "-0.20 (not interpretable: negative)"
    assert sa.alpha_text(0.81, 5) == "0.81"
    rng = np.random.default_rng(4)
    result = sa.analyze(ratings_of(condition_forms(Q, rng, 3, {"uniform": 1.2})), [], Q)
    negative = [(s.scale.name, c) for s in result.scales for c, a in s.alpha.items() if a is not None and a < 0]
    assert negative  # three participants: alpha swings below 0
    text = sa.report(result, "s", [])
    rows = [line for line in text.splitlines() if line.startswith("| Perceived Safety | UR | 3 |")]
    assert len(rows) == 1 and "not interpretable: N = 3" in rows[0]
    assert all("not interpretable" in line for line in
               text.split("## Descriptive statistics")[1].split("## Friedman")[0].splitlines() if "| 3 |" in line)


def test_every_boxplot_shows_each_participants_score():
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(4)
    result = sa.analyze(ratings_of(condition_forms(Q, rng, 3, {"uniform": 1.2})), [], Q)
    for kind in ("godspeed", "custom"):
        fig = sa._boxplot_figure(result, kind, kind)
        scales = [s for s in result.scales if s.scale.kind == kind]
        for ax, s in zip(fig.axes, scales):
            shown = np.concatenate([np.asarray(c.get_offsets())[:, 1] for c in ax.collections])
            expected = np.concatenate([list(s.scores[c].values()) for c in result.conditions])
            assert sorted(shown.tolist()) == pytest.approx(sorted(expected.tolist())), s.scale.name
        plt.close(fig)


def test_the_radar_plots_question_names_stay_off_its_ring():
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(4)
    forms = condition_forms(Q, rng, 3, {})
    finals = [a for f in final_forms(Q, rng, 3, {"uniform": 2, "cartesian": 1, "none": 1})
              for a in _final_answers(f)]
    result = sa.analyze(ratings_of(forms), finals, Q)
    fig = sa._radar_figure(result)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    ring = ax.get_window_extent(renderer)
    names = {c.short for c in Q.choice}
    labels = [t for t in ax.texts if t.get_text() in names]
    assert len(labels) == len(Q.choice)
    for t in labels:
        box = t.get_window_extent(renderer)
        assert box.x0 >= ring.x1 or box.x1 <= ring.x0 or box.y0 >= ring.y1 or box.y1 <= ring.y0, t.get_text()
    plt.close(fig)


def _final_answers(form: FinalForm) -> list[FinalAnswer]:
    return [FinalAnswer(form.participant, item, "choice", text, "") for item, text in form.choices.items()]


# -- what the recordings measured ------------------------------------------------------


@pytest.fixture(scope="module")
def cartesian_session() -> list[Recorded]:
    """The lockstep pipeline (gateway, planner, simulated bridge; no network) on the short touch script under
    the Cartesian reflex: its second touch's pain rises over several skin samples, each restarting the reflex."""
    import msgspec

    from nwr.common import keys
    from nwr.common.config import Profile
    from nwr.common.launch import load_script
    from nwr.services.gateway.core import Gateway, SimSkin, sim_settings
    from nwr.services.pipeline.lockstep import Lockstep

    profile, script = Profile(), load_script(str(DATA / "short.toml"))
    sim = SimSkin(sim_settings(profile.gateway), DESC.pads, script)
    gateway = Gateway(profile.gateway, len(DESC.pads))
    samples = []
    for i in range(int(script.duration_s * 25)):
        t = (i + 1) / 25
        samples.append(gateway.process(t, 10**9 + round(t * 1e9), sim.sample(t))[0])
    produced: list[tuple[str, bytes, int]] = []
    Lockstep(Profile(), strategy="cartesian").run(
        samples, lambda k, msg, t: produced.append((k, msgspec.msgpack.encode(msg), t)))
    records = [Recorded("skin/pressure", s.stamp_ns, s) for s in samples]
    records += [Recorded(k, t, keys.codec(k).decode(b)) for k, b, t in produced]
    return sorted(records, key=lambda r: r.log_time_ns)


def test_the_peak_speed_is_the_whole_withdrawals_not_its_first_skin_period(cartesian_session):
    model = RobotModel(DESC)
    touches = analysis.summarize(cartesian_session, DESC, model)
    states = [r.message for r in cartesian_session if r.key == "robot/state"]
    checked = 0
    for touch in touches:
        if not touch.reflex_seq or touch.withdrawal_mm is None or touch.withdrawal_mm < 50:
            continue
        # The touched pad's mean speed along its normal from the onset to its furthest withdrawal (where the
        # arm stops withdrawing): the peak of the arm's fastest point can be no lower.
        onset = next(s for s in states if s.reflex_seq == touch.reflex_seq and s.accepted is not None)
        n0 = model.pad_normal(np.asarray(onset.q), touch.pad)
        p0 = model.pad_points(np.asarray(onset.q))[touch.pad]
        along = [(s.stamp_ns, float((model.pad_points(np.asarray(s.q))[touch.pad] - p0) @ n0))
                 for s in states if s.stamp_ns >= onset.accepted_ns and s.phase == "REFLEX"]
        t_far, far = min(along, key=lambda x: x[1])
        mean_speed = -far / ((t_far - onset.accepted_ns) / 1e9)
        assert mean_speed > 0.1, touch  # the session's slow-building touch: a real withdrawal
        # (before, summarize stopped at the touch's own first restart, 40 ms in: 0.068 m/s for 126 mm)
        assert touch.peak_speed_m_s is not None and touch.peak_speed_m_s >= mean_speed, (touch.name, mean_speed)
        checked += 1
    assert checked == 1


def test_the_reports_peak_speed_comes_from_the_whole_withdrawal(cartesian_session, tmp_path, monkeypatch):
    from nwr.common import recordings

    monkeypatch.setattr(recordings, "read_recording", lambda path, only=None: (
        [r for r in cartesian_session if only is None or only(r.key)], {}))
    forms = condition_forms(Q, np.random.default_rng(1), 1, {}, ("cartesian", "uniform"))
    ratings = ratings_of(forms)
    for r in ratings:
        (tmp_path / r.recording).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / r.recording).touch()
    measures = sa.measure_recordings(ratings, tmp_path, lambda: DESC)
    model = RobotModel(DESC)
    touches = analysis.summarize(cartesian_session, DESC, model)
    assert measures["cartesian"].peak_m_s == pytest.approx([t.peak_speed_m_s for t in touches if t.reflex_seq])
    assert max(measures["cartesian"].peak_m_s) > 0.2  # summarize's own said 0.068


def test_the_study_reads_only_what_the_summary_needs_and_gets_the_same_touches(cartesian_session, tmp_path):
    from nwr.common import keys
    from nwr.common.recordings import McapRecorder, read_recording

    needed = [r for r in cartesian_session if analysis.summarized(r.key)]
    assert 0 < len(needed) < len(cartesian_session) / 2  # the commands are most of a session
    assert analysis.summarize(needed, DESC) == analysis.summarize(cartesian_session, DESC)
    path = tmp_path / "s.mcap"
    with path.open("wb") as f:
        recorder = McapRecorder(f, "ur10e")
        for r in cartesian_session:
            recorder.write(keys.key("ur10e", r.key), r.message, r.log_time_ns)
        recorder.finish()
    records, _ = read_recording(path, only=analysis.summarized)
    assert [(r.key, r.log_time_ns) for r in records] == [(r.key, r.log_time_ns) for r in needed]


def test_the_rank_biserial_interval_is_a_bootstrap_over_participants():
    rng = np.random.default_rng(2)
    a = rng.integers(1, 6, 12).astype(float)
    b = a - rng.choice([-1, 0, 0, 1, 1, 2], 12)  # ties and zero differences
    low, high = sa.rank_biserial_ci(a, b, resamples=400, seed=3)
    # The same resamples, one by one through rank_biserial.
    idx = np.random.default_rng(3).integers(0, 12, size=(400, 12))
    rs = [sa.rank_biserial(a[i], b[i]) for i in idx]
    assert (low, high) == pytest.approx(tuple(np.percentile(rs, [2.5, 97.5])))
    assert low <= sa.rank_biserial(a, b) <= high and -1 <= low < high <= 1
    assert sa.rank_biserial_ci(a + 1, a) == (1.0, 1.0)  # everyone higher: every resample says so
    # scipy's bootstrap of the same statistic agrees to within the resampling noise.
    ref = stats.bootstrap((a, b), lambda x, y: sa.rank_biserial(x, y), paired=True, vectorized=False,
                          method="percentile", n_resamples=2000, rng=np.random.default_rng(0)).confidence_interval
    assert sa.rank_biserial_ci(a, b) == pytest.approx((ref.low, ref.high), abs=0.1)
    result = sa.analyze(ratings_of(condition_forms(Q, np.random.default_rng(18), 12, {"uniform": 1.2})), [], Q)
    pair = result.scales[0].pairs[0]
    assert pair.r_ci is not None and f"| {pair.r:.2f} | {pair.r_ci[0]:.2f} to {pair.r_ci[1]:.2f} |" in \
        sa.report(result, "s", [])
