"""franky-sim on 127.0.0.1, headless, its FR3 at the robot description's home: the arm the franky backend drives.

Run it with ``python -m nwr.services.tools.hardware.franky_sim``; it prints
``ready <address>`` once libfranka's server (franky-sim: an FR3 in MuJoCo
behind libfranka's own network protocol) accepts connections and the arm has
moved to the FR3's home pose (``common/robots/fr3/robot.toml``, through franky
itself, as a lab moves a real arm before a session), then serves until SIGINT
or SIGTERM. Then ``nwr --profile fr3 demo --backend franky --robot-ip 127.0.0.1
--i-am-next-to-the-robot`` (with ``[bridge.franky] realtime = "ignore"``) runs
the pipeline on it (docs/robots.md).

libfranka's ports are fixed (TCP 1337 and the UDP state stream): one
simulator per address, and this one listens on 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import logging
import signal
import subprocess
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from nwr.common.pacing import realtime
from nwr.common.robot import load_description
from nwr.services.tools.hardware import stand_in

log = logging.getLogger(__name__)

HOST = "127.0.0.1"
# How fast the arm moves home, a fraction of Franka's limits.
HOMING_DYNAMICS = 0.2
# The arm is at home within this, rad (franky's motion ends before the simulated arm has settled).
HOME_TOLERANCE_RAD = 0.005
SETTLE_S = 3.0


def home(hostname: str, q_home: np.ndarray) -> float:
    """Move the arm to ``q_home`` through franky; the largest joint error left, rad. The connection is closed."""
    import franky

    robot = franky.Robot(hostname, realtime_config=franky.RealtimeConfig.Ignore)
    try:
        robot.relative_dynamics_factor = HOMING_DYNAMICS
        robot.move(franky.JointMotion(q_home))
        deadline = time.monotonic() + SETTLE_S
        error = float(np.max(np.abs(robot.state.q - q_home)))
        while error > HOME_TOLERANCE_RAD and time.monotonic() < deadline:
            time.sleep(0.05)
            error = float(np.max(np.abs(robot.state.q - q_home)))
        return error
    finally:
        del robot
        gc.collect()  # franky closes the connection when its robot is destroyed: the bridge connects next


def simulator_process(log_path: Path, *args: str) -> contextlib.AbstractContextManager[subprocess.Popen[str]]:
    """``python -m nwr.services.tools.hardware.franky_sim ARGS`` in a process of its own, ready (it printed
    ``ready``: the server accepts connections, the arm at home), then ended (:func:`..hardware.stand_in`)."""
    return stand_in("nwr.services.tools.hardware.franky_sim", log_path, *args)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m nwr.services.tools.hardware.franky_sim",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--robot", default="fr3", help="the robot description whose home the arm moves to "
                                                       "(default: the packaged fr3)")
    parser.add_argument("--no-home", action="store_true", help="leave the arm where franky-sim starts it")
    parser.add_argument("--realtime-priority", type=int, default=0, metavar="P",
                        help="run under SCHED_FIFO at priority P (1-99; 0: off): a real arm's controller is a "
                             "machine of its own, and a simulator starved beside a loaded pipeline falls behind "
                             "real time, its arm lagging the bridge's stream")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s franky-sim %(levelname)s %(message)s")
    logging.getLogger("franky_sim").setLevel(logging.WARNING)  # a line per libfranka command otherwise
    if not 0 <= args.realtime_priority <= 99:
        parser.error(f"--realtime-priority {args.realtime_priority}: give 1-99, or 0 for the normal scheduler")
    realtime(args.realtime_priority, "franky-sim")  # before the simulator's threads start: they inherit it
    try:
        from franky_sim import SimulationServer
        from franky_sim.mujoco_simulator import MujocoSimulator
    except ImportError as exc:
        parser.error(f"franky-sim is not installed ({exc}): pip install franky-sim")
    q_home = np.asarray(load_description(args.robot).home, dtype=float)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with MujocoSimulator(enable_visualization=False) as sim:
        robot = sim.add_robot()
        with SimulationServer(sim, hostname_candidates=[HOST]) as server:
            server.run_async()
            if robot.hostname != HOST:
                raise SystemExit(f"franky-sim bound {robot.hostname}, not {HOST}")
            if not args.no_home:
                error = home(HOST, q_home)
                log.info("arm at home, %.4f rad from it at worst", error)
            print(f"ready {HOST}", flush=True)
            stop.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
