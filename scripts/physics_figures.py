"""The physics world beside the scripted world, for every strategy: a held press, a slow press, a two-finger touch.

    .venv/bin/python scripts/physics_figures.py [--cases held-press,slow-press,two-fingers]
                                                [--strategies uniform,...] [--keep DIR]

For each case (a packaged touch script) and each reflex strategy, one
simulated session in the physics world and one in the scripted world, in
lockstep (``nwr demo --fast [--world physics] --script CASE --reflex R``), and
one table, a row per scripted touch:

- toward (mm): the touched pad's furthest move toward where the touch met
  it while the touch lasted (the per-touch table's ``pressed``; the largest
  over the touch's runs of contact). In the scripted world its finger never
  moves, so this is how far the pad moved into it; in the physics world the
  finger gives way;
- into (mm): physics only, how far the arm pushed the finger back from where
  its owner holds it (``into``): how far the pad moved into the finger. A
  finger held where it met the pad is held there; one that follows the arm
  (a touch's ``follow_m_s``: the packaged ``slow-press``) is held where it
  has caught up with the pad, so its "toward" says little and "into" is the
  figure;
- force (N): physics, the measured peak contact force on the person
  (``peak_force``); scripted, the force that makes the pressure the pad felt
  at its peak on a still pad (the physics world's inverse skin model: the
  scripted world has no force of its own);
- ISO (%): physics, the peak force or pressure as a share of ISO/TS 15066's
  quasi-static limits for the finger's body area (``of_limit``).

Each session's recording is written to a temporary directory (``--keep``: to
DIR, where ``nwr summary``, ``nwr compare`` and ``nwr verify`` read them).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from nwr.common.config import Profile
from nwr.common.launch import Touch, load_script
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner import strategies
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.replay import simulate
from nwr.services.worlds.hosted import finger_force, touch_end_s
from nwr.services.worlds.settings import PhysicsSettings

CASES = ("held-press", "slow-press", "two-fingers")
STRATEGIES = ("uniform", "location", "cartesian", "cartesian-smooth", "whole-arm")


@dataclass
class Figures:
    """One scripted touch in one session: see the module docstring."""

    toward_mm: float | None
    into_mm: float | None
    force_n: float | None
    of_limit: float | None
    reflex: bool


def profile_for(world: str) -> Profile:
    profile = Profile()
    if world == "physics":
        profile.bridge.backend, profile.gateway.source = "physics", "physics"
    return profile


def session(case: str, strategy: str, world: str, out: Path) -> list[Figures]:
    """One lockstep session of ``case``: the figures of each of its scripted touches, in script order."""
    profile = profile_for(world)
    path = out / f"{case}-{strategy}-{world}.mcap"
    simulate(profile, case, strategy, path)
    records, _ = read_recording(path, only=analysis.summarized)
    desc = load_description(profile.robot.description or None)
    touches = analysis.summarize(records, desc, RobotModel(desc))
    t0 = next((r.message.stamp_ns for r in records if r.key == "skin/pressure"), 0)
    return [figures(touch, touches, t0, desc.pad(touch.pad).id, world) for touch in load_script(case).touch]


def figures(scripted: Touch, touches: list[analysis.TouchSummary], t0_ns: int,
            pad: int, world: str) -> Figures:
    """The figures of one scripted touch from the recording's touches on its pad during it (a touch the pad
    stopped feeling and felt again is several runs of contact: the largest of each figure)."""
    start, end = scripted.start_s - 0.2, touch_end_s(scripted) + 0.3
    mine = [t for t in touches if t.pad == pad and start <= (t.start_ns - t0_ns) / 1e9 <= end]

    def most(values: list[float | None]) -> float | None:
        present = [v for v in values if v is not None]
        return max(present) if present else None

    if world == "physics":
        force = most([t.peak_force_n for t in mine])
    else:
        felt = most([t.peak_hpa for t in mine])
        force = None if felt is None else finger_force(felt, PhysicsSettings())
    return Figures(most([t.pressed_toward_mm for t in mine]), most([t.into_finger_mm for t in mine]), force,
                   most([t.of_limit for t in mine]), any(t.reflex_seq for t in mine))


HEADER = ["case", "strategy", "pad (hPa)", "scripted: toward (mm)", "scripted: force (N)", "scripted: reflex",
          "physics: toward (mm)", "physics: into (mm)", "physics: force (N)", "physics: ISO (%)", "physics: reflex"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--cases", default=",".join(CASES), help="packaged touch scripts, comma-separated")
    parser.add_argument("--strategies", default=",".join(STRATEGIES), help="reflex strategies, comma-separated")
    parser.add_argument("--keep", type=Path, help="write the recordings here (default: a temporary directory)")
    args = parser.parse_args()
    cases = [c for c in args.cases.split(",") if c]
    chosen = [s for s in args.strategies.split(",") if s]
    for strategy in chosen:
        strategies.check(strategy)
    scripts = {case: load_script(case) for case in cases}  # a bad name fails before any session runs
    f = analysis.cell
    rows = []
    began = time.monotonic()
    with tempfile.TemporaryDirectory() as scratch:
        out = args.keep or Path(scratch)
        out.mkdir(parents=True, exist_ok=True)
        for case in cases:
            for strategy in chosen:
                scripted = session(case, strategy, "scripted", out)
                physics = session(case, strategy, "physics", out)
                for touch, s, p in zip(scripts[case].touch, scripted, physics):
                    rows.append([case, strategy, f"{touch.pad} ({touch.peak_hpa:g})", f(s.toward_mm, ".1f"),
                                 f(s.force_n, ".1f"), "yes" if s.reflex else "no", f(p.toward_mm, ".1f"),
                                 f(p.into_mm, ".1f"), f(p.force_n, ".1f"),
                                 f(None if p.of_limit is None else 100 * p.of_limit, ".0f"),
                                 "yes" if p.reflex else "no"])
    print(analysis.format_table(HEADER, rows))
    print(f"\n{2 * len(cases) * len(chosen)} sessions in lockstep in {time.monotonic() - began:.0f} s"
          + (f"; recordings in {args.keep}" if args.keep else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
