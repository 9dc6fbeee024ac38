"""View process (read-only): the robot's keys -> a live 3D scene for Foxglove.

Subscribes to ``robot/state``, ``skin/pressure``, ``skin/pain`` and
``reflex/*/status`` and never publishes on the robot's keys (only its own
``diag/view``). Subscribers only keep the newest message; one paced loop
(``--rate``, 30 Hz by default, whatever the 500 Hz control rate) builds and
serves the scene, so the view costs little and never touches the reflex path.
"""

from __future__ import annotations

import argparse
import logging
import time

from nwr.common import keys
from nwr.common.config import Profile
from nwr.common.door import Door
from nwr.common.errors import ConfigError
from nwr.common.node import Node
from nwr.common.pacing import Rate
from nwr.common.robot import RobotModel, load_description
from nwr.services.view.core import DEFAULT_RATE_HZ, ViewCore, encode_frame
from nwr.services.view.server import DEFAULT_PORT, ViewServer

log = logging.getLogger(__name__)

STATS_EVERY_S = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to serve on (default: loopback). The Foxglove protocol has no "
                             "authentication: expose it on a trusted lab network only")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"WebSocket port (default: {DEFAULT_PORT})")
    parser.add_argument("--rate", type=float, default=DEFAULT_RATE_HZ,
                        help=f"3D scene rate cap, Hz (default: {DEFAULT_RATE_HZ:g})")


def check_arguments(args: argparse.Namespace) -> None:
    if not 0 < args.rate <= 200:
        raise ConfigError(f"--rate {args.rate}: expected a scene rate in (0, 200] Hz, e.g. 30")
    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: expected a TCP port in 0..65535 (0: any free one)")


def run(profile: Profile, args: argparse.Namespace) -> int:
    check_arguments(args)
    desc = load_description(profile.robot.description or None)
    core = ViewCore(desc, RobotModel(desc))
    view = ViewServer(args.host, args.port, name=f"nwr view {profile.robot.name}", channels=core.channels)
    try:
        with Node("view", profile.robot.name, profile.zenoh, door=Door.of(profile)) as node:
            node.install_signal_handlers()
            for relative in (keys.ROBOT_STATE, keys.SKIN_PRESSURE, keys.SKIN_PAIN, keys.planner_status("*"),
                             keys.WORLD_CONTACTS):
                node.subscribe(relative, core.apply)  # stores the newest message, nothing more
            log.info("serving %s at up to %.0f Hz on ws://%s:%d (open it in Foxglove: Open connection)",
                     profile.robot.name, args.rate, args.host, view.port)
            rate = Rate(args.rate, "view")
            cpu0, wall0 = time.process_time(), time.monotonic()
            window = (cpu0, wall0, 0)
            frames = 0
            view.log(core.description(node.clock.now_ns()))
            try:
                while rate.sleep(node.stop):
                    now = node.clock.now_ns()
                    if view.description_wanted.is_set():
                        view.description_wanted.clear()
                        view.log(core.description(now))
                    for output in encode_frame(core.frame(now)):
                        view.log(output)
                    frames += 1
                    view.server.broadcast_time(now)
                    cpu, wall = time.process_time(), time.monotonic()
                    if wall - window[1] >= STATS_EVERY_S:
                        # Whole-process CPU (Zenoh's and the server's threads too) over the last window.
                        view.stats.log({
                            "stamp_ns": now, "frames": frames, "scene_hz": (frames - window[2]) / (wall - window[1]),
                            "cpu_percent": 100.0 * (cpu - window[0]) / (wall - window[1]),
                            "cpu_s": cpu - cpu0, "wall_s": wall - wall0, "overruns": rate.overruns,
                        }, log_time=now)
                        window = (cpu, wall, frames)
            finally:
                cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
                log.info(rate.summary())
                log.info("view: %d frames in %.1f s (%.1f Hz), CPU %.2f s = %.1f %% of one core",
                         frames, wall, frames / wall if wall > 0 else 0.0, cpu, 100.0 * cpu / wall if wall > 0 else 0.0)
    finally:
        view.stop()
    return 0
