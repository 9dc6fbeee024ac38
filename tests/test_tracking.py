"""The bridge's tracker within the envelope's jerk limit: task streams, steps, withdrawals, velocity streams, stops.

Jerk is the change of the commanded acceleration (the tracker's ``ddq``)
over each control cycle, as a fraction of ``j_max``. Lockstep runs are
deterministic (seeded, for the jittered one), so every figure here is exact.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from ruckig import ControlInterface, InputParameter, Result, Ruckig, Trajectory

from nwr.common import messages as m
from nwr.common.config import Profile, load_profile
from nwr.common.launch import TouchScript
from nwr.common.robot import RobotModel, load_description
from nwr.common.task import FigureEight
from nwr.services.bridge.core import BridgeCore
from nwr.services.bridge.envelope import brake, make_envelope, stop_extent
from nwr.services.tools.bench import tracking as bench

DESC = load_description()
MODEL = RobotModel(DESC)
DT = 0.002
MS = 1_000_000
JERK_TOL = 1e-6  # relative: rounding
TR = m.Trace(0, 0)


def jerk_ratio(ddq: np.ndarray, j_max: np.ndarray, dt: float = DT) -> np.ndarray:
    return np.abs(np.diff(ddq, axis=0)) / dt / j_max


@pytest.fixture(scope="module")
def profile() -> Profile:
    return load_profile()


@pytest.fixture(scope="module")
def quiet(profile: Profile) -> bench.Figures:
    """Nobody touches the arm for 12 s (a whole period of the task): the whole chain in lockstep."""
    return bench.measure(profile, TouchScript(duration_s=bench.QUIET_S, touch=[]), "quiet")


@pytest.fixture(scope="module")
def jittered(profile: Profile) -> bench.Figures:
    """The same, each command up to 2 ms late and each bridge cycle up to 0.5 ms late (a loaded machine)."""
    return bench.measure(profile, TouchScript(duration_s=bench.QUIET_S, touch=[]), "jittered", jitter_ms=2.0)


# --------------------------------------------------------------------------- the task


def test_the_task_stream_stays_within_the_jerk_and_acceleration_limits(quiet: bench.Figures) -> None:
    assert quiet.cycles > 5000 and quiet.task.sum() > 5000
    assert quiet.jerk.max() <= 1.0 + JERK_TOL
    assert quiet.acc.max() <= 1.0 + JERK_TOL
    assert quiet.error.max() < 1e-5  # the plans are followed to within rounding


def test_the_task_is_no_faster_than_planned(quiet: bench.Figures) -> None:
    assert quiet.task_peak_m_s == pytest.approx(quiet.planned_peak_m_s, rel=0.05)


def test_late_commands_neither_speed_the_task_up_nor_shake_it(quiet: bench.Figures, jittered: bench.Figures) -> None:
    """Plans arriving with the jitter of a loaded machine: the bridge keeps their timeline (the previous plan's),
    so the reference does not jump back and forth with each arrival (it did: a_max at p99, the task 30 % faster)."""
    assert jittered.task_peak_m_s == pytest.approx(jittered.planned_peak_m_s, rel=0.05)
    assert jittered.jerk.max() <= 1.0 + JERK_TOL
    task_acc_p99 = np.percentile(jittered.acc[jittered.task], 99)
    assert task_acc_p99 <= 1.5 * np.percentile(quiet.acc[quiet.task], 99)
    assert np.percentile(jittered.error, 99) < 1e-4


# --------------------------------------------------------------------------- a step, the joint limits

ENV = make_envelope(("a", "b"), {"q_min": np.array([-1.0, -1.0]), "q_max": np.array([1.0, 1.0]),
                                 "v_max": np.array([1.0, 2.0]), "a_max": np.array([10.0, 10.0]),
                                 "j_max": np.array([200.0, 200.0])})


def core(q0=(0.0, 0.0)) -> BridgeCore:
    c = BridgeCore(ENV, np.array(q0), 0, active="p", n_pads=1)
    c.on_planner_alive(True, 0)
    return c


def drive(c: BridgeCore, cycles: int, command, t0: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``cycles`` control cycles, ``command(k, t)`` (or None) arriving before each; q, dq, ddq per cycle."""
    qs, dqs, ddqs = [], [], []
    skin = m.SkinPressure(seq=0, stamp_ns=0, absolute_hpa=[0.0], baseline_hpa=[0.0], change_hpa=[0.0],
                          contact=[False])
    for k in range(cycles):
        t = t0 + (k + 1) * 2 * MS
        if k % 20 == 0:
            c.on_skin(skin, t)
        cmd = command(k, t)
        if cmd is not None:
            c.on_command(cmd, t)
        sp = c.step(t)
        qs.append(sp.q), dqs.append(sp.dq), ddqs.append(sp.ddq)
    return np.array(qs), np.array(dqs), np.array(ddqs)


def pos(q, seq, t, phase="TASK", reflex=0) -> m.PositionCommand:
    return m.PositionCommand(seq=seq, stamp_ns=t, owner="p", q=list(q), trace=TR, phase=phase, reflex_seq=reflex)


def vel(dq, seq, t, phase="REFLEX", reflex=1) -> m.VelocityCommand:
    return m.VelocityCommand(seq=seq, stamp_ns=t, owner="p", dq=list(dq), trace=TR, phase=phase, reflex_seq=reflex)


def test_a_step_is_reached_without_overshoot_within_the_jerk_limit() -> None:
    target = np.array([0.08, -0.05])
    qs, dqs, ddqs = drive(core(), 300, lambda k, t: pos(target, k, t))
    assert qs[-1] == pytest.approx(target, abs=1e-9) and np.abs(dqs[-1]).max() < 1e-9
    assert qs[:, 0].max() <= target[0] + 1e-9 and qs[:, 1].min() >= target[1] - 1e-9  # no overshoot at all
    assert jerk_ratio(ddqs, ENV.j_max).max() <= 1.0 + JERK_TOL
    assert np.all(np.abs(ddqs) <= ENV.a_max * (1 + JERK_TOL)) and np.all(np.abs(dqs) <= ENV.v_max * (1 + JERK_TOL))
    # Time-optimal: joint a's 0.08 rad from rest at 10 rad/s^2 and 200 rad/s^3 takes 0.225 s, not much more.
    arrived = next(k for k in range(len(qs)) if abs(qs[k, 0] - target[0]) < 1e-6)
    assert (arrived + 1) * DT <= 0.235


def test_a_joint_limit_is_approached_within_the_jerk_limit() -> None:
    qs, dqs, ddqs = drive(core(q0=(0.5, 0.0)), 800, lambda k, t: vel([1.0, 0.0], k, t, phase="TASK", reflex=0))
    assert qs[:, 0].max() <= ENV.q_max[0] and qs[-1, 0] > 0.99  # brakes in time, and not far from the limit
    assert abs(dqs[-1, 0]) < 1e-9
    assert jerk_ratio(ddqs, ENV.j_max).max() <= 1.0 + JERK_TOL


@pytest.mark.parametrize(("v", "a"), [(1.0, 0.0), (1.0, 8.0), (1.0, -10.0), (0.05, -10.0), (0.0, 5.0), (-0.3, 2.0)])
def test_one_joints_stop_is_ruckigs_time_optimal_stop(v: float, a: float) -> None:
    """stop_extent and brake (cycle by cycle) against ruckig's own stop of one joint: the same extent, at rest."""
    otg, inp = Ruckig(1), InputParameter(1)
    inp.control_interface = ControlInterface.Velocity
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [10.0], [10.0], [200.0]
    inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [v], [a]
    inp.target_velocity, inp.target_acceleration = [0.0], [0.0]
    path = Trajectory(1)
    assert otg.calculate(inp, path) in (Result.Working, Result.Finished)
    xs = [path.at_time(t)[0][0] for t in np.linspace(0.0, path.duration, 2000)]
    lo, hi = stop_extent(v, a, 10.0, 200.0)
    assert lo == pytest.approx(min(min(xs), 0.0), abs=1e-7) and hi == pytest.approx(max(max(xs), 0.0), abs=1e-7)
    x = 0.0
    for _ in range(round(path.duration / DT) + 2):
        dx, v, a = brake(v, a, DT, 10.0, 200.0)
        x += dx
        assert lo - 1e-12 <= x <= hi + 1e-12
    assert (v, a) == (0.0, 0.0) and x == pytest.approx(path.at_time(path.duration)[0][0], abs=1e-9)


# --------------------------------------------------------------------------- withdrawals, velocity streams, stops


def test_a_withdrawal_stream_is_followed_closely_within_the_jerk_limit(profile: Profile) -> None:
    """A jerk-limited joint-space withdrawal (as the planner plans one, within 90 % of the jerk limit) from the
    task: followed within a milliradian (the reference's jerk is estimated from the stream, and the law has the
    last 10 % of the jerk limit to correct with), at rest where it ends, its onset a cycle after the command's."""
    run = bench.BridgeRun(profile, None)
    env = run.bridge.env
    task = FigureEight(profile.planner.task, DESC)
    ahead = profile.planner.task_ahead_cycles
    ddqs, errors = [], []
    for k in range(300):
        if k % ahead == 0:
            run.cycle(run.command(m.PositionCommand, q=task.position(k * DT).tolist(), period_s=DT,
                                  ahead=[task.position((k + i) * DT).tolist() for i in range(1, ahead + 1)]))
        else:
            run.cycle()
        ddqs.append(run.tracker.ddq.copy())
    q0, v0 = task.position(299 * DT), task.velocity(299 * DT)
    path = bench.withdrawal_path(env, run.tracker.limiter, q0, v0, q0 + np.array([0.0, -0.15, 0.2, 0.1, 0.0, 0.0]))
    for k in range(round(path.duration / DT) + 50):
        q = np.asarray(path.at_time(min((k + 1) * DT, path.duration))[0])
        run.cycle(run.command(m.PositionCommand, q=q.tolist(), phase="REFLEX", reflex_seq=1))
        ddqs.append(run.tracker.ddq.copy())
        errors.append(float(np.abs(run.tracker.q - q).max()))
    assert jerk_ratio(np.array(ddqs), env.j_max).max() <= 1.0 + JERK_TOL
    assert max(errors) < 1e-3 and errors[-1] < 1e-9
    found = bench.onset(profile, "position")
    assert found.bridge_ms <= found.command_ms + 2.0 + 1e-9


def test_a_velocity_stream_and_its_stop_stay_within_the_jerk_limit() -> None:
    c = core()
    qs, dqs, ddqs = drive(c, 150, lambda k, t: vel([0.5, -1.5], k, t))
    assert dqs[-1] == pytest.approx([0.5, -1.5], abs=1e-9)
    # The ramp keeps the command's direction (a Cartesian withdrawal's) all the way.
    moving = np.abs(dqs[:, 1]) > 1e-6
    assert np.allclose(dqs[moving, 0] / dqs[moving, 1], 0.5 / -1.5, rtol=1e-6)
    q2, dq2, ddq2 = drive(c, 200, lambda k, t: None, t0=150 * 2 * MS)  # the stream stops: a stale-command stop
    assert c.status == "stale_command" and np.abs(dq2[-1]).max() == 0.0
    ddq_all = np.vstack([ddqs, ddq2])
    assert jerk_ratio(ddq_all, ENV.j_max).max() <= 1.0 + JERK_TOL


def test_a_smooth_velocity_stream_is_followed_without_lag() -> None:
    """A velocity stream that changes every cycle (a smoothed Cartesian withdrawal) is followed, its rate of
    change fed forward: no lag beyond rounding once under way."""
    ramp = lambda k: 0.6 * (1 - math.cos(min(k * DT, 0.2) * math.pi / 0.2)) / 2  # noqa: E731
    c = core()
    _, dqs, ddqs = drive(c, 200, lambda k, t: vel([ramp(k), -2 * ramp(k)], k, t))
    errors = np.abs(dqs[:, 0] - [ramp(k) for k in range(200)])
    assert errors[30:].max() < 2e-3 and errors[-1] < 1e-9
    assert jerk_ratio(ddqs, ENV.j_max).max() <= 1.0 + JERK_TOL


def test_the_arm_levels_off_at_the_cartesian_speed_limit_within_the_jerk_limit(profile: Profile) -> None:
    """A velocity stream four times too fast: the arm reaches the collaborative speed, not beyond, with its
    acceleration ramped down in time (the limit anticipated), not cut in one cycle."""
    run = bench.BridgeRun(profile, None)
    limiter = run.tracker.limiter
    assert limiter is not None
    q0 = run.tracker.q.copy()
    direction = np.linalg.pinv(MODEL.speed_jacobians(q0)[-1]) @ np.array([0.0, 1.0, 0.0])
    dq = direction * 1.0 / float(limiter.speeds(q0, direction).max())
    ddqs, speeds = [], []
    for _ in range(150):
        run.cycle(run.command(m.VelocityCommand, dq=dq.tolist(), phase="TASK", reflex_seq=0))
        ddqs.append(run.tracker.ddq.copy())
        speeds.append(float(limiter.speeds(run.tracker.q, run.tracker.dq).max()))
    limit = limiter.limits.speed_m_s
    assert max(speeds) <= limit + 1e-3 and speeds[-1] > 0.99 * limit  # levelled off a little below
    assert jerk_ratio(np.array(ddqs), run.bridge.env.j_max).max() <= 1.0 + JERK_TOL


def test_a_stop_begun_while_accelerating_stays_within_the_cartesian_speed_limit(profile: Profile) -> None:
    """Stopping starts from the acceleration the arm has, so its speed first rises; where that would take a
    point past the speed limit, the stop starts at zero acceleration, the joints in proportion."""
    worst, limit = bench.stop_overshoot(profile)
    assert worst <= limit + 1e-3


# --------------------------------------------------------------------------- ruckig refusing an input

def test_an_input_ruckig_rejects_falls_back_to_the_acceleration_limited_law(monkeypatch: pytest.MonkeyPatch) -> None:
    """ruckig raises RuckigError (not a RuntimeError) on some inputs at the edge of its limits (one live
    uniform-reflex session did, with the acceleration exactly at a_max): the bridge crashed with it. The cycle
    now falls back to the acceleration-limited law, still within the envelope, and the arm stays commanded."""
    from ruckig import RuckigError

    c = core()
    drive(c, 5, lambda k, t: vel((0.5, -0.5), k, t))

    def refuse(*_args: object) -> None:
        raise RuckigError("[ruckig] error in step 1, dof: 1 input: ...")

    monkeypatch.setattr(c.tracker.law, "otg", type("Refusing", (), {"calculate": staticmethod(refuse)})())
    qs, dqs, ddqs = drive(c, 50, lambda k, t: vel((0.5, -0.5), 5 + k, t), t0=10 * MS)
    assert np.isfinite(qs).all() and np.abs(dqs[-1] - (0.5, -0.5)).max() < 1e-6  # it keeps following the command
    assert np.all(np.abs(ddqs) <= ENV.a_max * (1 + JERK_TOL)) and np.all(np.abs(dqs) <= ENV.v_max * (1 + JERK_TOL))


def test_a_limit_met_in_a_withdrawal_is_info_and_counted_elsewhere_a_warning() -> None:
    """The envelope shaping a withdrawal (a velocity step ramped at a_max) is expected: info, counted; the same
    step asked for by the task is the planner asking more than the envelope allows: a warning."""
    for phase, level in (("REFLEX", "info"), ("TASK", "warning")):
        c = core()
        drive(c, 3, lambda k, t, phase=phase: vel((0.0, 0.0) if k == 0 else (0.9, -0.9), k, t, phase=phase))
        clips = [e for e in c.events if e.code == "command_clipped"]
        assert clips and {e.level for e in clips} == {level}, (phase, clips)
        assert c.clipped >= 1 and c.clipped_expected == (c.clipped if phase == "REFLEX" else 0)
