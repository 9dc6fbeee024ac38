"""What the effective-mass gain model buys against the paper's thresholds, in the scripted and the physics world
(in lockstep), and its predicted impact forces beside the forces the physics world measures.

    .venv/bin/python scripts/effective_mass.py [--scripts demo,in_the_way] [--worlds scripted,physics]
                                               [--periods 12,6] [--strategy cartesian] [--keep DIR]

For each world, touch script and task period (the figure-eight's; 12 s is
the default task, a shorter one a faster task, run with its speed limits
acknowledged), one simulated session per gain model (the paper's continuous
one, the effective-mass one) and one without any touch (``nwr demo --fast
[--world physics]``):

- the reflexes;
- the task time lost: the time the task was not progressing (the session's
  time minus the task's own progress, from the active planner's statuses),
  less the same in the untouched session;
- the largest predicted impact force at a touch's onset (the effective-mass
  model's prediction, ``SkinPain.impact_n``);
- in the physics world, the peak contact force on the person (every body
  part's, ``world/contacts``).

Then, per physics session of the effective-mass model, each body part's
predicted impact force at its first contact beside the peak force the world
measured on it (``nwr.services.tools.recordings.impact_check``); and the
task speed the model allows: the largest factor on the task's speed at which
no pad's predicted impact force along the task's path reaches its body
region's limit (the force grows in proportion to the speed; the effective
mass does not change), with the bridge's Cartesian speed limit for
comparison.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import msgspec
import numpy as np

from nwr.common.config import Profile, SafetySection
from nwr.common.launch import load_script, resolve_script
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.common.task import FigureEight, peak_point_speed
from nwr.services.gain.impact import ImpactModel, speed_scale_allowed
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.impact_check import format_rows, impact_rows
from nwr.services.tools.recordings.replay import simulate
from nwr.services.worlds.people import KINDS
from nwr.services.worlds.settings import PhysicsSettings

DEFAULT_PERIOD_S = 12.0
MODELS = ("continuous", "effective-mass")


def profile_for(model: str, period_s: float, speed_m_s: float, world: str = "scripted") -> Profile:
    profile = Profile()
    profile.gain.model = model  # type: ignore[assignment]
    if world == "physics":
        profile.bridge.backend, profile.gateway.source = "physics", "physics"
    if period_s < DEFAULT_PERIOD_S:  # a faster task: its period and the bridge's speed limit loosened, acknowledged
        profile.planner.task.period_s = period_s
        acknowledge = ["planner.task.period_s"]
        if speed_m_s > profile.bridge.limits.speed_m_s:
            profile.bridge.limits.speed_m_s = round(speed_m_s * 1.1, 3)
            acknowledge.append("bridge.limits.speed_m_s")
        profile.safety = SafetySection(acknowledge=acknowledge, reason="simulated measurement, nobody in the cell")
    return msgspec.convert(msgspec.to_builtins(profile), Profile)


def session(profile: Profile, script: str, strategy: str, path: Path) -> dict[str, float]:
    """One lockstep session's figures (module docstring); ``untouched_s``: the time the task did not progress."""
    simulate(profile, script, strategy, path)
    records, _ = read_recording(path)
    desc = load_description()
    touches = analysis.summarize(records, desc)
    statuses = [r.message for r in records if r.key.endswith("/status") and r.message.active]
    elapsed = (statuses[-1].stamp_ns - statuses[0].stamp_ns) / 1e9
    progress = statuses[-1].task_time_s - statuses[0].task_time_s
    forces = [t.impact_n for t in touches if t.impact_n is not None and t.reflex_seq]
    people = [p.peak_force_n for r in records if r.key == "world/contacts" for p in r.message.people]
    return {"touches": len(touches), "reflexes": sum(1 for t in touches if t.reflex_seq),
            "stalled_s": elapsed - progress, "elapsed_s": elapsed,
            "force_n": max(forces) if forces else float("nan"),
            "person_n": max(people) if people else float("nan"),
            "rows": impact_rows(records, desc)}  # type: ignore[dict-item]


def untouched(script: str, directory: Path) -> str:
    """A script of the same length as ``script`` without its touches (the task's own pace)."""
    path = directory / f"untouched-{Path(resolve_script(script)).stem}.toml"
    path.write_text(f"duration_s = {load_script(script).duration_s}\n")
    return str(path)


def allowed_speed(period_s: float) -> tuple[float, str, float]:
    """The factor on the task's speed at which the first pad's predicted force reaches its limit, that pad, and the
    task's fastest point at period_s, m/s."""
    profile = Profile()
    desc = load_description()
    robot = RobotModel(desc)
    task = FigureEight(profile.planner.task, desc)
    task.omega = 2.0 * np.pi / period_s
    s = np.linspace(0.0, period_s, 480, endpoint=False)
    qs = np.array([task.position(x) for x in s])
    dqs = np.array([task.velocity(x) for x in s])
    scale, _, pad = speed_scale_allowed(ImpactModel(profile.gain.effective_mass, robot), qs, dqs)
    return scale, desc.pads[pad].name, peak_point_speed(task, period_s, robot)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scripts", default="demo,in_the_way", help="touch scripts, comma-separated")
    parser.add_argument("--worlds", default="scripted,physics", help="worlds, comma-separated")
    parser.add_argument("--periods", default="12", help="task periods, s, comma-separated")
    parser.add_argument("--strategy", default="cartesian")
    parser.add_argument("--keep", metavar="DIR", help="keep the recordings in DIR (default: a temporary directory)")
    args = parser.parse_args()
    periods = [float(p) for p in args.periods.split(",")]
    worlds = [w for w in args.worlds.split(",") if w]
    scripts = [s for s in args.scripts.split(",") if s]
    bad = [w for w in worlds if w not in ("scripted", "physics")]
    if bad:
        parser.error(f"--worlds {bad}: the worlds are scripted and physics")
    print(f"strategy {args.strategy!r}, lockstep; task time lost: the time the task did not progress, less the "
          "same without the touches")
    print(f"{'world':>8} {'script':>10} {'period (s)':>10} {'top speed (m/s)':>15} {'model':>15} {'reflexes':>8} "
          f"{'lost (s)':>8} {'of (s)':>7} {'max F at onset (N)':>18} {'peak on person (N)':>18}")
    checks = []
    with tempfile.TemporaryDirectory() as temporary:
        work = Path(args.keep or temporary)
        work.mkdir(parents=True, exist_ok=True)
        for world in worlds:
            for script in scripts:
                for period in periods:
                    _, _, top = allowed_speed(period)
                    name = f"{world}-{Path(script).stem}-{period:g}"
                    base = session(profile_for("continuous", period, top, world), untouched(script, work),
                                   args.strategy, work / f"{name}-untouched.mcap")
                    for model in MODELS:
                        out = session(profile_for(model, period, top, world), script, args.strategy,
                                      work / f"{name}-{model}.mcap")
                        lost = out["stalled_s"] - base["stalled_s"]
                        print(f"{world:>8} {Path(script).stem:>10} {period:>10g} {top:>15.3f} {model:>15} "
                              f"{out['reflexes']:>8d} {lost:>8.2f} {out['elapsed_s']:>7.1f} "
                              f"{out['force_n']:>18.0f} {out['person_n']:>18.1f}")
                        if world == "physics" and model == "effective-mass" and out["rows"]:
                            checks.append((name, out["rows"]))
    settings = PhysicsSettings()
    for name, rows in checks:
        print(f"\npredicted impact force at first contact and the force the physics world measured ({name}; "
              f"world k, m_H: the same formula with the world's person, {settings.person_stiffness_n_m:g} N/m):")
        print(format_rows(rows, settings.person_stiffness_n_m, {k: v.mass_kg for k, v in KINDS.items()}))
    scale, pad, top = allowed_speed(DEFAULT_PERIOD_S)
    print(f"\nthe default task (period {DEFAULT_PERIOD_S:g} s, fastest point {top:.3f} m/s): no pad's predicted impact "
          f"force reaches its region's limit up to {scale:.2f} x its speed (period {DEFAULT_PERIOD_S / scale:.1f} s, "
          f"fastest point {top * scale:.3f} m/s; {pad} binds first); the bridge's speed limit "
          f"{Profile().bridge.limits.speed_m_s} m/s allows {Profile().bridge.limits.speed_m_s / top:.2f} x")


if __name__ == "__main__":
    main()
