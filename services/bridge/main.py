"""Robot bridge process: robot/command -> the arm (simulated) -> robot/state."""

from __future__ import annotations

import argparse
import logging
import threading

import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.node import Node
from nwr.common.pacing import Rate
from nwr.common.robot import load_description
from nwr.services.bridge.core import Limits, SimArm, check_command

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--active", help="the planner whose commands move the arm (overrides bridge.active_planner)")


class Bridge:
    """Owns the arm; the command callback and the control loop share it under a lock."""

    def __init__(self, profile: Profile, node: Node) -> None:
        cfg = profile.bridge
        desc = load_description(profile.robot.description or None)
        limits = Limits(desc.q_min, desc.q_max, cfg.speed_fraction * desc.v_max, cfg.acceleration_fraction * desc.a_max)
        q0 = np.asarray(cfg.initial_q, dtype=float) if cfg.initial_q else desc.home
        if q0.shape != desc.home.shape:
            raise ValueError(f"bridge.initial_q has {q0.size} joints, the robot has {desc.home.size}")
        self.cfg = cfg
        self.node = node
        self.n = len(desc.joints)
        self.arm = SimArm(limits, q0)
        self.lock = threading.Lock()
        self.active = cfg.active_planner
        self.status: m.RobotStatus = "idle"
        self.last_command_ns = 0
        self.reflex_seq = 0
        self.accepted: m.Trace | None = None
        self.accepted_ns = 0
        self.rejected = 0
        self.seq = 0
        self.publish_state = node.publisher(keys.ROBOT_STATE)

    def on_command(self, cmd: m.Command) -> None:
        reason = check_command(cmd, self.active, self.n)
        now = self.node.clock.now_ns()
        if reason is not None:
            with self.lock:
                self.rejected += 1
            self.node.diag("warning", "command_rejected", reason)
            return
        with self.lock:
            if isinstance(cmd, m.PositionCommand):
                self.arm.command_position(np.asarray(cmd.q, dtype=float))
            else:
                self.arm.command_velocity(np.asarray(cmd.dq, dtype=float))
            self.last_command_ns = now
            self.status = "ok"
            onset = cmd.reflex_seq != self.reflex_seq and cmd.phase == "REFLEX"
            self.reflex_seq = cmd.reflex_seq
            if onset:
                # The first command of a reflex goes to the backend now, not at
                # the next cycle, and its acceptance is published at once.
                self.accepted = cmd.trace
                self.accepted_ns = now
                self._publish(now)

    def tick(self, dt: float) -> None:
        now = self.node.clock.now_ns()
        with self.lock:
            if self.status == "ok" and now - self.last_command_ns > self.cfg.command_timeout_s * 1e9:
                self.status = "stale_command"
                self.arm.stop()
                stop = self.arm.stopping_distance()
                self.node.diag(
                    "warning", "stale_command",
                    f"no command for {self.cfg.command_timeout_s * 1e3:.0f} ms: decelerating to rest "
                    f"(stopping distance up to {np.max(stop):.4f} rad)",
                )
            self.arm.step(dt)

    def publish(self) -> None:
        with self.lock:
            self._publish(self.node.clock.now_ns())

    def _publish(self, now: int) -> None:
        arm = self.arm
        self.publish_state(m.RobotState(
            seq=self.seq, stamp_ns=now, q=arm.q.tolist(), dq=arm.dq.tolist(), status=self.status,
            owner=self.active, backend=arm.backend, command_mode=arm.mode,  # type: ignore[arg-type]
            reflex_seq=self.reflex_seq, accepted=self.accepted, accepted_ns=self.accepted_ns,
            rejected=self.rejected, clipped=arm.clipped,
        ))
        self.seq += 1


def run(profile: Profile, args: argparse.Namespace) -> int:
    if args.active:
        profile.bridge.active_planner = args.active
    cfg = profile.bridge
    with Node("bridge", profile.robot.name, profile.zenoh, listen_slot="bridge") as node:
        node.install_signal_handlers()
        bridge = Bridge(profile, node)
        node.subscribe(keys.ROBOT_COMMAND, bridge.on_command)
        log.info("simulated arm at %.0f Hz, following planner %r", cfg.rate_hz, bridge.active)
        rate = Rate(cfg.rate_hz, "bridge")
        dt = 1.0 / cfg.rate_hz
        state_every = max(1, round(cfg.rate_hz / cfg.state_rate_hz))
        try:
            while rate.sleep(node.stop):
                bridge.tick(dt)
                if rate.ticks % state_every == 0:
                    bridge.publish()
        finally:
            with bridge.lock:
                bridge.arm.stop()
                bridge.status = "stopped"
            log.info(rate.summary())
            log.info("%d commands rejected, %d clipped", bridge.rejected, bridge.arm.clipped)
    return 0
