"""The robot bridge's wiring: commands, skin, pain, tokens, switches and control cycles -> the arm -> robot/state.

The call order of the service per input, with no Zenoh, no thread and no
clock of its own (time comes from the journal): the live process
(:mod:`.main`), lockstep runs and ``nwr verify`` run this code.
:class:`~nwr.services.bridge.core.BridgeCore` decides, a backend
(:class:`~nwr.services.bridge.backend.SimBackend` or the ur_rtde one) moves
the arm.

- a command is checked, with the planner its key belongs to; the first
  command of a reflex goes to the backend at once and its acceptance is
  published at once (not at the next cycle);
- skin and pain messages keep the skin data fresh;
- a planner's liveliness token appearing or vanishing, and a switch request,
  change who moves the arm (a switch is published at once); a safety-mode
  request switches the Cartesian limits (published at once);
- each control cycle: the backend's fault, the arm's measured pose, one
  setpoint, and the robot state every ``state_rate_hz``.
"""

from __future__ import annotations

import argparse
from typing import Any

import msgspec
import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.journal import Journal
from nwr.common.robot import RobotDescription, RobotModel, load_description
from nwr.common.skin import entry_pads, load_skin
from nwr.common.task import FigureEight, peak_point_speed
from nwr.services.bridge import backends
from nwr.services.bridge.backend import Backend, Observation, SimBackend
from nwr.services.bridge.cartesian import CartesianLimiter, Limits
from nwr.services.bridge.checks import StateBounds
from nwr.services.bridge.core import BridgeCore, at_rest
from nwr.services.bridge.envelope import Envelope, make_envelope
from nwr.services.wiring import Diag, Input, Out, Wiring, event, receives

SERVICE = "bridge"


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


def task_peak_speed(task: FigureEight, period_s: float, limiter: CartesianLimiter, samples: int = 240) -> float:
    """The speed of the task's fastest point (any the limits watch) over one period, m/s (as the profile's load
    checked it against bridge.limits.speed_m_s: :func:`nwr.common.task.peak_point_speed`)."""
    return peak_point_speed(task, period_s, limiter.model, samples)


def simulated_backend(profile: Profile, env: Envelope, q0: np.ndarray, desc: RobotDescription) -> Backend:
    """The profile's backend when it is a simulated arm (``sim``, ``physics``): what lockstep and ``nwr verify``
    run; the simulated arm otherwise (a real arm's backend is the live bridge's alone)."""
    cfg = profile.bridge
    plugin = backends.plugin(cfg.backend)
    if plugin.REAL_ARM:
        return SimBackend(env, 1.0 / cfg.rate_hz, q0)
    backend: Backend = plugin.make(cfg, env, q0, argparse.Namespace(), desc)
    return backend


def state_bounds(profile: Profile) -> StateBounds:
    """How far the robot's reported state may stray before it is not believed, from the profile."""
    cfg = profile.bridge
    return StateBounds(error_rad=cfg.following_error_rad, lag_s=cfg.following_lag_s, jump_rad=cfg.report_jump_rad,
                       speed_jump_rad_s=cfg.report_speed_jump_rad_s, frozen_s=cfg.report_frozen_s)


class BridgeWiring(Wiring):
    service = SERVICE
    outputs = (keys.ROBOT_STATE, keys.WORLD_SKIN, keys.WORLD_CONTACTS)

    def __init__(self, profile: Profile, *, journal: Journal, out: Out, diag: Diag,
                 backend: Backend | None = None) -> None:
        cfg = profile.bridge
        env, q0, n_pads = envelope_for(profile)
        desc = load_description(profile.robot.description or None)
        model = RobotModel(desc)
        if backend is None:  # a simulated arm (sim, physics), as the profile describes it
            backend = simulated_backend(profile, env, q0, desc)
            backend.connect()
        elif backend.name != "sim":
            q0 = backend.get_observation().q  # a real arm starts where it is
        self.env = env
        self.backend = backend
        self.journal = journal
        self.out = out
        self.diag = diag
        limiter = CartesianLimiter(model, Limits.of(cfg.limits, model, "bridge.limits"), a_max=env.a_max,
                                   j_max=env.j_max)
        task = FigureEight(profile.planner.task, desc)
        journal.begin("start")
        skin = load_skin(profile, desc)  # a taxel skin's samples have one entry per taxel
        if skin is not None:
            backend.use_skin(skin)  # a hosted world samples it
        self.core = BridgeCore(
            env, q0, journal.now_ns(), active=cfg.active_planner, n_pads=n_pads,
            command_timeout_s=cfg.command_timeout_s, skin_timeout_s=cfg.skin_timeout_s,
            seq_restart_gap=cfg.seq_restart_gap, period_s=1.0 / cfg.rate_hz,
            limiter=limiter,
            reduced=Limits.of(cfg.reduced, model, "bridge.reduced"),
            task_range=task.range(),
            task_peak_m_s=task_peak_speed(task, profile.planner.task.period_s, limiter),
            physical=(np.asarray(desc.v_max, dtype=float), np.asarray(desc.a_max, dtype=float)),
            state_bounds=state_bounds(profile), lag_s=backend.lag_s,
            pad_names=tuple(pad.name for pad in desc.pads), blind_pad_s=cfg.blind_pad_s, blind_pads=cfg.blind_pads,
            entry_pads=tuple(entry_pads(skin, desc.pads).tolist()) if skin is not None else (),
        )
        # The last finite report: published (marked stale) while the backend gives none.
        self.last_q = np.asarray(q0, dtype=float).copy()
        self.last_dq = np.zeros(env.n)
        self.state_every = max(1, round(cfg.rate_hz / cfg.state_rate_hz))
        self.ticks = 0
        self.seq = 0

    @classmethod
    def rebuild(cls, profile: Profile, params: dict[str, Any], *, journal: Journal, out: Out,
                diag: Diag) -> BridgeWiring:
        backend = params.get("backend", "sim")
        if backends.plugin(backend).REAL_ARM:
            raise ConfigError(f"the bridge drove the {backend} backend: the arm's measurements are not journaled, "
                              "so only a bridge on a simulated arm can be re-run")
        profile = msgspec.structs.replace(profile, bridge=msgspec.structs.replace(profile.bridge, backend=backend))
        return cls(profile, journal=journal, out=out, diag=diag)

    def params(self) -> dict[str, Any]:
        return {"backend": self.backend.name}

    def listens(self, inp: Input) -> bool:
        """The touch script's touches only for a backend that hosts a world (physics)."""
        return inp.name != "touch" or self.backend.touched

    # -- inputs ------------------------------------------------------------------------
    @receives("command", keys.ROBOT_COMMANDS, keyed=True)
    def on_command(self, key: str, cmd: m.Command) -> None:
        now = self.journal.now_ns()
        core = self.core
        verdict = core.on_command(cmd, now, publisher=keys.command_publisher(key))
        if verdict.onset:
            # The first command of a reflex goes to the backend now, not at
            # the next cycle, and its acceptance is published at once.
            self._cycle(now)
            self._publish(now)
        elif core.publish_now:
            self._publish(now)
        self._report()

    @receives("skin", keys.SKIN_PRESSURE)
    def on_skin(self, pressure: m.SkinPressure) -> None:
        self.core.on_skin(pressure, self.journal.now_ns())
        self._report()

    @receives("pain", keys.SKIN_PAIN)
    def on_pain(self, pain: m.SkinPain) -> None:
        self.core.on_pain(pain, self.journal.now_ns())
        self._report()

    @receives("touch", keys.SKIN_TOUCH)
    def on_touch(self, touch: m.SkinTouch) -> None:
        """A touch of the touch script (its ground truth): a hosted world's finger presses its pad."""
        refused = self.backend.on_touch(touch, self.journal.now_ns())
        if refused is not None:
            self.diag("error", "touch_refused", refused, every_s=0.0)

    @event("token", record=lambda name, alive: (int(alive), name, ()), recall=lambda w, e: (e.text, bool(e.arg)))
    def on_token(self, name: str, alive: bool) -> None:
        """The liveliness token of planner ``name`` appeared (``alive``) or vanished."""
        self.core.on_planner_token(name, alive, self.journal.now_ns())
        self._report()

    @receives("switch", keys.CONTROL_ACTIVE)
    def on_switch(self, request: m.SwitchRequest) -> None:
        now = self.journal.now_ns()
        self.core.request_switch(request, now)
        if self.core.publish_now:
            self._publish(now)  # the planners learn who is active at once
        self._report()

    @receives("safety", keys.CONTROL_SAFETY)
    def on_safety(self, request: m.SafetyModeRequest) -> None:
        now = self.journal.now_ns()
        self.core.set_safety_mode(request.mode, now, request.requested_by)
        if self.core.publish_now:
            self._publish(now)  # the operator's tool learns the mode at once
        self._report()

    @event("tick", record=lambda publish=False: (int(publish), "", ()), recall=lambda w, e: (bool(e.arg),))
    def tick(self, publish: bool = False) -> None:
        """One control cycle; the robot state every ``state_rate_hz`` (``publish``: this cycle too)."""
        now = self.journal.now_ns()
        core, backend = self.core, self.backend
        self.ticks += 1
        for key, message in backend.advance(now):  # a hosted world steps to now: its skin, its contacts
            self.out(key, message)
        obs = backend.get_observation()
        q = self._finite(obs)
        if obs.fault != core.fault:
            core.on_fault(obs.fault, obs.detail, q, now)
            backend.resync(q)
        if core.observe(obs.q, obs.dq, now, obs.stamp_s):  # a non-finite report is a fault there
            backend.resync(obs.q)  # the reports are believed again: the bridge starts over where the arm is
        self._cycle(now)
        if publish or self.ticks % self.state_every == 0 or core.publish_now:
            self._publish(now)
        self._report()

    @event("stop", record=lambda reason: (0, reason, ()), recall=lambda w, e: (e.text,))
    def stop(self, reason: str) -> float:
        """A controlled stop to rest; how long it takes at most, s."""
        self.core.request_stop(self.journal.now_ns(), reason)
        self._report()
        return self.core.tracker.stop_time_s

    def at_rest(self) -> bool:
        tracker = self.core.tracker
        return tracker.stop is None or tracker.stop.done or at_rest(tracker.dq)

    def _cycle(self, now: int) -> None:
        setpoint = self.core.step(now)
        if self.core.fault is None:  # (state_implausible, the bridge's own fault, sends a hold: the backend's stop)
            self.backend.send_action(setpoint)

    def _finite(self, obs: Observation) -> np.ndarray:
        """The report's joint positions if it is finite (then kept as the last known), else the last known."""
        if np.isfinite(obs.q).all() and np.isfinite(obs.dq).all():
            self.last_q, self.last_dq = obs.q, obs.dq
            return obs.q
        return self.last_q

    def _publish(self, now: int) -> None:
        obs = self.backend.get_observation()
        q = self._finite(obs)
        stale = q is not obs.q or obs.fault == "disconnected"  # never a non-finite value on the wire
        dq = np.zeros_like(q) if stale else obs.dq
        state = self.core.state(self.seq, now, q, dq, self.backend.name, pose_stale=stale)
        state.clipped += self.backend.guarded
        if obs.tau_ext is not None and not stale and np.isfinite(obs.tau_ext).all():
            state.tau_ext = obs.tau_ext.tolist()
        self.out(keys.ROBOT_STATE, state)
        self.seq += 1

    def _report(self) -> None:
        for ev in self.core.drain_events():
            self.diag(ev.level, ev.code, ev.message, every_s=ev.every_s)
