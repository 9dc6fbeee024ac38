"""The simulated skin (``gateway.source = "sim"``, the default): AIRSKIN pads pressed by a touch script.

The gateway's wiring ticks at ``gateway.rate_hz``: each tick the touches that
start (the ground truth on ``skin/touch``) and one sample of every pad
(``skin/pressure``). The script's clock starts once the services named by
``--wait-for`` are alive; ``--notify-fd`` tells a launcher when it has ended.
A late loop takes the sample periods it missed, each of its own time, up to
:data:`CATCH_UP_S` of them.
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time

from nwr.common.config import Profile
from nwr.common.door import Door
from nwr.common.launch import load_script
from nwr.common.node import Node
from nwr.common.pacing import Rate
from nwr.services.gateway.core import SimSkinSettings, sim_settings, with_sim
from nwr.services.gateway.wiring import SERVICE, GatewayWiring
from nwr.services.wiring import subscribe

log = logging.getLogger(__name__)

NAME = "sim"
Settings = SimSkinSettings  # [gateway.sim], beside the simulated skin it configures (gateway/core.py)

# The most a late loop catches up with, s of sample periods: longer stalls lose the periods beyond it.
CATCH_UP_S = 0.1


def run(profile: Profile, args: argparse.Namespace) -> int:
    cfg = profile.gateway
    if args.rate:
        cfg.rate_hz = args.rate
    if getattr(args, "closed_loop", False):
        cfg = profile.gateway = with_sim(cfg, closed_loop=True)
    sim = sim_settings(cfg)
    script_name = args.script or sim.script
    script = load_script(script_name, profile.robot.description) if script_name else None
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
        if sim.closed_loop:
            log.info("closed loop: a touch's pressure falls as its pad withdraws (depth %.3f m)", sim.contact_depth_m)
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
            if wiring.late_samples:
                log.warning("%d world skin samples arrived later than gateway.max_sample_age_s and were dropped",
                            wiring.late_samples)
    return 0


def notify_end(fd: int) -> None:
    """Tell the launcher the script has ended (one line on its pipe); a launcher gone is no error."""
    try:
        os.write(fd, b"script-end\n")
        os.close(fd)
    except OSError as exc:
        log.info("could not tell the launcher the script ended (fd %d: %s)", fd, exc)
