"""Fresh skin means fresh and valid: the bridge counts valid pads only, and a pad that stays invalid is blind."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile
from nwr.common.journal import Untracked
from nwr.services.bridge.core import BLIND_REPORT_S, pad_validity
from nwr.services.bridge.wiring import BridgeWiring

MS = 1_000_000
N = 10


def sample(seq: int, absolute: list[float] | None = None, valid: list[bool] | None = None) -> m.SkinPressure:
    absolute = absolute if absolute is not None else [1013.0] * N
    valid = valid if valid is not None else [True] * N
    return m.SkinPressure(seq=seq, stamp_ns=0, absolute_hpa=absolute, baseline_hpa=[1013.0] * N,
                          change_hpa=[0.0] * N, contact=[False] * N, valid=valid)


class Bridge:
    """The bridge's wiring on the simulated arm, on a manual clock, its diagnostics kept."""

    def __init__(self, **bridge: object) -> None:
        profile = Profile()
        for name, value in bridge.items():
            setattr(profile.bridge, name, value)
        self.clock = ManualClock()
        self.clock.t_ns = 10**9
        self.reports: list[tuple[str, str, str, float]] = []
        self.wiring = BridgeWiring(profile, journal=Untracked(self.clock), out=lambda k, msg: None,
                                   diag=lambda level, code, message, every_s=1.0: self.reports.append(
                                       (level, code, message, every_s)))
        self.core = self.wiring.core
        self.core.on_planner_alive(True, self.clock.t_ns)
        self.seq = 0
        self.q0 = self.core.tracker.q.copy()

    def run(self, seconds: float, skin: object = None, move: bool = True) -> None:
        """Skin samples at 25 Hz (``skin(seq)``), a task command and a control cycle every 2 ms."""
        for k in range(round(seconds / 0.002)):
            self.clock.t_ns += 2 * MS
            if skin is not None and k % 20 == 0:
                self.wiring.on_skin(skin(self.seq))  # type: ignore[operator]
            if move:
                q = self.q0 + np.array([0.1, 0, 0, 0, 0, 0]) * (1 - math.cos(self.seq * 0.002))
                self.wiring.on_command(keys.robot_command("cartesian"), m.PositionCommand(
                    seq=self.seq, stamp_ns=self.clock.t_ns, owner="cartesian", q=q.tolist(), trace=m.Trace(0, 0),
                    phase="TASK"))
            self.seq += 1
            self.wiring.tick()

    def codes(self) -> list[str]:
        return [code for _, code, _, _ in self.reports]


def test_validity_is_the_gateways_flag_and_the_range_a_pad_can_report():
    assert pad_validity(sample(0), N) == [True] * N
    assert pad_validity(sample(0, valid=[False] * 3 + [True] * 7), N) == [False] * 3 + [True] * 7
    assert pad_validity(sample(0, absolute=[101325.0] * N), N) == [False] * N  # Pa, not hPa
    no_flags = msgspec.structs.replace(sample(0), valid=[])  # an older gateway: every pad valid
    assert pad_validity(no_flags, N) == [True] * N


def test_a_fresh_valid_skin_lets_the_task_run():
    b = Bridge()
    b.run(0.5, lambda seq: sample(seq))
    assert b.core.status == "ok" and b.core.safety_mode == "normal" and not b.core.blind


@pytest.mark.parametrize("blind", [
    lambda seq: sample(seq, valid=[False] * N),  # every reading NaN: the gateway marks them invalid
    lambda seq: sample(seq, absolute=[101325.0] * N),  # a skin read in Pa
], ids=["nan", "pascal"])
def test_a_skin_without_a_valid_pad_is_stale_and_holds_the_task(blind):
    b = Bridge()
    b.run(0.3, lambda seq: sample(seq))
    assert b.core.status == "ok"
    b.run(0.5, blind)
    assert b.core.status == "stale_skin"
    assert "skin_blind" in b.codes() and "stale_skin" in b.codes()
    message = next(msg for _, code, msg, _ in b.reports if code == "skin_blind")
    assert "no valid pad" in message
    assert np.all(np.abs(b.core.tracker.dq) < 1e-9)  # held, at rest
    b.run(0.5, lambda seq: sample(seq))
    assert b.core.status == "ok"


def test_blind_pads_are_reported_once_then_rarely_and_reduce_the_limits():
    b = Bridge()
    b.run(0.3, lambda seq: sample(seq))
    seven = [False] * 7 + [True] * 3
    b.run(0.1, lambda seq: sample(seq, valid=seven))
    assert not b.core.blind and b.core.safety_mode == "normal"  # not yet: invalid for less than blind_pad_s
    b.run(0.3, lambda seq: sample(seq, valid=seven))
    assert b.core.blind == frozenset(range(7)) and b.core.status == "ok"
    assert b.core.safety_mode == "reduced" and b.core.tracker.limiter.limits is b.core.reduced_limits
    first = [r for r in b.reports if r[1] == "skin_blind_pad"]
    assert first[0][0] == "warning" and first[0][3] == 0.0 and "7 of 10 pads blind" in first[0][2]
    assert all(r[3] == BLIND_REPORT_S for r in first[1:])  # the repeats: at most every 10 s
    assert "safety_mode" in b.codes()
    # the operator cannot lift the reduced limits while a pad is blind
    b.core.set_safety_mode("normal", b.clock.t_ns, "nwr safety")
    assert b.core.safety_mode == "reduced"
    # the pads see again: the normal limits, and a report
    b.run(0.1, lambda seq: sample(seq))
    assert not b.core.blind and b.core.safety_mode == "normal" and "skin_pad_recovered" in b.codes()


def test_the_operators_reduced_mode_outlasts_blind_pads():
    b = Bridge()
    b.core.set_safety_mode("reduced", b.clock.t_ns, "nwr safety")
    b.run(0.4, lambda seq: sample(seq, valid=[False] + [True] * 9))
    assert b.core.blind == frozenset({0})
    b.run(0.1, lambda seq: sample(seq))
    assert not b.core.blind and b.core.safety_mode == "reduced"


def test_blind_pads_stop_the_task_when_the_profile_says_so():
    b = Bridge(blind_pads="stop")
    b.run(0.3, lambda seq: sample(seq))
    b.run(0.5, lambda seq: sample(seq, valid=[False] * 3 + [True] * 7))
    assert b.core.status == "stale_skin" and "blind" in b.core.detail
    assert b.core.safety_mode == "normal"
    b.run(0.3, lambda seq: sample(seq))
    assert b.core.status == "ok"
