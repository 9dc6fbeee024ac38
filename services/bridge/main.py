"""Robot bridge process: robot/command/<active> + skin/pressure + the planner's liveliness -> the arm -> robot/state.

A thin adapter: :class:`~nwr.services.bridge.core.BridgeCore` decides, a
backend (:class:`~nwr.services.bridge.backend.SimBackend` or
:class:`~nwr.services.bridge.ur_rtde.URRtdeBackend`) moves the arm. The
command callback and the control loop share both under one lock.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time

import numpy as np
import zenoh

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import BridgeSection, Profile
from nwr.common.errors import ConfigError
from nwr.common.node import Node
from nwr.common.pacing import realtime
from nwr.common.robot import load_description
from nwr.services.bridge.backend import Backend, SimBackend
from nwr.services.bridge.core import BridgeCore, Envelope, Event, at_rest, make_envelope
from nwr.services.planner.main import planner_service

PLANNER_PREFIX = planner_service("")
log = logging.getLogger(__name__)

CONFIRM_FLAG = "--i-am-next-to-the-robot"
# After SIGTERM, the controlled stop may take at most this long beyond its own duration, s.
SHUTDOWN_SLACK_S = 0.5
# A command's handler waits for the GIL while the control loop runs Python:
# switch at least this often, s (Python's default is 5 ms).
SWITCH_INTERVAL_S = 0.0005


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--active", help="the planner whose commands move the arm (overrides bridge.active_planner)")
    parser.add_argument("--backend", choices=["sim", "ur_rtde"], help="overrides bridge.backend")
    parser.add_argument("--robot-ip", default="", help="IP address of the UR controller (ur_rtde backend only)")
    parser.add_argument(CONFIRM_FLAG, dest="confirmed", action="store_true",
                        help="confirm that a person watches the real arm with the emergency stop at hand "
                             "(required by the ur_rtde backend)")
    parser.add_argument("--print-envelope", action="store_true", help="print the enforced envelope and exit")


def envelope_for(profile: Profile) -> tuple[Envelope, np.ndarray, int]:
    """The envelope, the initial pose and the number of pads, from the profile."""
    cfg = profile.bridge
    desc = load_description(profile.robot.description or None)
    env = make_envelope(
        desc.joints,
        {"q_min": desc.q_min, "q_max": desc.q_max, "v_max": desc.v_max, "a_max": desc.a_max, "j_max": desc.j_max},
        speed_fraction=cfg.speed_fraction, acceleration_fraction=cfg.acceleration_fraction,
        jerk_fraction=cfg.jerk_fraction,
        tighter={"q_min": cfg.q_min, "q_max": cfg.q_max, "v_max": cfg.v_max, "a_max": cfg.a_max, "j_max": cfg.j_max},
        position_jump_rad=cfg.position_jump_rad,
    )
    q0 = np.asarray(cfg.initial_q, dtype=float) if cfg.initial_q else np.asarray(desc.home, dtype=float)
    if q0.shape != (env.n,):
        raise ConfigError(f"bridge.initial_q has {q0.size} joints, the robot has {env.n}: give {env.n} or none")
    return env, q0, len(desc.pads)


def make_backend(cfg: BridgeSection, env: Envelope, q0: np.ndarray, args: argparse.Namespace) -> Backend:
    dt = 1.0 / cfg.rate_hz
    if cfg.backend == "sim":
        return SimBackend(env, dt, q0)
    if not getattr(args, "robot_ip", ""):
        raise ConfigError("the ur_rtde backend moves a real arm: give the controller's address with --robot-ip")
    if not getattr(args, "confirmed", False):
        raise ConfigError(
            f"the ur_rtde backend moves a real arm at {args.robot_ip}: add {CONFIRM_FLAG} once a person watches it "
            "with the emergency stop at hand (docs/bridge.md)"
        )
    from nwr.services.bridge.ur_rtde import URRtdeBackend

    return URRtdeBackend(env, dt, args.robot_ip, lookahead_s=cfg.servo_lookahead_s, gain=cfg.servo_gain,
                         reconnect_min_s=cfg.reconnect_min_s, reconnect_max_s=cfg.reconnect_max_s,
                         watchdog_hz=cfg.watchdog_hz)


class Bridge:
    """Wires the core and a backend to the node; every entry point takes the lock."""

    def __init__(self, profile: Profile, node: Node, backend: Backend, env: Envelope, q0: np.ndarray,
                 n_pads: int) -> None:
        cfg = profile.bridge
        self.cfg = cfg
        self.node = node
        self.backend = backend
        self.lock = threading.Lock()
        self.core = BridgeCore(
            env, q0, node.clock.now_ns(), active=cfg.active_planner, n_pads=n_pads,
            command_timeout_s=cfg.command_timeout_s, skin_timeout_s=cfg.skin_timeout_s,
            seq_restart_gap=cfg.seq_restart_gap, period_s=1.0 / cfg.rate_hz,
        )
        self.seq = 0
        self.publish_state = node.publisher(keys.ROBOT_STATE)

    # -- callbacks (Zenoh's threads) -------------------------------------------------
    def on_command(self, relative: str, cmd: m.Command) -> None:
        with self.lock:
            now = self.node.clock.now_ns()
            verdict = self.core.on_command(cmd, now, publisher=keys.command_publisher(relative))
            if verdict.onset:
                # The first command of a reflex goes to the backend now, not at
                # the next cycle, and its acceptance is published at once.
                self._cycle(now)
                self._publish(now)
            elif self.core.publish_now:
                self._publish(now)
            events = self.core.drain_events()
        self._report(events)

    def on_skin(self, pressure: m.SkinPressure) -> None:
        with self.lock:
            self.core.on_skin(pressure, self.node.clock.now_ns())
            events = self.core.drain_events()
        self._report(events)

    def on_pain(self, pain: m.SkinPain) -> None:
        with self.lock:
            self.core.on_pain(pain, self.node.clock.now_ns())
            events = self.core.drain_events()
        self._report(events)

    def on_liveliness(self, sample: zenoh.Sample) -> None:
        """Any planner's token (alive/planner-<name>) appearing or vanishing."""
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        name = service.removeprefix(PLANNER_PREFIX)
        with self.lock:
            self.core.on_planner_token(name, sample.kind == zenoh.SampleKind.PUT, self.node.clock.now_ns())
            events = self.core.drain_events()
        self._report(events)

    def on_switch(self, request: m.SwitchRequest) -> None:
        with self.lock:
            now = self.node.clock.now_ns()
            self.core.request_switch(request, now)
            if self.core.publish_now:
                self._publish(now)  # the planners learn who is active at once
            events = self.core.drain_events()
        self._report(events)

    # -- the control loop --------------------------------------------------------------
    def tick(self, publish: bool) -> None:
        with self.lock:
            now = self.node.clock.now_ns()
            obs = self.backend.get_observation()
            if obs.fault != self.core.fault:
                self.core.on_fault(obs.fault, obs.detail, obs.q, now)
                self.backend.resync(obs.q)
            self.core.observe(obs.q)
            self._cycle(now)
            if publish or self.core.publish_now:
                self._publish(now)
            events = self.core.drain_events()
        self._report(events)

    def _cycle(self, now: int) -> None:
        setpoint = self.core.step(now)
        if self.core.fault is None:
            self.backend.send_action(setpoint)

    def _publish(self, now: int) -> None:
        obs = self.backend.get_observation()
        state = self.core.state(self.seq, now, obs.q, obs.dq, self.backend.name)
        state.clipped += self.backend.guarded
        self.publish_state(state)
        self.seq += 1

    def at_rest(self) -> bool:
        with self.lock:
            return self.core.stop is None or self.core.stop.done or at_rest(self.core.dq)

    def _report(self, events: list[Event]) -> None:
        for event in events:
            self.node.diag(event.level, event.code, event.message)


def run(profile: Profile, args: argparse.Namespace) -> int:
    cfg = profile.bridge
    if getattr(args, "active", None):
        cfg.active_planner = args.active
    if getattr(args, "backend", None):
        cfg.backend = args.backend
    env, q0, n_pads = envelope_for(profile)
    if getattr(args, "print_envelope", False):
        print(env.describe())
        return 0
    backend = make_backend(cfg, env, q0, args)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    realtime(cfg.realtime_priority, "bridge")  # before the session: Zenoh's threads inherit it
    log.info("%s backend; the envelope it enforces:\n%s", backend.name, env.describe())
    backend.connect()
    if backend.name != "sim":
        q0 = backend.get_observation().q
    try:
        with Node("bridge", profile.robot.name, profile.zenoh, listen_slot="bridge") as node:
            node.install_signal_handlers()
            bridge = Bridge(profile, node, backend, env, q0, n_pads)
            # Every handler on Zenoh's network thread (direct: no hand-off to a
            # Python thread per command); the bridge subscribes to nothing it publishes.
            node.subscribe(keys.ROBOT_COMMANDS, bridge.on_command, keyed=True, direct=True)
            node.subscribe(keys.SKIN_PRESSURE, bridge.on_skin, direct=True)
            node.subscribe(keys.SKIN_PAIN, bridge.on_pain, direct=True)
            node.subscribe(keys.CONTROL_ACTIVE, bridge.on_switch, direct=True)
            tokens = keys.key(profile.robot.name, keys.alive(PLANNER_PREFIX + "$*"))
            watcher = node.session.liveliness().declare_subscriber(tokens, bridge.on_liveliness, history=True)
            log.info("following planner %r (tokens %s) at %.0f Hz; command timeout %.0f ms, skin timeout %.0f ms",
                     cfg.active_planner, tokens, cfg.rate_hz, cfg.command_timeout_s * 1e3,
                     cfg.skin_timeout_s * 1e3)
            pacer = backend.pacer(cfg.rate_hz)
            state_every = max(1, round(cfg.rate_hz / cfg.state_rate_hz))
            try:
                while pacer.sleep(node.stop):
                    bridge.tick(pacer.ticks % state_every == 0)
            finally:
                # One shutdown path: a controlled stop, then the robot released.
                with bridge.lock:
                    bridge.core.request_stop(node.clock.now_ns(), "bridge shutting down")
                    deadline = time.monotonic() + bridge.core.stop_time_s + SHUTDOWN_SLACK_S
                while not bridge.at_rest() and time.monotonic() < deadline:
                    pacer.sleep(None)
                    bridge.tick(pacer.ticks % state_every == 0)
                bridge.tick(True)
                watcher.undeclare()
                bridge.core.release()
                log.info(pacer.summary())
                log.info("%d commands rejected, %d clipped; stop distance %s rad", bridge.core.rejected,
                         bridge.core.clipped, np.round(bridge.core.stop_distance, 4).tolist())
    finally:
        backend.disconnect()
    return 0
