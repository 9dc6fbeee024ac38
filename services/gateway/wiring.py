"""The skin gateway's wiring: the simulated skin's ticks (or a real skin's samples) + robot/state (+ statuses)
-> skin/pressure, skin/touch.

The call order of the service, with no Zenoh, no thread and no clock of its
own (time comes from the journal): the live process (:mod:`.main`), lockstep
runs and ``nwr verify`` run this code.

- a robot state is kept: where the arm is when a touch meets its pad (the
  ground truth on ``skin/touch``) and, in closed loop, how far a pad has
  withdrawn from the finger;
- a planner's status names the study's target pad (``--follow-target``), which the
  simulated participant presses only while the active planner does its task;
- :meth:`GatewayWiring.origin` starts the touch script's clock;
- each tick: the follower's touch, the touches that start (forward
  kinematics only when one needs the pose), the sample (of the period's
  deadline: a late loop takes the periods it missed one by one);
- a real skin (``gateway.source = "ros1"`` or ``"ros2"``, :mod:`.sources.ros1`) has no ticks: each
  of its samples, mapped onto the pads, is an input (:meth:`GatewayWiring.on_sample`);
- a physics world's skin (``gateway.source = "physics"``, :mod:`.sources.physics`): the
  ticks run the touch script's clock (the touches' ground truth, which the
  bridge's world turns into fingers), the world's samples (``world/skin``)
  are an input (:meth:`GatewayWiring.on_world_skin`).
"""

from __future__ import annotations

from typing import Any

import msgspec
import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.journal import Journal
from nwr.common.launch import TouchScript
from nwr.common.robot import RobotModel, load_description
from nwr.common.skin import hpa_per_unit, load_skin
from nwr.services.gateway.core import Gateway, SimSkin, TargetFollower, sim_settings, touch_message
from nwr.services.gateway.taxels import ScriptedTaxels, check_covered
from nwr.services.wiring import Diag, Input, Out, Wiring, event, receives

SERVICE = "gateway"


class GatewayWiring(Wiring):
    service = SERVICE
    outputs = (keys.SKIN_PRESSURE, keys.SKIN_TOUCH)

    def __init__(self, profile: Profile, *, journal: Journal, out: Out, diag: Diag, script: TouchScript | None = None,
                 follow_target_s: float | None = None) -> None:
        cfg = profile.gateway
        self.cfg = cfg
        self.desc = load_description(profile.robot.description or None)
        self.pads = self.desc.pads
        self.script = script
        self.follow_target_s = follow_target_s
        sim = sim_settings(cfg)
        self.sim = SimSkin(sim, self.pads, script)
        # A taxel skin (robot.skin = "taxels"): the touch script's touches pressed on the taxels by a finger
        # each; one entry per taxel in every list of skin/pressure, in hPa.
        skin = load_skin(profile, self.desc)
        self.taxels: ScriptedTaxels | None = None
        self.taxel_hpa = 0.0
        n = len(self.pads)
        if skin is not None:
            if cfg.source not in ("sim", "physics") or sim.closed_loop or follow_target_s:
                raise ConfigError("robot.skin = \"taxels\" runs on a simulated skin: the scripted world's "
                                  "(gateway.source = \"sim\", open loop) or the physics world's (\"physics\"), on "
                                  "a touch script")
            if cfg.source == "sim":
                self.taxels = ScriptedTaxels(skin, self.pads, script if script is not None
                                             else TouchScript(duration_s=1.0), profile.gain.thresholds_hpa)
            elif script is not None:
                check_covered(skin, self.pads, script)
            self.taxel_hpa = hpa_per_unit(skin)
            n = len(skin)
        self.n_taxels = n if skin is not None else 0
        self.gateway = Gateway(cfg, n, source=cfg.source)
        # A physics world's skin (gateway.source = "physics"): the samples come from the world (world/skin, the
        # bridge hosts it); the ticks run the touch script's clock only (the touches' ground truth).
        self.world = cfg.source == "physics"
        self.model = RobotModel(self.desc)
        self.follower = TargetFollower(follow_target_s, sim.seed) if follow_target_s else None
        self.journal = journal
        self.out = out
        self.diag = diag
        self.pose: m.RobotState | None = None  # the newest robot state
        self.target = -1  # the study's target pad, from the planners' statuses
        self.arm_busy = False  # the active planner is in a reflex or its return (its status says)
        self.origin_ns = 0
        self.touch_seq = 0
        self.late_samples = 0  # world skin samples dropped for arriving too late (on_world_skin)
        journal.begin("start")

    @classmethod
    def rebuild(cls, profile: Profile, params: dict[str, Any], *, journal: Journal, out: Out,
                diag: Diag) -> GatewayWiring:
        script = params.get("script")
        return cls(profile, journal=journal, out=out, diag=diag,
                   script=msgspec.convert(script, TouchScript) if script is not None else None,
                   follow_target_s=params.get("follow_target_s"))

    def params(self) -> dict[str, Any]:
        return {"script": msgspec.to_builtins(self.script) if self.script is not None else None,
                "follow_target_s": self.follow_target_s}

    # -- inputs ------------------------------------------------------------------------
    @receives("state", keys.ROBOT_STATE)
    def on_state(self, state: m.RobotState) -> None:
        self.pose = state

    @receives("status", keys.planner_status("*"), keyed=True, direct=False)
    def on_status(self, key: str, status: m.PlannerStatus) -> None:
        self.target = status.target_pad
        if status.active:
            self.arm_busy = status.mode != "TASK"

    def listens(self, inp: Input) -> bool:
        """The planners' statuses only for a simulated participant who follows the study's target; a physics
        world's skin only on that source."""
        if inp.name == "world_skin":
            return self.world
        return inp.name != "status" or self.follower is not None

    @event("origin")
    def origin(self) -> int:
        """The touch script's clock starts now; its origin, ns."""
        self.origin_ns = self.journal.now_ns()
        return self.origin_ns

    @event("tick", record=lambda due_ns=0: (due_ns, "", ()), recall=lambda w, e: (e.arg,))
    def tick(self, due_ns: int = 0) -> float:
        """One sample period: the touches that start, the sample; the script's time, s.

        ``due_ns``: the period's deadline, when the loop is late and takes the periods it missed one after
        the other (a device's samples, read late, are the device's all the same); the sample is of that
        time, stamped when it is taken. 0: now.
        """
        now = self.journal.now_ns()
        t = ((min(due_ns, now) if due_ns else now) - self.origin_ns) / 1e9
        sim = self.sim
        if self.follower is not None:
            # A participant presses the lit target while the arm does its task, not during a reflex or return.
            touch = self.follower.poll(t, -1 if self.arm_busy else self.target)
            if touch is not None:
                sim.add_touch(*touch)
        state = self.pose
        points = normals = None
        if state is not None and sim.touches.needs_pose(t):  # forward kinematics only when used
            points, normals = self.model.pad_points(state.q), self.model.pad_normals(state.q)
        for started in sim.start(t, points, normals):
            self.out(keys.SKIN_TOUCH, touch_message(
                self.touch_seq, now, self.origin_ns, started, self.pads[started.pad].name, sim.touches,
                state.q if state is not None else None, state.stamp_ns if state is not None else 0))
            self.touch_seq += 1
        if self.world:
            return t  # the world's own skin is sampled by the world (on_world_skin)
        if self.taxels is not None:
            pressed = self.taxels.sample(t) * self.taxel_hpa  # the touches are all there is: no drift, no noise
            msg, events = self.gateway.process(t, now, pressed, pressed)
        else:
            msg, events = self.gateway.process(t, now, sim.sample(t, points), sim.touch_hpa)
        self.out(keys.SKIN_PRESSURE, msg)
        self._reacquired(events.reacquired)
        for pad in events.non_finite:
            self.diag("warning", "non_finite_pressure", f"pad {self.pads[pad].name} reported a non-finite pressure")
        return t

    @event("sample", record=lambda absolute: _sample_fields(absolute), recall=lambda w, e: (_sample_values(e),))
    def on_sample(self, absolute: np.ndarray) -> None:
        """A real skin's sample (``gateway.source = "ros1"`` or ``"ros2"``): each pad's absolute pressure, hPa,
        NaN where the pad is invalid in it (:func:`nwr.common.skinmap.map_values`, whose caller reports why)."""
        absolute = np.asarray(absolute, dtype=float)
        now = self.journal.now_ns()
        msg, events = self.gateway.process((now - self.origin_ns) / 1e9, now, absolute)
        self.out(keys.SKIN_PRESSURE, msg)
        self._reacquired(events.reacquired)

    @receives("world_skin", keys.WORLD_SKIN)
    def on_world_skin(self, sample: m.WorldSkin) -> None:
        """A physics world's skin sample (``gateway.source = "physics"``): its pads' absolute pressures, as a
        device's sample (stamped when it arrives); on a taxel skin its taxels' readings, in hPa as the
        scripted taxel skin's (the skin file's unit converted). A sample older than ``max_sample_age_s`` when
        it arrives is dropped (a gateway behind the stream catches up rather than pass on old pressures as new).
        """
        now = self.journal.now_ns()
        age_s = (now - sample.stamp_ns) / 1e9
        if age_s > self.cfg.max_sample_age_s:
            self.late_samples += 1
            self.diag("warning", "late_world_skin",
                      f"world skin sample {sample.seq} arrived {1e3 * age_s:.0f} ms after the world took it (limit "
                      f"gateway.max_sample_age_s = {1e3 * self.cfg.max_sample_age_s:g} ms): dropped, as "
                      f"{self.late_samples} so far; the gateway is behind the world's skin stream (a busy machine)")
            return
        if self.n_taxels:
            absolute = np.asarray(sample.taxels, dtype=float) * self.taxel_hpa
            count, what = self.n_taxels, "taxels"
        else:
            absolute = np.asarray(sample.absolute_hpa, dtype=float)
            count, what = len(self.pads), "pads"
        if absolute.shape != (count,):
            self.diag("error", "world_skin_pads", f"world skin sample {sample.seq} has {absolute.size} {what}, "
                      f"the skin has {count}: dropped")
            return
        msg, events = self.gateway.process((now - self.origin_ns) / 1e9, now, absolute)
        self.out(keys.SKIN_PRESSURE, msg)
        self._reacquired(events.reacquired)

    def _reacquired(self, pads: list[int]) -> None:
        for pad in pads:
            self.diag("warning", "baseline_reacquired",
                      f"pad {self.pads[pad].name} stayed above the contact threshold for more than "
                      f"{self.cfg.max_contact_s} s: its baseline was re-acquired")


def _sample_fields(absolute: np.ndarray) -> tuple[int, str, list[float]]:
    """A real skin's sample in the journal: the finite values (0 elsewhere), and which pads were not finite."""
    absolute = np.asarray(absolute, dtype=float)
    finite = np.isfinite(absolute)
    return 0, ",".join(str(int(i)) for i in np.flatnonzero(~finite)), np.where(finite, absolute, 0.0).tolist()


def _sample_values(entry: m.JournalEntry) -> np.ndarray:
    absolute = np.array(entry.data, dtype=float)
    for i in (int(x) for x in entry.text.split(",") if x):
        absolute[i] = np.nan
    return absolute
