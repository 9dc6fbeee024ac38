"""Baseline filter and simulated skin."""

import numpy as np
import pytest

from nwr.common.config import GatewaySection
from nwr.common.errors import ConfigError
from nwr.common.launch import Touch, TouchScript
from nwr.common.robot import Pad
from nwr.services.gateway.core import BaselineFilter, Gateway, SimSkin, SimSkinSettings, touch_profile, with_sim

RATE = 25.0


def run(filter_, signal, t0=0.0):
    """Feed a (T, n) array of absolute pressures; returns the (T, n) changes."""
    out = []
    for i, row in enumerate(signal):
        change, _ = filter_.update(t0 + i / RATE, np.asarray(row, dtype=float))
        out.append(change.copy())
    return np.array(out)


def test_noise_only_stays_near_zero():
    rng = np.random.default_rng(1)
    f = BaselineFilter(GatewaySection(), 2)
    change = run(f, 1000.0 + rng.normal(0, 0.08, (1000, 2)))
    assert np.abs(change[10:]).max() < 0.5
    assert not f.contact.any()


def test_slow_drift_is_tracked():
    f = BaselineFilter(GatewaySection(), 1)
    t = np.arange(0, 120, 1 / RATE)
    drift = 1000.0 + 0.01 * t  # 0.01 hPa/s, below max_drift_hpa_s
    change = run(f, drift[:, None])
    assert abs(change[-1, 0]) < 0.1
    assert f.baseline[0] == pytest.approx(drift[-1], abs=0.1)


def test_sustained_press_is_not_followed_and_release_returns_to_zero():
    f = BaselineFilter(GatewaySection(), 1)
    rest = [[1000.0]] * 50
    press = [[1010.0]] * int(30 * RATE)  # 30 s at +10 hPa
    change = run(f, rest + press + rest)
    during = change[50:50 + len(press), 0]
    assert during.min() == pytest.approx(10.0)
    assert during.max() == pytest.approx(10.0)  # frozen baseline: no drift away
    assert change[-1, 0] == pytest.approx(0.0, abs=1e-9)
    assert not f.contact[0]


def test_slow_ramp_is_not_absorbed_by_the_baseline():
    f = BaselineFilter(GatewaySection(), 1)
    ramp = 1000.0 + np.clip(np.arange(0, 10, 1 / RATE) - 1.0, 0, None) * 2.0  # +2 hPa/s from t = 1 s
    change = run(f, ramp[:, None])
    # The baseline moves at most max_drift_hpa_s while below the contact threshold.
    assert change[-1, 0] > ramp[-1] - 1000.0 - 0.06


def test_drift_during_press_is_bounded():
    cfg = GatewaySection()
    f = BaselineFilter(cfg, 1)
    rest = [[1000.0]] * 50
    press = [[1008.0 + 0.01 * i / RATE] for i in range(int(20 * RATE))]
    change = run(f, rest + press)
    assert f.baseline[0] == pytest.approx(1000.0)
    assert change[-1, 0] == pytest.approx(8.2, abs=0.01)


def test_too_long_contact_reacquires():
    cfg = GatewaySection(max_contact_s=2.0)
    f = BaselineFilter(cfg, 1)
    events = []
    for i in range(200):
        _, ev = f.update(i / RATE, np.array([1000.0 if i < 10 else 1005.0]))
        events += ev.reacquired
    assert events == [0]
    assert f.baseline[0] == pytest.approx(1005.0, abs=0.1)


def test_non_finite_reading_is_invalid_and_leaves_baseline():
    g = Gateway(GatewaySection(), 2)
    g.process(0.0, 0, np.array([1000.0, 1000.0]))
    msg, events = g.process(0.04, 1, np.array([np.nan, 1000.0]))
    assert events.non_finite == [0]
    assert msg.valid == [False, True]
    assert msg.change_hpa[0] == 0.0 and not msg.contact[0]
    assert g.filter.baseline[0] == pytest.approx(1000.0)


def test_touch_profiles():
    step = Touch(pad="a", start_s=1.0, duration_s=0.5, peak_hpa=9.0)
    assert [touch_profile(step, t) for t in (0.99, 1.0, 1.49, 1.5)] == [0.0, 9.0, 9.0, 0.0]
    ramp = Touch(pad="a", start_s=1.0, duration_s=0.5, peak_hpa=10.0, shape="ramp", ramp_s=0.5)
    assert touch_profile(ramp, 1.25) == pytest.approx(5.0)
    assert touch_profile(ramp, 1.75) == pytest.approx(10.0)
    assert touch_profile(ramp, 2.25) == pytest.approx(5.0)
    assert touch_profile(ramp, 2.5) == 0.0


def pads():
    return tuple(Pad(i, f"p{i}", "wrist", "l", np.zeros(3), np.array([0, 0, 1.0])) for i in range(3))


def test_sim_skin_with_gateway_recovers_the_script():
    script = TouchScript(duration_s=10.0, touch=[Touch(pad="p1", start_s=4.0, duration_s=1.0, peak_hpa=9.0)])
    sim = SimSkin(SimSkinSettings(), pads(), script)
    gw = Gateway(GatewaySection(), 3)
    changes = []
    for i in range(250):
        t = i / RATE
        msg, _ = gw.process(t, i, sim.sample(t))
        changes.append(msg.change_hpa)
    c = np.array(changes)
    inside = c[int(4.1 * RATE):int(4.9 * RATE), 1]
    assert np.all(np.abs(inside - 9.0) < 0.5)
    assert np.abs(c[int(6 * RATE):, :]).max() < 0.6
    assert np.abs(c[:, [0, 2]]).max() < 0.6


def test_sim_skin_rejects_unknown_pad():
    script = TouchScript(duration_s=10.0, touch=[Touch(pad="nope", start_s=1.0, duration_s=1.0, peak_hpa=9.0)])
    with pytest.raises(ConfigError, match="nope"):
        SimSkin(SimSkinSettings(), pads(), script)


def test_target_follower_presses_the_target_periodically():
    from nwr.services.gateway.core import TargetFollower

    f = TargetFollower(2.0, seed=3)
    assert f.poll(1.0, 4) is None
    pad, touch = f.poll(2.0, 4)
    assert pad == 4 and touch.start_s == 2.0 and touch.peak_hpa == TargetFollower.PEAKS_HPA[0]
    assert f.poll(2.5, 4) is None
    assert f.poll(4.1, -1) is None  # no target published yet
    sim = SimSkin(SimSkinSettings(noise_hpa=0.0, drift_walk_hpa=0.0, drift_sine_hpa=0.0), pads(), None)
    sim.add_touch(1, touch)
    assert sim.touch_pressure(2.0 + touch.ramp_s + 0.1)[1] == pytest.approx(touch.peak_hpa)


@pytest.mark.parametrize("closed_loop", [False, True])
def test_the_pads_pose_is_needed_only_when_a_touch_uses_it(closed_loop):
    from nwr.services.gateway.core import TouchSet

    touches = TouchSet(2, 0.02, closed_loop)
    touches.add(1, Touch(pad="b", start_s=1.0, duration_s=0.5, peak_hpa=9.0, shape="ramp", ramp_s=0.25))
    assert not touches.needs_pose(0.9)
    assert touches.needs_pose(1.0)  # it begins: it meets its pad where the pad is
    points = normals = np.zeros((2, 3))
    touches.start(1.0, points, normals)
    assert touches.needs_pose(1.5) == closed_loop  # under way: only the closed loop follows the pad
    assert not touches.needs_pose(2.01)  # over


def _reference_update(cfg, state, t, absolute):
    """The baseline filter as numpy array expressions (its form before it went pad by pad on floats)."""
    baseline, contact, since, last_t = state
    dt = 0.0 if last_t is None else max(0.0, t - last_t)
    finite = np.isfinite(absolute)
    fresh = finite & np.isnan(baseline)
    baseline[fresh] = absolute[fresh]
    change = absolute - baseline
    starting = finite & ~contact & (change > cfg.contact_hpa)
    ending = finite & contact & (change < cfg.release_hpa)
    since[starting] = t
    contact = (contact | starting) & ~ending
    too_long = contact & (t - since > cfg.max_contact_s)
    reacquired = [int(i) for i in np.flatnonzero(too_long)]
    if too_long.any():
        baseline[too_long] = absolute[too_long]
        contact[too_long] = False
        change[too_long] = 0.0
    track = finite & ~contact
    if dt > 0 and track.any():
        alpha = 1.0 - np.exp(-dt / cfg.baseline_tau_s)
        baseline[track] += np.clip(alpha * change[track], -cfg.max_drift_hpa_s * dt, cfg.max_drift_hpa_s * dt)
    return (baseline, contact, since, t), change, reacquired, [int(i) for i in np.flatnonzero(~finite)]


@pytest.mark.parametrize("max_contact_s,max_drift", [(10.0, 0.5), (0.05, 0.5), (10.0, 0.0)])
def test_filter_on_floats_matches_the_array_expressions_bit_for_bit(max_contact_s, max_drift):
    """Touches, reacquisitions, NaN and infinite readings, repeated and backward stamps."""
    cfg = GatewaySection(max_contact_s=max_contact_s, max_drift_hpa_s=max_drift)
    n = 10
    rng = np.random.default_rng(7)
    gateway = Gateway(cfg, n)
    state = (np.full(n, np.nan), np.zeros(n, dtype=bool), np.zeros(n), None)
    base = 1000 + rng.normal(0, 5, n)
    t = 0.0
    reacquisitions = 0
    for k in range(4000):
        t += rng.choice([0.0, 0.04, -0.001]) if k % 97 == 0 else 0.001
        absolute = base + rng.normal(0, 0.3, n) + (rng.random(n) < 0.05) * rng.uniform(0, 30, n) * (k % 400 < 200)
        absolute[(k // 300) % n] += 15.0 * ((k // 300) % 2 == 0)  # sustained presses (reacquired at 0.05 s)
        if k < 3:
            absolute[:] = np.nan
        if k % 53 == 0:
            absolute[rng.integers(n)] = np.nan
        if k % 301 == 0:
            absolute[rng.integers(n)] = rng.choice([np.inf, -np.inf])
        msg, events = gateway.process(t, k, absolute.copy())
        state, change, reacquired, non_finite = _reference_update(cfg, state, t, absolute.copy())
        baseline, contact = state[0], state[1]
        valid = np.isfinite(change)
        assert msg.change_hpa == np.where(valid, change, 0.0).tolist()
        assert msg.baseline_hpa == np.where(np.isfinite(baseline), baseline, 0.0).tolist()
        assert msg.absolute_hpa == np.where(valid, absolute, 0.0).tolist()
        assert msg.contact == (contact & valid).tolist() and msg.valid == valid.tolist()
        assert (events.reacquired, events.non_finite) == (reacquired, non_finite)
        assert all(type(x) is float for x in (*msg.absolute_hpa, *msg.baseline_hpa, *msg.change_hpa))
        np.testing.assert_array_equal(gateway.filter.baseline, baseline)
        reacquisitions += len(reacquired)
    assert reacquisitions > 0 if max_contact_s < 1.0 else reacquisitions == 0


def test_a_late_loop_takes_the_periods_it_missed_each_of_its_own_time_and_replays_them():
    """The live loop, late, ticks once per missed period with that period's deadline: the samples are those an
    on-time loop takes (the touch's pressure at each deadline), stamped when taken; the journal replays them."""
    from nwr.common.clock import ManualClock
    from nwr.common.config import Profile
    from nwr.common.journal import Playback, Recording
    from nwr.services.gateway.wiring import GatewayWiring

    profile = Profile()
    profile.gateway.rate_hz = 1000.0
    profile.gateway = with_sim(profile.gateway, noise_hpa=0.0)
    script = TouchScript(duration_s=1.0, touch=[Touch(pad="forearm_top", start_s=0.05, duration_s=0.2, peak_hpa=12.0,
                                                      shape="ramp", ramp_s=0.05)])
    period = 1_000_000

    def run(stall: range) -> tuple[list, Recording]:
        clock = ManualClock(10**9)
        journal = Recording(clock)
        outs: list = []
        wiring = GatewayWiring(profile, journal=journal, out=lambda k, msg: outs.append(msg) if k == "skin/pressure"
                               else None, diag=lambda *a: None, script=script)
        origin = wiring.origin()
        for k in range(1, 150):
            due = origin + k * period
            if k in stall:  # the loop sleeps through these; they are taken at the stall's end, in order
                continue
            if k == stall.stop:
                for missed in (*stall, k):
                    clock.t_ns = due + 20_000  # each taken a little later than the one before
                    wiring.tick(origin + missed * period)
                    due += 1
                continue
            clock.t_ns = due + 20_000
            wiring.tick(due)
        return outs, journal

    on_time, _ = run(range(0))
    late, journal = run(range(60, 90))  # 30 ms asleep in the touch's ramp
    assert len(late) == len(on_time) == 149
    assert [s.change_hpa for s in late] == [s.change_hpa for s in on_time]
    assert [s.touch_hpa for s in late] == [s.touch_hpa for s in on_time]
    assert late[70].stamp_ns > on_time[70].stamp_ns + 10 * period  # stamped when taken
    assert max(late[70].change_hpa) > 1.0  # in the touch: the ramp's pressure of its own time

    again: list = []
    entries = journal.take()
    rerun = GatewayWiring(profile, journal=Playback(entries), out=lambda k, msg: again.append(msg)
                          if k == "skin/pressure" else None, diag=lambda *a: None, script=script)
    for entry in entries[1:]:
        rerun.replay(entry, None)
    assert again == late


def test_the_live_skin_sources_are_the_modules_of_their_package_and_a_wrong_name_says_which_there_are() -> None:
    from nwr.common.errors import ConfigError
    from nwr.services.gateway import sources

    assert sources.names() == ["physics", "ros1", "ros2", "sim"]
    assert sources.live("sim").NAME == "sim" and callable(sources.live("ros2").run)
    with pytest.raises(ConfigError, match="gateway.source = 'ros3' is no skin source; there are: physics, ros1, ros2, "
                                          "sim"):
        sources.live("ros3")
