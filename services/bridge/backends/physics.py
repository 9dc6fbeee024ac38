"""The physics world's arm (``bridge.backend = "physics"``): the bridge hosts a MuJoCo world and drives its arm.

The world (:class:`nwr.services.worlds.hosted.HostedWorld`) holds the arm,
its skin and the people touching it. Each control cycle the bridge steps it
at its fixed step up to the cycle's time with the last setpoint (the
servos track position and speed) and reads the arm back as the measured
state; the world's skin samples go out on ``world/skin`` (the gateway's
``physics`` source turns them into ``skin/pressure``), its body parts'
contact figures on ``world/contacts``. The touch script's touches reach the
world as messages (``skin/touch``, an input of the bridge's wiring), so the
bridge's journal holds every input of the world and ``nwr verify`` re-runs
it bit for bit.

A world that diverges (:class:`~nwr.services.worlds.physics.WorldUnstable`)
stays stopped: the backend reports a protective stop with the world's
diagnostic, the arm frozen where its last good step left it (the bridge
holds it, as it does for a real controller's protective stop).

Its settings are ``[bridge.physics]`` (:class:`~nwr.services.worlds.physics.PhysicsSettings`).
No field is guarded: nothing in this world is beside a person.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

import numpy as np

from nwr.common import messages as m
from nwr.common.config import BridgeSection, Profile
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotDescription
from nwr.common.taxels import TaxelSkin
from nwr.services.bridge.backend import Backend, Observation
from nwr.services.bridge.core import Setpoint
from nwr.services.bridge.envelope import Envelope
from nwr.services.worlds.settings import PhysicsSettings, WorldUnstable, check_taxel_rate

log = logging.getLogger(__name__)

NAME = "physics"
REAL_ARM = False
Settings = PhysicsSettings  # [bridge.physics]
# How often a world that falls behind the bridge's clock is warned about, ns of bridge time.
WARN_EVERY_NS = 5_000_000_000


def check_settings(settings: PhysicsSettings, profile: Profile, desc: RobotDescription) -> None:
    """The world's step divides the bridge's cycle (a whole number of steps per cycle: an even command rate); a
    taxel skin's rate is at most the step rate."""
    period_ns = round(1e9 / profile.bridge.rate_hz)
    step_ns = round(settings.timestep_s * 1e9)
    if period_ns % step_ns:
        raise ConfigError(f"bridge.physics.timestep_s = {settings.timestep_s} s does not divide the bridge's cycle "
                          f"of {period_ns / 1e6:g} ms (bridge.rate_hz = {profile.bridge.rate_hz:g}): choose a "
                          "divisor, e.g. 0.001")
    if profile.robot.skin == "taxels":
        check_taxel_rate(settings)


def make(cfg: BridgeSection, env: Envelope, q0: np.ndarray, args: argparse.Namespace,
         desc: RobotDescription) -> Backend:
    from nwr.services.bridge.backends import KIND

    return PhysicsBackend(env, 1.0 / cfg.rate_hz, q0, desc, KIND.settings(cfg, NAME, PhysicsSettings))


class PhysicsBackend(Backend):
    """The arm of a physics world the bridge hosts."""

    name = NAME
    touched = True
    # The servos follow a moving setpoint a few ms behind (kv / kp = servo_damping_s).
    lag_s = 0.0

    def __init__(self, env: Envelope, dt: float, q0: np.ndarray, desc: RobotDescription,
                 settings: PhysicsSettings) -> None:
        super().__init__(env, dt)
        from nwr.services.worlds.hosted import HostedWorld  # MuJoCo: only a bridge that hosts the world loads it

        self.hosted = HostedWorld(desc, settings, np.asarray(q0, dtype=float))
        self.lag_s = settings.servo_damping_s
        self.q_command = np.asarray(q0, dtype=float).copy()
        self.dq_command = np.zeros_like(self.q_command)
        self.streaming = False  # the last setpoint was a velocity one: q_command integrates the stream
        self.connected = False
        self.fault: m.RobotStatus | None = None
        self.detail = ""
        self.warned_ns = -WARN_EVERY_NS

    def connect(self) -> None:
        self.connected = True

    def disconnect(self) -> None:
        self.connected = False

    def get_observation(self) -> Observation:
        arm = self.hosted.world.arm()
        if self.fault is not None:
            return Observation(arm.q.copy(), np.zeros_like(arm.q), self.fault, self.detail)
        return Observation(arm.q.copy(), arm.dq.copy())

    def _send(self, setpoint: Setpoint) -> None:
        # A velocity stream is integrated into the servos' own position reference, as a real arm's controller
        # does (UR's speedj): the bridge's velocity setpoint follows the measured pose, which alone would leave
        # the arm held by its velocity servo only, so that a push (a finger, the arm's own dynamics) drifts it
        # away from what the planner commanded for as long as the stream lasts.
        if setpoint.mode == "velocity" and self.streaming:
            self.q_command = np.clip(self.q_command + setpoint.dq * (setpoint.h or self.dt), self.env.q_min,
                                     self.env.q_max)
        else:
            self.q_command = setpoint.q.copy()
        self.streaming = setpoint.mode == "velocity"
        self.dq_command = setpoint.dq.copy() if setpoint.mode != "hold" else np.zeros_like(self.q_command)

    def advance(self, now_ns: int) -> list[tuple[str, Any]]:
        if self.fault is not None:
            return []
        lost = self.hosted.lost_ns
        try:
            out = self.hosted.advance(now_ns, self.q_command, self.dq_command)
        except WorldUnstable as exc:
            self.fault, self.detail = "protective_stop", f"physics world stopped: {exc}"
            return []
        if self.hosted.lost_ns > lost and now_ns - self.warned_ns >= WARN_EVERY_NS:
            self.warned_ns = now_ns
            log.warning("the physics world is %.3f s behind the bridge's clock: late cycles caught up at most "
                        "%.0f ms of world time each (the machine is too slow or too busy for it in real time)",
                        self.hosted.lost_ns / 1e9, self.hosted.max_steps * self.hosted.step_ns / 1e6)
        return out

    def use_skin(self, skin: TaxelSkin) -> None:
        self.hosted.use_taxels(skin)

    def on_touch(self, touch: m.SkinTouch, now_ns: int) -> str | None:
        try:
            self.hosted.touch(touch, now_ns)
        except ConfigError as exc:
            return str(exc)
        return None
