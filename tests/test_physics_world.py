"""The physics world's core (nwr.services.worlds.physics): MuJoCo arm, pad cushions, people on springs, skin."""

from __future__ import annotations

import dataclasses
import time

import msgspec
import numpy as np
import pytest

from nwr.common.config import GainSection
from nwr.common.errors import ConfigError, SafetyError
from nwr.common.robot import RobotModel, load_description
from nwr.services.gain.core import pain_level
from nwr.services.worlds import mjcf
from nwr.services.worlds.people import ISO_TS_15066, KINDS, region_of
from nwr.services.worlds.physics import BodyPart, PhysicsSettings, PhysicsWorld, WorldUnstable
from nwr.services.worlds.skin import force_for_pressure, pressure_from_force

DESC = load_description()
MODEL = RobotModel(DESC)
THRESHOLDS = tuple(GainSection().thresholds_hpa)
UPPER_ARM_TOP = DESC.pad("upper_arm_top").id
FOREARM_TOP = DESC.pad("forearm_top").id


def level(p: float) -> int:
    return pain_level(p, THRESHOLDS)


def settle(world: PhysicsWorld, seconds: float = 0.6, q: np.ndarray | None = None) -> None:
    world.run(world.arm().q_command if q is None else q, seconds)


def move_pad(world: PhysicsWorld, pad: int, distance_m: float, seconds: float = 0.5) -> np.ndarray:
    """Command the arm so that ``pad`` moves ``distance_m`` along its outward normal (smoothly, in ``seconds``);
    returns the final command."""
    q0 = world.arm().q_command
    normal = MODEL.pad_normal(q0, pad)
    dq = np.linalg.pinv(MODEL.pad_jacobian(q0, pad)[:3]) @ (normal * distance_m)
    steps = round(seconds * 1e9 / world.timestep_ns)
    for i in range(1, steps + 1):
        x = i / steps
        world.step(q0 + dq * x * x * (3.0 - 2.0 * x))
    return q0 + dq


# ------------------------------------------------------------------------------ the model


def test_the_model_places_every_cushion_where_the_skin_file_puts_its_pad() -> None:
    world = PhysicsWorld(DESC)
    for pad in DESC.pads:
        point, normal = world.pad_surface(pad.id)
        np.testing.assert_allclose(point, MODEL.pad_point(DESC.home, pad.id), atol=1e-12)
        np.testing.assert_allclose(normal, MODEL.pad_normal(DESC.home, pad.id), atol=1e-12)


def test_a_robot_without_packaged_shapes_gets_capsules_between_its_joint_frames() -> None:
    other = dataclasses.replace(DESC, name="not_a_ur10e")
    world = PhysicsWorld(other, PhysicsSettings(skeleton_radius_m=0.04))
    shapes = [world.model.geom(name) for name in world.layout.arm_geoms]
    # base -> shoulder, upper arm, forearm, wrist 1 -> 2, wrist 2 -> 3 (the shoulder's two joints share an origin)
    assert len(shapes) == 5 and all(geom.size[0] == 0.04 for geom in shapes)
    world.press("finger", UPPER_ARM_TOP, 10.0)
    settle(world)
    assert level(world.pressure_hpa()[UPPER_ARM_TOP]) == 3


def test_a_model_that_does_not_load_is_refused_before_anything_moves(monkeypatch: pytest.MonkeyPatch) -> None:
    bad = mjcf.LinkShape(link="no_such_link", start_m=[0, 0, 0], end_m=[0, 0, 0.1], radius_m=0.05)
    with pytest.raises(ConfigError, match="no_such_link"):
        PhysicsWorld(DESC, PhysicsSettings(shapes=[bad]))

    def broken(desc: object, params: object) -> tuple[str, object]:
        return "<mujoco><worldbody><body><geom type='nonsense'/></body></worldbody></mujoco>", None

    monkeypatch.setattr(mjcf, "build", broken)
    with pytest.raises(ConfigError, match="MuJoCo cannot load"):
        PhysicsWorld(DESC)


def test_settings_are_bounded_and_strict() -> None:
    decode = msgspec.convert
    assert decode({"timestep_s": 0.002}, PhysicsSettings).timestep_s == 0.002
    with pytest.raises(msgspec.ValidationError, match="timestep_s"):
        decode({"timestep_s": 0.1}, PhysicsSettings)
    with pytest.raises(msgspec.ValidationError, match="unknown field"):
        decode({"time_step": 0.001}, PhysicsSettings)


# ------------------------------------------------------------------------------ the arm


def test_the_arm_tracks_a_joint_command_and_holds_it() -> None:
    world = PhysicsWorld(DESC)
    amplitude = np.array([0.3, 0.2, 0.2, 0.3, 0.3, 0.3])
    worst = 0.0
    for i in range(1, 2001):  # 2 s of a 0.5 Hz sine on every joint (peak speeds 0.6-0.9 rad/s), 1 kHz commands
        command = DESC.home + amplitude * np.sin(np.pi * i * 1e-3)
        world.step(command)
        if i > 200:
            worst = max(worst, float(np.abs(world.arm().q - command).max()))
    assert worst < 0.01, worst
    held = DESC.home + 0.05
    world.run(held, 1.0)
    np.testing.assert_allclose(world.arm().q, held, atol=1e-5)
    assert np.abs(world.arm().dq).max() < 1e-4


def test_a_command_that_is_not_a_joint_vector_moves_nothing() -> None:
    world = PhysicsWorld(DESC)
    for bad in ([0.0] * 5, [np.nan] * 6, "home"):
        with pytest.raises(SafetyError, match="nothing moved"):
            world.step(bad)
    assert world.time_ns == 0


# ------------------------------------------------------------------------------ skin from contact


def test_the_pressure_model_puts_the_papers_thresholds_at_finger_forces() -> None:
    area, saturation = 125e-4, 80.0
    forces = [force_for_pressure(p, area, saturation) for p in THRESHOLDS]
    np.testing.assert_allclose(forces, [2.50, 7.51, 15.11, 25.54], atol=0.01)
    np.testing.assert_allclose(pressure_from_force(np.array(forces), area, saturation), THRESHOLDS)


@pytest.mark.parametrize(("force_n", "expected"), [(1.5, 1), (4.0, 2), (10.0, 3), (20.0, 4), (35.0, 4)])
def test_a_finger_pressing_a_pad_lands_in_the_pain_level_of_its_force(force_n: float, expected: int) -> None:
    """A light touch (PL 1-2, no reflex), a press (PL 3), a firm and a hard press (PL 4, G = 1 beyond 20 hPa)."""
    world = PhysicsWorld(DESC)
    world.press("finger", UPPER_ARM_TOP, force_n)
    settle(world)
    pressure = world.pressure_hpa()
    assert level(pressure[UPPER_ARM_TOP]) == expected, pressure[UPPER_ARM_TOP]
    assert np.delete(pressure, UPPER_ARM_TOP).max() == 0.0
    person = world.people()["finger"]
    assert person.pads == (UPPER_ARM_TOP,)
    assert person.force_n == pytest.approx(force_n, rel=0.05)


@pytest.mark.parametrize("peak_hpa", [4.0, 9.0, 16.0, 22.0])
def test_a_scripted_pressure_becomes_the_finger_force_that_makes_it(peak_hpa: float) -> None:
    """Today's touch scripts in the physics world: a touch of peak p is a finger pressing with the force for p."""
    world = PhysicsWorld(DESC)
    world.press("finger", FOREARM_TOP, world.force_for_pressure(peak_hpa))
    settle(world)
    measured = world.pressure_hpa()[FOREARM_TOP]
    assert measured == pytest.approx(peak_hpa, rel=0.05)
    assert level(measured) == level(peak_hpa)


def test_the_skin_samples_at_its_rate_with_its_noise_and_latency() -> None:
    settings = PhysicsSettings(skin_rate_hz=25.0, skin_latency_s=0.012, skin_noise_hpa=0.1, seed=3)
    world = PhysicsWorld(DESC, settings)
    world.press("finger", UPPER_ARM_TOP, 10.0)
    samples = []
    for _ in range(2000):
        world.step(DESC.home)
        samples += world.skin()
    taken = np.array([s.taken_ns for s in samples])
    assert len(samples) == 49  # every 40 ms from 40 ms; the one taken at 2.000 s arrives at 2.012 s
    np.testing.assert_array_equal(np.diff(taken), 40_000_000)
    assert all(s.delivered_ns - s.taken_ns == 12_000_000 for s in samples)
    at_rest = np.array([s.absolute_hpa for s in samples[-20:]])
    noise = at_rest - at_rest.mean(axis=0)
    assert 0.07 < noise[:, [p.id for p in DESC.pads if p.id != UPPER_ARM_TOP]].std() < 0.13
    change = samples[-1].absolute_hpa - world.sampler.baseline_hpa
    assert level(change[UPPER_ARM_TOP]) == 3
    assert np.abs(np.delete(change, UPPER_ARM_TOP)).max() < 0.6  # noise only
    assert 1010.0 <= world.sampler.baseline_hpa.min() and world.sampler.baseline_hpa.max() <= 1016.0


def test_a_sample_is_the_mean_of_its_period_so_a_contact_lost_for_one_step_dims_it_never_blanks_it() -> None:
    from nwr.services.worlds.skin import SkinSampler

    def run(mean: bool) -> list[float]:
        sampler = SkinSampler(1, rate_hz=25.0, latency_s=0.0, noise_hpa=0.0, base_hpa=0.0, spread_hpa=0.0, seed=1,
                              mean=mean)
        got = []
        for k in range(1, 201):  # 1 ms steps: a 4 hPa press that drops to 0 at every sample's own step
            sample = sampler.observe(k * 1_000_000, np.array([0.0 if k % 40 == 0 else 4.0]))
            if sample is not None:
                got.append(float(sample.change_hpa[0]))
        return got

    assert run(mean=False) == [0.0] * 5  # the instant: blank at every sample, the touch split or lost
    assert run(mean=True) == pytest.approx([4.0 * 39 / 40] * 5)


# ------------------------------------------------------------------------------ people


def test_a_finger_that_keeps_pressing_presses_harder_when_the_arm_moves_into_it() -> None:
    world = PhysicsWorld(DESC)
    world.press("finger", UPPER_ARM_TOP, 10.0)
    settle(world)
    before = world.people()["finger"].force_n
    assert level(world.pressure_hpa()[UPPER_ARM_TOP]) == 3
    q = move_pad(world, UPPER_ARM_TOP, 0.02)  # the pad moves 2 cm into the finger
    settle(world, q=q)
    after = world.people()["finger"]
    # The person's spring (500 N/m) pushes 2 cm x 500 N/m = 10 N harder: PL 3 became PL 4.
    assert after.force_n == pytest.approx(before + 10.0, abs=1.5)
    assert level(world.pressure_hpa()[UPPER_ARM_TOP]) == 4
    assert after.peak_force_n >= after.force_n
    assert after.energy_j > 0.0  # the arm did work on the finger it pushed back


def test_a_finger_loses_contact_when_the_arm_withdraws() -> None:
    world = PhysicsWorld(DESC)
    part = world.press("finger", UPPER_ARM_TOP, 10.0)
    settle(world)
    assert world.people()["finger"].in_contact
    q = move_pad(world, UPPER_ARM_TOP, -0.05)  # 5 cm away: beyond the finger's target (2 cm behind the surface)
    settle(world, q=q)
    person = world.people()["finger"]
    assert not person.in_contact and person.pads == ()
    assert world.pressure_hpa().max() == 0.0 and world.touches() == []
    np.testing.assert_allclose(person.position, part.target, atol=1e-3)  # where its owner wanted it
    assert person.peak_force_n == pytest.approx(10.0, rel=0.1)


def test_two_fingers_on_two_pads_at_once() -> None:
    world = PhysicsWorld(DESC)
    world.press("left", UPPER_ARM_TOP, world.force_for_pressure(9.0))
    world.press("right", FOREARM_TOP, world.force_for_pressure(16.0))
    settle(world)
    pressure = world.pressure_hpa()
    assert (level(pressure[UPPER_ARM_TOP]), level(pressure[FOREARM_TOP])) == (3, 4)
    assert np.delete(pressure, [UPPER_ARM_TOP, FOREARM_TOP]).max() == 0.0
    people = world.people()
    assert (people["left"].pads, people["right"].pads) == ((UPPER_ARM_TOP,), (FOREARM_TOP,))
    assert {t.person for t in world.touches()} == {"left", "right"}
    for touch in world.touches():
        assert touch.force @ touch.normal > 0.0  # the arm pushes the person away from itself
    world.remove("left")
    settle(world, 0.2)
    pressure = world.pressure_hpa()
    assert pressure[UPPER_ARM_TOP] == 0.0 and level(pressure[FOREARM_TOP]) == 4


def _on_link(link: str, point: list[float], normal: list[float], force_n: float) -> BodyPart:
    """A finger touching ``point`` (on the surface of ``link``, its frame) along ``-normal`` with ``force_n``."""
    pose = MODEL.frame_pose(DESC.home, link)
    rotation, origin = pose[:3, :3], pose[:3, 3]
    surface, out = origin + rotation @ np.array(point), rotation @ np.array(normal)
    radius = KINDS["finger"].extent_m
    return BodyPart(name="finger", kind="finger", position=tuple(surface + out * radius),
                    target=tuple(surface + out * (radius - force_n / 500.0)))


def test_the_skin_covers_the_housings_between_the_pads_but_not_the_base() -> None:
    world = PhysicsWorld(DESC)
    # The top of the upper-arm tube, 18 cm from its pad's cushion: the housing, under the upper_arm_top pad.
    world.add(_on_link("upper_arm_link", [-0.12, 0.06, 0.176], [0.0, 1.0, 0.0], 10.0))
    settle(world)
    assert {(t.geom.startswith("shape"), t.pad) for t in world.touches()} == {(True, UPPER_ARM_TOP)}
    assert level(world.pressure_hpa()[UPPER_ARM_TOP]) == 3
    world.remove("finger")
    # The base has no pad: the person feels the arm, the skin does not.
    world.add(_on_link("base_link", [0.095, 0.0, 0.05], [1.0, 0.0, 0.0], 10.0))
    settle(world)
    assert world.people()["finger"].force_n == pytest.approx(10.0, rel=0.05)
    assert world.pressure_hpa().max() == 0.0 and {t.pad for t in world.touches()} == {None}


def test_a_palm_and_a_forearm_press_too_and_a_retargeted_finger_follows() -> None:
    world = PhysicsWorld(DESC)
    world.press("palm", UPPER_ARM_TOP, 15.0, kind="palm")
    world.press("forearm", FOREARM_TOP, 15.0, kind="forearm")
    settle(world)
    pressure = world.pressure_hpa()
    assert pressure[UPPER_ARM_TOP] == pytest.approx(pressure[FOREARM_TOP], rel=0.05)
    assert level(pressure[UPPER_ARM_TOP]) == 3
    point, normal = world.pad_surface(UPPER_ARM_TOP)
    world.retarget("palm", point + normal * 0.10)  # the hand lifts off
    settle(world, 0.5)
    assert world.pressure_hpa()[UPPER_ARM_TOP] == 0.0


def test_a_body_inside_the_arm_at_start_is_refused_before_anything_moves() -> None:
    world = PhysicsWorld(DESC)
    point, normal = world.pad_surface(UPPER_ARM_TOP)
    inside = BodyPart(name="finger", kind="finger", position=tuple(point - normal * 0.02), target=tuple(point))
    with pytest.raises(ConfigError, match="inside the arm"):
        world.add(inside)
    assert world.time_ns == 0 and world.people() == {}
    world.add(BodyPart(name="finger", kind="finger", position=tuple(point + normal * 0.05), target=tuple(point)))
    assert list(world.people()) == ["finger"]  # the slot was freed: the same name enters from outside


def test_a_push_beyond_a_plausible_human_push_is_refused() -> None:
    world = PhysicsWorld(DESC)
    with pytest.raises(ConfigError, match="plausible push"):
        world.press("finger", UPPER_ARM_TOP, 120.0)
    point, normal = world.pad_surface(UPPER_ARM_TOP)
    with pytest.raises(ConfigError, match="plausible push"):
        world.add(BodyPart(name="palm", kind="palm", position=tuple(point + normal * 0.1), target=tuple(point),
                           max_force_n=900.0))
    with pytest.raises(ConfigError, match="no free finger"):
        for i in range(5):
            world.press(f"finger{i}", i, 5.0)
    assert world.time_ns == 0


def test_the_force_figures_stand_beside_iso_ts_15066() -> None:
    hand = region_of("finger")
    assert (hand.force_n, hand.transient_force_n) == (140.0, 280.0)
    assert (hand.pressure_n_cm2, hand.transient_pressure_n_cm2) == (300.0, 600.0)
    assert (region_of("forearm").force_n, region_of("palm").pressure_n_cm2) == (160.0, 260.0)
    assert ISO_TS_15066["forehead"].transient_force_n == 0.0  # no transient contact permitted on the head
    assert KINDS["finger"].mass_kg == hand.mass_kg == 0.6
    world = PhysicsWorld(DESC)
    world.press("finger", UPPER_ARM_TOP, 20.0)
    settle(world)
    person = world.people()["finger"]
    assert person.area_cm2 > 0.0 and person.pressure_n_cm2 == pytest.approx(person.force_n / person.area_cm2)
    ratios = person.limits()
    assert ratios["force_quasi_static"] == pytest.approx(person.peak_force_n / 140.0)
    assert 0.0 < ratios["pressure_transient"] < ratios["pressure_quasi_static"] < 1.0


# ------------------------------------------------------------------------------ determinism and divergence


def _session(world: PhysicsWorld) -> tuple[bytes, ...]:
    world.press("a", UPPER_ARM_TOP, 12.0)
    q = DESC.home.copy()
    out = []
    for i in range(1500):
        if i == 300:
            world.press("b", FOREARM_TOP, 22.0)
        if i == 900:
            world.remove("a")
        if i == 1000:
            point, normal = world.pad_surface(FOREARM_TOP)
            world.retarget("b", point + normal * 0.05)
        q = DESC.home + 0.1 * np.sin(np.arange(1, 7) * i * 1e-3)
        world.step(q)
    arm = world.arm()
    out += [arm.q.tobytes(), arm.dq.tobytes(), arm.tau.tobytes(), world.data.qpos.tobytes(),
            world.data.qvel.tobytes(), world.pressure_hpa().tobytes()]
    out += [s.absolute_hpa.tobytes() for s in world.skin()]
    out += [repr(sorted((r.name, r.peak_force_n, r.energy_j) for r in world.people().values())).encode()]
    return tuple(out)


def test_the_same_inputs_give_bit_identical_outputs() -> None:
    first = _session(PhysicsWorld(DESC))
    second = _session(PhysicsWorld(DESC))
    assert first == second
    assert _session(PhysicsWorld(DESC, PhysicsSettings(seed=8))) != first  # the noise is the seed's


def test_a_diverging_simulation_stops_the_world_and_never_returns_a_jump() -> None:
    # Servos far too stiff for the step and nothing to damp them: the wrist explodes within a few steps.
    world = PhysicsWorld(DESC, PhysicsSettings(timestep_s=0.005, servo_error_rad=0.005, servo_damping_s=0.0,
                                               armature_kg_m2=0.0))
    last = world.arm()
    with pytest.raises(WorldUnstable, match="moves at .* rad/s"):
        for _ in range(100):
            world.step(DESC.home + 0.001)
            last = world.arm()
    assert world.arm() is last and np.abs(last.q - DESC.home).max() < 0.1
    with pytest.raises(WorldUnstable, match="stopped"):
        world.step(DESC.home)


def test_a_non_finite_force_is_caught_before_mujocos_reset_becomes_a_jump() -> None:
    world = PhysicsWorld(DESC)
    world.run(DESC.home + 0.1, 0.5)
    before = world.arm()
    world.data.qfrc_applied[2] = np.nan  # what a broken model or input would make
    with pytest.raises(WorldUnstable, match="bad accelerations"):
        world.step(DESC.home + 0.1)
    assert world.arm() is before and world.stopped is not None


def test_speed_of_the_world() -> None:
    """A benchmark figure, printed (not asserted): steps per second and the real-time factor at 1 ms."""
    world = PhysicsWorld(DESC)
    world.press("a", UPPER_ARM_TOP, 10.0)
    world.press("b", FOREARM_TOP, 20.0)
    steps = 3000
    start = time.perf_counter()
    for i in range(steps):
        world.step(DESC.home + 0.05 * np.sin(i * 1e-3))
    elapsed = time.perf_counter() - start
    print(f"\nphysics world: {steps / elapsed:.0f} steps/s, real-time factor {steps * 1e-3 / elapsed:.1f} at 1 ms "
          "(two fingers pressing, the arm moving)")
