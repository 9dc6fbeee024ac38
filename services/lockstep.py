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

Where the skin samples come from (a :class:`SkinSource`):

- :class:`RecordedSkin`: a recording's samples, as recorded (open loop);
- :class:`ResimulatedSkin`: a simulated session's samples with their touches
  re-simulated against this run's arm (``nwr replay --fast --resimulate``,
  :class:`nwr.services.gateway.core.Resimulator`);
- :class:`SimulatedSkin`: the simulated skin itself on a touch script, open
  or closed loop against this run's arm (``nwr demo --fast``).

A source that makes samples sees the arm's pose at the control cycle the
sample is delivered in (at most one cycle after its stamp) and emits what it
makes (``skin/pressure``, ``skin/touch``) at its own stamp.

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
from nwr.common.config import Profile, TouchScript
from nwr.common.robot import RobotModel, load_description
from nwr.services.bridge.backend import SimBackend
from nwr.services.bridge.core import BridgeCore
from nwr.services.bridge.main import envelope_for
from nwr.services.gain.core import GainEstimator
from nwr.services.gateway.core import Gateway, Resimulator, SimSkin, touch_message
from nwr.services.planner.core import Planner

Emit = Callable[[str, Any, int], None]  # (relative key, message, simulated time ns)


class SkinSource:
    """The skin samples of a lockstep run, in stamp order."""

    def __len__(self) -> int:
        raise NotImplementedError

    def stamp(self, i: int) -> int:
        """Stamp of the ``i``-th sample, ns."""
        raise NotImplementedError

    def take(self, i: int, q: np.ndarray, emit: Emit) -> m.SkinPressure:
        """The ``i``-th sample, made with the arm at ``q``; emits what it makes."""
        raise NotImplementedError


class RecordedSkin(SkinSource):
    """Recorded samples, delivered as they are (open loop); the caller has them already, nothing is emitted."""

    def __init__(self, samples: Iterable[m.SkinPressure]) -> None:
        self.samples = sorted(samples, key=lambda s: s.stamp_ns)

    def __len__(self) -> int:
        return len(self.samples)

    def stamp(self, i: int) -> int:
        return self.samples[i].stamp_ns

    def take(self, i: int, q: np.ndarray, emit: Emit) -> m.SkinPressure:
        return self.samples[i]


class ResimulatedSkin(RecordedSkin):
    """Recorded samples of the simulated skin, their touches re-simulated against the run's arm."""

    def __init__(self, samples: Iterable[m.SkinPressure], resimulator: Resimulator, model: RobotModel) -> None:
        super().__init__(samples)
        self.resimulator = resimulator
        self.model = model
        self.touch_seq = 0

    def take(self, i: int, q: np.ndarray, emit: Emit) -> m.SkinPressure:
        res = self.resimulator
        sample, started = res.apply(self.samples[i], self.model.pad_points(q), self.model.pad_normals(q))
        for touch in started:  # the ground truth of this run: the touches met the pads where this arm had them
            emit(keys.SKIN_TOUCH, touch_message(self.touch_seq, sample.stamp_ns, res.origin_ns, touch,
                                                self.model.desc.pads[touch.pad].name, res.touches, q,
                                                sample.stamp_ns), sample.stamp_ns)
            self.touch_seq += 1
        emit(keys.SKIN_PRESSURE, sample, sample.stamp_ns)
        return sample


class SimulatedSkin(SkinSource):
    """The simulated skin on a touch script at ``gateway.rate_hz``, as the gateway process runs it.

    Its script clock starts at ``origin_ns``; the samples are stamped every
    sample period from one period after it until the script's end (the
    sample at or after ``duration_s`` is the last, as ``--exit-at-end``).
    """

    def __init__(self, profile: Profile, script: TouchScript, model: RobotModel, origin_ns: int = 10**9) -> None:
        cfg = profile.gateway
        self.pads = model.desc.pads
        self.sim = SimSkin(cfg.sim, self.pads, script)
        self.gateway = Gateway(cfg, len(self.pads), source="sim")
        self.model = model
        self.origin_ns = origin_ns
        period = 1e9 / cfg.rate_hz
        self.stamps: list[int] = []
        k = 1
        while True:
            self.stamps.append(origin_ns + round(k * period))
            if (self.stamps[-1] - origin_ns) / 1e9 >= script.duration_s:
                break
            k += 1
        self.touch_seq = 0

    def __len__(self) -> int:
        return len(self.stamps)

    def stamp(self, i: int) -> int:
        return self.stamps[i]

    def take(self, i: int, q: np.ndarray, emit: Emit) -> m.SkinPressure:
        now = self.stamps[i]
        t = (now - self.origin_ns) / 1e9
        points, normals = self.model.pad_points(q), self.model.pad_normals(q)
        for started in self.sim.start(t, points, normals):
            touch = touch_message(self.touch_seq, now, self.origin_ns, started, self.pads[started.pad].name,
                                  self.sim.touches, q, now)
            self.touch_seq += 1
            emit(keys.SKIN_TOUCH, touch, now)
        sample, _ = self.gateway.process(t, now, self.sim.sample(t, points), self.sim.touch_hpa)
        emit(keys.SKIN_PRESSURE, sample, now)
        return sample


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
        emit(keys.robot_command(cmd.owner), cmd, t)
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

    def run(self, samples: Iterable[m.SkinPressure] | SkinSource, emit: Emit, *,
            settle_s: float = 2.0, start_ns: int | None = None) -> LockstepReport:
        """Feed skin samples (in stamp order) through the chain; ``emit`` gets every message
        the chain makes (and those a source makes, but not recorded samples given as they are).

        The chain's first control cycle (the planner's first command, the
        start of its task) is at ``start_ns``, by default at the first
        sample's stamp; a replay gives the original pipeline's, so that the
        task is at the same phase when each touch comes.
        """
        source = samples if isinstance(samples, SkinSource) else RecordedSkin(samples)
        n = len(source)
        if not n:
            return LockstepReport(0, 0, 0, 0.0)
        t0 = (source.stamp(0) if start_ns is None else min(start_ns, source.stamp(0))) - self.period_ns
        end = source.stamp(n - 1) + round(settle_s * 1e9)
        self.bridge.on_planner_token(self.planner.name, True, t0)
        self.bridge.last_step_ns = t0
        i = 0
        t = t0
        self._state(t, emit)
        while t < end:
            t += self.period_ns
            while i < n and source.stamp(i) <= t:
                self.deliver(source.take(i, self.backend.get_observation().q, emit), t, emit)
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

