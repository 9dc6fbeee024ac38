"""Every contact counts, measured: touch scripts x poses x worlds x strategies, one quality table.

    .venv/bin/python scripts/contact_figures.py [--scripts contacts,survey-held-out] [--poses home,reach,limits]
                                                [--worlds open,closed,physics] [--strategies uniform,...]
                                                [--jobs 2] [--keep DIR | --read DIR] [--by world]
                                            [--guarded] [--contacts every|strongest]

For each touch script, pose, world and reflex strategy, one simulated
session in lockstep (``nwr demo --fast --script S --reflex R`` with the task
drawn around the pose, ``planner.task.home_rad``), and one row of the reflex
quality table (:func:`nwr.services.tools.recordings.analysis.quality`, as
``nwr compare`` prints it) per strategy over all of them:

- worlds: ``open`` (the scripted world, the skin not touched by the arm's
  motion), ``closed`` (the scripted world's closed loop: a pad moving into the
  finger presses harder, ``gateway.sim.closed_loop``), ``physics`` (the
  physics world: fingers that push back);
- poses: ``home`` (the robot's), ``reach`` (the elbow almost straight: near
  the elbow singularity, the arm stretched out), ``limits`` (the base a few
  tenths of a radian from its joint limit, the elbow near its own, the
  figure-eight taking them closer);
- any toward: touches with a gain (any touched pad, not only the reflex's)
  whose pad moved more than 5 mm toward where it was touched while the touch
  lasted; worst toward (mm): the largest such move;
- worst other (mm): any other pad's largest approach to a reflex's contact
  point; back past: touches (any the skin felt, with a gain or not) whose pad
  the arm took more than 10 mm back through where it had been touched, within
  3 s of their end;
- rho: Spearman's rank correlation of withdrawal with gain per pad (pads
  touched at three or more pressures; the touches whose reflex withdrew the
  pad along its normal as far as the joints let it, not sideways or blocked:
  `analysis.serves_normal`), the median over pads; rho min: the lowest
  pad's, named.

``--guarded`` runs every session in guarded mode (``planner.guarded``);
``--contacts strongest`` gives each strategy the strongest contact only, the
paper's (``planner.contacts``), for a comparison with every contact.

A session that a world refuses (a script the physics world cannot play) is
reported as such, never dropped silently.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.launch import load_script
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.gateway.core import with_sim
from nwr.services.planner import strategies
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.replay import simulate

SCRIPTS = ("contacts", "survey-held-out")
STRATEGIES = ("uniform", "location", "cartesian", "cartesian-smooth", "whole-arm")
WORLDS = ("open", "closed", "physics")
# The task is drawn around each pose (planner.task.home_rad), UR10e joint order.
POSES = {
    "home": [0.0, -1.15, 1.85, -2.27, -1.57, 0.0],
    "reach": [0.3, -0.9, 0.35, -1.0, -1.57, 0.0],
    "limits": [5.85, -1.5, 2.85, -2.6, -1.57, 0.5],
}


PRESSURES_HPA = 2.0  # touches of one pad whose peaks differ by more than this were pressed at other pressures


@dataclass
class Session:
    """One session's touches (or why it did not run)."""

    script: str
    pose: str
    world: str
    strategy: str
    touches: list[analysis.TouchSummary] = field(default_factory=list)
    refused: str = ""
    wall_s: float = 0.0


def profile_for(world: str, pose: str, guarded: bool = False, contacts: str = "every") -> Profile:
    profile = Profile()
    profile.planner.guarded = guarded
    profile.planner.contacts = "strongest" if contacts == "strongest" else "every"
    profile.planner.task.home_rad = list(POSES[pose])
    profile.bridge.initial_q = list(POSES[pose])  # the arm starts where its task is drawn
    if world == "physics":
        profile.bridge.backend, profile.gateway.source = "physics", "physics"
    elif world == "closed":
        profile.gateway = with_sim(profile.gateway, closed_loop=True)
    return profile


def run(script: str, pose: str, world: str, strategy: str, out: Path, read: bool = False,
        resume: bool = False, guarded: bool = False, contacts: str = "every") -> Session:
    """One session (``read``: its recording in ``out``, made before; ``resume``: that recording if it is
    there)."""
    logging.disable(logging.WARNING)  # the services' own warnings, hundreds per session: the table says what counts
    s = Session(script, pose, world, strategy)
    began = time.monotonic()
    profile = profile_for(world, pose, guarded, contacts)
    path = out / f"{script}-{pose}-{world}-{strategy}.mcap"
    if read and not path.exists():
        s.refused = f"{path} is not there"
        return s
    try:
        if not (read or (resume and path.exists())):
            simulate(profile, script, strategy, path)
    except ConfigError as e:
        s.refused = str(e)
        return s
    records, _ = read_recording(path, only=analysis.summarized)
    desc = load_description(profile.robot.description or None)
    s.touches = analysis.summarize(records, desc, RobotModel(desc))
    s.wall_s = time.monotonic() - began
    return s


def pad_rhos(touches: list[analysis.TouchSummary]) -> dict[str, float]:
    """Spearman's rho of withdrawal with gain, per pad touched at three or more pressures (peaks more than
    PRESSURES_HPA apart: a burst of taps at one pressure, whose gains differ by the sampling alone, is one)."""
    from scipy.stats import spearmanr

    done = [t for t in touches if t.reflex_seq and t.withdrawal_mm is not None and analysis.serves_normal(t)]
    out = {}
    for name in sorted({t.name for t in done}):
        mine = [(t.gain, analysis.withdrawal_share(t)) for t in done if t.name == name]
        peaks = sorted(t.peak_hpa for t in done if t.name == name)
        pressures = 1 + sum(b - a > PRESSURES_HPA for a, b in zip(peaks, peaks[1:]))
        if pressures >= 3 and len({w for _, w in mine}) > 1 and len({g for g, _ in mine}) > 1:
            out[name] = float(spearmanr(*zip(*mine)).statistic)
    return out


HEADER = ["strategy", "sessions", "touches with a gain", "any touched pad toward >5 mm", "worst toward (mm)",
          "worst other pad closer (mm)", "back past a recent touch", "rho p50", "rho min (pad)", "refused"]


def rows(sessions: list[Session], chosen: list[str]) -> list[list[str]]:
    f = analysis.cell
    out = []
    for strategy in chosen:
        mine = [s for s in sessions if s.strategy == strategy]
        ran = [s for s in mine if not s.refused]
        felt = [t for s in ran for t in s.touches if t.gain > 0.0]
        done = [t for s in ran for t in s.touches if t.reflex_seq and t.withdrawal_mm is not None]
        toward = [t.pressed_toward_mm or 0.0 for t in felt]
        rhos = {f"{s.script}/{s.pose}/{s.world}/{pad}": r for s in ran for pad, r in pad_rhos(s.touches).items()}
        low = min(rhos, key=rhos.__getitem__) if rhos else None
        out.append([
            strategy, str(len(ran)), str(len(felt)), str(sum(x > analysis.APPROACH_MM for x in toward)),
            f(max(toward, default=None), ".1f"),
            f(max((t.other_approach_mm or 0.0 for t in done), default=None), ".1f"),
            str(sum((t.past_after_mm or 0.0) > analysis.PAST_MM for t in felt)),
            f(float(np.median(list(rhos.values()))) if rhos else None, ".2f"),
            "-" if low is None else f"{rhos[low]:.2f} ({low})", str(len(mine) - len(ran)),
        ])
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--scripts", default=",".join(SCRIPTS), help="packaged touch scripts, comma-separated")
    parser.add_argument("--poses", default=",".join(POSES), help=f"poses, comma-separated, of {', '.join(POSES)}")
    parser.add_argument("--worlds", default=",".join(WORLDS), help=f"worlds, comma-separated, of {', '.join(WORLDS)}")
    parser.add_argument("--strategies", default=",".join(STRATEGIES), help="reflex strategies, comma-separated")
    parser.add_argument("--jobs", type=int, default=2, help="sessions run at once (processes)")
    parser.add_argument("--keep", type=Path, help="write the recordings here (default: a temporary directory)")
    parser.add_argument("--resume", action="store_true",
                        help="with --keep DIR: read the sessions whose recordings DIR has, run the others")
    parser.add_argument("--read", type=Path, metavar="DIR",
                        help="run nothing: read the recordings a run with --keep DIR wrote")
    parser.add_argument("--by", choices=("strategy", "world", "pose", "script"), action="append", default=[],
                        help="also print one table per value of this (repeatable)")
    parser.add_argument("--guarded", action="store_true", help="every session in guarded mode (planner.guarded)")
    parser.add_argument("--contacts", choices=("every", "strongest"), default="every",
                        help="planner.contacts: every active contact (default) or the strongest only (the paper's)")
    args = parser.parse_args()

    def listed(text: str, known: tuple[str, ...] | dict[str, list[float]] | None = None) -> list[str]:
        names = [x for x in text.split(",") if x]
        for name in names:
            if known is not None and name not in known:
                parser.error(f"{name!r} is none of {', '.join(known)}")
        return names

    scripts, poses, worlds = listed(args.scripts), listed(args.poses, POSES), listed(args.worlds, WORLDS)
    chosen = listed(args.strategies)
    for strategy in chosen:
        strategies.check(strategy)
    for script in scripts:
        load_script(script)  # a bad name fails before any session runs
    began = time.monotonic()
    with tempfile.TemporaryDirectory() as scratch:
        out = args.read or args.keep or Path(scratch)
        out.mkdir(parents=True, exist_ok=True)
        plan = [(sc, p, w, st) for sc in scripts for p in poses for w in worlds for st in chosen]
        with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            sessions = list(pool.map(run, *zip(*plan), [out] * len(plan), [args.read is not None] * len(plan),
                                     [args.resume] * len(plan), [args.guarded] * len(plan),
                                     [args.contacts] * len(plan)))
    for s in sessions:
        if s.refused:
            print(f"refused: {s.script} at {s.pose} in the {s.world} world with {s.strategy}: {s.refused}")
    print(analysis.format_table(HEADER, rows(sessions, chosen)))
    for by in args.by:
        for value in dict.fromkeys(getattr(s, by) for s in sessions):
            print(f"\n{by} = {value}")
            print(analysis.format_table(HEADER, rows([s for s in sessions if getattr(s, by) == value], chosen)))
    print(f"\n{len(sessions)} sessions in lockstep in {time.monotonic() - began:.0f} s"
          + (f"; recordings in {args.keep}" if args.keep else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
