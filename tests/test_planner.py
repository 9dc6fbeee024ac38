"""The planner's state machine, task and Cartesian reflex, driven without a network."""

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import PlannerSection, load_profile
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner.core import Planner
from nwr.services.planner.reflexes import damped_pinv, scale_to_limits

DESC = load_description()
MODEL = RobotModel(DESC)
N_PADS = len(DESC.pads)
DT_NS = 2_000_000


def touch(pad: int, gain: float) -> m.Contact:
    info = DESC.pads[pad]
    return m.Contact(pad=pad, name=info.name, region=info.region, change_hpa=25.0, level=4, gain=gain)


class Sim:
    """Drives a planner like the pipeline does: commands integrated exactly."""

    def __init__(self, cfg: PlannerSection | None = None):
        self.p = Planner(cfg or PlannerSection(), DESC, MODEL)
        self.t = 0
        self.seq = 0
        self.commands: list[m.Command] = []
        self.qs: list[np.ndarray] = []
        self.modes: list[str] = []
        self.p.on_state(DESC.home.copy(), following=True)

    def step(self, n=1):
        for _ in range(n):
            self.t += DT_NS
            before = self.p.q
            cmd = self.p.step(self.t)
            if cmd is not None:
                self.record(cmd)
            elif self.p.q is not before:  # a task cycle the last command planned ahead
                self.record(None)
            # else: the tick after an event-driven first command (no motion)

    def record(self, cmd):
        if cmd is not None:
            self.commands.append(cmd)
        self.qs.append(self.p.q.copy())
        self.modes.append(self.p.mode)

    def until(self, mode, limit_s=10.0):
        for _ in range(round(limit_s / 0.002)):
            self.step()
            if self.p.mode == mode:
                return
        raise AssertionError(f"planner never reached {mode}, still {self.p.mode}")

    def pain(self, pad=None, gain=0.0, level=4):
        gains = [0.0] * N_PADS
        contact = None
        if pad is not None:
            gains[pad] = gain
            info = DESC.pads[pad]
            contact = m.Contact(pad=pad, name=info.name, region=info.region, change_hpa=10.0, level=level, gain=gain)
        self.seq += 1
        msg = m.SkinPain(seq=self.seq, stamp_ns=self.t, trace=m.Trace(self.seq, self.t - 1000), model="continuous",
                         level=[1] * N_PADS, gain=gains, strongest=contact)
        cmd = self.p.on_pain(msg, self.t)
        if cmd is not None:
            self.record(cmd)
        return cmd


def test_starts_by_returning_to_the_task_then_runs_it():
    sim = Sim()
    assert sim.p.mode == "RETURNING"
    sim.until("TASK")
    sim.step(2500)  # 5 s of task
    assert sim.p.clock.s > 4.0
    assert all(isinstance(c, m.PositionCommand) for c in sim.commands)
    q = np.array(sim.qs)
    assert np.ptp(q[:, 0]) > 0.3  # the base swings out to its 0.35 rad amplitude


def test_no_reflex_without_gain_and_before_the_arm_is_known():
    sim = Sim()
    sim.until("TASK")
    assert sim.pain(None) is None
    assert sim.p.mode == "TASK"
    fresh = Planner(PlannerSection(), DESC, MODEL)
    msg = m.SkinPain(seq=1, stamp_ns=0, trace=m.Trace(1, 0), model="c", level=[4] * N_PADS, gain=[1.0] * N_PADS,
                     strongest=m.Contact(pad=0, name="x", region="shoulder", change_hpa=30, level=4, gain=1.0))
    assert fresh.on_pain(msg, 0) is None


def test_full_cycle_task_reflex_returning_task():
    sim = Sim()
    sim.until("TASK")
    sim.step(500)
    s_paused = sim.p.clock.s
    q_contact = sim.p.q.copy()
    pad = DESC.pad("wrist_2").id
    first = sim.pain(pad, 0.675)
    assert isinstance(first, m.VelocityCommand)  # issued at once, not at the next cycle
    assert first.reflex_seq == 1 and first.trace.seq == sim.seq and first.phase == "REFLEX"
    assert sim.p.mode == "REFLEX"
    np.testing.assert_array_equal(sim.p.saved, q_contact)
    n0 = MODEL.pad_normal(q_contact, pad)
    p0 = MODEL.pad_point(q_contact, pad)
    sim.until("RETURNING")
    reflex_steps = sum(1 for md in sim.modes if md == "REFLEX")
    assert reflex_steps == pytest.approx(0.5 / 0.002, abs=2)
    withdrawn = -(MODEL.pad_point(sim.p.q, pad) - p0) @ n0
    assert withdrawn > 0.05  # moved away from the contact (G 0.675 * 0.25 m/s * 0.5 s ~ 8 cm)
    sim.until("TASK")
    np.testing.assert_allclose(sim.p.q, q_contact, atol=1e-9)  # back to the saved pose
    assert sim.p.clock.s == pytest.approx(s_paused)  # the task resumes where it paused
    assert sim.p.saved is None and sim.p.reflex is None
    sim.step(500)
    assert sim.p.clock.s > s_paused + 0.5


def test_motion_stays_within_speed_and_acceleration_limits():
    cfg = PlannerSection()
    sim = Sim(cfg)
    sim.until("TASK")
    sim.step(100)
    sim.pain(DESC.pad("wrist_1").id, 1.0)
    sim.until("TASK")
    sim.step(300)
    q = np.array(sim.qs)
    v = np.diff(q, axis=0) / 0.002
    a = np.diff(v, axis=0) / 0.002
    assert np.all(np.abs(v) <= cfg.speed_fraction * DESC.v_max + 1e-6)
    # Acceleration bound over the whole run, transitions included (with a small
    # allowance for the discretisation of the task's own trajectory).
    assert np.all(np.abs(a) <= cfg.speed_fraction * DESC.a_max * 1.05 + 1e-6)


def test_stronger_and_new_contacts_update_the_reflex_weaker_ones_do_not():
    sim = Sim()
    sim.until("TASK")
    up = DESC.pad("upper_arm_top").id
    sim.pain(up, 0.3)
    sim.step(50)
    assert sim.pain(up, 0.32) is None  # not stronger by the margin
    assert sim.p.reflex.seq == 1
    cmd = sim.pain(up, 0.8)
    assert cmd is not None and cmd.reflex_seq == 2
    assert sim.p.reflex.elapsed_s == pytest.approx(0.002)  # duration restarted (one cycle run at once)
    sim.step(50)
    other = DESC.pad("forearm_bottom").id
    cmd = sim.pain(other, 0.2)  # a new pad, weaker, still updates
    assert cmd is not None and cmd.reflex_seq == 3 and sim.p.reflex.contact.pad == other
    # What the exit line counts: one reflex started from the task, two restarts, none in shadow.
    assert (sim.p.started, sim.p.restarted, sim.p.shadowed) == (1, 2, 0)


def test_touch_during_returning_keeps_the_saved_pose():
    sim = Sim()
    sim.until("TASK")
    sim.step(200)
    q_contact = sim.p.q.copy()
    pad = DESC.pad("upper_arm_bottom").id
    sim.pain(pad, 0.5)
    sim.pain(None)
    sim.until("RETURNING")
    sim.step(50)
    cmd = sim.pain(pad, 0.5)  # the same pad again, after it had been released: a new contact
    assert cmd is not None and sim.p.mode == "REFLEX"
    np.testing.assert_array_equal(sim.p.saved, q_contact)
    sim.until("TASK")
    np.testing.assert_allclose(sim.p.q, q_contact, atol=1e-9)


def test_resync_when_the_arm_is_elsewhere():
    sim = Sim()
    sim.until("TASK")
    moved = sim.p.q + 0.3
    sim.p.on_state(moved, following=True)
    assert sim.p.mode == "RETURNING" and sim.p.resyncs == 1
    sim.until("TASK")


def test_no_resync_while_the_bridge_follows_the_position_stream_behind_it():
    """The bridge continues a position stream from the stream's own setpoints and refuses a jump back to the
    arm: a planner that resynchronised on the arm lagging its stream (the bridge's limits slowing a withdrawal)
    had every command refused as a jump, and the bridge stopped the arm (stale commands)."""
    sim = Sim()
    sim.until("TASK")
    q = sim.p.q.copy()
    sim.p.on_state(q - 0.3, following=True, streaming=True)
    assert sim.p.mode == "TASK" and sim.p.resyncs == 0
    np.testing.assert_array_equal(sim.p.q, q)  # the stream goes on from its own setpoint
    sim.p.on_state(q - 0.3, following=False, streaming=True)  # the bridge holds the arm: start again from it
    assert sim.p.resyncs == 1


def test_damped_pinv_exact_away_from_singularities():
    q = DESC.home
    for pad in range(N_PADS):
        jac = MODEL.pad_jacobian(q, pad)
        v = np.array([0.1, -0.05, 0.02, 0, 0, 0])
        dq = damped_pinv(jac, 0.05, 0.05) @ v
        np.testing.assert_allclose(dq, np.linalg.pinv(jac) @ v, atol=1e-6 if np.linalg.matrix_rank(jac) == 6 else 1e-2)


def test_cartesian_reflex_reproduces_the_pad_velocity():
    sim = Sim()
    sim.until("TASK")
    pad = DESC.pad("wrist_3").id  # six joints behind it: [v_c; 0] is reachable
    q = sim.p.q.copy()
    v_c = np.array(sim.p.strategy.start(q, touch(pad, 1.0)).direction)
    dq = sim.p.strategy.velocity(q, 0.0)
    twist = MODEL.pad_jacobian(q, pad) @ dq
    np.testing.assert_allclose(twist[:3], v_c, atol=1e-3)
    np.testing.assert_allclose(twist[3:], 0.0, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(v_c), 0.25)


def test_joint_speeds_bounded_at_a_singular_pose():
    q = np.array([0.0, -1.57, 0.0, -1.57, 0.0, 0.0])  # arm straight up, wrist 2 at 0: singular
    jac = MODEL.pad_jacobian(q, DESC.pad("wrist_3").id)
    assert np.linalg.svd(jac, compute_uv=False)[-1] < 1e-6
    dq = scale_to_limits(damped_pinv(jac, 0.05, 0.05) @ np.array([0.25, 0.1, 0.0, 0, 0, 0]), 0.9 * DESC.v_max)
    assert np.all(np.isfinite(dq))
    assert np.all(np.abs(dq) <= 0.9 * DESC.v_max + 1e-12)


@pytest.mark.parametrize("hold", [True, False])
def test_every_pad_that_can_withdraw_does(hold):
    """Integrate a G = 1 reflex from home: each pad moves away along its normal, never toward it."""
    cfg = PlannerSection(hold_orientation=hold)
    planner = Planner(cfg, DESC, MODEL)
    for pad in DESC.pads:
        q = DESC.home.copy()
        n0, p0 = MODEL.pad_normal(q, pad.id), MODEL.pad_point(q, pad.id)
        planner.strategy.start(q, touch(pad.id, 1.0))
        for i in range(250):
            q = q + planner.strategy.velocity(q, i * 0.002) * 0.002
        withdrawn = -(MODEL.pad_point(q, pad.id) - p0) @ n0
        assert withdrawn >= -1e-9, pad.name
        if pad.region in ("wrist",) or not hold:
            if pad.region != "shoulder":  # the shoulder pads' normals are tangent to what the joints can do
                assert withdrawn > 0.03, pad.name


def test_least_squares_solution_for_pads_with_fewer_joints():
    q = DESC.home
    pad = DESC.pad("forearm_top").id
    planner = Planner(PlannerSection(), DESC, MODEL)
    v_c = np.array(planner.strategy.start(q, touch(pad, 1.0)).direction)
    dq = planner.strategy.velocity(q, 0.0)
    jac = MODEL.pad_jacobian(q, pad)
    expected = np.linalg.pinv(jac) @ np.concatenate([v_c, np.zeros(3)])
    np.testing.assert_allclose(dq, expected, atol=1e-9)


def test_the_task_is_sent_planned_ahead_and_the_plan_is_what_the_planner_then_does():
    sim = Sim()
    sim.until("TASK")
    start = len(sim.commands)
    sim.step(1000)
    task = [c for c in sim.commands[start:] if c.phase == "TASK"]
    assert 95 <= len(task) <= 101  # one command per 10 cycles
    first = len(sim.qs) - 1000
    for c in task[1:]:
        assert len(c.ahead) == 10 and c.period_s == pytest.approx(0.002)
        k = next(i for i in range(first, len(sim.qs)) if np.array_equal(sim.qs[i], c.q))
        done = [q.tolist() for q in sim.qs[k + 1:k + 11]]
        assert c.ahead[: len(done)] == done  # bit for bit


def test_a_touch_interrupts_the_plan_at_once_and_the_return_resumes_planning():
    sim = Sim()
    sim.until("TASK")
    sim.step(7)  # mid-plan
    q_contact = sim.p.q.copy()
    first = sim.pain(DESC.pad("forearm_top").id, 0.8)
    assert first is not None and first.phase == "REFLEX"
    np.testing.assert_array_equal(sim.p.saved, q_contact)  # the pose of this cycle, not the plan's start
    n = len(sim.commands)
    sim.until("RETURNING")
    sim.until("TASK")
    # Reflex and return: one command per cycle, none planned ahead.
    assert all(not getattr(c, "ahead", []) for c in sim.commands[n:-1]) and len(sim.commands) - n > 200
    assert sim.commands[-1].phase == "TASK" and len(sim.commands[-1].ahead) == 10


def test_one_command_per_cycle_in_the_task_on_request():
    sim = Sim(PlannerSection(task_ahead_cycles=1))
    sim.until("TASK")
    n = len(sim.commands)
    sim.step(100)
    assert len(sim.commands) - n == 100 and not any(c.ahead for c in sim.commands[n:])


def test_a_plan_longer_than_the_bridge_accepts_is_a_configuration_error(tmp_path):
    bad = tmp_path / "far.toml"
    bad.write_text("[planner]\nrate_hz = 100.0\ntask_ahead_cycles = 20\n")
    with pytest.raises(ConfigError, match="plans more than 0.1 s ahead"):
        load_profile(str(bad))
