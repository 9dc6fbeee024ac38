"""``nwr bench --tracking``: how the bridge's tracker follows the planner, measured in this process.

Three measurements, all on simulated time (the figures are the same every
run; only the cost per cycle depends on the machine):

- **Sessions** (:func:`measure`): the whole chain in lockstep
  (:class:`~nwr.services.pipeline.lockstep.Lockstep`) on the simulated skin,
  touch-free and the demo's touches, with the robot state at 50 and 100 Hz.
  Every control cycle of the bridge, the commanded state (the tracker's
  ``q``, ``dq``, ``ddq``) is kept, and from it: jerk (the change of ``ddq``
  over the cycle) and acceleration per joint as fractions of the envelope's
  ``j_max`` and ``a_max``, peak and 99th percentile, over all cycles and over
  the task's; the tracking error (the commanded ``q`` against the target the
  planner gave for that instant: a stream's last target, or the plan's
  setpoint), max and 99th percentile, rad; the fastest point of the arm (every
  point the Cartesian limits watch) while it follows the task, against the
  task's own fastest point (:func:`~nwr.services.bridge.wiring.task_peak_speed`);
  the cost of :meth:`Tracker.track` per call. ``jitter_ms`` delays each
  command by up to that much and each bridge cycle by up to a quarter of it
  (seeded), as a loaded machine does to the live services.
- **Reflex onsets** (:func:`onset`): the bridge alone, following the task's
  plans, then a withdrawal of the touched pad (a Cartesian velocity stream, or
  a jerk-limited joint-space position stream as the planner plans them): the
  time from the first reflex command until the pad is ``ONSET_MM`` farther from
  the contact than the task would have taken it, for the commanded pose and
  for the command itself.
- **Stops begun while accelerating** (:func:`stop_overshoot`): a velocity
  stream accelerating the arm toward the Cartesian speed limit, a controlled
  stop begun at every cycle of the ramp: the fastest any point then moves.

``tracker`` swaps in another tracker class (the same constructor; see
:func:`tracker_from`), so two versions can be compared in one process.
"""

from __future__ import annotations

import importlib.util
import inspect
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from ruckig import InputParameter, Result, Ruckig, Trajectory

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile
from nwr.common.launch import TouchScript, load_script
from nwr.common.journal import Untracked
from nwr.common.robot import RobotDescription, RobotModel, load_description
from nwr.common.task import FigureEight
from nwr.services.bridge.core import Setpoint
from nwr.services.bridge.wiring import BridgeWiring, task_peak_speed
from nwr.services.gateway.stepped import SimulatedSkin, SkinSource
from nwr.services.pipeline.lockstep import Lockstep
from nwr.services.wiring import no_diag

ONSET_MM = 1.0
QUIET_S = 12.0  # the touch-free session
WITHDRAWAL_M_S = 0.25  # the velocity reflex's pad speed
WITHDRAWAL_M = 0.03  # how far the position reflex withdraws the pad
PLANNER_FRACTION = 0.9  # of the envelope, as the planner plans its reflexes


def stats(values: np.ndarray) -> tuple[float, float]:
    """Peak and 99th percentile (over every value), NaN when empty."""
    if values.size == 0:
        return float("nan"), float("nan")
    return float(values.max()), float(np.percentile(values, 99))


@dataclass
class Figures:
    """What one lockstep session shows of the tracking (see the module docstring)."""

    label: str
    cycles: int = 0
    jerk: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # per cycle and joint, / j_max
    acc: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # per cycle and joint, / a_max
    task: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # the cycle follows the task
    error: np.ndarray = field(default_factory=lambda: np.zeros(0))  # rad, cycles following a position
    task_peak_m_s: float = 0.0  # the fastest point while following the task
    planned_peak_m_s: float = 0.0  # the task's own fastest point
    track_ns: list[int] = field(default_factory=list)  # Tracker.track per call

    def row(self) -> dict[str, Any]:
        """The figures as one table row."""
        us = np.asarray(self.track_ns, dtype=float) / 1e3
        task_jerk = self.jerk[self.task[1:]] if self.jerk.size else self.jerk
        return {
            "session": self.label,
            "jerk/j_max peak": stats(self.jerk)[0], "jerk/j_max p99": stats(self.jerk)[1],
            "task jerk/j_max peak": stats(task_jerk)[0], "task jerk/j_max p99": stats(task_jerk)[1],
            "acc/a_max peak": stats(self.acc)[0], "acc/a_max p99": stats(self.acc)[1],
            "task acc/a_max p99": stats(self.acc[self.task])[1] if self.acc.size else float("nan"),
            "error max (mrad)": 1e3 * stats(self.error)[0], "error p99 (mrad)": 1e3 * stats(self.error)[1],
            "task peak (m/s)": self.task_peak_m_s, "planned (m/s)": self.planned_peak_m_s,
            "track p50 (us)": float(np.median(us)) if us.size else float("nan"),
            "track p99 (us)": float(np.percentile(us, 99)) if us.size else float("nan"),
        }


def _timed(tracker: Any, sink: list[int]) -> None:
    """Time every call of ``tracker.track`` into ``sink`` (ns)."""
    track = tracker.track

    def timed_track(h: float, t_ns: int, active: str) -> Any:
        start = time.perf_counter_ns()
        out = track(h, t_ns, active)
        sink.append(time.perf_counter_ns() - start)
        return out

    tracker.track = timed_track


def _swap(bridge: BridgeWiring, tracker: type | None) -> None:
    """Give the bridge's core a tracker of class ``tracker`` (None: keep its own), in the state of its own."""
    if tracker is None:
        return
    core = bridge.core
    old = core.tracker
    core.tracker = tracker(old.env, old.q.copy(), core.last_step_ns, period_s=old.period_s, limiter=old.limiter)


class _Probe:
    """Watches the bridge's core every control cycle (and times its tracker)."""

    def __init__(self, tracker: type | None, jitter_ms: float = 0.0, seed: int = 1) -> None:
        self.tracker_cls = tracker
        self.jitter_ns = round(jitter_ms * 1e6)
        self.rng = np.random.default_rng(seed)
        self.pending: list[tuple[int, str, Any]] = []  # commands on their way: (arrival, key, command)
        self.q: list[np.ndarray] = []
        self.dq: list[np.ndarray] = []
        self.ddq: list[np.ndarray] = []
        self.h: list[float] = []
        self.task: list[bool] = []
        self.error: list[float] = []
        self.track_ns: list[int] = []

    def attach(self, bridge: BridgeWiring, clock: ManualClock) -> None:
        _swap(bridge, self.tracker_cls)
        core = bridge.core
        _timed(core.tracker, self.track_ns)
        step = core.step

        def watched_step(now_ns: int) -> Setpoint:
            setpoint = step(now_ns)
            self._watch(core, now_ns, setpoint)
            return setpoint

        core.step = watched_step  # type: ignore[method-assign]
        if self.jitter_ns:
            self._delay(bridge, clock)

    def _delay(self, bridge: BridgeWiring, clock: ManualClock) -> None:
        """Commands arrive up to ``jitter_ns`` after they were sent, the bridge's cycles begin up to a quarter
        of that late (seeded)."""
        on_command, tick = bridge.on_command, bridge.tick

        def delayed(key: str, cmd: Any) -> None:
            self.pending.append((clock.t_ns + int(self.rng.integers(0, self.jitter_ns)), key, cmd))

        def late_tick(publish: bool = False) -> None:
            t = clock.t_ns
            cycle = t + int(self.rng.integers(0, self.jitter_ns // 4 + 1))
            due = sorted((p for p in self.pending if p[0] <= cycle), key=lambda p: p[0])
            self.pending = [p for p in self.pending if p[0] > cycle]
            for arrival, key, cmd in due:
                clock.t_ns = arrival
                on_command(key, cmd)
            clock.t_ns = cycle
            tick(publish=publish)
            clock.t_ns = t

        bridge.on_command = delayed  # type: ignore[method-assign]
        bridge.tick = late_tick  # type: ignore[method-assign]

    def _watch(self, core: Any, now_ns: int, setpoint: Setpoint) -> None:
        if setpoint.h <= 0.0:
            return
        tracker = core.tracker
        following = core.status == "ok" and tracker.stop is None and tracker.mode == "position"
        self.q.append(setpoint.q)
        self.dq.append(setpoint.dq)
        self.ddq.append(setpoint.ddq)
        self.h.append(setpoint.h)
        self.task.append(following and core.phase == "TASK" and not tracker.withdrawal)
        if following:
            target = tracker.planned(now_ns)[0] if tracker.plan is not None else tracker.target
            self.error.append(float(np.max(np.abs(setpoint.q - target))))


class _Watched(Lockstep):
    """Lockstep with a probe on the bridge, attached once the wirings are built."""

    def __init__(self, profile: Profile, probe: _Probe, strategy: str | None) -> None:
        super().__init__(profile, strategy=strategy, journal=False)
        self.probe = probe

    def _start(self, t0: int, source: SkinSource) -> None:
        super()._start(t0, source)
        self.probe.attach(self.bridge, self.clock)


def measure(profile: Profile, script: TouchScript, label: str, *, strategy: str | None = None,
            tracker: type | None = None, jitter_ms: float = 0.0) -> Figures:
    """One lockstep session on the simulated skin's ``script``: the tracking's figures (module docstring)."""
    probe = _Probe(tracker, jitter_ms)
    chain = _Watched(profile, probe, strategy)
    chain.run(SimulatedSkin(profile, script), _ignore, settle_s=1.0)
    env = chain.bridge.env
    limiter = chain.bridge.core.tracker.limiter
    assert limiter is not None
    ddq = np.array(probe.ddq)
    h = np.array(probe.h)[1:, None]
    task = FigureEight(chain.profile.planner.task, _description(profile))
    return Figures(
        label, cycles=len(probe.h), jerk=np.abs(np.diff(ddq, axis=0)) / h / env.j_max, acc=np.abs(ddq) / env.a_max,
        task=np.array(probe.task, dtype=bool), error=np.array(probe.error), track_ns=probe.track_ns,
        planned_peak_m_s=task_peak_speed(task, chain.profile.planner.task.period_s, limiter),
        task_peak_m_s=max((float(limiter.speeds(q, dq).max())
                           for q, dq, in_task in zip(probe.q, probe.dq, probe.task) if in_task), default=0.0),
    )


def sessions(profile: Profile) -> list[tuple[str, Profile, TouchScript]]:
    """The sessions the tracking is measured on: touch-free and the demo's touches, robot state at 50 and 100 Hz."""
    out = []
    for rate in (profile.bridge.state_rate_hz, 100.0):
        p = msgspec.structs.replace(profile, bridge=msgspec.structs.replace(profile.bridge, state_rate_hz=rate))
        out.append((f"touch-free {QUIET_S:g} s, state {rate:g} Hz", p, TouchScript(duration_s=QUIET_S, touch=[])))
        out.append((f"demo, state {rate:g} Hz", p, load_script("demo")))
    return out


# ------------------------------------------------------------------------------ the bridge alone


class BridgeRun:
    """The bridge's wiring on a manual clock, its active planner alive, its skin fresh."""

    def __init__(self, profile: Profile, tracker: type | None) -> None:
        self.clock = ManualClock()
        self.clock.t_ns = 10**9
        self.profile = profile
        self.bridge = BridgeWiring(profile, journal=Untracked(self.clock), out=_drop, diag=no_diag)
        _swap(self.bridge, tracker)
        self.name = profile.bridge.active_planner
        self.bridge.on_token(self.name, True)
        self.period_ns = round(1e9 / profile.bridge.rate_hz)
        self.cycles = 0
        self.seq = 0
        pads = len(_description(profile).pads)
        self.skin = m.SkinPressure(seq=0, stamp_ns=0, absolute_hpa=[1000.0] * pads, baseline_hpa=[1000.0] * pads,
                                   change_hpa=[0.0] * pads, contact=[False] * pads, valid=[True] * pads,
                                   source="bench")

    @property
    def tracker(self) -> Any:
        return self.bridge.core.tracker

    def cycle(self, command: m.Command | None = None) -> None:
        """One control cycle, with ``command`` arriving at its start."""
        self.clock.t_ns += self.period_ns
        if self.cycles % 20 == 0:
            self.bridge.on_skin(msgspec.structs.replace(self.skin, seq=self.cycles, stamp_ns=self.clock.t_ns))
        if command is not None:
            self.bridge.on_command(keys.robot_command(self.name), command)
        self.bridge.tick()
        self.cycles += 1

    def command(self, cls: type, **fields: Any) -> Any:
        """A command of class ``cls`` for the coming cycle, of the active planner, with ``fields``."""
        self.seq += 1
        return cls(seq=self.seq, stamp_ns=self.clock.t_ns + self.period_ns, owner=self.name, trace=m.NO_TRACE,
                   **fields)


@dataclass
class Onset:
    kind: str
    bridge_ms: float  # the commanded pose
    command_ms: float  # the command itself


def onset(profile: Profile, kind: str, *, tracker: type | None = None, at_s: float = 1.0,
          moved_mm: float = ONSET_MM) -> Onset:
    """A withdrawal of ``kind`` ("velocity" or "position") from the task at ``at_s``: its onset (module docstring)."""
    desc = _description(profile)
    model = RobotModel(desc)
    run = BridgeRun(profile, tracker)
    env = run.bridge.env
    task = FigureEight(profile.planner.task, desc)
    dt = run.period_ns / 1e9
    ahead = profile.planner.task_ahead_cycles
    start = round(at_s / dt)
    for k in range(start):
        if k % ahead == 0:
            run.cycle(run.command(m.PositionCommand, q=task.position(k * dt).tolist(), period_s=dt,
                                  ahead=[task.position((k + i) * dt).tolist() for i in range(1, ahead + 1)]))
        else:
            run.cycle()
    pad = desc.pad(desc.figure_pads[1]).id  # the forearm pad of the figures (the UR10e's forearm_top)
    q0, v0 = task.position((start - 1) * dt), task.velocity((start - 1) * dt)  # where the last cycle left it
    inward = -model.pad_normal(q0, pad)
    jacobian = model.pad_jacobian(q0, pad)[:3]
    commanded: list[np.ndarray] = []
    ideal: list[np.ndarray] = []
    steps = round(0.3 / dt)
    if kind == "velocity":
        dq = np.linalg.pinv(jacobian) @ (WITHDRAWAL_M_S * inward)
        for k in range(steps):
            run.cycle(run.command(m.VelocityCommand, dq=dq.tolist(), phase="REFLEX", reflex_seq=1))
            commanded.append(run.tracker.q.copy())
            ideal.append(q0 + dq * (k + 1) * dt)
    else:
        target = q0 + np.linalg.pinv(jacobian) @ (WITHDRAWAL_M * inward)
        path = withdrawal_path(env, run.tracker.limiter, q0, v0, target)
        for k in range(steps):
            q = np.asarray(path.at_time(min((k + 1) * dt, path.duration))[0])
            run.cycle(run.command(m.PositionCommand, q=q.tolist(), phase="REFLEX", reflex_seq=1))
            commanded.append(run.tracker.q.copy())
            ideal.append(q)

    def first(poses: list[np.ndarray]) -> float:
        for k, q in enumerate(poses):
            along = task.position((start + k) * dt)  # where the task would have taken the pad
            if float((model.pad_point(q, pad) - model.pad_point(along, pad)) @ inward) >= moved_mm / 1e3:
                return (k + 1) * dt * 1e3
        return float("nan")

    return Onset(kind, first(commanded), first(ideal))


def withdrawal_path(env: Any, limiter: Any, q0: np.ndarray, v0: np.ndarray, target: np.ndarray) -> Trajectory:
    """A joint-space withdrawal as the planner plans one: jerk-limited, within a share of the envelope, its joint
    speeds in proportion to the motion and low enough that no point moves faster than that share of the
    withdrawal speed."""
    n = env.n
    direction = target - q0
    fastest = PLANNER_FRACTION * limiter.limits.withdrawal_speed_m_s / float(limiter.speeds(q0, direction).max())
    otg = Ruckig(n)
    inp = InputParameter(n)
    inp.current_position, inp.current_velocity, inp.current_acceleration = q0.tolist(), v0.tolist(), [0.0] * n
    inp.target_position, inp.target_velocity, inp.target_acceleration = target.tolist(), [0.0] * n, [0.0] * n
    inp.max_velocity = np.maximum(np.minimum(PLANNER_FRACTION * env.v_max, np.abs(direction) * fastest),
                                  1e-3).tolist()
    inp.max_acceleration = (PLANNER_FRACTION * env.a_max).tolist()
    inp.max_jerk = (PLANNER_FRACTION * env.j_max).tolist()
    path = Trajectory(n)
    if otg.calculate(inp, path) not in (Result.Working, Result.Finished):
        raise RuntimeError("ruckig could not plan the bench's withdrawal")
    return path


def stop_overshoot(profile: Profile, *, tracker: type | None = None, ramp_s: float = 0.25) -> tuple[float, float]:
    """The fastest any point moves in a controlled stop begun while the arm accelerates (module docstring), and
    the limit, m/s.

    A velocity stream four times too fast for the speed limit, from rest: the
    arm accelerates and levels off at the limit; a stop is begun at every
    cycle of that ramp, on a copy of the tracker, and run to rest.
    """
    run = BridgeRun(profile, tracker)
    limiter = run.tracker.limiter
    assert limiter is not None
    q0 = run.tracker.q.copy()
    direction = np.linalg.pinv(limiter.model.speed_jacobians(q0)[-1]) @ np.array([0.0, 1.0, 0.0])
    dq = direction * 4.0 * limiter.limits.speed_m_s / float(limiter.speeds(q0, direction).max())
    dq *= min(1.0, float(np.min(run.bridge.env.v_max / np.maximum(np.abs(dq), 1e-12))))
    worst = 0.0
    h = run.period_ns / 1e9
    for _ in range(round(ramp_s / h)):
        run.cycle(run.command(m.VelocityCommand, dq=dq.tolist(), phase="TASK", reflex_seq=0))
        now = run.tracker
        t = run.clock.t_ns
        twin: Any = type(now)(now.env, now.q.copy(), t, period_s=now.period_s, limiter=limiter)  # a twin to stop
        twin.dq, twin.ddq, twin.withdrawal = now.dq.copy(), now.ddq.copy(), now.withdrawal
        twin.begin_stop(t)
        while twin.stop is not None and not twin.stop.done:
            t += run.period_ns
            twin.stop_step(t, h)
            worst = max(worst, float(limiter.speeds(twin.q, twin.dq).max()))
    return worst, limiter.limits.speed_m_s


# ------------------------------------------------------------------------------ the report


def tracker_from(path: str) -> type:
    """The ``Tracker`` of another ``tracking.py`` (e.g. ``git show REV:services/bridge/tracking.py > old.py``).

    Since the tracker was split into parts (``reference.py``, ``law.py``, ``limits.py``, ``stop.py``), a
    ``tracking.py`` of a later revision imports this tree's parts, not its own: only its own module differs.
    """
    spec = importlib.util.spec_from_file_location("nwr_tracking_against", Path(path))
    if spec is None or spec.loader is None:
        raise FileNotFoundError(path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    tracker: Any = module.Tracker
    if len(inspect.signature(tracker.follow_velocity).parameters) == 2:  # (self, dq): before the stream's timing

        class Adapted(tracker):
            def follow_velocity(self, dq: np.ndarray, *_timing: Any) -> None:
                super().follow_velocity(dq)

        return Adapted
    return tracker


def run(profile: Profile, *, against: str | None = None, strategy: str | None = None, jitter_ms: float = 0.0,
        print_row: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Every measurement with this tracker and (``against``: a tracking.py) another, alternated; one row each."""
    other = tracker_from(against) if against else None
    versions: list[tuple[str, type | None]] = [("this", None)]
    if other is not None:
        versions = [("against", other), ("this", None)]
    rows: list[dict[str, Any]] = []

    def add(row: dict[str, Any]) -> None:
        rows.append(row)
        if print_row is not None:
            print_row(row)

    for label, p, script in sessions(profile):
        mine: dict[str, dict[str, Any]] = {}
        for name, cls in versions:
            mine[name] = {"tracker": name, **measure(p, script, label, strategy=strategy, tracker=cls,
                                                     jitter_ms=jitter_ms).row()}
        if other is not None:
            for q in ("p50", "p99"):
                mine["this"][f"cost ratio {q}"] = mine["this"][f"track {q} (us)"] / mine["against"][f"track {q} (us)"]
        for row in mine.values():
            add(row)
    for name, cls in versions:
        row = {"tracker": name, "session": "onset and stop"}
        for kind in ("velocity", "position"):
            found = onset(profile, kind, tracker=cls)
            row[f"{kind} reflex to {ONSET_MM:g} mm (ms)"] = found.bridge_ms
            row[f"{kind} command to {ONSET_MM:g} mm (ms)"] = found.command_ms
        row["stop begun accelerating: fastest point (m/s)"], row["speed limit (m/s)"] = \
            stop_overshoot(profile, tracker=cls)
        add(row)
    return rows


def _description(profile: Profile) -> RobotDescription:
    return load_description(profile.robot.description or None)


def _ignore(key: str, message: Any, t: int) -> None:
    del key, message, t


def _drop(key: str, message: Any) -> None:
    del key, message
