"""The bridge's pure parts: the envelope, the command check, the supervisor, the tracker and the guard."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import BridgeSection, Profile
from nwr.common.errors import ConfigError, SafetyError
from nwr.common.robot import load_description
from nwr.services.bridge.backend import SimBackend, guard
from nwr.services.bridge.checks import CheckContext, check_command
from nwr.services.bridge.core import BridgeCore, Setpoint
from nwr.services.bridge.envelope import Envelope, make_envelope
from nwr.services.bridge.main import make_backend
from nwr.services.bridge.tracking import Tracker
from nwr.services.bridge.wiring import envelope_for

MS = 1_000_000
DT = 0.002
TR = m.Trace(0, 0)
JOINTS = ("a", "b")


def lim(**kw) -> Envelope:
    base = dict(q_min=[-1.0, -1.0], q_max=[1.0, 1.0], v_max=[1.0, 2.0], a_max=[10.0, 10.0], j_max=[200.0, 200.0])
    base.update(kw)
    return make_envelope(JOINTS, {k: np.array(v) for k, v in base.items()}, position_jump_rad=0.1)


ENV = lim()


def pos(q, owner="p", seq=1, phase="TASK", stamp=0, reflex=0):
    return m.PositionCommand(seq=seq, stamp_ns=stamp, owner=owner, q=list(q), trace=TR, phase=phase, reflex_seq=reflex)


def vel(dq, owner="p", seq=1, phase="REFLEX", stamp=0, reflex=1):
    return m.VelocityCommand(seq=seq, stamp_ns=stamp, owner=owner, dq=list(dq), trace=TR, phase=phase,
                             reflex_seq=reflex)


def skin(seq=0, pads=3):
    return m.SkinPressure(seq=seq, stamp_ns=0, absolute_hpa=[0.0] * pads, baseline_hpa=[0.0] * pads,
                          change_hpa=[0.0] * pads, contact=[False] * pads)


# --------------------------------------------------------------------------- envelope


def test_envelope_defaults_come_from_the_robot_description():
    desc = load_description()
    env, q0, pads = envelope_for(Profile())
    assert env.joints == desc.joints and pads == len(desc.pads)
    for name in ("q_min", "q_max", "v_max", "a_max", "j_max"):
        assert np.array_equal(getattr(env, name), getattr(desc, name)), name
    assert np.array_equal(q0, desc.home)
    assert "shoulder_pan_joint" in env.describe()


def test_profile_tightens_but_never_loosens():
    env = make_envelope(JOINTS, {k: np.asarray(getattr(ENV, k)) for k in ("q_min", "q_max", "v_max", "a_max", "j_max")},
                        speed_fraction=0.5, tighter={"q_max": [0.5, 1.0], "a_max": [4.0, 20.0 / 2]})
    assert env.q_max.tolist() == [0.5, 1.0]
    assert env.v_max.tolist() == [0.5, 1.0]
    assert env.a_max.tolist() == [4.0, 10.0]
    with pytest.raises(ConfigError, match=r"bridge.v_max\[1\] = 3.0 is looser"):
        make_envelope(JOINTS, {k: np.asarray(getattr(ENV, k)) for k in ("q_min", "q_max", "v_max", "a_max", "j_max")},
                      tighter={"v_max": [1.0, 3.0]})
    with pytest.raises(ConfigError, match="one per joint"):
        make_envelope(JOINTS, {k: np.asarray(getattr(ENV, k)) for k in ("q_min", "q_max", "v_max", "a_max", "j_max")},
                      tighter={"q_min": [0.0]})
    with pytest.raises(ConfigError, match="q_min"):
        make_envelope(JOINTS, {k: np.asarray(getattr(ENV, k)) for k in ("q_min", "q_max", "v_max", "a_max", "j_max")},
                      tighter={"q_min": [0.9, 0.0], "q_max": [0.5, 1.0]})


def test_envelope_from_profile_rejects_looser_limits():
    profile = Profile()
    profile.bridge.v_max = [10.0] * 6
    with pytest.raises(ConfigError, match="looser"):
        envelope_for(profile)


def test_braking_speed_stops_within_the_distance():
    d = np.array([0.0, 0.05])
    v = ENV.braking_speed(d)
    assert v[0] == 0.0
    # The jerk-limited stop from v (at constant speed) takes v^2/(2a) + v a / (2j).
    assert v[1] ** 2 / (2 * 10.0) + v[1] * 10.0 / 400.0 == pytest.approx(0.05)


# --------------------------------------------------------------------------- the command check


def ctx(**kw):
    base = dict(active="p", alive=True, q_ref=np.zeros(2), last_seq=None, seq_restart_gap=100)
    base.update(kw)
    return CheckContext(**base)


@pytest.mark.parametrize(
    ("cmd", "context", "code", "text"),
    [
        (pos([0.0, 0.0], owner="intruder"), {}, "command_rejected", "not the active planner 'p'"),
        (pos([0.0, 0.0]), {"alive": False}, "command_rejected", "no liveliness token"),
        (pos([0.0]), {}, "command_invalid", "1 joint values"),
        (vel([0.0, 0.0, 0.0]), {}, "command_invalid", "3 joint values"),
        (vel([0.0, math.nan]), {}, "command_invalid", "non-finite"),
        (pos([math.inf, 0.0]), {}, "command_invalid", "non-finite"),
        (pos([0.0, 0.0], seq=5), {"last_seq": 5}, "command_out_of_order", "duplicated"),
        (pos([0.0, 0.0], seq=3), {"last_seq": 5}, "command_out_of_order", "out of order"),
        (pos([0.0, 0.0], seq=455), {"last_seq": 5, "since_last_ns": 2_000_000}, "command_seq_jump",
         "450 ahead of the last accepted (5) 2.0 ms ago"),
        (pos([0.0, 0.3]), {}, "command_jump", "0.3000 rad from the commanded"),
        ("not a command", {}, "command_invalid", "not a joint command"),
    ],
)
def test_rejections_name_value_limit_and_sender(cmd, context, code, text):
    out = check_command(cmd, ENV, ctx(**context))
    assert out.rejected and out.values is None
    assert [e.code for e in out.events] == [code]
    assert text in out.events[0].message
    if not isinstance(cmd, str):
        assert repr(cmd.owner) in out.events[0].message


def test_phase_outside_the_modes_is_rejected():
    cmd = pos([0.0, 0.0])
    cmd.phase = "DANCE"  # type: ignore[assignment]  # a bug elsewhere, not a decodable message
    out = check_command(cmd, ENV, ctx())
    assert out.rejected and "phase 'DANCE'" in out.events[0].message


def test_valid_commands_pass_untouched():
    for cmd in (pos([0.05, -0.05]), vel([0.5, -1.5])):
        out = check_command(cmd, ENV, ctx())
        assert not out.rejected and not out.clipped and not out.events
        assert out.values is not None


def test_a_seq_ahead_within_what_a_planner_counts_in_the_time_passes():
    # One command per cycle, a few lost, or a planner silent for a second: its next seq is no jump.
    for seq, since_ns in ((6, 2_000_000), (25, 2_000_000), (505, 1_000_000_000)):
        assert not check_command(pos([0.0, 0.0], seq=seq), ENV, ctx(last_seq=5, since_last_ns=since_ns)).rejected
    assert check_command(pos([0.0, 0.0], seq=26), ENV, ctx(last_seq=5, since_last_ns=0)).rejected


def test_restarted_planner_is_accepted():
    out = check_command(pos([0.0, 0.0], seq=0), ENV, ctx(last_seq=5000))
    assert not out.rejected and out.restarted


def test_position_beyond_a_joint_limit_is_clipped_to_it():
    out = check_command(pos([1.05, 0.0]), ENV, ctx(q_ref=np.array([0.98, 0.0])))
    assert out.clipped and out.values.tolist() == [1.0, 0.0]
    assert "beyond q_max 1.0000" in out.events[0].message and "'p'" in out.events[0].message


def test_velocity_above_the_limit_is_scaled_keeping_its_direction():
    out = check_command(vel([3.0, 2.0]), ENV, ctx())
    assert out.clipped
    assert out.values == pytest.approx([1.0, 2.0 / 3.0])
    assert "speed 3.0000 rad/s above v_max 1.0000" in out.events[0].message


# --------------------------------------------------------------------------- the supervisor


def core(q0=(0.0, 0.0), **kw) -> BridgeCore:
    c = BridgeCore(kw.pop("env", ENV), np.array(q0), 0, active="p", n_pads=3, **kw)
    c.on_planner_alive(True, 0)
    c.on_skin(skin(), 0)
    return c


class Run:
    """Drives a core at 500 Hz and keeps what it commanded."""

    def __init__(self, c: BridgeCore, t_ns: int = 0) -> None:
        self.c, self.t = c, t_ns
        self.q, self.dq, self.status, self.modes = [], [], [], []
        self.seq = 0
        self.skin_every = 20

    def cycles(self, n, command=None, skin_ok=True, dt=DT):
        for _ in range(n):
            self.t += round(dt * 1e9)
            if skin_ok and (self.t // MS) % 40 < 2:
                self.c.on_skin(skin(), self.t)
            if command is not None:
                cmd = command(self.seq, self.t)
                if cmd is not None:
                    self.c.on_command(cmd, self.t)
                self.seq += 1
            sp = self.c.step(self.t)
            self.q.append(sp.q)
            self.dq.append(sp.dq)
            self.status.append(self.c.status)
            self.modes.append(sp.mode)
        return self

    def arrays(self):
        return np.array(self.q), np.array(self.dq)


def assert_within(env, qs, dqs, dt=DT, accel_tol=1e-6):
    assert np.all(qs >= env.q_min - 1e-12) and np.all(qs <= env.q_max + 1e-12)
    assert np.all(np.abs(dqs) <= env.v_max + 1e-9)
    acc = np.diff(dqs, axis=0) / dt
    assert np.all(np.abs(acc) <= env.a_max * (1 + accel_tol) + 1e-6), np.abs(acc).max(axis=0)


def test_velocity_stream_is_speed_and_acceleration_limited():
    c = core()
    r = Run(c).cycles(200, lambda s, t: vel([0.5, -5.0], seq=s, stamp=t))
    qs, dqs = r.arrays()
    assert_within(ENV, qs, dqs)
    assert dqs[-1] == pytest.approx([0.5 * 2 / 5.0, -2.0])  # scaled uniformly to the limit of joint b
    assert c.clipped > 0 and c.status == "ok"


def test_smooth_position_stream_is_followed_closely_with_jittery_timing():
    env = lim(q_min=[-2.0, -2.0], q_max=[2.0, 2.0])
    c = core(env=env)
    rng = np.random.default_rng(3)
    # Starts at rest, as the planner's streams do.
    traj = lambda k: np.array([0.4 * (1 - math.cos(k * DT * 2.0)), -0.2 * (1 - math.cos(k * DT * 3.0))])  # noqa: E731
    t, sent, qs, dqs, errs, stamps = 0, 0, [], [], [], []
    for k in range(1500):
        # The planner publishes at 500 Hz with its own jitter; the bridge ticks out of phase.
        t = k * 2 * MS + int(rng.uniform(0, 0.9) * MS)
        while sent <= k and sent * 2 * MS + int(rng.uniform(0, 0.5) * MS) <= t:
            c.on_command(pos(traj(sent), seq=sent, stamp=sent * 2 * MS + int(rng.uniform(0, 0.3) * MS)), t)
            sent += 1
        if k % 20 == 0:
            c.on_skin(skin(), t)
        sp = c.step(t)
        qs.append(sp.q), dqs.append(sp.dq), stamps.append(t)
        errs.append(np.max(np.abs(sp.q - traj(sent - 1))))
    qs, dqs = np.array(qs), np.array(dqs)
    assert max(errs) < 0.005  # a cycle or two of the stream's motion
    acc = np.diff(dqs, axis=0) / (np.diff(stamps)[:, None] / 1e9)
    assert np.all(np.abs(acc) <= env.a_max + 1e-6)
    assert c.status == "ok"


def test_position_step_is_reached_without_overshoot():
    c = core()
    r = Run(c).cycles(400, lambda s, t: pos([0.08, -0.05], seq=s, stamp=t))
    qs, dqs = r.arrays()
    assert_within(ENV, qs, dqs)
    assert qs[-1] == pytest.approx([0.08, -0.05], abs=1e-6)
    # Discretisation leaves at most a few cycles of motion of overshoot.
    assert qs[:, 0].max() <= 0.08 + 3e-3 and qs[:, 1].min() >= -0.05 - 3e-3


def test_stale_commands_bring_the_arm_to_rest_with_a_jerk_limited_stop():
    env = lim(q_min=[-5.0, -5.0], q_max=[5.0, 5.0])
    c = core(env=env, command_timeout_s=0.02)
    r = Run(c).cycles(300, lambda s, t: vel([1.0, -1.5], seq=s, stamp=t))
    q_before = r.q[-1].copy()
    r.cycles(300)
    qs, dqs = r.arrays()
    assert_within(env, qs, dqs)
    jerk = np.diff(dqs, n=2, axis=0) / DT**2
    assert np.all(np.abs(jerk[310:]) <= env.j_max * 1.05 + 1e-6)
    assert dqs[-1] == pytest.approx([0.0, 0.0]) and r.modes[-1] == "hold"
    assert c.status == "stale_command"
    # At rest within the timeout plus the stopping time it reported.
    rest = next(i for i in range(300, 600) if np.all(np.abs(dqs[i]) < 1e-9))
    assert (rest - 299) * DT <= 0.02 + c.tracker.stop_time_s + 2 * DT
    # The reported stopping distance is the distance it travelled once stopping.
    start = next(i for i in range(300, 600) if r.status[i] == "stale_command")
    assert qs[-1] - qs[start - 1] == pytest.approx(c.tracker.stop_distance, abs=5e-3)
    assert np.all(np.abs(qs[-1] - q_before) > 0)
    events = [e.code for e in c.drain_events()]
    assert "stale_command" in events
    state = c.state(0, r.t, qs[-1], dqs[-1], "sim")
    assert state.status == "stale_command" and state.stop_time_s > 0 and not state.stopping


def test_a_fresh_command_resumes_after_a_stale_stop():
    c = core()
    r = Run(c).cycles(50, lambda s, t: vel([0.3, 0.0], seq=s, stamp=t))
    r.cycles(30)
    assert c.status == "stale_command"
    r.cycles(100, lambda s, t: vel([0.3, 0.0], seq=s, stamp=t))
    qs, dqs = r.arrays()
    assert c.status == "ok" and dqs[-1][0] == pytest.approx(0.3)
    assert_within(ENV, qs, dqs)


def test_stale_skin_holds_task_and_return_but_lets_a_reflex_finish():
    c = core()
    task = lambda s, t: pos([min(0.0005 * s, 0.05), 0.0], seq=s, stamp=t)  # noqa: E731
    r = Run(c).cycles(20, task)
    assert c.status == "ok"
    r.cycles(100, task, skin_ok=False)
    assert c.status == "stale_skin" and np.all(np.abs(r.dq[-1]) < 1e-9)
    assert "stale_skin" in [e.code for e in c.drain_events()]
    held = r.q[-1].copy()
    # A reflex (phase REFLEX) is followed even without skin...
    r.cycles(50, lambda s, t: vel([-0.2, 0.0], seq=s, stamp=t), skin_ok=False)
    assert c.status == "ok" and r.dq[-1][0] == pytest.approx(-0.2)
    # ...and the return after it is held again.
    r.cycles(100, lambda s, t: pos(r.q[-1], seq=s, stamp=t, phase="RETURNING"), skin_ok=False)
    assert c.status == "stale_skin" and np.all(np.abs(r.dq[-1]) < 1e-9)
    # Skin back: the task goes on.
    r.cycles(50, lambda s, t: pos(held, seq=s, stamp=t), skin_ok=True)
    assert c.status == "ok"
    qs, dqs = r.arrays()
    assert_within(ENV, qs, dqs)


def test_no_skin_yet_holds_the_task():
    c = BridgeCore(ENV, np.zeros(2), 0, active="p", n_pads=3)
    c.on_planner_alive(True, 0)
    c.on_command(pos([0.01, 0.0], seq=0), MS)
    assert c.status == "stale_skin" and "no skin data yet" in c.detail
    assert c.skin_age_s(MS) == -1.0
    # The skin is starting (the gateway starts last): reported, but not as a fault.
    assert [e.level for e in c.drain_events() if e.code == "stale_skin"] == ["info"]


def test_foreign_skin_does_not_count_as_fresh():
    c = BridgeCore(ENV, np.zeros(2), 0, active="p", n_pads=3)
    c.on_skin(skin(pads=4), MS)
    assert c.last_skin_ns is None and c.drain_events()[0].code == "skin_invalid"


def test_lost_planner_stops_the_arm_and_only_its_return_resumes():
    c = core()
    r = Run(c).cycles(100, lambda s, t: vel([0.5, 0.5], seq=1000 + s, stamp=t))
    c.on_planner_alive(False, r.t)
    assert c.status == "planner_lost"
    r.cycles(200, lambda s, t: vel([0.5, 0.5], seq=2000 + s, stamp=t))  # a zombie or a spoofer: rejected
    qs, dqs = r.arrays()
    assert_within(ENV, qs, dqs)
    assert c.status == "planner_lost" and np.all(dqs[-1] == 0.0) and c.rejected == 200
    c.on_planner_alive(True, r.t)
    assert c.status == "idle"
    r.cycles(10, lambda s, t: vel([0.1, 0.0], seq=s - 300, stamp=t))  # counts from 0 again
    assert c.status == "ok"


def test_joint_limit_is_approached_with_room_to_brake():
    c = core(q0=(0.5, 0.0))
    r = Run(c).cycles(800, lambda s, t: vel([1.0, 0.0], seq=s, stamp=t))
    qs, dqs = r.arrays()
    assert_within(ENV, qs, dqs)
    assert qs[:, 0].max() <= 1.0 and qs[-1, 0] > 0.99
    assert "joint_limit" in [e.code for e in c.drain_events()]


def test_stop_near_a_joint_limit_never_passes_it():
    c = core(q0=(0.5, 0.0))
    r = Run(c).cycles(180, lambda s, t: vel([1.0, 0.0], seq=s, stamp=t))
    r.cycles(200)
    qs, dqs = r.arrays()
    assert_within(ENV, qs, dqs)


def test_onset_is_reported_once_per_reflex():
    c = core()
    first = c.on_command(vel([0.1, 0.0], seq=1, reflex=3), MS)
    again = c.on_command(vel([0.1, 0.0], seq=2, reflex=3), 2 * MS)
    assert first.onset and not again.onset
    assert c.accepted == TR and c.accepted_ns == MS


def test_backend_fault_holds_and_waits_for_fresh_commands():
    c = core()
    r = Run(c).cycles(50, lambda s, t: vel([0.3, 0.0], seq=s, stamp=t))
    c.on_fault("protective_stop", "check the cell", np.array([0.2, 0.0]), r.t)
    assert c.status == "protective_stop" and c.tracker.q.tolist() == [0.2, 0.0]
    verdict = c.on_command(vel([0.3, 0.0], seq=60), r.t)
    assert not verdict.accepted and c.step(r.t + 2 * MS).mode == "hold"
    c.on_fault(None, "", np.array([0.2, 0.0]), r.t + 4 * MS)
    assert c.status == "idle"
    codes = [e.code for e in c.drain_events()]
    assert {"protective_stop", "command_ignored", "robot_recovered"} <= set(codes)


def test_shutdown_is_a_controlled_stop():
    c = core()
    r = Run(c).cycles(100, lambda s, t: vel([0.8, -0.8], seq=s, stamp=t))
    c.request_stop(r.t, "test")
    r.cycles(200, lambda s, t: vel([0.8, -0.8], seq=500 + s, stamp=t))  # ignored once stopping for good
    qs, dqs = r.arrays()
    assert_within(ENV, qs, dqs)
    assert c.status == "stopped" and np.all(dqs[-1] == 0.0)


def test_bridge_core_refuses_an_initial_pose_outside_the_limits():
    with pytest.raises(ConfigError, match="outside the joint limits"):
        BridgeCore(ENV, np.array([2.0, 0.0]), 0, active="p", n_pads=3)


# --------------------------------------------------------------------------- guard and sim backend


def test_guard_passes_what_the_core_sends_and_clips_anything_else():
    sp = Setpoint("position", np.array([0.001, 0.0]), np.array([0.5, 0.0]), np.zeros(2), DT)
    assert guard(ENV, np.zeros(2), sp, DT) == (sp, None)
    wild = Setpoint("position", np.array([0.5, -3.0]), np.array([5.0, 0.0]), np.zeros(2), DT)
    sent, why = guard(ENV, np.zeros(2), wild, DT)
    assert why is not None and "clipped" in why
    assert np.all(np.abs(sent.q) <= ENV.v_max * DT * 1.5 + 1e-9) and sent.dq[0] == 1.0
    with pytest.raises(SafetyError, match="non-finite"):
        guard(ENV, np.zeros(2), Setpoint("velocity", np.zeros(2), np.array([math.nan, 0.0]), np.zeros(2)), DT)


def test_sim_backend_returns_what_it_sent():
    backend = SimBackend(ENV, DT, np.zeros(2))
    backend.connect()
    sent = backend.send_action(Setpoint("position", np.array([0.5, 0.0]), np.zeros(2), np.zeros(2), DT))
    assert sent.q[0] == pytest.approx(ENV.v_max[0] * DT * 1.5 + 1e-9) and backend.guarded == 1
    assert backend.get_observation().q.tolist() == sent.q.tolist()
    backend.send_action(Setpoint("hold", sent.q, np.ones(2), np.zeros(2), DT))
    assert backend.get_observation().dq.tolist() == [0.0, 0.0]
    backend.disconnect()


# --------------------------------------------------------------------------- the real backend's gate


@pytest.mark.parametrize(
    ("ip", "confirmed", "error"),
    [("", True, "--robot-ip"), ("192.0.2.10", False, "--i-am-next-to-the-robot")],
)
def test_real_backend_needs_an_ip_and_a_confirmation(ip, confirmed, error):
    cfg = BridgeSection(backend="ur_rtde")
    env, q0, _ = envelope_for(Profile())
    with pytest.raises(ConfigError, match=error):
        make_backend(cfg, env, q0, argparse.Namespace(robot_ip=ip, confirmed=confirmed))


def test_real_backend_is_built_without_connecting():
    cfg = BridgeSection(backend="ur_rtde")
    env, q0, _ = envelope_for(Profile())
    backend = make_backend(cfg, env, q0, argparse.Namespace(robot_ip="192.0.2.10", confirmed=True))
    assert backend.name == "ur_rtde" and backend.control is None  # type: ignore[attr-defined]


def test_print_envelope(capsys):
    from nwr.services.bridge.main import run

    args = argparse.Namespace(active=None, backend=None, robot_ip="", confirmed=False, print_envelope=True)
    assert run(Profile(), args) == 0
    out = capsys.readouterr().out
    assert "shoulder_pan_joint" in out and "2.094" in out


def test_a_continuous_stream_the_arm_lags_is_not_a_jump():
    c = core(env=lim(q_min=[-5.0, -5.0], q_max=[5.0, 5.0]))
    # 1.5 v_max on joint a: the arm follows at the limit and falls behind by
    # more than position_jump_rad, but each target continues the last one.
    r = Run(c).cycles(300, lambda s, t: pos([min(1.5 * 1.0 * DT * s, 3.0), 0.0], seq=s, stamp=s * 2 * MS))
    qs, dqs = r.arrays()
    assert_within(c.env, qs, dqs)
    assert c.rejected == 0 and 1.5 * DT * 299 - qs[-1, 0] > 0.1
    assert "command_clipped" in [e.code for e in c.drain_events()]


def test_stale_pain_holds_the_task_like_stale_skin():
    """A dead gain estimator: skin/pressure still flows, skin/pain does not; the task must not go on blind."""
    c = core()
    pain = m.SkinPain(seq=0, stamp_ns=0, trace=TR, model="continuous", level=[1] * 3, gain=[0.0] * 3)
    c.on_pain(pain, 0)
    c.on_command(pos([0.0, 0.0], seq=1, stamp=1 * MS), 1 * MS)
    assert c.status == "ok"
    t = 1 * MS
    for i in range(100):  # 200 ms: skin keeps coming, pain stopped at t = 0
        t += 2 * MS
        c.on_skin(skin(i), t)
        c.on_command(pos([0.0, 0.0], seq=2 + i, stamp=t), t)
        c.step(t)
    assert c.status == "stale_skin" and "gain estimator" in c.detail
    c.on_pain(pain, t + MS)
    assert c.status == "ok"
    bad = m.SkinPain(seq=1, stamp_ns=0, trace=TR, model="continuous", level=[1], gain=[0.0])
    c.on_pain(bad, t + 2 * MS)
    assert any(e.code == "pain_invalid" for e in c.drain_events())


def test_a_command_on_another_planners_key_is_refused_whatever_owner_it_claims():
    """Each planner commands on robot/command/<name>, which only its certificate may put on: the key names it."""
    c = core()
    verdict = c.on_command(vel([0.5, 0.0], seq=1, stamp=MS), MS, publisher="standby")  # claims owner "p"
    assert not verdict.accepted and c.rejected == 1
    event = c.drain_events()[-1]
    assert event.code == "command_spoofed" and event.level == "error"
    assert "robot/command/standby" in event.message and "claims owner 'p'" in event.message
    assert c.on_command(vel([0.5, 0.0], seq=2, stamp=2 * MS), 2 * MS, publisher="p").accepted
    assert c.rejected == 1


# --------------------------------------------------------------------------- commands planned ahead


def plan(q, ahead, seq=1, period=DT, owner="p", stamp=0):
    cmd = pos(q, owner=owner, seq=seq, stamp=stamp)
    cmd.ahead = [list(row) for row in ahead]
    cmd.period_s = period
    return cmd


@pytest.mark.parametrize(
    ("ahead", "period", "text"),
    [
        ([[0.0, 0.0]], 0.0, "period_s 0.0"),
        ([[0.0, 0.0]], 0.2, "period_s 0.2"),
        ([[0.0, 0.0]] * 60, DT, "cover more than 0.1 s"),
        ([[0.0, 0.0], [0.0]], DT, "does not have 2 joint values"),
        ([[0.0, 0.0], [0.0, math.nan]], DT, "non-finite"),
    ],
)
def test_setpoints_ahead_that_cannot_be_trusted_reject_the_command(ahead, period, text):
    out = check_command(plan([0.0, 0.0], ahead, period=period), ENV, ctx())
    assert out.rejected and out.values is None and out.ahead is None
    assert out.events[0].code == "command_invalid" and text in out.events[0].message


def test_a_jump_between_setpoints_ahead_rejects_the_command():
    out = check_command(plan([0.0, 0.0], [[0.01, 0.0], [0.01, 0.2]]), ENV, ctx())
    assert out.rejected and out.events[0].code == "command_jump"
    assert "joint b setpoint 2 ahead moves 0.2000 rad" in out.events[0].message


def test_setpoints_ahead_beyond_a_joint_limit_are_clipped():
    out = check_command(plan([0.98, 0.0], [[0.99, 0.0], [1.01, 0.0]]), ENV, ctx(q_ref=np.array([0.98, 0.0])))
    assert not out.rejected and out.clipped
    assert out.ahead is not None and out.ahead.tolist() == [[0.99, 0.0], [1.0, 0.0]]
    assert out.events[0].code == "command_clipped"


def test_a_plan_is_followed_between_its_commands_and_times_out_after_its_end():
    env = lim(q_min=[-2.0, -2.0], q_max=[2.0, 2.0])
    c = core(env=env, command_timeout_s=0.02)
    traj = lambda k: np.array([0.3 * (1 - math.cos(k * DT * 2.0)), -0.1 * (1 - math.cos(k * DT * 3.0))])  # noqa: E731
    n = 10

    def every_tenth(s, t):
        if s % n:
            return None
        return plan(traj(s), [traj(s + k) for k in range(1, n + 1)], seq=s // n, stamp=t)

    r = Run(c).cycles(1000, every_tenth)
    qs, dqs = r.arrays()
    assert_within(env, qs, dqs)
    # Followed as closely as the same motion sent one command per cycle (the
    # tracker's own lag of about a cycle's motion, ~1 mrad here).
    single = Run(core(env=env)).cycles(1000, lambda s, t: pos(traj(s), seq=s, stamp=t)).arrays()[0]
    errors = np.abs(qs - [traj(k) for k in range(1000)])[100:].max()
    assert errors <= np.abs(single - [traj(k) for k in range(1000)])[100:].max() + 1e-6
    assert errors < 2e-3
    assert c.status == "ok" and c.tracker.covered_ns == n * 2 * MS
    # The planner falls silent: the plan carries the arm to its end, then the timeout stops it.
    r.cycles(60)
    # The last command came on cycle 990: its plan reaches cycle 1000, the 20 ms timeout cycle 1010.
    assert r.status[990:1011] == ["ok"] * 21 and r.status[1011] == "stale_command"
    assert c.status == "stale_command"
    assert "past the 20 ms the last one planned ahead" in c.detail


def test_a_reflex_after_a_plan_starts_from_where_the_plan_is():
    c = core()
    c.on_command(plan([0.0, 0.0], [[0.002 * k, 0.0] for k in range(1, 11)]), 0)
    for k in range(1, 6):
        c.step(k * 2 * MS)
    # Ten cycles later the plan is at 0.02 rad: a reflex starting at 0.0195 is no jump ...
    assert check_command(pos([0.0195, 0.0], seq=2), ENV, ctx(q_ref=c.tracker.planned(20 * MS)[0])).events == []
    verdict = c.on_command(pos([0.0195, 0.0], seq=2, phase="REFLEX", reflex=1, stamp=20 * MS), 20 * MS)
    assert verdict.accepted and verdict.onset and c.tracker.plan is None and c.tracker.covered_ns == 0
    # ... and the stream carries on at the plan's speed (1 rad/s) until its own period is known.
    assert c.tracker.v_ff.tolist() == pytest.approx([1.0, 0.0])
    # A target far from where the plan is now is refused as a jump.
    c.on_command(plan([0.0, 0.0], [[0.012 * k, 0.0] for k in range(1, 11)], seq=3), 30 * MS)
    c.step(30 * MS + 20 * MS)
    verdict = c.on_command(pos([0.0, 0.0], seq=4), 50 * MS)
    assert not verdict.accepted and "command_jump" in [e.code for e in c.drain_events()]


def test_a_plan_faster_than_the_limits_is_followed_at_the_limit():
    c = core()
    c.drain_events()
    verdict = c.on_command(plan([0.0, 0.0], [[0.004 * k, 0.0] for k in range(1, 11)]), 0)  # 2 rad/s, v_max 1
    assert verdict.accepted and c.clipped == 1
    assert "planned to move at 2.000 rad/s, v_max 1.000 rad/s" in c.drain_events()[0].message
    assert c.tracker.plan_v[:, 0].tolist() == pytest.approx([1.0] * 10)


# --------------------------------------------------------------------------- per-joint arithmetic = numpy's


def _numpy_limit(env, q, dq, v_des, h, target=None):
    """The tracker's limits as numpy expressions: the reference the per-joint floats must equal bit for bit."""
    if target is not None:
        e = target - q
        v_des = v_des + np.sign(e) * np.minimum(np.abs(e) / h, np.sqrt(2.0 * env.a_max * np.abs(e)))
    v_des = np.minimum(np.maximum(v_des, -env.v_max), env.v_max)
    v_hi = env.braking_speed(env.q_max - q)
    v_lo = -env.braking_speed(q - env.q_min)
    bounded = np.minimum(np.maximum(v_des, v_lo), v_hi)
    v = np.minimum(np.maximum(bounded, dq - env.a_max * h), dq + env.a_max * h)
    q1 = np.minimum(np.maximum(q + 0.5 * (dq + v) * h, env.q_min), env.q_max)
    return q1, v, (v - dq) / h


def _numpy_guard(env, previous, sp, dt):
    dq = np.minimum(np.maximum(sp.dq, -env.v_max), env.v_max)
    step = env.v_max * max(sp.h, dt) * 1.5 + 1e-9
    q = sp.q
    if sp.mode == "position":
        q = np.minimum(np.maximum(np.minimum(np.maximum(sp.q, previous - step), previous + step), env.q_min),
                       env.q_max)
    return q, dq


def test_the_tracker_and_the_guard_compute_what_numpy_computes():
    desc = load_description()
    env, _q0, _pads = envelope_for(Profile())
    rng = np.random.default_rng(11)
    n = len(desc.joints)
    for trial in range(3000):
        t = Tracker(env, desc.home.copy(), 0)
        t.q = rng.uniform(env.q_min, env.q_max)
        if trial % 10 == 0:  # at a limit exactly, and at rest
            t.q[trial % n] = env.q_max[trial % n]
        t.dq = rng.uniform(-env.v_max, env.v_max) * rng.choice([0.0, 0.1, 1.0])
        h = float(rng.choice([0.002, 0.0015, 0.05, 1e-6]))
        v_des = rng.uniform(-2 * env.v_max, 2 * env.v_max) * rng.choice([0.0, 0.01, 1.0])
        target = None
        if trial % 2:
            target = np.clip(t.q + rng.normal(0, 10.0 ** rng.integers(-6, 0), n), env.q_min, env.q_max)
            if trial % 7 == 0:
                target = t.q.copy()  # e = 0 exactly
        expected = _numpy_limit(env, t.q, t.dq, v_des, h, target)
        t._limit(v_des.tolist(), h, None if target is None else target.tolist(), "p")
        for got, want in zip((t.q, t.dq, t.ddq), expected):
            assert got.tolist() == want.tolist()  # bit for bit, not approximately
        previous = t.q + rng.normal(0, 0.01, n)
        sp = Setpoint(str(rng.choice(["position", "velocity"])), t.q + rng.normal(0, 0.02, n),
                      t.dq * rng.choice([1.0, 3.0]), t.ddq, h)
        sent, why = guard(env, previous, sp, 0.002)
        q_ref, dq_ref = _numpy_guard(env, previous, sp, 0.002)
        assert sent.q.tolist() == q_ref.tolist() and sent.dq.tolist() == dq_ref.tolist()
        assert (why is None) == (q_ref.tolist() == sp.q.tolist() and dq_ref.tolist() == sp.dq.tolist())


def test_every_fault_of_the_controller_and_its_end_is_reported_however_soon_after_the_last():
    """A program stopped 0.3 s after an emergency stop's restart is heard: fault changes are never rate limited."""
    from nwr.common.clock import ManualClock
    from nwr.common.journal import Untracked
    from nwr.services.bridge.backend import Observation
    from nwr.services.bridge.wiring import BridgeWiring

    class Faulting(SimBackend):
        fault: m.RobotStatus | None = None

        def get_observation(self) -> Observation:
            return Observation(self.q.copy(), self.dq.copy(), self.fault, "injected")

    profile = Profile()
    env, q0, _ = envelope_for(profile)
    backend = Faulting(env, 1.0 / profile.bridge.rate_hz, q0)
    clock = ManualClock()
    clock.t_ns = 10**9
    reports: list[tuple[str, float]] = []
    wiring = BridgeWiring(profile, journal=Untracked(clock), out=lambda k, msg: None, backend=backend,
                          diag=lambda level, code, message, every_s=1.0: reports.append((code, every_s)))
    for fault in ("emergency_stop", None, "script_not_running", None, "script_not_running", None):
        backend.fault = fault
        for _ in range(3):
            wiring.tick()
            clock.t_ns += 2_000_000
    changes = [r for r in reports if r[0] in ("emergency_stop", "script_not_running", "robot_recovered")]
    assert [code for code, _ in changes] == ["emergency_stop", "robot_recovered", "script_not_running",
                                             "robot_recovered", "script_not_running", "robot_recovered"]
    assert {every_s for _, every_s in changes} == {0.0}
    assert all(every_s == 1.0 for code, every_s in reports if (code, every_s) not in changes)


def test_the_backends_are_the_modules_of_their_package_and_a_real_arm_needs_its_address_and_a_person() -> None:
    from nwr.common.errors import ConfigError
    from nwr.services.bridge import backends
    from nwr.services.bridge.main import check_arm_flags

    assert backends.names() == ["franky", "physics", "sim", "ur_rtde"]
    assert not backends.plugin("sim").REAL_ARM
    assert backends.plugin("ur_rtde").REAL_ARM and backends.plugin("franky").REAL_ARM
    with pytest.raises(ConfigError,
                       match="bridge.backend = 'franka' is no backend; there are: franky, physics, sim, ur_rtde"):
        backends.plugin("franka")
    check_arm_flags("sim", "", False)
    check_arm_flags("ur_rtde", "192.0.2.10", True)
    with pytest.raises(ConfigError, match="--robot-ip"):
        check_arm_flags("ur_rtde", "", True)
    with pytest.raises(ConfigError, match="for a real arm's backend"):
        check_arm_flags("sim", "192.0.2.10", False)
