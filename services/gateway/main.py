"""Skin gateway process: a skin source's pads -> skin/pressure (and skin/touch per simulated touch).

The source is ``gateway.source`` (``--source``), a module of :mod:`.sources`:
``sim`` (the default: simulated AIRSKIN pads on a touch script), ``physics``
(a physics world's pads, sampled by the world the bridge hosts, on a touch
script), ``ros1`` (a real skin's pressures from a ROS 1 topic, docs/lab.md) or
``ros2`` (from a ROS 2 topic through rmw_zenoh).

It follows the arm's pose (``robot/state``) to tell where each touch meets
its pad (the ground truth published on ``skin/touch``) and, with
``gateway.sim.closed_loop`` (``--closed-loop``), to let a touch's pressure
fall as its pad withdraws from the finger.
"""

from __future__ import annotations

import argparse
import logging

from nwr.common.config import Profile
from nwr.services.gateway import sources

log = logging.getLogger(__name__)

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source", choices=sources.names(),
                        help="the skin source, a module of services/gateway/sources/ (overrides gateway.source)")
    parser.add_argument("--script", help="touch script: a packaged name (e.g. demo) or a .toml path")
    parser.add_argument("--rate", type=float, help="skin sample rate, Hz (overrides gateway.rate_hz)")
    parser.add_argument(
        "--wait-for", default="", metavar="SERVICES",
        help="comma-separated services to wait for (liveliness) before the script's clock starts",
    )
    parser.add_argument("--exit-at-end", action="store_true", help="exit when the touch script ends")
    parser.add_argument(
        "--notify-fd", type=int, metavar="FD",
        help="when the touch script ends, write 'script-end' to this inherited file descriptor and go on "
             "publishing the pads at rest until stopped (how a launcher ends a session in order: the arm "
             "comes to rest while the skin is still watched)",
    )
    parser.add_argument(
        "--follow-target", type=float, metavar="SECONDS",
        help="simulated participant: press the planner's current target pad every SECONDS while the arm does "
             "its task (the study's game)",
    )
    parser.add_argument(
        "--closed-loop", action="store_true",
        help="a touch's pressure falls as its pad withdraws from the finger (gateway.sim.closed_loop)",
    )


def run(profile: Profile, args: argparse.Namespace) -> int:
    if getattr(args, "source", None):
        profile.gateway.source = args.source
    source = sources.live(profile.gateway.source)  # a ConfigError naming the sources there are
    scripted = args.script or args.follow_target or getattr(args, "closed_loop", False)
    if source.NAME not in ("sim", "physics") and scripted:
        log.warning("gateway.source = %r: --script, --follow-target and --closed-loop are the simulated skin's and "
                    "are ignored", source.NAME)
    return int(source.run(profile, args))
