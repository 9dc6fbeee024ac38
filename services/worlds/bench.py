"""How fast the physics world runs alone: ``python -m nwr.services.worlds.bench``.

The arm draws the study's figure-eight (commands every step) while body
parts press pads; for each time step and number of body parts it prints the
steps per second and the real-time factor (simulated time over wall time,
the best of ``--repeat`` runs: other load on the machine only slows a run).
"""

from __future__ import annotations

import argparse
import time

from nwr.common.robot import load_description
from nwr.common.task import FigureEight, TaskSection
from nwr.services.worlds.physics import PhysicsSettings, PhysicsWorld

# Pads and forces of the body parts that press while the arm moves (the first n of them).
_PRESSES = ((2, "finger", 10.0), (5, "finger", 20.0), (1, "palm", 15.0), (6, "forearm", 15.0),
            (4, "finger", 8.0), (7, "finger", 12.0), (3, "palm", 25.0), (8, "forearm", 20.0))


def measure(timestep_s: float, parts: int, seconds: float) -> float:
    """The real-time factor of one run: ``seconds`` of world time over the wall time it took."""
    desc = load_description()
    world = PhysicsWorld(desc, PhysicsSettings(timestep_s=timestep_s))
    for index, (pad, kind, force) in enumerate(_PRESSES[:parts]):
        world.press(f"{kind}{index}", pad, force, kind=kind)  # type: ignore[arg-type]
    task = FigureEight(TaskSection(), desc)
    steps = round(seconds / timestep_s)
    commands = [task.position((i + 1) * timestep_s) for i in range(steps)]
    start = time.perf_counter()
    for q in commands:
        world.step(q)
    return seconds / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="world time per run (default 5 s)")
    parser.add_argument("--repeat", type=int, default=3, help="runs per case, the best one counts (default 3)")
    args = parser.parse_args(argv)
    print(f"{'step':>6} {'parts':>5} {'steps/s':>9} {'real-time factor':>17}")
    for timestep_s in (0.001, 0.002):
        for parts in (0, 2, 8):
            factor = max(measure(timestep_s, parts, args.seconds) for _ in range(args.repeat))
            print(f"{timestep_s * 1000:>4.0f} ms {parts:>5} {factor / timestep_s:>9.0f} {factor:>17.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
