"""Figures from the code paths the services use: ``nwr figure gain|reflexes``.

- ``gain``: the discrete and continuous gain models over 0-25 hPa with the
  pain-level thresholds (the paper's Fig. 1, top right), computed with the
  gain estimator's own functions.
- ``reflexes``: the arm in its home pose and the end pose of each reflex for
  G(p) = 1 at touch points on three regions, one column per reflex (the
  paper's Fig. 5), each computed by running the planner core on a pain
  message (within the profile's Cartesian limits, as a session plans it),
  with the touch points and pad normals drawn. End poses that coincide (the
  uniform reflex's, whatever was touched) are drawn striped in their touches'
  colours and said to coincide. Below, per reflex, the touched pad's motion
  along its outward normal at the onset and its speed over time (withdrawal
  up, toward the contact down), where reflexes that end alike differ: the
  smoothed Cartesian reflex ramps its speed in and out, the plain one steps
  (drawn dashed under it). These are the strategies' motions as planned; a
  session's planner also runs its retreat check on them.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from nwr.common import messages as m
from nwr.common.config import CartesianLimits, PlannerSection
from nwr.common.robot import RobotDescription, RobotModel, load_description
from nwr.services.gain.core import continuous_gain, discrete_gain
from nwr.services.planner.core import Planner
from nwr.services.planner.strategies import names as strategy_names
from nwr.services.profile import profile_for
from nwr.services.tools.recordings.analysis import contact_motion

CONTINUOUS_COLOR = "#d62728"
DISCRETE_COLOR = "#1f77b4"
TOUCH_COLORS = ("#2ca02c", "#9467bd", "#e377c2")  # the robot's figure_pads: upper arm green, forearm purple, wrist
# pink (as the paper)


def _pyplot() -> Any:
    """matplotlib's pyplot on the file-only backend, imported when a figure is drawn.

    Not at import: every ``nwr`` command (every service process) imports this
    module to register its subcommand, and matplotlib costs ~0.5 s and tens
    of MB there.
    """
    import matplotlib

    matplotlib.use("Agg")  # files only: no display is needed or wanted
    import matplotlib.pyplot as plt

    return plt


TITLES = {"uniform": "Uniform (UR)", "location": "Location-dependent (LR)", "cartesian": "Cartesian (CR)",
          "cartesian-smooth": "Cartesian, smoothed", "whole-arm": "Whole-arm (QP)"}


def gain_figure(path: Path, thresholds: tuple[float, ...] = (2.0, 6.0, 12.0, 20.0), k: float = 3.0) -> Path:
    p = np.linspace(0.0, 25.0, 2501)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=150)
    ax.plot(p, [discrete_gain(x, thresholds) for x in p], color=DISCRETE_COLOR, lw=2, label="discrete $G_d(p)$")
    ax.plot(p, [continuous_gain(x, thresholds, k) for x in p], color=CONTINUOUS_COLOR, lw=2,
            label=f"continuous $G(p)$, k = {k:g}")
    for t in thresholds:
        ax.axvline(t, color="0.5", ls="--", lw=0.8)
    edges = (0.0, *thresholds[:3], 25.0)
    for level, (a, b) in enumerate(zip(edges, edges[1:]), start=1):
        ax.text((a + b) / 2, 1.04, f"PL {level}", ha="center", va="bottom", fontsize=9)
    ax.set_xlim(0, 25)
    ax.set_ylim(-0.03, 1.12)
    ax.set_xlabel("pressure change p (hPa)")
    ax.set_ylabel("pain gain G(p)")
    ax.legend(loc="center right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def reflex_motion(strategy: str, desc: RobotDescription, model: RobotModel, pad: str,
                  cfg: PlannerSection | None = None, limits: CartesianLimits | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A G = 1 reflex on ``pad`` from home, by the planner core itself: times (s from the onset) and the
    commanded poses, one row per control cycle from the onset pose (first) to the end pose (last).

    ``limits``: the bridge's Cartesian limits, which the planner of a session
    plans its joint-space reflexes within (None: the joint limits only).
    """
    base = cfg or PlannerSection()
    planner = Planner(msgspec.structs.replace(base, strategy=strategy), desc, model, limits=limits)
    planner.on_state(desc.home.copy(), following=True)
    while planner.mode != "TASK":
        planner.step(0)
    poses = [planner.q.copy()]
    info = desc.pad(pad)
    gains = [0.0] * len(desc.pads)
    gains[info.id] = 1.0
    contact = m.Contact(pad=info.id, name=info.name, region=info.region, change_hpa=25.0, level=4, gain=1.0)
    planner.on_pain(m.SkinPain(seq=1, stamp_ns=0, trace=m.Trace(1, 0), model="continuous",
                               level=[1] * len(gains), gain=gains, strongest=contact), 0)
    poses.append(planner.q.copy())  # the reflex's first cycle runs on the pain message itself
    while planner.mode == "REFLEX":
        if planner.step(0) is not None:  # None: the cycle the first one took the place of
            poses.append(planner.q.copy())
    return planner.dt * np.arange(len(poses)), np.array(poses)


def reflex_end_pose(strategy: str, desc: RobotDescription, model: RobotModel, pad: str,
                    cfg: PlannerSection | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Start and end pose of a G = 1 reflex on ``pad`` from home, by the planner core itself."""
    _, poses = reflex_motion(strategy, desc, model, pad, cfg)
    return poses[0], poses[-1]


def coinciding(poses: list[np.ndarray], tol_rad: float = 1e-4) -> list[list[int]]:
    """Groups of indices of ``poses`` that are the same pose (within ``tol_rad`` on every joint), in order."""
    groups: list[list[int]] = []
    for i, q in enumerate(poses):
        group = next((g for g in groups if np.abs(poses[g[0]] - q).max() <= tol_rad), None)
        if group is None:
            groups.append([i])
        else:
            group.append(i)
    return groups


def _draw_arm(ax: Any, model: RobotModel, q: np.ndarray, color: str, lw: float, alpha: float = 1.0,
              ls: Any = "-") -> None:
    pts = np.vstack([[0.0, 0.0, 0.0], model.joint_positions(q)])
    ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], ls=ls, marker="o", color=color, lw=lw, ms=3, alpha=alpha)


# A panel's reflex drawn faintly under another's time series: what the smoothing changed.
REFERENCE = {"cartesian-smooth": "cartesian"}
STRIPE = 4.0  # points: the dash of each of several end poses drawn on one another


@dataclass
class ReflexRun:
    """One reflex of the figure: the touched pad's motion along its normal at the onset, over time."""

    t: np.ndarray  # s from the onset
    poses: np.ndarray  # rad, one row per control cycle
    away_mm: np.ndarray  # + away from the contact, - toward it (analysis.contact_motion)
    speed_m_s: np.ndarray  # its rate: + withdrawing


def reflex_runs(strategies: tuple[str, ...], desc: RobotDescription, model: RobotModel,
                cfg: PlannerSection | None = None, limits: CartesianLimits | None = None
                ) -> dict[tuple[str, str], ReflexRun]:
    """Every strategy's reflex on each of the robot's figure pads (robot.toml figure_pads), keyed (strategy, pad)."""
    runs = {}
    for strategy in strategies:
        for pad in desc.figure_pads:
            t, poses = reflex_motion(strategy, desc, model, pad, cfg, limits)
            away, _, _ = contact_motion(model, poses, desc.pad(pad).id, poses[0])
            runs[(strategy, pad)] = ReflexRun(t, poses, 1e3 * away, np.gradient(away, t))
    return runs


SPREAD = 8.0  # curves whose extents differ more than this share a symmetric log scale


def fit_scale(axes: list[Any], unit: str) -> None:
    """One y scale for ``axes`` (which share it) on which every curve shows: linear, unless one curve spans more
    than SPREAD times another (a uniform reflex's 900 mm beside a Cartesian 20 mm), then linear up to the smallest
    curve's extent and logarithmic beyond it (symlog), which each panel says."""
    extents = [float(np.nanmax(np.abs(line.get_ydata()))) for ax in axes for line in ax.get_lines()
               if len(line.get_ydata()) > 1 and np.isfinite(line.get_ydata()).any()]
    extents = [e for e in extents if e > 0.001 * max(extents, default=0.0)]  # flat on any scale: not counted
    if len(extents) < 2 or max(extents) <= SPREAD * min(extents):
        return
    linear = min(extents)
    for ax in axes:
        ax.set_yscale("symlog", linthresh=linear, linscale=1.5)
        ax.text(0.99, 0.03, f"log scale beyond \u00b1{linear:.2g} {unit}", transform=ax.transAxes, ha="right",
                va="bottom", fontsize=7, color="0.35")


def draw_reflexes(strategies: tuple[str, ...] = strategy_names(), cfg: PlannerSection | None = None,
                  limits: CartesianLimits | None = None) -> Any:
    """The reflexes figure (a matplotlib Figure): per strategy, the end poses in 3-D, then the touched pad's
    withdrawal along its normal and its speed over time."""
    desc = load_description()
    model = RobotModel(desc)
    touches = desc.figure_pads
    runs = reflex_runs(strategies, desc, model, cfg, limits)
    plt = _pyplot()
    fig = plt.figure(figsize=(4.0 * len(strategies), 9.4), dpi=130, layout="constrained")
    grid = fig.add_gridspec(3, len(strategies), height_ratios=(2.3, 1, 1))
    rows: tuple[list[Any], list[Any]] = ([], [])  # the withdrawal and the speed panels, left to right
    for i, strategy in enumerate(strategies):
        ax = fig.add_subplot(grid[0, i], projection="3d")
        start = runs[(strategy, touches[0])].poses[0]
        ends = [runs[(strategy, pad)].poses[-1] for pad in touches]
        for group in coinciding(ends):
            for k, touch in enumerate(group):  # poses drawn on one another: interleaved dashes, every colour shows
                if len(group) == 1:
                    _draw_arm(ax, model, ends[touch], TOUCH_COLORS[touch], 2.0, 0.9)
                else:  # dash patterns scale with the line width: STRIPE / lw of it
                    lw = 3.0
                    ls = (k * STRIPE / lw, (STRIPE / lw, (len(group) - 1) * STRIPE / lw))
                    _draw_arm(ax, model, ends[touch], TOUCH_COLORS[touch], lw, 1.0, ls)
        for pad, color in zip(touches, TOUCH_COLORS):
            point, normal = model.pad_point(start, desc.pad(pad).id), model.pad_normal(start, desc.pad(pad).id)
            ax.scatter(*point, s=60, facecolors="none", edgecolors=color, linewidths=2)
            ax.quiver(*point, *(0.15 * normal), color=color, arrow_length_ratio=0.3)
        _draw_arm(ax, model, start, "0.55", 3.5)
        same = [g for g in coinciding(ends) if len(g) > 1]
        if same:
            which = "all three touches" if len(same[0]) == len(touches) else \
                " and ".join(touches[k] for k in same[0])
            ax.text2D(0.5, 0.97, f"{which}: the same end pose\n(drawn striped in their colours)",
                      transform=ax.transAxes, ha="center", va="top", fontsize=9, fontweight="bold",
                      bbox={"boxstyle": "round", "fc": "#fff8dc", "ec": "0.6"})
        ax.set_title(TITLES.get(strategy, strategy), fontsize=12, fontweight="bold")
        ax.set_xlim(-0.3, 1.0)
        ax.set_ylim(-0.6, 0.7)
        ax.set_zlim(-0.2, 1.1)
        ax.set_box_aspect((1.3, 1.3, 1.3))
        ax.view_init(elev=18, azim=-60)
        ax.set_xlabel("x (m)", fontsize=8)
        ax.set_ylabel("y (m)", fontsize=8)
        ax.set_zlabel("z (m)", fontsize=8)
        ax.tick_params(labelsize=7)

        # One scale per row across the strategies: their withdrawals and speeds compare by eye.
        ax_d = fig.add_subplot(grid[1, i], sharex=rows[0][0] if rows[0] else None,
                               sharey=rows[0][0] if rows[0] else None)
        ax_v = fig.add_subplot(grid[2, i], sharex=ax_d, sharey=rows[1][0] if rows[1] else None)
        rows[0].append(ax_d)
        rows[1].append(ax_v)
        reference = REFERENCE.get(strategy)
        if reference in strategies:
            for pad, color in zip(touches, TOUCH_COLORS):
                run = runs[(reference, pad)]
                ax_d.plot(run.t, run.away_mm, "--", color=color, lw=1.0, alpha=0.7)
                ax_v.plot(run.t, run.speed_m_s, "--", color=color, lw=1.0, alpha=0.7)
        for pad, color in zip(touches, TOUCH_COLORS):
            run = runs[(strategy, pad)]
            ax_d.plot(run.t, run.away_mm, color=color, lw=1.8)
            ax_v.plot(run.t, run.speed_m_s, color=color, lw=1.8)
        for axis in (ax_d, ax_v):
            axis.axhline(0.0, color="0.3", lw=0.8)
            axis.grid(alpha=0.3)
            axis.tick_params(labelsize=7)
        compared = f" (dashed: {TITLES.get(reference, reference)})" if reference in strategies else ""
        ax_d.set_title("touched pad along its normal" + compared, fontsize=9)
        ax_v.set_title("its speed along the normal" + compared, fontsize=9)
        ax_v.set_xlabel("time from the reflex onset (s)", fontsize=8)
        if i == 0:
            ax_d.set_ylabel("withdrawal (mm)\n(shaded: toward the contact)", fontsize=8)
            ax_v.set_ylabel("speed (m/s)\n+ away from the contact", fontsize=8)
    for row, unit in zip(rows, ("mm", "m/s")):  # a shared scale that shows every curve, room toward the contact
        fit_scale(row, unit)
        low, high = row[0].get_ylim()
        row[0].set_ylim(min(low, -0.08 * (high - low)), high)
        for axis in row:
            axis.axhspan(axis.get_ylim()[0], 0.0, color="#d62728", alpha=0.07, lw=0)
    handles = [plt.Line2D([], [], color="0.55", lw=3.5, label="initial pose")]
    handles += [plt.Line2D([], [], color=c, lw=2, label=f"touch on {p}") for p, c in zip(touches, TOUCH_COLORS)]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=9)
    fig.suptitle("Each reflex for G(p) = 1 from the same pose: its end pose (circles: touch points, arrows: pad "
                 "normals) and how the touched pad withdraws", fontsize=11)
    return fig


def reflexes_figure(path: Path, strategies: tuple[str, ...] = strategy_names(),
                    cfg: PlannerSection | None = None, limits: CartesianLimits | None = None) -> Path:
    fig = draw_reflexes(strategies, cfg, limits)
    fig.savefig(path)
    _pyplot().close(fig)
    return path


def _run(args: argparse.Namespace) -> int:
    profile = profile_for(args)
    default = {"gain": "figure-gain.png", "reflexes": "figure-reflexes.png"}[args.which]
    out = Path(args.output or default)
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.which == "gain":
        gain_figure(out, tuple(profile.gain.thresholds_hpa), profile.gain.k)
    else:
        reflexes_figure(out, cfg=profile.planner, limits=profile.bridge.limits)
    print(f"wrote {out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("figure", help="draw the gain curves or the reflexes' end poses as PNG",
                       description="Draw a figure with the services' own code: 'gain' (the gain models over "
                                   "0-25 hPa with the thresholds) or 'reflexes' (end poses of every reflex for "
                                   "G = 1 at touches on three regions).")
    p.add_argument("which", choices=["gain", "reflexes"])
    p.add_argument("--output", "-o", help="PNG file (default: figure-<which>.png)")
    p.set_defaults(handler=_run)
