"""The reflex onset on the FR3 through franky and libfranka's protocol (franky-sim), printed as figures.

    .venv/bin/python scripts/benchmarks/franky_onset.py [--runs N] [--script NAME|FILE]

Starts franky-sim on 127.0.0.1 (``python -m nwr.services.tools.hardware.franky_sim``:
headless, its FR3 moved home, SCHED_FIFO ``--sim-priority`` where permitted), runs ``nwr demo`` on the FR3 with
``bridge.backend = "franky"`` N times (the simulator restarted for each: a
session leaves its arm where it ended), and prints, over every touch's reflex, its
onset (the per-touch table's *onset*) from the touching skin sample's stamp (the gateway) to the bridge
handing the reflex's first setpoint to franky (``set_reference`` on the
running impedance motion, in the cycle the bridge accepts the command:
``RobotState.accepted_ns``), which libfranka's 1 kHz loop takes up at its
next cycle (at most 1 ms later). Both ends on the machine's monotonic clock.
The machine's load is printed beside the figures: they are a loaded
machine's when it is one.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from nwr.common.recordings import read_recording
from nwr.common.robot import load_description
from nwr.services.tools.hardware.franky_sim import simulator_process
from nwr.services.tools.recordings import analysis

# The simulator real-time below the bridge (20), as in tests/test_franky_e2e.py (where permitted).
SIM_PRIORITY = 10
PROFILE = ('[robot]\nname = "fr3"\ndescription = "fr3"\n'
           '[bridge]\nbackend = "franky"\n'
           '[bridge.franky]\nrealtime = "ignore"\n')


def onsets_ms(path: Path) -> list[float]:
    """Each touch's reflex onset (the per-touch table's *onset*), ms."""
    records, _ = read_recording(path)
    touches = analysis.summarize(records, load_description("fr3"))
    return [t.onset_latency_ms for t in touches if t.reflex_seq > 0 and t.onset_latency_ms is not None]


def session(tmp: Path, run: int, script: str, priority: int) -> list[float]:
    with simulator_process(tmp / f"franky-sim-{run}.log", "--realtime-priority", str(priority)):
        out = tmp / f"run{run}.mcap"
        demo = subprocess.run([sys.executable, "-m", "nwr.services.cli", "--profile", str(tmp / "profile.toml"),
                               "demo", "--script", script, "--output", str(out), "--backend", "franky",
                               "--robot-ip", "127.0.0.1", "--i-am-next-to-the-robot"],
                              capture_output=True, text=True, timeout=600)
        print(demo.stdout.strip().splitlines()[-1] if demo.stdout.strip() else demo.stderr[-2000:])
        return onsets_ms(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--script", default="demo", help="the touch script (default: the FR3's demo session)")
    parser.add_argument("--sim-priority", type=int, default=SIM_PRIORITY,
                        help=f"the simulator's SCHED_FIFO priority (default {SIM_PRIORITY}; the bridge's is 20)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="franky-onset-") as name:
        tmp = Path(name)
        (tmp / "profile.toml").write_text(f'[recorder]\ndirectory = "{tmp}"\n{PROFILE}')
        load = []
        values: list[float] = []
        for run in range(args.runs):
            values += session(tmp, run, args.script, args.sim_priority)
            load.append(os.getloadavg()[0])
    if not values:
        print("no reflex onset recorded")
        return 1
    v = np.array(values)
    print(f"reflex onset on the FR3 through franky (skin sample -> setpoint handed to libfranka's loop), "
          f"{v.size} reflexes in {args.runs} sessions: p50 {np.percentile(v, 50):.2f} ms, "
          f"p90 {np.percentile(v, 90):.2f} ms, worst {v.max():.2f} ms; the simulator at SCHED_FIFO "
          f"{args.sim_priority}; load average {min(load):.1f}-{max(load):.1f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
