"""Reflex storms: a flickering pad or a forged skin stream must not restart the reflex at every sample, while a
real touch still starts it at its first sample and a real escalation still updates it (docs/reflexes.md,
"Restarts")."""

from __future__ import annotations

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import PlannerSection, RestartSection
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner.core import Planner

DESC = load_description()
MODEL = RobotModel(DESC)
N_PADS = len(DESC.pads)
CYCLE_NS = 2_000_000
FOREARM = DESC.pad("forearm_top").id
WRIST = DESC.pad("wrist_2").id
# The demo's firm press on forearm_top at 25 Hz (its recorded gains): it escalates in 6 samples.
DEMO_PRESS = [0.059, 0.258, 0.425, 0.688, 0.941, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.945, 0.692, 0.419, 0.258, 0.064]


def level_of(gain: float) -> int:
    return 1 if gain <= 0.0 else 3 if gain < 0.35 else 4


class Driver:
    """A planner in its task, fed pain messages at given times, its control cycles stepped in between."""

    def __init__(self, cfg: PlannerSection | None = None) -> None:
        self.p = Planner(cfg or PlannerSection(), DESC, MODEL)
        self.t = 0
        self.seq = 0
        self.p.on_state(DESC.home.copy(), following=True)
        while self.p.mode != "TASK":
            self.advance(self.t + CYCLE_NS)
        self.advance(self.t + 1_000_000_000)  # 1 s into the task
        self.first_commands: list[tuple[int, m.Command]] = []  # (time, command) of each reflex's first command

    def advance(self, until_ns: int) -> None:
        while self.t + CYCLE_NS <= until_ns:
            self.t += CYCLE_NS
            self.p.step(self.t)
        self.t = max(self.t, until_ns)

    def pain(self, t_ns: int, gains: list[float]) -> m.Command | None:
        self.advance(t_ns)
        self.seq += 1
        strongest = None
        if max(gains) > 0.0:
            pad = int(np.argmax(gains))
            info = DESC.pads[pad]
            strongest = m.Contact(pad=pad, name=info.name, region=info.region, change_hpa=10.0,
                                  level=level_of(gains[pad]), gain=gains[pad])
        msg = m.SkinPain(seq=self.seq, stamp_ns=t_ns, trace=m.Trace(self.seq, t_ns), model="continuous",
                         level=[level_of(g) for g in gains], gain=list(gains), strongest=strongest)
        before = self.p.reflex_count
        command = self.p.on_pain(msg, t_ns)
        if self.p.reflex_count != before:
            assert command is not None
            self.first_commands.append((t_ns, command))
        return command

    def press(self, pad: int, gains: list[float], period_ns: int, start_ns: int | None = None) -> int:
        """Samples of ``pad`` every ``period_ns`` from ``start_ns`` (default: now); the reflexes they started."""
        start = self.t if start_ns is None else start_ns
        before = self.p.reflex_count
        for i, gain in enumerate(gains):
            row = [0.0] * N_PADS
            row[pad] = gain
            self.pain(start + i * period_ns, row)
        return self.p.reflex_count - before

    def notes(self, code: str) -> list[str]:
        return [message for _, c, message in self.p.drain_notes() if c == code]


def flicker(driver: Driver, seconds: float = 2.0) -> int:
    """One pad flickering between pressed (G 0.675) and not pressed at 200 Hz for ``seconds``."""
    samples = round(seconds * 200)
    return driver.press(FOREARM, [0.675 if i % 2 == 0 else 0.0 for i in range(samples)], 5_000_000)


def forged_press(driver: Driver) -> int:
    """A compromised gateway's 0.4 s press on one pad at 1 kHz: its gain climbs from 0 to 1 with jitter, and
    drops to 0 for one sample every 10 ms."""
    rng = np.random.default_rng(3)
    gains = np.clip(np.linspace(0.0, 1.0, 400) + rng.uniform(-0.03, 0.03, 400), 0.01, 1.0).round(3)
    gains[::10] = 0.0
    return driver.press(FOREARM, gains.tolist(), 1_000_000)


def forged_ramp(driver: Driver) -> int:
    """A forged 0.4 s press at the skin's 25 Hz whose gain climbs by 0.1 each sample (11 samples)."""
    return driver.press(FOREARM, [round(0.1 * i, 1) for i in range(11)] + [1.0] * 5, 40_000_000)


def forged_stream(driver: Driver, seconds: float = 2.0) -> int:
    """A compromised gateway: 2 s at 1 kHz, a random pad at a random gain, or nothing, every sample."""
    rng = np.random.default_rng(11)
    before = driver.p.reflex_count
    start = driver.t
    for i in range(round(seconds * 1000)):
        row = [0.0] * N_PADS
        if rng.random() < 0.7:
            row[int(rng.integers(N_PADS))] = float(rng.uniform(0.05, 1.0))
        driver.pain(start + i * 1_000_000, row)
    return driver.p.reflex_count - before


def paper_cfg() -> PlannerSection:
    return PlannerSection(restarts=RestartSection(gap_s=0.0, pad_burst=20, pad_interval_s=1e-9, burst=100,
                                                  interval_s=1e-9, escalate_at_once=1.0))


@pytest.mark.parametrize("storm, limit", [(flicker, 1), (forged_press, 9), (forged_ramp, 8), (forged_stream, 20)])
def test_storms_start_few_reflexes(storm, limit) -> None:
    unlimited = storm(Driver(paper_cfg()))  # no debounce and no rate limit: how the planner behaved before
    limited = storm(Driver())
    print(f"{storm.__name__}: {unlimited} reflexes without the limits, {limited} with them")
    assert limited <= limit < unlimited


def test_a_flickering_pad_is_one_touch_reported_once_then_at_a_low_rate() -> None:
    d = Driver()
    assert flicker(d, 2.0) == 1
    notes = d.notes("pad_flicker")
    assert len(notes) == 1 and "forearm_top" in notes[0] and "flickers" in notes[0]
    assert flicker(d, 5.0) == 0
    assert d.notes("pad_flicker") == []  # within 10 s of the report
    flicker(d, 4.0)
    assert len(d.notes("pad_flicker")) == 1  # 10 s later: once more
    # The flicker stops: after the gap, a press is a new touch again.
    d.press(FOREARM, [0.0, 0.0, 0.0, 0.0], 40_000_000)
    assert d.p.mode in ("HOLDING", "REFLEX")
    assert d.press(FOREARM, [0.675], 40_000_000) == 1


@pytest.mark.parametrize("samples", [[0.675], [0.2, 0.4]])
def test_a_short_real_press_at_25_hz_starts_the_reflex_at_its_first_sample(samples) -> None:
    d = Driver()
    t0 = d.t + 40_000_000
    assert d.press(WRIST, samples + [0.0, 0.0], 40_000_000, start_ns=t0) >= 1
    t, command = d.first_commands[0]
    assert t == t0 and command.stamp_ns == t0 and command.reflex_seq == 1 and command.phase == "REFLEX"


def test_the_demo_press_escalates_as_before_sample_by_sample() -> None:
    before, after = Driver(paper_cfg()), Driver()
    t0 = before.t + 40_000_000
    assert after.t + 40_000_000 == t0
    assert before.press(FOREARM, DEMO_PRESS, 40_000_000, start_ns=t0) == 6
    assert after.press(FOREARM, DEMO_PRESS, 40_000_000, start_ns=t0) == 6
    assert [t for t, _ in after.first_commands] == [t for t, _ in before.first_commands]
    assert after.p.reflex is not None and after.p.reflex.contact.gain == 1.0


def test_a_real_escalation_beyond_the_pads_burst_still_reaches_the_reflex() -> None:
    """A slow press (+0.08 a sample at 25 Hz): the pad's burst runs out, and the reflex follows the touch
    within escalate_at_once, reaching its full gain while the touch lasts."""
    d = Driver()
    ramp = [round(min(1.0, 0.08 * (i + 1)), 2) for i in range(16)] + [1.0] * 4
    count = d.press(FOREARM, ramp, 40_000_000)
    assert 6 < count < len(ramp)
    assert d.p.reflex is not None and d.p.reflex.contact.gain == 1.0
    assert d.notes("reflex_rate_limited")


def test_a_new_contact_kept_waiting_by_the_overall_limit_restarts_once_allowed() -> None:
    d = Driver(PlannerSection(restarts=RestartSection(burst=2, interval_s=0.5)))
    assert d.press(FOREARM, [0.5], 40_000_000) == 1  # from the task: 1 token left
    row = [0.0] * N_PADS
    row[FOREARM], row[WRIST] = 0.5, 0.6
    assert d.pain(d.t + 40_000_000, row) is not None  # a new pad: the last token
    row[DESC.pad("elbow_outer").id] = 0.62  # the strongest, but not by update_margin: only new
    assert d.pain(d.t + 40_000_000, row) is None  # a third pad at once: refused, pending
    notes = d.notes("reflex_rate_limited")
    assert len(notes) == 1 and "elbow_outer" in notes[0] and "overall" in notes[0]
    refused_at = d.t
    started = d.p.reflex_count
    while d.p.reflex_count == started:
        d.pain(d.t + 40_000_000, row)  # the same contact, not stronger: still new, it restarts once allowed
    assert d.p.reflex is not None and d.p.reflex.contact.name == "elbow_outer"
    assert d.t - refused_at <= 500_000_000  # within interval_s


def test_a_start_from_the_task_is_never_refused_even_with_no_token_left() -> None:
    d = Driver()
    d.p.restarts.overall.tokens = 0.0
    d.p.restarts.buckets[WRIST].tokens = 0.0
    t0 = d.t + 40_000_000
    assert d.p.mode == "TASK"
    assert d.press(WRIST, [0.3, 0.0], 40_000_000, start_ns=t0) == 1
    assert d.first_commands[0][0] == t0 and d.p.started == 1


def test_the_wiring_reports_a_flickering_pad_when_the_pain_message_shows_it_not_with_a_later_state() -> None:
    from nwr.common.clock import ManualClock
    from nwr.common.config import Profile
    from nwr.common.journal import Untracked
    from nwr.services.planner.wiring import PlannerWiring

    clock = ManualClock()
    reported: list[str] = []
    wiring = PlannerWiring(Profile(), journal=Untracked(clock), out=lambda key, msg: None,
                           diag=lambda level, code, message, every_s=1.0: reported.append(code))
    for i in range(400):  # 200 Hz on and off on one pad, 2 s; no robot state meanwhile
        clock.t_ns = 1_000_000_000 + i * 5_000_000
        gains = [0.0] * N_PADS
        gains[FOREARM] = 0.6 if i % 2 == 0 else 0.0
        pad = DESC.pads[FOREARM]
        strongest = m.Contact(pad=FOREARM, name=pad.name, region=pad.region, change_hpa=10.0, level=4, gain=0.6) \
            if i % 2 == 0 else None
        wiring.on_pain(m.SkinPain(seq=i, stamp_ns=clock.t_ns, trace=m.Trace(i, clock.t_ns), model="continuous",
                                  level=[level_of(g) for g in gains], gain=gains, strongest=strongest), clock.t_ns)
    assert "pad_flicker" in reported, reported
