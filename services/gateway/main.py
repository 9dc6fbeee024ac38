"""Skin gateway process: simulated AIRSKIN pads -> skin/pressure, and skin/touch per touch.

It follows the arm's pose (``robot/state``) to tell where each touch meets
its pad (the ground truth published on ``skin/touch``) and, with
``gateway.sim.closed_loop`` (``--closed-loop``), to let a touch's pressure
fall as its pad withdraws from the finger.
"""

from __future__ import annotations

import argparse
import logging

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile, load_script
from nwr.common.node import Node
from nwr.common.pacing import Rate
from nwr.common.robot import RobotModel, load_description
from nwr.services.gateway.core import Gateway, SimSkin, TargetFollower, touch_message

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--script", help="touch script: a packaged name (e.g. demo) or a .toml path")
    parser.add_argument("--rate", type=float, help="skin sample rate, Hz (overrides gateway.rate_hz)")
    parser.add_argument(
        "--wait-for", default="", metavar="SERVICES",
        help="comma-separated services to wait for (liveliness) before the script's clock starts",
    )
    parser.add_argument("--exit-at-end", action="store_true", help="exit when the touch script ends")
    parser.add_argument(
        "--follow-target", type=float, metavar="SECONDS",
        help="simulated participant: press the planner's current target pad every SECONDS (the study's game)",
    )
    parser.add_argument(
        "--closed-loop", action="store_true",
        help="a touch's pressure falls as its pad withdraws from the finger (gateway.sim.closed_loop)",
    )


def run(profile: Profile, args: argparse.Namespace) -> int:
    cfg = profile.gateway
    if args.rate:
        cfg.rate_hz = args.rate
    if getattr(args, "closed_loop", False):
        cfg.sim.closed_loop = True
    script_name = args.script or cfg.sim.script
    script = load_script(script_name) if script_name else None
    desc = load_description(profile.robot.description or None)
    sim = SimSkin(cfg.sim, desc.pads, script)
    gateway = Gateway(cfg, len(desc.pads), source="sim")
    with Node("gateway", profile.robot.name, profile.zenoh, listen_slot="gateway") as node:
        node.install_signal_handlers()
        publish = node.publisher(keys.SKIN_PRESSURE)
        publish_touch = node.publisher(keys.SKIN_TOUCH)
        model = RobotModel(desc)
        pose: list[m.RobotState | None] = [None]  # the newest robot state (a Zenoh thread writes it)

        def on_state(state: m.RobotState) -> None:
            pose[0] = state

        node.subscribe(keys.ROBOT_STATE, on_state)
        touch_seq = 0
        follower = TargetFollower(args.follow_target, cfg.sim.seed) if args.follow_target else None
        target = [-1]
        if follower is not None:

            def on_status(status: m.PlannerStatus) -> None:
                target[0] = status.target_pad

            node.subscribe(keys.planner_status("*"), on_status)
        wait_for = [s for s in args.wait_for.split(",") if s]
        if wait_for:
            missing = node.wait_for(wait_for, timeout_s=30.0)
            if missing:
                log.error("services %s did not come up within 30 s", missing)
                return 1
        log.info(
            "publishing %d pads at %.0f Hz%s", len(desc.pads), cfg.rate_hz,
            f", touch script {script_name} ({len(sim.touches)} touches, {script.duration_s} s)" if script else "",
        )
        if cfg.sim.closed_loop:
            log.info("closed loop: a touch's pressure falls as its pad withdraws (depth %.3f m)",
                     cfg.sim.contact_depth_m)
        rate = Rate(cfg.rate_hz, "gateway")
        t0 = node.clock.now_ns()
        try:
            while rate.sleep(node.stop):
                now = node.clock.now_ns()
                t = (now - t0) / 1e9
                if follower is not None:
                    touch = follower.poll(t, target[0])
                    if touch is not None:
                        sim.add_touch(*touch)
                state = pose[0]
                points = normals = None
                if state is not None and sim.touches.needs_pose(t):  # forward kinematics only when used
                    points, normals = model.pad_points(state.q), model.pad_normals(state.q)
                for started in sim.start(t, points, normals):
                    publish_touch(touch_message(touch_seq, now, t0, started, desc.pads[started.pad].name, sim.touches,
                                                state.q if state is not None else None,
                                                state.stamp_ns if state is not None else 0))
                    touch_seq += 1
                msg, events = gateway.process(t, now, sim.sample(t, points), sim.touch_hpa)
                publish(msg)
                for pad in events.reacquired:
                    node.diag("warning", "baseline_reacquired",
                              f"pad {desc.pads[pad].name} stayed above the contact threshold for more than "
                              f"{cfg.max_contact_s} s: its baseline was re-acquired")
                for pad in events.non_finite:
                    node.diag("warning", "non_finite_pressure",
                              f"pad {desc.pads[pad].name} reported a non-finite pressure")
                if args.exit_at_end and script is not None and t >= script.duration_s:
                    log.info("touch script finished after %.1f s", t)
                    break
        finally:
            log.info(rate.summary())
    return 0
