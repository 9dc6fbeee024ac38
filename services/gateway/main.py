"""Skin gateway process: simulated AIRSKIN pads -> skin/pressure, and skin/touch per touch.

With ``gateway.source = "ros1"`` the pads are a real skin's, from a ROS 1
topic (:mod:`.ros1`, docs/lab.md).

It follows the arm's pose (``robot/state``) to tell where each touch meets
its pad (the ground truth published on ``skin/touch``) and, with
``gateway.sim.closed_loop`` (``--closed-loop``), to let a touch's pressure
fall as its pad withdraws from the finger.
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time

from nwr.common.config import Profile, load_script
from nwr.common.door import Door
from nwr.common.node import Node
from nwr.common.pacing import Rate
from nwr.services.gateway.wiring import SERVICE, GatewayWiring
from nwr.services.wiring import subscribe

log = logging.getLogger(__name__)

# The most a late loop catches up with, s of sample periods: longer stalls lose the periods beyond it.
CATCH_UP_S = 0.1


def add_arguments(parser: argparse.ArgumentParser) -> None:
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
    cfg = profile.gateway
    if cfg.source == "ros1":  # a real skin on a ROS 1 topic (docs/lab.md); rospy only then
        from nwr.services.gateway import ros1

        if args.script or args.follow_target or getattr(args, "closed_loop", False):
            log.warning("gateway.source = \"ros1\": --script, --follow-target and --closed-loop are the simulated "
                        "skin's and are ignored")
        return ros1.run(profile, args)
    if args.rate:
        cfg.rate_hz = args.rate
    if getattr(args, "closed_loop", False):
        cfg.sim.closed_loop = True
    script_name = args.script or cfg.sim.script
    script = load_script(script_name) if script_name else None
    lock = threading.Lock()  # the state handler, the loop and the journal's batches
    with Node(SERVICE, profile.robot.name, profile.zenoh, listen_slot="gateway",
              door=Door.of(profile), exclusive=True) as node:
        node.install_signal_handlers()
        wiring = node.wire(GatewayWiring, profile, lock, script=script, follow_target_s=args.follow_target)

        # The robot state on Zenoh's network thread (direct): the handler only keeps it (the bridge's 500 Hz at
        # 1 kHz skin would each cost a hand-off to a Python thread), and nothing this process puts, under the lock
        # or not, reaches a subscription of its own; the planners' statuses only with --follow-target.
        subscribe(node, wiring, lock)
        wait_for = [s for s in args.wait_for.split(",") if s]
        if wait_for:
            missing = node.wait_for(wait_for, timeout_s=30.0)
            if missing:
                log.error("services %s did not come up within 30 s", missing)
                return 1
        log.info(
            "publishing %d pads at %.0f Hz%s", len(wiring.pads), cfg.rate_hz,
            f", touch script {script_name} ({len(wiring.sim.touches)} touches, {script.duration_s} s)"
            if script else "",
        )
        if cfg.sim.closed_loop:
            log.info("closed loop: a touch's pressure falls as its pad withdraws (depth %.3f m)",
                     cfg.sim.contact_depth_m)
        rate = Rate(cfg.rate_hz, "gateway")
        # A late loop takes the sample periods it missed, each of its own time (a device's samples, read
        # late, are all there), up to CATCH_UP_S of them; beyond that, the periods are skipped (an overrun).
        catch_up = max(1, round(CATCH_UP_S * cfg.rate_hz))
        with lock:
            rate.restart(wiring.origin())
        notify = getattr(args, "notify_fd", None)
        ended = False
        t = 0.0
        try:
            while rate.wait(node.stop):
                now = time.monotonic_ns()
                first = rate.next_ns
                due = rate.take(now, limit=catch_up)
                rate.skip(now)
                for k in range(due):
                    with lock:
                        t = wiring.tick(first + k * rate.period_ns)
                if not ended and script is not None and t >= script.duration_s:
                    ended = True
                    log.info("touch script finished after %.1f s", t)
                    if args.exit_at_end:
                        break
                    if notify is not None:
                        notify_end(notify)
        finally:
            log.info(rate.summary())
    return 0


def notify_end(fd: int) -> None:
    """Tell the launcher the script has ended (one line on its pipe); a launcher gone is no error."""
    try:
        os.write(fd, b"script-end\n")
        os.close(fd)
    except OSError as exc:
        log.info("could not tell the launcher the script ended (fd %d: %s)", fd, exc)
