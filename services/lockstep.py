"""The pipeline's cores chained in one process, on simulated time, in lockstep.

Skin samples go through the gain estimator, the planner and the bridge with
its simulated arm exactly as the services chain them over Zenoh, but as
direct calls, each control cycle of 2 ms one step of simulated time:

- a skin sample is delivered at its own stamp: gain estimator, then the
  planner's event path (a reflex's first command reaches the bridge at once);
- every control cycle the planner steps, the bridge takes its command and
  steps the arm;
- the robot state goes back to the planner at ``state_rate_hz``, the planner
  status is published on every transition and at ``status_rate_hz``.

Nothing here reads a clock, so a run is deterministic: the same skin samples
give the same messages, bit for bit. It is what ``nwr replay --fast`` runs
(as fast as the cores go) and the lower bound of ``nwr bench``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.robot import RobotModel, load_description
from nwr.services.bridge.backend import SimBackend
from nwr.services.bridge.core import BridgeCore
from nwr.services.bridge.main import envelope_for
from nwr.services.gain.core import GainEstimator
from nwr.services.planner.core import Planner

Emit = Callable[[str, Any, int], None]  # (relative key, message, simulated time ns)


@dataclass
class LockstepReport:
    skin_samples: int
    cycles: int
    messages: int
    simulated_s: float


class Lockstep:
    """gain -> planner -> bridge (simulated arm), stepped on simulated time."""

    def __init__(self, profile: Profile, *, strategy: str | None = None, name: str | None = None) -> None:
        cfg = msgspec.structs.replace(profile.planner, strategy=strategy or profile.planner.strategy,
                                      name=name or strategy or profile.planner.name)
        self.profile = profile
        desc = load_description(profile.robot.description or None)
        self.gain = GainEstimator(profile.gain, desc.pads)
        self.planner = Planner(cfg, desc, RobotModel(desc))
        env, q0, n_pads = envelope_for(profile)
        self.period_ns = round(1e9 / profile.bridge.rate_hz)
        self.bridge = BridgeCore(env, q0, 0, active=cfg.name, n_pads=n_pads,
                                 command_timeout_s=profile.bridge.command_timeout_s,
                                 skin_timeout_s=profile.bridge.skin_timeout_s,
                                 seq_restart_gap=profile.bridge.seq_restart_gap,
                                 period_s=1.0 / profile.bridge.rate_hz)
        self.backend = SimBackend(env, 1.0 / profile.bridge.rate_hz, q0)
        self.backend.connect()
        self.status_key = keys.planner_status(cfg.name)
        self.decision_key = keys.planner_decision(cfg.name)
        self.state_every = max(1, round(profile.bridge.rate_hz / profile.bridge.state_rate_hz))
        self.status_every = max(1, round(cfg.rate_hz / cfg.status_rate_hz))
        self.state_seq = 0
        self.cycles = 0
        self.messages = 0

    def _command(self, cmd: m.Command | None, t: int, emit: Emit) -> None:
        if cmd is None:
            return
        emit(keys.ROBOT_COMMAND, cmd, t)
        self.messages += 1
        verdict = self.bridge.on_command(cmd, t)
        if verdict.onset:  # as the bridge process: the onset goes to the arm at once
            self.backend.send_action(self.bridge.step(t))
            self._state(t, emit)

    def _state(self, t: int, emit: Emit) -> None:
        obs = self.backend.get_observation()
        state = self.bridge.state(self.state_seq, t, obs.q, obs.dq, self.backend.name)
        self.state_seq += 1
        emit(keys.ROBOT_STATE, state, t)
        self.messages += 1
        self.planner.on_state(m.as_array(state.q), state.owner == self.planner.name and state.status == "ok",
                              dq=m.as_array(state.dq), owner=state.owner, now_ns=t)

    def _status(self, t: int, emit: Emit) -> None:
        emit(self.status_key, self.planner.status(t), t)
        self.messages += 1

    def deliver(self, sample: m.SkinPressure, t: int, emit: Emit) -> m.Command | None:
        """One skin sample at simulated time ``t``, through the event path; the command it caused."""
        self.bridge.on_skin(sample, t)
        pain = self.gain.process(sample, t)
        emit(keys.SKIN_PAIN, pain, t)
        self.messages += 1
        self.bridge.on_pain(pain, t)
        command = self.planner.on_pain(pain, t)
        self._command(command, t, emit)
        emit(self.decision_key, self.planner.decision(pain, t, t, command), t)
        self.messages += 1
        if command is not None:
            self.planner.assess()
        if self.planner.changed:
            self._status(t, emit)
        return command

    def run(self, samples: Iterable[m.SkinPressure], emit: Emit, *, settle_s: float = 2.0) -> LockstepReport:
        """Feed skin samples (in stamp order) through the chain; ``emit`` gets every message."""
        pending = sorted(samples, key=lambda s: s.stamp_ns)
        if not pending:
            return LockstepReport(0, 0, 0, 0.0)
        t0 = pending[0].stamp_ns - self.period_ns
        end = pending[-1].stamp_ns + round(settle_s * 1e9)
        self.bridge.on_planner_token(self.planner.name, True, t0)
        self.bridge.last_step_ns = t0
        i = 0
        t = t0
        self._state(t, emit)
        while t < end:
            t += self.period_ns
            while i < len(pending) and pending[i].stamp_ns <= t:
                self.deliver(pending[i], t, emit)
                i += 1
            self._command(self.planner.step(t), t, emit)
            self.backend.send_action(self.bridge.step(t))
            self.cycles += 1
            if self.cycles % self.state_every == 0 or self.bridge.publish_now:
                self._state(t, emit)
            if self.planner.changed or self.cycles % self.status_every == 0:
                self._status(t, emit)
            self.bridge.drain_events()
        return LockstepReport(i, self.cycles, self.messages, (t - t0) / 1e9)

