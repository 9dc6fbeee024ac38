"""Robot bridge process: robot/command/<active> + skin/pressure + the planner's liveliness -> the arm -> robot/state.

A thin adapter around :class:`~nwr.services.bridge.wiring.BridgeWiring`
(the core, a backend and the call order): Zenoh callbacks and the control
loop call it under one lock.
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
from nwr.common.config import BridgeSection, Profile
from nwr.common.door import Door
from nwr.common.errors import ConfigError
from nwr.common.node import Node
from nwr.common.pacing import realtime
from nwr.common.robot import RobotDescription, load_description
from nwr.services.bridge import backends
from nwr.services.bridge.backend import Backend
from nwr.services.bridge.envelope import Envelope
from nwr.services.bridge.wiring import SERVICE, BridgeWiring, envelope_for
from nwr.services.wiring import subscribe

log = logging.getLogger(__name__)

CONFIRM_FLAG = "--i-am-next-to-the-robot"
# After SIGTERM, the controlled stop may take at most this long beyond its own duration, s.
SHUTDOWN_SLACK_S = 0.5
# A command's handler waits for the GIL while the control loop runs Python:
# switch at least this often, s (Python's default is 5 ms).
SWITCH_INTERVAL_S = 0.0005


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--active", help="the planner whose commands move the arm (overrides bridge.active_planner)")
    add_arm_arguments(parser)
    parser.add_argument("--print-envelope", action="store_true", help="print the enforced envelope and exit")


def add_arm_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The backend, the robot's address and the confirmation (the bridge's, and `nwr up` / `nwr demo` pass them on)."""
    parser.add_argument("--backend", choices=backends.names(),
                        help="the bridge's backend, a module of services/bridge/backends/ (overrides bridge.backend)")
    parser.add_argument("--robot-ip", default="", help="IP address of the arm's controller (a real arm's backend only)")
    parser.add_argument(CONFIRM_FLAG, dest="confirmed", action="store_true",
                        help="confirm that a person watches the real arm with the emergency stop at hand "
                             "(required by a real arm's backend, such as ur_rtde)")


def check_arm_flags(backend: str, robot_ip: str, confirmed: bool) -> None:
    """A real arm needs its controller's address and a person's confirmation; the simulated one neither."""
    if not backends.plugin(backend).REAL_ARM:
        if robot_ip or confirmed:
            raise ConfigError(f"--robot-ip and {CONFIRM_FLAG} are for a real arm's backend, such as ur_rtde "
                              "(add --backend ur_rtde or set bridge.backend)")
        return
    if not robot_ip:
        raise ConfigError(f"the {backend} backend moves a real arm: give the controller's address with --robot-ip")
    if not confirmed:
        raise ConfigError(f"the {backend} backend moves a real arm at {robot_ip}: add {CONFIRM_FLAG} once a person "
                          "watches it with the emergency stop at hand (docs/bridge.md)")


def make_backend(cfg: BridgeSection, env: Envelope, q0: np.ndarray, args: argparse.Namespace,
                 desc: RobotDescription | None = None) -> Backend:
    """The backend ``cfg`` names, for the robot ``desc`` (None: the packaged one)."""
    check_arm_flags(cfg.backend, getattr(args, "robot_ip", ""), getattr(args, "confirmed", False))
    backend: Backend = backends.plugin(cfg.backend).make(cfg, env, q0, args, desc or load_description(None))
    return backend


class PipelinePlanners:
    """Which planners the bridge may follow or switch to: those of its own pipeline.

    A planner's liveliness token (``alive/planner-<name>``) counts only while the planner also holds an owner
    token (``owner/planner-<name>/<instance>/...``, which every planner declares before its liveliness) of the
    bridge's pipeline instance, or of a planner started alone (``nwr run planner`` beside ``nwr up``). A token
    alone, or a planner of another pipeline on the same robot's keys, is reported and never followed. A bridge
    started alone follows every planner token, as before instances: its own owner token kept it from starting
    beside another pipeline.
    """

    def __init__(self, instance: str) -> None:
        self.instance = instance
        self.alive: set[str] = set()
        self.owners: dict[str, set[str]] = {}  # planner name -> its owner tokens of this pipeline (relative keys)
        self.followed: set[str] = set()  # what the wiring was told is alive

    def _ours(self, name: str) -> bool:
        return self.instance == keys.NO_INSTANCE or bool(self.owners.get(name))

    def _change(self, name: str) -> tuple[str, bool] | None:
        now = name in self.alive and self._ours(name)
        if now == (name in self.followed):
            return None
        (self.followed.add if now else self.followed.discard)(name)
        return name, now

    def on_alive(self, name: str, present: bool) -> tuple[str, bool] | None:
        """A planner's liveliness token; the change the wiring must hear (name, alive), if any."""
        (self.alive.add if present else self.alive.discard)(name)
        return self._change(name)

    def on_owner(self, relative: str, present: bool) -> tuple[str, bool] | None:
        """An owner token (its key relative to the robot's prefix); the change the wiring must hear, if any."""
        owner = keys.parse_owner(relative)
        if owner is None or not owner.service.startswith(keys.PLANNER_SERVICE_PREFIX):
            return None
        if owner.instance not in (self.instance, keys.NO_INSTANCE):
            return None
        name = owner.service.removeprefix(keys.PLANNER_SERVICE_PREFIX)
        tokens = self.owners.setdefault(name, set())
        (tokens.add if present else tokens.discard)(relative)
        return self._change(name)

    def strangers(self) -> list[str]:
        """The planners whose liveliness token is there but that hold no owner token of this pipeline."""
        return sorted(self.alive - self.followed)


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
    backend = make_backend(cfg, env, q0, args, load_description(profile.robot.description or None))
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    realtime(cfg.realtime_priority, "bridge")  # before the session: Zenoh's threads inherit it
    log.info("%s backend; the envelope it enforces:\n%s", backend.name, env.describe())
    backend.connect()  # a real arm's starting pose is read by the wiring
    lock = threading.Lock()  # the handlers, the control loop and the journal's batches
    try:
        with Node(SERVICE, profile.robot.name, profile.zenoh, listen_slot="bridge", token=False,
                  door=Door.of(profile), exclusive=True) as node:
            node.install_signal_handlers()
            bridge = node.wire(BridgeWiring, profile, lock, backend=backend)

            planners = PipelinePlanners(node.instance)

            def follow(change: tuple[str, bool] | None) -> None:
                if change is not None:
                    bridge.on_token(*change)
                for name in planners.strangers():
                    node.diag("warning", "planner_not_of_pipeline",
                              f"planner {name!r} announces itself (alive/planner-{name}) but holds no owner token "
                              f"of this pipeline ({node.instance}): it is neither followed nor switched to",
                              every_s=10.0)

            def on_liveliness(sample: zenoh.Sample) -> None:
                """Any planner's token (alive/planner-<name>) appearing or vanishing."""
                name = str(sample.key_expr).rsplit("/", 1)[-1].removeprefix(keys.PLANNER_SERVICE_PREFIX)
                with lock:
                    follow(planners.on_alive(name, sample.kind == zenoh.SampleKind.PUT))

            def on_owner(sample: zenoh.Sample) -> None:
                """A planner's owner token (owner/planner-<name>/<instance>/...) appearing or vanishing."""
                relative = keys.relative_key(profile.robot.name, str(sample.key_expr))
                with lock:
                    follow(planners.on_owner(relative, sample.kind == zenoh.SampleKind.PUT))

            # Every handler on Zenoh's network thread (direct: no hand-off to a
            # Python thread per command); the bridge subscribes to nothing it publishes.
            subscribe(node, bridge, lock)
            # Owner tokens first: a planner declares its owner token before its liveliness.
            owners = node.session.liveliness().declare_subscriber(
                keys.key(profile.robot.name, f"owner/{keys.PLANNER_SERVICE_PREFIX}$*/**"), on_owner, history=True)
            tokens = keys.key(profile.robot.name, keys.alive(keys.PLANNER_SERVICE_PREFIX + "$*"))
            watcher = node.session.liveliness().declare_subscriber(tokens, on_liveliness, history=True)
            node.declare_token()  # alive once subscribed
            log.info("following planner %r (tokens %s) at %.0f Hz; command timeout %.0f ms, skin timeout %.0f ms",
                     cfg.active_planner, tokens, cfg.rate_hz, cfg.command_timeout_s * 1e3,
                     cfg.skin_timeout_s * 1e3)
            pacer = backend.pacer(cfg.rate_hz)
            try:
                while pacer.sleep(node.stop):
                    with lock:
                        bridge.tick()
                        pacer.starting = bridge.core.last_skin_ns is None  # start-up lasts until the skin flows
            finally:
                # One shutdown path: a controlled stop, then the robot released.
                with lock:
                    deadline = time.monotonic() + bridge.stop("bridge shutting down") + SHUTDOWN_SLACK_S
                while time.monotonic() < deadline:
                    with lock:
                        if bridge.at_rest():
                            break
                    pacer.sleep(None)
                    with lock:
                        bridge.tick()
                if not backend.wind_down(SHUTDOWN_SLACK_S):  # the stream's stop answered before the last state
                    log.warning("the robot had not answered the bridge's last commands within %.1f s of its stop",
                                SHUTDOWN_SLACK_S)
                with lock:
                    bridge.tick(publish=True)
                watcher.undeclare()
                owners.undeclare()
                bridge.core.release()
                log.info(pacer.summary())
                core = bridge.core
                log.info("%d commands rejected, %d held to a limit (%d of them in withdrawals or rejoins); "
                         "stop distance %s rad", core.rejected, core.clipped, core.clipped_expected,
                         np.round(core.tracker.stop_distance, 4).tolist())
    finally:
        backend.disconnect()
    return 0
