"""The physics world in the pipeline: the bridge's physics backend, its hosted world, the gateway's physics source."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.launch import Touch, TouchScript, load_script
from nwr.common.robot import RobotModel, load_description
from nwr.services.bridge.backends.physics import PhysicsBackend
from nwr.services.bridge.core import Setpoint
from nwr.services.bridge.wiring import envelope_for
from nwr.services.gateway.stepped import SimulatedSkin
from nwr.services.pipeline.lockstep import Lockstep
from nwr.services.worlds.hosted import HostedWorld, check_script, finger_force
from nwr.services.worlds.physics import PhysicsSettings, WorldUnstable

DESC = load_description()
MODEL = RobotModel(DESC)
SETTINGS = PhysicsSettings()
FOREARM_TOP = DESC.pad("forearm_top").id


def touch_message(seq: int, pad: int, start_s: float, peak_hpa: float, duration_s: float = 0.4,
                  shape: str = "step", ramp_s: float = 0.0) -> m.SkinTouch:
    return m.SkinTouch(seq=seq, stamp_ns=0, pad=pad, name=DESC.pads[pad].name, origin_ns=0, start_s=start_s,
                       duration_s=duration_s, peak_hpa=peak_hpa, shape=shape, ramp_s=ramp_s)  # type: ignore[arg-type]


def run_hosted(world: HostedWorld, until_s: float, q: np.ndarray, start_ns: int = 0,
               period_ns: int = 2_000_000) -> list[tuple[str, object]]:
    out: list[tuple[str, object]] = []
    for now in range(start_ns + period_ns, round(until_s * 1e9) + 1, period_ns):
        out += world.advance(now, q, np.zeros_like(q))
    return out


def physics_profile() -> Profile:
    profile = Profile()
    profile.bridge.backend = "physics"
    profile.gateway.source = "physics"
    return profile


# ------------------------------------------------------------------------------ the script against the world


def test_todays_touch_scripts_fit_the_physics_world() -> None:
    for name in ("demo", "contacts", "survey", "held-press", "slow-press", "two-fingers"):
        check_script(load_script(name), SETTINGS, DESC)


@pytest.mark.parametrize(("touches", "match"), [
    ([Touch(pad="forearm_top", start_s=1.0, duration_s=0.3, peak_hpa=60.0)],
     r"60.0 hPa takes .* N of finger force in the physics world, beyond a finger's plausible push of 50 N"),
    ([Touch(pad="forearm_top", start_s=1.0, duration_s=0.3, peak_hpa=90.0)], r"beyond a finger's plausible push"),
    ([Touch(pad="forearm_top", start_s=1.0 + 0.01 * i, duration_s=0.5, peak_hpa=9.0) for i in range(5)],
     r"5 touches at once at 1.04 s; the physics world holds 4 fingers"),
    ([Touch(pad="knee", start_s=1.0, duration_s=0.5, peak_hpa=9.0)], r"names pad 'knee'"),
    ([Touch(pad="forearm_top", start_s=1.0, duration_s=0.5, peak_hpa=9.0, body_area="elbow")],
     r"names body_area 'elbow'; ISO/TS 15066's are forehead, temple, .*forearm_muscle"),
])
def test_a_script_the_world_cannot_play_is_refused_before_anything_moves(touches: list[Touch], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        check_script(TouchScript(duration_s=5.0, touch=touches), SETTINGS, DESC)


# ------------------------------------------------------------------------------ the hosted world


def test_a_touch_becomes_a_finger_whose_pressure_follows_the_script_and_which_leaves_at_its_end() -> None:
    world = HostedWorld(DESC, SETTINGS, DESC.home)
    q = np.asarray(DESC.home, dtype=float)
    run_hosted(world, 0.2, q)
    world.touch(touch_message(0, FOREARM_TOP, start_s=0.2, peak_hpa=16.0, duration_s=0.6), 200_000_000)
    out = run_hosted(world, 1.6, q, start_ns=200_000_000)
    skin = [msg for key, msg in out if key == keys.WORLD_SKIN]
    assert all(isinstance(s, m.WorldSkin) for s in skin)
    pressing = [s.change_hpa[FOREARM_TOP] for s in skin if 0.5e9 <= s.stamp_ns <= 0.8e9]  # type: ignore[union-attr]
    assert pressing and all(abs(p - 16.0) < 16.0 * 0.1 for p in pressing), pressing
    others = [max(abs(c) for i, c in enumerate(s.change_hpa) if i != FOREARM_TOP) for s in skin]  # type: ignore[union-attr]
    assert max(others) < 0.5
    after = [s.change_hpa[FOREARM_TOP] for s in skin if s.stamp_ns >= 1.0e9]  # type: ignore[union-attr]
    assert after and max(after) < 0.5  # lifted at 0.8 s, out of the world 0.3 s later
    assert not world.fingers and not world.world.people()
    contacts = [msg for key, msg in out if key == keys.WORLD_CONTACTS]
    assert contacts and all(isinstance(c, m.WorldContacts) for c in contacts)
    peak = max(p.peak_force_n for c in contacts for p in c.people)  # type: ignore[union-attr]
    assert abs(peak - finger_force(16.0, SETTINGS)) < 3.0


def test_a_pad_that_moves_into_the_finger_presses_harder_and_pushes_it_back() -> None:
    world = HostedWorld(DESC, SETTINGS, DESC.home)
    q0 = np.asarray(DESC.home, dtype=float)
    run_hosted(world, 0.1, q0)
    world.touch(touch_message(0, FOREARM_TOP, start_s=0.1, peak_hpa=9.0, duration_s=2.0), 100_000_000)
    run_hosted(world, 0.6, q0, start_ns=100_000_000)
    still = world.world.pressure_hpa()[FOREARM_TOP]
    normal = MODEL.pad_normal(q0, FOREARM_TOP)
    q1 = q0 + np.linalg.pinv(MODEL.pad_jacobian(q0, FOREARM_TOP)[:3]) @ (normal * 0.01)  # 10 mm into the finger
    out = []
    for i, now in enumerate(range(602_000_000, 1_400_000_001, 2_000_000)):
        x = min(1.0, (i + 1) / 200)
        out += world.advance(now, q0 + (q1 - q0) * x * x * (3 - 2 * x), np.zeros(6))
    assert world.world.pressure_hpa()[FOREARM_TOP] > still + 3.0  # 10 mm more against 500 N/m: about 5 N more
    people = [c for key, c in out if key == keys.WORLD_CONTACTS][-1].people  # type: ignore[union-attr]
    assert 0.006 < people[0].pushed_m < 0.011 and people[0].peak_pushed_m >= people[0].pushed_m


def carry_away(follow_m_s: float, away_m: float, over_s: float) -> tuple[float, float, float]:
    """A 9 hPa press on forearm_top while the arm carries the pad ``away_m`` back along its normal over
    ``over_s`` (smoothly, from 0.6 s): the pad's pressure before, at the end of the move and 0.3 s later."""
    world = HostedWorld(DESC, SETTINGS, DESC.home)
    q0 = np.asarray(DESC.home, dtype=float)
    run_hosted(world, 0.1, q0)
    msg = touch_message(0, FOREARM_TOP, start_s=0.1, peak_hpa=9.0, duration_s=3.0)
    world.touch(msgspec.structs.replace(msg, follow_m_s=follow_m_s), 100_000_000)
    run_hosted(world, 0.6, q0, start_ns=100_000_000)
    before = float(world.world.pressure_hpa()[FOREARM_TOP])
    normal = MODEL.pad_normal(q0, FOREARM_TOP)
    q1 = q0 - np.linalg.pinv(MODEL.pad_jacobian(q0, FOREARM_TOP)[:3]) @ (normal * away_m)
    steps = round(over_s / 0.002)
    for i, now in enumerate(range(602_000_000, 600_000_001 + steps * 2_000_000, 2_000_000)):
        x = min(1.0, (i + 1) / steps)
        world.advance(now, q0 + (q1 - q0) * x * x * (3 - 2 * x), np.zeros(6))
    moved = float(world.world.pressure_hpa()[FOREARM_TOP])
    end = 600_000_000 + steps * 2_000_000
    run_hosted(world, end / 1e9 + 0.3, q1, start_ns=end)
    return before, moved, float(world.world.pressure_hpa()[FOREARM_TOP])


def test_a_finger_that_follows_keeps_pressing_a_pad_carried_away_slowly_and_loses_one_withdrawn_fast() -> None:
    # Carried 40 mm away over 1 s (about 60 mm/s at most): a finger held where it met the pad loses it (its
    # spring travel is 9 hPa's 11.6 N / 500 N/m = 23 mm); one that follows at up to 0.3 m/s keeps pressing.
    held = carry_away(0.0, 0.04, 1.0)
    follows = carry_away(0.3, 0.04, 1.0)
    assert abs(held[0] - 9.0) < 1.0 and abs(follows[0] - 9.0) < 1.0
    assert held[1] < 0.5 and held[2] < 0.5
    assert abs(follows[1] - 9.0) < 1.5 and abs(follows[2] - 9.0) < 0.5
    # Withdrawn 40 mm in 0.1 s (up to 0.6 m/s): faster than its owner follows (0.05 m/s), the pad leaves it.
    slow_owner = carry_away(0.05, 0.04, 0.1)
    assert slow_owner[1] < 0.5


def test_a_touch_the_world_cannot_take_enters_nothing() -> None:
    world = HostedWorld(DESC, SETTINGS, DESC.home)
    with pytest.raises(ConfigError, match="beyond a finger's plausible push"):
        world.touch(touch_message(0, FOREARM_TOP, start_s=0.0, peak_hpa=60.0), 0)
    odd = touch_message(0, FOREARM_TOP, start_s=0.0, peak_hpa=5.0)
    with pytest.raises(ConfigError, match="body_area 'elbow' is none of ISO/TS 15066's: not pressed"):
        world.touch(msgspec.structs.replace(odd, body_area="elbow"), 0)
    with pytest.raises(ConfigError, match="follow_m_s = 3.0; expected 0 to 1.0 m/s"):
        world.touch(msgspec.structs.replace(odd, follow_m_s=3.0), 0)
    for seq in range(4):
        world.touch(touch_message(seq, FOREARM_TOP, start_s=0.0, peak_hpa=5.0), 0)
    with pytest.raises(ConfigError, match="no free finger"):
        world.touch(touch_message(4, FOREARM_TOP, start_s=0.0, peak_hpa=5.0), 0)
    assert sorted(world.world.people()) == [f"touch-{i}" for i in range(4)]


def test_a_late_cycle_catches_up_a_bounded_number_of_steps_and_counts_the_rest() -> None:
    world = HostedWorld(DESC, SETTINGS, DESC.home)
    q = np.asarray(DESC.home, dtype=float)
    world.advance(0, q, np.zeros(6))
    world.advance(10_000_000, q, np.zeros(6))
    assert world.world.time_ns == 10_000_000 and world.lost_ns == 0
    world.advance(210_000_000, q, np.zeros(6))  # 200 ms late: 50 ms caught up, 150 ms lost
    assert world.world.time_ns == 60_000_000 and world.lost_ns == 150_000_000


# ------------------------------------------------------------------------------ the backend


def test_the_backend_reads_the_world_arm_back_and_a_diverged_world_is_a_protective_stop_without_a_jump(
        monkeypatch: pytest.MonkeyPatch) -> None:
    env, q0, _ = envelope_for(physics_profile())
    backend = PhysicsBackend(env, 0.002, q0, DESC, SETTINGS)
    backend.connect()
    target = q0 + np.array([0.002, 0, 0, 0, 0, 0])
    backend.send_action(Setpoint("position", target, np.zeros(6), np.zeros(6)))
    for k in range(1, 151):
        backend.advance(k * 2_000_000)
    obs = backend.get_observation()
    assert obs.fault is None and np.abs(obs.q - target).max() < 1e-4
    before = obs.q

    def diverge(*args: object, **kwargs: object) -> None:
        raise WorldUnstable("the physics world diverged at t = 0.3 s: a test")

    monkeypatch.setattr(backend.hosted.world, "step", diverge)
    assert backend.advance(302_000_000) == []
    obs = backend.get_observation()
    assert obs.fault == "protective_stop" and "physics world stopped" in obs.detail
    np.testing.assert_array_equal(obs.q, before)
    assert not obs.dq.any()
    assert backend.advance(304_000_000) == []  # it stays stopped


# ------------------------------------------------------------------------------ the pipeline in lockstep


def lockstep_run() -> list[tuple[str, object, int]]:
    profile = physics_profile()
    script = TouchScript(duration_s=2.0, touch=[Touch(pad="forearm_top", start_s=0.5, duration_s=0.4,
                                                      peak_hpa=16.0)])
    out: list[tuple[str, object, int]] = []
    Lockstep(profile, strategy="cartesian").run(SimulatedSkin(profile, script, MODEL),
                                                lambda key, message, t: out.append((key, message, t)), settle_s=0.5)
    return out


def test_the_pipeline_in_lockstep_feels_the_worlds_finger_withdraws_and_runs_the_same_twice() -> None:
    first = lockstep_run()
    pressure = [msg for key, msg, _ in first if key == keys.SKIN_PRESSURE]
    assert pressure and all(p.source == "physics" and not p.touch_hpa for p in pressure)  # type: ignore[union-attr]
    assert max(p.change_hpa[FOREARM_TOP] for p in pressure) > 12.0  # type: ignore[union-attr]
    touches = [msg for key, msg, _ in first if key == keys.SKIN_TOUCH]
    assert len(touches) == 1
    states = [msg for key, msg, _ in first if key == keys.ROBOT_STATE]
    assert any(s.reflex_seq > 0 for s in states) and all(s.backend == "physics" for s in states)  # type: ignore
    world_skin = [msg for key, msg, _ in first if key == keys.WORLD_SKIN]
    assert len(world_skin) == len(pressure)  # every world sample became one pressure sample
    second = lockstep_run()
    assert [(k, msgspec.msgpack.encode(x), t) for k, x, t in first if not k.startswith("journal/")] == \
        [(k, msgspec.msgpack.encode(x), t) for k, x, t in second if not k.startswith("journal/")]


# ------------------------------------------------------------------------------ the launch


def test_a_launch_chooses_the_world_and_refuses_half_of_one_or_a_script_it_cannot_play(tmp_path) -> None:
    import argparse

    from nwr.services.tools.demo import layout_for, world_for

    def args(**kw: object) -> argparse.Namespace:
        base = dict(world=None, script=None, closed_loop=False, backend=None, robot_ip="", confirmed=False,
                    planners=None, reflex=None, view=None, follow_target=None)
        return argparse.Namespace(**{**base, **kw})

    profile = Profile()
    assert world_for(args(), profile) == "scripted" and profile.bridge.backend == "sim"
    layout = layout_for(args(world="physics", script="demo"), profile, None)
    assert profile.bridge.backend == "physics" and profile.gateway.source == "physics"
    assert layout.bridge == ["--backend", "physics"] and layout.gateway[-2:] == ["--source", "physics"]
    half = Profile()
    half.bridge.backend = "physics"
    with pytest.raises(ConfigError, match="a physics world is both"):
        world_for(args(), half)
    with pytest.raises(ConfigError, match="--closed-loop is the scripted world's"):
        world_for(args(world="physics", closed_loop=True), Profile())
    hard = tmp_path / "hard.toml"
    hard.write_text('duration_s = 3.0\n[[touch]]\npad = "wrist_1"\nstart_s = 1.0\nduration_s = 0.5\npeak_hpa = 45.0\n')
    with pytest.raises(ConfigError, match="beyond a finger's plausible push"):
        world_for(args(world="physics", script=str(hard)), Profile())


def test_nwr_demo_runs_the_physics_world_by_default_and_says_where_it_cannot(tmp_path, caplog) -> None:
    """`nwr demo` with no --world: the physics world; the scripted world, with a warning that says why, for the
    scripted skin's closed loop, a robot without collision shapes or a script the physics world refuses;
    silently for a backend given or a profile's arm or skin; `--world scripted` and `nwr up` as before."""
    import logging

    from nwr.common.config import load_profile
    from nwr.services.cli import build_parser
    from nwr.services.tools.demo import layout_for, world_for

    parser = build_parser()

    def world(*argv: str, profile: Profile | None = None) -> tuple[str, Profile, str]:
        profile = profile or Profile()
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="nwr.services.tools.demo"):
            got = world_for(parser.parse_args(list(argv)), profile)
        return got, profile, caplog.text

    got, profile, said = world("demo")
    assert got == "physics" and (profile.bridge.backend, profile.gateway.source) == ("physics", "physics")
    assert "`nwr demo`'s default" in said
    assert world("demo", "--fast", "--script", "two-fingers")[0] == "physics"
    assert layout_for(parser.parse_args(["demo"]), Profile(), None).bridge == ["--backend", "physics"]
    for argv in (("demo", "--world", "scripted"), ("up",), ("demo", "--backend", "sim")):
        got, profile, said = world(*argv)
        assert (got, profile.bridge.backend, profile.gateway.source, said) == ("scripted", "sim", "sim", ""), argv
    real = Profile()
    real.bridge.backend = "ur_rtde"
    assert world("demo", profile=real)[:2] == ("scripted", real) and real.bridge.backend == "ur_rtde"
    ros = Profile()
    ros.gateway.source = "ros2"
    assert world("demo", profile=ros)[0] == "scripted" and ros.gateway.source == "ros2"

    hard = tmp_path / "hard.toml"
    hard.write_text('duration_s = 3.0\n[[touch]]\npad = "wrist_1"\nstart_s = 1.0\nduration_s = 0.5\npeak_hpa = 45.0\n')
    for argv, profile, why in [(("demo", "--closed-loop"), None, "closed loop is the scripted world's"),
                               (("demo", "--script", str(hard)), None, "beyond a finger's plausible push"),
                               (("demo", "--fast"), load_profile("fr3"), "no collision shapes for the fr3")]:
        got, profile, said = world(*argv, profile=profile)
        assert got == "scripted" and profile.bridge.backend == "sim", argv
        assert "WARNING" in said and "the scripted world" in said and why in said, (argv, said)
    with pytest.raises(ConfigError, match="beyond a finger's plausible push"):
        world("demo", "--world", "physics", "--script", str(hard))  # asked for: refused, never replaced
    with pytest.raises(ConfigError, match="--closed-loop is the scripted world's"):
        world("demo", "--world", "physics", "--closed-loop")


def test_a_world_that_diverges_under_the_bridge_stops_the_arm_where_it_was_with_a_diagnostic(
        monkeypatch: pytest.MonkeyPatch) -> None:
    from nwr.common.clock import ManualClock
    from nwr.common.journal import Untracked
    from nwr.services.bridge.wiring import BridgeWiring

    clock = ManualClock(10**9)
    out: list[tuple[str, object]] = []
    reports: list[tuple[str, str, str]] = []
    bridge = BridgeWiring(physics_profile(), journal=Untracked(clock), out=lambda k, msg: out.append((k, msg)),
                          diag=lambda level, code, text, every_s=1.0: reports.append((level, code, text)))
    assert isinstance(bridge.backend, PhysicsBackend) and bridge.listens(bridge.inputs["touch"])
    for _ in range(50):
        clock.t_ns += 2_000_000
        bridge.tick()
    q_before = bridge.backend.get_observation().q

    def diverge(*args: object, **kwargs: object) -> None:
        raise WorldUnstable("the physics world diverged at t = 0.1 s: a contact is 25.0 mm deep")

    monkeypatch.setattr(bridge.backend.hosted.world, "step", diverge)
    for _ in range(30):
        clock.t_ns += 2_000_000
        bridge.tick()
    states = [msg for key, msg in out if key == keys.ROBOT_STATE]
    assert states[-1].status == "protective_stop"  # type: ignore[attr-defined]
    np.testing.assert_array_equal(m.as_array(states[-1].q), q_before)  # type: ignore[attr-defined]
    assert any(code == "protective_stop" and "25.0 mm deep" in text for _, code, text in reports), reports


def test_a_finger_that_would_start_inside_the_arm_at_its_starting_pose_is_refused_before_anything_moves() -> None:
    folded = np.array(DESC.home, dtype=float)
    folded[2] = 3.1  # the elbow folded: the wrist lies against the shoulder
    script = TouchScript(duration_s=3.0, touch=[Touch(pad="wrist_1", start_s=1.0, duration_s=0.5, peak_hpa=9.0)])
    check_script(script, SETTINGS, DESC, np.asarray(DESC.home, dtype=float))  # at home it fits
    with pytest.raises(ConfigError, match=r"touch on wrist_1 at 1.0 s, at the arm's starting pose: .* starts "
                                          r"1\d.\d mm inside the arm"):
        check_script(script, SETTINGS, DESC, folded)
