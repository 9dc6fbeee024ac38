"""Safe for the person beside the arm: no catch-up after a hold, Cartesian limits in every demo session.

Measured from the robot states (every control cycle: ``state_rate_hz`` =
500), each point's speed from its Jacobian and the state's measured joint
velocity.
"""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile, load_profile
from nwr.common.journal import Untracked
from nwr.common.launch import TouchScript, load_script
from nwr.common.recordings import Recorded
from nwr.common.robot import RobotModel, load_description
from nwr.common.task import FigureEight
from nwr.services.bridge.wiring import BridgeWiring
from nwr.services.gateway.stepped import SimulatedSkin
from nwr.services.pipeline.lockstep import Lockstep
from nwr.services.tools.recordings import analysis
from nwr.services.wiring import no_diag

DESC = load_description()
MODEL = RobotModel(DESC)
HOLDS_S = (0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
# Rounding and the measured (not commanded) velocity, m/s.
TOLERANCE = 0.005


def every_cycle() -> Profile:
    profile = load_profile()
    profile.bridge.state_rate_hz = profile.bridge.rate_hz
    return profile


def speeds(state: m.RobotState) -> np.ndarray:
    return np.linalg.norm(MODEL.speed_jacobians(state.q) @ np.asarray(state.dq), axis=1)


def states_of(profile: Profile, samples: list[m.SkinPressure], strategy: str = "cartesian",
              settle_s: float = 0.5) -> list[m.RobotState]:
    out: list[m.RobotState] = []
    Lockstep(profile, strategy=strategy, journal=False).run(
        samples, lambda k, msg, t: out.append(msg) if k == keys.ROBOT_STATE else None, settle_s=settle_s)
    return out


@pytest.fixture(scope="module")
def quiet_session() -> tuple[Profile, list[m.SkinPressure], float, float]:
    """Nobody touches the arm: the skin samples, the task's peak point speed and when the task is fastest."""
    profile = every_cycle()
    samples: list[m.SkinPressure] = []
    Lockstep(profile, journal=False).run(SimulatedSkin(profile, TouchScript(duration_s=12.0, touch=[])),
                                         lambda k, msg, t: samples.append(msg) if k == keys.SKIN_PRESSURE else None,
                                         settle_s=0.0)
    t0 = samples[0].stamp_ns
    states = [s for s in states_of(profile, samples) if s.status == "ok" and s.stamp_ns > t0 + 1_000_000_000]
    peak = max(float(speeds(s).max()) for s in states)
    # The task's fastest point between 3 and 7 s: the longest hold still ends well before the skin does.
    window = [s for s in states if t0 + 3_000_000_000 < s.stamp_ns < t0 + 7_000_000_000]
    fastest = window[int(np.argmax([float(speeds(s).max()) for s in window]))].stamp_ns
    return profile, samples, peak, fastest


@pytest.mark.parametrize("hold_s", HOLDS_S)
def test_after_a_skin_outage_the_task_resumes_no_faster_than_it_runs(quiet_session, hold_s: float) -> None:
    profile, samples, peak, fastest = quiet_session
    timeout_ns = round(profile.bridge.skin_timeout_s * 1e9)
    start = fastest - timeout_ns  # the hold begins at the task's fastest point
    end = fastest + round(hold_s * 1e9)
    kept = [s for s in samples if not start <= s.stamp_ns < end]
    states = [s for s in states_of(profile, kept) if s.stamp_ns < end + 3_000_000_000]  # the skin still flows
    held = [s for s in states if s.status == "stale_skin" and s.stamp_ns > start]
    assert held, "the outage held the arm"
    after = [s for s in states if s.stamp_ns > held[-1].stamp_ns]
    assert len(after) > 1000 and all(s.status == "ok" for s in after)
    worst = max(float(speeds(s).max()) for s in after)
    assert worst <= peak + TOLERANCE, f"{worst:.3f} m/s on resuming after {hold_s} s, the task peaks at {peak:.3f}"


def stream(hold: tuple[float, float] | None, *, reduced: bool = False, seconds: float = 8.0) -> list[m.RobotState]:
    """An external planner streaming the task at 500 Hz whatever the arm does; skin stops during ``hold`` (s)."""
    profile = every_cycle()
    clock = ManualClock()
    clock.t_ns = 10**9
    states: list[m.RobotState] = []
    bridge = BridgeWiring(profile, journal=Untracked(clock), out=lambda k, msg: states.append(msg), diag=no_diag)
    name = profile.bridge.active_planner
    bridge.on_token(name, True)
    if reduced:
        bridge.on_safety(m.SafetyModeRequest(seq=0, stamp_ns=clock.t_ns, mode="reduced", requested_by="test"))
    task = FigureEight(profile.planner.task, DESC)
    period = 1.0 / profile.bridge.rate_hz
    skin = m.SkinPressure(seq=0, stamp_ns=0, absolute_hpa=[1000.0] * 10, baseline_hpa=[1000.0] * 10,
                          change_hpa=[0.0] * 10, contact=[False] * 10, valid=[True] * 10, source="test")
    for k in range(int(seconds / period)):
        t = k * period
        clock.t_ns += round(period * 1e9)
        if (hold is None or not hold[0] <= t < hold[1]) and k % 20 == 0:
            bridge.on_skin(msgspec.structs.replace(skin, seq=k, stamp_ns=clock.t_ns))
        bridge.on_command(keys.robot_command(name), m.PositionCommand(
            seq=k, stamp_ns=clock.t_ns, owner=name, q=task.position(t).tolist(), trace=m.Trace(-1, 0)))
        bridge.tick()
    return states


@pytest.mark.parametrize("hold_s", (0.05, 0.5, 2.0))
def test_a_stream_that_ignores_the_hold_is_rejoined_at_its_own_speed(hold_s: float) -> None:
    """The planner does not wait for the arm: the bridge does not catch up with it (no point faster than the
    stream itself ever moves), it rejoins the stream at that speed."""
    peak = max(float(speeds(s).max()) for s in stream(None)[100:])
    states = stream((3.0, 3.0 + 0.12 + hold_s))
    assert any(s.status == "stale_skin" for s in states)
    resumed = [s for s in states if s.stamp_ns - 10**9 > (3.12 + hold_s) * 1e9]
    worst = max(float(speeds(s).max()) for s in resumed)
    assert worst <= peak + TOLERANCE, f"{worst:.3f} m/s rejoining a stream that peaks at {peak:.3f} m/s"
    assert resumed[-1].limited > 0  # the rejoin was held to the stream's speed, and counted


def test_the_reduced_mode_holds_every_point_to_its_own_limit() -> None:
    reduced = load_profile().bridge.reduced
    normal = stream(None, seconds=4.0)
    slow = stream(None, reduced=True, seconds=4.0)
    assert slow[-1].safety_mode == "reduced" and normal[-1].safety_mode == "normal"
    assert max(float(speeds(s).max()) for s in normal) > reduced.speed_m_s  # the task is faster than reduced...
    assert max(float(speeds(s).max()) for s in slow) <= reduced.speed_m_s + TOLERANCE  # ...and held to it
    assert slow[-1].limited > normal[-1].limited


@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["uniform", "location", "cartesian", "cartesian-smooth", "whole-arm"])
def test_a_demo_session_keeps_every_point_within_the_limits(strategy: str) -> None:
    profile = every_cycle()
    limits = profile.bridge.limits
    out: list[tuple[str, object]] = []
    records: list[Recorded] = []

    def emit(key: str, msg: object, t: int) -> None:
        out.append((key, msg))
        records.append(Recorded(key, t, msg))

    Lockstep(profile, strategy=strategy, journal=False).run(SimulatedSkin(profile, load_script("demo")), emit,
                                                            settle_s=1.0)
    states = [msg for k, msg in out if k == keys.ROBOT_STATE]
    assert isinstance(states[0], m.RobotState)
    contacts = {msg.reflex.reflex_seq: msg.reflex.contact for k, msg in out
                if isinstance(msg, m.PlannerStatus) and msg.reflex is not None}
    reflexes = 0
    toward: dict[int, np.ndarray] = {}  # into each reflex's contact, where the pad was at the onset
    for s in states:
        v = MODEL.speed_jacobians(s.q) @ np.asarray(s.dq)
        fastest = float(np.linalg.norm(v, axis=1).max())
        if s.phase != "REFLEX":
            assert fastest <= limits.speed_m_s + TOLERANCE, (s.stamp_ns, s.phase, s.reflex_seq, fastest, s.dq)
            continue
        reflexes += 1
        assert fastest <= limits.withdrawal_speed_m_s + TOLERANCE, (s.stamp_ns, fastest)
        if s.reflex_seq not in toward:
            toward[s.reflex_seq] = MODEL.pad_normal(s.q, contacts[s.reflex_seq].pad)
        approach = float((v @ toward[s.reflex_seq]).max())
        # Also a reflex restarted while the arm withdraws (a press whose pain rises over several samples): the
        # bridge follows the restarted stream closely (its period measured afresh), nothing catches up.
        assert approach <= limits.speed_m_s + TOLERANCE, (s.stamp_ns, approach)
    assert reflexes > 100
    # The per-touch table shows what the limits let through, reflex by reflex.
    touches = [t for t in analysis.summarize(records, DESC, MODEL) if t.reflex_seq]
    assert len(touches) == 6
    for t in touches:
        # A reflex whose pad cannot withdraw may hold the arm still (cartesian-smooth on shoulder_outer, whose
        # normal its joints cannot follow: 0 m/s, 4e-51 m/s once, a rounding's residue).
        assert t.peak_speed_m_s is not None and t.peak_speed_m_s <= limits.withdrawal_speed_m_s + TOLERANCE
        assert t.peak_speed_m_s > 0 or not t.withdraws, t.name
        # Over the whole withdrawal of a press that restarted its reflex too, along the first onset's normal.
        assert t.peak_toward_m_s is not None and t.peak_toward_m_s <= limits.speed_m_s + TOLERANCE, t.name


@pytest.mark.e2e
@pytest.mark.slow
def test_reduced_mode_from_the_command_line_on_a_live_pipeline(tmp_path) -> None:
    import subprocess
    import sys
    import time

    profile = tmp_path / "profile.toml"
    profile.write_text("[zenoh]\nbase_port = 18350\n")
    cli = [sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), "--log-level", "WARNING"]
    up = subprocess.Popen([*cli, "up", "--no-record"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60
        while True:
            shown = subprocess.run([*cli, "safety"], capture_output=True, text=True, timeout=60)
            if shown.returncode == 0 or time.monotonic() > deadline:
                break
        assert "safety mode: normal" in shown.stdout, shown.stdout + shown.stderr
        reduced = subprocess.run([*cli, "safety", "reduced"], capture_output=True, text=True, timeout=60)
        assert reduced.returncode == 0, reduced.stdout + reduced.stderr
        assert "safety mode: reduced: every point at most 0.15 m/s" in reduced.stdout
        assert "safety mode: reduced" in subprocess.run([*cli, "safety"], capture_output=True, text=True,
                                                        timeout=60).stdout
        normal = subprocess.run([*cli, "safety", "normal"], capture_output=True, text=True, timeout=60)
        assert normal.returncode == 0 and "safety mode: normal" in normal.stdout, normal.stdout + normal.stderr
    finally:
        up.terminate()
        out, _ = up.communicate(timeout=30)
    assert up.returncode == 0, out
