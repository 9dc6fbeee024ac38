"""The bridge's Cartesian limits: every point's speed, the speed toward a contact, the momentum."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nwr.common.config import CartesianLimits, Profile, load_profile
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotModel, load_description
from nwr.services.bridge.cartesian import CartesianLimiter, Limits, row_norms

DESC = load_description()
MODEL = RobotModel(DESC)
HOME = np.asarray(DESC.home, dtype=float)


def limiter(speed: float = 0.25, withdrawal: float = 0.5, momentum: float = 10.0) -> CartesianLimiter:
    return CartesianLimiter(MODEL, Limits(speed, withdrawal, momentum))


def test_the_speed_points_are_every_pad_the_elbow_and_the_flange() -> None:
    assert MODEL.speed_points == (*(p.name for p in DESC.pads), "elbow", "flange")
    assert MODEL.link_masses.sum() == pytest.approx(29.104)


def test_point_velocities_are_the_derivative_of_the_points() -> None:
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = HOME + rng.uniform(-0.5, 0.5, 6)
        dq = rng.uniform(-1, 1, 6)
        h = 1e-7
        points = lambda x: np.vstack([MODEL.pad_points(x), MODEL.frame_pose(x, "forearm_link")[:3, 3],  # noqa: E731
                                      MODEL.tool_position(x)])
        numeric = (points(q + h * dq) - points(q - h * dq)) / (2 * h)
        assert MODEL.speed_jacobians(q) @ dq == pytest.approx(numeric, abs=1e-6)


def test_row_norms_are_numpy_s_norm_bit_for_bit() -> None:
    rng = np.random.default_rng(19)
    for _ in range(2000):
        x = rng.normal(size=(int(rng.integers(1, 14)), 3)) * 10.0 ** rng.uniform(-8, 3)
        assert row_norms(x).tobytes() == np.linalg.norm(x, axis=1).tobytes()
    x = MODEL.speed_jacobians(HOME) @ rng.uniform(-1, 1, 6)
    assert row_norms(x).tobytes() == np.linalg.norm(x, axis=1).tobytes()


def test_the_stop_from_given_speeds_is_the_stop_from_the_velocity() -> None:
    lim = CartesianLimiter(MODEL, Limits(0.25, 0.5, 10.0), a_max=np.full(6, 3.0), j_max=np.full(6, 30.0))
    rng = np.random.default_rng(5)
    for _ in range(200):
        q, dq = HOME + rng.uniform(-1, 1, 6), rng.uniform(-2, 2, 6)
        assert lim.stopping(q, dq, lim.speeds(q, dq)) == lim.stopping(q, dq)


def test_within_the_limits_nothing_is_scaled() -> None:
    assert limiter().scale(HOME, np.zeros(6)) is None
    assert limiter().scale(HOME, np.array([0.05, 0, 0, 0, 0, 0])) is None


@pytest.mark.parametrize("joint", range(4))  # the wrists 2 and 3 move no point that fast at 2 rad/s
def test_a_fast_joint_is_scaled_to_the_speed_limit_of_its_fastest_point(joint: int) -> None:
    lim = limiter(momentum=1e3)
    dq = np.zeros(6)
    dq[joint] = 2.0
    scaling = lim.scale(HOME, dq)
    assert scaling is not None and scaling.what == "speed"
    speeds = lim.speeds(HOME, dq)
    assert scaling.value == pytest.approx(speeds.max()) and scaling.point == MODEL.speed_points[int(speeds.argmax())]
    assert lim.speeds(HOME, scaling.factor * dq).max() == pytest.approx(0.25)
    assert f"above 0.250 m/s: scaled by {scaling.factor:.3f}" in scaling.describe()


def test_a_withdrawal_may_move_away_faster_but_not_toward_the_contact() -> None:
    lim = limiter(momentum=1e3)
    pad = DESC.pad("forearm_top").id
    jac = MODEL.speed_jacobians(HOME)[pad]
    normal = MODEL.pad_normal(HOME, pad)  # outward: toward the finger that touches the pad
    away = np.linalg.pinv(jac) @ (-0.4 * normal)  # the pad withdraws from the finger at 0.4 m/s
    # As a withdrawal: within its own limit (0.5 m/s), nothing scaled if no point approaches faster than 0.25.
    withdrawing = lim.scale(HOME, away, withdrawal=True, toward=normal)
    velocities = MODEL.speed_jacobians(HOME) @ away
    if float((velocities @ normal).max()) <= 0.25 and lim.speeds(HOME, away).max() <= 0.5:
        assert withdrawing is None
    # The same motion as a task motion is held to the collaborative speed.
    task = lim.scale(HOME, away)
    assert task is not None and task.limit == 0.25
    # Toward the contact: at most the collaborative speed, even in a withdrawal.
    toward = lim.scale(HOME, -away, withdrawal=True, toward=normal)
    assert toward is not None and toward.what == "speed toward the contact" and toward.limit == 0.25
    velocities = MODEL.speed_jacobians(HOME) @ (toward.factor * -away)
    assert float((velocities @ normal).max()) == pytest.approx(0.25)


def test_momentum_is_bounded_from_the_link_masses() -> None:
    lim = limiter(speed=1.0, withdrawal=1.0, momentum=2.0)
    dq = np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0])
    scaling = lim.scale(HOME, dq)
    assert scaling is not None and scaling.what == "momentum" and scaling.point == "arm"
    assert lim.momentum(HOME, scaling.factor * dq) == pytest.approx(2.0)
    # The momentum of a joint that moves nothing but the last link is small.
    assert lim.momentum(HOME, np.array([0, 0, 0, 0, 0, 1.0])) < 0.1


@pytest.mark.parametrize(("field", "value"), [("speed_m_s", 1.5), ("withdrawal_speed_m_s", 2.0),
                                              ("momentum_kg_m_s", 100.0)])
def test_limits_beyond_the_robot_are_configuration_errors_naming_the_field(field: str, value: float) -> None:
    section = CartesianLimits(**{field: value})
    with pytest.raises(ConfigError, match=rf"bridge.limits.{field} = {value}"):
        Limits.of(section, MODEL, "bridge.limits")


@pytest.mark.parametrize("value", [math.nan, -1.0, 0.0, math.inf])
def test_non_finite_or_non_positive_limits_are_refused(tmp_path, value: float) -> None:
    path = tmp_path / "p.toml"
    path.write_text(f"[bridge.limits]\nspeed_m_s = {value!r}\n".replace("nan", "nan").replace("inf", "inf"))
    with pytest.raises(ConfigError):
        Limits.of(load_profile(str(path)).bridge.limits, MODEL, "bridge.limits")


def test_a_reduced_limit_above_the_normal_one_is_a_configuration_error(tmp_path) -> None:
    path = tmp_path / "p.toml"
    path.write_text("[bridge.reduced]\nspeed_m_s = 0.3\n")
    with pytest.raises(ConfigError, match=r"bridge.reduced.speed_m_s = 0.3 is above bridge.limits.speed_m_s"):
        load_profile(str(path))
    assert Profile().bridge.reduced.speed_m_s < Profile().bridge.limits.speed_m_s


# -- power, stopping time and distance ------------------------------------------------------

def test_the_motion_power_is_the_rate_of_change_of_the_kinetic_energy() -> None:
    rng = np.random.default_rng(7)
    for _ in range(5):
        q, dq, ddq = HOME + rng.uniform(-0.5, 0.5, 6), rng.uniform(-1, 1, 6), rng.uniform(-5, 5, 6)
        h = 1e-6
        ahead, behind = MODEL.kinetic_energy(q + h * dq, dq + h * ddq), MODEL.kinetic_energy(q - h * dq, dq - h * ddq)
        numeric = (ahead - behind) / (2 * h)
        assert MODEL.motion_power(q, dq, ddq) == pytest.approx(numeric, rel=1e-5, abs=1e-6)
    assert MODEL.motion_power(HOME, np.zeros(6), np.zeros(6)) == pytest.approx(0.0, abs=1e-12)  # holding: no power


def test_the_power_limit_eases_the_acceleration_never_reverses_it() -> None:
    lim = limiter(speed=1.0, withdrawal=1.0, momentum=1e3)
    lim.limits = Limits(1.0, 1.0, 1e3, power_w=5.0)
    dq0 = np.array([0.2, -0.1, 0.1, 0.0, 0.0, 0.0])
    dq1 = dq0 + np.array([8.0, -8.0, 10.0, 0, 0, 0]) * 0.002  # a cycle at the acceleration limit
    assert MODEL.motion_power(HOME, dq1, (dq1 - dq0) / 0.002) > 5.0
    scaling = lim.power_scale(HOME, dq0, dq1, 0.002)
    assert scaling is not None and scaling.what == "power" and 0.0 < scaling.factor < 1.0
    eased = dq0 + scaling.factor * (dq1 - dq0)
    assert MODEL.motion_power(HOME, eased, (eased - dq0) / 0.002) <= 5.0
    assert "acceleration eased" in scaling.describe()
    # Braking puts no power into the motion: never limited.
    assert lim.power_scale(HOME, dq1, dq0, 0.002) is None


def test_the_predicted_stop_is_the_bridge_s_own_stop() -> None:
    """The stop's time and distance the limiter predicts against the tracker's ruckig stop, run cycle by cycle."""
    from nwr.services.bridge.tracking import Tracker
    from nwr.services.bridge.wiring import envelope_for

    env, _, _ = envelope_for(Profile())
    lim = CartesianLimiter(MODEL, Limits(1.0, 1.0, 1e3), a_max=env.a_max, j_max=env.j_max)
    rng = np.random.default_rng(11)
    for _ in range(8):
        dq = rng.uniform(-1.0, 1.0, 6) * rng.choice([0.1, 0.5, 1.0])
        tracker = Tracker(env, HOME.copy(), 0)
        tracker.dq = dq.copy()
        tracker.ddq = np.zeros(6)
        points0 = np.vstack([MODEL.pad_points(HOME), MODEL.frame_pose(HOME, "forearm_link")[:3, 3],
                             MODEL.tool_position(HOME)])
        tracker.begin_stop(0)
        assert tracker.stop is not None
        t, distance, _ = lim.stopping(HOME, dq)
        assert tracker.stop.duration_s == pytest.approx(t, abs=0.004)
        q_end = HOME + tracker.stop.distance
        points1 = np.vstack([MODEL.pad_points(q_end), MODEL.frame_pose(q_end, "forearm_link")[:3, 3],
                             MODEL.tool_position(q_end)])
        moved = float(np.linalg.norm(points1 - points0, axis=1).max())
        assert moved == pytest.approx(distance, rel=0.1, abs=0.002)


def test_a_velocity_whose_stop_is_too_long_or_too_far_is_scaled_into_both() -> None:
    from nwr.services.bridge.wiring import envelope_for

    env, _, _ = envelope_for(Profile())
    lim = CartesianLimiter(MODEL, Limits(1.0, 1.0, 1e3, stopping_time_s=0.1, stopping_distance_m=0.02),
                           a_max=env.a_max, j_max=env.j_max)
    for dq in (np.array([1.0, 0, 0, 0, 0, 0]), np.array([0, 0, 0, 0, 2.0, 0]), np.array([0.3, -0.4, 0.5, 0, 0, 0])):
        scaling = lim.scale(HOME, dq)
        assert scaling is not None and scaling.what in ("stopping time", "stopping distance"), scaling
        t, distance, _ = lim.stopping(HOME, scaling.factor * dq)
        assert t <= 0.1 + 1e-9 and distance <= 0.02 + 1e-9
        assert scaling.factor > 0.9 * max(f for f in np.linspace(0, 1, 200)
                                          if lim.stopping(HOME, f * dq)[0] <= 0.1 and
                                          lim.stopping(HOME, f * dq)[1] <= 0.02)  # not needlessly slow
    assert lim.scale(HOME, np.array([0.05, 0, 0, 0, 0, 0])) is None


def test_a_tracker_under_a_tight_power_limit_never_exceeds_it() -> None:
    from nwr.services.bridge.tracking import Tracker
    from nwr.services.bridge.wiring import envelope_for

    env, _, _ = envelope_for(Profile())
    lim = CartesianLimiter(MODEL, Limits(1.0, 1.0, 1e3, power_w=3.0), a_max=env.a_max, j_max=env.j_max)
    tracker = Tracker(env, HOME.copy(), 0, limiter=lim)
    tracker.mode = "velocity"
    tracker.target = np.array([0.6, -0.6, 0.6, 0.0, 0.0, 0.0])
    worst = 0.0
    for k in range(400):
        dq0 = tracker.dq.copy()
        q0 = tracker.q.copy()
        tracker.track(0.002, k * 2_000_000, "test")
        worst = max(worst, MODEL.motion_power(q0, tracker.dq, (tracker.dq - dq0) / 0.002))
    assert worst <= 3.0 + 1e-6 and tracker.limited > 0
    assert float(np.abs(tracker.dq).max()) > 0.1  # eased, not stopped


@pytest.mark.parametrize(("field", "value"), [("power_w", math.inf), ("stopping_time_s", 2.0),
                                              ("stopping_distance_m", -0.1)])
def test_power_and_stopping_limits_out_of_range_name_the_field(tmp_path, field: str, value: float) -> None:
    path = tmp_path / "p.toml"
    path.write_text(f"[bridge.limits]\n{field} = {value!r}\n")
    with pytest.raises(ConfigError, match=field):
        load_profile(str(path))


def test_a_reduced_power_above_the_normal_one_is_a_configuration_error(tmp_path) -> None:
    path = tmp_path / "p.toml"
    path.write_text("[bridge.reduced]\npower_w = 60.0\n")
    with pytest.raises(ConfigError, match=r"bridge.reduced.power_w = 60.0 is above bridge.limits.power_w"):
        load_profile(str(path))
