"""The second robot, the Franka Research 3 (7 joints): every strategy in lockstep withdraws the touched pad
within the bridge's limits, and a lockstep session on it re-runs bit for bit.

The checks of tests/test_limits.py (every point within the Cartesian limits, measured from the robot
states of every control cycle) and of the per-touch table, on a short script of two touches that every
strategy can withdraw from on this arm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile, load_profile
from nwr.common.launch import Touch, TouchScript, load_script, resolve_script
from nwr.common.recordings import Recorded
from nwr.common.robot import ROBOTS_DIR, RobotModel, load_description
from nwr.services.gateway.stepped import SimulatedSkin
from nwr.services.pipeline.lockstep import Lockstep
from nwr.services.planner.strategies import names as strategy_names
from nwr.services.tools.recordings import analysis
from nwr.services.tools.recordings.replay import simulate
from nwr.services.tools.recordings.verify import verify

DESC = load_description("fr3")
MODEL = RobotModel(DESC)
TOLERANCE = 0.005  # m/s: rounding and the measured (not commanded) velocity, as tests/test_limits.py
# A full-gain press of the forearm, then a PL 4 press of the flange ring while the arm may still be away.
SCRIPT = TouchScript(duration_s=9.0, touch=[
    Touch(pad="forearm_top", start_s=1.0, duration_s=0.3, peak_hpa=25.0),
    Touch(pad="wrist_flange", start_s=5.0, duration_s=0.3, peak_hpa=14.0),
])


def fr3_profile() -> Profile:
    profile = load_profile("fr3")
    profile.bridge.state_rate_hz = profile.bridge.rate_hz  # every control cycle
    return profile


def test_the_fr3_profile_takes_the_robots_own_data() -> None:
    profile = load_profile("fr3")
    assert profile.robot.description == "fr3" and len(DESC.joints) == 7
    assert not profile.planner.q_max_deg and not profile.planner.task.amplitude_rad  # the robot's, from robot.toml
    # A packaged script is first the robot's own: the demo's touches on the FR3's pads.
    assert resolve_script("demo", "fr3") == ROBOTS_DIR / "fr3" / "scripts" / "demo.toml"
    assert {touch.pad for touch in load_script("demo", "fr3").touch} <= {pad.name for pad in DESC.pads}
    assert resolve_script("demo") != resolve_script("demo", "fr3")


@pytest.mark.parametrize("strategy", strategy_names())
def test_every_strategy_withdraws_the_touched_pad_within_the_limits_on_the_fr3(strategy: str) -> None:
    profile = fr3_profile()
    limits = profile.bridge.limits
    out: list[tuple[str, object]] = []
    records: list[Recorded] = []

    def emit(key: str, msg: object, t: int) -> None:
        out.append((key, msg))
        records.append(Recorded(key, t, msg))

    Lockstep(profile, strategy=strategy, journal=False).run(SimulatedSkin(profile, SCRIPT, MODEL), emit,
                                                            settle_s=1.0)
    states = [msg for k, msg in out if k == keys.ROBOT_STATE and isinstance(msg, m.RobotState)]
    contacts = {msg.reflex.reflex_seq: msg.reflex.contact for k, msg in out
                if isinstance(msg, m.PlannerStatus) and msg.reflex is not None}
    in_reflex = 0
    toward: dict[int, np.ndarray] = {}
    for s in states:
        q = np.asarray(s.q)
        assert np.all(q >= DESC.q_min) and np.all(q <= DESC.q_max), (s.stamp_ns, q)
        assert np.all(np.abs(np.asarray(s.dq)) <= DESC.v_max + 1e-9), (s.stamp_ns, s.dq)
        v = MODEL.speed_jacobians(q) @ np.asarray(s.dq)
        fastest = float(np.linalg.norm(v, axis=1).max())
        if s.phase != "REFLEX":
            assert fastest <= limits.speed_m_s + TOLERANCE, (s.stamp_ns, s.phase, fastest)
            continue
        in_reflex += 1
        assert fastest <= limits.withdrawal_speed_m_s + TOLERANCE, (s.stamp_ns, fastest)
        if s.reflex_seq not in toward:
            toward[s.reflex_seq] = MODEL.pad_normal(q, contacts[s.reflex_seq].pad)
        # A reflex restarted on the same pad blends from its motion (tests/test_limits.py: the known excess).
        restarted = s.reflex_seq - 1 in contacts and contacts[s.reflex_seq - 1].pad == contacts[s.reflex_seq].pad
        allowed = limits.speed_m_s * (1.25 if restarted else 1.0) + TOLERANCE
        assert float((v @ toward[s.reflex_seq]).max()) <= allowed, (s.stamp_ns, restarted)
    assert in_reflex > 50
    touches = [t for t in analysis.summarize(records, DESC, MODEL) if t.reflex_seq]
    assert [t.name for t in touches] == ["forearm_top", "wrist_flange"]
    for t in touches:  # away from the finger, never into it
        assert t.withdrawal_mm is not None and t.withdrawal_mm > 20.0, (t.name, t.withdrawal_mm)
        assert t.toward_mm is not None and t.toward_mm < analysis.APPROACH_MM, (t.name, t.toward_mm)
        assert t.peak_speed_m_s is not None and t.peak_speed_m_s <= limits.withdrawal_speed_m_s + TOLERANCE


def test_a_lockstep_session_on_the_fr3_re_runs_bit_for_bit(tmp_path: Path) -> None:
    script = tmp_path / "short.toml"
    script.write_text("duration_s = 4.0\n[[touch]]\npad = \"forearm_top\"\nstart_s = 1.0\nduration_s = 0.3\n"
                      "peak_hpa = 25.0\n")
    path = simulate(load_profile("fr3"), str(script), "location", tmp_path / "fr3.mcap")[0]
    results = verify(path)
    assert {r.service: r.verdict for r in results} == {
        "gateway": "identical", "gain": "identical", "planner-location": "identical", "bridge": "identical"}
    assert next(r for r in results if r.service == "planner-location").outputs["robot/command/location"] > 500
