"""The paper's gain models at values worked out by hand."""

import math

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import GainSection, PadGainOverride
from nwr.common.errors import ConfigError
from nwr.common.robot import Pad
from nwr.services.gain.core import (
    GainEstimator,
    continuous_gain,
    discrete_gain,
    pain_level,
    scaled_sigmoid,
)

T = (2.0, 6.0, 12.0, 20.0)


def test_scaled_sigmoid_endpoints_and_centre():
    assert scaled_sigmoid(0.0, 3.0) == pytest.approx(0.0, abs=1e-15)
    assert scaled_sigmoid(1.0, 3.0) == pytest.approx(1.0)
    assert scaled_sigmoid(0.5, 3.0) == pytest.approx(0.5)


def test_scaled_sigmoid_by_hand():
    # sigma(x) = 1/(1+e^{-3(x-0.5)}); sigma(0) = 1/(1+e^{1.5}) = 0.182426, sigma(1) = 0.817574
    s0, s1 = 1 / (1 + math.exp(1.5)), 1 / (1 + math.exp(-1.5))
    x = 0.25
    expected = (1 / (1 + math.exp(-3 * (x - 0.5))) - s0) / (s1 - s0)
    assert scaled_sigmoid(x, 3.0) == pytest.approx(expected)
    assert expected == pytest.approx(0.2179, abs=1e-4)  # (0.32082 - 0.18243) / 0.63515


@pytest.mark.parametrize(
    ("p", "g"),
    [
        (9.0, 0.175),  # 0.35 * sigma_s(0.5)
        (16.0, 0.675),  # 0.35 + 0.65 * sigma_s(0.5)
        (0.0, 0.0),
        (5.999, 0.0),
        (6.0, 0.0),
        (12.0, 0.35),
        (20.0, 1.0),
        (25.0, 1.0),
        (-3.0, 0.0),
    ],
)
def test_continuous_gain_values(p, g):
    assert continuous_gain(p, T) == pytest.approx(g, abs=1e-12)


def test_continuous_gain_is_continuous_and_monotonic():
    p = np.linspace(0, 25, 25001)
    g = np.array([continuous_gain(x, T) for x in p])
    assert np.all(np.diff(g) >= -1e-15)
    assert np.max(np.abs(np.diff(g))) < 1e-3  # no jumps at the thresholds
    for t, below, above in [(12.0, 0.35, 0.35), (20.0, 1.0, 1.0), (6.0, 0.0, 0.0)]:
        assert continuous_gain(t - 1e-9, T) == pytest.approx(below, abs=1e-6)
        assert continuous_gain(t + 1e-9, T) == pytest.approx(above, abs=1e-6)


@pytest.mark.parametrize(
    ("p", "level", "g"),
    [
        (0.0, 1, 0.0), (1.999, 1, 0.0), (2.0, 2, 0.0), (5.999, 2, 0.0), (6.0, 3, 0.35), (11.999, 3, 0.35),
        (12.0, 4, 1.0), (19.0, 4, 1.0), (30.0, 4, 1.0),
    ],
)
def test_discrete_model_at_and_around_thresholds(p, level, g):
    assert pain_level(p, T) == level
    assert discrete_gain(p, T) == g


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_pressure_never_hurts(bad):
    assert pain_level(bad, T) == 1
    assert continuous_gain(bad, T) == 0.0
    assert discrete_gain(bad, T) == 0.0


def pads(n=3):
    regions = ["shoulder", "upper_arm", "wrist"]
    return tuple(Pad(i, f"pad{i}", regions[i % 3], "l", np.zeros(3), np.array([0, 0, 1.0])) for i in range(n))


def sample(change, seq=5):
    n = len(change)
    return m.SkinPressure(seq=seq, stamp_ns=1000, absolute_hpa=[0.0] * n, baseline_hpa=[0.0] * n,
                          change_hpa=change, contact=[c > 1 for c in change])


def test_estimator_strongest_contact_and_trace():
    est = GainEstimator(GainSection(), pads())
    pain = est.process(sample([9.0, 16.0, 3.0]), now_ns=2000)
    assert pain.trace == m.Trace(5, 1000)
    assert pain.level == [3, 4, 2]
    assert pain.gain == pytest.approx([0.175, 0.675, 0.0])
    assert pain.strongest is not None
    assert (pain.strongest.pad, pain.strongest.region, pain.strongest.level) == (1, "upper_arm", 4)
    assert pain.strongest.gain == pytest.approx(0.675)


def test_estimator_no_contact_below_pl3():
    est = GainEstimator(GainSection(), pads())
    assert est.process(sample([5.9, 1.0, 0.0]), 0).strongest is None


def test_estimator_says_which_pads_the_skin_feels_in_contact_below_pl_2():
    est = GainEstimator(GainSection(), pads())
    pain = est.process(sample([1.5, 0.5, 3.0]), 0)  # the gateway's contact on pad 0 (1.5 hPa), PL 1
    assert pain.level == [1, 1, 2] and pain.light_touch == [0]  # pad 2 is felt (PL 2): no light touch
    assert est.process(sample([0.0, 0.0, 9.0]), 0).light_touch == []
    bare = m.SkinPressure(seq=1, stamp_ns=0, absolute_hpa=[0.0] * 3, baseline_hpa=[0.0] * 3,
                          change_hpa=[1.5, 0.0, 0.0], contact=[])
    assert est.process(bare, 0).light_touch == []  # no contact flags: none known


def test_estimator_discrete_model_and_override():
    cfg = GainSection(model="discrete", overrides={"pad2": PadGainOverride(thresholds_hpa=[1.0, 2.0, 3.0, 4.0])})
    est = GainEstimator(cfg, pads())
    pain = est.process(sample([7.0, 0.0, 3.5]), 0)
    assert pain.gain == [0.35, 0.0, 1.0]
    assert pain.level == [3, 1, 4]


def test_estimator_rejects_unknown_override_and_wrong_length():
    with pytest.raises(ConfigError, match="nope"):
        GainEstimator(GainSection(overrides={"nope": PadGainOverride(k=2.0)}), pads())
    est = GainEstimator(GainSection(), pads())
    with pytest.raises(ValueError, match="has 2 pads"):
        est.process(sample([1.0, 2.0]), 0)
