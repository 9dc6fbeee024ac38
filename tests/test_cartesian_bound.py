"""The bounds that let the bridge's Cartesian limits skip their exact computation: conservative, and invisible.

:class:`~nwr.common.robot.ChainBounds` bounds every point's speed, the
change of its velocity with the configuration, the momentum and the power
without kinematics; :class:`~nwr.services.bridge.cartesian.CartesianLimiter`
returns at once where they prove every limit holds. Checked here: each bound
is at least the exact value on thousands of random configurations and
velocities (the UR10e, and a variant with a prismatic joint, a revolute
joint off the frame's axes and a base frame that is not the URDF root), and
the limiter's answers, the tracker's cycles included, are those of the exact
computation bit for bit, near every limit.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import load_profile
from nwr.common.robot import DEFAULT_DESCRIPTION, RobotModel, load_description
from nwr.services.bridge.cartesian import CartesianLimiter, Limits, row_norms
from nwr.services.tools.bench import tracking as bench

UR10E = RobotModel(load_description())
A_MAX = np.array(UR10E.desc.a_max) * 0.9
J_MAX = np.array(UR10E.desc.j_max) * 0.9


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert text.count(old) == 1, f"{old!r} must occur exactly once in {path}"
    path.write_text(text.replace(old, new))


@pytest.fixture(scope="module")
def variant(tmp_path_factory: pytest.TempPathFactory) -> RobotModel:
    """The UR10e with a prismatic elbow (travel -0.2..0.3 m along a tilted axis), wrist 2 turning about a
    tilted axis and the base frame turned by pi from the URDF root."""
    folder = tmp_path_factory.mktemp("variant") / "ur10e"
    shutil.copytree(DEFAULT_DESCRIPTION.parent, folder)
    urdf = folder / "ur10e.urdf"
    text = urdf.read_text()
    start = text.index('<joint name="elbow_joint" type="revolute">')
    end = text.index("</joint>", start)
    elbow = text[start:end].replace('type="revolute"', 'type="prismatic"').replace('<axis xyz="0 0 1"/>',
                                                                                  '<axis xyz="0.6 0.8 0"/>')
    elbow = elbow.replace('lower="-3.141592653589793" upper="3.141592653589793"', 'lower="-0.2" upper="0.3"')
    text = text[:start] + elbow + text[end:]
    start = text.index('<joint name="wrist_2_joint" type="revolute">')
    end = text.index("</joint>", start)
    text = text[:start] + text[start:end].replace('<axis xyz="0 0 1"/>', '<axis xyz="0.6 0 0.8"/>') + text[end:]
    urdf.write_text(text)
    edit(folder / "robot.toml", "home = [0.0, -1.15, 1.85, -2.27, -1.57, 0.0]",
         "home = [0.0, -1.15, 0.1, -2.27, -1.57, 0.0]")
    edit(folder / "robot.toml", 'base_frame = "base_link"', 'base_frame = "base"')
    model = RobotModel(load_description(folder / "robot.toml"))
    kinds = [model.model.joints[j].shortname() for j in range(1, model.model.njoints)]
    assert kinds[2] == "JointModelPrismaticUnaligned" and kinds[4] == "JointModelRevoluteUnaligned"
    return model


@pytest.fixture(params=["ur10e", "variant"])
def model(request: pytest.FixtureRequest, variant: RobotModel) -> RobotModel:
    return UR10E if request.param == "ur10e" else variant


def configurations(model: RobotModel, rng: np.random.Generator, count: int) -> list[np.ndarray]:
    """Random configurations within the joint limits, with their velocities of every scale."""
    desc = model.desc
    return [rng.uniform(desc.q_min, desc.q_max) for _ in range(count)]


def velocity(rng: np.random.Generator, n: int) -> np.ndarray:
    """A random joint velocity: some joints still, magnitudes from 1e-4 to 3 rad/s."""
    dq = rng.normal(size=n) * 10.0 ** rng.uniform(-4, 0.5)
    return np.where(rng.random(n) < 0.2, 0.0, dq)


# --------------------------------------------------------------------------- the bounds are bounds


def test_the_reach_bounds_every_point_s_speed_and_the_momentum(model: RobotModel) -> None:
    bounds = model.bounds
    assert bounds is not None
    rng = np.random.default_rng(2024)
    worst_speed = worst_momentum = 0.0
    for q in configurations(model, rng, 3000):
        dq = velocity(rng, model.nq)
        speeds = row_norms(model.speed_jacobians(q) @ dq)
        reach = bounds.speed_reach @ np.abs(dq)
        assert (speeds <= reach * (1 + 1e-12)).all()
        centres = row_norms(model.com_jacobians(q) @ dq)
        assert (centres <= bounds.com_reach @ np.abs(dq) * (1 + 1e-12)).all()
        momentum = float(model.link_masses @ centres)
        momentum_bound = float(model.link_masses @ bounds.com_reach @ np.abs(dq))
        assert momentum <= momentum_bound * (1 + 1e-12)
        if reach.max() > 0:
            worst_speed = max(worst_speed, float((speeds / np.maximum(reach, 1e-300)).max()))
            worst_momentum = max(worst_momentum, momentum / momentum_bound)
    assert 0.6 < worst_speed <= 1.0 + 1e-12 and 0.5 < worst_momentum <= 1.0 + 1e-12  # tight at times


def test_the_bend_bounds_how_much_each_point_s_velocity_changes_with_the_configuration(model: RobotModel) -> None:
    bounds = model.bounds
    assert bounds is not None
    rng = np.random.default_rng(7)
    desc = model.desc
    for q0 in configurations(model, rng, 2000):
        step = rng.normal(size=model.nq) * 10.0 ** rng.uniform(-5, 0)
        q = np.clip(q0 + step, desc.q_min, desc.q_max)  # both within the limits: the prismatic travel counted
        dq = velocity(rng, model.nq)
        change = row_norms(model.speed_jacobians(q) @ dq - model.speed_jacobians(q0) @ dq)
        bend = np.einsum("i,pik,k->p", np.abs(dq), bounds.speed_bend, np.abs(q - q0))
        assert (change <= bend * (1 + 1e-9) + 1e-15).all()
        change = row_norms(model.com_jacobians(q) @ dq - model.com_jacobians(q0) @ dq)
        bend = np.einsum("i,lik,k->l", np.abs(dq), bounds.com_bend, np.abs(q - q0))
        assert (change <= bend * (1 + 1e-9) + 1e-15).all()


def test_the_power_bound_bounds_the_motion_power(model: RobotModel) -> None:
    bounds = model.bounds
    assert bounds is not None
    rng = np.random.default_rng(11)
    for q in configurations(model, rng, 3000):
        dq, ddq = velocity(rng, model.nq), velocity(rng, model.nq) * 10.0 ** rng.uniform(0, 2)
        power = model.motion_power(q, dq, ddq)
        a, b = np.abs(dq), np.abs(ddq)
        bound = float(a @ bounds.power_rate @ b) + float(bounds.power_cubic @ a @ a @ a)
        assert abs(power) <= bound * (1 + 1e-9) + 1e-12


def test_the_limiter_s_bounds_hold_from_any_reference(model: RobotModel) -> None:
    """From an exact computation at q0, dq0: the fastest point and the momentum at q, dq, far or near."""
    lim = CartesianLimiter(model, Limits(0.25, 0.5, 10.0), a_max=A_MAX, j_max=J_MAX)
    rng = np.random.default_rng(13)
    desc = model.desc
    for q0 in configurations(model, rng, 2000):
        dq0 = velocity(rng, model.nq)
        assert lim.top_speed(q0, dq0) == float(lim.speeds(q0, dq0).max())
        near = rng.random() < 0.7
        q = np.clip(q0 + rng.normal(size=model.nq) * (1e-3 if near else 1.0), desc.q_min, desc.q_max)
        dq = dq0 + rng.normal(size=model.nq) * 1e-2 if near else velocity(rng, model.nq)
        bound = lim._bound(q, dq)
        assert bound is not None
        assert float(lim.speeds(q, dq).max()) <= bound[0]
        assert lim.momentum(q, dq) <= bound[1]


def test_outside_the_travel_counted_nothing_is_skipped(variant: RobotModel) -> None:
    lim = CartesianLimiter(variant, Limits(0.25, 0.5, 10.0), a_max=A_MAX, j_max=J_MAX)
    q = np.array(variant.desc.home)
    lim.top_speed(q, np.zeros(6))
    assert lim.within_speed(q, np.zeros(6), 0.1)
    beyond = q.copy()
    beyond[2] = 0.5  # the prismatic elbow past its 0.3 m
    assert not lim.within_speed(beyond, np.zeros(6), 0.1)
    assert not lim._power_within(beyond, np.zeros(6), np.zeros(6), 50.0)


# --------------------------------------------------------------------------- the same answers


def near_limits(lim: CartesianLimiter, q: np.ndarray, dq: np.ndarray, toward: np.ndarray | None,
                rng: np.random.Generator) -> Limits:
    """Limits that one of the exact values (the fastest point, toward the contact, the momentum, the stop's
    time or distance, the power) meets, just within or just beyond; the others far or near too."""
    speeds = lim.speeds(q, dq)
    top = float(speeds.max())
    approach = float((lim.model.speed_jacobians(q) @ dq @ toward).max()) if toward is not None else 0.0
    momentum = lim.momentum(q, dq)
    t, distance, _ = lim.stopping(q, dq)
    power = abs(lim.model.motion_power(q, dq, dq * 5.0))

    def around(x: float) -> float:
        eps = rng.choice([-1e-6, -1e-12, 0.0, 1e-15, 1e-12, 1e-10, 1e-9, 2e-9, 1e-8, 1e-6, 1e-3, 0.5, 3.0])
        return max(x * (1.0 + eps), 1e-12)

    speed = around(max(top, approach))
    return Limits(speed, around(top) if rng.random() < 0.5 else speed * 2.0, around(momentum), around(power),
                  around(t), around(distance))


def test_scale_with_the_bounds_is_scale_without_them(model: RobotModel) -> None:
    """Random walks of q and dq as the tracker makes them (the bounds then fire), under limits near the exact
    values: every answer is the exact computation's, and the bounds answered a share of them."""
    rng = np.random.default_rng(17)
    desc = model.desc
    fired = calls = 0
    for _ in range(60):
        q = rng.uniform(desc.q_min, desc.q_max)
        dq = velocity(rng, model.nq)
        bounded = CartesianLimiter(model, Limits(0.25, 0.5, 10.0), a_max=A_MAX, j_max=J_MAX)
        exact = CartesianLimiter(model, Limits(0.25, 0.5, 10.0), a_max=A_MAX, j_max=J_MAX, bounded=False)
        for _ in range(40):
            q = np.clip(q + dq * 0.002, desc.q_min, desc.q_max)
            dq = dq * (1.0 + rng.normal() * 0.01) + rng.normal(size=model.nq) * 1e-3
            toward = rng.normal(size=3)
            toward = toward / np.linalg.norm(toward) if rng.random() < 0.4 else None
            withdrawal = bool(rng.random() < 0.4)
            limits = near_limits(exact, q, dq, toward, rng) if rng.random() < 0.8 else Limits(0.25, 0.5, 10.0)
            bounded.limits = exact.limits = limits
            cap = float(rng.uniform(0.01, 0.3)) if rng.random() < 0.2 else None
            for v in (dq, dq * 1.02, dq * float(rng.uniform(0.0, 1.0))):
                fired += bounded._within(q, v, *bounded._limit(withdrawal, cap)[:1], toward)
                calls += 1
                assert bounded.scale(q, v, withdrawal=withdrawal, toward=toward, speed_cap=cap) == \
                    exact.scale(q, v, withdrawal=withdrawal, toward=toward, speed_cap=cap)
            h = 0.002
            dq1 = dq + rng.normal(size=model.nq) * 10.0 ** rng.uniform(-4, -1)
            assert bounded.power_scale(q, dq, dq1, h) == exact.power_scale(q, dq, dq1, h)
    assert 0.05 < fired / calls < 0.95  # both paths are exercised


def test_near_the_margin_the_bounds_decide_as_the_exact_computation(model: RobotModel) -> None:
    """At the reference itself the speed bound is the exact speed and the margin: limits between the two are
    computed, limits past the margin skipped; both return None."""
    rng = np.random.default_rng(23)
    desc = model.desc
    for _ in range(300):
        q, dq = rng.uniform(desc.q_min, desc.q_max), velocity(rng, model.nq)
        exact = CartesianLimiter(model, Limits(1.0, 1.0, 1e3), bounded=False)
        top = float(exact.speeds(q, dq).max())
        for eps in (-1e-12, 0.0, 1e-12, 1e-9, 1e-6):
            limits = Limits(top * (1 + eps), top * (1 + eps), 1e3)
            bounded = CartesianLimiter(model, limits)
            exact.limits = limits
            bounded.top_speed(q, dq)
            assert bounded.scale(q, dq) == exact.scale(q, dq)
            if eps >= 1e-6 and top > 0:
                assert bounded._within(q, dq, limits.speed_m_s, None)


def test_the_tracker_with_the_bounds_is_the_tracker_without_them() -> None:
    """The bridge in lockstep, with and without the bounds, on a position stream that speeds up past the speed
    limit and a withdrawal: every cycle's state, the stream's peak, the scalings reported, bit for bit."""
    profile = load_profile()
    runs = [bench.BridgeRun(profile, None), bench.BridgeRun(profile, None)]
    old = runs[1].tracker.limiter
    runs[1].tracker.limiter = CartesianLimiter(old.model, old.limits, a_max=old.a_max, j_max=old.j_max,
                                               bounded=False)
    q0 = runs[0].tracker.q.copy()
    direction = np.array([1.0, -0.4, 0.6, 0.3, 0.2, 0.1])
    fired = 0
    for k in range(1500):
        t = k * 0.002
        amplitude = 0.02 + 0.3 * t  # the stream's speed grows past the collaborative limit
        if k < 1200:
            q = q0 + direction * amplitude * np.sin(2.0 * t)
            make = lambda run, q=q: run.command(m.PositionCommand, q=q.tolist(), phase="TASK", reflex_seq=0)  # noqa: E731
        else:
            make = lambda run: run.command(m.VelocityCommand, dq=(-0.3 * direction).tolist(),  # noqa: E731
                                           phase="REFLEX", reflex_seq=1)
        for run in runs:
            run.cycle(make(run))
        a, b = runs[0].tracker, runs[1].tracker
        assert a.q.tobytes() == b.q.tobytes() and a.dq.tobytes() == b.dq.tobytes()
        assert a.ddq.tobytes() == b.ddq.tobytes()
        assert (a.stream_peak, a.catching_up, a.limited, a.withdrawal) == \
            (b.stream_peak, b.catching_up, b.limited, b.withdrawal)
        fired += a.limiter._within(a.q, a.dq, a.limiter.limits.speed_m_s, None)
    assert runs[0].tracker.limited > 0 and 0 < fired < 1500
