"""One bad message must not stop the pipeline: the door, and every service's handling of what it lets through.

The services run in process on their own wirings (as lockstep chains them),
each input passing a door of its own as :meth:`Node.subscribe` does; wrong
messages (the catalogue in ``wrong_messages.py``, and hypothesis's arbitrary
well-formed ones) are delivered between control cycles of a quiet session.
Checked: the door refuses what it must and nothing the pipeline itself
sends; no handler raises on what the door lets through; the arm keeps its
task, its owner and its limits.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from msgspec.structs import replace
from wrong_messages import catalogue

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import load_profile
from nwr.common.door import SEQ_LIMIT, Door
from nwr.common.launch import TouchScript, load_script
from nwr.common.robot import RobotModel, load_description
from nwr.services.gateway.stepped import SimulatedSkin
from nwr.services.pipeline.lockstep import Lockstep

DESC = load_description()
MODEL = RobotModel(DESC)
N, PADS = len(DESC.joints), len(DESC.pads)
TOLERANCE = 0.01  # m/s: the measured velocity's rounding


def test_the_catalogue_decodes_and_the_door_refuses_what_it_must() -> None:
    wrong = catalogue(DESC)
    assert len(wrong) >= 50 and len({w.name for w in wrong}) == len(wrong)
    door = Door(DESC)
    for w in wrong:
        codec = keys.codec(w.key)
        message = codec.decode(codec.encode(w.message))  # well-formed: it decodes
        refusal = door.refuse(message)
        assert (refusal is not None) == w.refused, (w.name, refusal)
        if refusal is not None:
            assert refusal.cause and str(refusal).startswith(refusal.cause), w.name


def test_the_door_lets_a_whole_session_through() -> None:
    """No false refusal: every message a demo session's services send passes a fresh door."""
    profile = load_profile()
    doors: dict[str, Door] = {}
    refused: list[tuple[str, str]] = []

    def emit(key: str, message: Any, _t: int) -> None:
        door = doors.setdefault(key.split("/")[0], Door(DESC))  # one per consumer, as each service has its own
        refusal = door.refuse(message)
        if refusal is not None:
            refused.append((key, str(refusal)))

    Lockstep(profile, journal=False).run(SimulatedSkin(profile, load_script("demo")), emit, settle_s=1.0)
    assert not refused, refused[:5]


def test_the_door_s_quick_checks_refuse_the_value_its_full_ones_name_wherever_it_is() -> None:
    """The checks over a whole list (min, max) fall back to the pad-by-pad ones, which name the value: a NaN
    (which min and max may pass over) or a value out of range at any pad is refused as before."""
    door = Door(DESC)
    base = m.SkinPressure(seq=1, stamp_ns=1, absolute_hpa=[1000.0] * PADS, baseline_hpa=[1000.0] * PADS,
                          change_hpa=[0.0] * PADS, contact=[False] * PADS)
    pain = m.SkinPain(seq=1, stamp_ns=1, trace=m.Trace(1, 1), model="continuous", level=[1] * PADS,
                      gain=[0.0] * PADS)
    assert door.refuse(base) is None and door.refuse(pain) is None
    for i in (0, PADS // 2, PADS - 1):
        for bad in (float("nan"), -1.0, 6000.0):
            values = [1000.0] * PADS
            values[i] = bad
            refusal = door.refuse(replace(base, baseline_hpa=values))
            assert refusal is not None and refusal.cause == "pressure out of range" and str(bad) in refusal.detail
        for bad_gain in (float("nan"), -0.5, 1.5):
            gains = [0.0] * PADS
            gains[i] = bad_gain
            refusal = door.refuse(replace(pain, gain=gains))
            assert refusal is not None and refusal.cause == "gain out of range" and f"pad {i} gain" in refusal.detail
        levels = [1] * PADS
        levels[i] = 5
        refusal = door.refuse(replace(pain, level=levels))
        assert refusal is not None and refusal.cause == "level out of range" and f"pad {i} level" in refusal.detail
        change = [0.0] * PADS
        change[i] = -2500.0
        refusal = door.refuse(replace(base, change_hpa=change))
        assert refusal is not None and "-2500.0" in refusal.detail


def test_a_command_on_no_skin_sample_yet_passes_and_no_other_negative_trace() -> None:
    """A planner's task commands before its first pain message carry NO_TRACE: the live bridge refused them
    (``trace out of range``) at every start-up, while the gain estimator was still starting."""
    home = [float(x) for x in DESC.home]
    cmd = m.PositionCommand(seq=0, stamp_ns=10**9, owner="cartesian", q=home, trace=m.NO_TRACE)
    assert Door(DESC).refuse(cmd) is None
    for forged in (m.Trace(-1, 5), m.Trace(-2, 0), m.Trace(0, -1)):
        refusal = Door(DESC).refuse(replace(cmd, trace=forged))
        assert refusal is not None and refusal.cause == "trace out of range", forged


def test_a_robot_state_that_does_not_continue_the_bridge_s_stream_is_refused() -> None:
    door = Door(DESC)
    home = [float(x) for x in DESC.home]
    state = m.RobotState(seq=10, stamp_ns=10**9, q=home, dq=[0.0] * N, status="ok", owner="cartesian", backend="sim")
    assert door.refuse(state) is None
    later = replace(state, seq=11, stamp_ns=10**9 + 20_000_000)
    assert door.refuse(later) is None
    # A forged state: the same seq again, an older one, or a pose the arm cannot have reached in time.
    for forged in (replace(later, q=[x + 0.3 for x in home]), replace(state, seq=5, stamp_ns=10**9 + 30_000_000)):
        refusal = door.refuse(forged)
        assert refusal is not None and "bridge's stream" in refusal.detail, forged
    jump = replace(later, seq=12, stamp_ns=10**9 + 40_000_000, q=[x + 0.5 for x in home])
    refusal = door.refuse(jump)
    assert refusal is not None and refusal.cause == "robot state jumps"
    # The external torques, where the backend has them, are one per joint.
    torques = replace(later, seq=13, stamp_ns=10**9 + 60_000_000, tau_ext=[0.5] * N)
    assert door.refuse(torques) is None
    refusal = door.refuse(replace(torques, seq=14, stamp_ns=10**9 + 80_000_000, tau_ext=[0.5] * 1000))
    assert refusal is not None and refusal.cause == "wrong joint count" and "tau_ext" in refusal.detail
    # A restarted bridge (seq from 0) is followed once its old stream has been silent for a second.
    restarted = replace(state, seq=0, stamp_ns=10**9 + 1_200_000_000, q=[x + 0.5 for x in home])
    assert door.refuse(restarted) is None


# -- the services, in process ----------------------------------------------------------------

class Pipeline:
    """A quiet session of the services' wirings, in lockstep, into which anything can be delivered."""

    def __init__(self, strategy: str = "cartesian") -> None:
        profile = load_profile()
        profile.bridge.state_rate_hz = profile.bridge.rate_hz  # every cycle's state, for the checks
        self.profile = profile
        self.ls = Lockstep(profile, strategy=strategy, journal=False)
        self.states: list[m.RobotState] = []
        self.ls.emit = self._emit
        self.skin = SimulatedSkin(profile, TouchScript(duration_s=600.0, touch=[]))
        self.t = self.skin.stamp(0) - self.ls.period_ns
        self.ls._start(self.t, self.skin)
        self.ls.drain()
        self.i = 0
        self.doors = {service: Door(DESC) for service in ("bridge", "planner", "gain", "gateway")}
        self.refused = 0
        self.raised: list[tuple[str, str, str]] = []

    def _emit(self, key: str, message: Any, _t: int) -> None:
        if key == keys.ROBOT_STATE:
            self.states.append(message)
            for service in ("planner", "gateway"):  # what the pipeline sends passes their doors (stream state)
                assert self.doors[service].refuse(message) is None, message

    def run(self, seconds: float) -> None:
        ls, skin = self.ls, self.skin
        end = self.t + round(seconds * 1e9)
        while self.t < end:
            self.t += ls.period_ns
            while skin.stamp(self.i) <= self.t:
                ls.clock.t_ns = skin.stamp(self.i)
                sample = skin.take(self.i, ls.pose(), ls.emit)
                ls.clock.t_ns = self.t
                if sample is not None:
                    ls.queue.append((keys.SKIN_PRESSURE, sample))
                ls.drain()
                self.i += 1
            ls.clock.t_ns = self.t
            ls.planner.tick()
            assert ls.planner.failure is None, ls.planner.failure
            ls.drain()
            ls.bridge.tick()
            ls.drain()

    def consumers(self, key: str) -> list[tuple[str, Callable[[Any], Any]]]:
        """Every handler any wiring declares for ``key`` (the gateway's statuses too, follower or not)."""
        ls = self.ls
        return [("planner" if wiring is ls.planner else wiring.service,
                 lambda msg, wiring=wiring, inp=inp: wiring.deliver(inp, key, msg, ls.clock.t_ns))
                for wiring in ls.wirings for inp in wiring.inputs.values()
                if inp.key is not None and keys.matches(key, inp.key)]

    def deliver(self, key: str, message: Any, name: str = "") -> None:
        """As each subscribing service's node would: its door, then its handler (whose exception it would catch)."""
        codec = keys.codec(key)
        message = codec.decode(codec.encode(message))
        for service, handler in self.consumers(key):
            if self.doors[service].refuse(message) is not None:
                self.refused += 1
                continue
            try:
                handler(message)
            except Exception as exc:  # noqa: BLE001  recorded: the test fails on any
                self.raised.append((name or type(message).__name__, service, repr(exc)))
        self.ls.drain()

    def check_the_arm(self, since: int) -> None:
        """From state ``since`` on: one owner, every point within the limits, no jump between states."""
        limits = self.profile.bridge.limits
        states = self.states[since:]
        assert states
        previous = states[0]
        for s in states:
            assert s.owner == self.ls.name, (s.owner, s.stamp_ns)
            speeds = np.linalg.norm(MODEL.speed_jacobians(s.q) @ np.asarray(s.dq), axis=1)
            bound = limits.withdrawal_speed_m_s if s.phase == "REFLEX" else limits.speed_m_s
            assert float(speeds.max()) <= bound + TOLERANCE, (s.stamp_ns, s.phase, float(speeds.max()))
            dt = (s.stamp_ns - previous.stamp_ns) / 1e9
            step = np.abs(np.asarray(s.q) - np.asarray(previous.q))
            assert (step <= DESC.v_max * dt + 1e-6).all(), (s.stamp_ns, step)
            previous = s


@pytest.fixture(scope="module")
def pipeline() -> Pipeline:
    p = Pipeline()
    p.run(2.0)
    return p


def test_every_wrong_message_on_every_key_leaves_the_services_running_and_the_arm_on_its_task(
        pipeline: Pipeline) -> None:
    p = pipeline
    since = len(p.states)
    seq = 10**6  # above anything the session has sent: only the values are wrong
    for w in catalogue(DESC, active=p.ls.name, seq=seq, stamp_ns=p.t):
        p.deliver(w.key, w.message, w.name)
        p.run(0.02)
    p.run(1.0)
    assert not p.raised, p.raised
    assert p.refused >= 50
    p.check_the_arm(since)
    moving = [s for s in p.states[-100:] if s.status == "ok" and max(abs(v) for v in s.dq) > 1e-3]
    assert moving, "the task stopped"
    assert p.ls.bridge.core.safety_mode == "normal"


# Well-formed messages of arbitrary values: ints anywhere in 64 bits, floats within the wire's bound, lists of
# any length up to a few more than the robot has.
ints = st.integers(min_value=-(2**63), max_value=2**64 - 1)
small = st.one_of(st.integers(min_value=-3, max_value=12), ints)
floats = st.one_of(st.floats(min_value=-m.FINITE_BOUND, max_value=m.FINITE_BOUND, allow_nan=False),
                   st.sampled_from([0.0, -0.0, 1.0, -1.0, 1e-300, 1e12, -1e12, 0.5]))
seqs = st.one_of(st.integers(min_value=0, max_value=SEQ_LIMIT - 1), ints)
names = st.one_of(st.sampled_from(["cartesian", "uniform", "location", "intruder", "", "X", "a" * 40]),
                  st.text(max_size=8))


def lists(of: st.SearchStrategy[Any], around: int) -> st.SearchStrategy[list[Any]]:
    return st.one_of(st.lists(of, min_size=around, max_size=around), st.lists(of, max_size=around + 3))


traces = st.builds(m.Trace, seq=seqs, stamp_ns=ints)
contacts = st.builds(m.Contact, pad=small, name=names, region=names, change_hpa=floats, level=small, gain=floats)
MESSAGES = st.one_of(
    st.tuples(st.just(keys.SKIN_PRESSURE), st.builds(
        m.SkinPressure, seq=seqs, stamp_ns=ints, absolute_hpa=lists(floats, PADS), baseline_hpa=lists(floats, PADS),
        change_hpa=lists(floats, PADS), contact=lists(st.booleans(), PADS), valid=lists(st.booleans(), 0))),
    st.tuples(st.just(keys.SKIN_PAIN), st.builds(
        m.SkinPain, seq=seqs, stamp_ns=ints, trace=traces, model=names, level=lists(small, PADS),
        gain=lists(floats, PADS), strongest=st.one_of(st.none(), contacts))),
    st.tuples(st.just(keys.ROBOT_STATE), st.builds(
        m.RobotState, seq=seqs, stamp_ns=ints, q=lists(floats, N), dq=lists(floats, N),
        status=st.sampled_from(["ok", "idle", "stopped"]), owner=names, backend=names)),
    st.tuples(st.just("robot/command/cartesian"), st.builds(
        m.PositionCommand, seq=seqs, stamp_ns=ints, owner=st.sampled_from(["cartesian", "intruder"]),
        q=lists(floats, N), trace=traces, reflex_seq=small, phase=st.sampled_from(m.MODES),
        ahead=st.lists(lists(floats, N), max_size=3), period_s=floats)),
    st.tuples(st.just("robot/command/cartesian"), st.builds(
        m.VelocityCommand, seq=seqs, stamp_ns=ints, owner=st.sampled_from(["cartesian", "intruder"]),
        dq=lists(floats, N), trace=traces, reflex_seq=small, phase=st.sampled_from(m.MODES))),
    st.tuples(st.just(keys.CONTROL_ACTIVE), st.builds(m.SwitchRequest, seq=seqs, stamp_ns=ints, name=names)),
    st.tuples(st.sampled_from(["reflex/intruder/status", "reflex/cartesian/status"]), st.builds(
        m.PlannerStatus, seq=seqs, stamp_ns=ints, name=names, strategy=names, mode=st.sampled_from(m.MODES),
        task_time_s=floats, saved_pose=st.one_of(st.none(), lists(floats, N)), target_pad=small)),
)


@pytest.mark.slow
def test_arbitrary_well_formed_messages_never_raise_nor_move_the_arm_out_of_its_limits() -> None:
    p = Pipeline()
    p.run(2.0)
    since = len(p.states)

    @settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
    @given(MESSAGES)
    def deliver(item: tuple[str, Any]) -> None:
        key, message = item
        p.deliver(key, message)
        p.run(0.004)

    deliver()
    p.run(1.0)
    assert not p.raised, p.raised[:5]
    p.check_the_arm(since)
