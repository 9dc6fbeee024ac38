"""Figures from the code paths the services use: ``nwr figure gain|reflexes``.

- ``gain``: the discrete and continuous gain models over 0-25 hPa with the
  pain-level thresholds (the paper's Fig. 1, top right), computed with the
  gain estimator's own functions.
- ``reflexes``: the arm in its home pose and the end pose of each reflex for
  G(p) = 1 at touch points on three regions, one panel per reflex (the
  paper's Fig. 5), each end pose computed by running the planner core on a
  pain message, with the touch points and pad normals drawn.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from nwr.common import messages as m
from nwr.common.config import PlannerSection, profile_for
from nwr.common.robot import RobotDescription, RobotModel, load_description
from nwr.services.gain.core import continuous_gain, discrete_gain
from nwr.services.planner.core import Planner
from nwr.services.planner.strategies import names as strategy_names

CONTINUOUS_COLOR = "#d62728"
DISCRETE_COLOR = "#1f77b4"
TOUCHES = ("upper_arm_top", "forearm_top", "wrist_2")  # one pad on each of three regions
TOUCH_COLORS = ("#2ca02c", "#9467bd", "#e377c2")  # upper arm green, forearm purple, wrist pink (as the paper)


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
          "cartesian-smooth": "Cartesian, smoothed"}


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


def reflex_end_pose(strategy: str, desc: RobotDescription, model: RobotModel, pad: str,
                    cfg: PlannerSection | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Start and end pose of a G = 1 reflex on ``pad`` from home, by the planner core itself."""
    base = cfg or PlannerSection()
    planner = Planner(msgspec.structs.replace(base, strategy=strategy), desc, model)
    planner.on_state(desc.home.copy(), following=True)
    while planner.mode != "TASK":
        planner.step(0)
    start = planner.q.copy()
    info = desc.pad(pad)
    gains = [0.0] * len(desc.pads)
    gains[info.id] = 1.0
    contact = m.Contact(pad=info.id, name=info.name, region=info.region, change_hpa=25.0, level=4, gain=1.0)
    planner.on_pain(m.SkinPain(seq=1, stamp_ns=0, trace=m.Trace(1, 0), model="continuous",
                               level=[1] * len(gains), gain=gains, strongest=contact), 0)
    while planner.mode == "REFLEX":
        planner.step(0)
    return start, planner.q.copy()


def _draw_arm(ax: Any, model: RobotModel, q: np.ndarray, color: str, lw: float, alpha: float = 1.0) -> None:
    pts = np.vstack([[0.0, 0.0, 0.0], model.joint_positions(q)])
    ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], "-o", color=color, lw=lw, ms=3, alpha=alpha)


def reflexes_figure(path: Path, strategies: tuple[str, ...] = strategy_names(),
                    cfg: PlannerSection | None = None) -> Path:
    desc = load_description()
    model = RobotModel(desc)
    plt = _pyplot()
    fig = plt.figure(figsize=(4.0 * len(strategies), 4.6), dpi=130)
    for i, strategy in enumerate(strategies):
        ax = fig.add_subplot(1, len(strategies), i + 1, projection="3d")
        start = None
        for pad, color in zip(TOUCHES, TOUCH_COLORS):
            start, end = reflex_end_pose(strategy, desc, model, pad, cfg)
            _draw_arm(ax, model, end, color, 2.0, 0.9)
            point, normal = model.pad_point(start, desc.pad(pad).id), model.pad_normal(start, desc.pad(pad).id)
            ax.scatter(*point, s=60, facecolors="none", edgecolors=color, linewidths=2)
            ax.quiver(*point, *(0.15 * normal), color=color, arrow_length_ratio=0.3)
        assert start is not None
        _draw_arm(ax, model, start, "0.55", 3.5)
        ax.set_title(TITLES.get(strategy, strategy), fontsize=11)
        ax.set_xlim(-0.3, 1.0)
        ax.set_ylim(-0.6, 0.7)
        ax.set_zlim(-0.2, 1.1)
        ax.set_box_aspect((1.3, 1.3, 1.3))
        ax.view_init(elev=18, azim=-60)
        ax.set_xlabel("x (m)", fontsize=8)
        ax.set_ylabel("y (m)", fontsize=8)
        ax.set_zlabel("z (m)", fontsize=8)
        ax.tick_params(labelsize=7)
    handles = [plt.Line2D([], [], color="0.55", lw=3.5, label="initial pose")]
    handles += [plt.Line2D([], [], color=c, lw=2, label=f"touch on {p}") for p, c in zip(TOUCHES, TOUCH_COLORS)]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=9)
    fig.suptitle("End pose of each reflex for G(p) = 1 (circles: touch points, arrows: pad normals)", fontsize=11)
    fig.tight_layout(rect=(0, 0.07, 1, 0.95))
    fig.savefig(path)
    plt.close(fig)
    return path


def _run(args: argparse.Namespace) -> int:
    profile = profile_for(args)
    default = {"gain": "figure-gain.png", "reflexes": "figure-reflexes.png"}[args.which]
    out = Path(args.output or default)
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.which == "gain":
        gain_figure(out, tuple(profile.gain.thresholds_hpa), profile.gain.k)
    else:
        reflexes_figure(out, cfg=profile.planner)
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
