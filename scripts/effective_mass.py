"""What the effective-mass gain model buys on a touch script, against the paper's thresholds (in lockstep).

    .venv/bin/python scripts/effective_mass.py [--script demo] [--periods 12,6] [--strategy cartesian]

For each task period (the figure-eight's; 12 s is the default task, a shorter
one a faster task, run with its speed limits acknowledged) and each gain
model (the paper's continuous one, the effective-mass one), one simulated
session of the touch script in lockstep (``nwr demo --fast``): the reflexes,
the task time lost (the session's time minus the task's own progress, from
the active planner's statuses) and the largest predicted impact force at a
touch's onset. Then the task speed the model allows: the largest factor on
the task's speed at which no pad's predicted impact force along the task's
path reaches its body region's limit (the force grows in proportion to the
speed; the effective mass does not change), and the bridge's Cartesian speed
limit for comparison.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import msgspec
import numpy as np

from nwr.common.config import Profile, SafetySection
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.common.task import FigureEight, peak_point_speed
from nwr.services.gain.impact import ImpactModel, speed_scale_allowed
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.replay import simulate

DEFAULT_PERIOD_S = 12.0


def profile_for(model: str, period_s: float, speed_m_s: float) -> Profile:
    profile = Profile()
    profile.gain.model = model  # type: ignore[assignment]
    if period_s < DEFAULT_PERIOD_S:  # a faster task: its period and the bridge's speed limit loosened, acknowledged
        profile.planner.task.period_s = period_s
        acknowledge = ["planner.task.period_s"]
        if speed_m_s > profile.bridge.limits.speed_m_s:
            profile.bridge.limits.speed_m_s = round(speed_m_s * 1.1, 3)
            acknowledge.append("bridge.limits.speed_m_s")
        profile.safety = SafetySection(acknowledge=acknowledge, reason="simulated measurement, nobody in the cell")
    return msgspec.convert(msgspec.to_builtins(profile), Profile)


def session(profile: Profile, script: str, strategy: str, path: Path) -> dict[str, float]:
    simulate(profile, script, strategy, path)
    records, _ = read_recording(path)
    desc = load_description()
    touches = analysis.summarize(records, desc)
    statuses = [r.message for r in records if r.key.endswith("/status") and r.message.active]
    elapsed = (statuses[-1].stamp_ns - statuses[0].stamp_ns) / 1e9
    progress = statuses[-1].task_time_s - statuses[0].task_time_s
    forces = [t.impact_n for t in touches if t.impact_n is not None and t.reflex_seq]
    return {"touches": len(touches), "reflexes": sum(1 for t in touches if t.reflex_seq),
            "lost_s": elapsed - progress, "elapsed_s": elapsed,
            "force_n": max(forces) if forces else float("nan")}


def allowed_speed(period_s: float) -> tuple[float, str, float]:
    """The factor on the task's speed at which the first pad's predicted force reaches its limit, that pad, and the
    task's fastest point at period_s, m/s."""
    profile = Profile()
    desc = load_description()
    robot = RobotModel(desc)
    task = FigureEight(profile.planner.task, desc.home)
    task.omega = 2.0 * np.pi / period_s
    s = np.linspace(0.0, period_s, 480, endpoint=False)
    qs = np.array([task.position(x) for x in s])
    dqs = np.array([task.velocity(x) for x in s])
    scale, _, pad = speed_scale_allowed(ImpactModel(profile.gain.effective_mass, robot), qs, dqs)
    return scale, desc.pads[pad].name, peak_point_speed(task, period_s, robot)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--script", default="demo")
    parser.add_argument("--periods", default="12,6", help="task periods, s, comma-separated")
    parser.add_argument("--strategy", default="cartesian")
    parser.add_argument("--keep", metavar="DIR", help="keep the recordings in DIR (default: a temporary directory)")
    args = parser.parse_args()
    periods = [float(p) for p in args.periods.split(",")]
    print(f"script {args.script!r}, strategy {args.strategy!r}, lockstep")
    print(f"{'period (s)':>10} {'top speed (m/s)':>15} {'model':>15} {'reflexes':>8} {'lost (s)':>8} "
          f"{'of (s)':>7} {'max F at onset (N)':>18}")
    with tempfile.TemporaryDirectory() as temporary:
        work = args.keep or temporary
        Path(work).mkdir(parents=True, exist_ok=True)
        for period in periods:
            _, _, top = allowed_speed(period)
            for model in ("continuous", "effective-mass"):
                out = session(profile_for(model, period, top), args.script, args.strategy,
                              Path(work) / f"{model}-{period:g}.mcap")
                print(f"{period:>10g} {top:>15.3f} {model:>15} {out['reflexes']:>8d} {out['lost_s']:>8.2f} "
                      f"{out['elapsed_s']:>7.1f} {out['force_n']:>18.0f}")
    scale, pad, top = allowed_speed(DEFAULT_PERIOD_S)
    print(f"\nthe default task (period {DEFAULT_PERIOD_S:g} s, fastest point {top:.3f} m/s): no pad's predicted impact "
          f"force reaches its region's limit up to {scale:.2f} x its speed (period {DEFAULT_PERIOD_S / scale:.1f} s, "
          f"fastest point {top * scale:.3f} m/s; {pad} binds first); the bridge's speed limit "
          f"{Profile().bridge.limits.speed_m_s} m/s allows {Profile().bridge.limits.speed_m_s / top:.2f} x")


if __name__ == "__main__":
    main()
