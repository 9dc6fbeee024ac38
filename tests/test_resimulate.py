"""Touch ground truth, the contact model and re-simulated replay (``nwr replay --fast --resimulate``)."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import GatewaySection, Profile
from nwr.common.errors import ConfigError
from nwr.common.launch import Touch, TouchScript
from nwr.common.recordings import read_recording
from nwr.common.robot import RobotModel, load_description
from nwr.services.gateway.core import (
    Gateway,
    Resimulator,
    SimSkin,
    TouchSet,
    contact_pressure,
    sim_settings,
    touch_message,
    with_sim,
    withdrawal_m,
)
from nwr.services.tools.recordings import analysis, compare
from nwr.services.tools.recordings.replay import run_fast, simulate
from nwr.services.tools.recordings.verify import verify

DATA = Path(__file__).parent / "data"
DESC = load_description()
MODEL = RobotModel(DESC)
N = len(DESC.pads)


# ------------------------------------------------------------------------------ the contact model

def test_zero_withdrawal_gives_the_scripted_pressure():
    assert contact_pressure(9.0, 0.0, 0.02) == 9.0


def test_withdrawal_lowers_the_pressure_until_none_is_left():
    values = [contact_pressure(10.0, w, 0.02) for w in (0.0, 0.005, 0.01, 0.015, 0.02, 0.05)]
    assert values == pytest.approx([10.0, 7.5, 5.0, 2.5, 0.0, 0.0])


def test_moving_toward_the_finger_never_presses_harder_than_scripted():
    assert contact_pressure(10.0, -0.05, 0.02) == 10.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_the_contact_model_refuses_non_finite_input(bad):
    with pytest.raises(ValueError, match="finite"):
        contact_pressure(bad, 0.0, 0.02)
    with pytest.raises(ValueError, match="finite"):
        contact_pressure(9.0, bad, 0.02)
    with pytest.raises(ValueError, match="depth"):
        contact_pressure(9.0, 0.0, bad)


def test_the_contact_model_refuses_a_depth_of_zero():
    with pytest.raises(ValueError, match="depth"):
        contact_pressure(9.0, 0.0, 0.0)


def test_withdrawal_is_measured_along_the_contact_normal():
    point, normal = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    assert withdrawal_m(point, normal, point - [0.0, 0.0, 0.01]) == pytest.approx(0.01)  # pad moved away
    assert withdrawal_m(point, normal, point + [0.0, 0.0, 0.01]) == pytest.approx(-0.01)  # toward the finger
    assert withdrawal_m(point, normal, point + [0.3, 0.2, 0.0]) == 0.0  # sliding along the surface


def test_touch_set_closed_loop_and_unknown_pose():
    step = Touch(pad="1", start_s=1.0, duration_s=1.0, peak_hpa=8.0)
    points = np.zeros((3, 3))
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    closed = TouchSet(3, 0.02, closed_loop=True)
    closed.add(1, step)
    assert closed.start(0.5, points, normals) == []
    assert [a.pad for a in closed.start(1.0, points, normals)] == [1]
    assert closed.start(1.1, points, normals) == []  # once only
    moved = points.copy()
    moved[1, 2] = -0.015  # pad 1 withdrew 15 mm
    assert closed.pressure(1.5, moved)[1] == pytest.approx(2.0)
    assert closed.pressure(1.5, None)[1] == 8.0  # no pose now: as scripted
    opened = TouchSet(3, 0.02, closed_loop=False)
    opened.add(1, step)
    opened.start(1.0, points, normals)
    assert opened.pressure(1.5, moved)[1] == 8.0
    blind = TouchSet(3, 0.02, closed_loop=True)
    blind.add(1, step)
    assert blind.start(1.0, None, None)[0].point is None  # the pose was unknown: no contact point is invented
    assert blind.pressure(1.5, moved)[1] == 8.0


def test_touch_message_carries_the_ground_truth_or_says_it_has_none():
    touches = TouchSet(N, 0.02, closed_loop=False)
    touches.add(4, Touch(pad="elbow_outer", start_s=2.0, duration_s=0.4, peak_hpa=11.0, shape="ramp", ramp_s=0.1))
    q = np.array(DESC.home)
    (started,) = touches.start(2.0, MODEL.pad_points(q), MODEL.pad_normals(q))
    msg = touch_message(0, 5, 3, started, "elbow_outer", touches, q, 4)
    assert (msg.pad, msg.name, msg.origin_ns, msg.shape, msg.ramp_s, msg.pose_stamp_ns) == (
        4, "elbow_outer", 3, "ramp", 0.1, 4)
    assert msg.contact_point == pytest.approx(MODEL.pad_point(q, 4).tolist())
    assert msg.normal == pytest.approx(MODEL.pad_normal(q, 4).tolist())
    decoded = keys.codec(keys.SKIN_TOUCH).decode(keys.codec(keys.SKIN_TOUCH).encode(msg))
    assert decoded == msg
    blind = TouchSet(N, 0.02, closed_loop=False)
    blind.add(4, Touch(pad="elbow_outer", start_s=2.0, duration_s=0.4, peak_hpa=11.0))
    (started,) = blind.start(2.0, None, None)
    msg = touch_message(0, 5, 3, started, "elbow_outer", blind, None)
    assert msg.contact_point is None and msg.normal is None and msg.q is None


def test_skin_touch_schema_is_an_object():
    assert m.json_schema(m.SkinTouch)["type"] == "object"
    assert keys.topic_for("skin/touch").type is m.SkinTouch
    assert not keys.topic_for("skin/touch").drop


# ------------------------------------------------------------------------------ the simulated skin's ground truth

def simulated_stream(q: np.ndarray, script: TouchScript, *, closed_loop: bool = False,
                     origin_ns: int = 10**9) -> tuple[list[m.SkinPressure], list[m.SkinTouch]]:
    """The gateway's cores on a script with the arm held at ``q`` (25 Hz)."""
    profile = Profile()
    sim = SimSkin(sim_settings(with_sim(profile.gateway, closed_loop=closed_loop)), DESC.pads, script)
    gateway = Gateway(profile.gateway, N)
    points, normals = MODEL.pad_points(q), MODEL.pad_normals(q)
    samples, touches = [], []
    for k in range(1, round(script.duration_s * 25) + 1):
        stamp = origin_ns + k * 40_000_000
        t = (stamp - origin_ns) / 1e9
        for started in sim.start(t, points, normals):
            touches.append(touch_message(len(touches), stamp, origin_ns, started, DESC.pads[started.pad].name,
                                         sim.touches, q, stamp))
        sample, _ = gateway.process(t, stamp, sim.sample(t, points), sim.touch_hpa)
        samples.append(sample)
    return samples, touches


SCRIPT = TouchScript(duration_s=4.0, touch=[
    Touch(pad="forearm_top", start_s=1.0, duration_s=1.0, peak_hpa=12.0),
    Touch(pad="wrist_1", start_s=2.0, duration_s=0.5, peak_hpa=9.0, shape="ramp", ramp_s=0.2),
])


def test_samples_carry_the_touch_part_of_the_pressure():
    q = np.array(DESC.home)
    samples, touches = simulated_stream(q, SCRIPT)
    assert [t.name for t in touches] == ["forearm_top", "wrist_1"]
    forearm = DESC.pad("forearm_top").id
    during = [s for s in samples if 1.2e9 < s.stamp_ns - 10**9 < 1.8e9]
    assert all(s.touch_hpa[forearm] == 12.0 for s in during)
    assert all(sum(s.touch_hpa) == 0.0 for s in samples if s.stamp_ns - 10**9 < 0.99e9)
    # A real skin (no simulated touches) leaves it empty.
    assert Gateway(GatewaySection(), 3).process(0.0, 0, np.full(3, 1000.0))[0].touch_hpa == []


def test_resimulation_against_the_same_pose_is_bit_for_bit_the_recording():
    q = np.array(DESC.home)
    samples, touches = simulated_stream(q, SCRIPT)
    res = Resimulator(GatewaySection(), touches, N)
    again = [res.apply(s, MODEL.pad_points(q), MODEL.pad_normals(q))[0] for s in samples]
    assert [msgspec.msgpack.encode(s) for s in again] == [msgspec.msgpack.encode(s) for s in samples]


def test_resimulation_of_a_window_continues_the_baseline_filter():
    q = np.array(DESC.home)
    samples, touches = simulated_stream(q, SCRIPT)
    res = Resimulator(GatewaySection(), touches, N, previous_stamp_ns=samples[29].stamp_ns)
    again = [res.apply(s, MODEL.pad_points(q), MODEL.pad_normals(q))[0] for s in samples[30:]]
    assert again == samples[30:]


def test_a_withdrawn_pad_feels_less_and_noise_is_kept():
    q = np.array(DESC.home)
    samples, touches = simulated_stream(q, SCRIPT)
    forearm = DESC.pad("forearm_top").id
    res = Resimulator(GatewaySection(), touches, N)
    points, normals = MODEL.pad_points(q), MODEL.pad_normals(q)
    out = []
    for s in samples:
        moved = points.copy()
        if s.stamp_ns - 10**9 >= 1.4e9:  # from 0.4 s into the touch, the pad is 10 mm behind the finger
            moved[forearm] -= 0.010 * normals[forearm]
        out.append(res.apply(s, moved, normals)[0])
    late = [i for i, s in enumerate(samples) if 1.5e9 <= s.stamp_ns - 10**9 < 1.9e9]
    for i in late:
        assert out[i].touch_hpa[forearm] == pytest.approx(6.0)
        assert out[i].change_hpa[forearm] == pytest.approx(samples[i].change_hpa[forearm] - 6.0, abs=1e-9)
    others = [p for p in range(N) if p != forearm]
    assert all(np.array_equal(np.asarray(a.absolute_hpa)[others], np.asarray(b.absolute_hpa)[others])
               for a, b in zip(out, samples))


def test_resimulation_without_ground_truth_is_a_clear_error():
    with pytest.raises(ConfigError, match="no touch ground truth.*only open-loop replay applies"):
        Resimulator(GatewaySection(), [], N)
    q = np.array(DESC.home)
    samples, touches = simulated_stream(q, SCRIPT)
    real = msgspec.structs.replace(samples[0], touch_hpa=[])
    with pytest.raises(ConfigError, match="no touch ground truth"):
        Resimulator(GatewaySection(), touches, N).apply(real, MODEL.pad_points(q), MODEL.pad_normals(q))


# ------------------------------------------------------------------------------ lockstep sessions and replays

def commands(path: Path) -> list[bytes]:
    return [msgspec.msgpack.encode(r.message) for r in read_recording(path)[0] if keys.is_command(r.key)]


DEMO = str(DATA / "resim.toml")  # the demo's kinds of touch, in 9 s


@pytest.fixture(scope="module")
def demo_sessions(tmp_path_factory):
    """A demo-like session in lockstep (open and closed loop, CR) and replays of the open-loop one."""
    d = tmp_path_factory.mktemp("resim")
    out = {}
    out["open"] = simulate(Profile(), DEMO, "cartesian", d / "open.mcap")[0]
    closed = Profile()
    closed.gateway = with_sim(closed.gateway, closed_loop=True)
    out["closed"] = simulate(closed, DEMO, "cartesian", d / "closed.mcap")[0]
    records, metadata = read_recording(out["open"])
    for strategy, runs in (("cartesian", (1, 2)), ("uniform", (1,))):
        out[f"open-{strategy}"] = run_fast(Profile(), records, strategy, d / f"open-{strategy}.mcap", out["open"],
                                           metadata)[0]
        for run in runs:
            out[f"resim-{strategy}-{run}"] = run_fast(Profile(), records, strategy, d / f"resim-{strategy}-{run}.mcap",
                                                      out["open"], metadata, resimulate=True)[0]
    return out


def test_a_lockstep_session_records_its_touch_ground_truth(demo_sessions):
    records, _ = read_recording(demo_sessions["open"])
    touches = [r.message for r in records if r.key == "skin/touch"]
    assert [t.name for t in touches] == ["upper_arm_top", "forearm_top", "forearm_bottom", "wrist_1", "wrist_3"]
    assert all(t.contact_point is not None and t.q is not None for t in touches)
    states = {r.message.stamp_ns: r.message for r in records if r.key == "robot/state"}
    for t in touches:  # where the pad was when the touch started
        assert t.contact_point == pytest.approx(MODEL.pad_point(t.q, t.pad).tolist())
        assert min(abs(s - t.stamp_ns) for s in states) < 10_000_000


@pytest.mark.parametrize("strategy", ["cartesian", "uniform"])
def test_resimulated_pressure_falls_below_the_open_loop_replay_during_reflexes(demo_sessions, strategy):
    opened, _ = read_recording(demo_sessions[f"open-{strategy}"])
    resim, _ = read_recording(demo_sessions[f"resim-{strategy}-1"])
    before = {r.message.seq: r.message for r in opened if r.key == "skin/pressure"}
    after = {r.message.seq: r.message for r in resim if r.key == "skin/pressure"}
    falls = {}
    for touch in analysis.summarize(opened, DESC):
        if touch.reflex_seq:
            seqs = range(touch.first_seq, touch.last_seq + 1)
            gap = [before[s].change_hpa[touch.pad] - after[s].change_hpa[touch.pad] for s in seqs]
            assert min(gap) > -1e-9, touch.name  # never more than the open-loop pressure
            falls[touch.name] = max(gap)
    # The strong ramp on the forearm is withdrawn from by both reflexes; the short wrist_3 touch by the
    # Cartesian one (the uniform reflex, within the bridge's Cartesian limits, is still returning from the
    # forearm's and moves the wrist ring away too slowly for a 0.3 s touch).
    assert falls["forearm_top"] > 5.0, falls
    if strategy == "cartesian":
        assert falls["wrist_3"] > 5.0, falls


def test_two_resimulated_replays_are_identical(demo_sessions):
    a, b = demo_sessions["resim-cartesian-1"], demo_sessions["resim-cartesian-2"]
    ra, rb = read_recording(a)[0], read_recording(b)[0]
    assert [(r.key, msgspec.msgpack.encode(r.message)) for r in ra] == \
        [(r.key, msgspec.msgpack.encode(r.message)) for r in rb]
    assert commands(a) != commands(demo_sessions["open-cartesian"])  # and the loop was closed


def test_replays_reproduce_the_original_commands(demo_sessions, tmp_path):
    # Open loop: the open-loop session replayed open loop with its strategy.
    assert commands(demo_sessions["open-cartesian"]) == commands(demo_sessions["open"])
    # Closed loop: the closed-loop session replayed with --resimulate, and open loop.
    records, metadata = read_recording(demo_sessions["closed"])
    resim = run_fast(Profile(), records, "cartesian", tmp_path / "r.mcap", demo_sessions["closed"], metadata,
                     resimulate=True)[0]
    opened = run_fast(Profile(), records, "cartesian", tmp_path / "o.mcap", demo_sessions["closed"], metadata)[0]
    original = commands(demo_sessions["closed"])
    assert len(original) > 2_000  # reflexes and returns: one per cycle; the task: one per 10
    assert commands(resim) == original
    assert commands(opened) == original
    again = read_recording(resim)[0]
    assert [r.message for r in again if r.key == "skin/pressure"] == \
        [r.message for r in records if r.key == "skin/pressure"]
    assert [r.message for r in again if r.key == "skin/touch"] == [r.message for r in records if r.key == "skin/touch"]
    # nwr compare says so.
    sessions = [compare.load_session(p, DESC, MODEL) for p in (demo_sessions["closed"], resim, demo_sessions["open"])]
    assert compare.command_streams(sessions[0], sessions[1]).endswith("identical to closed (cartesian)'s")
    assert "they part at command" in compare.command_streams(sessions[0], sessions[2])
    rows = compare.line_up(sessions, 0.3)
    errors = [compare.trajectory_error(sessions[0], row[0], sessions[1], row[1]) for row in rows if row[0].reflex_seq]
    assert errors and all(e == 0.0 for e in errors)
    text = compare.table(sessions, rows)
    assert "dq vs first (mrad)" in text


def test_resimulating_a_recording_without_ground_truth_fails_clearly(demo_sessions, tmp_path):
    records, metadata = read_recording(demo_sessions["open"])
    real = [r for r in records if r.key != "skin/touch"]
    with pytest.raises(ConfigError, match="no touch ground truth: it was not recorded from the simulated skin"):
        run_fast(Profile(), real, "cartesian", tmp_path / "x.mcap", demo_sessions["open"], metadata, resimulate=True)


# ------------------------------------------------------------------------------ a live session

@pytest.mark.e2e
@pytest.mark.slow
def test_live_session_records_ground_truth_and_its_fast_replay_makes_the_same_decisions(tmp_path):
    import subprocess
    import sys

    profile = tmp_path / "profile.toml"
    profile.write_text(f'[zenoh]\nbase_port = 18250\n[recorder]\ndirectory = "{tmp_path}"\n')
    cli = [sys.executable, "-m", "nwr.services.cli", "--profile", str(profile), "--log-level", "WARNING"]
    live = tmp_path / "live.mcap"
    demo = subprocess.run([*cli, "demo", "--world", "scripted", "--script", str(DATA / "short.toml"), "--reflex",
                           "uniform", "-o", str(live)], capture_output=True, text=True, timeout=120)
    assert demo.returncode == 0, demo.stdout + demo.stderr

    records, _ = read_recording(live)
    touches = [r.message for r in records if r.key == "skin/touch"]
    assert [t.name for t in touches] == ["upper_arm_top", "forearm_top", "wrist_2", "elbow_outer"]
    # The gateway followed robot/state: each contact point is where the pad was, from a fresh pose.
    for t in touches:
        assert t.contact_point is not None and t.q is not None and not t.closed_loop
        assert t.contact_point == pytest.approx(MODEL.pad_point(t.q, t.pad).tolist())
        assert 0 <= t.stamp_ns - t.pose_stamp_ns < 200_000_000
    info = subprocess.run([*cli, "info", str(live)], capture_output=True, text=True, timeout=60)
    assert "nwr/ur10e/skin/touch" in info.stdout and "nwr.SkinTouch" in info.stdout

    outputs = {}
    for name, extra in (("fast", []), ("resim", ["--resimulate"])):
        outputs[name] = tmp_path / f"{name}.mcap"
        proc = subprocess.run([*cli, "replay", str(live), "--fast", *extra, "-o", str(outputs[name])],
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
    # Exact where the design makes it so: every live service re-runs bit for bit from its journal (the live
    # planner's lost cycles included), and the replay feeds the same samples to the same gain core, so its pain
    # messages and each touch's decision are those of the live session, to the bit. (The reflex motion itself
    # follows the live machine's timing, which the journal, not a lockstep replay, reproduces.)
    results = verify(live)
    assert {r.service for r in results} == {"gateway", "gain", "planner-uniform", "bridge"}
    assert all(r.verdict == "identical" for r in results), [r.format() for r in results]
    replayed, _ = read_recording(outputs["fast"])
    pain = [(r.message.seq, r.message.level, r.message.gain) for r in records if r.key == "skin/pain"]
    assert pain == [(r.message.seq, r.message.level, r.message.gain) for r in replayed if r.key == "skin/pain"]
    live_touches = analysis.summarize(records, DESC)
    sessions = [compare.load_session(p, DESC, MODEL) for p in (live, outputs["fast"])]
    rows = compare.line_up(sessions, 0.3)
    assert len(rows) == len(live_touches) == 4
    for a, b in rows:  # the same decision per touch: a reflex or none, with the same gain
        assert a is not None and b is not None
        assert (a.reflex_seq > 0) == (b.reflex_seq > 0) and b.gain == a.gain
    # A live session was recorded open loop: --resimulate changes what the withdrawn pads felt.
    fast = {r.message.seq: r.message for r in read_recording(outputs["fast"])[0] if r.key == "skin/pressure"}
    resim = {r.message.seq: r.message for r in read_recording(outputs["resim"])[0] if r.key == "skin/pressure"}
    assert fast.keys() == resim.keys()
    assert any(fast[s].change_hpa != resim[s].change_hpa for s in fast)
