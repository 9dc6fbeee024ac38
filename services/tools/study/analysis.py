"""``nwr study analyze``: the study's answers and recordings, analysed as the paper did, as tables and figures.

Per participant and condition, each subscale's score is the mean of its
items, reversed items flipped (``points + 1 - x``). Across conditions, for
the participants who answered every condition (the others are listed, with
what they miss, and kept in the descriptive statistics only): the Friedman
test (``scipy.stats.friedmanchisquare``, effect size Kendall's W =
chi2 / (N (k - 1)); its p exact while the participants' orderings k!^N are at
most 2^20, ``friedman_exact_p``, else from chi2), and where its p < 0.05 the pairwise Wilcoxon signed-rank
tests (two-sided, zero differences dropped; with up to 20 non-zero
differences the exact p, every sign pattern counted with tied differences at
their mid-ranks, ``signed_rank_exact_p``; beyond, ``scipy.stats.wilcoxon``'s
normal approximation with the tie correction), their
p-values Holm-corrected within each subscale (the family: its k (k - 1) / 2
pairs), effect size the matched-pairs rank-biserial correlation. With two
conditions the one Wilcoxon test is the test. Cronbach's alpha per subscale
and condition describes the items' consistency (marked not interpretable with
fewer than 5 participants or below 0). Stars: *, **, *** for
(corrected) p below 0.05, 0.01, 0.001.

Per condition, what the recordings measured (``analysis.summarize`` of each
block's recording): reflexes per block, onset latency, withdrawal and peak
speed (over the whole withdrawal, a touch's restarts included), medians over
the condition's reflexes. A missing or unreadable
recording is said in the report, not fatal.

Besides report.md and the figures: the whole study as one table, a row per
block with its recording's figures beside its answers, as study.csv and
study.parquet (``nwr.services.tools.study.table``; columns in docs/study.md).
Open answers appear in the report as literal blocks (never Markdown or HTML),
at most 2000 characters each.
"""

from __future__ import annotations

import itertools
import logging
import math
import re
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from scipy import stats

from nwr.common.errors import NwrError
from nwr.common.questionnaire import Questionnaire, Scale
from nwr.services.tools.study import table
from nwr.services.tools.study.store import MAX_ANSWER_CHARS, NO_PREFERENCE, FinalAnswer, Rating, Store

log = logging.getLogger(__name__)

ALPHA = 0.05


def stars(p: float | None) -> str:
    if p is None or not np.isfinite(p):
        return ""
    return "***" if p < 0.001 else "**" if p < 0.01 else "*" if p < 0.05 else ""


def holm(p: list[float]) -> list[float]:
    """Holm's step-down adjusted p-values (the k-th smallest times (m - k + 1), made monotone, capped at 1)."""
    m = len(p)
    order = np.argsort(p, kind="stable")
    adjusted = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adjusted[i] = running
    return [float(x) for x in adjusted]


def cronbach_alpha(items: np.ndarray) -> float | None:
    """Cronbach's alpha of a participants x items matrix; None with fewer than 2 items or 2 participants, or
    no variance in the total."""
    n, k = items.shape
    if k < 2 or n < 2:
        return None
    total = items.sum(axis=1).var(ddof=1)
    if total == 0:
        return None
    # Rounded: an alpha of exactly 0 (the items' covariances summing to 0) comes out as -3e-16, which would
    # print "-0.00" and be called negative.
    return round(float(k / (k - 1) * (1 - items.var(axis=0, ddof=1).sum() / total)), 12) + 0.0


FRIEDMAN_EXACT_MAX = 2**20  # up to this many within-participant orderings (k!^n), the Friedman p is exact


def friedman_exact_p(data: np.ndarray) -> float:
    """The exact p of the Friedman test on ``data`` (participants x conditions), ties at their mid-ranks:
    under the null hypothesis each participant's ratings are equally likely in any order across the
    conditions, so each of the k!^n orderings is equally likely; p is the share whose statistic (the sum of the
    squared rank sums, which orders the orderings as chi2 does: the tie correction does not change under
    them) is at least the observed one. Built by counting the rank-sum vectors participant by participant."""
    doubled = np.rint(2 * stats.rankdata(data, axis=1)).astype(np.int64)  # mid-ranks: multiples of 1/2
    k = doubled.shape[1]
    counts: dict[tuple[int, ...], int] = {(0,) * k: 1}
    for row in doubled:
        orders = list(itertools.permutations(row.tolist()))
        grown: dict[tuple[int, ...], int] = defaultdict(int)
        for sums, c in counts.items():
            for order in orders:
                grown[tuple(a + b for a, b in zip(sums, order))] += c
        counts = grown
    observed = int((doubled.sum(axis=0) ** 2).sum())
    total = sum(counts.values())
    return sum(c for sums, c in counts.items() if sum(x * x for x in sums) >= observed) / total


def _differences(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b, rounded so that equal scores (means of integer ratings) differ by exactly 0 and equal differences
    tie: floating-point noise would otherwise break a tie or turn a zero difference into a rank."""
    return np.round(np.asarray(a, dtype=float) - np.asarray(b, dtype=float), 9)


ALPHA_MIN_N = 5  # Cronbach's alpha from fewer participants swings too widely to say anything about the items


def alpha_text(alpha: float | None, n: int) -> str:
    """Cronbach's alpha as the report prints it: with the reason it is not interpretable where it is not (too
    few participants, or negative: the items vary against each other more than together)."""
    if alpha is None:
        return "- (no variance or fewer than 2 items or participants)" if n else "-"
    if n < ALPHA_MIN_N:
        return f"{alpha:.2f} (not interpretable: N = {n} < {ALPHA_MIN_N})"
    if alpha < 0:
        return f"{alpha:.2f} (not interpretable: negative)"
    return f"{alpha:.2f}"


def rank_biserial(a: np.ndarray, b: np.ndarray) -> float:
    """Matched-pairs rank-biserial correlation of a - b (zero differences dropped): +1 every participant rated
    ``a`` higher, -1 every one ``b``."""
    d = _differences(a, b)
    d = d[d != 0]
    if d.size == 0:
        return 0.0
    ranks = stats.rankdata(np.abs(d))
    return float((ranks[d > 0].sum() - ranks[d < 0].sum()) / ranks.sum())


BOOTSTRAP_RESAMPLES = 2000


def rank_biserial_ci(a: np.ndarray, b: np.ndarray, resamples: int = BOOTSTRAP_RESAMPLES,
                     seed: int = 0) -> tuple[float, float]:
    """95 % percentile bootstrap interval of ``rank_biserial(a, b)``: the participants resampled with
    replacement (their pairs kept together), the same seed every run so a report is reproducible."""
    d = _differences(a, b)
    rng = np.random.default_rng(seed)
    resampled = d[rng.integers(0, d.size, size=(resamples, d.size))]
    zeros = (resampled == 0).sum(axis=1, keepdims=True)
    # Zero differences tie at the lowest ranks (1..z): the others' ranks among the non-zero ones are theirs - z.
    ranks = np.where(resampled != 0, stats.rankdata(np.abs(resampled), axis=1) - zeros, 0.0)
    total = ranks.sum(axis=1)
    signed = (np.sign(resampled) * ranks).sum(axis=1)
    r = np.divide(signed, total, out=np.zeros_like(total), where=total > 0)
    low, high = np.percentile(r, [2.5, 97.5])
    return float(low), float(high)


EXACT_MAX_N = 20  # up to this many non-zero differences, every one of the 2^n sign patterns is counted


def signed_rank_exact_p(d: np.ndarray) -> float:
    """Two-sided exact p of the Wilcoxon signed-rank test on the non-zero differences ``d``, ties given their
    mid-ranks: under the null hypothesis each difference's sign is + or - with probability 1/2, so the
    statistic T+ (the sum of the positive differences' ranks) takes each of the 2^n sign patterns' values with
    probability 2^-n. p is the probability of a T+ at least as far from its mean as the one observed. The
    distribution is built by convolution over the doubled ranks (mid-ranks are multiples of 1/2), so it is
    exact in integers and takes n^3 steps, not 2^n."""
    d = np.asarray(d, dtype=float)
    if d.size == 0 or np.any(d == 0):
        raise ValueError(f"signed_rank_exact_p needs non-zero differences, got {d.tolist()}")
    doubled = np.rint(2 * stats.rankdata(np.abs(d))).astype(np.int64)
    total = int(doubled.sum())
    counts = np.zeros(total + 1, dtype=np.float64)  # counts[s]: sign patterns with 2 T+ = s (exact below 2^53)
    counts[0] = 1.0
    for r in doubled:
        shifted = np.zeros_like(counts)
        shifted[r:] = counts[:-r]
        counts = counts + shifted
    observed = int(doubled[d > 0].sum())
    # |2 T+ - total| >= |2 t - total|, in integers: the two tails at once, no double counting at the centre.
    far = np.abs(2 * np.arange(total + 1) - total) >= abs(2 * observed - total)
    return float(counts[far].sum() / counts.sum())


@dataclass
class PairTest:
    a: str
    b: str
    n: int  # pairs in the test: complete participants whose scores differ (zero differences dropped)
    statistic: float  # the smaller of the signed-rank sums
    p: float
    zeros: int = 0  # complete participants who gave both conditions the same score (dropped)
    method: str = "exact"  # "exact" (every sign pattern counted) or "normal" (the tie-corrected approximation)
    p_holm: float = 1.0
    r: float = 0.0  # rank-biserial, > 0: a rated higher
    r_ci: tuple[float, float] | None = None  # its 95 % bootstrap interval


@dataclass
class ScaleResult:
    scale: Scale
    scores: dict[str, dict[str, float]]  # condition -> participant -> score
    alpha: dict[str, float | None]  # condition -> Cronbach's alpha
    n: int = 0  # complete participants in the tests
    chi2: float | None = None
    p: float | None = None
    p_method: str = ""  # "exact" (every ordering counted, k!^n <= 2^20) or "chi2" (the asymptotic distribution)
    kendall_w: float | None = None
    pairs: list[PairTest] = field(default_factory=list)
    note: str = ""


@dataclass
class Analysis:
    questionnaire: Questionnaire
    conditions: list[str]
    participants: list[str]
    complete: list[str]
    excluded: dict[str, str]  # participant -> why not in the within-subject tests
    scales: list[ScaleResult]
    votes: dict[str, Counter[str]]  # choice id -> option -> votes
    no_final: list[str]
    open_answers: dict[str, list[tuple[str, str]]]  # question id -> (participant, text)


def _order(conditions: set[str], q: Questionnaire) -> list[str]:
    known = list(q.labels)
    return sorted(conditions, key=lambda c: (known.index(c) if c in known else len(known), c))


def analyze(ratings: list[Rating], finals: list[FinalAnswer], q: Questionnaire) -> Analysis:
    """The analysis of a store's answers (pure: no files)."""
    values: dict[tuple[str, str], dict[str, int]] = defaultdict(dict)  # (participant, condition) -> item -> value
    for r in ratings:
        values[(r.participant, r.condition)][r.item] = r.value
    conditions = _order({c for _, c in values}, q)
    final_by: dict[str, list[FinalAnswer]] = defaultdict(list)
    for a in finals:
        final_by[a.participant].append(a)
    participants = sorted({p for p, _ in values} | set(final_by))
    excluded: dict[str, str] = {}
    for p in participants:
        missing = [c for c in conditions if (p, c) not in values]
        if len(missing) == len(conditions):
            excluded[p] = "no per-condition form (final form only)"
        elif missing:
            excluded[p] = f"no answers for {', '.join(missing)} (a skipped block?)"
    complete = [p for p in participants if p not in excluded]

    results = []
    for scale in q.scales():
        flip = scale.reversed
        scores: dict[str, dict[str, float]] = {c: {} for c in conditions}
        alpha: dict[str, float | None] = {}
        for c in conditions:
            rows = [[q.points + 1 - v[i] if i in flip else v[i] for i in scale.items]
                    for (p, cond), v in sorted(values.items()) if cond == c]
            who = [p for (p, cond) in sorted(values) if cond == c]
            matrix = np.array(rows, dtype=float).reshape(len(rows), len(scale.items))
            scores[c] = dict(zip(who, matrix.mean(axis=1).tolist()))
            alpha[c] = cronbach_alpha(matrix)
        result = ScaleResult(scale, scores, alpha, n=len(complete))
        _test(result, conditions, complete)
        results.append(result)

    votes: dict[str, Counter[str]] = {c.id: Counter() for c in q.choice}
    open_answers: dict[str, list[tuple[str, str]]] = {o.id: [] for o in q.open}
    for p, answers in sorted(final_by.items()):
        for a in answers:
            if a.kind == "choice" and a.item in votes:
                votes[a.item][a.text] += 1
            elif a.kind == "open" and a.text and a.item in open_answers:
                open_answers[a.item].append((p, a.text))
    no_final = [p for p in participants if p not in final_by]
    return Analysis(q, conditions, participants, complete, excluded, results, votes, no_final, open_answers)


def _test(result: ScaleResult, conditions: list[str], complete: list[str]) -> None:
    k, n = len(conditions), len(complete)
    if k < 2:
        result.note = "one condition: nothing to compare"
        return
    if n < 3:
        result.note = f"{n} participant(s) answered every condition: too few for the tests (3 or more)"
        return
    raw = np.array([[result.scores[c][p] for c in conditions] for p in complete])  # participants x conditions
    data = np.round(raw, 9)  # equal means of integer ratings tie exactly in the Friedman ranks
    if k >= 3:
        if np.all(data == data[:, :1]):  # every participant rated every condition alike: no ranks differ
            result.chi2, result.p, result.kendall_w, result.p_method = 0.0, 1.0, 0.0, "exact"
        else:
            chi2, p = stats.friedmanchisquare(*data.T)
            result.chi2, result.p, result.p_method = float(chi2), float(p), "chi2"
            if math.factorial(k) ** n <= FRIEDMAN_EXACT_MAX:
                result.p, result.p_method = friedman_exact_p(data), "exact"
            result.kendall_w = float(chi2) / (n * (k - 1))
        if result.p >= ALPHA:
            return
    pairs = []
    for i in range(k):
        for j in range(i + 1, k):
            a, b = raw[:, i], raw[:, j]  # rounded after the subtraction (two roundings could break a tie)
            d = _differences(a, b)
            nonzero = d[d != 0]
            zeros = int(d.size - nonzero.size)
            if nonzero.size == 0:
                pairs.append(PairTest(conditions[i], conditions[j], 0, 0.0, 1.0, zeros=zeros))
                continue
            ranks = stats.rankdata(np.abs(nonzero))
            statistic = float(min(ranks[nonzero > 0].sum(), ranks[nonzero < 0].sum()))
            if nonzero.size <= EXACT_MAX_N:
                p, method = signed_rank_exact_p(nonzero), "exact"
            else:  # beyond 2^20 sign patterns: the normal approximation with the tie correction
                p, method = float(stats.wilcoxon(nonzero, method="approx").pvalue), "normal"
            pairs.append(PairTest(conditions[i], conditions[j], int(nonzero.size), statistic, p, zeros=zeros,
                                  method=method, r=rank_biserial(a, b), r_ci=rank_biserial_ci(a, b)))
    for pair, adjusted in zip(pairs, holm([pt.p for pt in pairs])):
        pair.p_holm = adjusted
    result.pairs = pairs
    if k == 2:
        result.note = "two conditions: the Wilcoxon signed-rank test alone (no Friedman test)"


# -- what the recordings measured ------------------------------------------------------


@dataclass
class BlockMeasures:
    """One block's recording summarized (``analysis.summarize``): its touches, or why it could not be read."""

    participant: str
    block: int
    condition: str
    recording: str  # relative to the store's folder
    touches: list[Any] = field(default_factory=list)  # TouchSummary, every touch of the block
    problem: str = ""  # "": read; else "missing" or "unreadable (why)"
    health: Any = None  # analysis.BridgeHealth: commands the bridge rejected, arm stops (None: not read)

    @property
    def degraded(self) -> bool:
        """Whether the bridge rejected commands or stopped the arm during the block (its reflexes and task
        were not what the participant would otherwise have met)."""
        return self.health is not None and self.health.degraded

    @property
    def reflexes(self) -> list[Any]:
        return [t for t in self.touches if t.reflex_seq]


@dataclass
class ConditionMeasures:
    condition: str
    blocks: int = 0
    reflexes_per_block: list[int] = field(default_factory=list)
    onset_ms: list[float] = field(default_factory=list)
    withdrawal_mm: list[float] = field(default_factory=list)
    peak_m_s: list[float] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)  # "P03 block 2: ... is missing"
    degraded: list[str] = field(default_factory=list)  # "P03 block 2: 12 commands rejected, 1 x stale_skin"


def measure_blocks(blocks: list[tuple[str, int, str, str]], root: Path, desc: Any) -> list[BlockMeasures]:
    """Each block (participant, block, condition, recording relative to ``root``) with its recording
    summarized; a recording that is missing or unreadable is noted in its ``problem``, not fatal. ``desc``: a
    RobotDescription, or a callable returning one (loaded only when a recording is there). The peak speed is
    the whole withdrawal's (``analysis.summarize``: a touch's own restarts go on with its withdrawal)."""
    from nwr.common import keys, recordings
    from nwr.common.robot import RobotModel
    from nwr.services.tools.recordings import analysis

    out = []
    model = None
    for participant, block, condition, recording in blocks:
        bm = BlockMeasures(participant, block, condition, recording)
        out.append(bm)
        path = root / recording
        if not path.exists():
            bm.problem = "missing"
            continue
        try:
            records, _ = recordings.read_recording(path, only=analysis.summarized)
            if callable(desc):
                desc = desc()
            model = model or RobotModel(desc)
            bm.touches = analysis.summarize(records, desc, model)
            bm.health = analysis.bridge_health([r.message for r in records if r.key == keys.ROBOT_STATE])
        except (NwrError, OSError) as exc:
            bm.problem = f"unreadable ({exc})"
    return out


def condition_measures(blocks: list[BlockMeasures]) -> dict[str, ConditionMeasures]:
    """Per condition, its blocks' reflexes pooled (medians over them in the report)."""
    out: dict[str, ConditionMeasures] = {}
    for bm in blocks:
        cm = out.setdefault(bm.condition, ConditionMeasures(bm.condition))
        if bm.problem:
            cm.problems.append(f"{bm.participant} block {bm.block}: {bm.recording} is {bm.problem}")
            continue
        cm.blocks += 1
        if bm.degraded:
            cm.degraded.append(f"{bm.participant} block {bm.block}: {bm.health.describe()}")
        reflexes = bm.reflexes
        cm.reflexes_per_block.append(len(reflexes))
        cm.onset_ms += [t.onset_latency_ms for t in reflexes if t.onset_latency_ms is not None]
        cm.withdrawal_mm += [t.withdrawal_mm for t in reflexes if t.withdrawal_mm is not None]
        cm.peak_m_s += [t.peak_speed_m_s for t in reflexes if t.peak_speed_m_s is not None]
    return out


def rated_blocks(ratings: list[Rating]) -> list[tuple[str, int, str, str]]:
    """The blocks that have answers: (participant, block, condition, recording), sorted."""
    return sorted({(r.participant, r.block, r.condition, r.recording) for r in ratings})


def measure_recordings(ratings: list[Rating], root: Path, desc: Any) -> dict[str, ConditionMeasures]:
    """Per condition, each rated block's recording (relative to ``root``) summarized (:func:`measure_blocks`)."""
    return condition_measures(measure_blocks(rated_blocks(ratings), root, desc))


# -- figures ---------------------------------------------------------------------------


def _boxplots(result: Analysis, kind: str, path: Path, title: str) -> Path | None:
    fig = _boxplot_figure(result, kind, title)
    if fig is None:
        return None
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=150)
    plt.close(fig)
    return path


def _boxplot_figure(result: Analysis, kind: str, title: str) -> Any:
    """The boxplots of one kind of subscale, each participant's score a dot over its condition's box (jittered
    sideways, the same seed every run: at a few participants the box alone hides how few answers it has)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scales = [s for s in result.scales if s.scale.kind == kind]
    if not scales:
        return None
    labels = [result.questionnaire.label(c) for c in result.conditions]
    cols = 2 if len(scales) == 4 else len(scales)
    rows = -(-len(scales) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.6 * rows), squeeze=False)
    rng = np.random.default_rng(0)
    for ax, s in zip(axes.flat, scales):
        data = [list(s.scores[c].values()) for c in result.conditions]
        ax.boxplot(data, tick_labels=labels, showmeans=True, widths=0.5, showfliers=False,
                   medianprops={"color": "red", "linewidth": 2},
                   meanprops={"marker": "o", "markerfacecolor": "red", "markeredgecolor": "red", "markersize": 5},
                   boxprops={"color": "0.2"}, whiskerprops={"color": "0.2"}, capprops={"color": "0.2"})
        for position, values in enumerate(data, start=1):
            x = position + rng.uniform(-0.15, 0.15, len(values))
            ax.scatter(x, values, s=22, color="tab:blue", alpha=0.7, edgecolors="none", zorder=3)
        ax.set_title(s.scale.name, fontsize=11)
        ax.set_ylim(0.8, 5.2)
        ax.set_yticks(range(1, 6))
        ax.grid(axis="y", alpha=0.3)
        top = 5.25
        # Narrow brackets first: a wider one goes above them, its stars (in its middle) clear of their legs.
        spans = sorted(((result.conditions.index(pair.a) + 1, result.conditions.index(pair.b) + 1, stars(pair.p_holm))
                        for pair in s.pairs if stars(pair.p_holm)), key=lambda x: (x[1] - x[0], x[0]))
        for i, j, mark in spans:
            ax.plot([i, i, j, j], [top, top + 0.08, top + 0.08, top], color="black", linewidth=1)
            ax.text((i + j) / 2, top + 0.06, mark, ha="center", va="bottom", fontsize=11)
            top += 0.35
        ax.set_ylim(0.8, max(5.2, top + 0.1))
        ax.set_xlabel(_friedman_text(s), fontsize=8, color="0.35")
    for ax in list(axes.flat)[len(scales):]:
        ax.set_visible(False)
    fig.suptitle(title, fontsize=12)
    fig.text(0.5, 0.005, "blue dots: each participant's score; red dot: mean, red line: median\n* p < 0.05, "
             "** p < 0.01, *** p < 0.001 (Wilcoxon signed-rank, Holm-corrected)", ha="center", va="bottom",
             fontsize=7, color="0.35")
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    return fig


def _friedman_text(s: ScaleResult) -> str:
    if s.p is None:
        return s.note.split(":")[0] if s.note else ""
    return f"Friedman p = {s.p:.3g}, Kendall's W = {s.kendall_w:.2f}, N = {s.n}"


def _radar(result: Analysis, path: Path) -> Path | None:
    fig = _radar_figure(result)
    if fig is None:
        return None
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=150, bbox_inches="tight")
    plt.close(fig)
    return path


def _radar_figure(result: Analysis) -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    q = result.questionnaire
    if not q.choice or not any(result.votes.values()):
        return None
    options = [*result.conditions, NO_PREFERENCE]
    names = [q.label(c) for c in result.conditions] + [q.no_preference]
    angles = np.linspace(0, 2 * np.pi, len(q.choice), endpoint=False)
    top = max(max(v.values(), default=0) for v in result.votes.values())
    from matplotlib.projections.polar import PolarAxes

    fig, axes = plt.subplots(figsize=(6.4, 6.4), subplot_kw={"projection": "polar"})
    ax = cast(PolarAxes, axes)
    ax.set_theta_offset(np.pi / 2)  # the first question at the top, the others clockwise
    ax.set_theta_direction(-1)
    colors = plt.get_cmap("tab10")
    palette = ["0.45" if o == NO_PREFERENCE else colors(n) for n, o in enumerate(options)]
    closed = np.append(angles, angles[0])
    for option, name, color in zip(options, names, palette):
        counts = np.array([result.votes[c.id][option] for c in q.choice], dtype=float)
        ax.plot(closed, np.append(counts, counts[0]), color=color, linewidth=2, marker="o", markersize=4,
                linestyle="--" if option == NO_PREFERENCE else "-", label=name)
        ax.fill(closed, np.append(counts, counts[0]), color=color, alpha=0.08)
    ax.set_xticks(angles)
    ax.set_xticklabels([])
    # The counts beside each question's name: points of equal count would hide each other's numbers. Each
    # name and its counts a block just outside the outer ring, growing away from it (left of a question on the
    # left, above one at the top): centred on the ring, a long name ran across it.
    short = [*(q.label(c) for c in result.conditions), "none"]
    for angle, choice in zip(angles, q.choice):
        x, y = np.sin(angle), np.cos(angle)  # on the page: the first question at the top, then clockwise
        ha = "left" if x > 0.1 else "right" if x < -0.1 else "center"
        dx, dy = 6 * np.sign(x) * (abs(x) > 0.1), 26 * np.sign(y) * (abs(y) > 0.1)
        tally = "  ".join(f"{n} {result.votes[choice.id][o]}" for n, o in zip(short, options))
        ax.annotate(choice.short, (angle, top + 1), xytext=(dx, dy + 1), textcoords="offset points", ha=ha,
                    va="bottom", fontsize=11, fontweight="bold", annotation_clip=False)
        ax.annotate(tally, (angle, top + 1), xytext=(dx, dy - 1), textcoords="offset points", ha=ha, va="top",
                    fontsize=9, color="0.3", annotation_clip=False)
    ax.set_ylim(0, top + 1)
    ax.set_yticks(range(0, top + 2, max(1, (top + 1) // 4)))
    ax.tick_params(axis="y", labelsize=7, labelcolor="0.5")
    ax.set_title(f"Forced choice: votes of {sum(result.votes[q.choice[0].id].values())} participants", fontsize=12,
                 pad=64)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=len(options), fontsize=9, frameon=False)
    return fig


def figures(result: Analysis, out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    made = [_boxplots(result, "godspeed", out / "godspeed.png", "Godspeed scores per condition"),
            _boxplots(result, "custom", out / "custom.png", "Custom scales per condition"),
            _radar(result, out / "votes.png")]
    return [p for p in made if p is not None]


# -- the report ------------------------------------------------------------------------


def _f(x: float | None, fmt: str = ".2f") -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, fmt)


def _p(p: float | None) -> str:
    """p to 3 significant digits, more where rounding would cross a star's threshold (0.0498 stays below 0.05:
    "0.0498", and 0.049996 is "0.049996", never "0.0500" beside a star)."""
    if p is None or not np.isfinite(p):
        return "-"
    for digits in range(3, 10):
        text = f"{p:.{digits}g}"
        if stars(float(text)) == stars(p):
            return text
    return repr(p)


def _ci(ci: tuple[float, float] | None) -> str:
    return "-" if ci is None else f"{ci[0]:.2f} to {ci[1]:.2f}"


_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f\u0085\u2028\u2029]")


def literal(text: str, limit: int = MAX_ANSWER_CHARS) -> list[str]:
    """A participant's free text as Markdown lines that show it and nothing else: a fenced code block (its
    fence longer than any run of backticks in the text, so no line of it can close the block), in which no
    heading, image, link or HTML is possible; line breaks kept, other control characters dropped, at most
    ``limit`` characters (the rest said, not shown)."""
    text = _CONTROL.sub("", text.replace("\r\n", "\n").replace("\r", "\n").replace("\t", "    "))
    more = len(text) - limit
    if more > 0:
        text = text[:limit]
    fence = "`" * max(3, 1 + max((len(run) for run in re.findall(r"`+", text)), default=0))
    lines = [fence + "text", *text.split("\n"), fence]
    if more > 0:
        lines.append(f"({more} more characters not shown: at most {limit} of an answer)")
    return lines


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|",
            *("| " + " | ".join(r) + " |" for r in rows), ""]


def report(result: Analysis, store: str, pictures: list[Path],
           measures: dict[str, ConditionMeasures] | None = None, tables: list[Path] | None = None) -> str:
    q = result.questionnaire
    lab = q.label
    conds = ", ".join(f"{lab(c)} ({c})" if lab(c) != c else c for c in result.conditions)
    lines = [f"# Study analysis: {store}", "",
             f"Questionnaire `{q.name}`; conditions {conds}; {len(result.participants)} participants, "
             f"{len(result.complete)} with every condition answered.", ""]
    if result.excluded:
        lines += ["**Excluded from the within-subject tests** (kept in the descriptive statistics):", ""]
        lines += [f"- {p}: {why}" for p, why in result.excluded.items()] + [""]
    lines += ["## Method", "",
              "Each subscale's score is the mean of its items per participant and condition, reversed items "
              f"flipped ({q.points + 1} - x). Across conditions, over the participants who answered every "
              "condition: the Friedman test (exact p while there are at most 2^20 orderings of the "
              "participants' ratings, else the chi2 approximation; effect size Kendall's W); where its p < 0.05, "
              "pairwise Wilcoxon signed-rank tests (two-sided, zero differences dropped; with up to "
              f"{EXACT_MAX_N} non-zero differences the exact p of the signed-rank statistic, every sign pattern "
              "counted with ties at their mid-ranks, else the normal approximation with the tie correction; the "
              "table says which) with the Holm correction over the "
              "subscale's pairs (p Holm), effect size the matched-pairs rank-biserial correlation r (> 0: the "
              "first condition rated higher). The Friedman p-values are not corrected across subscales. Stars: "
              "*, **, *** for p Holm < 0.05, 0.01, 0.001. Cronbach's alpha per subscale and condition over "
              f"every participant who answered it, marked not interpretable with fewer than {ALPHA_MIN_N} "
              "participants or when negative.", "",
              "## Descriptive statistics", ""]
    rows = []
    for s in result.scales:
        for c in result.conditions:
            v = np.array(list(s.scores[c].values()))
            if v.size == 0:
                rows.append([s.scale.name, lab(c), "0", "-", "-", "-", "-", "-"])
                continue
            q1, med, q3 = np.percentile(v, [25, 50, 75])
            rows.append([s.scale.name, lab(c), str(v.size), f"{v.mean():.2f}",
                         _f(float(v.std(ddof=1)) if v.size > 1 else None), f"{med:.2f}", f"{q1:.2f}-{q3:.2f}",
                         alpha_text(s.alpha[c], int(v.size))])
    lines += _table(["subscale", "condition", "n", "mean", "SD", "median", "IQR", "Cronbach's alpha"], rows)
    lines += ["## Friedman tests", ""]
    k = len(result.conditions)
    lines += ["p method: exact (every ordering of each participant's ratings across the conditions counted, "
              "while k!^N <= 2^20: N <= 7 for 3 conditions) or chi2 (the asymptotic distribution).", ""]
    lines += _table(["subscale", "N", f"chi2 (df = {k - 1})", "p", "p method", "Kendall's W", "note"],
                    [[s.scale.name, str(s.n), _f(s.chi2), _p(s.p) + (" " + stars(s.p) if stars(s.p) else ""),
                      s.p_method or "-", _f(s.kendall_w), s.note] for s in result.scales])
    post = [[s.scale.name, f"{lab(pt.a)} vs {lab(pt.b)}", str(pt.n), str(pt.zeros), _f(pt.statistic, ".1f"),
             _p(pt.p), pt.method, _p(pt.p_holm), _f(pt.r), _ci(pt.r_ci), stars(pt.p_holm)]
            for s in result.scales for pt in s.pairs]
    lines += ["## Pairwise Wilcoxon signed-rank tests", ""]
    if post:
        lines += ["N: the pairs tested (participants whose two scores differ); zeros: participants who gave both "
                  "conditions the same score, dropped from the test. p method: exact (every sign pattern of the "
                  f"N differences counted, ties at their mid-ranks; N <= {EXACT_MAX_N}) or normal (the "
                  f"tie-corrected normal approximation, N > {EXACT_MAX_N}). r 95 % CI: percentile bootstrap over the "
                  f"participants ({BOOTSTRAP_RESAMPLES} resamples, seed 0); with few participants it takes few "
                  "distinct values and says little.", ""]
        lines += _table(["subscale", "pair", "N", "zeros", "T (smaller rank sum)", "p", "p method", "p Holm",
                         "r (rank-biserial)", "r 95 % CI", ""], post)
    else:
        lines += ["None: no Friedman test had p < 0.05.", ""]
    lines += ["## Forced choice", ""]
    if q.choice:
        options = [*result.conditions, NO_PREFERENCE]
        lines += _table(["question", *(lab(c) for c in result.conditions), q.no_preference],
                        [[c.text, *(str(result.votes[c.id][o]) for o in options)] for c in q.choice])
        if result.no_final:
            lines += [f"No final form from: {', '.join(result.no_final)}.", ""]
    if measures is not None:
        lines += ["## What the recordings measured", "",
                  "Per condition, every rated block's recording (`nwr summary`'s figures); medians over the "
                  "condition's reflexes.", ""]
        rows = []
        for c in result.conditions:
            cm = measures.get(c)
            if cm is None:
                continue
            rows.append([lab(c), str(cm.blocks), _f(float(np.median(cm.reflexes_per_block)) if cm.blocks else None,
                                                   ".1f"),
                         _f(float(np.median(cm.onset_ms)) if cm.onset_ms else None),
                         _f(float(np.median(cm.withdrawal_mm)) if cm.withdrawal_mm else None, ".1f"),
                         _f(float(np.median(cm.peak_m_s)) if cm.peak_m_s else None, ".3f")])
        lines += _table(["condition", "blocks read", "reflexes per block", "onset (ms)", "withdrawal (mm)",
                         "peak speed (m/s)"], rows)
        problems = [p for cm in measures.values() for p in cm.problems]
        if problems:
            lines += ["Recordings not read:", "", *(f"- {p}" for p in problems), ""]
        degraded = [d for cm in measures.values() for d in cm.degraded]
        if degraded:
            lines += ["**Degraded blocks**: the bridge rejected commands or stopped the arm, so the participant "
                      "did not meet the condition as designed (column `degraded` of the study table; "
                      "`nwr study analyze --exclude-degraded` leaves their answers out of the tests):", "",
                      *(f"- {d}" for d in degraded), ""]
        elif measures:
            lines += ["No block was degraded: the bridge rejected no command and never stopped the arm.", ""]
    if tables:
        lines += ["## The whole study as one table", "",
                  f"{', '.join(f'`{t.name}`' for t in tables)} beside this report: one row per block, what its "
                  "recording measured beside its answers and the participant's forced choices (no free text); "
                  "every column in docs/study.md.", ""]
    if any(result.open_answers.values()):
        lines += ["## Open answers", "",
                  "As the participants wrote them, each in a literal block (never read as Markdown or HTML), at "
                  f"most {MAX_ANSWER_CHARS} characters each.", ""]
        for o in q.open:
            answers = result.open_answers.get(o.id, [])
            if answers:
                lines += [f"**{o.text}**", ""]
                for p, text in answers:
                    lines += [f"{p}:", "", *literal(text), ""]
    if pictures:
        lines += ["## Figures", "", *(f"![{p.stem}]({p.name})" for p in pictures), ""]
    return "\n".join(lines)


def run(store_path: Path, out: Path, desc: Any = None, *, exclude_degraded: bool = False
        ) -> tuple[Analysis, Path, list[Path], list[Path]]:
    """Analyse the store at ``store_path`` into ``out``: report.md, the figures and the whole study as one
    table (``study.csv``, ``study.parquet``: :mod:`nwr.services.tools.study.table`); the analysis and the
    report's, the figures' and the tables' paths. ``desc``: the robot description for the recordings (a
    callable is called when the first recording is read); None: the recordings are not read.
    ``exclude_degraded``: the answers of degraded blocks (:attr:`BlockMeasures.degraded`) left out of the
    statistics (a participant without every condition is then out of the within-subject tests)."""
    with Store(store_path, create=False) as store:
        ratings, finals, q, planned = store.ratings(), store.final_answers(), store.questionnaire, store.blocks()
    if not ratings:
        log.warning("%s holds no per-condition answers yet", store_path)
    rated = rated_blocks(ratings)
    everyone = sorted({(b.participant, b.block, b.condition, b.recording) for b in planned} | set(rated))
    measured = measure_blocks(everyone, store_path.parent, desc) if desc is not None else None
    tested = ratings
    if exclude_degraded and measured is not None:
        degraded = {(bm.participant, bm.block) for bm in measured if bm.degraded}
        tested = [r for r in ratings if (r.participant, r.block) not in degraded]
        if degraded:
            log.warning("%d degraded blocks left out of the tests: %s", len(degraded),
                        ", ".join(f"{p} block {b}" for p, b in sorted(degraded)))
    result = analyze(tested, finals, q)
    pictures = figures(result, out)
    measures = None if measured is None else condition_measures(
        [bm for bm in measured if (bm.participant, bm.block, bm.condition, bm.recording) in set(rated)])
    rows = table.block_table(q, planned, ratings, finals,
                             None if measured is None else {(bm.participant, bm.block): bm for bm in measured})
    tables = [table.write_csv(q, rows, out / table.CSV_NAME), table.write_parquet(q, rows, out / table.PARQUET_NAME)]
    path = out / "report.md"
    path.write_text(report(result, str(store_path), pictures, measures, tables), encoding="utf-8")
    return result, path, pictures, tables
