"""The pure pieces of ``nwr bench``: statistics, trace matching, the lower-bound chain, the touch script.

Nothing here starts a process or opens a network session; :mod:`nwr.services.tools.bench.main`
does that and hands the recordings to these functions.

Trace matching, per recording (all stamps on the machine's monotonic clock):

- sample latency: every skin sample (``skin/pressure``, stamped in the gateway)
  -> the active planner's :class:`~nwr.common.messages.PlannerDecision` that
  carries its trace (``decision.stamp_ns - sample.stamp_ns``);
- reflex onset: ``RobotState.accepted_ns - accepted.stamp_ns``, once per
  reflex number (the bridge repeats the newest onset on every later state);
- hops: gateway -> gain (``pain.stamp_ns - pain.trace.stamp_ns``), gain ->
  planner (``decision.stamp_ns - decision.pain_stamp_ns``), planner -> bridge
  (``accepted_ns`` minus the stamp of the reflex's first command; the bridge
  notes acceptance times of reflex onsets only).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.recordings import Recorded
from nwr.common.robot import Pad
from nwr.services.gateway.core import Gateway
from nwr.services.gateway.stepped import Emit, Pose, RecordedSkin
from nwr.services.pipeline.lockstep import Lockstep

STAT_NAMES = ("n", "p50", "p90", "p99", "max")
# Pressure changes of the scripted touches, hPa: above the PL 3 threshold
# (a reflex) and sub-threshold (PL 2: felt, no reflex).
STRONG_HPA = (9.0, 16.0, 25.0, 12.0, 22.0)
WEAK_HPA = (3.0, 4.5, 5.0)


def summarize(values_ms: Sequence[float]) -> dict[str, float]:
    """n, p50, p90, p99 and max of a list of latencies, ms (NaN when empty)."""
    if len(values_ms) == 0:
        return {"n": 0, "p50": float("nan"), "p90": float("nan"), "p99": float("nan"), "max": float("nan")}
    a = np.asarray(values_ms, dtype=float)
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return {"n": int(a.size), "p50": float(p50), "p90": float(p90), "p99": float(p99), "max": float(a.max())}


def median_over(runs: Sequence[dict[str, float]]) -> dict[str, float]:
    """The median of each statistic over repetitions (NaN entries ignored)."""
    out: dict[str, float] = {}
    for name in {k for run in runs for k in run}:
        values = [run[name] for run in runs if name in run and not np.isnan(run[name])]
        out[name] = float(statistics.median(values)) if values else float("nan")
    return out


@dataclass
class Traces:
    """The latencies of one recording, ms, and what could not be matched."""

    sample: list[float] = field(default_factory=list)
    onset: list[float] = field(default_factory=list)
    gateway_gain: list[float] = field(default_factory=list)
    gain_planner: list[float] = field(default_factory=list)
    planner_bridge: list[float] = field(default_factory=list)
    planner_bridge_planning: list[float] = field(default_factory=list)  # of it: the planner's work on the pain
    planner_bridge_hop: list[float] = field(default_factory=list)  # of it: the command's hop to the bridge
    skin_samples: int = 0
    unmatched_samples: int = 0  # skin samples with no decision of the active planner
    orphan_decisions: int = 0  # decisions whose skin sample is not in the recording
    reflexes: int = 0  # reflexes the planner started (decisions with a reflex number)
    unmatched_onsets: int = 0  # reflexes started whose acceptance the bridge never reported


def match_traces(records: Iterable[Recorded], planner: str, *, tail_ns: int = 0) -> Traces:
    """Match the traces of one recording (see the module docstring).

    ``planner`` names the active planner. Skin samples stamped within
    ``tail_ns`` of the last one are not counted as unmatched: the pipeline
    was being stopped while they travelled.
    """
    samples: dict[int, int] = {}
    pains: list[m.SkinPain] = []
    decisions: list[m.PlannerDecision] = []
    commands: dict[int, int] = {}  # reflex number -> stamp of its first REFLEX command
    decided: dict[int, int] = {}  # reflex number -> stamp of the decision that started it
    onsets: dict[int, tuple[m.Trace, int]] = {}
    accepted_at: set[int] = set()
    for r in records:
        msg = r.message
        if r.key == "skin/pressure":
            samples[msg.seq] = msg.stamp_ns
        elif r.key == "skin/pain":
            pains.append(msg)
        elif r.key.endswith("/decision") and msg.name == planner and msg.active:
            decisions.append(msg)
            if msg.reflex_seq > 0:
                decided.setdefault(msg.reflex_seq, msg.stamp_ns)
        elif r.key == keys.robot_command(planner) and msg.owner == planner and msg.phase == "REFLEX":
            commands.setdefault(msg.reflex_seq, msg.stamp_ns)
        elif r.key == "robot/state" and msg.accepted is not None and msg.owner == planner \
                and msg.accepted_ns not in accepted_at:
            # Later states repeat the newest onset (with the reflex number of
            # their own command): the first state that names it is the onset's.
            accepted_at.add(msg.accepted_ns)
            onsets.setdefault(msg.reflex_seq, (msg.accepted, msg.accepted_ns))
    out = Traces(skin_samples=len(samples))
    answered: set[int] = set()
    for d in decisions:
        stamp = samples.get(d.trace.seq)
        if stamp is None or stamp != d.trace.stamp_ns:
            out.orphan_decisions += 1
            continue
        answered.add(d.trace.seq)
        out.sample.append((d.stamp_ns - stamp) / 1e6)
        out.gain_planner.append((d.stamp_ns - d.pain_stamp_ns) / 1e6)
        if d.reflex_seq > 0:
            out.reflexes += 1
            if d.reflex_seq not in onsets:
                out.unmatched_onsets += 1
    last = max(samples.values(), default=0)
    out.unmatched_samples = sum(1 for seq, stamp in samples.items()
                                if seq not in answered and stamp <= last - tail_ns)
    out.gateway_gain = [(p.stamp_ns - p.trace.stamp_ns) / 1e6 for p in pains if p.trace.seq in samples]
    for reflex_seq, (trace, accepted_ns) in sorted(onsets.items()):
        out.onset.append((accepted_ns - trace.stamp_ns) / 1e6)
        first = commands.get(reflex_seq)
        if first is not None:
            out.planner_bridge.append((accepted_ns - first) / 1e6)
            decision = decided.get(reflex_seq)
            if decision is not None:
                out.planner_bridge_planning.append((decision - first) / 1e6)
                out.planner_bridge_hop.append((accepted_ns - decision) / 1e6)
    return out


# ------------------------------------------------------------------------------ the lower bound


class TimedSkin(RecordedSkin):
    """Recorded samples, each first put through the gateway's core (its absolute pressures): the clock starts there."""

    def __init__(self, profile: Profile, samples: Sequence[m.SkinPressure]) -> None:
        super().__init__(samples)
        self.gateway = Gateway(profile.gateway, len(samples[0].absolute_hpa) if samples else 0)
        self.t0_ns = self.samples[0].stamp_ns if self.samples else 0
        self.started_ns: int | None = None

    def take(self, i: int, pose: Pose, emit: Emit) -> m.SkinPressure | None:
        sample = self.samples[i]
        absolute = np.asarray(sample.absolute_hpa, dtype=float)  # the device's reading: not timed
        self.started_ns = time.perf_counter_ns()
        self.gateway.process((sample.stamp_ns - self.t0_ns) / 1e9, sample.stamp_ns, absolute)
        return sample


def lower_bound(profile: Profile, strategy: str, samples: Sequence[m.SkinPressure]) -> tuple[list[float], list[float]]:
    """Sample and onset latencies (ms) of the services' wirings chained in this process, on the same skin samples.

    Per sample, from the gateway's core on: through the gain estimator's and
    the planner's wirings up to the planner's decision (the sample latency's
    lower bound) and, when a reflex starts, on through the bridge's wiring to
    the robot state that reports its acceptance (the onset's). Messages are
    not encoded or sent, and no journal is kept: that is what the pipeline adds.
    """
    source = TimedSkin(profile, samples)
    chain = Lockstep(profile, strategy=strategy, journal=False)
    decision_key = keys.planner_decision(chain.name)
    sample_ns: list[int] = []
    onset_ns: list[int] = []
    onsets: set[int] = set()

    def emit(key: str, message: Any, _t: int) -> None:
        started = source.started_ns
        if started is None:
            return
        if key == decision_key:
            sample_ns.append(time.perf_counter_ns() - started)
        elif key == keys.ROBOT_STATE and message.accepted is not None and message.accepted_ns not in onsets:
            onsets.add(message.accepted_ns)
            onset_ns.append(time.perf_counter_ns() - started)

    chain.run(source, emit, settle_s=0.5)
    return [x / 1e6 for x in sample_ns], [x / 1e6 for x in onset_ns]


def source_skipped(stamps_ns: Sequence[int], rate_hz: float) -> int:
    """Sample periods the skin source let pass without a sample, from its samples' stamps.

    The simulated skin is paced on absolute deadlines (:class:`~nwr.common.pacing.Rate`): a late loop
    takes the periods it missed one after the other, up to ``CATCH_UP_S`` of them
    (:mod:`nwr.services.gateway.sources.sim`), and skips those beyond, with no gap in the sequence numbers
    (the samples were never taken, not lost on the way). The periods between the first and the last
    stamp, less the samples between them, are those skipped (to within one).
    """
    if len(stamps_ns) < 2:
        return 0
    expected = round((max(stamps_ns) - min(stamps_ns)) * rate_hz / 1e9) + 1
    return max(0, expected - len(stamps_ns))


# ------------------------------------------------------------------------------ the touch script


def touch_script(pads: Sequence[Pad], onsets: int, spacing_s: float, *, lead_s: float = 1.0) -> tuple[str, float]:
    """A touch script (TOML) of ``onsets`` reflex-causing touches, every region in turn,
    each followed half a spacing later by a sub-threshold touch on another pad.

    Consecutive strong touches are on different pads, so each starts a reflex
    (a new contact) even while the previous one is returning. Returns the
    script and its duration, s.
    """
    by_region: dict[str, list[Pad]] = {}
    for pad in pads:
        by_region.setdefault(pad.region, []).append(pad)
    regions = sorted(by_region)
    lines = []
    t = lead_s
    for i in range(onsets):
        group = by_region[regions[i % len(regions)]]
        strong = group[(i // len(regions)) % len(group)]
        weak = pads[(strong.id + 3 + i) % len(pads)]
        if weak.id == strong.id:
            weak = pads[(strong.id + 1) % len(pads)]
        lines.append(_touch(strong.name, t, STRONG_HPA[i % len(STRONG_HPA)]))
        lines.append(_touch(weak.name, t + spacing_s / 2, WEAK_HPA[i % len(WEAK_HPA)]))
        t += spacing_s
    duration = t + 0.5
    return f"# nwr bench: {onsets} reflex onsets, sub-threshold touches between them\nduration_s = {duration:.2f}\n\n" \
        + "\n".join(lines), duration


def _touch(pad: str, start_s: float, peak_hpa: float) -> str:
    return (f'[[touch]]\npad = "{pad}"\nstart_s = {start_s:.3f}\nduration_s = 0.25\npeak_hpa = {peak_hpa}\n'
            'shape = "ramp"\nramp_s = 0.04\n')
